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

``scale: stiffness`` is not the default: the sweep draws forces from the same
range for every material, so the error in newtons does not grow with the
stiffness, and scaling the interval by ``k`` over-covers stiffer livers. Measured on the
7d265e6 run's shards (pca_sv, scenario IV, 3 splits, 4-fold calibration), on
the 8 unseen livers with constants x1.4, per component: 94-99 % for a 90 %
interval with ``stiffness``, 87.5-93.3 % with ``none``.

For ``n`` calibration cases exchangeable with a new case, the interval covers
the new case's component with probability at least ``c`` (and below
``c + 1/(n+1)``). A new liver is exchangeable with calibration livers only
if it comes from the same population: the validation on unseen livers
(constants outside the training range) measures the coverage actually
reached.

Outside the calibration's stiffness range (``scale: none``, ``force`` and ``force_bins``) the model
extrapolates. Two rules widen the half-widths there (``widen``; the config's ``train.interval.widen``):

- ``proportional`` (the only rule until session 41): by how far the case lies outside the calibration cases'
  range ``[k_lo, k_hi]``, as if the error in newtons grew in proportion to the stiffness (the error a
  displacement error makes does), the same factor for a softer liver, a conservative choice::

      half_ij = q_j * max(1, k_i / k_hi, k_lo / k_i)

- ``fitted`` (the default since session 41): as the calibration residuals themselves grow with the stiffness.
  :func:`stiffness_exponent_fit` cuts the calibration cases into 5 bins of ``k`` and fits
  ``q_c(s_j) ~ k^g_j`` per component (the slope of ``log q_c`` on ``log k`` over the bins), ``s`` the residuals
  over what the widths already scale them by (``sigma_j`` with ``scale: force``, the bin's width with
  ``force_bins``: a growth with ``k`` that comes with larger forces is not counted twice). The widths grow
  where the scores grow, never narrow; where nothing can be fitted (one material, fewer than two bins of
  cases) the proportional rule holds::

      half_ij = q_j * max(1, k_i / k_hi)^clip(g_j, 0, 1) * max(1, k_lo / k_i)^clip(-g_j, 0, 1)

  The widening starts from the pooled quantile ``q_j`` (that of a mid-range ``k``), so for a component whose
  error does grow as ``k`` both rules under-cover a much stiffer liver alike (a test shows it).

Inside the range neither changes anything. Measured on the 7423f34 run's camera model (cloud_sv, unseen
livers at constants x1.4, k = 1.4 against k_hi = 1.3): residuals growing little inside the range (exponents
-0.02 to 0.10), coverage per component 91.7 / 87.1 / 85.0 % unwidened, 93.3 / 90.0 / 89.2 % proportional.
The camera model of the a6136ee clone's shards (``benchmarks/experiment_interval.py --scales force_bins
--widen proportional fitted none``, IV, 5 splits): its calibration scores shrink with ``k`` more often than
they grow (``g`` -0.87 to 0.14 per component and split), so ``fitted`` widens the unseen livers by 1 % at
most. On the training side (``--train-stiffness 0.8 1.2``: each split model fitted and calibrated on the
cases with ``k`` in [0.8, 1.2], the test livers' cases outside scored, a liver outside every calibration case
without the validation's livers) the coverage was 91.7 / 91.7 / 89.4 % fitted, 92.7 / 92.2 / 89.7 %
proportional, 91.0 / 91.0 / 88.7 % unwidened (sd over the splits 2-6 points: a weak preference); on the unseen
livers 91.6 / 91.1 / 92.2 % fitted against 93.0 / 92.2 / 93.6 % proportional (the unseen figures were seen
before the default was changed, so they do not check the choice independently). The exponents rest on 5
quantiles of about 200 cases each and carry sampling noise that was not measured here.

Scaled by the predicted force (``scale: force``, the default until session 28; locally weighted
conformal, Lei et al. 2018 section 5.2): the error in newtons grows with the
force, so a fixed half-width over-covers small forces and under-covers the
large ones a surgeon most needs bounded. The score divides each residual by a
per-component scale that is linear in the predicted magnitude ``|f^_i|``
(frame-free)::

    sigma_j(f) = a_j + b_j |f|,        s_ij = |f_ij - f^_ij| / sigma_j(f^_i)
    interval_ij = f^_ij +- sigma_j(f^_i) q_j x  max(1, k_i / k_hi, k_lo / k_i)

``(a_j, b_j)`` is the least-squares fit of ``|r_ij|`` on ``[1, |f^_i|]`` over
the same calibration residuals (``b_j >= 0``; ``a_j`` at least a tenth of the
mean ``|r_j|``, so the scale never vanishes): two numbers per component fitted
on hundreds of cases, which loosens the exchangeability argument a little (the
validation measures the coverage reached). Outside the calibration's stiffness
range the widths widen as with ``scale: none``.

Measured with ``benchmarks/experiment_interval.py`` on the ac86fa2 run's shards
(IV, 5 seeded splits; coverage per quintile of the true |F|, t1 / t2 / n, mean
over the splits). The camera model (cloud_sv), fixed widths (``none``): on the
IV test livers 99 / 99 / 99 % in the smallest quintile and 77 / 79 / 83 % in the
largest (4-5 N), on the unseen livers 100 / 100 / 100 and 79 / 78 / 87 %;
``force``: 94 / 87 / 89 and 89 / 91 / 90 % (test), 85 / 82 / 95 and 95 / 90 /
94 % (unseen), with mean half-widths 4-8 % narrower. The unseen livers' small
forces under-cover in t1 and t2 with every scale tried on the same
calibration residuals (an ad-hoc comparison, not in the repository), binned
(Mondrian) conformal over quintiles of ``|f^|`` included (85 / 85 / 96 %):
their relative error is larger than the training livers'. (That was the
ac86fa2 model; on the 08f70c9 model the line under-covers them more, and
the bins below do better.) A square-root or
quadrature scale did no better on the test livers (largest departure of a
quintile from 90 %: 5.6 and 6.7 points against the linear scale's 4.4).

A fixed width per bin of the predicted force (``scale: force_bins``, the default
since session 29; Mondrian conformal, Vovk et al. 2005 section 4.5, with the
bins a function of the prediction only): the calibration cases are cut into
``bins`` bins at the quantiles of their predicted ``|f^|``, and each bin gets
its own split-conformal quantile per component::

    q_bj = s_(ceil((n_b + 1) c)) of |f_ij - f^_ij| over the n_b cases of bin b
    interval_ij = f^_ij +- q_b(i)j x max(1, k_i / k_hi, k_lo / k_i)

with ``b(i)`` the bin of the case's own predicted ``|f^_i|``. For cases
exchangeable with the calibration cases the coverage then holds within each
bin, not only on average (approximately: the edges come from the same
calibration predictions, and cross-conformal weakens the guarantee as above):
the small forces get their own width instead of a share of a line fitted
through all of them. A calibration case whose prediction is not finite counts
as an infinite residual in every bin (its bin is unknown). The linear scale's line is pulled
by the many mid-range cases and is too narrow at the small forces of a new
liver, whose relative error is larger. Each bin needs
:func:`min_calibration_cases` cases; with fewer, fewer bins are used (the
number used is recorded). Measured with ``benchmarks/experiment_interval.py
--scales force force_bins --bins 2 3 4 5 8`` on the 08f70c9 run's shards
(cloud_sv, IV, 5 seeded splits, each scale fitted on the same calibration
predictions of a split; coverage t1 / t2 / n, mean over the splits; spread: the
range of a component's coverage over the quintiles of the true |F|, mean over
components and splits):

- IV test livers (the choice of the scale and of 5 bins): spread ``force``
  10.7 points, ``force_bins`` with 2 / 3 / 4 / 5 / 8 bins 12.6 / 11.1 / 8.7 /
  8.1 / 8.7; the worst quintile-component 81.1 % against 84.4 % (5 bins).
- Unseen livers: ``force`` 90.2 / 88.2 / 93.7 %, spread 16.2 points, the
  smallest fifth of the forces covered in 82 / 71 / 91 %; 5 bins 91.1 / 90.0 /
  94.3 %, spread 10.4 points, the smallest fifth 89 / 85 / 97 %, at mean
  half-widths within 0.007 N of ``force``'s.

Scaled by how far the GP ensemble's members disagree (``spread: beta``, the default since session 59;
normalised conformal, Papadopoulos et al. 2008, Lei et al. 2018 section 5.2). The camera and node models'
GP is a mean of members over code sizes (:class:`liverforce.learn.gp.GPEnsemble`); where the members
disagree, the model is less sure of the case. Each residual is divided by

    u_ij = d_ij + beta m_j,      d_ij the sd of the members' local forces (N, ddof 1),
                                 m_j the median of d_.j over the calibration cases

