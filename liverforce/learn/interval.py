"""Calibrated intervals per force component: split conformal prediction on a training-side split.

Every prediction of a model comes with an interval for each local force
component ``(F.t1, F.t2, F.n)`` (the local frame at the exertion point,
:mod:`liverforce.learn.frames`): the tangential and the normal force, the
components a surgeon-engineer reads.

Calibration (split conformal, Vovk et al. 2005; Lei et al. 2018): the training
split is split again, by liver where the test split is by liver (scenario IV).
A model with the main model's settings and hyper-parameters is fitted on the
larger part and predicts the calibration part (with the evaluation's
observation model). With ``folds > 1`` (cross-conformal, Vovk 2015; the
calibration of Barber et al. 2021's CV+ with the main model's prediction) the
training split is cut into ``folds`` parts (by liver in IV) and every part is
predicted by a model fitted on the others: every training case calibrates
once, so the quantile rests on all training livers rather than a few (its
guarantee weakens to about ``1 - 2 (1 - c)`` in the worst case; in practice
it stays near ``c``). The scores are the absolute residuals, optionally divided
by the stiffness factor ``k`` of each case (``scale: stiffness``;
:meth:`liverforce.learn.model.Preprocessor.material_factor`, ``C10 / C10_ref``):

    s_ij = |f_ij - f^_ij| / k_i,      q_j = s_(ceil((n + 1) c)) of component j,
    interval_ij = f^_ij +- k_i q_j                (k_i = 1 with scale: none)

``scale: none`` is the default: the sweep draws forces from the same range for
every material, so the error in newtons does not grow with the stiffness, and
scaling the interval by ``k`` over-covers stiffer livers. Measured on the
7d265e6 run's shards (pca_sv, scenario IV, 3 splits, 4-fold calibration), on
the 8 unseen livers with constants x1.4, per component: 94-99 % for a 90 %
interval with ``stiffness``, 87.5-93.3 % with ``none``.

For ``n`` calibration cases exchangeable with a new case, the interval covers
the new case's component with probability at least ``c`` (and below
``c + 1/(n+1)``). A new liver is exchangeable with calibration livers only
if it comes from the same population: the validation on unseen livers
(constants outside the training range) measures the coverage actually
reached.

Outside the calibration's stiffness range (``scale: none``): inside the range
the calibration residuals do not grow with the stiffness factor (fitted
exponent of |r| ~ k^g per component: -0.02 to 0.10 on the 7423f34 run's
camera model), but beyond it the model extrapolates. The half-widths are then
widened by how far the case lies outside the calibration cases' range
``[k_lo, k_hi]``::

    half_ij = q_j * max(1, k_i / k_hi, k_lo / k_i)

(the error a displacement error makes in newtons grows with the stiffness;
the same factor is kept for a softer liver, a conservative choice). Inside
the range this changes nothing. Measured on that run's camera model
(cloud_sv, unseen livers at constants x1.4, k = 1.4 against k_hi = 1.3):
coverage per component 91.7 / 87.1 / 85.0 % unwidened, 93.3 / 90.0 / 89.2 %
widened; the IV test livers (inside the range) are unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ConformalInterval:
    """Half-widths ``q`` (3,) N per local component (before the stiffness factor) at nominal ``coverage``."""

    coverage: float
    half_width_n: tuple[float, float, float]
    n_calibration: int
    grouping: str  # what the calibration split held out: "geometry" (livers) or "case"
    scale: str = "stiffness"  # "stiffness": half-widths x the case's stiffness factor; "none": fixed
    folds: int = 1  # 1: one calibration split; > 1: cross-conformal over the whole training split
    stiffness_range: tuple[float, float] | None = None  # calibration cases' stiffness factors (scale: none)

    def half_widths(self, stiffness: np.ndarray) -> np.ndarray:
        """Half-widths ``(n, 3)`` N for rows with stiffness factors ``(n, 1)``: times ``k`` with ``scale:
        stiffness``; with ``scale: none`` fixed inside the calibration's stiffness range, widened outside it
        (module docstring)."""
        k = np.asarray(stiffness, dtype=np.float64).reshape(-1, 1)
        if self.scale == "none":
            k = self.extrapolation_factor(k)
        return k * np.asarray(self.half_width_n)[None, :]

    def extrapolation_factor(self, stiffness: np.ndarray) -> np.ndarray:
        """``max(1, k / k_hi, k_lo / k)`` per row (ones without a recorded range)."""
        k = np.asarray(stiffness, dtype=np.float64)
        if self.stiffness_range is None:
            return np.ones_like(k)
        lo, hi = self.stiffness_range
        return np.maximum(1.0, np.maximum(k / hi, lo / np.maximum(k, 1e-300)))

    @property
    def bounded(self) -> bool:
        """False when there were too few calibration cases (:func:`min_calibration_cases`): infinite width."""
        return all(math.isfinite(v) for v in self.half_width_n)

    def to_dict(self) -> dict:
        """JSON-ready; an unbounded half-width is written as null."""
        return {"coverage": float(self.coverage),
                "half_width_n": [float(v) if math.isfinite(v) else None for v in self.half_width_n],
                "n_calibration": int(self.n_calibration), "grouping": self.grouping, "scale": self.scale,
                "folds": int(self.folds),
                "stiffness_range": None if self.stiffness_range is None else [float(v) for v in self.stiffness_range]}

    @classmethod
    def from_dict(cls, d: dict) -> "ConformalInterval":
        rng = d.get("stiffness_range")
        return cls(float(d["coverage"]), tuple(math.inf if v is None else float(v) for v in d["half_width_n"]),
                   int(d["n_calibration"]), str(d["grouping"]), str(d.get("scale", "stiffness")),
                   int(d.get("folds", 1)), None if rng is None else (float(rng[0]), float(rng[1])))


def fit_conformal(true_local: np.ndarray, pred_local: np.ndarray, stiffness: np.ndarray, coverage: float,
                  grouping: str, scale: str = "stiffness", folds: int = 1) -> ConformalInterval:
    """The split-conformal quantile per component (module docstring) from calibration predictions."""
    if not 0.0 < coverage < 1.0:
        raise ValueError(f"interval coverage must be in (0, 1), got {coverage}")
    if scale not in ("stiffness", "none"):
        raise ValueError(f"interval scale must be 'stiffness' or 'none', got {scale!r}")
    k_rows = np.asarray(stiffness, float).reshape(-1, 1)
    k = k_rows if scale == "stiffness" else 1.0
    s = np.abs(np.asarray(true_local, float) - np.asarray(pred_local, float)) / k
    n = len(s)
    rng = (float(k_rows.min()), float(k_rows.max())) if scale == "none" and k_rows.size else None
    rank = _rank(n, coverage)
    if rank > n:  # too few cases for this coverage: the honest split-conformal interval is unbounded
        return ConformalInterval(float(coverage), (math.inf,) * 3, int(n), grouping, scale, int(folds), rng)
    q = np.sort(s, axis=0)[rank - 1]
    return ConformalInterval(float(coverage), tuple(float(v) for v in q), int(n), grouping, scale, int(folds), rng)


def _rank(n: int, coverage: float) -> int:
    """``ceil((n + 1) c)``, robust to round-off in ``(n + 1) c`` (10 x 0.9 is 9.000000000000002 in floats)."""
    return math.ceil((n + 1) * coverage - 1e-9)


def min_calibration_cases(coverage: float) -> int:
    """The fewest calibration cases that bound a ``coverage`` interval: ``ceil((n + 1) c) <= n``."""
    n = 1
    while _rank(n, coverage) > n:
        n += 1
    return n


def coverage_per_component(true_local: np.ndarray, pred_local: np.ndarray, half: np.ndarray) -> list[float]:
    """Fraction of rows whose true component lies in ``pred +- half``, per local component."""
    inside = np.abs(np.asarray(true_local, float) - np.asarray(pred_local, float)) <= np.asarray(half, float)
    return [float(v) for v in inside.mean(axis=0)]
