"""model.rigid_motion: remove -- the ROI's best rigid motion is not read as force; a pure indentation is kept."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from liverforce.learn.frames import case_rotations, points_to_local
from liverforce.learn.model import fit_force_model, prepare, subset
from liverforce.learn.regressor import FitParams
from liverforce.learn.representation import Representation, rigid_fit_nodes, undo_rigid_motion
from liverforce.learn.state import state_vector
from liverforce.learn.synthetic import random_rotation, synthetic_arrays

torch.set_num_threads(1)
RADIUS = 15.0


@pytest.fixture(scope="module")
def arrays():
    return synthetic_arrays(10, n_geometries=2, seed=7, nodes=(150, 220), dtype=np.float64)


def rep(mode: str, **kw) -> Representation:
    return Representation(**{"grid_size": 8, "half_width_mm": 15.0, "rigid_motion": mode,
                             "rigid_motion_radius_mm": RADIUS, **kw})


def inputs(r: Representation, arrays: dict) -> np.ndarray:
    """Grid features and state vector of every case (what the regressor is built from)."""
    return np.hstack([r.features_of(arrays), state_vector(r.state_arrays(arrays))])


def moved_roi(arrays: dict, seed: int = 0) -> dict:
    """Every case's deformed ROI (and its centroid) moved by its own rigid motion (a few degrees, a few mm)."""
    rng = np.random.default_rng(seed)
    out = dict(arrays)
    dfm = []
    for D in arrays["roi_deformed_mm"]:
        axis = rng.normal(size=3)
        angle = np.deg2rad(rng.uniform(1.0, 5.0))
        K = np.cross(np.eye(3), axis / np.linalg.norm(axis))
        A = np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K
        dfm.append(np.asarray(D, dtype=np.float64) @ A.T + rng.uniform(-4.0, 4.0, 3))
    out["roi_deformed_mm"] = dfm
    out["roi_centroid_deformed_mm"] = np.array([d.mean(axis=0) for d in dfm])
    return out


def far_at_rest(arrays: dict) -> dict:
    """The cases with the ROI nodes at least RADIUS from the exertion point at rest: a pure local indentation."""
    R = case_rotations(arrays)
    P = np.asarray(arrays["exertion_point_mm"], dtype=np.float64)
    out = dict(arrays)
    dfm = []
    for i, (U, D) in enumerate(zip(arrays["roi_undeformed_mm"], arrays["roi_deformed_mm"])):
        U = np.asarray(U, dtype=np.float64)
        far = rigid_fit_nodes(points_to_local(U, P[i], R[i]), RADIUS)
        assert far.sum() >= 10 and (~far).sum() >= 10
        D = np.array(D, dtype=np.float64)
        D[far] = U[far]
        dfm.append(D)
    out["roi_deformed_mm"] = dfm
    out["roi_centroid_deformed_mm"] = np.array([d.mean(axis=0) for d in dfm])
    return out


def test_undo_rigid_motion_recovers_the_undeformed_nodes():
    rng = np.random.default_rng(1)
    U = rng.normal(scale=30.0, size=(60, 3))
    Q, t = random_rotation(rng), rng.normal(scale=20.0, size=3)
    fit = np.arange(60) % 2 == 0
    np.testing.assert_allclose(undo_rigid_motion(U, U @ Q.T + t, fit), U, atol=1e-9)


def test_rigid_motion_of_the_roi_leaves_the_features_unchanged(arrays):
    moved = moved_roi(arrays)
    new = rep("remove")
    np.testing.assert_allclose(inputs(new, moved), inputs(new, arrays), rtol=0, atol=1e-9)
    old = rep("keep")
    assert np.abs(inputs(old, moved) - inputs(old, arrays)).max() > 0.5  # mm: the old features read the motion


@pytest.mark.parametrize("kw", [{}, {"features": "both"}, {"occlusion_radius_mm": 4.0}])
def test_pure_indentation_is_kept(arrays, kw):
    dent = far_at_rest(arrays)
    np.testing.assert_allclose(inputs(rep("remove", **kw), dent), inputs(rep("keep", **kw), dent),
                               rtol=0, atol=1e-9)
    # and the same dent with the whole ROI moved rigidly on top gives the dent alone
    np.testing.assert_allclose(inputs(rep("remove", **kw), moved_roi(dent, seed=3)),
                               inputs(rep("keep", **kw), dent), rtol=0, atol=1e-9)


def test_only_node_displacement_features_remove_rigid_motion():
    with pytest.raises(ValueError, match="rigid_motion"):
        rep("remove", features="deformed")
    with pytest.raises(ValueError, match="rigid_motion"):
        rep("remove", features="cloud")
    with pytest.raises(ValueError, match="rigid_motion"):
        rep("sometimes")
    # bundles written before the option load as 'keep'
    d = rep("keep").to_dict()
    del d["rigid_motion"], d["rigid_motion_radius_mm"]
    assert Representation.from_dict(d).rigid_motion == "keep"


def test_compiled_serving_path_equals_reference(tmp_path):
    from liverforce.serve import Predictor, Preop

    data = synthetic_arrays(60, n_geometries=2, seed=2, nodes=(150, 220), material_varies=True, dtype=np.float64)
    r = rep("remove")
    model, _ = fit_force_model(prepare(data, r, observation_seeds=[0]), r, encoder="pca", code_size=4,
                               use_state=True, hidden=[16], dropout=0.0,
                               fit=FitParams(lr=3e-3, batch_size=16, epochs=5), seed=0,
                               force_scaling="stiffness", linear_force_radius_mm=5.0)
    pred = Predictor.load(model.save(tmp_path / "model"))
    cases = moved_roi(data, seed=5)
    for i in (0, 17, 41):
        ctx = Preop.from_arrays(cases, i)
        comp = pred.compile(ctx)
        D = np.asarray(cases["roi_deformed_mm"][i], dtype=np.float64)
        Ds = np.stack([D, D + 0.3, np.asarray(data["roi_deformed_mm"][i], dtype=np.float64)])
        ref = np.array([pred.model.predict(ctx.to_arrays(x))[0] for x in Ds])
        np.testing.assert_allclose(np.array([comp.predict(x) for x in Ds]), ref, rtol=0, atol=1e-6)
        np.testing.assert_allclose(comp.predict_batch(Ds), ref, rtol=0, atol=1e-6)
        # the rigid motion does not change the force: the original and the moved ROI predict the same
        np.testing.assert_allclose(ref[0], ref[2], rtol=0, atol=1e-6)
        np.testing.assert_allclose(ref[1], ref[0], rtol=0, atol=1e-6)  # a translation is rigid too
    # the batch path with shared contexts (the predictor passes the given deformed centroids: ignored here)
    rows = subset(cases, [0, 1, 2, 3])
    np.testing.assert_allclose(pred.predict_arrays(rows, fast=True, min_group=1), pred.model.predict(rows),
                               rtol=0, atol=1e-6)
