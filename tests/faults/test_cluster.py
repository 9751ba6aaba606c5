"""The SLURM profile (workflow/profiles/slurm): sane settings, every job's resources, a real cluster run.

- fast: the profile parses and its values are sane; a dry run of the default
  experiment through the profile (the slurm executor plugin loaded, nothing
  submitted) lists every job with threads, ``mem_mb`` and ``runtime``, and
  those are the values the rules declare (not the profile's fall-backs);
- slow: a one-node SLURM cluster (Debian's ``slurm-wlm``: munged, slurmctld,
  slurmd on loopback, configless) is started inside the test and the smoke
  experiment's first mesh is built through the profile with ``sbatch``; the
  scheduler's record of each job shows the memory, time limit and CPUs the
  rule declared.
"""
from __future__ import annotations

import os
import math
import re
import shutil
import signal
import socket
import subprocess
import time
from pathlib import Path

import pytest
import yaml

from test_workflow import ROOT, SNAKEMAKE, job_counts, snakemake

PROFILE = ROOT / "workflow" / "profiles" / "slurm"
RULES_DIR = ROOT / "workflow" / "rules"


def rule_declarations() -> dict[str, dict]:
    """``rule name -> {threads, mem_mb, runtime, runs}`` read from workflow/rules/*.smk and the Snakefile."""
    out: dict[str, dict] = {}
    for path in [ROOT / "Snakefile", *sorted(RULES_DIR.glob("*.smk"))]:
        text = path.read_text()
        blocks = re.split(r"^rule (\w+):\s*$", text, flags=re.M)
        for name, body in zip(blocks[1::2], blocks[2::2]):
            body = re.split(r"^\S", body, maxsplit=1, flags=re.M)[0]  # up to the next top-level statement
            decl = {"runs": bool(re.search(r"^\s+(script|shell|run|notebook|wrapper):", body, re.M))}
            for key, pat in (("threads", r"^\s+threads:\s*(\d+|lambda)"), ("mem_mb", r"^\s+mem_mb\s*=\s*(\d+|lambda)"),
                             ("runtime", r"^\s+runtime\s*=\s*(\d+|lambda)")):
                m = re.search(pat, body, re.M)
                decl[key] = None if not m else ("callable" if m.group(1) == "lambda" else int(m.group(1)))
            out[name] = decl
    return out


def dry_run_jobs(text: str) -> list[dict]:
    """Jobs of ``snakemake -n`` output: rule, threads (1 when not printed) and the resources line."""
    jobs = []
    for block in re.split(r"^\[[^\]]+\]\s*$", text, flags=re.M):
        m = re.search(r"^(?:local)?rule (\w+):", block, re.M)
        if not m:
            continue
        res = re.search(r"^\s+resources: (.*)$", block, re.M)
        thr = re.search(r"^\s+threads: (\d+)", block, re.M)
        resources = {}
        if res:
            for item in res.group(1).split(", "):
                k, _, v = item.partition("=")
                resources[k.strip()] = v.strip()
        jobs.append({"rule": m.group(1), "threads": int(thr.group(1)) if thr else 1, "resources": resources})
    return jobs


def test_profile_values_are_sane():
    cfg = yaml.safe_load((PROFILE / "config.yaml").read_text())
    assert cfg["executor"] == "slurm"
    assert 1 <= int(cfg["jobs"]) <= 10_000
    assert 5 <= int(cfg["latency-wait"]) <= 600  # shared file systems show outputs late
    assert cfg.get("rerun-incomplete") is True  # resuming after a killed head job is the plain command
    assert 0 <= int(cfg.get("retries", 0)) <= 3
    defaults = dict(item.split("=", 1) for item in cfg["default-resources"])
    assert 256 <= int(defaults["mem_mb"]) <= 64_000
    assert 1 <= int(defaults["runtime"]) <= 7 * 24 * 60  # minutes
    # a default cpus_per_task would override every rule's `threads:`
    assert "cpus_per_task" not in defaults and "threads" not in cfg
    assert not any(k in cfg for k in ("cores", "local-cores")) or int(cfg.get("local-cores", 1)) >= 1


def test_every_rule_that_runs_declares_threads_memory_and_runtime():
    decls = rule_declarations()
    runs = {name: d for name, d in decls.items() if d["runs"]}
    assert {"geometry", "mesh", "sweep", "simulate", "manifest", "train", "validate", "report"} <= set(runs)
    for name, d in runs.items():
        assert d["threads"] and d["mem_mb"] and d["runtime"], f"rule {name} misses a resource: {d}"


