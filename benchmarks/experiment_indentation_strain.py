"""Experiment: what the indentation strain ``u_w,n / h`` (``model.indentation_strain``) is worth.

Trains each variant with and without it through the pipeline's own training
(:func:`liverforce.learn.train.train_scenario`, ``train.repeats`` seeded splits
with the pipeline's split seed, so the "on" rows of the default config repeat
the run's own figures; no interval, no held-out points) on a finished run's
shards (``--results``). Prints per variant, scenario and setting: test accuracy
and MAE (mean +- sd over the splits), the accuracy of each split, and for IV the
MAE on the run's unseen livers (mean +- sd over livers; the main split's model,
the one the validation scores)::

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python benchmarks/experiment_indentation_strain.py \\
        --results results/default --variants pca_sv ae_sv cloud_sv --scenarios II III IV

The strain reads the linear force estimate's ``u_w`` (the tool tip's for a
camera model), so a variant without it (no state vector) is the same either way.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results/default")
    ap.add_argument("--variants", nargs="*", default=["pca_sv"])
    ap.add_argument("--scenarios", nargs="*", default=["IV"])
    ap.add_argument("--out", default="/tmp/liverforce-experiment-indentation-strain")
    args = ap.parse_args()

    from liverforce.config import compose
    from liverforce.learn.metrics import metrics_by_group
    from liverforce.learn.model import ForceModel, eval_seed
    from liverforce.learn.torchutil import configure_torch
    from liverforce.learn.train import train_scenario
    from liverforce.pipeline.plan import Plan
    from liverforce.pipeline.shared import run_arrays

    configure_torch(1)
    cfg = compose([])
    plan = Plan(cfg)
    seed = plan.train_seed()
    train = {k: v for k, v in cfg["train"].items() if k != "variants"}
    train.update(interval=None, heldout_points=None)
    variants = plan.variants()
    results = Path(args.results)
    loaded: dict = {}

    def load(scenario: str, camera: bool) -> dict:
        if (scenario, camera) not in loaded:
            loaded[(scenario, camera)] = run_arrays(results, scenario, camera, "indentation-strain experiment")
        return loaded[(scenario, camera)]

    for name in args.variants:
        v = dict(variants[name])
        camera = v.get("roi_features") == "cloud"
        for scenario in args.scenarios:
            arrays = load(scenario, camera)
            for strain in (False, True):
                model_cfg = {**v, "indentation_strain": strain}
                t = time.perf_counter()
                res = train_scenario(arrays, model_cfg, train, cfg["tune"], scenario, name, seed=seed,
                                     out_dir=f"{args.out}/{name}-{scenario}-{int(strain)}")
                m, s = res["metrics_mean"], res["metrics_sd"]
                per_split = [r["metrics"]["accuracy_pct"] for r in res["repeats"]]  # the main split first
                line = (f"{name:8s} {scenario:3s} strain {'on ' if strain else 'off'} test {m['accuracy_pct']:6.2f} +- "
                        f"{s['accuracy_pct']:.2f} % (splits {' '.join(f'{a:.1f}' for a in per_split)}), "
                        f"MAE {m['mae_vec']:.4f} +- {s['mae_vec']:.4f} N")
                if scenario == "IV":
                    model = ForceModel.load(res["model_path"])
                    u = load("V", camera)
                    pred = model.predict(u, observation_seed=eval_seed(int(res["seed"])))
                    g = metrics_by_group(u["force_n"], pred, u["geometry_id"])
                    line += f" | unseen MAE {g['mean']['mae_vec']:.4f} +- {g['sd']['mae_vec']:.4f} N"
                print(f"{line} | {time.perf_counter() - t:.0f} s", flush=True)


if __name__ == "__main__":
    main()
