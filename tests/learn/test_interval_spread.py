"""The interval scaled by the GP ensemble members' spread (normalised conformal, train.interval.spread)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from liverforce.learn.interval import ConformalInterval, fit_conformal
from liverforce.learn.train import interval_from_calibration


def _cases(n: int, seed: int):
    """Cases whose error sd per component is known to the 'members': true = pred + e, e ~ N(0, s), and the
    members' spread d = s times a noisy factor (the members see how hard a case is, roughly)."""
    rng = np.random.default_rng(seed)
    pred = rng.normal(0.0, 2.0, (n, 3))
    s = rng.lognormal(np.log(0.1), 0.7, (n, 3))  # the case's own error sd (N): heteroscedastic
    true = pred + rng.normal(0.0, 1.0, (n, 3)) * s
    d = s * rng.lognormal(0.0, 0.2, (n, 3)) * 0.3
    return true, pred, d


@pytest.mark.parametrize("scale", ["none", "force_bins"])
def test_the_spread_keeps_the_coverage_on_new_cases_and_narrows_the_widths_where_it_knows_the_error(scale):
    true, pred, d = _cases(2000, 0)
    k = np.ones((len(true), 1))
    plain = fit_conformal(true, pred, k, 0.9, "case", scale=scale, bins=3)
    spread = fit_conformal(true, pred, k, 0.9, "case", scale=scale, bins=3, spread=d, spread_beta=0.5)
    assert spread.uses_spread and not plain.uses_spread
    t2, p2, d2 = _cases(20000, 1)  # new cases from the same population
    k2 = np.ones((len(t2), 1))
    hs, hp = spread.half_widths(k2, p2, d2), plain.half_widths(k2, p2)
    cov_s, cov_p = (np.abs(t2 - p2) <= hs).mean(axis=0), (np.abs(t2 - p2) <= hp).mean(axis=0)
    # split conformal on 2,000 calibration cases: coverage within about 1.5 points of 90 % (3 binomial sd)
    assert np.all(np.abs(cov_s - 0.9) < 0.015), cov_s
    assert np.all(np.abs(cov_p - 0.9) < 0.015), cov_p
    assert np.all(hs.mean(axis=0) < 0.9 * hp.mean(axis=0))  # the spread tells the hard cases from the easy
    # the hardest fifth of the cases (largest error sd) and the easiest: the plain interval under-covers the one
    # (65 %) and over-covers the other (100 %); with the spread both move toward 90 % (84 %, 97 %)
    s_true = d2 / 0.3
    hard, easy = s_true > np.quantile(s_true, 0.8, axis=0), s_true < np.quantile(s_true, 0.2, axis=0)
    inside_s, inside_p = np.abs(t2 - p2) <= hs, np.abs(t2 - p2) <= hp
    assert inside_s[hard].mean() > inside_p[hard].mean() + 0.15 and inside_p[hard].mean() < 0.7
    assert inside_s[easy].mean() < inside_p[easy].mean() - 0.02 and inside_p[easy].mean() > 0.99


def test_a_large_beta_is_the_interval_without_the_spread():
    true, pred, d = _cases(500, 2)
    k = np.ones((len(true), 1))
    plain = fit_conformal(true, pred, k, 0.9, "case", scale="force_bins", bins=3)
    huge = fit_conformal(true, pred, k, 0.9, "case", scale="force_bins", bins=3, spread=d, spread_beta=1e9)
    np.testing.assert_allclose(huge.half_widths(k, pred, d), plain.half_widths(k, pred), rtol=1e-6)


def test_the_unit_is_the_spread_plus_beta_times_its_calibration_median():
    true, pred, d = _cases(400, 3)
    ci = fit_conformal(true, pred, np.ones((400, 1)), 0.9, "case", scale="none", spread=d, spread_beta=2.0)
    np.testing.assert_allclose(ci.spread_median_n, np.median(d, axis=0))
    u = d + 2.0 * np.median(d, axis=0)
    # the quantile is that of |r| / u, and the widths are it times each case's u
    np.testing.assert_allclose(ci.half_width_n, np.sort(np.abs(true - pred) / u, axis=0)[360])
    np.testing.assert_allclose(ci.half_widths(np.ones((400, 1)), pred, d), np.asarray(ci.half_width_n) * u)


