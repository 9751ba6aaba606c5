"""Calibrated intervals per local force component (split conformal, liverforce.learn.interval)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from liverforce.learn.frames import force_to_local, local_rotations
from liverforce.learn.interval import ConformalInterval, coverage_per_component, fit_conformal, min_calibration_cases
from liverforce.learn.model import ForceModel, subset
from liverforce.learn.synthetic import synthetic_arrays
from liverforce.learn.train import train_scenario

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
        fit_conformal(r, np.zeros_like(r), k, 0.9, "case", scale="force")


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
    fresh = subset(data, np.arange(300, 900))
    got = model.predict_interval(fresh, observation_seed=777)
    R = local_rotations(fresh["frame_normal"], fresh["frame_t1"], fresh["frame_t2"])
    cov = coverage_per_component(force_to_local(fresh["force_n"], R), got["force_local_n"], got["half_width_local_n"])
    n_cal = res["interval"]["n_calibration"]
    sd = np.sqrt(0.9 * 0.1 / (n_cal + 2) + 0.9 * 0.1 / len(fresh["force_n"]))
    assert all(abs(c - 0.9) <= 2.5 * sd for c in cov), (cov, sd)
    np.testing.assert_allclose(got["half_width_local_n"], np.tile(model.interval.half_width_n, (600, 1)))
