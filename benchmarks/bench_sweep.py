"""Benchmark of the data factory end to end: geometry -> mesh -> sweep -> simulate -> shards.

Runs ``snakemake --cores 2 shards`` (every scenario's manifest, from scratch)
for an experiment in a temporary directory and prints:

1. end-to-end cases per hour on the given cores: rows in the manifests (all
   cases, failed ones included; converged ones separately) over the wall
   time of the Snakemake run;
2. where the time went, as shares of the summed job time (start to finish of
   every Snakemake job, from the run's ``.snakemake/log``, 1 s resolution):
   meshing (``meshing_time_s`` of every ``mesh/*.features.json``), solving
   (sum of ``wall_time_s`` over all shard rows), and the rest: I/O, ROI
   extraction, process start-up and imports of every job, geometry, case
   tables, manifests;
3. how busy the cores were: summed job time / (cores x wall time); the
   remainder is Snakemake scheduling and idle cores.

Medians over ``--repeats`` runs.

Usage::

    python benchmarks/bench_sweep.py --quick             # smoke experiment, 1 run
    python benchmarks/bench_sweep.py                     # default experiment
    python benchmarks/bench_sweep.py --experiment smoke --repeats 3 --overrides "mesh.target_nodes=600"
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from datetime import datetime

from liverforce.pipeline.job import thread_env
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SNAKEMAKE = str(Path(sys.executable).with_name("snakemake"))

_TS = re.compile(r"^\[(\w{3} \w{3} +\d+ \d\d:\d\d:\d\d \d{4})\]$")
_START = re.compile(r"^(?:local)?rule (\w+):$")
_JOBID = re.compile(r"^\s+jobid: (\d+)$")
_END = re.compile(r"^Finished jobid: (\d+) \(Rule: (\w+)\)$")


def job_times(log_text: str) -> dict[int, tuple[str, float]]:
    """``{jobid: (rule, seconds)}`` from a Snakemake 9 run log (start/finish timestamps)."""
    now = None
    pending = None
    start: dict[int, tuple[str, datetime]] = {}
    out: dict[int, tuple[str, float]] = {}
    for line in log_text.splitlines():
        if m := _TS.match(line):
            now = datetime.strptime(m.group(1), "%a %b %d %H:%M:%S %Y")
        elif m := _START.match(line):
            pending = (m.group(1), now)
        elif (m := _JOBID.match(line)) and pending is not None:
            start[int(m.group(1))] = pending
            pending = None
        elif m := _END.match(line):
            jid = int(m.group(1))
            if jid in start:
                rule, t0 = start[jid]
                out[jid] = (rule, (now - t0).total_seconds())
    return out


def read_parquet_column(path: Path, name: str) -> list:
    import pyarrow.parquet as pq

    return pq.read_table(path, columns=[name]).column(name).to_pylist()


def one_run(experiment: str, cores: int, overrides: str, keep: bool) -> dict:
    work = Path(tempfile.mkdtemp(prefix=f"bench_sweep_{experiment}_"))
    cmd = [SNAKEMAKE, "--snakefile", str(ROOT / "Snakefile"), "--cores", str(cores), "--directory", str(work),
           "--config", f"experiment={experiment}"]
    if overrides:
        cmd.append(f"overrides={overrides}")
    cmd += ["--", "shards"]
    env = thread_env(1, {**os.environ, "PYTHONUNBUFFERED": "1"}, override=False)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"snakemake failed (outputs kept in {work}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    root = work / "results" / experiment
    rows = failed = 0
    solve = 0.0
    for m in sorted((root / "shards").glob("*/manifest.json")):
        man = json.loads(m.read_text())
        rows += man["rows"]
        failed += man["failed"]
        for e in man["shards"]:
            solve += sum(read_parquet_column(m.parent / e["file"], "wall_time_s"))
    meshing = sum(json.loads(f.read_text())["meshing_time_s"] for f in (root / "mesh").glob("*.features.json"))
    logs = sorted((work / ".snakemake" / "log").glob("*.snakemake.log"))
    jobs = job_times(logs[-1].read_text())
    per_rule: dict[str, float] = defaultdict(float)
    n_jobs: dict[str, int] = defaultdict(int)
    for rule, sec in jobs.values():
        per_rule[rule] += sec
        n_jobs[rule] += 1
    job_total = sum(per_rule.values())
    if not keep:
        import shutil

        shutil.rmtree(work, ignore_errors=True)
    return {
        "wall_s": wall, "rows": rows, "failed": failed, "cases_per_h": rows / wall * 3600,
        "converged_per_h": (rows - failed) / wall * 3600, "meshing_s": meshing, "solve_s": solve,
        "job_total_s": job_total, "rest_s": job_total - meshing - solve,
        "share_meshing": meshing / job_total, "share_solve": solve / job_total,
        "share_rest": (job_total - meshing - solve) / job_total,
        "core_busy": job_total / (cores * wall), "per_rule_s": dict(per_rule), "n_jobs": dict(n_jobs),
        "work": str(work) if keep else None,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the smoke experiment, one run")
    ap.add_argument("--experiment", default=None, help="experiment (default: smoke with --quick, else default)")
    ap.add_argument("--repeats", type=int, default=1, help="runs from scratch (medians reported)")
    ap.add_argument("--cores", type=int, default=2)
    ap.add_argument("--overrides", default="", help='Hydra overrides, e.g. "mesh.target_nodes=600"')
    ap.add_argument("--keep", action="store_true", help="keep the temporary run folders")
    args = ap.parse_args()
    experiment = args.experiment or ("smoke" if args.quick else "default")
    repeats = 1 if args.quick else max(1, args.repeats)
    print(f"bench_sweep: experiment={experiment}, snakemake --cores {args.cores} shards, repeats={repeats}"
          + (f", overrides '{args.overrides}'" if args.overrides else ""), flush=True)
    runs = []
    for i in range(repeats):
        r = one_run(experiment, args.cores, args.overrides, args.keep)
        runs.append(r)
        print(f"  run {i + 1}: {r['rows']} cases ({r['failed']} failed) in {r['wall_s']:.1f} s wall -> "
              f"{r['cases_per_h']:.0f} cases/h" + (f"  [kept: {r['work']}]" if r["work"] else ""), flush=True)

    def med(key):
        return statistics.median(r[key] for r in runs)

    print(f"\n== data factory, experiment '{experiment}', {args.cores} cores (median of {repeats}) ==")
    print(f"cases                      {runs[0]['rows']} ({runs[0]['failed']} failed)")
    print(f"wall time                  {med('wall_s'):.1f} s")
    print(f"end-to-end throughput      {med('cases_per_h'):.0f} cases/h  ({med('converged_per_h'):.0f} converged cases/h)")
    print(f"summed job time            {med('job_total_s'):.0f} s  (cores busy {100 * med('core_busy'):.0f} % "
          f"of {args.cores} x wall; the rest is scheduling and idle cores)")
    print("share of summed job time:")
    print(f"  meshing                  {100 * med('share_meshing'):5.1f} %  ({med('meshing_s'):.1f} s, features.json meshing_time_s)")
    print(f"  solving                  {100 * med('share_solve'):5.1f} %  ({med('solve_s'):.1f} s, shard wall_time_s)")
    print(f"  rest (I/O + overhead)    {100 * med('share_rest'):5.1f} %  ({med('rest_s'):.1f} s)")
    print("summed job time per rule (median s, jobs):")
    for rule in sorted(runs[0]["per_rule_s"], key=lambda k: -runs[0]["per_rule_s"][k]):
        t = statistics.median(r["per_rule_s"].get(rule, 0.0) for r in runs)
        print(f"  {rule:24s} {t:8.0f} s  {runs[0]['n_jobs'][rule]:4d} jobs")
    return 0


if __name__ == "__main__":
    sys.exit(main())
