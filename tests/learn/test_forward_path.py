"""One forward path: the local frame of a case is computed once and passed along (issue #15).

Training (``prepare``), every prediction of a :class:`ForceModel` and the serving
context (``Preop.rotation``) each compute a case's rotation once; every later step
(observation, features, state vector, targets, force back in the source frame,
input checks, the compiled paths) receives it. The tests count the calls of
:func:`liverforce.learn.frames.local_rotations` in every module that holds it, and
check that the learning and serving sides get the same rotation, bit for bit.
"""
from __future__ import annotations

import sys

import numpy as np
import pytest
import torch

from liverforce.learn import camera, frames
from liverforce.learn.frames import case_rotations, force_to_local
from liverforce.learn.interval import fit_conformal
from liverforce.learn.model import fit_force_model, prepare, subset
from liverforce.learn.regressor import FitParams
from liverforce.learn.representation import representation_from_config
from liverforce.learn.synthetic import random_rotation, synthetic_arrays, synthetic_surface_arrays
from liverforce.serve import Predictor
from liverforce.serve.errors import PredictionInputError
from liverforce.serve.preop import Preop

torch.set_num_threads(1)

MODEL = {"grid_size": 6, "occlusion": {"radius_mm": 3.0, "mode": "noise"}, "noise_mm": 0.1}


@pytest.fixture
def count_rotations(monkeypatch):
    """Count every call of ``local_rotations`` (patched in each ``liverforce`` module that imported it)."""
    calls = []
    original = frames.local_rotations

    def counted(*args, **kw):
        calls.append(1)
        return original(*args, **kw)

    for name, mod in list(sys.modules.items()):
        if name.startswith("liverforce") and getattr(mod, "local_rotations", None) is original:
            monkeypatch.setattr(mod, "local_rotations", counted)

    class Counter:
        def __call__(self) -> int:
            n = len(calls)
            calls.clear()
            return n

    return Counter()


@pytest.fixture(scope="module")
def data():
    return synthetic_arrays(40, n_geometries=2, seed=4, nodes=(150, 200), material_varies=True)


@pytest.fixture(scope="module")
def model(data):
    """A small state-vector model (PCA, linear force estimate, force scaling) with a calibrated interval."""
    rep = representation_from_config(MODEL, data)
    prep = prepare(data, rep, observation_seeds=[1, 2])
    m, _ = fit_force_model(prep, rep, encoder="pca", code_size=4, use_state=True, hidden=[16], dropout=0.0,
                           fit=FitParams(epochs=5, lr=3e-3, batch_size=16), seed=0, force_scaling="stiffness",
                           linear_force_radius_mm=5.0)
    f = m.predict_local(data, observation_seed=3)
    ci = fit_conformal(prep.y_local, f, m.pre.stiffness(prep.state, len(f)), 0.8, "case")
    m.meta["interval"] = ci.to_dict()
    return m


def test_prepare_computes_the_local_frame_once(data, count_rotations):
    rep = representation_from_config(MODEL, data)
    assert rep.occludes and rep.stochastic  # two views + the clean features + the state vector + the targets
    count_rotations()
    prep = prepare(data, rep, observation_seeds=[1, 2])
    assert count_rotations() == 1
    np.testing.assert_array_equal(prep.R, case_rotations(data))


def test_each_prediction_computes_the_local_frame_once(data, model, count_rotations):
    count_rotations()
    f = model.predict(data, observation_seed=3)
    assert count_rotations() == 1
    model.predict_local(data, observation_seed=3)
    assert count_rotations() == 1
    iv = model.predict_interval(data, observation_seed=3)
    assert count_rotations() == 1
    np.testing.assert_array_equal(iv["force_n"], f)
    # rotations the caller already holds are used as given, not computed again
    R = case_rotations(data)
    count_rotations()
    np.testing.assert_array_equal(model.predict(data, observation_seed=3, rotations=R), f)
    assert count_rotations() == 0


def test_the_given_rotations_are_the_ones_used(data, model):
    """The forward path reads the rotations it is handed: a different frame gives a different local force."""
    a = subset(data, np.arange(6))
    R = case_rotations(a)
    Q = random_rotation(np.random.default_rng(0))
    fw = model.forward(a, rotations=R)
    turned = model.forward(a, rotations=R @ Q.T)
    np.testing.assert_array_equal(fw.R, R)
    assert np.abs(turned.force_local - fw.force_local).max() > 1e-3
    np.testing.assert_allclose(force_to_local(fw.force_source, R), fw.force_local, atol=1e-12)
    with pytest.raises(ValueError, match="one 3 x 3 rotation per case"):
        model.forward(a, rotations=R[:5])


def test_serving_context_rotation_equals_the_learning_side(data):
    R = case_rotations(data)
    for i in range(len(data["case_id"])):
        ctx = Preop.from_arrays(data, i)
        np.testing.assert_array_equal(ctx.rotation, R[i])
        np.testing.assert_array_equal(ctx.rotation, case_rotations(ctx.to_arrays(ctx.roi_undeformed_mm))[0])
    # and after a round trip through the context's JSON form
    back = Preop.from_dict(Preop.from_arrays(data, 3).to_dict())
    np.testing.assert_array_equal(back.rotation, R[3])


def test_a_bad_frame_is_refused_when_the_context_is_used(data):
    ctx = Preop.from_arrays(data, 0)
    bad = Preop(ctx.exertion_point_mm, ctx.frame * np.array([[1.0], [1.3], [1.0]]), ctx.roi_undeformed_mm)
    with pytest.raises(PredictionInputError, match="not orthonormal"):
        bad.rotation


def test_serving_computes_the_context_frame_once(data, model, count_rotations):
    pred = Predictor(model)
    ctx = Preop.from_arrays(data, 0)
    D = data["roi_deformed_mm"][0]
    count_rotations()
    f = pred.predict(D, ctx)  # checks, features, state vector, force back in the liver frame
    assert count_rotations() == 1
    np.testing.assert_array_equal(f, model.predict(ctx.to_arrays(D))[0])
    count_rotations()
    pred.predict(D, ctx)
    pred.interval(D, ctx)
    pred.predict_cloud(np.asarray(D)[::-1], ctx, approximate=True)
    pred.compile(ctx).predict(D)
    assert count_rotations() == 0  # the same context: its rotation is already known
    rows = subset(data, np.arange(5))
    got = pred.predict_arrays(rows)
    assert count_rotations() == 5  # one per row, in its input check; the model reuses them
    np.testing.assert_array_equal(got, model.predict(rows))


def test_camera_model_prepare_computes_the_local_frame_once(count_rotations, monkeypatch):
    arrays = synthetic_surface_arrays(6, n_geometries=1, seed=2, n_vertices=1500)
    cfg = {"grid_size": 6, "roi_features": "cloud", "occlusion": {"radius_mm": 0.0}, "noise_mm": 0.0,
           "camera": {"observation": {"n_points": [300, 600], "noise_sd_mm": 0.2}, "grid": {}, "tip_noise_mm": 0.1}}
    rep = representation_from_config(cfg, arrays)
    monkeypatch.setattr(camera, "_CACHE", {})  # observe every case here, not from another test's memo
    count_rotations()
    prep = prepare(arrays, rep, observation_seeds=[1, 2])  # per view: a reference surface per case, the tip
    assert count_rotations() == 1
    assert np.isfinite(prep.x_obs).all()
