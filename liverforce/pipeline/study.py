"""Study stage adapter: one comparison study on existing shards (no new FE)."""

from __future__ import annotations

import json
import logging
from pathlib import Path

from liverforce.atomic import write_json_atomic
from liverforce.pipeline.shared import load_study_arrays, surface_graphs

log = logging.getLogger("liverforce")


def run_study_stage(study: str, study_cfg: dict, manifests: dict, main_metrics: dict, mesh_paths: list[str],
                    model_cfg: dict, train_cfg: dict, tracking_uri: str, experiment_name: str, experiment: str,
                    seed: int, threads: int, out_json, out_png) -> dict:
    """Run one comparison study on the existing shards; write ``studies/<study>.json`` + PNG, log MLflow runs.

    ``manifests`` / ``main_metrics``: scenario -> path. ``experiment_name``:
    the MLflow experiment (``Plan.experiment_name("studies")``); ``experiment``
    the run's experiment, a tag. The points reuse the main model's split seed
    (``seed``: ``Plan.train_seed()``, as the training jobs) and tuned
    hyper-parameters.
    """
    from liverforce.learn.study import plot_study, run_study
    from liverforce.tracking import Tracker

    surfaces = surface_graphs(mesh_paths) if study == "roi_fraction" else None
    data, versions = {}, {}
    for sc, mp in manifests.items():
        data[sc] = load_study_arrays(mp, full_surface=study == "roi_fraction")
        versions[sc] = json.loads(Path(mp).read_text())["data_version"]
        log.info("study %s: scenario %s, %d converged cases (data version %s)", study, sc,
                 len(data[sc]["case_id"]), versions[sc])
    mains = {sc: json.loads(Path(p).read_text()) for sc, p in main_metrics.items()}
    tracker = Tracker(tracking_uri, experiment_name)
    doc = run_study(study, study_cfg, data, model_cfg, mains, train_cfg, seed=seed,
                    threads=threads, surfaces=surfaces, tracker=tracker,
                    tags={"experiment": experiment,
                          "data_version": ",".join(f"{k}:{v}" for k, v in sorted(versions.items()))})
    doc["data_version"] = versions
    doc["main_model_runs"] = {sc: m.get("run_id") for sc, m in mains.items()}
    plot_study(doc, out_png)
    doc["figure"] = Path(out_png).name
    write_json_atomic(out_json, doc)
    ok = sum(p["status"] == "ok" for p in doc["points"])
    log.info("study %s: %d/%d points in %.1f s (%.1f s CPU)", study, ok, len(doc["points"]), doc["seconds"],
             doc["cpu_seconds"])
    return doc