def test_it_round_trips_and_an_older_bundle_reads_without_it():
    true, pred, d = _cases(300, 4)
    ci = fit_conformal(true, pred, np.ones((300, 1)), 0.9, "case", scale="force_bins", bins=2, spread=d,
                       spread_beta=4.0)
    back = ConformalInterval.from_dict(json.loads(json.dumps(ci.to_dict())))
    assert back == ci and back.spread_beta == 4.0 and len(back.spread_median_n) == 3
    old = {k: v for k, v in ci.to_dict().items() if not k.startswith("spread")}  # a format-16 bundle's interval
    assert not ConformalInterval.from_dict(old).uses_spread


def test_widths_without_the_spread_are_refused_and_a_bad_spread_is_named():
    true, pred, d = _cases(300, 5)
    k = np.ones((300, 1))
    ci = fit_conformal(true, pred, k, 0.9, "case", spread=d, spread_beta=4.0)
    with pytest.raises(ValueError, match="members' sd"):
        ci.half_widths(k, pred)
    with pytest.raises(ValueError, match="shape"):
        fit_conformal(true, pred, k, 0.9, "case", spread=d[:, :2], spread_beta=4.0)
    with pytest.raises(ValueError, match="positive"):
        fit_conformal(true, pred, k, 0.9, "case", spread=d, spread_beta=0.0)
    with pytest.raises(ValueError, match="negative"):
        fit_conformal(true, pred, k, 0.9, "case", spread=-d, spread_beta=4.0)
    with pytest.raises(ValueError, match="median sd"):
        fit_conformal(true, pred, k, 0.9, "case", spread=np.zeros_like(d), spread_beta=4.0)
    # a NaN spread (a refused case) gives no width, not a number
    assert np.isnan(ci.half_widths(k[:1], pred[:1], np.full((1, 3), np.nan))).all()


def test_the_config_and_the_calibration_decide_together():
    true, pred, d = _cases(300, 6)
    cal = {"true_local": true, "pred_local": pred, "stiffness": np.ones((300, 1)), "folds": 4, "spread_local": d}
    cfg = {"coverage": 0.9, "scale": "force_bins", "bins": 3, "widen": "fitted"}
    assert interval_from_calibration(cal, {**cfg, "spread": 4.0}, "IV").spread_beta == 4.0
    assert not interval_from_calibration(cal, {**cfg, "spread": None}, "IV").uses_spread
    assert not interval_from_calibration(cal, cfg, "IV").uses_spread  # a config before the key
    no_members = {k: v for k, v in cal.items() if k != "spread_local"}  # one GP or an MLP: nothing to scale by
    assert not interval_from_calibration(no_members, {**cfg, "spread": 4.0}, "IV").uses_spread


@pytest.fixture(scope="module")
def ensemble_model():
    """A node model whose GP is an ensemble of two code sizes (a few seconds: 12 cases), and test cases."""
    from liverforce.learn.model import fit_force_model, prepare, view_seeds
    from liverforce.learn.regressor import FitParams
    from liverforce.learn.representation import representation_from_config
    from liverforce.learn.synthetic import synthetic_arrays

    arrays = synthetic_arrays(12, n_geometries=2, seed=4, material_varies=True)
    cfg = {"grid_size": 6, "occlusion": {"radius_mm": 0.0, "mode": "remove"}, "noise_mm": 0.0}
    rep = representation_from_config(cfg, arrays)
    prep = prepare(arrays, rep, observation_seeds=view_seeds(0, 1))
    fit = FitParams(0.0, 1, 0, regressor="gp", gp_iterations=20, gp_code_members=(2, 4))
    model, _ = fit_force_model(prep, rep, encoder="pca", code_size=4, use_state=True, hidden=[], dropout=0.0,
                               fit=fit, seed=0)
    true, pred, d = _cases(300, 7)
    ci = fit_conformal(true, pred, np.ones((300, 1)), 0.9, "case", scale="force_bins", bins=2, spread=d,
                       spread_beta=4.0)
    model.meta["interval"] = ci.to_dict()
    return model, arrays


