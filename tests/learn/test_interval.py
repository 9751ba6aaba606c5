"""Calibrated intervals per local force component (split conformal, liverforce.learn.interval)."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from liverforce.learn.frames import force_to_local, local_rotations
from liverforce.learn.interval import (ConformalInterval, coverage_per_component, fit_conformal, min_calibration_cases,
                                      stiffness_exponent_fit)
from liverforce.learn.model import ForceModel, subset
from liverforce.learn.synthetic import synthetic_arrays
from liverforce.learn.train import interval_from_calibration, train_scenario

MODEL = {"encoder": "pca", "code_size": 6, "state_vector": True, "grid_size": 8, "hidden": [64], "dropout": 0.0,
         "occlusion": {"radius_mm": 0.0, "mode": "remove"}, "noise_mm": 0.5, "force_scaling": "stiffness",
         "probe_force_radius_mm": 5.0}
TRAIN = {"test_fraction": 0.2, "epochs": 40, "batch_size": 32, "lr": 3e-3, "weight_decay": 0.0, "seed": 0,
         "repeats": 1, "interval": {"coverage": 0.9, "calibration_fraction": 0.3}}
NO_TUNE = {"enabled": False, "trials": 1, "folds": 2, "sobol_trials": 1, "epochs": 1}


def test_the_quantile_is_the_conformal_rank():
    rng = np.random.default_rng(0)
    r = rng.normal(size=(19, 3))
    ci = fit_conformal(r, np.zeros_like(r), np.ones(19), 0.9, "case")
    # ceil((19 + 1) * 0.9) = 18th smallest |r| per component
    np.testing.assert_allclose(ci.half_width_n, np.sort(np.abs(r), axis=0)[17])
    # residuals divided by the stiffness factor: doubling k and the residuals gives the same q
    np.testing.assert_allclose(fit_conformal(2 * r, np.zeros_like(r), 2 * np.ones(19), 0.9, "case").half_width_n,
                               ci.half_width_n)
    assert ConformalInterval.from_dict(ci.to_dict()) == ci
    # too few cases for 90 %: unbounded (the honest answer), and it round-trips through JSON as null
    few = fit_conformal(r[:8], np.zeros((8, 3)), np.ones(8), 0.9, "case")
    assert not few.bounded and min_calibration_cases(0.9) == 9 and few.to_dict()["half_width_n"] == [None] * 3
    assert ConformalInterval.from_dict(few.to_dict()).half_width_n == (math.inf,) * 3


@pytest.mark.slow  # one of the default set's slowest (CI's --durations): run with -m slow
def test_coverage_on_fresh_cases_is_the_nominal_one(tmp_path):
    """Trained and calibrated on 400 cases, the 90 % interval covers 90 % of 600 fresh exchangeable cases per
    local component, within 2.5 sd of the two sources of spread: the calibration quantile's own (coverage given
    n calibration cases is Beta-distributed, sd ~ sqrt(c (1 - c) / (n + 2)), ~3 % here) and the fresh cases'
    binomial sd (~1.2 %); and the interval scales with the stiffness."""
    kw = dict(n_geometries=1, nodes=(150, 200), dent_width_mm=12.0, material_varies=True, dtype=np.float64)
    data = synthetic_arrays(1000, seed=11, **kw)
    first = synthetic_arrays(400, seed=11, **kw)
    np.testing.assert_array_equal(first["force_n"], data["force_n"][:400])  # the fresh cases extend the set
    res = train_scenario(first, MODEL, TRAIN, NO_TUNE, "II", "v", out_dir=tmp_path)
    assert res["interval"]["n_calibration"] >= 90 and len(res["interval"]["test_coverage"]) == 3
    model = ForceModel.load(res["model_path"])
    fresh = subset(data, np.arange(400, 1000))
    got = model.predict_interval(fresh, observation_seed=12345)
    R = local_rotations(fresh["frame_normal"], fresh["frame_t1"], fresh["frame_t2"])
    cov = coverage_per_component(force_to_local(fresh["force_n"], R), got["force_local_n"], got["half_width_local_n"])
    n_cal = res["interval"]["n_calibration"]
    sd = np.sqrt(0.9 * 0.1 / (n_cal + 2) + 0.9 * 0.1 / len(fresh["force_n"]))
    assert all(abs(c - 0.9) <= 2.5 * sd for c in cov), (cov, sd)
    np.testing.assert_allclose(got["force_n"], model.predict(fresh, observation_seed=12345))
    k = np.asarray(fresh["material_params_mpa"])[:, 0] / model.pre.stiffness_ref
    np.testing.assert_allclose(got["half_width_local_n"], k[:, None] * np.asarray(model.interval.half_width_n))
    # a model with half the calibration cases of the minimum has no bounded interval, and says so
    small = {**TRAIN, "interval": {"coverage": 0.99, "calibration_fraction": 0.05}}
    res2 = train_scenario(first, MODEL, small, NO_TUNE, "II", "v", out_dir=tmp_path / "small")
    assert res2["interval"]["half_width_n"] == [None] * 3 and res2["interval"]["test_coverage"] == [1.0] * 3


@pytest.mark.parametrize("cov", [0.0, 1.0])
def test_coverage_must_be_a_probability(cov):
    with pytest.raises(ValueError, match="coverage"):
        fit_conformal(np.zeros((30, 3)), np.zeros((30, 3)), np.ones(30), cov, "case")


def test_scale_none_gives_the_same_width_inside_the_stiffness_range_and_widens_outside():
    rng = np.random.default_rng(1)
    r = rng.normal(size=(40, 3))
    k = rng.uniform(0.5, 2.0, size=40)
    ci = fit_conformal(r, np.zeros_like(r), k, 0.9, "case", scale="none")
    np.testing.assert_allclose(ci.half_width_n, np.sort(np.abs(r), axis=0)[36])  # ceil(41 * 0.9) = 37th
    assert ci.stiffness_range == (k.min(), k.max())
    inside = np.array([k.min(), 1.0, k.max()])
    np.testing.assert_allclose(ci.half_widths(inside), np.tile(ci.half_width_n, (3, 1)))
    # outside the calibration's range the model extrapolates: widened by the distance out, both ways
    np.testing.assert_allclose(ci.half_widths(np.array([1.5 * k.max(), k.min() / 2])),
                               np.array([[1.5], [2.0]]) * np.asarray(ci.half_width_n))
    assert ConformalInterval.from_dict(ci.to_dict()) == ci
    # a bundle written before the range was recorded keeps fixed widths everywhere
    old = {key: v for key, v in ci.to_dict().items() if key != "stiffness_range"}
    np.testing.assert_allclose(ConformalInterval.from_dict(old).half_widths(np.array([3.0])), [ci.half_width_n])
    with pytest.raises(ValueError, match="scale"):
        fit_conformal(r, np.zeros_like(r), k, 0.9, "case", scale="magnitude")


def _heteroscedastic(n, rng, a=(0.05, 0.03, 0.08), b=(0.05, 0.04, 0.02)):
    """Predicted forces with |f^| uniform in 0-5 N and residuals ~ N(0, a_j + b_j |f^|) per component."""
    d = rng.normal(size=(n, 3))
    pred = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0.0, 5.0, (n, 1))
    sd = np.asarray(a)[None, :] + np.asarray(b)[None, :] * np.linalg.norm(pred, axis=1, keepdims=True)
    return pred, pred + sd * rng.normal(size=(n, 3)), sd


def _by_quintile(pred, true, half):
    m = np.linalg.norm(pred, axis=1)
    e = np.quantile(m, np.linspace(0, 1, 6))
    inside = np.abs(true - pred) <= half
    return np.array([inside[(m >= e[i]) & (m <= e[i + 1])].mean(axis=0) for i in range(5)])


def test_scale_force_holds_the_coverage_for_small_and_large_forces_alike():
    """Residuals whose sd grows with the force (as the camera model's do): a fixed width over-covers the small
    forces and under-covers the large ones; scaled by a + b |f^| (fitted on the calibration residuals) every
    quintile of |f^| is covered at the nominal 90 % within 3.5 points, and the mean width is smaller. The
    spread of a quintile's coverage: binomial on 4,000 fresh cases (~0.5 %), the calibration quantile's and
    the fitted (a, b)'s on 10,000 calibration cases (together ~0.8 %); over 60 seeds the largest deviation of
    any quintile-component was 2.4 points (with 3,000 calibration cases, 4.5)."""
    rng = np.random.default_rng(4)
    pred, true, sd = _heteroscedastic(10000, rng)
    k = np.ones(10000)
    fixed = fit_conformal(true, pred, k, 0.9, "case", scale="none")
    scaled = fit_conformal(true, pred, k, 0.9, "case", scale="force")
    # the fitted scale is the mean |r| = sqrt(2 / pi) sd: within 10 % of it over 0.5-5 N
    f = np.column_stack([np.linspace(0.5, 5.0, 10), np.zeros((10, 2))])
    want = np.sqrt(2 / np.pi) * (np.array([0.05, 0.03, 0.08]) + np.array([0.05, 0.04, 0.02]) * f[:, :1])
    np.testing.assert_allclose(scaled.sigma(f), want, rtol=0.1)
    p2, t2, _ = _heteroscedastic(20000, rng)
    ones = np.ones((20000, 1))
    cov_fixed = _by_quintile(p2, t2, fixed.half_widths(ones))
    cov_scaled = _by_quintile(p2, t2, scaled.half_widths(ones, p2))
    assert (cov_fixed[0] > 0.97).all() and (cov_fixed[-1] < 0.85).all(), cov_fixed
    assert np.abs(cov_scaled - 0.9).max() < 0.035, cov_scaled
    assert (scaled.half_widths(ones, p2).mean(axis=0) < fixed.half_widths(ones).mean(axis=0)).all()
    # the scale is frame-free (it reads |f^|), JSON round-trips, and the force is required
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    np.testing.assert_allclose(scaled.half_widths(ones[:5], p2[:5] @ R.T), scaled.half_widths(ones[:5], p2[:5]))
    assert ConformalInterval.from_dict(scaled.to_dict()) == scaled
    v10 = scaled.to_dict()  # a bundle of format 10 (before force_bins) has no bin keys: it reads the same
    assert v10.pop("bin_edges_n") is None and v10.pop("bin_half_width_n") is None
    np.testing.assert_array_equal(ConformalInterval.from_dict(v10).half_widths(ones[:5], p2[:5]),
                                  scaled.half_widths(ones[:5], p2[:5]))
    with pytest.raises(ValueError, match="predicted forces"):
        scaled.half_widths(ones)
    # outside the calibration's stiffness range it widens as scale: none does
    scaled_k = fit_conformal(true, pred, rng.uniform(0.8, 1.2, 10000), 0.9, "case", scale="force")
    lo, hi = scaled_k.stiffness_range
    np.testing.assert_allclose(scaled_k.half_widths(np.array([[2 * hi], [1.0]]), p2[:2])[0],
                               2 * scaled_k.half_widths(np.array([[hi]]), p2[:1])[0])


def test_scale_force_falls_back_to_a_fixed_width_when_errors_do_not_grow_with_the_force():
    """A slope fitted negative is refused (the scale would shrink for the large forces): the scale is then the
    mean |r|, a constant, and the interval is the fixed one."""
    rng = np.random.default_rng(5)
    pred = rng.normal(size=(500, 3))
    m = np.linalg.norm(pred, axis=1, keepdims=True)
    true = pred + rng.normal(size=(500, 3)) * (1.0 / (1.0 + m))  # errors shrink with the force
    ci = fit_conformal(true, pred, np.ones(500), 0.9, "case", scale="force")
    assert all(b == 0.0 for _, b in ci.force_scale)
    fixed = fit_conformal(true, pred, np.ones(500), 0.9, "case", scale="none")
    np.testing.assert_allclose(ci.half_widths(np.ones((3, 1)), pred[:3]), fixed.half_widths(np.ones(3)))


def _step_noise(n, rng):
    """|f^| uniform in 0-5 N; residual sd 0.12 N per component below 1 N, 0.02 + 0.05 |f^| above: the small
    forces err more than a line through the rest says (as a new liver's small forces do)."""
    d = rng.normal(size=(n, 3))
    pred = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0.0, 5.0, (n, 1))
    m = np.linalg.norm(pred, axis=1, keepdims=True)
    sd = np.where(m < 1.0, 0.12, 0.02 + 0.05 * m) * np.ones((1, 3))
    return pred, pred + sd * rng.normal(size=(n, 3))


def test_scale_force_bins_covers_every_bin_of_the_predicted_force_where_a_line_does_not():
    """Mondrian conformal: a split-conformal quantile per bin of |f^| (bins at the calibration's quintiles here)
    covers each bin's fresh cases at the nominal 90 % (binomial sd on 4,000 per bin ~0.5 %, the quantile's on
    2,000 calibration cases per bin ~0.7 %: 3.5 points is over 4 sd). The linear force scale, fitted through
    the same residuals, under-covers the smallest fifth: the test's errors break its line there."""
    rng = np.random.default_rng(11)
    pred, true = _step_noise(10000, rng)
    k = np.ones(10000)
    binned = fit_conformal(true, pred, k, 0.9, "case", scale="force_bins", bins=5)
    line = fit_conformal(true, pred, k, 0.9, "case", scale="force")
    assert len(binned.bin_half_width_n) == 5 and len(binned.bin_edges_n) == 4
    p2, t2 = _step_noise(20000, rng)
    ones = np.ones((20000, 1))
    cov_bins = _by_quintile(p2, t2, binned.half_widths(ones, p2))
    cov_line = _by_quintile(p2, t2, line.half_widths(ones, p2))
    assert np.abs(cov_bins - 0.9).max() < 0.035, cov_bins
    assert (cov_line[0] < 0.85).all(), cov_line  # the case is one a line gets wrong
    # each bin's width is the conformal rank of its own residuals, the edges the calibration's quantiles
    mag = np.linalg.norm(pred, axis=1)
    np.testing.assert_allclose(binned.bin_edges_n, np.quantile(mag, [0.2, 0.4, 0.6, 0.8]))
    which = np.searchsorted(binned.bin_edges_n, mag, side="right")
    for b in range(5):
        r = np.abs(true - pred)[which == b]
        np.testing.assert_array_equal(binned.bin_half_width_n[b], np.sort(r, axis=0)[math.ceil((len(r) + 1) * 0.9) - 1])
    # frame-free, JSON round-trips (through json text), needs the force, widens outside the stiffness range
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    np.testing.assert_allclose(binned.half_widths(ones[:5], p2[:5] @ R.T), binned.half_widths(ones[:5], p2[:5]))
    assert ConformalInterval.from_dict(json.loads(json.dumps(binned.to_dict()))) == binned
    with pytest.raises(ValueError, match="predicted forces"):
        binned.half_widths(ones)
    wide = fit_conformal(true, pred, rng.uniform(0.8, 1.2, 10000), 0.9, "case", scale="force_bins", bins=5)
    lo, hi = wide.stiffness_range
    in_bin = np.asarray(wide.bin_half_width_n)[wide.force_bin(p2[:2])]
    np.testing.assert_allclose(wide.half_widths(np.array([[2 * hi], [lo / 3]]), p2[:2]), [[2.0], [3.0]] * in_bin)
    np.testing.assert_allclose(wide.half_widths(np.array([[hi], [lo]]), p2[:2]), in_bin)
    # a NaN force (a refused case) falls in the last bin instead of failing
    assert binned.force_bin(np.array([[np.nan, 0.0, 0.0]]))[0] == 4


def test_scale_force_bins_uses_fewer_bins_when_too_few_cases_and_is_unbounded_below_the_minimum():
    """A bin needs min_calibration_cases cases (9 for 90 %) for a bounded quantile: 30 cases give at most 3
    bins; tied predictions that would leave a bin short give fewer; below 9 cases the interval is unbounded."""
    rng = np.random.default_rng(12)
    pred, true = _step_noise(30, rng)
    ci = fit_conformal(true, pred, np.ones(30), 0.9, "case", scale="force_bins", bins=8)
    assert len(ci.bin_half_width_n) == 3 and ci.bounded
    counts = np.bincount(ci.force_bin(pred), minlength=3)
    assert counts.min() >= min_calibration_cases(0.9) and counts.sum() == 30
    tied = np.vstack([np.tile(pred[:1], (25, 1)), pred[:5]])  # 25 equal predictions: no quantile splits them
    ci = fit_conformal(tied + 0.1, tied, np.ones(30), 0.9, "case", scale="force_bins", bins=3)
    assert len(ci.bin_half_width_n) < 3 and ci.bounded
    assert np.bincount(ci.force_bin(tied)).min() >= min_calibration_cases(0.9)
    # 60 tied of 100: the duplicate edge is dropped, and the tied cases get a bin of their own
    rng2 = np.random.default_rng(13)
    p60 = np.vstack([np.zeros((60, 3)), rng2.uniform(1.0, 5.0, (40, 3))])
    ci = fit_conformal(p60 + 0.01 * rng2.normal(size=(100, 3)), p60, np.ones(100), 0.9, "case", scale="force_bins",
                       bins=4)
    assert len(ci.bin_half_width_n) >= 2 and np.bincount(ci.force_bin(p60)).min() >= min_calibration_cases(0.9)
    assert (ci.force_bin(p60[:60]) == 0).all()
    # a calibration case the model could not predict (NaN) counts as an infinite residual in every bin: with 3 of
    # 200 the 90 % quantile of every bin stays finite, and each bin's width is not below the one without them
    p200, t200 = _step_noise(200, rng2)
    clean = fit_conformal(t200[3:], p200[3:], np.ones(197), 0.9, "case", scale="force_bins", bins=2)
    p_nan = p200.copy()
    p_nan[:3] = np.nan
    dirty = fit_conformal(t200, p_nan, np.ones(200), 0.9, "case", scale="force_bins", bins=2)
    assert dirty.bounded and len(dirty.bin_half_width_n) == 2
    assert (np.asarray(dirty.bin_half_width_n) >= np.asarray(clean.bin_half_width_n)).all()
    few = fit_conformal(true[:8], pred[:8], np.ones(8), 0.9, "case", scale="force_bins")
    assert not few.bounded and np.isinf(few.half_widths(np.ones((2, 1)), pred[:2])).all()
    assert ConformalInterval.from_dict(json.loads(json.dumps(few.to_dict()))) == few
    with pytest.raises(ValueError, match="bins"):
        fit_conformal(true, pred, np.ones(30), 0.9, "case", scale="force_bins", bins=0)


def _growing(n, rng, g, k_range=(0.7, 1.3)):
    """Calibration-like cases: stiffness factors uniform in ``k_range``, residual sd ``0.1 k^g_j`` per component."""
    k = rng.uniform(*k_range, (n, 1))
    pred = rng.normal(0.0, 1.0, (n, 3))
    return k, pred, pred + 0.1 * k ** np.asarray(g, float)[None, :] * rng.normal(size=(n, 3))


def test_fitted_widening_follows_the_residuals_growth_with_the_stiffness_and_covers_a_stiffer_liver():
    """widen: fitted: the exponent of q_90(|r_j|) ~ k^g_j is recovered from the calibration (residuals growing as
    k^1, k^0 and k^-1 per component); outside [k_lo, k_hi] the widths grow by (k / k_hi)^g_j above, (k_lo / k)^-g_j
    below, clipped to [0, 1], never narrower. Fresh cases at k = 1.8 (residual sd 0.1 k^g): the component that
    does not grow is covered near 90 % where proportional over-covers it; the widening starts from the pooled
    quantile, so a component growing as k is under-covered by both rules alike (a limit of the rule)."""
    rng = np.random.default_rng(21)
    g_true = (1.0, 0.0, -1.0)
    k, pred, true = _growing(20_000, rng, g_true)
    g = stiffness_exponent_fit(k, np.abs(true - pred), 0.9)
    np.testing.assert_allclose(g, g_true, atol=0.12)
    fitted = fit_conformal(true, pred, k, 0.9, "geometry", scale="none", widen="fitted")
    prop = fit_conformal(true, pred, k, 0.9, "geometry", scale="none")
    assert fitted.stiffness_exponent == g and prop.widen == "proportional" and prop.stiffness_exponent is None
    lo, hi = fitted.stiffness_range
    f = np.zeros((3, 3))
    kk = np.array([[1.0], [1.8], [0.35]])
    ratio = fitted.half_widths(kk, f) / fitted.half_widths(np.ones((3, 1)), f)
    np.testing.assert_allclose(ratio[0], 1.0)  # inside the range: unchanged
    gc = np.clip(g, -1.0, 1.0)
    np.testing.assert_allclose(ratio[1], (1.8 / hi) ** np.maximum(gc, 0.0))  # stiffer: the growing ones
    np.testing.assert_allclose(ratio[2], (lo / 0.35) ** np.maximum(-gc, 0.0))  # softer: the one growing there
    assert ratio[1, 0] > 1.3 and ratio[1, 1] < 1.02 and ratio[1, 2] == 1.0  # (1.8 / 1.3)^1; ~1; 1
    assert ratio[2, 0] == 1.0 and ratio[2, 1] < 1.02 and ratio[2, 2] > 1.9  # 1; ~1; 0.7 / 0.35
    assert ConformalInterval.from_dict(json.loads(json.dumps(fitted.to_dict()))) == fitted
    k_new, p_new, t_new = _growing(20_000, np.random.default_rng(22), g_true, k_range=(1.8, 1.8))
    got = coverage_per_component(t_new, p_new, fitted.half_widths(k_new, p_new))
    over = coverage_per_component(t_new, p_new, prop.half_widths(k_new, p_new))
    assert abs(got[1] - 0.9) < 0.015 and over[1] > 0.95, (got, over)  # not growing: x 1.8 / 1.3 over-covers
    assert got[2] > 0.97 and over[2] > 0.99, (got, over)  # shrinking: never narrowed, over-covers either way
    # growing as k: both widen by ~1.8 / k_hi from the pooled quantile (that of k ~ 1, below k_hi's): under-cover
    assert abs(got[0] - over[0]) < 0.02 and got[0] < 0.85, (got, over)
    # a bundle written before the key meant proportional; one material (no stiffness range): no exponent to fit
    old = {k_: v for k_, v in prop.to_dict().items() if k_ not in ("widen", "stiffness_exponent")}
    assert ConformalInterval.from_dict(old) == prop
    # one material (scenarios I, II): nothing to fit, the proportional rule; likewise too few cases for two bins
    one = fit_conformal(true[:50], pred[:50], np.ones((50, 1)), 0.9, "case", scale="none", widen="fitted")
    assert one.stiffness_exponent is None and stiffness_exponent_fit(k[:15], true[:15], 0.9) is None
    np.testing.assert_allclose(one.stiffness_factor(np.array([[1.3], [0.5]])), [[1.3], [2.0]])
    with pytest.raises(ValueError, match="widen"):
        fit_conformal(true, pred, k, 0.9, "geometry", scale="none", widen="double")


def test_the_stiffness_exponent_ignores_a_growth_the_widths_already_follow_and_survives_ties_and_zeros():
    """scale: force with errors proportional to |f| and forces growing as k: the widths already follow the growth,
    so the exponent of the scores r / sigma is ~0 (raw |r| would give ~1 and widen a stiffer liver twice). Tied
    stiffness factors (an edge at the smallest k) still give bins; a component with zero residuals gets the
    proportional 1 without touching the others."""
    rng = np.random.default_rng(31)
    n = 6000
    k = rng.uniform(0.7, 1.3, (n, 1))
    d = rng.normal(size=(n, 3))
    pred = d / np.linalg.norm(d, axis=1, keepdims=True) * 3.0 * k  # |f^| = 3 k
    true = pred + 0.05 * np.linalg.norm(pred, axis=1, keepdims=True) * rng.normal(size=(n, 3))
    raw = stiffness_exponent_fit(k, np.abs(true - pred), 0.9)
    ci = fit_conformal(true, pred, k, 0.9, "geometry", scale="force", widen="fitted")
    assert all(abs(v - 1.0) < 0.15 for v in raw), raw
    assert all(abs(v) < 0.15 for v in ci.stiffness_exponent), ci.stiffness_exponent
    binned = fit_conformal(true, pred, k, 0.9, "geometry", scale="force_bins", widen="fitted")
    assert all(abs(v) < 0.3 for v in binned.stiffness_exponent), binned.stiffness_exponent  # 5 steps of |f^|
    m = 40_000  # two bins 0.26 apart in log k: the slope's sd is ~0.04 here
    tied = np.where(np.arange(m)[:, None] < 0.6 * m, 1.0, 1.3)  # 60 % at k = 1: the 20-60 % quantiles are 1.0
    r = np.abs(rng.normal(size=(m, 3))) * tied ** np.array([0.5, 0.0, 0.0])
    r[:, 2] = 0.0
    g = stiffness_exponent_fit(tied, r, 0.9)
    assert abs(g[0] - 0.5) < 0.15 and abs(g[1]) < 0.15 and g[2] == 1.0, g


@pytest.mark.slow  # one of the default set's slowest (CI's --durations): run with -m slow
def test_calibrate_folds_recalibrates_the_same_split_model_as_a_run_with_that_fold_count(tmp_path):
    """train_scenario(calibrate_folds=(2,)) with the config's 4 folds writes the 2-fold calibration of the same
    split model: identical to the calibration of a run configured with 2 folds (the model is fitted once, the
    benchmark's --folds reads it); with final_fit on, or no interval, it refuses."""
    data = synthetic_arrays(200, seed=6, n_geometries=1, nodes=(150, 200), dent_width_mm=12.0, material_varies=True,
                            dtype=np.float64)
    iv = {"coverage": 0.9, "calibration_fraction": 0.3, "folds": 4, "scale": "none"}
    res = train_scenario(data, MODEL, {**TRAIN, "interval": iv}, NO_TUNE, "II", "v", out_dir=tmp_path / "a",
                         calibrate_folds=(2,))
    two = train_scenario(data, MODEL, {**TRAIN, "interval": {**iv, "folds": 2}}, NO_TUNE, "II", "v",
                         out_dir=tmp_path / "b")
    with np.load(tmp_path / "a" / "interval_calibration_folds2.npz") as z:
        extra = {k: z[k] for k in z.files}
    with np.load(tmp_path / "b" / "interval_calibration.npz") as z:
        ref = {k: z[k] for k in z.files}
    with np.load(tmp_path / "a" / "interval_calibration.npz") as z:
        four = {k: z[k] for k in z.files}
    assert int(extra["folds"]) == 2 and int(four["folds"]) == 4 and len(extra["pred_local"]) == res["n_train"]
    assert extra.keys() == ref.keys()
    for k in ref:
        np.testing.assert_array_equal(extra[k], ref[k])
    assert not np.array_equal(four["pred_local"], extra["pred_local"])  # other fold models, other predictions
    assert res["metrics"] == two["metrics"]  # the same split model
    with pytest.raises(ValueError, match="final_fit"):
        train_scenario(data, MODEL, {**TRAIN, "interval": iv, "final_fit": True}, NO_TUNE, "II", "v",
                       out_dir=tmp_path / "c", calibrate_folds=(2,))
    with pytest.raises(ValueError, match="interval"):
        train_scenario(data, MODEL, {**TRAIN, "interval": None}, NO_TUNE, "II", "v", out_dir=tmp_path / "d",
                       calibrate_folds=(2,))


@pytest.mark.slow  # one of the default set's slowest (CI's --durations): run with -m slow
def test_cross_conformal_calibrates_on_every_training_case_and_covers_fresh_cases(tmp_path):
    """folds: 4 -> every training case is predicted once by a model that did not see it; the 90 % interval
    covers 85-95 % of 600 fresh exchangeable cases per component."""
    kw = dict(n_geometries=1, nodes=(150, 200), dent_width_mm=12.0, material_varies=True, dtype=np.float64)
    data = synthetic_arrays(900, seed=5, **kw)
    first = subset(data, np.arange(300))
    train = {**TRAIN, "interval": {"coverage": 0.9, "calibration_fraction": 0.3, "folds": 4, "scale": "none"}}
    res = train_scenario(first, MODEL, train, NO_TUNE, "II", "v", out_dir=tmp_path)
    assert res["interval"]["folds"] == 4 and res["interval"]["n_calibration"] == res["n_train"]
    model = ForceModel.load(res["model_path"])
    # the calibration predictions are kept next to the model: the same interval refits from them, another scale too
    with np.load(tmp_path / "interval_calibration.npz") as z:
        cal = {k: z[k] for k in z.files}
    assert len(cal["pred_local"]) == res["n_train"] and int(cal["folds"]) == 4
    assert interval_from_calibration(cal, train["interval"], "II") == model.interval
    binned = interval_from_calibration(cal, {**train["interval"], "scale": "force_bins", "bins": 2}, "II")
    assert binned.scale == "force_bins" and len(binned.bin_half_width_n) == 2
    fresh = subset(data, np.arange(300, 900))
    got = model.predict_interval(fresh, observation_seed=777)
    R = local_rotations(fresh["frame_normal"], fresh["frame_t1"], fresh["frame_t2"])
    cov = coverage_per_component(force_to_local(fresh["force_n"], R), got["force_local_n"], got["half_width_local_n"])
    n_cal = res["interval"]["n_calibration"]
    sd = np.sqrt(0.9 * 0.1 / (n_cal + 2) + 0.9 * 0.1 / len(fresh["force_n"]))
    assert all(abs(c - 0.9) <= 2.5 * sd for c in cov), (cov, sd)
    np.testing.assert_allclose(got["half_width_local_n"], np.tile(model.interval.half_width_n, (600, 1)))
    # a bundle of format 9 (before the force scale) holds no force_scale: it loads and computes the same widths
    path = model.save(tmp_path / "v9")
    doc = json.loads((path / "model.json").read_text())
    assert doc["meta"]["interval"].pop("force_scale") is None
    doc["format_version"] = 9
    (path / "model.json").write_text(json.dumps(doc))
    old = ForceModel.load(path).predict_interval(fresh, observation_seed=777)
    np.testing.assert_array_equal(old["half_width_local_n"], got["half_width_local_n"])
