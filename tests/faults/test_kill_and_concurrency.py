"""SIGKILL of the whole workflow mid-sweep and mid-training; two trainings on one SQLite store at once.

A small slice of the smoke experiment (scenario I, 12 cases in 4 shards, both
variants trained) runs once uninterrupted: the reference. Its two training
jobs run together (``--cores 2``) and log to the same embedded SQLite MLflow
store: no "database is locked" failure, no lost run, and the two runs really
overlapped in time.

Then, in copies of the reference folder (Snakemake metadata kept), the
workflow's process group is SIGKILLed

- mid-sweep: at least one shard written, not all;
- mid-training: a training job's MLflow run has started;

and resumed with the README's command (``snakemake --unlock`` then
``snakemake --cores 2 --rerun-incomplete``). The final shards' payload hashes,
their case ids and the models' metrics must equal the reference's. Rows lost
are measured (case ids of the final shards against the reference) and go to
the fault ledger.
"""
from __future__ import annotations

import base64
import json
import os
import shutil
import signal
import sqlite3
import subprocess
import tempfile
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from test_workflow import ROOT, SNAKEMAKE, job_counts, snakemake

pytestmark = [pytest.mark.slow, pytest.mark.workflow]

EXPERIMENT = "smoke"
N_CASES, PER_SHARD = 12, 3
N_SHARDS = N_CASES // PER_SHARD
OVERRIDES = f"sweep.scenarios.I.n_cases={N_CASES} sweep.cases_per_shard={PER_SHARD} mesh.target_nodes=300"
RESULTS = Path("results") / EXPERIMENT
VARIANTS = ("pca_sv", "ae_sv")
TARGETS = [str(RESULTS / "models" / "I" / v / "metrics.json") for v in VARIANTS]
#: metrics that depend on the wall clock or the run, not on data and config
VOLATILE = {"run_id", "seconds", "wall_time_s", "model_uri", "model_path", "trial_seconds", "started", "finished"}


def args(work: Path, *extra: str) -> list[str]:
    return [*extra, "--directory", str(work), "--config", f"experiment={EXPERIMENT}", f"overrides={OVERRIDES}",
            "--", *TARGETS]


def shard_dir(work: Path) -> Path:
    return work / RESULTS / "shards" / "I"


def payloads(work: Path) -> dict[str, str]:
    m = json.loads((shard_dir(work) / "manifest.json").read_text())
    return {e["file"]: e["payload_sha256"] for e in m["shards"]}


def case_ids(work: Path) -> set[str]:
    ids: list[str] = []
    for p in sorted(shard_dir(work).glob("shard-*.parquet")):
        ids += pq.read_table(p, columns=["case_id"]).column("case_id").to_pylist()
    assert len(ids) == len(set(ids)), "a case is in two shards"
    return set(ids)


def stable(value):
    if isinstance(value, dict):
        return {k: stable(v) for k, v in value.items() if k not in VOLATILE}
    if isinstance(value, list):
        return [stable(v) for v in value]
    return value


def model_metrics(work: Path) -> dict[str, dict]:
    return {v: stable(json.loads((work / RESULTS / "models" / "I" / v / "metrics.json").read_text()))
            for v in VARIANTS}


def store_runs(work: Path) -> list[tuple]:
    """(run name, status, start ms, end ms, parent run id or None) of every run in the embedded store."""
    con = sqlite3.connect(work / "results" / "mlflow.db")
    try:
        rows = con.execute(
            "select r.name, r.status, r.start_time, r.end_time, "
            "(select value from tags t where t.run_uuid = r.run_uuid and t.key = 'mlflow.parentRunId') "
            "from runs r").fetchall()
    finally:
        con.close()
    return rows


def all_logs(work: Path) -> str:
    return "\n".join(p.read_text(errors="replace") for p in (work / RESULTS / "logs").rglob("*.log"))


def incomplete_markers(work: Path) -> set[str]:
    """File names Snakemake has marked incomplete (job started, its finish not yet recorded)."""
    names = set()
    folder = work / ".snakemake" / "incomplete"
    for p in folder.iterdir() if folder.is_dir() else []:
        try:
            names.add(Path(base64.urlsafe_b64decode(p.name).decode()).name)
        except (ValueError, UnicodeDecodeError):
            names.add(Path(base64.b64decode(p.name).decode(errors="replace")).name)
    return names


def copy_run(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst, symlinks=True)
    return dst


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
        return True
    except ProcessLookupError:
        return False