def test_an_interval_scaled_by_the_spread_on_a_regressor_without_members_is_refused_on_every_path(ensemble_model):
    """The spread is the members' sd: an ensemble of one member (or one GP, an MLP) has none. A bundle whose
    interval reads it on such a regressor is refused, in the same words, wherever the interval is read: the
    reference path said 'pass each row's members' sd (Forward.spread_local)', which its user cannot, and the
    compiled camera path's head gave one member's spread as 0 (a width of q beta m, as if calibrated so)."""
    from liverforce.learn.gp import GPEnsemble
    from liverforce.learn.model import ModelFormatError
    from liverforce.serve.compiled import regressor_head

    model, arrays = ensemble_model
    reg = model.regressor
    assert isinstance(reg, GPEnsemble) and len(reg.members) == 2
    assert reg.columns(1).tolist() == list(range(model.pre.n_inputs))
    fw = model.forward(arrays)
    got = model.predict_interval(arrays)["half_width_local_n"]
    np.testing.assert_allclose(got, model.interval.half_widths(fw.stiffness, fw.force_local, fw.spread_local))
    assert np.isfinite(got).all() and (fw.spread_local > 0).all()
    try:
        for one, what in ((GPEnsemble([reg.members[0]], [reg.columns(0)]), "a GP ensemble of one member"),
                          (reg.members[1], "one GP")):  # (member 1, code size 4, reads every input)
            model.regressor = one
            assert model.forward(arrays).spread_local is None
            for read in (lambda: model.interval, lambda: model.predict_interval(arrays)):
                with pytest.raises(ModelFormatError, match=f"its regressor is {what}, which has no members' spread"):
                    read()
        with pytest.raises(ValueError, match="one member is undefined"):
            regressor_head(GPEnsemble([reg.members[0]], [reg.columns(0)]), members=True)
    finally:
        model.regressor = reg
    # without the spread the same regressors read their interval as before
    model.meta["interval"] = {**model.meta["interval"], "spread_beta": None, "spread_median_n": None}
    model.regressor = GPEnsemble([reg.members[0]], [reg.columns(0)])
    try:
        assert np.isfinite(model.predict_interval(arrays)["half_width_local_n"]).all()
    finally:
        model.regressor = reg


def test_members_that_agree_leave_the_interval_without_the_spread_and_say_so():
    true, pred, d = _cases(300, 7)
    cal = {"true_local": true, "pred_local": pred, "stiffness": np.ones((300, 1)), "folds": 4,
           "spread_local": np.zeros_like(d)}
    cfg = {"coverage": 0.9, "scale": "force_bins", "bins": 3, "widen": "fitted", "spread": 4.0}
    notes: list = []
    ci = interval_from_calibration(cal, cfg, "IV", notes)
    assert not ci.uses_spread and ci.bounded
    assert ci == interval_from_calibration(cal, {**cfg, "spread": None}, "IV")
    assert len(notes) == 1 and "without the members' spread" in notes[0] and "median sd" in notes[0]


def test_a_bundle_with_a_beta_but_no_median_is_refused_in_words():
    true, pred, d = _cases(300, 8)
    doc = fit_conformal(true, pred, np.ones((300, 1)), 0.9, "case", spread=d, spread_beta=4.0).to_dict()
    doc["spread_median_n"] = None
    with pytest.raises(ValueError, match="needs spread_median_n.*edited or damaged"):
        ConformalInterval.from_dict(doc)
