"""The far widths' Mondrian factors (liverforce.learn.interval.mondrian_factors, benchmarks/experiment_far_interval.py):
each group's split-conformal quantile, and on exchangeable scores they bring each group's coverage to the nominal
one."""
from __future__ import annotations

import math

import numpy as np
import pytest

from liverforce.learn.interval import mondrian_factors


def test_each_groups_factor_is_its_own_conformal_quantile_and_covers_it():
    rng = np.random.default_rng(0)
    n = 4000
    far = rng.random(n) < 0.1
    scale = np.where(far, 1.8, 0.9)[:, None]  # the far cases' scores larger, as the calibration's are
    s = np.abs(rng.normal(size=(n, 3))) * scale
    fk, nk = mondrian_factors(s, far, 0.9)
    k = math.ceil((far.sum() + 1) * 0.9)
    np.testing.assert_array_equal(fk, np.sort(s[far], axis=0)[k - 1])
    assert (fk > nk).all()
    fresh_far = rng.random(n) < 0.1
    t = np.abs(rng.normal(size=(n, 3))) * np.where(fresh_far, 1.8, 0.9)[:, None]
    for grp, fac in ((fresh_far, fk), (~fresh_far, nk)):
        cov = (t[grp] <= fac).mean(axis=0)
        assert np.all(np.abs(cov - 0.9) < 0.04)  # binomial sd on ~400 far cases: 1.5 points
    assert (t[fresh_far] <= 1.0).mean() < 0.6  # without the factor the far cases are under-covered


def test_a_group_too_small_to_bound_the_quantile_gets_an_unbounded_factor():
    s = np.ones((20, 3))
    far = np.zeros(20, dtype=bool)
    far[:3] = True
    fk, nk = mondrian_factors(s, far, 0.9)
    assert np.isinf(fk).all() and np.isfinite(nk).all()


def _cal(n=600, seed=1):
    """A calibration of ``n`` cases whose far fifth (by distance) errs twice as much."""
    rng = np.random.default_rng(seed)
    d = rng.gamma(3.0, 0.1, n)
    far = d > np.quantile(d, 0.8)
    pred = rng.normal(size=(n, 3))
    err = rng.normal(size=(n, 3)) * np.where(far, 0.4, 0.2)[:, None]
    return {"true_local": pred + err, "pred_local": pred, "stiffness": np.ones((n, 1)), "input_distance": d}


def test_far_widths_are_each_groups_conformal_factor_over_the_one_width():
    from liverforce.learn.interval import fit_conformal, with_far_widths

    cal = _cal(2000)
    ci = fit_conformal(cal["true_local"], cal["pred_local"], cal["stiffness"], 0.9, "geometry", scale="none")
    line = float(np.quantile(cal["input_distance"], 0.8))  # the served model's threshold: here the same rule
    wide = with_far_widths(ci, cal, threshold=line, quantile=0.8)
    s = np.abs(cal["true_local"] - cal["pred_local"]) / ci.half_widths(cal["stiffness"])
    fk, nk = mondrian_factors(s, cal["input_distance"] > line, 0.9)
    np.testing.assert_allclose(wide.far_factor, fk)
    np.testing.assert_allclose(wide.near_factor, nk)
    assert (np.asarray(wide.far_factor) > 1.2).all() and (np.asarray(wide.near_factor) < 1.0).all()
    h = wide.half_widths(np.ones((3, 1)), distance=np.array([0.5 * line, 2.0 * line, np.nan]))
    np.testing.assert_allclose(h[0], np.asarray(ci.half_width_n) * nk)
    np.testing.assert_allclose(h[1], np.asarray(ci.half_width_n) * fk)
    assert np.isnan(h[2]).all()  # no distance, no width
    # on fresh cases drawn alike, each group is covered near the nominal 90 %, which the one width misses
    new = _cal(4000, seed=7)
    far = new["input_distance"] > line
    r = np.abs(new["true_local"] - new["pred_local"])
    inside = r <= wide.half_widths(np.ones((4000, 1)), distance=new["input_distance"])
    one = r <= ci.half_widths(np.ones((4000, 1)))
    assert np.all(np.abs(inside[far].mean(0) - 0.9) < 0.04) and np.all(np.abs(inside[~far].mean(0) - 0.9) < 0.03)
    assert (one[far].mean(0) < 0.8).all()
    with pytest.raises(ValueError, match="input distance"):
        wide.half_widths(np.ones((3, 1)))