def run_and_kill(work: Path, log: Path, ready) -> dict:
    """Start the workflow in its own process group; SIGKILL the group as soon as ``ready()`` is truthy."""
    cmd = [SNAKEMAKE, "--snakefile", str(ROOT / "Snakefile"), *args(work, "--cores", "2")]
    with open(log, "w") as out:
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT, start_new_session=True,
                                env={**os.environ, "PYTHONUNBUFFERED": "1"})
        deadline = time.monotonic() + 600
        state = None
        try:
            while time.monotonic() < deadline and proc.poll() is None:
                state = ready()
                if state:
                    os.killpg(proc.pid, signal.SIGKILL)
                    break
                time.sleep(0.05)
        finally:
            if proc.poll() is None and not state:
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=60)
    assert proc.returncode == -signal.SIGKILL and state, (
        f"the workflow was not killed at the intended moment (return code {proc.returncode}):\n"
        f"{log.read_text()[-3000:]}")
    t0 = time.monotonic()
    while _group_alive(proc.pid) and time.monotonic() - t0 < 30:
        time.sleep(0.1)
    assert not _group_alive(proc.pid), "jobs of the killed workflow are still running"
    return state


def resume_with_readme_command(work: Path) -> str:
    """``snakemake --unlock && snakemake --cores 2 --rerun-incomplete`` (as the README says)."""
    readme = (ROOT / "README.md").read_text()
    assert "snakemake --unlock && .venv/bin/snakemake --cores 2 --rerun-incomplete" in readme
    snakemake(*args(work, "--unlock"))
    res = snakemake(*args(work, "--cores", "2", "--rerun-incomplete"))
    return res.stdout + res.stderr


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    work = tmp_path_factory.mktemp("reference")
    res = snakemake(*args(work, "--cores", "2"))
    counts = job_counts(res.stdout + res.stderr)
    assert counts.get("simulate") == N_SHARDS and counts.get("train") == len(VARIANTS), counts
    (work.parent / "reference-payloads.json").write_text(json.dumps(payloads(work)))
    return work


def reference_payloads(reference: Path) -> dict[str, str]:
    """The reference's payload hashes as first written (and a check that nothing changed them since)."""
    first = json.loads((reference.parent / "reference-payloads.json").read_text())
    assert payloads(reference) == first, "the reference run's shards changed during the session"
    return first


def test_two_trainings_share_the_sqlite_store_at_once(reference, fault_ledger):
    text = all_logs(reference)
    runs = store_runs(reference)
    with fault_ledger.check("two trainings writing one SQLite MLflow store at once", rows_expected=len(runs)) as seen:
        seen.rows_found = sum(r[1] == "FINISHED" for r in runs)
        seen.detail["runs"] = len(runs)
        parents = {name: (status, start, end) for name, status, start, end, parent in runs if parent is None}
        assert set(parents) == {f"I-{v}" for v in VARIANTS}, parents
        (s1, a1, b1), (s2, a2, b2) = parents.values()
        assert s1 == s2 == "FINISHED"
        overlap_ms = min(b1, b2) - max(a1, a2)
        seen.detail["overlap_s"] = round(overlap_ms / 1000, 1)
        assert overlap_ms > 0, f"the two trainings did not run at the same time: {parents}"
        nested = [r for r in runs if r[4] is not None]
        per_parent = {}
        for r in nested:
            per_parent[r[4]] = per_parent.get(r[4], 0) + 1
        # nested runs are Ax trials: the smoke experiment tunes ae_sv's MLP; pca_sv's GP has no search
        assert len(per_parent) == 1 and min(per_parent.values()) >= 1, per_parent
        assert all(r[1] == "FINISHED" for r in runs), runs
        assert "database is locked" not in text.lower()
        for v in VARIANTS:
            m = json.loads((reference / RESULTS / "models" / "I" / v / "metrics.json").read_text())
            assert m["run_id"] in {row for row in _run_ids(reference)}


def _run_ids(work: Path) -> list[str]:
    con = sqlite3.connect(work / "results" / "mlflow.db")
    try:
        return [r[0] for r in con.execute("select run_uuid from runs")]
    finally:
        con.close()


