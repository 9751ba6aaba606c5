"""Mode (b): an unordered observed cloud + the pre-operative context.

Measured on the session's small models (synthetic cases, 180-260 ROI nodes):

- deformed-height model, the simulation's deformed nodes in any order: equal to
  mode (a) to 1e-6 N (float32 network rounding);
- the same surface sampled anew (300 points): median |ΔF| 0.25 N, max 0.90 N
  over 24 cases of 1-5 N, below the model's own test MAE (1.09 N) — the
  difference is the grid's interpolation error on another sampling (denser
  clouds do not help: the model learned the interpolation bias of ~220 nodes);
- displacement model, ``approximate=True`` (normal-only estimate): the normal
  force component is within 0.06 N median (0.59 N max) of mode (a); the
  tangential components are not recovered (median 0.34 / 0.50 N, max 1.55 N off).
"""
from __future__ import annotations

import numpy as np
import pytest

from liverforce.learn.frames import local_rotations
from liverforce.serve import PredictionInputError, Predictor, Preop


def test_exact_for_a_deformed_height_model_in_any_order(trained, test_cases):
    pred = Predictor.load(trained("deformed"))
    assert pred.cloud_support == "exact"
    rng = np.random.default_rng(0)
    ref = pred.model.predict(test_cases)
    for i in range(len(ref)):
        ctx = Preop.from_arrays(test_cases, i)
        D = np.asarray(test_cases["roi_deformed_mm"][i])
        f, info = pred.predict_cloud(D[rng.permutation(len(D))], ctx, return_info=True)
        iv = info.pop("interval")  # the calibrated interval of the same force, per local component
        assert info == {"mode": "exact", "points_given": len(D), "points_used": len(D),
                        "warnings": []}  # no state vector: no context to be outside the training range
        np.testing.assert_allclose(iv["force_local_n"], ctx.frame @ f, atol=1e-9)
        np.testing.assert_allclose(f, ref[i], atol=1e-6)


def test_another_sampling_of_the_same_surface_agrees_within_the_models_error(trained, test_cases, resample):
    pred = Predictor.load(trained("deformed"))
    ref = pred.model.predict(test_cases)
    rng = np.random.default_rng(1)
    diff = np.array([np.linalg.norm(pred.predict_cloud(resample(test_cases, i)(300, rng),
                                                       Preop.from_arrays(test_cases, i)) - ref[i])
                     for i in range(len(ref))])
    mae = pred.model.meta["test_metrics"]["mae_vec"]
    assert np.median(diff) < 0.5 * mae, (np.median(diff), mae)
    assert diff.max() < 1.2  # N, on forces of 1-5 N (0.90 N seen)


def test_extra_points_off_the_roi_are_cropped(trained, test_cases):
    pred = Predictor.load(trained("deformed"))
    ctx = Preop.from_arrays(test_cases, 3)
    D = np.asarray(test_cases["roi_deformed_mm"][3])
    rng = np.random.default_rng(2)
    far = ctx.exertion_point_mm + rng.normal(scale=300.0, size=(500, 3))  # the rest of the scene
    far = far[np.linalg.norm(far - ctx.exertion_point_mm, axis=1) > 100.0]  # not on the ROI itself (radius 25 mm)
    tool = ctx.exertion_point_mm + ctx.frame[2] * rng.uniform(60, 120, size=(50, 1))  # the tool shaft above
    f, info = pred.predict_cloud(np.vstack([far, D, tool]), ctx, return_info=True)
    assert info["points_used"] == len(D)
    np.testing.assert_allclose(f, pred.predict(D, ctx), atol=1e-6)


def test_correspondence_models_need_explicit_approximation(trained, test_cases):
    pred = Predictor.load(trained("disp"))
    assert pred.cloud_support == "approximate"
    ctx = Preop.from_arrays(test_cases, 0)
    D = np.asarray(test_cases["roi_deformed_mm"][0])
    with pytest.raises(PredictionInputError, match="node correspondence.*approximate=True"):
        pred.predict_cloud(D, ctx)
    ref = pred.model.predict(test_cases)
    R = local_rotations(test_cases["frame_normal"], test_cases["frame_t1"], test_cases["frame_t2"])
    rng = np.random.default_rng(3)
    err = []
    for i in range(len(ref)):
        D = np.asarray(test_cases["roi_deformed_mm"][i])
        f, info = pred.predict_cloud(D[rng.permutation(len(D))], Preop.from_arrays(test_cases, i), approximate=True,
                                     return_info=True)
        assert info["mode"] == "approximate"
        err.append(np.abs(R[i] @ (f - ref[i])))
    err = np.array(err)
    # normal force: close (the linear force estimate C^-1 u_w of a state-vector model also reads the tangential
    # displacement, which the approximation sets to zero: a few cases move further; 0.59 N max seen)
    assert np.median(err[:, 2]) < 0.15 and err[:, 2].max() < 0.8
    assert np.median(err[:, :2]) > np.median(err[:, 2])  # tangential: not recovered (documented)


def test_cloud_in_other_units_or_frame_is_refused(trained, test_cases, resample):
    pred = Predictor.load(trained("deformed"))
    ctx = Preop.from_arrays(test_cases, 0)
    D = np.asarray(test_cases["roi_deformed_mm"][0])
    with pytest.raises(PredictionInputError, match="lie on the ROI footprint.*in mm and registered"):
        pred.predict_cloud(D * 1000, ctx)
    with pytest.raises(PredictionInputError, match="lie on the ROI footprint"):
        pred.predict_cloud(D + np.array([0.0, 0.0, 500.0]), ctx)
    # plenty of points, but only a 16 mm patch of the model's ~47 mm grid is visible
    dense = resample(test_cases, 0)(3000, np.random.default_rng(4))
    tang = (dense - ctx.exertion_point_mm) @ ctx.frame[:2].T
    with pytest.raises(PredictionInputError, match="cover only .* the observed region is too small"):
        pred.predict_cloud(dense[np.abs(tang).max(axis=1) < 8.0], ctx)
