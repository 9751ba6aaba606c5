"""Experiment: would a width of its own for the cases the input-distance flag fires on restore the interval's coverage?

The interval of one width covers the unseen livers' flagged cases (``meta.input_distance``) in 72-78 % per component
against 91-95 % for the others (fresh clone f73). On a finished run's results, nothing refitted:

1. the calibration (``models/IV/<variant>/interval_calibration.npz``, cross-conformal by liver): each case's
   residual over the one width's half-width, per component (``s <= 1``: covered), and whether the case is far
   from its fold model's training rows (its distance above the calibration's own quantile at the flag's
   ``distance_quantile``, 90 %: the flag's rule in the fold models' space);
2. a Mondrian split of the calibration on that taxonomy: per component the split-conformal quantile of ``s`` among
   the far cases and among the others (:func:`liverforce.learn.interval.mondrian_factors`), the factors their
   half-widths are multiplied by (what ``train.interval.far_widths`` fits since session 62; a model trained with
   them is read without them first, and the factors found here are checked against its own);
3. on the unseen livers: the interval with one width, and the same with the far factor on the cases the served
   flag fires on and the near factor on the others; coverage overall, of the flagged cases and of the others, per
   liver (min and sd), and the mean half-widths.

Usage::

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python benchmarks/experiment_far_interval.py --results results/default

Measured on the fresh clone f73 of 6362e9e (session 62; these unseen figures were seen before any such width was
built): calibration, 120 far cases of 1,200, covered 67.5 / 74.2 / 71.7 % (t1 / t2 / n) against 93.0 / 92.2 /
92.5 % for the others; factors far 1.70 / 1.68 / 1.96, near 0.88 / 0.93 / 0.86. Unseen livers, shipped 94.2 /
90.4 / 92.1 % (flagged 77.8 / 77.8 / 72.2 %), half-widths 0.138 / 0.138 / 0.265 N; Mondrian 91.7 / 89.6 / 92.1 %
(flagged 88.9 / 83.3 / 94.4 %, the others 91.9 / 90.1 / 91.9 %), half-widths 0.139 / 0.145 / 0.271 N; the
lowest liver's coverage 73.3 / 76.7 / 76.7 % against 83.3 / 76.7 / 76.7 % shipped.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from liverforce.learn.interval import mondrian_factors


def main() -> None:
    from liverforce.learn.frames import force_to_local
    from liverforce.learn.interval import coverage_per_component
    from liverforce.learn.model import ForceModel
    from liverforce.pipeline.shared import camera_arrays

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results/default")
    ap.add_argument("--variant", default="cloud_sv")
    args = ap.parse_args()
    root = Path(args.results)
    d = root / "models" / "IV" / args.variant
    m = ForceModel.load(d / "model")
    shipped, rec = m.interval, m.distance_flag
    ci = dataclasses.replace(shipped, far_threshold=None, far_factor=None, near_factor=None) if shipped else None
    if ci is None or rec is None or "fold_quantiles" not in rec:
        raise SystemExit(f"{d}: the model needs an interval and the input-distance flag with the fold quantiles "
                         "(train.interval.distance_quantile, session 62 and later)")
    with np.load(d / "interval_calibration.npz") as z:
        cal = {k: z[k] for k in z.files}
    half = ci.half_widths(cal["stiffness"], cal["pred_local"], cal.get("spread_local"))
    s = np.abs(cal["true_local"] - cal["pred_local"]) / half
    far_cal = cal["input_distance"] > np.nanquantile(cal["input_distance"], rec["quantile"])
    pct = lambda v: " / ".join(f"{100 * x:.1f}" for x in v)  # noqa: E731
    print(f"calibration: {int(far_cal.sum())} far cases of {len(far_cal)}, covered {pct((s[far_cal] <= 1).mean(0))} % "
          f"(t1 / t2 / n) against {pct((s[~far_cal] <= 1).mean(0))} % for the others")
    far_k, near_k = mondrian_factors(s, far_cal, ci.coverage)
    print("factors: far " + " / ".join(f"{v:.2f}" for v in far_k) + ", near " + " / ".join(f"{v:.2f}" for v in near_k)
          + ("" if not shipped.uses_distance else "; the model's own: far " + " / ".join(
              f"{v:.2f}" for v in shipped.far_factor) + ", near "
              + " / ".join(f"{v:.2f}" for v in shipped.near_factor)))
    meshes = sorted(str(p) for p in (root / "mesh").glob("*.vtu"))
    a = camera_arrays(root / "shards" / "V" / "manifest.json", meshes, "the unseen livers")
    fw = m.forward(a, int(m.meta.get("eval_observation_seed", 0)))
    true = force_to_local(np.asarray(a["force_n"], float), fw.R)
    pred = fw.force_local
    h = ci.half_widths(fw.stiffness, pred, fw.spread_local)
    f = fw.input_distance > rec["threshold"]
    h2 = h * near_k
    h2[f] = h[f] * far_k
    geo = np.asarray(a["geometry_id"]).astype(str)
    for name, hh in (("one width", h), ("Mondrian on the flag", h2)):
        per = np.array([coverage_per_component(true[geo == g], pred[geo == g], hh[geo == g]) for g in sorted(set(geo))])
        print(f"{name}: unseen {pct(coverage_per_component(true, pred, hh))} %; flagged ({int(f.sum())}) "
              f"{pct(coverage_per_component(true[f], pred[f], hh[f]))} %, the others "
              f"{pct(coverage_per_component(true[~f], pred[~f], hh[~f]))} %; lowest liver {pct(per.min(0))} %, sd over "
              f"livers {pct(per.std(0, ddof=1))} points; mean half-widths "
              + " / ".join(f"{v:.3f}" for v in hh.mean(0)) + " N")


if __name__ == "__main__":
    main()