def test_far_widths_round_trip_and_a_damaged_record_is_refused():
    from liverforce.learn.interval import ConformalInterval, fit_conformal, with_far_widths

    cal = _cal()
    ci = fit_conformal(cal["true_local"], cal["pred_local"], cal["stiffness"], 0.9, "geometry", scale="none")
    wide = with_far_widths(ci, cal, threshold=0.33, quantile=0.8)
    assert ConformalInterval.from_dict(wide.to_dict()) == wide
    assert ConformalInterval.from_dict(ci.to_dict()) == ci and not ci.uses_distance  # a bundle before them
    bad = {**wide.to_dict(), "near_factor": None}
    with pytest.raises(ValueError, match="far widths need far_threshold"):
        ConformalInterval.from_dict(bad)


def test_a_calibration_too_small_for_a_group_keeps_the_one_width_and_says_so():
    from liverforce.learn.interval import fit_conformal, with_far_widths
    from liverforce.learn.train import far_widths

    cal = _cal(40)
    ci = fit_conformal(cal["true_local"], cal["pred_local"], cal["stiffness"], 0.9, "geometry", scale="none")
    with pytest.raises(ValueError, match="each group needs 9"):
        with_far_widths(ci, cal, threshold=0.3, quantile=0.9)  # 4 far cases
    notes = []
    assert far_widths(ci, cal, {"threshold": 0.3, "quantile": 0.9}, {"far_widths": True}, notes) is ci
    assert notes and "no far widths" in notes[0]
    assert far_widths(ci, cal, {"threshold": 0.3, "quantile": 0.9}, {"far_widths": False}) is ci
    assert far_widths(ci, cal, None, {"far_widths": True}) is ci  # no flag (an MLP): nothing to split on


def test_a_calibration_case_without_a_distance_is_in_neither_group():
    from liverforce.learn.interval import fit_conformal, with_far_widths

    cal = _cal(600)
    ci = fit_conformal(cal["true_local"], cal["pred_local"], cal["stiffness"], 0.9, "geometry", scale="none")
    want = with_far_widths(ci, cal, threshold=0.4, quantile=0.8)
    holed = {**cal, "input_distance": np.append(cal["input_distance"], np.nan),
             "true_local": np.vstack([cal["true_local"], [[9.0, 9.0, 9.0]]]),
             "pred_local": np.vstack([cal["pred_local"], [[0.0, 0.0, 0.0]]]),
             "stiffness": np.vstack([cal["stiffness"], [[1.0]]])}
    assert with_far_widths(ci, holed, threshold=0.4, quantile=0.8) == want  # before: the NaN quantile, no far case


def test_far_widths_on_a_regressor_without_distances_are_refused_by_the_bundle(tmp_path):
    """A bundle edited to put far widths on an MLP: its interval cannot be computed, and says so on loading it."""
    from liverforce.learn.interval import fit_conformal, with_far_widths
    from liverforce.learn.model import ModelFormatError
    from liverforce.learn.synthetic import synthetic_arrays
    from liverforce.learn.train import train_scenario

    arrays = synthetic_arrays(40, n_geometries=2, seed=1, nodes=(120, 160))
    model = {"encoder": "pca", "code_size": 3, "state_vector": True, "grid_size": 6, "hidden": [8], "dropout": 0.0,
             "occlusion": {"radius_mm": 0.0, "mode": "remove"}, "noise_mm": 0.0}
    train = {"test_fraction": 0.25, "epochs": 2, "batch_size": 32, "lr": 3e-3, "weight_decay": 0.0, "seed": 0}
    tune = {"enabled": False, "trials": 1, "folds": 2, "sobol_trials": 1, "epochs": 1}
    from liverforce.learn.model import ForceModel

    m = ForceModel.load(train_scenario(arrays, model, train, tune, "III", "mlp", out_dir=tmp_path)["model_path"])
    cal = _cal()
    ci = fit_conformal(cal["true_local"], cal["pred_local"], cal["stiffness"], 0.9, "geometry", scale="none")
    m.meta["interval"] = with_far_widths(ci, cal, threshold=0.4, quantile=0.8).to_dict()
    with pytest.raises(ModelFormatError, match="far widths.*has none"):
        m.interval