before everything above (the scale's bins or line, the stiffness widening, all on ``r / u``), and the width is
multiplied by it again: ``half_ij = q_b(i)j u_ij x ...`` (``q`` then has no unit). ``beta m_j`` keeps the
width from vanishing where the members happen to agree; a large ``beta`` is the interval without the spread.
A model without an ensemble (one GP, an MLP) records no spread and gets the interval without it. Measured on
the f67 clone's shards (2936f9e; cloud_sv, IV, 5 seeded splits, the split models' own cross-conformal
calibration; ``benchmarks/experiment_interval.py --spread``): on the IV test livers, with 5 force bins, beta 4
gave the same coverage as the bins alone (90.9 / 91.6 / 90.8 against 90.8 / 91.9 / 91.0 %) with half-widths
7-10 % narrower on every split (0.147 / 0.155 / 0.303 against 0.161 / 0.166 / 0.329 N), and the per-liver
coverage's sd over the test livers 5.8 / 5.4 / 6.3 against 6.7 / 5.8 / 6.6 points; beta 1 and 2 were as
narrow with a point less coverage on some splits, 0.25 and 0.5 wider. On the unseen livers (a check, not the
choice) beta 4 covered 91.0 / 92.0 / 91.4 % against 92.0 / 92.5 / 92.3 %, 9-12 % narrower on every split.

