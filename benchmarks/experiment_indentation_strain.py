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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results/default")
    ap.add_argument("--variants", nargs="*", default=["pca_sv"])
    ap.add_argument("--scenarios", nargs="*", default=["IV"])
    ap.add_argument("--out", default="/tmp/liverforce-experiment-indentation-strain")
    args = ap.parse_args()

    from benchmarks.experiment import PipelineTraining

    run = PipelineTraining(args.results, "indentation-strain experiment")
    for name in args.variants:
        v = dict(run.variants[name])
        for scenario in args.scenarios:
            for strain in (False, True):
                print(run.score({**v, "indentation_strain": strain}, scenario, name,
                                f"strain {'on' if strain else 'off'}", f"{args.out}/{name}-{scenario}-{int(strain)}", 0),
                      flush=True)


if __name__ == "__main__":
    main()
