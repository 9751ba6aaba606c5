"""Experiment: where the camera model loses against the node model, per local force component.

Reads a finished run (``--results``), trains nothing. For the scenario-IV models
of the node variant (``--node``, default ``pca_sv``) and the camera variant
(``--camera``, default ``cloud_sv``) it prints the MAE of each local force
component (t1, t2 along the surface, n along the normal) and of the force
vector, mean over livers, on the run's unseen livers (scenario V) and on the
main split's IV test livers. The camera model is then re-observed with one
ideal camera setting at a time, nothing refitted (the validation's own
evaluation observation seed):

- ``noise0``: no point noise (``observation.noise_sd_mm: 0``);
- ``20k``: 20,000 points in the ROI (``observation.n_points``);
- ``tip0``: an exact tool tracker (``tip_noise_mm: 0``, every direction);
- ``ideal``: the three at once.

What is left under ``ideal`` is what the model's input (the height field over
the pre-operative surface, its coverage mask, the tool tip) and its fit cost,
not the camera's noise or density.

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python benchmarks/experiment_camera_loss.py --results results/default
"""

from __future__ import annotations

import argparse
import copy
import json
from pathlib import Path

import numpy as np

#: the ideal camera settings, one at a time and together (module docstring)
IDEAL = ("noise0", "20k", "tip0", "ideal")


def ideal_camera(camera: dict, which: str) -> dict:
    """These camera settings with one ideal setting (:data:`IDEAL`)."""
    from liverforce.learn.camera import isotropic_tip

    if which not in IDEAL:
        raise ValueError(f"unknown ideal setting '{which}' ({', '.join(IDEAL)})")
    cam = copy.deepcopy(camera)
    obs = cam.setdefault("observation", {})
    if which in ("noise0", "ideal"):
        obs["noise_sd_mm"] = 0.0
    if which in ("20k", "ideal"):
        obs["n_points"] = [20000, 20000]
    if which in ("tip0", "ideal"):
        cam = isotropic_tip(cam, 0.0)
    return cam


def component_mae(true_local: np.ndarray, pred_local: np.ndarray, groups) -> np.ndarray:
    """``[t1, t2, n, vector]`` MAE (N): each liver's mean absolute error, then the mean over the livers."""
    t = np.asarray(true_local, dtype=np.float64).reshape(-1, 3)
    p = np.asarray(pred_local, dtype=np.float64).reshape(-1, 3)
    g = np.asarray(groups).astype(str)
    if len(t) != len(p) or len(t) != len(g) or not len(t):
        raise ValueError(f"need as many true and predicted forces as groups, at least one (got {len(t)}, {len(p)}, "
                         f"{len(g)})")
    err = np.column_stack([np.abs(p - t), np.linalg.norm(p - t, axis=1)])
    return np.mean([err[g == k].mean(axis=0) for k in sorted(set(g.tolist()))], axis=0)


def line(variant: str, part: str, setting: str, mae: np.ndarray) -> str:
    return f"{variant:9s} {part:7s} {setting:8s} MAE t1 / t2 / n / vector " + " / ".join(f"{v:.3f}" for v in mae) + " N"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results/default")
    ap.add_argument("--node", default="pca_sv")
    ap.add_argument("--camera", default="cloud_sv")
    args = ap.parse_args()

    from liverforce.layout import Layout
    from liverforce.learn.frames import case_rotations, force_to_local
    from liverforce.learn.model import ForceModel, subset
    from liverforce.pipeline.shared import run_arrays

    run = Layout(args.results)
    unseen = run_arrays(args.results, "V", True, "camera-loss experiment")
    iv = run_arrays(args.results, "IV", True, "camera-loss experiment")
    geo = np.asarray(iv["geometry_id"]).astype(str)
    for variant in (args.node, args.camera):
        m = ForceModel.load(Path(run.model_dir("IV", variant)))
        doc = json.loads(Path(run.model_metrics("IV", variant)).read_text())
        test = subset(iv, np.flatnonzero(np.isin(geo, doc["split"]["test_geometries"])))
        seed = int(m.meta.get("eval_observation_seed", 0))
        parts = [("unseen", unseen), ("IV test", test)]
        if m.meta.get("final_fit"):  # train.final_fit: the saved model was fitted on the split's test livers too
            print(f"{variant}: the saved model is the final fit on every IV liver; no IV test row", flush=True)
            parts = parts[:1]
        for part, arrays in parts:
            settings = [("as is", m)]
            if m.representation.is_camera:
                settings += [(w, m.observed_with(ideal_camera(m.representation.camera, w))) for w in IDEAL]
            R = case_rotations(arrays)
            true_local = force_to_local(np.asarray(arrays["force_n"], dtype=np.float64), R)
            for name, model in settings:
                pred_local = force_to_local(model.predict(arrays, observation_seed=seed), R)
                print(line(variant, part, name, component_mae(true_local, pred_local, arrays["geometry_id"])),
                      flush=True)


if __name__ == "__main__":
    main()