def test_sigkill_mid_sweep_then_resume_equals_uninterrupted(reference, tmp_path, fault_ledger):
    work = copy_run(reference, tmp_path / "sweep-killed")
    shutil.rmtree(shard_dir(work))  # keep geometry, mesh, case table: the sweep starts again
    shutil.rmtree(work / RESULTS / "models")
    shutil.rmtree(work / RESULTS / "progress", ignore_errors=True)

    def ready():
        # at least one shard written and registered by Snakemake as finished, not all shards there
        on_disk = sorted(p.name for p in shard_dir(work).glob("shard-*.parquet")) if shard_dir(work).exists() else []
        registered = [n for n in on_disk if n not in incomplete_markers(work)]
        return registered if registered and len(on_disk) < N_SHARDS else None

    killed_with = run_and_kill(work, tmp_path / "killed.out", ready)
    ref_ids = case_ids(reference)
    # what a kill in the middle of writing leaves, made sure of whatever the moment of this kill was: the
    # temporary files of a shard the resume must redo (not on disk, or marked incomplete; decided now that every
    # job is dead) and of its progress file, under atomic_path's own names for them
    incomplete = incomplete_markers(work)
    names = [f"shard-{i:04d}.parquet" for i in range(N_SHARDS)]
    redo = next(n for n in names if not (shard_dir(work) / n).exists() or n in incomplete)
    unfinished = redo.removesuffix(".parquet")
    planted = []
    for target in (shard_dir(work) / f"{unfinished}.parquet",
                   work / RESULTS / "progress" / f"I-{unfinished.removeprefix('shard-')}.json"):
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(prefix=f".{target.stem}.", suffix=f".tmp{target.suffix}", dir=target.parent)
        os.write(fd, b"half of it")
        os.close(fd)
        planted.append(Path(name))
    with fault_ledger.check("SIGKILL of the workflow mid-sweep", rows_expected=len(ref_ids),
                            shards_finished_at_kill=len(killed_with)) as seen:
        assert not (shard_dir(work) / "manifest.json").exists()
        text = resume_with_readme_command(work)
        counts = job_counts(text)
        ids = case_ids(work)
        seen.rows_found = len(ids & ref_ids)
        seen.detail["simulate_rerun"] = counts.get("simulate", 0)
        assert 1 <= counts.get("simulate", 0) <= N_SHARDS - len(killed_with), counts  # finished shards were kept
        assert not {"geometry", "mesh", "sweep"} & set(counts), counts
        assert ids == ref_ids
        assert payloads(work) == reference_payloads(reference)
        assert model_metrics(work) == model_metrics(reference)
        assert not any(p.exists() for p in planted)
        assert not list((work / RESULTS).rglob(".*.tmp*"))


def test_sigkill_mid_training_then_resume_equals_uninterrupted(reference, tmp_path, fault_ledger):
    work = copy_run(reference, tmp_path / "train-killed")
    shutil.rmtree(work / RESULTS / "models")  # shards stay: only the trainings run again
    before = set(_run_ids(work))

    def ready():
        logs = list((work / RESULTS / "logs" / "train").glob("*.log"))
        try:
            started = set(_run_ids(work)) - before
        except sqlite3.Error:
            return None
        # a training job has begun logging to MLflow (its parent run exists), and no model is complete
        done = list((work / RESULTS / "models").rglob("metrics.json"))
        return started if started and logs and not done else None

    started = run_and_kill(work, tmp_path / "killed.out", ready)
    ref_ids = case_ids(reference)
    with fault_ledger.check("SIGKILL of the workflow mid-training", rows_expected=len(ref_ids),
                            runs_started_before_kill=len(started)) as seen:
        _check_training_resume(work, reference, tmp_path, started, seen, ref_ids)


def _check_training_resume(work, reference, tmp_path, started, seen, ref_ids):
    killed_text = (tmp_path / "killed.out").read_text()
    killed_counts = job_counts(killed_text) if "Job stats" in killed_text else {}
    assert set(killed_counts) <= {"train"}, killed_counts  # the killed run had only trainings to do
    assert not list((work / RESULTS / "models").rglob("metrics.json"))
    text = resume_with_readme_command(work)
    seen.rows_found = len(case_ids(work) & ref_ids)
    counts = job_counts(text)
    assert set(counts) <= {"train"} and counts.get("train") == len(VARIANTS), counts

    after = store_runs(work)
    finished_parents = [r for r in after if r[4] is None and r[1] == "FINISHED"]
    assert payloads(work) == reference_payloads(reference)
    assert model_metrics(work) == model_metrics(reference)
    # every model's metrics.json names a finished run of the store (the killed run is not the one cited)
    finished_ids = {r for r in _run_ids(work)}
    for v in VARIANTS:
        m = json.loads((work / RESULTS / "models" / "I" / v / "metrics.json").read_text())
        assert m["run_id"] in finished_ids and m["run_id"] not in started
    assert len(finished_parents) >= 2 * len(VARIANTS)  # the reference's two + the resumed two
    # the killed jobs' runs are not left RUNNING: the resumed jobs' trackers marked them KILLED
    killed_runs = {r for r in started}
    statuses = {run_id: status for run_id, status in _run_status(work)}
    assert {statuses[r] for r in killed_runs} <= {"KILLED", "FINISHED"}  # trials done before the kill stay
    assert "KILLED" in {statuses[r] for r in killed_runs}, {r: statuses[r] for r in killed_runs}
    assert "RUNNING" not in statuses.values()


