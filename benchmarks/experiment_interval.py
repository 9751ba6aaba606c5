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

With ``--widen`` (``proportional``, ``fitted``, ``none``) every scale is scored with each widening outside the
calibration's stiffness range (``train.interval.widen``,
:meth:`liverforce.learn.interval.ConformalInterval.extrapolation_factor`; ``none``: the same interval with its
``stiffness_range`` removed); ``--unwidened`` adds ``none``.

With ``--spread`` (betas; 0: none) every interval is also scored scaled by the GP ensemble members' spread
(``train.interval.spread``, :mod:`liverforce.learn.interval`): the calibration file holds the members' sd of each
calibration prediction (``spread_local``), so every beta is fitted on the same predictions.

With ``--train-stiffness LO HI`` the split model and its calibration see only the training livers' cases whose
stiffness factor (first constant over the mean) lies in ``[LO, HI]``; the test livers' cases outside it are
scored apart (``test outside``): a liver stiffer or softer than every calibration case, as the unseen livers
are, on the training side of the data (the widening can be chosen there without looking at the unseen livers).

The validate stage writes the same numbers for the validated model
(``validate/metrics.json`` ``interval``: ``coverage``, ``coverage_by_force``).

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python benchmarks/experiment_interval.py --results results/default \\
        --variant cloud_sv --scales force force_bins --bins 2 3 4 5 8
    ... --variant cloud_sv --scales force_bins --widen proportional fitted none --train-stiffness 0.8 1.2
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from liverforce.config import interval_scales, interval_widenings


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


def interval_form(cal: dict, cfg: dict, widen: str = "proportional") -> dict:
    """The interval of config ``cfg`` fitted on calibration predictions ``cal`` (scenario IV), as a model's
    ``meta["interval"]``, with widening ``widen`` outside the calibration's stiffness range (``train.interval.widen``:
    ``proportional`` or ``fitted``); ``none``: the same interval without any (its ``stiffness_range`` removed)."""
    from liverforce.learn.train import interval_from_calibration

    iv = interval_from_calibration(cal, {**cfg, "widen": "proportional" if widen == "none" else widen}, "IV")
    iv = iv.to_dict()
    return {**iv, "stiffness_range": None} if widen == "none" else iv


WIDEN_NAMES = {"proportional": "", "fitted": " widen fitted", "none": " unwidened"}  # suffix of a printed name


def interval_forms(fold_counts, scales, bins, widenings=("proportional",), spreads=(None,)) -> dict:
    """Every interval the experiment scores, ``(folds, scale, bins or None, widen, spread beta or None)`` -> its
    printed name: each scale once per fold count, ``force_bins`` once per number of bins, each with every widening
    of ``widenings`` (``proportional``, ``fitted``, ``none``: :func:`interval_form`) and every spread beta of
    ``spreads`` (None: not scaled by the members' spread)."""
    return {(k, s, b, w, p): (s if b is None else f"{s}:{b}") + f" {k} folds" + WIDEN_NAMES[w]
            + ("" if p is None else f" spread {p:g}")
            for k in fold_counts for s in scales for b in (bins if s == "force_bins" else [None])
            for w in widenings for p in spreads}


def stiffness_factors(arrays: dict) -> np.ndarray:
    """Each case's first material constant over the mean of the arrays' cases (the model's stiffness factor
    ``k``, up to the training split's mean instead of all cases')."""
    c1 = np.asarray(arrays["material_params_mpa"], dtype=np.float64)[:, 0]
    return c1 / c1.mean()


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
    ap.add_argument("--widen", nargs="+", default=None, choices=[*interval_widenings(), "none"],
                    help="widenings outside the stiffness range to score (default: the config's)")
    ap.add_argument("--spread", nargs="+", type=float, default=None,
                    help="spread betas to score (train.interval.spread; 0: none; default: the config's)")
    ap.add_argument("--train-stiffness", nargs=2, type=float, default=None, metavar=("LO", "HI"),
                    help="fit and calibrate the split model on the training livers' cases with stiffness factor "
                    "in [LO, HI] only, and also score the test livers' cases outside it (a training-side stand-in "
                    "for a liver stiffer or softer than every calibration case)")
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
    widenings = list(dict.fromkeys([*(args.widen or [str(base.get("widen", "proportional"))]),
                                    *(["none"] if args.unwidened else [])]))
    spreads = ([base.get("spread")] if args.spread is None
               else list(dict.fromkeys(None if p == 0 else float(p) for p in args.spread)))
    forms = interval_forms(fold_counts, args.scales, args.bins, widenings, spreads)
    parts = ["test", "unseen"]
    fit_arrays, outside_rows = arrays, None
    if args.train_stiffness is not None:
        lo, hi = args.train_stiffness
        k_case = stiffness_factors(arrays)
        inside = (k_case >= lo) & (k_case <= hi)
        if not inside.any() or inside.all():
            raise SystemExit(f"--train-stiffness {lo} {hi}: keeps {int(inside.sum())} of {len(inside)} cases")
        fit_arrays, outside_rows = subset(arrays, np.flatnonzero(inside)), ~inside
        parts = ["test", "test outside", "unseen"]
        print(f"training on the {int(inside.sum())} of {len(inside)} cases with k in [{lo}, {hi}]; the test "
              f"livers' cases outside it scored as 'test outside'", flush=True)
    got: dict = {f: {p: [] for p in parts} for f in forms}
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
        res = train_scenario(fit_arrays, model_cfg, train, run.cfg["tune"], "IV", args.variant, seed=seed,
                             out_dir=out, calibrate_folds=tuple(fold_counts[1:]))
        if res["interval"] is None:  # no calibration (its npz would be an earlier run's)
            raise SystemExit(f"split {r}: no calibrated interval ({'; '.join(res['split']['notes'])})")
        m = ForceModel.load(res["model_path"])
        in_test = np.isin(geo, res["split"]["test_geometries"])
        scored = {"test": subset(arrays, np.flatnonzero(in_test & (True if outside_rows is None else ~outside_rows))),
                  "unseen": unseen}
        if outside_rows is not None:
            scored["test outside"] = subset(arrays, np.flatnonzero(in_test & outside_rows))
        for i, k in enumerate(fold_counts):
            with np.load(f"{out}/interval_calibration{'' if i == 0 else f'_folds{k}'}.npz") as z:
                cal = {key: z[key] for key in z.files}
            if int(cal["folds"]) != k:
                raise SystemExit(f"split {r}: the calibration file holds {int(cal['folds'])} folds, not {k}")
            for f in (f for f in forms if f[0] == k):
                cfg = {**base, "folds": k, "scale": f[1], **({} if f[2] is None else {"bins": f[2]}), "spread": f[4]}
                if f[4] is not None and "spread_local" not in cal:
                    raise SystemExit(f"split {r}: no members' spread in the calibration (not a GP ensemble)")
                m.meta["interval"] = interval_form(cal, cfg, widen=f[3])
                for part, cases in scored.items():
                    if len(cases["case_id"]):  # (a split's test livers may have no case outside the range)
                        got[f][part].append(interval_coverage(m, cases))
        print(f"split {r + 1}/{args.splits} done ({time.perf_counter() - t:.0f} s)", flush=True)
    for f in forms:
        for part in parts:
            docs = got[f][part]
            print(f"{args.variant} scale {forms[f]:22s} {part:12s} ({len(docs)} splits): "
                  + (summary(docs) if docs else "no cases"))


if __name__ == "__main__":
    main()
