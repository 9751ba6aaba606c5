"""Experiment: how a state-vector model brings in the material (``model.force_scaling``), inside and outside
the training range of the constants.

Trains each variant once per force scaling through the pipeline's own training
(:func:`liverforce.learn.train.train_scenario`, ``train.repeats`` seeded
splits; no interval, no held-out points) on a finished run's shards
(``--results``), and scores the scenario-IV models on the unseen livers of
that run and of any further runs given with ``--unseen`` (the same unseen
livers and forces with other constants). Prints per variant, scenario and
scaling: test accuracy and MAE (mean +- sd over the splits); for IV, per
unseen set, the constants' factor against the training mean, the MAE (mean +-
sd over livers) and the median ratio of the predicted to the true force along
the true force (above 1: over-predicts).

``linear`` scales the linear force estimate by ``k = C10 / C10_ref``;
``stiffness`` the predicted force; ``none`` neither (:mod:`liverforce.learn.model`).
The supports' springs do not scale with the tissue, so ``stiffness`` over-predicts
a stiffer liver. Unseen sets at other constants, with no other stage re-run::

    .venv/bin/snakemake --cores 2 --config overrides="results_dir=results_x2 validate.material_scale=2.0" \\
        -- results_x2/default/shards/V/manifest.json
    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python benchmarks/experiment_force_scaling.py \\
        --results results/default --unseen results_x0.6/default results_x2/default
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

SCALINGS = ("linear", "stiffness", "none")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results/default")
    ap.add_argument("--unseen", nargs="*", default=[], help="further runs' folders whose V shards to score on")
    ap.add_argument("--variants", nargs="*", default=["pca_sv"])
    ap.add_argument("--scenarios", nargs="*", default=["III", "IV"])
    ap.add_argument("--scalings", nargs="*", default=list(SCALINGS))
    ap.add_argument("--out", default="/tmp/liverforce-experiment-force-scaling")
    args = ap.parse_args()

    from liverforce.config import compose, variant_model
    from liverforce.pipeline.shared import run_arrays
    from liverforce.learn.metrics import metrics_by_group
    from liverforce.learn.model import ForceModel, eval_seed
    from liverforce.learn.torchutil import configure_torch
    from liverforce.learn.train import train_scenario

    configure_torch(1)
    cfg = compose([])
    train = {k: v for k, v in cfg["train"].items() if k != "variants"}
    train.update(interval=None, heldout_points=None)
    variants = {x["name"]: x for x in cfg["train"]["variants"]}
    loaded: dict = {}

    def load(results: Path, scenario: str, camera: bool) -> dict:
        key = (str(results), scenario, camera)
        if key not in loaded:
            loaded[key] = run_arrays(results, scenario, camera, "force-scaling experiment")
        return loaded[key]

    results = Path(args.results)
    unseen_sets = [results, *map(Path, args.unseen)]
    for name in args.variants:
        v = variants[name]
        camera = str(v.get("roi_features", cfg["model"].get("roi_features"))) == "cloud"
        for scenario in args.scenarios:
            arrays = load(results, scenario, camera)
            c1_train = float(np.mean(np.asarray(arrays["material_params_mpa"])[:, 0]))
            for scaling in args.scalings:
                model_cfg = {**variant_model(cfg["model"], v), "force_scaling": scaling}
                t = time.perf_counter()
                res = train_scenario(arrays, model_cfg, train, cfg["tune"], scenario, name,
                                     out_dir=f"{args.out}/{name}-{scenario}-{scaling}")
                m, s = res["metrics_mean"], res["metrics_sd"]
                line = (f"{name:8s} {scenario:3s} {scaling:9s} test {m['accuracy_pct']:5.1f} +- "
                        f"{s['accuracy_pct']:.1f} %, MAE {m['mae_vec']:.3f} +- {s['mae_vec']:.3f} N "
                        f"({res['n_splits']} splits)")
                if scenario == "IV":
                    model = ForceModel.load(res["model_path"])
                    for folder in unseen_sets:
                        u = load(folder, "V", camera)
                        pred = model.predict(u, observation_seed=eval_seed(int(res["seed"])))
                        g = metrics_by_group(u["force_n"], pred, u["geometry_id"])
                        true = np.asarray(u["force_n"], float)
                        ratio = np.median((pred * true).sum(1) / (true * true).sum(1))
                        k = np.median(np.asarray(u["material_params_mpa"])[:, 0]) / c1_train
                        line += (f" | unseen x{k:.2f}: MAE {g['mean']['mae_vec']:.3f} +- {g['sd']['mae_vec']:.3f} N, "
                                 f"ratio {ratio:.3f}")
                print(f"{line} | {time.perf_counter() - t:.0f} s", flush=True)


if __name__ == "__main__":
    main()
