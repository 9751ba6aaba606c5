"""Train stage adapter: one scenario/variant from verified shards, tracked in MLflow."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from liverforce.atomic import write_json_atomic
from liverforce.dataset import io as dio
from liverforce.pipeline.provenance import training_provenance
from liverforce.pipeline.shared import camera_arrays, load_study_arrays, surface_graphs

log = logging.getLogger("liverforce")


def train_model(manifest_path, scenario: str, variant: str, model_cfg: dict, train_cfg: dict, tune_cfg: dict,
                tracking_uri: str, experiment_name: str, experiment: str, seed: int, threads: int,
                metrics_path, model_dir, mesh_paths: list[str] | None = None) -> dict:
    """Train one scenario/variant from verified shards; track it in MLflow.

    ``experiment_name``: the MLflow experiment (``Plan.experiment_name(scenario)``);
    ``experiment`` the run's experiment, a tag. ``seed``: the split seed every
    variant of the run shares (``Plan.train_seed()``).

    Every shard is checked against the manifest's hash before it is read: a
    truncated or modified shard stops training with its name (delete it and
    re-run to rebuild it). A camera-cloud variant (``roi_features: cloud``) reads the
    full-surface displacements and the scenario's meshes (``mesh_paths``) to observe
    the cases with the camera model. With ``model_cfg["roi_fraction"]`` set, the ROI is
    re-grown at that area fraction from the stored full-surface displacements
    (``mesh_paths``: the scenario's meshes) and the model is trained and saved
    for that fraction.

    The model and its run record what it was trained on (``meta["provenance"]``: each liver's origin, the
    material as configured), read from the results layout the manifest sits in
    (:func:`liverforce.pipeline.provenance.training_provenance`); what is missing there is recorded as unknown.
    """
    from liverforce.config import config_hash
    from liverforce.learn.provenance import provenance_lines
    from liverforce.learn.train import clear_outputs, train_scenario
    from liverforce.tracking import Tracker

    out_dir = Path(metrics_path).parent
    # before anything slow: an earlier run's metrics and model files never stay beside (or instead of) this
    # run's, even when an interrupt stops it before training (Snakemake removes the declared outputs only)
    Path(metrics_path).unlink(missing_ok=True)
    for p in clear_outputs(out_dir):
        log.info("removed %s, an earlier training run's output", p)
    shards = dio.verify_manifest(manifest_path)
    manifest = json.loads(Path(manifest_path).read_text())
    shard_meta = dio.read_metadata(shards[0])
    roi_fraction = float(shard_meta["dataset"]["roi_fraction"])
    wanted = model_cfg.get("roi_fraction")
    if wanted is not None and abs(float(wanted) - roi_fraction) > 1e-12:
        from liverforce.learn.representation import with_roi_fraction

        if not mesh_paths:
            raise ValueError(f"variant {variant}: model.roi_fraction={wanted} needs the scenario's meshes")
        arrays = with_roi_fraction(load_study_arrays(manifest_path, full_surface=True), float(wanted),
                                   surface_graphs(mesh_paths))
        arrays.pop("surface_displacement_mm", None)
        log.info("scenario %s / %s: ROI re-grown at %.3f of the surface (shards: %.3f; achieved mean %.3f)",
                 scenario, variant, float(wanted), roi_fraction, float(np.mean(arrays["roi_area_fraction"])))
        roi_fraction = float(wanted)
    elif model_cfg.get("roi_features") == "cloud":
        if wanted is not None:
            raise ValueError(f"variant {variant}: model.roi_fraction does not apply to a camera-cloud model "
                             "(the camera sees what model.camera says)")
        arrays = camera_arrays(manifest_path, mesh_paths, f"variant {variant}")
    else:
        arrays = dio.load_training_arrays(shards)
    n = len(arrays["case_id"])
    log.info("scenario %s / %s: %d converged cases from %d shards (data version %s)", scenario, variant, n,
             len(shards), manifest["data_version"])
    if n < 10:
        raise RuntimeError(
            f"scenario {scenario}: only {n} converged cases in {manifest_path}; too few to train "
            f"({manifest['failed']} failed — see the 'reason' column); raise sweep.scenarios.{scenario}.n_cases"
        )
    tracker = Tracker(tracking_uri, experiment_name)
    tags = {
        "rule": "train", "scenario": scenario, "variant": variant, "experiment": experiment,
        "config_hash": config_hash({"model": model_cfg, "train": train_cfg, "tune": tune_cfg}),
        "data_version": manifest["data_version"],
    }
    model_meta = {
        "roi_fraction": roi_fraction,
        "frame_radius_mm": float(shard_meta["simulate"]["tool_radius_mm"]),
        "data_version": manifest["data_version"],
    }
    if shard_meta.get("probe"):  # what serving needs to recompute the probe compliance from a liver's mesh
        model_meta["probe"] = {"reference": shard_meta["probe"], "boundary": shard_meta["boundary"],
                               "simulate": shard_meta["simulate"],
                               "tool_radius_mm": float(shard_meta["simulate"]["tool_radius_mm"])}
    # what it was trained on, from the geometry records and the case table the earlier stages wrote
    provenance = training_provenance(manifest_path, arrays["geometry_id"], shard_meta)
    for line in provenance_lines(provenance):
        log.info("scenario %s / %s: trained on %s", scenario, variant, line)
    result = train_scenario(arrays, model_cfg, train_cfg, tune_cfg, scenario, variant, tracker=tracker,
                            threads=threads, seed=seed, out_dir=out_dir, tags=tags,
                            model_meta=model_meta, provenance=provenance)
    result.update(encoder=model_cfg["encoder"], state_vector=bool(model_cfg["state_vector"]), model_cfg=model_cfg)
    write_json_atomic(metrics_path, result)
    log.info("scenario %s / %s: test %s", scenario, variant,
             {k: round(v, 4) for k, v in result.get("metrics", {}).items() if isinstance(v, float)})
    return result


