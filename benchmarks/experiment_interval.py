"""Experiment: the calibrated interval's coverage with each scale, on the IV test livers and the unseen livers.

Retrains the scenario-IV model of one variant on a finished run's shards once
per seeded split (``--splits``: the main split, then the repeats' split seeds,
as :meth:`benchmarks.experiment.PipelineTraining.score` uses them), with the
default config's training settings (cross-conformal calibration on the
training livers only). Every scale (``--scales``; ``force_bins`` once per
``--bins``) is then fitted on the same calibration predictions
(``interval_calibration.npz`` next to the model,
:func:`liverforce.learn.train.interval_from_calibration`): the scales share
the model and differ only in their interval. Prints, per scale, mean +- sd
over the splits of:

- the coverage per local component (t1, t2, n) on the split's IV test livers
  and on the unseen livers of scenario V, and the mean half-widths;
- the coverage per quintile of the true |F| (mean over the splits), the worst
  quintile-component of each split (mean), and the spread: the range over
  the quintiles of each component's coverage, mean over the components and
  splits. Whether the interval holds for the small forces as for the large.

With ``--folds`` (several fold counts) the split's model, fitted once, is
calibrated once per fold count (cross-conformal, ``train.interval.folds``;
``train_scenario(..., calibrate_folds=...)``): the same model, each fold
model fitted on fewer or more of the training livers.

With ``--unwidened`` every scale is also scored without the widening outside
the calibration's stiffness range (:meth:`liverforce.learn.interval.ConformalInterval.extrapolation_factor`;
the same interval with its ``stiffness_range`` removed): how much of a coverage
the widening makes.

The validate stage writes the same numbers for the validated model
(``validate/metrics.json`` ``interval``: ``coverage``, ``coverage_by_force``).

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python benchmarks/experiment_interval.py --results results/default \\
        --variant cloud_sv --scales force force_bins --bins 2 3 4 5 8
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from liverforce.config import interval_scales


def summary(docs: list[dict]) -> str:
    """One line of :func:`liverforce.pipeline.validate.interval_coverage` results over splits."""
    cov = 100 * np.array([d["coverage"] for d in docs])
    half = np.array([d["half_width_mean_n"] for d in docs], dtype=float)
    if any(len(d["coverage_by_force"]) != 5 for d in docs):  # an empty quintile (tied or very few cases)
        raise SystemExit("a split has fewer than 5 force quintiles with cases: too few cases to bin")
    bins = 100 * np.array([[b["coverage"] for b in d["coverage_by_force"]] for d in docs])  # (splits, 5, 3)
    sd = cov.std(axis=0, ddof=1) if len(docs) > 1 else np.zeros(3)
    per_bin = " | ".join(f"{ax} " + " ".join(f"{v:.0f}" for v in bins.mean(axis=0)[:, j])
                         for j, ax in enumerate(("t1", "t2", "n")))
    spread = (bins.max(axis=1) - bins.min(axis=1)).mean()
    return (f"coverage {' / '.join(f'{m:.1f} +- {s:.1f}' for m, s in zip(cov.mean(axis=0), sd))} %, "
            f"half-widths {' / '.join(f'{h:.3f}' for h in half.mean(axis=0))} N; per |F| quintile {per_bin} %; "
            f"worst quintile {bins.min(axis=(1, 2)).mean():.1f} %; spread over the quintiles {spread:.1f} points")


def interval_form(cal: dict, cfg: dict, widened: bool = True) -> dict:
    """The interval of config ``cfg`` fitted on calibration predictions ``cal`` (scenario IV), as a model's
    ``meta["interval"]``; ``widened`` False: the same interval without the widening outside the calibration's
    stiffness range (its ``stiffness_range`` removed)."""
    from liverforce.learn.train import interval_from_calibration

    iv = interval_from_calibration(cal, cfg, "IV").to_dict()
    return iv if widened else {**iv, "stiffness_range": None}


def interval_forms(fold_counts, scales, bins, unwidened: bool) -> dict:
    """Every interval the experiment scores, ``(folds, scale, bins or None, widened)`` -> its printed name: each
    scale once per fold count, ``force_bins`` once per number of bins, and with ``unwidened`` each also without
    the widening outside the stiffness range."""
    return {(k, s, b, w): (s if b is None else f"{s}:{b}") + f" {k} folds" + ("" if w else " unwidened")
            for k in fold_counts for s in scales for b in (bins if s == "force_bins" else [None])
            for w in ((True, False) if unwidened else (True,))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results/default")
    ap.add_argument("--variant", default="cloud_sv")
    ap.add_argument("--scales", nargs="+", default=["force", "force_bins"], choices=interval_scales())
    ap.add_argument("--bins", nargs="+", type=int, default=[5], help="bins for scale force_bins (one row each)")
    ap.add_argument("--splits", type=int, default=5)
    ap.add_argument("--folds", nargs="+", type=int, default=None,
                    help="cross-conformal folds (one calibration each, on the same split model; default: the config's)")
    ap.add_argument("--out", default="/tmp/liverforce-interval-experiment")
    ap.add_argument("--unwidened", action="store_true", help="also each scale without the widening outside the "
                    "calibration's stiffness range (the same interval, its stiffness_range removed)")
    args = ap.parse_args()

    from liverforce.learn.model import ForceModel, subset
    from liverforce.learn.train import train_scenario
    from liverforce.pipeline.validate import interval_coverage
    from liverforce.seeds import derive

    from benchmarks.experiment import PipelineTraining

    run = PipelineTraining(args.results, "interval experiment")
    model_cfg = dict(run.variants[args.variant])
    camera = model_cfg.get("roi_features") == "cloud"
    arrays, unseen = run.arrays("IV", camera), run.arrays("V", camera)
    geo = np.asarray(arrays["geometry_id"]).astype(str)
    base = run.cfg["train"]["interval"]
    fold_counts = args.folds or [int(base["folds"])]
    forms = interval_forms(fold_counts, args.scales, args.bins, args.unwidened)
    got: dict = {f: {"test": [], "unseen": []} for f in forms}
    t = time.perf_counter()
    for r in range(args.splits):
        seed = run.seed if r == 0 else derive(run.seed, "split.repeat", r)
        # final_fit off: the split's own model, so that its test livers are held out (the pipeline then refits the
        # configuration on every liver and calibrates that model's interval the same way)
        # one split model; its calibration with the first fold count, and again with each other fold count
        # (train_scenario's calibrate_folds: the same model's settings, each fold model fitted on more or fewer
        # of the training livers)
        train = {**run.train, "repeats": 1, "interval": {**base, "folds": fold_counts[0]}, "final_fit": False}
        out = f"{args.out}/{args.variant}-{r}"
        res = train_scenario(arrays, model_cfg, train, run.cfg["tune"], "IV", args.variant, seed=seed,
                             out_dir=out, calibrate_folds=tuple(fold_counts[1:]))
        if res["interval"] is None:  # no calibration (its npz would be an earlier run's)
            raise SystemExit(f"split {r}: no calibrated interval ({'; '.join(res['split']['notes'])})")
        m = ForceModel.load(res["model_path"])
        test = subset(arrays, np.flatnonzero(np.isin(geo, res["split"]["test_geometries"])))
        for i, k in enumerate(fold_counts):
            with np.load(f"{out}/interval_calibration{'' if i == 0 else f'_folds{k}'}.npz") as z:
                cal = {key: z[key] for key in z.files}
            if int(cal["folds"]) != k:
                raise SystemExit(f"split {r}: the calibration file holds {int(cal['folds'])} folds, not {k}")
            for f in (f for f in forms if f[0] == k):
                cfg = {**base, "folds": k, "scale": f[1], **({} if f[2] is None else {"bins": f[2]})}
                m.meta["interval"] = interval_form(cal, cfg, widened=f[3])
                got[f]["test"].append(interval_coverage(m, test))
                got[f]["unseen"].append(interval_coverage(m, unseen))
        print(f"split {r + 1}/{args.splits} done ({time.perf_counter() - t:.0f} s)", flush=True)
    for f in forms:
        for part in ("test", "unseen"):
            print(f"{args.variant} scale {forms[f]:22s} {part:6s} ({args.splits} splits): {summary(got[f][part])}")


if __name__ == "__main__":
    main()
