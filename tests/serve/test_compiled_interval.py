"""The fixed-topology fast path's calibrated interval (CompiledROI.predict_interval, predict_batch(with_interval=True))
equals the reference path's (ForceModel.predict_interval): the same force, and the same half-widths to rounding,
for an MLP with a width per bin of the force and for a GP ensemble whose widths read its members' spread, with the
material changed (outside the calibration's stiffness range) on the compiled context and per row."""
from __future__ import annotations

import copy

import numpy as np
import pytest

from liverforce.learn.model import ModelFormatError
from liverforce.learn.train import train_scenario
from liverforce.serve import PredictionInputError, Predictor, Preop
from tests.serve.test_compiled import TOL, frames_of

RTOL = 1e-6  # the half-widths: the reference's float32 network and its members' sd, to rounding
INTERVAL = {"coverage": 0.9, "calibration_fraction": 0.3, "scale": "force_bins", "bins": 2}


@pytest.fixture(scope="module", params=["mlp", "gp_ensemble"])
def served(request, data, configs, tmp_path_factory):
    """A node model with a calibrated interval of a width per bin of the predicted force: the MLP without force
    scaling (its stiffness factor C10 / C10_ref is not the force scaling's factor, ones) and widened in proportion
    outside the calibration's stiffness range; the GP ensemble over PCA code sizes with the force scaled by the
    stiffness, its widths scaled by the members' spread (beta 4) and widened as fitted."""
    base, train, tune = configs
    if request.param == "mlp":
        model_cfg, interval = base, {**INTERVAL, "widen": "proportional"}
    else:
        model_cfg = {**base, "regressor": "gp", "force_scaling": "stiffness",
                     "gp": {"max_points": 2000, "iterations": 100, "code_members": [2, 3, 4]}}
        interval = {**INTERVAL, "widen": "fitted", "spread": 4.0}
    res = train_scenario(data, model_cfg, {**train, "interval": interval}, tune, "III", request.param,
                         out_dir=tmp_path_factory.mktemp(f"interval-{request.param}"))
    pred = Predictor.load(res["model_path"])
    ci = pred.model.interval
    assert ci.scale == "force_bins" and len(ci.bin_half_width_n) == 2  # the force picks the width
    assert ci.uses_spread == (request.param == "gp_ensemble")
    assert ci.stiffness_range is not None
    return request.param, pred


def reference(pred, ctx, Ds):
    """``(forces (n, 3), half-widths (n, 3))`` of the reference path, one deformed ROI of ``ctx`` at a time."""
    got = [pred.model.predict_interval(ctx.to_arrays(D), rotations=ctx.rotation[None]) for D in Ds]
    return np.array([g["force_n"][0] for g in got]), np.array([g["half_width_local_n"][0] for g in got])


def test_compiled_interval_equals_the_reference(served, test_cases):
    kind, pred = served
    halves = []
    for i in range(0, len(test_cases["case_id"]), 5):
        ctx = Preop.from_arrays(test_cases, i)
        comp = pred.compile(ctx)
        Ds = frames_of(test_cases, i, 4, seed=i)
        F_ref, h_ref = reference(pred, ctx, Ds)
        plain = np.array([comp.predict(D) for D in Ds])
        plain_batch = comp.predict_batch(Ds)
        assert comp._member_head is None  # the force alone computes no members' sd
        single = [comp.predict_interval(D) for D in Ds]
        F1, h1 = np.array([f for f, _ in single]), np.array([h for _, h in single])
        Fb, hb = comp.predict_batch(Ds, with_interval=True)
        np.testing.assert_array_equal(F1, plain)  # the force is the same bits with its interval as without
        np.testing.assert_array_equal(Fb, plain_batch)
        np.testing.assert_allclose(F1, F_ref, rtol=0, atol=TOL)
        np.testing.assert_allclose(Fb, F_ref, rtol=0, atol=TOL)
        np.testing.assert_allclose(h1, h_ref, rtol=RTOL)
        np.testing.assert_allclose(hb, h_ref, rtol=RTOL)
        assert h1.shape == (len(Ds), 3) and (h1 > 0).all()
        halves.append(h_ref)
    halves = np.vstack(halves)
    assert np.ptp(halves, axis=0).max() > 1e-3  # the widths vary between rows: the force (and spread) reach them
    assert comp.interval == pred.model.interval and comp.coverage == 0.9