def _run_status(work: Path) -> list[tuple[str, str]]:
    con = sqlite3.connect(work / "results" / "mlflow.db")
    try:
        return list(con.execute("select run_uuid, status from runs"))
    finally:
        con.close()


@pytest.mark.parametrize("fault", ["slow_solver", "diverging", "crash"])
def test_hanging_diverging_or_crashing_cases_are_bounded_and_recorded(reference, tmp_path, monkeypatch, fault,
                                                                     fault_ledger):
    """One shard of the reference's case table simulated with a solver fault: every case becomes a row
    with its reason, each case is bounded by the configured limits, and the shard is written."""
    from liverforce.config import compose
    from liverforce.fem.linsolve import LinearSolver
    from liverforce.fem.problem import LiverModel
    from liverforce.pipeline.simulate import simulate_shard

    cfg = compose([f"experiment={EXPERIMENT}", *OVERRIDES.split()])
    sim = dict(cfg["simulate"])
    cases = reference / RESULTS / "sweep" / "I" / "cases.parquet"
    meshes = [str(p) for p in sorted((reference / RESULTS / "mesh").glob("*.vtu"))]
    expected = [r["case_id"] for r in pq.read_table(cases).to_pylist() if r["shard_index"] == 0]
    if fault == "slow_solver":  # every linear solve takes 0.3 s: a case would run far past its limit
        real_solve = LinearSolver.solve
        monkeypatch.setattr(LinearSolver, "solve", lambda self, b: (time.sleep(0.3), real_solve(self, b))[1])
        sim["time_limit_s"] = 1.0
        sim["warm_start"] = False
    elif fault == "diverging":
        sim["max_iter"], sim["max_steps"] = 1, 2
    else:  # the second case's solve raises
        real = LiverModel.solve
        calls = []

        def flaky(self, *a, **kw):
            calls.append(1)
            if len(calls) == 2:
                raise FloatingPointError("injected solver crash")
            return real(self, *a, **kw)

        monkeypatch.setattr(LiverModel, "solve", flaky)
    out = tmp_path / RESULTS / "shards" / "I" / "shard-0000.parquet"
    reference_converged = {r["case_id"]: r["converged"] for r in pq.read_table(
        reference / RESULTS / "shards" / "I" / "shard-0000.parquet", columns=["case_id", "converged"]).to_pylist()}
    with fault_ledger.check(f"solver fault: {fault}", rows_expected=len(expected)) as seen:
        t0 = time.monotonic()
        entry = simulate_shard(str(cases), meshes, 0, sim, cfg["boundary"], cfg["dataset"], str(out))
        seen.detail["seconds"] = round(time.monotonic() - t0, 1)
        rows = pq.read_table(out).to_pylist()
        seen.rows_found = len({r["case_id"] for r in rows} & set(expected))
        seen.detail["failed"] = entry["failed"]
        assert [r["case_id"] for r in rows] == expected  # no case dropped, the shard went on after each failure
        failed = [r for r in rows if not r["converged"]]
        if fault == "slow_solver":
            assert failed and all("time limit" in r["reason"] for r in failed), [r["reason"] for r in rows]
            assert max(r["wall_time_s"] for r in rows) < sim["time_limit_s"] + 5.0  # bounded by the limit
        elif fault == "diverging":
            assert len(failed) == len(rows) and all("max_steps=2" in r["reason"] for r in failed)
        else:
            assert [r["case_id"] for r in failed][:1] == [expected[1]]
            assert "FloatingPointError: injected solver crash" in failed[0]["reason"]
            # every other case ends as in the uninterrupted reference run (the crash costs only its own case)
            others = {r["case_id"]: r["converged"] for r in rows if r["case_id"] != expected[1]}
            assert others == {c: reference_converged[c] for c in others}, (others, reference_converged)
        assert entry["failed"] == len(failed)
