"""Experiment: how the unseen-liver error falls with the number of training livers (a learning curve).

On a finished run's shards (``--results``), scenario IV's livers are cut to ``--livers`` of them (a seeded subset per
replicate; with all of the run's livers the replicates differ by their split only). Each subset is trained as the
pipeline trains it (:func:`liverforce.learn.train.train_scenario`: its split by liver, ``train.test_fraction`` of the
livers held out, the GP's 4-fold CV by liver), one split per replicate, and the split's model scores the run's unseen
livers (scenario V, the validation's 8 livers at constants x``validate.material_scale``). ``train.final_fit`` is off
here: the model is fitted on the subset's training livers, as in session 34's figures (the pipeline's saved model now
sees all of a run's livers). Printed per variant, number of livers and cases per liver: the unseen MAE (mean +- sd
over the replicates of the mean over the unseen livers, and each replicate's) and the training-side CV MAE (mean over
the replicates).

The subsets are drawn independently for each number of livers (not nested, unlike the ``train_livers`` study's
:func:`liverforce.learn.study.first_geometries`), so that ``--cases-per-liver`` can draw cases from the same
generator; the figures in docs/experiments.md (session 34) were measured with this draw.

The unseen livers are the same for every point of the curve, so the curve says whether more simulated livers would
still lower the error a new liver sees, for the camera model and the node model alike::

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python benchmarks/experiment_train_livers.py --results results/default \\
        --variants pca_sv cloud_sv --livers 8 14 20 --cases-per-liver 0 30 --replicates 3

(``--cases-per-liver 30``: the same number of cases from each kept liver, to tell livers from cases.)
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def liver_subset(geo: np.ndarray, n: int, per: int, rng: np.random.Generator) -> np.ndarray:
    """Sorted rows of ``n`` livers drawn from ``geo`` (one geometry id per case), all of their cases or ``per`` of
    each (all of a liver with fewer)."""
    livers = np.array(sorted(set(geo)))
    keep = np.sort(rng.choice(livers, n, replace=False))
    rows = np.flatnonzero(np.isin(geo, keep))
    if per > 0:
        own = [rows[geo[rows] == g] for g in keep]
        rows = np.sort(np.concatenate([rng.choice(o, min(per, len(o)), replace=False) for o in own]))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results/default")
    ap.add_argument("--variants", nargs="+", default=["pca_sv", "cloud_sv"])
    ap.add_argument("--livers", type=int, nargs="+", default=[8, 12, 16, 20], help="IV livers per subset")
    ap.add_argument("--cases-per-liver", type=int, nargs="+", default=[0],
                    help="cases kept per liver (a seeded subset; 0: all of them)")
    ap.add_argument("--replicates", type=int, default=3, help="seeded subsets (and splits) per number of livers")
    ap.add_argument("--out", default="/tmp/liverforce-experiment-train-livers")
    args = ap.parse_args()

    from liverforce.learn.model import subset
    from liverforce.learn.train import train_scenario
    from liverforce.seeds import derive

    from benchmarks.experiment import PipelineTraining

    run = PipelineTraining(args.results, "train-livers experiment")
    train = {**run.train, "repeats": 1, "final_fit": False}  # the split's model: n x (1 - test_fraction) livers
    for name in args.variants:
        cfg = dict(run.variants[name])
        camera = cfg.get("roi_features") == "cloud"
        arrays = run.arrays("IV", camera)
        geo = np.asarray(arrays["geometry_id"]).astype(str)
        livers = np.array(sorted(set(geo)))
        for n, per in [(n, c) for n in args.livers for c in args.cases_per_liver]:
            if not 3 <= n <= len(livers):
                raise SystemExit(f"--livers {n}: the run has {len(livers)} IV livers (at least 3 are needed)")
            unseen, cv = [], []
            t = time.perf_counter()
            for r in range(args.replicates):
                rng = np.random.default_rng(derive(run.seed, "experiment.train_livers", n, r))
                rows = liver_subset(geo, n, per, rng)
                seed = run.seed if r == 0 else derive(run.seed, "split.repeat", r)
                res = train_scenario(subset(arrays, rows), cfg, train, run.cfg["tune"], "IV", name, seed=seed,
                                     out_dir=f"{args.out}/{name}-{n}-{per}-{r}")
                g = run.unseen(res, camera)
                unseen.append(g["mean"]["mae_vec"])
                cv.append(res["cv_mae_n"])
            cases = f"{per} cases each" if per > 0 else "all cases"
            sd = np.std(unseen, ddof=1) if len(unseen) > 1 else 0.0
            print(f"{name:8s} {n:3d} livers, {cases:14s} | unseen MAE {np.mean(unseen):.4f} +- {sd:.4f} N "
                  f"({' '.join(f'{u:.4f}' for u in unseen)}) | CV MAE {np.mean(cv):.4f} N | "
                  f"{time.perf_counter() - t:.0f} s", flush=True)


if __name__ == "__main__":
    main()