def test_compiled_interval_follows_the_material_outside_the_calibration_range(served, test_cases):
    """The stiffness factor is the material's C10 over the training mean (not the force scaling's factor): a
    material outside the calibration's range widens the interval, on the compiled context (with_material) and
    per row of a batch (material_params_mpa), as on the reference path."""
    kind, pred = served
    model = pred.model
    ci = model.interval
    i = 2
    ctx = Preop.from_arrays(test_cases, i)
    D = np.asarray(test_cases["roi_deformed_mm"][i])
    base = np.asarray(test_cases["material_params_mpa"][i])
    mats = base[None] * np.array([[2.2], [0.4], [1.0]])  # stiffer and softer than every calibration case, and its own
    lo, hi = ci.stiffness_range
    k = mats[:, 0] / model.pre.material_ref
    assert k[0] > hi and k[1] < lo
    widen = ci.stiffness_factor(k[:, None])
    # the widening reaches some component (widen: fitted widens only the components whose residuals grow that way)
    assert (widen[:2] > 1.01).any()
    refs = [reference(pred, ctx.with_material(m), [D]) for m in mats]
    F_ref, h_ref = np.vstack([r[0] for r in refs]), np.vstack([r[1] for r in refs])
    comp = pred.compile(ctx)
    for m, f, h in zip(mats, F_ref, h_ref):
        got_f, got_h = comp.with_material(m).predict_interval(D)
        np.testing.assert_allclose(got_f, f, rtol=0, atol=TOL)
        np.testing.assert_allclose(got_h, h, rtol=RTOL)
    # per row, on a context compiled with yet another material: each row's own stiffness factor
    comp = pred.compile(ctx).with_material(base * 1.1)
    Fb, hb = comp.predict_batch(np.stack([D] * 3), material_params_mpa=mats, with_interval=True)
    np.testing.assert_allclose(Fb, F_ref, rtol=0, atol=TOL)
    np.testing.assert_allclose(hb, h_ref, rtol=RTOL)
    # with the deformed centroids given (as predict_arrays' fast path passes them)
    Fc, hc = comp.predict_batch(np.stack([D] * 3), roi_centroid_deformed_mm=np.tile(D.mean(axis=0), (3, 1)),
                                material_params_mpa=mats, with_interval=True)
    np.testing.assert_allclose(Fc, F_ref, rtol=0, atol=TOL)
    np.testing.assert_allclose(hc, h_ref, rtol=RTOL)


def test_a_model_without_an_interval_says_so_on_the_compiled_path(trained, test_cases):
    pred = Predictor.load(trained("disp"))
    model = copy.copy(pred.model)
    model.meta = {k: v for k, v in model.meta.items() if k != "interval"}
    p = Predictor(model)
    ctx = Preop.from_arrays(test_cases, 0)
    comp = p.compile(ctx)
    D = np.asarray(test_cases["roi_deformed_mm"][0])
    assert comp.interval is None and comp.coverage is None
    with pytest.raises(ValueError, match="no calibrated interval") as ref:
        model.predict_interval(ctx.to_arrays(D))
    with pytest.raises(PredictionInputError, match=r"no calibrated interval \(trained without train.interval\)"):
        comp.predict_interval(D)
    with pytest.raises(PredictionInputError, match=r"trained without train.interval"):
        comp.predict_batch(np.stack([D, D]), with_interval=True)
    assert "trained without train.interval" in str(ref.value)
    np.testing.assert_allclose(comp.predict(D), pred.model.predict(ctx.to_arrays(D))[0], rtol=0, atol=TOL)


def test_an_interval_that_cannot_be_computed_is_refused_as_on_the_reference_path(trained, test_cases):
    """An interval scaled by the members' spread on an MLP (a bundle edited by hand): its widths cannot be computed;
    the compiled path refuses the interval in the reference path's words and still gives the force alone."""
    pred = Predictor.load(trained("disp"))
    model = copy.copy(pred.model)
    model.meta = {**model.meta, "interval": {**model.meta["interval"], "spread_beta": 4.0,
                                             "spread_median_n": [0.1, 0.1, 0.2]}}
    p = Predictor(model)
    ctx = Preop.from_arrays(test_cases, 0)
    comp = p.compile(ctx)
    D = np.asarray(test_cases["roi_deformed_mm"][0])
    with pytest.raises(ModelFormatError) as reference_error:
        model.predict_interval(ctx.to_arrays(D))
    with pytest.raises(ModelFormatError, match="its regressor is an MLP") as compiled_error:
        comp.predict_interval(D)
    assert str(compiled_error.value) == str(reference_error.value)
    np.testing.assert_allclose(comp.predict(D), pred.model.predict(ctx.to_arrays(D))[0], rtol=0, atol=TOL)
