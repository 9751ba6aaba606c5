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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results/default")
    ap.add_argument("--variants", nargs="*", default=["pca_sv"])
    ap.add_argument("--scenarios", nargs="*", default=["IV"])
    ap.add_argument("--out", default="/tmp/liverforce-experiment-indentation-strain")
    args = ap.parse_args()

    from liverforce.learn.train import train_scenario

    from benchmarks.experiment import PipelineTraining

    run = PipelineTraining(args.results, "indentation-strain experiment")
    for name in args.variants:
        v = dict(run.variants[name])
        camera = v.get("roi_features") == "cloud"
        for scenario in args.scenarios:
            arrays = run.arrays(scenario, camera)
            for strain in (False, True):
                model_cfg = {**v, "indentation_strain": strain}
                t = time.perf_counter()
                res = train_scenario(arrays, model_cfg, run.train, run.cfg["tune"], scenario, name, seed=run.seed,
                                     out_dir=f"{args.out}/{name}-{scenario}-{int(strain)}")
                m, s = res["metrics_mean"], res["metrics_sd"]
                per_split = [r["metrics"]["accuracy_pct"] for r in res["repeats"]]  # the main split first
                line = (f"{name:8s} {scenario:3s} strain {'on ' if strain else 'off'} test {m['accuracy_pct']:6.2f} +- "
                        f"{s['accuracy_pct']:.2f} % (splits {' '.join(f'{a:.1f}' for a in per_split)}), "
                        f"MAE {m['mae_vec']:.4f} +- {s['mae_vec']:.4f} N")
                if scenario == "IV":
                    g = run.unseen(res, camera)
                    line += f" | unseen MAE {g['mean']['mae_vec']:.4f} +- {g['sd']['mae_vec']:.4f} N"
                print(f"{line} | {time.perf_counter() - t:.0f} s", flush=True)


if __name__ == "__main__":
    main()
