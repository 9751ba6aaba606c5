"""Sweep progress: cases done / total and the rate, from the jobs' progress files.

Each simulate job rewrites its progress file (``Plan.paths.progress``:
``<results>/progress/<scenario>-<shard>.json``, atomically) after every case;
finished shards count fully. Read-only: safe to call while Snakemake runs
(``liverforce progress -e default``, or ``watch -n 5 liverforce progress``).
"""

from __future__ import annotations

import json
import time
from pathlib import Path


def sweep_progress(plan) -> dict:
    """Summarise the progress of every scenario's shards of ``plan`` (a :class:`~liverforce.pipeline.plan.Plan`)."""
    done = failed = 0
    rates = []
    now = time.time()
    running = 0
    for scenario in plan.all_scenarios():
        for sid in plan.shard_ids(scenario):
            pfile = Path(plan.paths.progress(scenario, sid))
            shard = Path(plan.paths.shard(scenario, sid))
            if not pfile.exists():
                continue
            try:
                p = json.loads(pfile.read_text())
            except (OSError, json.JSONDecodeError):
                continue
            done += p["done"]
            failed += p["failed"]
            if p["elapsed_s"] > 0:
                rates.append(p["done"] / p["elapsed_s"] * 3600)
            if not shard.exists() and now - p["updated"] < 600:
                running += 1
    total = sum(plan.scenario_spec(s)["n_cases"] for s in plan.all_scenarios())
    return {"done": done, "total": total, "failed": failed, "running_shards": running,
            "cases_per_hour_per_job": (sum(rates) / len(rates)) if rates else 0.0}


def format_progress(p: dict) -> str:
    pct = 100 * p["done"] / p["total"] if p["total"] else 0.0
    bar = "#" * int(pct / 5) + "." * (20 - int(pct / 5))
    return (f"[{bar}] {p['done']}/{p['total']} cases ({pct:.0f} %), {p['failed']} failed, "
            f"{p['running_shards']} shard jobs running, ~{p['cases_per_hour_per_job']:.0f} cases/h per job")
