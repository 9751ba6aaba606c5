"""The linear force estimate f_lin = C^-1 u_w of state-vector models (liverforce.learn.model).

u_w is read from the model's own grid features (what is observed, after occlusion
and noise), C from the state vector (the pre-operative stiffness probe).
"""
from __future__ import annotations

import numpy as np
import pytest

from liverforce.learn.frames import force_to_local, local_rotations
from liverforce.learn.model import Preprocessor, indentation_strain_of, linear_force_radius_of, linear_force_weights
from liverforce.learn.representation import Representation
from liverforce.learn.state import state_vector
from liverforce.learn.synthetic import synthetic_arrays


def _pre(rep: Representation, radius: float) -> Preprocessor:
    return Preprocessor(None, None, None, None, None, None, linear_force_weights(rep, radius))


def test_a_uniform_displacement_gives_the_force_exactly():
    """A dent much wider than the ROI moves every node by C f: then u_w = C f and f_lin = f (local frame)."""
    a = synthetic_arrays(12, n_geometries=3, seed=4, dent_width_mm=1e5, compliance_mm_per_n=(0.7, 1.9),
                         dtype=np.float64)
    rep = Representation(grid_size=9, half_width_mm=15.0)
    f_lin = _pre(rep, 5.0).linear_force(rep.features_of(a, clean=True), state_vector(a))
    R = local_rotations(a["frame_normal"], a["frame_t1"], a["frame_t2"])
    np.testing.assert_allclose(f_lin, force_to_local(a["force_n"], R), rtol=1e-6, atol=1e-9)


def test_it_reads_only_what_is_observed():
    """Under `remove` occlusion, moving the hidden nodes under the tool leaves f_lin unchanged; moving visible
    nodes changes it (no clean information leaks into the estimate)."""
    a = synthetic_arrays(6, seed=5, dtype=np.float64)
    rep = Representation(grid_size=9, half_width_mm=15.0, occlusion_radius_mm=4.0)
    pre = _pre(rep, 5.0)
    s = state_vector(a)
    base = pre.linear_force(rep.features_of(a), s)
    R = local_rotations(a["frame_normal"], a["frame_t1"], a["frame_t2"])
    hidden, visible = dict(a), dict(a)
    hidden["roi_deformed_mm"], visible["roi_deformed_mm"] = [], []
    for i, (und, dfm) in enumerate(zip(a["roi_undeformed_mm"], a["roi_deformed_mm"])):
        loc = (und - a["exertion_point_mm"][i]) @ R[i].T
        under = np.hypot(loc[:, 0], loc[:, 1]) < 4.0
        assert under.any()
        h, v = dfm.copy(), dfm.copy()
        h[under] += 3.0 * R[i][2]  # 3 mm along the normal, hidden by the tool
        v[~under & (np.hypot(loc[:, 0], loc[:, 1]) < 8.0)] += 3.0 * R[i][2]
        hidden["roi_deformed_mm"].append(h)
        visible["roi_deformed_mm"].append(v)
    np.testing.assert_allclose(pre.linear_force(rep.features_of(hidden), s), base, atol=1e-12)
    assert np.abs(pre.linear_force(rep.features_of(visible), s) - base).max() > 0.1


def test_which_models_carry_it():
    assert linear_force_radius_of({"state_vector": True, "probe_force_radius_mm": 5.0}) == 5.0
    assert linear_force_radius_of({"state_vector": False, "probe_force_radius_mm": 5.0}) == 0.0
    assert linear_force_radius_of({"state_vector": True, "roi_features": "deformed", "probe_force_radius_mm": 5.0}) == 0
    assert linear_force_radius_of({"state_vector": True, "probe_force_radius_mm": 0.0}) == 0.0
    # the indentation strain reads the same u_w: only with the linear force estimate
    assert indentation_strain_of({"state_vector": True, "probe_force_radius_mm": 5.0, "indentation_strain": True})
    assert not indentation_strain_of({"state_vector": True, "probe_force_radius_mm": 5.0, "indentation_strain": False})
    assert not indentation_strain_of({"state_vector": False, "probe_force_radius_mm": 5.0, "indentation_strain": True})
    assert not indentation_strain_of({"state_vector": True, "probe_force_radius_mm": 0.0, "indentation_strain": True})


def test_fit_refuses_it_without_displacement_features():
    from liverforce.learn.model import fit_preprocessor, prepare

    a = synthetic_arrays(30, seed=6, dtype=np.float64)
    rep = Representation(grid_size=6, half_width_mm=15.0, features="deformed")
    prep = prepare(a, rep, observation_seeds=[0])
    with pytest.raises(ValueError, match="displacement features"):
        fit_preprocessor(prep, rep, encoder="pca", code_size=3, use_state=True, seed=0, epochs=1, lr=1e-3,
                         batch_size=8, linear_force_radius_mm=5.0)


def test_fit_refuses_the_indentation_strain_without_the_linear_force_estimate():
    from liverforce.learn.model import fit_preprocessor, prepare

    a = synthetic_arrays(30, seed=6, dtype=np.float64)
    rep = Representation(grid_size=6, half_width_mm=15.0)
    prep = prepare(a, rep, observation_seeds=[0])
    with pytest.raises(ValueError, match="indentation strain .*probe_force_radius_mm"):
        fit_preprocessor(prep, rep, encoder="pca", code_size=3, use_state=True, seed=0, epochs=1, lr=1e-3,
                         batch_size=8, indentation_strain=True)
