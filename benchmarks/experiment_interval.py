"""Experiment: the calibrated interval's coverage with each scale, on the IV test livers and the unseen livers.

Retrains the scenario-IV model of one variant on a finished run's shards, once
per ``train.interval.scale`` (``--scales``) on each of ``--splits`` seeded
splits (the main split, then the repeats' split seeds, as
:meth:`benchmarks.experiment.PipelineTraining.score` uses them), with the
default config's training settings otherwise (cross-conformal calibration on
the training livers only). The fits are seeded, so the scales get the same
models and differ only in their interval; each scale still trains its own (the
model and its 4 calibration fits per split and scale). Prints, per scale,
mean +- sd over the splits of:

- the coverage per local component (t1, t2, n) on the split's IV test livers
  and on the unseen livers of scenario V, and the mean half-widths;
- the coverage per quintile of the true |F| (mean over the splits), and the
  worst quintile-component of each split (mean): whether the interval holds
  for the large forces as well as for the small ones.

The validate stage writes the same numbers for the validated model
(``validate/metrics.json`` ``interval``: ``coverage``, ``coverage_by_force``).

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python benchmarks/experiment_interval.py --results results/default \\
        --variant cloud_sv --scales none force
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from liverforce.config import interval_scales


def summary(docs: list[dict]) -> str:
    """One line of :func:`liverforce.pipeline.validate.interval_on_unseen` results over splits."""
    cov = 100 * np.array([d["coverage"] for d in docs])
    half = np.array([d["half_width_mean_n"] for d in docs], dtype=float)
    if any(len(d["coverage_by_force"]) != 5 for d in docs):  # an empty quintile (tied or very few cases)
        raise SystemExit("a split has fewer than 5 force quintiles with cases: too few cases to bin")
    bins = 100 * np.array([[b["coverage"] for b in d["coverage_by_force"]] for d in docs])  # (splits, 5, 3)
    sd = cov.std(axis=0, ddof=1) if len(docs) > 1 else np.zeros(3)
    per_bin = " | ".join(f"{ax} " + " ".join(f"{v:.0f}" for v in bins.mean(axis=0)[:, j])
                         for j, ax in enumerate(("t1", "t2", "n")))
    return (f"coverage {' / '.join(f'{m:.1f} +- {s:.1f}' for m, s in zip(cov.mean(axis=0), sd))} %, "
            f"half-widths {' / '.join(f'{h:.3f}' for h in half.mean(axis=0))} N; per |F| quintile {per_bin} %; "
            f"worst quintile {bins.min(axis=(1, 2)).mean():.1f} %")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results/default")
    ap.add_argument("--variant", default="cloud_sv")
    ap.add_argument("--scales", nargs="+", default=["none", "force"], choices=interval_scales())
    ap.add_argument("--splits", type=int, default=5)
    ap.add_argument("--out", default="/tmp/liverforce-interval-experiment")
    args = ap.parse_args()

    from liverforce.learn.model import subset
    from liverforce.learn.train import train_scenario
    from liverforce.pipeline.validate import interval_on_unseen
    from liverforce.seeds import derive

    from benchmarks.experiment import PipelineTraining

    run = PipelineTraining(args.results, "interval experiment")
    model_cfg = dict(run.variants[args.variant])
    camera = model_cfg.get("roi_features") == "cloud"
    arrays, unseen = run.arrays("IV", camera), run.arrays("V", camera)
    geo = np.asarray(arrays["geometry_id"]).astype(str)
    got: dict = {s: {"test": [], "unseen": []} for s in args.scales}
    t = time.perf_counter()
    for r in range(args.splits):
        seed = run.seed if r == 0 else derive(run.seed, "split.repeat", r)
        for s in args.scales:
            train = {**run.train, "repeats": 1, "interval": {**run.cfg["train"]["interval"], "scale": s}}
            res = train_scenario(arrays, model_cfg, train, run.cfg["tune"], "IV", args.variant, seed=seed,
                                 out_dir=f"{args.out}/{args.variant}-{s}-{r}")
            test = subset(arrays, np.flatnonzero(np.isin(geo, res["split"]["test_geometries"])))
            got[s]["test"].append(interval_on_unseen(res["model_path"], test))
            got[s]["unseen"].append(interval_on_unseen(res["model_path"], unseen))
        print(f"split {r + 1}/{args.splits} done ({time.perf_counter() - t:.0f} s)", flush=True)
    for s in args.scales:
        for part in ("test", "unseen"):
            print(f"{args.variant} scale {s:9s} {part:6s} ({args.splits} splits): {summary(got[s][part])}")


if __name__ == "__main__":
    main()