@pytest.mark.workflow
@pytest.mark.slow  # a dry run of the whole default DAG through the profile (~35 s under CI load)
def test_dry_run_through_the_profile_gives_every_job_its_resources(tmp_path):
    out = snakemake("-n", "--profile", str(PROFILE), "--directory", str(tmp_path),
                    "--config", "experiment=default")
    text = out.stdout + out.stderr
    counts = job_counts(text)
    jobs = dry_run_jobs(text)
    assert len(jobs) == sum(counts.values()), (len(jobs), counts)
    decls = rule_declarations()
    cfg = yaml.safe_load((PROFILE / "config.yaml").read_text())
    defaults = dict(item.split("=", 1) for item in cfg["default-resources"])
    checked = 0
    for job in jobs:
        d = decls[job["rule"]]
        res = job["resources"]
        assert "mem_mb" in res and "runtime" in res, job
        if not d["runs"]:  # aggregate targets (all, ...): nothing is submitted, profile defaults apply
            assert res["mem_mb"] == defaults["mem_mb"] and res["runtime"] == defaults["runtime"], job
            continue
        assert job["threads"] == d["threads"], job
        expect = dict(d)
        if job["rule"] == "simulate":  # cases at 15 s + one at the wall-time safety net (+5 min), first attempt
            from liverforce.config import compose

            c = compose(["experiment=default"])
            expect["mem_mb"] = 4000
            expect["runtime"] = 5 + math.ceil((c["sweep"]["cases_per_shard"] * 15 + c["simulate"]["time_limit_s"]) / 60)
        assert int(res["mem_mb"]) == expect["mem_mb"] and int(res["runtime"]) == expect["runtime"], (job, expect)
        assert 1 <= job["threads"] <= 64 and 256 <= int(res["mem_mb"]) <= 256_000
        assert 1 <= int(res["runtime"]) <= 7 * 24 * 60
        checked += 1
    assert checked == sum(n for r, n in counts.items() if decls[r]["runs"])
    assert counts["simulate"] >= 2 and counts["train"] >= 2


# --------------------------------------------------------------------------- a real one-node cluster


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _munge_ok() -> bool:
    try:
        enc = subprocess.run(["munge", "-n"], capture_output=True, timeout=10)
        return enc.returncode == 0 and subprocess.run(["unmunge"], input=enc.stdout, capture_output=True,
                                                      timeout=10).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


def _kill_pidfile(path: Path) -> None:
    try:
        pid = int(path.read_text().strip())
    except (OSError, ValueError):
        return
    try:
        os.kill(pid, signal.SIGTERM)
        for _ in range(50):
            os.kill(pid, 0)
            time.sleep(0.1)
        os.kill(pid, signal.SIGKILL)
    except ProcessLookupError:
        pass