How far a case lies from what the GP learned from (``distance_quantile``, the config's
``train.interval.distance_quantile``; a GP model only). The interval is calibrated on cases like the
training livers' and cannot know that a new case lies where no training case does. Each prediction's GP inputs
are measured against the regressor's training rows, in the kernel's own units (each input divided by its length
scale), and the distance to the nearest is averaged over the ensemble's members
(:meth:`liverforce.learn.gp.GPEnsemble.nearest_distance`). The training side gives the distances of cases of
livers the model has not seen, in the served model's own space: each training case (its evaluation view) is
measured against the GP's rows of the other livers (IV; of the other cases in the scenarios split by case), as
an unseen liver's case is against all of them (:func:`liverforce.learn.model.training_distances`). Above their
``distance_quantile`` (0.9) a prediction is returned with a warning (:func:`distance_flags`;
:func:`liverforce.serve.checks.distance_warnings` words it). Measuring each calibration case against the fold
model that did not see it instead (``fold_quantiles`` in the record, for comparison) gives larger distances: a
fold model has fewer livers and its own length scales. On a 4-liver test model the 90 % quantile was 0.84
against 0.28 and would have flagged almost nothing; on the default run's camera model (40 training livers, fresh
clone f73) 0.516 against 0.459, which flagged 12 of the 240 unseen cases instead of 18. Measured before it was
built (``benchmarks/experiment_input_distance.py``, the f70 clone's camera model, its own liver left out on the
training side): the 9 % of the unseen livers' cases above the training side's 90 % quantile had a mean error of
0.51 N against 0.13 N for the others, and held 10 of the 15 errors above 0.4 N; the distance ranked the errors
better (Spearman 0.63) than the GP's posterior sd (0.60) or the members' spread (0.58). As built, from the fresh
clone f73 (6362e9e, the validation's ``interval.input_distance``): threshold 0.459 from the 1,200 training cases;
18 of the 240 unseen cases flagged (7.5 %; 4.6 % above the 95 % quantile, none above the 99 %), MAE 0.583 N
against 0.132 N, 10 of the 15 errors above 0.4 N. The interval of one width covered the flagged cases'
components in 78 / 78 / 72 % (t1 / t2 / n), the others' in 95 / 91 / 94 %.

Far widths (``far_widths``, the config's ``train.interval.far_widths``: the default since session 62; Mondrian
conformal with the flag as the taxonomy, Vovk et al. 2005 section 4.5). The calibration shows the same: its
cases far from the fold model that did not see them (above the calibration's own ``distance_quantile`` of
those distances, the flag's rule in the fold models' space) were covered in 67.5 / 74.2 / 71.7 % by the one
width, the others in 93.0 / 92.2 / 92.5 % (f73). So each group gets its own factor on the widths above (the
split-conformal quantile of its residuals over them, :func:`mondrian_factors`): ``far_factor`` for a case whose
distance to the served model is above the flag's threshold (``far_threshold``), ``near_factor`` for the others::

    half_ij = (the widths above)_ij x (far_factor_j if distance_i > far_threshold else near_factor_j)

On f73's calibration the factors were 1.70 / 1.68 / 1.96 and 0.88 / 0.93 / 0.86; applied to the unseen livers
(``benchmarks/experiment_far_interval.py``; these unseen figures were seen before it was built, its only choice
is the flag's own quantile) the coverage went from 94.2 / 90.4 / 92.1 % to 91.7 / 89.6 / 92.1 %, the flagged
cases' from 78 / 78 / 72 % to 89 / 83 / 94 %, at mean half-widths 0.139 / 0.145 / 0.271 N against 0.138 / 0.138 /
0.265 N; the lowest liver's t1 coverage fell from 83.3 to 73.3 %. A calibration with too few cases in a group
(:func:`min_calibration_cases`) keeps the one width, and says so in the model's notes.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

SCALES = ("none", "stiffness", "force", "force_bins")  # how the half-widths vary per case (module docstring)
WIDENINGS = ("proportional", "fitted")  # outside the calibration's stiffness range (module docstring)
FORCE_SCALES = ("force", "force_bins")  # the half-widths read the predicted force


@dataclass(frozen=True)
class ConformalInterval:
    """Half-widths ``q`` (3,) per local component (before the stiffness factor) at nominal ``coverage``: N, or
    with ``scale: force`` a multiple of ``sigma_j(|f^|)`` (no unit; ``force_scale`` holds ``sigma``'s N). With
    ``scale: force_bins`` ``q`` is the quantile over all calibration cases (what ``none`` would give, for
    reference) and ``bin_half_width_n`` holds the widths used, per bin of ``|f^|`` between ``bin_edges_n``."""

    coverage: float
    half_width_n: tuple[float, float, float]
    n_calibration: int
    grouping: str  # what the calibration split held out: "geometry" (livers) or "case"
    scale: str = "stiffness"  # "stiffness": x k; "none": fixed; "force": x sigma(|f^|); "force_bins": per bin
    folds: int = 1  # 1: one calibration split; > 1: cross-conformal over the whole training split
    stiffness_range: tuple[float, float] | None = None  # calibration cases' stiffness factors (not stiffness)
    force_scale: tuple[tuple[float, float], ...] | None = None  # scale: force: (a_j, b_j) N, N/N per component
    bin_edges_n: tuple[float, ...] | None = None  # scale: force_bins: the B - 1 inner edges of |f^| (N), ascending
    bin_half_width_n: tuple[tuple[float, float, float], ...] | None = None  # scale: force_bins: (B, 3) N
    widen: str = "proportional"  # outside the stiffness range: "proportional" (k / k_hi) or "fitted" (^g_j)
    stiffness_exponent: tuple[float, float, float] | None = None  # widen: fitted: g_j of q_c(s_j) ~ k^g_j (None:
    # nothing to fit, the proportional rule)
    spread_beta: float | None = None  # spread: the widths are multiples of u = d + beta m (module docstring);
    # None: not scaled by the members' spread (and half_width_n, bin_half_width_n are in N)
    spread_median_n: tuple[float, float, float] | None = None  # m_j: the calibration's median member sd (N)
    far_threshold: float | None = None  # far widths: the input distance above which a case is far (the model's
    # input-distance threshold); None: one width for every distance (module docstring)
    far_factor: tuple[float, float, float] | None = None  # far widths: the far cases' factor per component
    near_factor: tuple[float, float, float] | None = None  # far widths: the other cases' factor per component

    def half_widths(self, stiffness: np.ndarray, force: np.ndarray | None = None,
                    spread: np.ndarray | None = None, distance: np.ndarray | None = None) -> np.ndarray:
        """Half-widths ``(n, 3)`` N for rows with stiffness factors ``(n, 1)`` and predicted forces ``(n, 3)``
        (any frame; ``scale: force`` and ``force_bins`` only): times ``k`` with ``scale: stiffness``; with
        ``scale: none`` fixed inside the calibration's stiffness range, widened outside it; with ``scale: force``
        times ``sigma_j(|f^|)``, with ``force_bins`` the width of the bin of ``|f^|``, both widened the same way
        (module docstring); with ``spread_beta``, times ``u = spread + beta m``, ``spread`` ``(n, 3)`` the
        members' sd of each row's local force (:attr:`liverforce.learn.model.Forward.spread_local`); with far
        widths, times the far or the near factor by each row's input distance ``(n,)``
        (:attr:`liverforce.learn.model.Forward.input_distance`, :meth:`distance_factor`)."""
        return self.stiffness_factor(stiffness) * self.force_widths(force, spread, distance)

    @property
    def uses_distance(self) -> bool:
        """Whether the widths read each case's input distance (far widths: ``far_factor``)."""
        return self.far_factor is not None

    def distance_factor(self, distance: np.ndarray | None) -> np.ndarray:
        """The far widths' factor ``(n, 3)`` of input distances ``(n,)``: ``far_factor`` above ``far_threshold``,
        ``near_factor`` at or below it, NaN for a distance that is not finite (no width); ones ``(1, 3)`` without far
        widths. ValueError when the interval has far widths and no distance is given."""
        if not self.uses_distance:
            return np.ones((1, 3))
        if distance is None:
            raise ValueError("this interval's widths depend on how far each case lies from the training cases (far "
                             "widths): pass each row's input distance (Forward.input_distance)")
        d = np.asarray(distance, dtype=np.float64).reshape(-1, 1)
        out = np.where(d > self.far_threshold, np.asarray(self.far_factor)[None, :],
                       np.asarray(self.near_factor)[None, :])
        out[~np.isfinite(d[:, 0])] = np.nan
        return out

    @property
    def uses_spread(self) -> bool:
        """Whether the widths read the ensemble members' spread (``spread_beta``)."""
        return self.spread_beta is not None

    def spread_unit(self, spread: np.ndarray | None) -> np.ndarray:
        """``u = d + beta m`` ``(n, 3)`` N of the members' sd ``d`` ``(n, 3)`` (module docstring); ones without
        ``spread_beta``. A row whose spread is not finite gets NaN (no width)."""
        if not self.uses_spread:
            return np.ones((1, 3)) if spread is None else np.ones_like(np.asarray(spread, dtype=np.float64))
        if spread is None:
            raise ValueError("this interval is scaled by the spread of the model's GP ensemble members "
                             "(spread_beta): pass each row's members' sd (Forward.spread_local)")
        d = np.asarray(spread, dtype=np.float64).reshape(-1, 3)
        return d + self.spread_beta * np.asarray(self.spread_median_n, dtype=np.float64)[None, :]

    def stiffness_factor(self, stiffness: np.ndarray) -> np.ndarray:
        """What the widths are multiplied by for each row's stiffness factor ``(n, 1)``: ``k`` with
        ``scale: stiffness``, else the widening outside the calibration's range (:meth:`extrapolation_factor`:
        ``(n, 3)``, one factor per component, with ``widen: fitted`` and fitted exponents; ``(n, 1)`` otherwise)."""
        k = np.asarray(stiffness, dtype=np.float64).reshape(-1, 1)
        return k if self.scale == "stiffness" else self.extrapolation_factor(k)

    def force_widths(self, force: np.ndarray | None = None, spread: np.ndarray | None = None,
                     distance: np.ndarray | None = None) -> np.ndarray:
        """The half-widths before the stiffness factor: ``(n, 3)`` for predicted forces ``(n, 3)`` (any frame:
        only ``|f^|`` is read), ``(1, 3)`` without forces for a scale that does not read them; times
        :meth:`spread_unit` with ``spread_beta`` (``spread``: the members' sd, ``(n, 3)`` N) and
        :meth:`distance_factor` with far widths (``distance``: the input distances ``(n,)``)."""
        w = self._scaled_widths(force)
        if self.uses_spread:
            w = w * self.spread_unit(spread)
        if self.uses_distance:
            w = w * self.distance_factor(distance)
        return w

    def _scaled_widths(self, force: np.ndarray | None) -> np.ndarray:
        """:meth:`force_widths` before the spread's unit."""
        q = np.asarray(self.half_width_n, dtype=np.float64)[None, :]
        if self.scale not in FORCE_SCALES:
            return q if force is None else np.repeat(q, len(np.asarray(force).reshape(-1, 3)), axis=0)
        if force is None:
            raise ValueError(f"an interval scaled by the force (scale: {self.scale}) needs the predicted forces")
        if self.scale == "force":
            return q * self.sigma(force)
        return np.asarray(self.bin_half_width_n, dtype=np.float64)[self.force_bin(force)]

    def force_bin(self, force: np.ndarray) -> np.ndarray:
        """The bin ``(n,)`` of ``|f^|`` of each predicted force ``(n, 3)`` (``scale: force_bins``; a NaN force
        falls in the last bin)."""
        return force_bin_of(self.bin_edges_n or (), force)

    def sigma(self, force: np.ndarray) -> np.ndarray:
        """``sigma_j(|f|)`` ``(n, 3)`` of predicted forces ``(n, 3)`` (``scale: force``; ones otherwise)."""
        return force_sigma(self.force_scale, force)

    def extrapolation_factor(self, stiffness: np.ndarray) -> np.ndarray:
        """The widening outside the calibration's stiffness range ``[k_lo, k_hi]`` for stiffness factors ``(n, 1)``
        (ones without a recorded range): ``widen: proportional`` ``max(1, k / k_hi, k_lo / k)`` ``(n, 1)``;
        ``widen: fitted`` per component ``(k / k_hi)^min(g_j, 1)`` above the range where ``g_j > 0``,
        ``(k_lo / k)^min(-g_j, 1)`` below it where ``g_j < 0``, else 1 ``(n, 3)`` (module docstring); without
        fitted exponents (one material, too few cases) the proportional rule."""
        k = np.asarray(stiffness, dtype=np.float64)
        if self.stiffness_range is None:
            return np.ones_like(k)
        lo, hi = self.stiffness_range
        above, below = np.maximum(1.0, k / hi), np.maximum(1.0, lo / np.maximum(k, 1e-300))
        if self.widen != "fitted" or self.stiffness_exponent is None:
            return np.maximum(above, below)
        g = np.asarray(self.stiffness_exponent, float)
        k2 = k.reshape(-1, 1)
        return (np.maximum(1.0, k2 / hi) ** np.clip(g, 0.0, 1.0)[None, :]
                * np.maximum(1.0, lo / np.maximum(k2, 1e-300)) ** np.clip(-g, 0.0, 1.0)[None, :])

    @property
    def bounded(self) -> bool:
        """False when there were too few calibration cases (:func:`min_calibration_cases`): infinite width."""
        bins = [v for row in (self.bin_half_width_n or ()) for v in row]
        return all(math.isfinite(v) for v in (*self.half_width_n, *bins))

    def to_dict(self) -> dict:
        """JSON-ready; an unbounded half-width is written as null."""
        return {"coverage": float(self.coverage),
                "half_width_n": [float(v) if math.isfinite(v) else None for v in self.half_width_n],
                "n_calibration": int(self.n_calibration), "grouping": self.grouping, "scale": self.scale,
                "folds": int(self.folds),
                "stiffness_range": None if self.stiffness_range is None else [float(v) for v in self.stiffness_range],
                "force_scale": None if self.force_scale is None else
                [[float(a), float(b)] for a, b in self.force_scale],
                "bin_edges_n": None if self.bin_edges_n is None else [float(v) for v in self.bin_edges_n],
                "bin_half_width_n": None if self.bin_half_width_n is None else
                [[float(v) if math.isfinite(v) else None for v in row] for row in self.bin_half_width_n],
                "widen": self.widen,
                "stiffness_exponent": None if self.stiffness_exponent is None else
                [float(v) for v in self.stiffness_exponent],
                "spread_beta": None if self.spread_beta is None else float(self.spread_beta),
                "spread_median_n": None if self.spread_median_n is None else
                [float(v) for v in self.spread_median_n],
                "far_threshold": None if self.far_threshold is None else float(self.far_threshold),
                "far_factor": None if self.far_factor is None else [float(v) for v in self.far_factor],
                "near_factor": None if self.near_factor is None else [float(v) for v in self.near_factor]}

    @classmethod
    def from_dict(cls, d: dict) -> "ConformalInterval":
        rng, fs = d.get("stiffness_range"), d.get("force_scale")
        edges, bins = d.get("bin_edges_n"), d.get("bin_half_width_n")
        g = d.get("stiffness_exponent")  # a bundle before the key: widen proportional, what it meant then
        med = d.get("spread_median_n")
        if d.get("spread_beta") is not None and (med is None or len(med) != 3):
            raise ValueError(f"the interval's spread_beta {d['spread_beta']} needs spread_median_n, 3 values (got "
                             f"{med!r}): the model's model.json was edited or damaged; train the model again")
        return cls(float(d["coverage"]), _widths(d["half_width_n"]),
                   int(d["n_calibration"]), str(d["grouping"]), str(d.get("scale", "stiffness")),
                   int(d.get("folds", 1)), None if rng is None else (float(rng[0]), float(rng[1])),
                   None if fs is None else tuple((float(a), float(b)) for a, b in fs),
                   None if edges is None else tuple(float(v) for v in edges),
                   None if bins is None else tuple(_widths(row) for row in bins),
                   str(d.get("widen", "proportional")), None if g is None else tuple(float(v) for v in g),
                   None if d.get("spread_beta") is None else float(d["spread_beta"]),  # before format 17: none
                   None if d.get("spread_median_n") is None else tuple(float(v) for v in d["spread_median_n"]),
                   *_far_widths(d))


def _far_widths(d: dict) -> tuple:
    """``(far_threshold, far_factor, near_factor)`` of a stored interval: all three or none (a bundle before
    them: none)."""
    keys = ("far_threshold", "far_factor", "near_factor")
    got = [d.get(k) for k in keys]
    if all(v is None for v in got):
        return None, None, None
    if any(v is None for v in got) or np.ndim(got[1]) != 1 or np.ndim(got[2]) != 1 or len(got[1]) != 3 \
            or len(got[2]) != 3:
        raise ValueError(f"the interval's far widths need far_threshold and two factors of 3 values (got "
                         f"{dict(zip(keys, got))!r}): the model's model.json was edited or damaged; train the model "
                         "again")
    return float(got[0]), tuple(float(v) for v in got[1]), tuple(float(v) for v in got[2])


def _widths(row) -> tuple[float, ...]:
    """Half-widths as stored (an unbounded one as null) back to floats."""
    return tuple(math.inf if v is None else float(v) for v in row)


def fit_conformal(true_local: np.ndarray, pred_local: np.ndarray, stiffness: np.ndarray, coverage: float,
                  grouping: str, scale: str = "stiffness", folds: int = 1, bins: int = 5,
                  widen: str = "proportional", spread: np.ndarray | None = None,
                  spread_beta: float | None = None) -> ConformalInterval:
    """The split-conformal quantile per component (module docstring) from calibration predictions; ``bins``:
    the bins of the predicted ``|f^|`` with ``scale: force_bins`` (fewer when a bin would hold too few cases);
    ``widen``: the widening outside the calibration's stiffness range (not with ``scale: stiffness``).
    ``spread``: the calibration cases' members' sd ``(n, 3)`` N and ``spread_beta`` > 0: every residual over
    ``u = spread + beta median(spread)`` first (module docstring); either None: not scaled by it."""
    if not 0.0 < coverage < 1.0:
        raise ValueError(f"interval coverage must be in (0, 1), got {coverage}")
    if scale not in SCALES:
        raise ValueError(f"interval scale must be one of {SCALES}, got {scale!r}")
    if int(bins) < 1:
        raise ValueError(f"interval bins must be >= 1, got {bins}")
    if widen not in WIDENINGS:
        raise ValueError(f"interval widen must be one of {WIDENINGS}, got {widen!r}")
    k_rows = np.asarray(stiffness, float).reshape(-1, 1)
    k = k_rows if scale == "stiffness" else 1.0
    pred = np.asarray(pred_local, float)
    r = np.abs(np.asarray(true_local, float) - pred)
    n = len(r)
    beta = med = None
    if spread is not None and spread_beta is not None:
        beta, med = _spread_median(spread, pred, r, spread_beta)
        r = r / (np.asarray(spread, dtype=np.float64) + beta * np.asarray(med)[None, :])
    rng = (float(k_rows.min()), float(k_rows.max())) if scale != "stiffness" and k_rows.size else None
    rank = _rank(n, coverage)
    if rank > n:  # too few cases for this coverage: the honest split-conformal interval is unbounded
        unbounded = ((), ((math.inf,) * 3,)) if scale == "force_bins" else (None, None)
        return ConformalInterval(float(coverage), (math.inf,) * 3, int(n), grouping, scale, int(folds), rng,
                                 None, *unbounded, widen, None, beta, med)
    ok = np.isfinite(pred).all(axis=1) & np.isfinite(r).all(axis=1)  # a non-finite row sorts last, as before
    fs = force_scale_fit(pred[ok], r[ok]) if scale == "force" and ok.any() else None
    s = r / k if fs is None else r / force_sigma(fs, pred)
    q = np.sort(s, axis=0)[rank - 1]
    edges = widths = None
    if scale == "force_bins":
        edges, widths = _force_bins(pred, r, ok, coverage, int(bins))
    g = None
    if widen == "fitted" and rng is not None:  # the growth with k of the scores the widths do not already follow
        score = s[ok]  # r, or r / sigma with scale: force (k is 1 for every scale with a range)
        if widths is not None:
            w = np.asarray(widths, dtype=np.float64)[force_bin_of(edges, pred[ok])]
            score = np.where(np.isfinite(w) & (w > 0), score / np.where(w > 0, w, 1.0), score)
        g = stiffness_exponent_fit(k_rows[ok], score, coverage)
    return ConformalInterval(float(coverage), tuple(float(v) for v in q), int(n), grouping, scale, int(folds), rng,
                             fs, edges, widths, widen, g, beta, med)


class SpreadUnusable(ValueError):
    """The calibration's members agree on most cases (median sd 0): nothing to scale the widths by."""


def _spread_median(spread, pred: np.ndarray, r: np.ndarray, beta) -> tuple[float, tuple[float, ...]]:
    """``(beta, m)`` of :func:`fit_conformal`'s ``spread``: ``m_j`` the median members' sd of the calibration
    cases whose prediction, residual and spread are finite. Refused (ValueError): a spread of another shape than
    the predictions, a negative one, ``beta <= 0``, or a zero median (the members agree on most cases: nothing to
    scale by; ``train.interval.spread: null``)."""
    d = np.asarray(spread, dtype=np.float64)
    if d.shape != pred.shape:
        raise ValueError(f"interval spread: one members' sd per prediction, shape {pred.shape}; got {d.shape}")
    if not (isinstance(beta, (int, float)) and math.isfinite(beta) and beta > 0):
        raise ValueError(f"interval spread: beta must be a positive number, got {beta!r}")
    ok = np.isfinite(pred).all(axis=1) & np.isfinite(r).all(axis=1) & np.isfinite(d).all(axis=1)
    if (d[ok] < 0).any():
        raise ValueError("interval spread: a members' sd is negative")
    med = np.median(d[ok], axis=0) if ok.any() else np.zeros(3)
    if not (med > 0).all():
        raise SpreadUnusable(f"interval spread: the members' median sd is {med.tolist()} N; with zero, nothing "
                             "scales the widths (set train.interval.spread: null)")
    return float(beta), tuple(float(v) for v in med)


def stiffness_exponent_fit(stiffness: np.ndarray, score: np.ndarray, coverage: float,
                           bins: int = 5) -> tuple[float, ...] | None:
    """``g_j`` per component: how the calibration's ``coverage`` quantile of the scores grows with the stiffness
    factor, ``q_c(s_j) ~ k^g_j`` (``widen: fitted``, module docstring). ``score``: the residuals ``|r|`` divided by
    what the interval already scales them by (``sigma_j(|f^|)`` with ``scale: force``, the bin's width with
    ``force_bins``), so that a growth the widths already follow is not counted twice. The cases are cut into
    ``bins`` bins at the quantiles of ``k`` (fewer while a bin would hold fewer than
    :func:`min_calibration_cases`); ``g_j`` is the least-squares slope of ``log q_c`` of each bin on the log of
    its mean ``k``. A component with a zero quantile in some bin gets 1 (the proportional rule). None when
    nothing can be fitted: the cases span no stiffness range (one material) or fill fewer than two bins (the
    interval then widens in proportion, :meth:`ConformalInterval.extrapolation_factor`)."""
    k = np.asarray(stiffness, dtype=np.float64).ravel()
    r = np.asarray(score, dtype=np.float64).reshape(len(k), -1)
    if k.size == 0 or not k.min() > 0 or k.max() <= k.min() * (1 + 1e-9):
        return None
    cut = _quantile_bins(k, int(bins), min_calibration_cases(coverage), fewest=2)
    if cut is None:
        return None
    _, which, counts = cut
    x = np.log([k[which == i].mean() for i in range(len(counts))])
    q = np.array([np.sort(r[which == i], axis=0)[_rank(int(counts[i]), coverage) - 1] for i in range(len(counts))])
    return tuple(float(np.polyfit(x, np.log(q[:, j]), 1)[0]) if (q[:, j] > 0).all() and np.isfinite(q[:, j]).all()
                 else 1.0 for j in range(r.shape[1]))


def _quantile_bins(values: np.ndarray, bins: int, need: int, n_extra: int = 0, fewest: int = 1):
    """``(inner edges, bin of each value, cases per bin)`` with the edges at the quantiles of ``values``: as many
    bins as asked for, fewer while a bin would hold fewer than ``need`` cases (``n_extra`` cases counted in every
    bin: :func:`_force_bins`' non-finite ones). Tied values share an edge: the duplicate, or one at the smallest
    value (an empty first bin), is dropped. None when not even ``fewest`` bins can be filled (one bin always can)."""
    top = max(1, (len(values) + n_extra) // need)
    for b in range(min(bins, top), fewest - 1, -1):
        e = np.unique(np.quantile(values, np.arange(1, b) / b)) if values.size else np.empty(0)
        edges = e[e > values.min()] if values.size else e
        which = np.searchsorted(edges, values, side="right")
        counts = np.bincount(which, minlength=len(edges) + 1) + n_extra
        if len(edges) == 0:
            if fewest <= 1:
                return edges, which, counts
        elif counts.min() >= need:
            return edges, which, counts
    return None


def _force_bins(pred: np.ndarray, r: np.ndarray, ok: np.ndarray, coverage: float, bins: int):
    """Inner edges (at the quantiles of the calibration cases' ``|f^|``) and the quantile of ``|r|`` per bin and
    component; as many bins as asked for, fewer while a bin would hold fewer than :func:`min_calibration_cases`
    cases (tied predictions share an edge: the duplicate, or one at the smallest ``|f^|``, is dropped). A case
    whose prediction or residual is not finite (``ok`` False) counts as an infinite residual in every bin."""
    mag = np.linalg.norm(pred[ok], axis=1)
    r_ok = r[ok]
    n_bad = int((~ok).sum())
    e, which, counts = _quantile_bins(mag, bins, min_calibration_cases(coverage), n_extra=n_bad)
    widths = []
    for j in range(len(e) + 1):
        rj = np.vstack([r_ok[which == j], np.full((n_bad, r.shape[1]), math.inf)])
        widths.append(tuple(float(v) for v in np.sort(rj, axis=0)[_rank(int(counts[j]), coverage) - 1]))
    return tuple(float(v) for v in e), tuple(widths)


def force_bin_of(edges, force: np.ndarray) -> np.ndarray:
    """Bin index ``(n,)`` of ``|f|`` for forces ``(n, 3)`` between ascending inner ``edges`` (a value on an edge
    goes to the bin above it; NaN to the last)."""
    mag = np.linalg.norm(np.asarray(force, dtype=np.float64).reshape(-1, 3), axis=1)
    return np.searchsorted(np.asarray(edges, dtype=np.float64), mag, side="right")


def force_sigma(force_scale, force: np.ndarray) -> np.ndarray:
    """``sigma_j(|f|) = a_j + b_j |f|`` ``(n, 3)`` for forces ``(n, 3)`` (ones when ``force_scale`` is None)."""
    f = np.asarray(force, dtype=np.float64).reshape(-1, 3)
    if force_scale is None:
        return np.ones_like(f)
    ab = np.asarray(force_scale, dtype=np.float64)  # (3, 2)
    return ab[None, :, 0] + ab[None, :, 1] * np.linalg.norm(f, axis=1, keepdims=True)


def force_scale_fit(pred_local: np.ndarray, abs_residual: np.ndarray) -> tuple[tuple[float, float], ...]:
    """``(a_j, b_j)`` per component: least squares of ``|r_ij|`` on ``[1, |f^_i|]``, with ``b_j >= 0`` (refitted
    as a constant, the mean ``|r_j|``, when the slope comes out negative) and ``a_j`` at least a tenth of the mean
    ``|r_j|`` (and positive), so that ``sigma_j`` never vanishes (module docstring)."""
    m = np.linalg.norm(np.asarray(pred_local, float), axis=1)
    r = np.asarray(abs_residual, float)
    A = np.column_stack([np.ones_like(m), m])
    out = []
    for j in range(r.shape[1]):
        mean = float(r[:, j].mean())
        a, b = (np.linalg.lstsq(A, r[:, j], rcond=None)[0] if m.std() > 0 else (mean, 0.0))
        if b < 0:
            a, b = mean, 0.0
        out.append((max(float(a), 0.1 * mean, 1e-12), float(b)))
    return tuple(out)



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


DISTANCE_QUANTILES = (0.5, 0.9, 0.95, 0.99)  #: recorded with the threshold (``meta["input_distance"]``)


def fit_input_distance(distance: np.ndarray, quantile: float) -> dict:
    """The input-distance flag of the module docstring, from the training side's distances (``(n,)``, each training
    case's to the GP's rows of the other livers): ``{"quantile", "threshold", "n_calibration",
    "calibration_quantiles"}`` (JSON-ready, ``meta["input_distance"]``; ``n_calibration``: the cases measured).
    ValueError for a quantile outside [0.5, 1) or no finite distance."""
    q = float(quantile)
    if not 0.5 <= q < 1.0:
        raise ValueError(f"distance_quantile must be in [0.5, 1), got {quantile!r}")
    d = np.asarray(distance, dtype=np.float64).reshape(-1)
    d = d[np.isfinite(d)]
    if d.size == 0:
        raise ValueError("no finite calibration distance to fit the input-distance flag on")
    return {"quantile": q, "threshold": float(np.quantile(d, q)), "n_calibration": int(d.size),
            "calibration_quantiles": {f"{p:g}": float(np.quantile(d, p)) for p in DISTANCE_QUANTILES}}


def distance_flags(distance, record: dict | None) -> np.ndarray:
    """``(n,)`` bool: the cases whose input distance lies above ``record["threshold"]`` (:func:`fit_input_distance`);
    all False without a record or a distance (NaN compares False)."""
    if distance is None:
        return np.zeros(0, dtype=bool)
    d = np.asarray(distance, dtype=np.float64).reshape(-1)
    if not record:
        return np.zeros(d.shape, dtype=bool)
    return d > float(record["threshold"])


def mondrian_factors(scores: np.ndarray, far: np.ndarray, coverage: float) -> tuple[np.ndarray, np.ndarray]:
    """Per component, the split-conformal quantile (rank ``ceil((n + 1) c)``) of ``scores`` ``(n, k)`` among the rows
    ``far`` and among the others: ``(far factors (k,), near factors (k,))``. A group too small to bound the
    quantile (:func:`min_calibration_cases`) gets inf."""
    s = np.asarray(scores, dtype=np.float64)
    f = np.asarray(far, dtype=bool)

    def q(rows):
        k = _rank(len(rows), coverage)
        return np.full(s.shape[1], np.inf) if k > len(rows) else np.sort(rows, axis=0)[k - 1]

    return q(s[f]), q(s[~f])


def with_far_widths(ci: ConformalInterval, cal: dict, threshold: float, quantile: float) -> ConformalInterval:
    """``ci`` with far widths (module docstring), fitted on its calibration ``cal`` (``true_local``,
    ``pred_local``, ``stiffness``, ``spread_local`` as its widths read them, and ``input_distance``: each case's
    distance to the fold model that did not see it). A calibration case is far when its distance lies above the
    calibration's own ``quantile`` of them (the flag's rule in the fold models' space); each group's scores are
    its residuals over ``ci``'s half-widths, and its factor their split-conformal quantile per component
    (:func:`mondrian_factors`). Serving calls a case far when its distance to the served model lies above
    ``threshold`` (the model's input-distance threshold). ValueError when a group is too small to bound its
    quantile, or the calibration has no distances."""
    d = cal.get("input_distance")
    if d is None:
        raise ValueError("far widths need the calibration cases' input distances (a GP regressor)")
    d = np.asarray(d, dtype=np.float64)
    ok = np.isfinite(d)  # a case without a distance (a prediction that was not finite) is in neither group
    if not ok.any():
        raise ValueError("far widths: no calibration case has a finite input distance")
    half = ci.half_widths(cal["stiffness"], cal["pred_local"], cal.get("spread_local"))
    scores = np.abs(np.asarray(cal["true_local"], float) - np.asarray(cal["pred_local"], float)) / half
    far = d[ok] > np.quantile(d[ok], quantile)
    fk, nk = mondrian_factors(scores[ok], far, ci.coverage)
    if not (np.isfinite(fk).all() and np.isfinite(nk).all()):
        raise ValueError(f"far widths: {int(far.sum())} far and {int((~far).sum())} other calibration cases; each "
                         f"group needs {min_calibration_cases(ci.coverage)} to bound a {100 * ci.coverage:.0f} % width")
    return dataclasses.replace(ci, far_threshold=float(threshold), far_factor=tuple(float(v) for v in fk),
                               near_factor=tuple(float(v) for v in nk))