@pytest.fixture
def one_node_cluster(tmp_path):
    if shutil.which("sbatch") is None:
        pytest.skip("sbatch not on PATH: the one-node SLURM cluster needs Debian's slurm-wlm "
                    "(apt-get install slurm-wlm munge)")
    for tool in ("slurmctld", "slurmd", "munged", "sinfo", "squeue", "scontrol"):
        assert shutil.which(tool) or Path(f"/usr/sbin/{tool}").exists(), f"{tool} missing next to sbatch"
    root = tmp_path / "slurm"
    for d in ("ctld", "d", "log", "run"):
        (root / d).mkdir(parents=True)
    user = os.environ.get("USER") or __import__("getpass").getuser()
    host = socket.gethostname().split(".")[0]
    mem = min(8000, os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2**20 - 1000)
    conf = root / "slurm.conf"
    conf.write_text(f"""ClusterName=lftest
SlurmctldHost={host}(127.0.0.1)
SlurmUser={user}
SlurmdUser={user}
AuthType=auth/munge
CredType=cred/munge
SlurmctldParameters=enable_configless
StateSaveLocation={root}/ctld
SlurmdSpoolDir={root}/d
SlurmctldPidFile={root}/run/slurmctld.pid
SlurmdPidFile={root}/run/slurmd.pid
SlurmctldLogFile={root}/log/slurmctld.log
SlurmdLogFile={root}/log/slurmd.log
SlurmctldPort={_free_port()}
SlurmdPort={_free_port()}
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
ReturnToService=2
MinJobAge=600
MpiDefault=none
NodeName={host} NodeAddr=127.0.0.1 CPUs={os.cpu_count()} RealMemory={mem} State=UNKNOWN
PartitionName=test Nodes={host} Default=YES MaxTime=INFINITE State=UP
""")
    started_munge = None
    if not _munge_ok():
        for d in ("/run/munge", "/var/lib/munge", "/var/log/munge"):
            Path(d).mkdir(parents=True, exist_ok=True)
        key = root / "munge.key"
        key.write_bytes(os.urandom(1024))
        key.chmod(0o400)
        started_munge = root / "run" / "munged.pid"
        subprocess.run(["/usr/sbin/munged", "--force", f"--key-file={key}", f"--pid-file={started_munge}",
                        f"--log-file={root}/log/munged.log", f"--seed-file={root}/run/munged.seed"],
                       check=True, timeout=30)
        assert _munge_ok(), (root / "log" / "munged.log").read_text()
    env = {k: v for k, v in os.environ.items() if not k.startswith("SLURM_")}
    try:
        subprocess.run(["/usr/sbin/slurmctld", "-c", "-f", str(conf)], check=True, timeout=60, env=env)
        port = re.search(r"SlurmctldPort=(\d+)", conf.read_text()).group(1)
        subprocess.run(["/usr/sbin/slurmd", "-c", "--conf-server", f"127.0.0.1:{port}"], check=True, timeout=60,
                       env=env)
        deadline = time.monotonic() + 60
        state = ""
        while time.monotonic() < deadline:
            state = subprocess.run(["sinfo", "-h", "-o", "%T"], capture_output=True, text=True, env=env).stdout.strip()
            if state == "idle":
                break
            time.sleep(1)
        assert state == "idle", (state, (root / "log" / "slurmctld.log").read_text()[-2000:],
                                 (root / "log" / "slurmd.log").read_text()[-2000:])
        yield {"root": root, "env": env}
    finally:
        subprocess.run(["scancel", "--user", user], capture_output=True, env=env)
        _kill_pidfile(root / "run" / "slurmd.pid")
        _kill_pidfile(root / "run" / "slurmctld.pid")
        if started_munge is not None:
            _kill_pidfile(started_munge)
        cache = Path("/run/slurm/conf")  # slurmd's configless cache link, pointing into our tmp folder
        if cache.is_symlink() and str(root) in os.readlink(cache):
            cache.unlink()


@pytest.mark.slow
@pytest.mark.workflow
def test_smoke_mesh_runs_on_a_real_one_node_slurm_cluster(one_node_cluster, tmp_path):
    work = tmp_path / "work"
    target = "results/smoke/mesh/proc-0000.vtu"
    cmd = [SNAKEMAKE, "--snakefile", str(ROOT / "Snakefile"), "--profile", str(PROFILE), "--directory", str(work),
           "--config", "experiment=smoke", "--slurm-no-account", "--slurm-status-command", "squeue",
           "--slurm-init-seconds-before-status-checks", "2", "--jobs", "2", "--", target]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=900,
                          env={**one_node_cluster["env"], "PYTHONUNBUFFERED": "1"})
    text = proc.stdout + proc.stderr
    assert proc.returncode == 0, text[-4000:]
    submitted = re.findall(r"submitted with SLURM jobid (\d+)", text)
    assert len(submitted) == 2, text[-3000:]  # geometry + mesh went through sbatch
    from liverforce.mesh.io import read_mesh

    assert len(read_mesh(work / target).points) > 100
    decls = rule_declarations()
    seen = set()
    for jid in submitted:
        info = subprocess.run(["scontrol", "show", "job", jid], capture_output=True, text=True,
                              env=one_node_cluster["env"]).stdout
        assert "JobState=COMPLETED" in info, info
        comment = re.search(r"Comment=(\S+)", info).group(1)  # rule_<name>[_wildcards_...]
        name = next(r for r in decls if comment == f"rule_{r}" or comment.startswith(f"rule_{r}_wildcards"))
        d = decls[name]
        assert re.search(rf"MinMemoryNode={d['mem_mb']}M", info), (name, info)
        h, m = divmod(d["runtime"], 60)
        assert f"TimeLimit={h:02d}:{m:02d}:00" in info, (name, info)
        assert re.search(rf"NumCPUs={d['threads']}\b", info), (name, info)
        seen.add(name)
    assert seen == {"geometry", "mesh"}
