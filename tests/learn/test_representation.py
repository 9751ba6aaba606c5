"""Representation, frames and state vector: invariances and the observation model."""

import numpy as np
import pytest

from liverforce.learn.frames import force_to_local, force_to_source, local_rotations
from liverforce.learn.model import subset
from liverforce.learn.representation import Representation, fit_half_width, roi_half_extent
from liverforce.learn.state import state_names, state_vector
from liverforce.learn.synthetic import random_rotation, rigid_motion, synthetic_arrays

Q = random_rotation(np.random.default_rng(42))
C = np.array([123.0, -45.6, 78.9])


@pytest.fixture(scope="module")
def arrays():
    # float64 clouds: a float32 cloud 100+ mm from the origin carries ~1e-5 mm rounding
    return synthetic_arrays(12, n_geometries=2, seed=3, nodes=(80, 140), dtype=np.float64)


def rep(**kw) -> Representation:
    return Representation(**{"grid_size": 8, "half_width_mm": 15.0, **kw})


@pytest.mark.parametrize(
    "kw",
    [
        {},
        {"features": "both"},
        {"occlusion_radius_mm": 4.0, "occlusion_mode": "remove"},
        {"occlusion_radius_mm": 4.0, "occlusion_mode": "noise", "noise_mm": 0.2},
    ],
)
def test_features_invariant_to_rigid_motion(arrays, kw):
    moved = rigid_motion(arrays, Q, C)
    r = rep(**kw)
    a = r.features_of(arrays, observation_seed=5)
    b = r.features_of(moved, observation_seed=5)
    assert a.shape == (12, r.n_features)
    np.testing.assert_allclose(a, b, atol=1e-6)
    assert np.abs(a).max() > 0.1  # not trivially zero


def test_state_vector_and_local_force_invariant_to_rigid_motion(arrays):
    moved = rigid_motion(arrays, Q, C)
    np.testing.assert_allclose(state_vector(arrays), state_vector(moved), rtol=1e-9, atol=1e-6)
    R0 = local_rotations(arrays["frame_normal"], arrays["frame_t1"], arrays["frame_t2"])
    R1 = local_rotations(moved["frame_normal"], moved["frame_t1"], moved["frame_t2"])
    f0, f1 = force_to_local(arrays["force_n"], R0), force_to_local(moved["force_n"], R1)
    np.testing.assert_allclose(f0, f1, atol=1e-9)
    # the synthetic force pushes into the surface: negative normal component
    assert (f0[:, 2] < 0).all()
    np.testing.assert_allclose(force_to_source(f1, R1), moved["force_n"], atol=1e-9)
    assert state_vector(arrays).shape[1] == len(state_names(2))


def test_features_invariant_to_node_order(arrays):
    rng = np.random.default_rng(0)
    perm = dict(arrays)
    perm["roi_undeformed_mm"], perm["roi_deformed_mm"] = [], []
    for u, d in zip(arrays["roi_undeformed_mm"], arrays["roi_deformed_mm"]):
        p = rng.permutation(len(u))
        perm["roi_undeformed_mm"].append(u[p])
        perm["roi_deformed_mm"].append(d[p])
    for kw in ({}, {"features": "deformed"}, {"occlusion_radius_mm": 4.0}):
        r = rep(**kw)
        np.testing.assert_allclose(r.features_of(arrays), r.features_of(perm), atol=1e-9)
    np.testing.assert_allclose(roi_half_extent(arrays), roi_half_extent(perm))


def test_remove_occlusion_uses_visible_nodes_only(arrays):
    r = rep(occlusion_radius_mm=5.0, occlusion_mode="remove")
    tampered = dict(arrays)
    tampered["roi_deformed_mm"] = []
    R = local_rotations(arrays["frame_normal"], arrays["frame_t1"], arrays["frame_t2"])
    for i, (u, d) in enumerate(zip(arrays["roi_undeformed_mm"], arrays["roi_deformed_mm"])):
        loc = (u - arrays["exertion_point_mm"][i]) @ R[i].T
        hidden = np.hypot(loc[:, 0], loc[:, 1]) < 5.0
        assert hidden.any()
        d = d.copy()
        d[hidden] += 50.0  # whatever the tool hides must not matter
        tampered["roi_deformed_mm"].append(d)
    np.testing.assert_array_equal(r.features_of(arrays), r.features_of(tampered))
    # ... while without occlusion it does
    assert not np.allclose(rep().features_of(arrays), rep().features_of(tampered))
    # the clean features ignore the observation model
    np.testing.assert_array_equal(r.features_of(arrays, clean=True), rep().features_of(arrays))


def test_noise_is_seeded_per_case(arrays):
    r = rep(noise_mm=0.3)
    a = r.features_of(arrays, observation_seed=1)
    np.testing.assert_array_equal(a, r.features_of(arrays, observation_seed=1))
    assert not np.allclose(a, r.features_of(arrays, observation_seed=2))
    # no seed: no stochastic corruption
    np.testing.assert_array_equal(r.features_of(arrays), rep().features_of(arrays))
    # per-case draws do not depend on the row order
    rev = subset(arrays, np.arange(len(arrays["case_id"]))[::-1])
    np.testing.assert_array_equal(r.features_of(rev, observation_seed=1), a[::-1])


def test_displacement_grid_matches_the_dent():
    """Interpolated displacement at the grid equals the analytic dent (local frame) to interpolation error."""
    arrays = synthetic_arrays(3, seed=9, nodes=(600, 600), dent_width_mm=12.0, compliance_mm_per_n=(0.8, 1.5),
                              dtype=np.float64)
    r = rep(grid_size=9, half_width_mm=14.0)
    x = r.features_of(arrays).reshape(3, 3, 81)
    R = local_rotations(arrays["frame_normal"], arrays["frame_t1"], arrays["frame_t2"])
    f = force_to_local(arrays["force_n"], R)
    g = r.grid()
    G = np.exp(-(g[:, 0] ** 2 + g[:, 1] ** 2) / (2 * 12.0**2))
    expect = G[None, None, :] * (np.array([0.8, 0.8, 1.5]) * f)[:, :, None]
    # only the piecewise-linear interpolation error remains (600 random nodes leave some ~5 mm gaps)
    assert np.abs(x - expect).max() < 0.05 * np.abs(expect).max()
    assert np.abs(x - expect).mean() < 0.005 * np.abs(expect).max()


def test_half_width_is_the_median_inscribed_square(arrays):
    ext = roi_half_extent(arrays)
    assert np.all((ext > 15) & (ext <= 25.0 + 1e-9))  # ROI radius 25 mm
    assert fit_half_width(arrays) == pytest.approx(float(np.median(ext)))


def test_bad_frame_is_refused(arrays):
    bad = dict(arrays)
    bad["frame_t2"] = -np.asarray(arrays["frame_t2"])  # left-handed
    with pytest.raises(ValueError, match="right-handed"):
        rep().features_of(bad)


def test_occlusion_removing_everything_names_the_case(arrays):
    with pytest.raises(ValueError, match="S-000000.*radius_mm"):
        rep(occlusion_radius_mm=500.0).features_of(subset(arrays, [0]))


@pytest.mark.parametrize("kw", [{"noise_mm": 0.5}, {"occlusion_radius_mm": 5.0, "occlusion_mode": "remove"},
                                {"occlusion_radius_mm": 5.0, "occlusion_mode": "noise"}])
def test_an_observed_model_never_reads_the_clean_deformed_centroid(arrays, kw):
    """Under an observation model the state vector must not carry the mean of every clean ROI node (issue 18):
    moving the stored deformed centroid changes nothing, while the clean model reads it."""
    moved = dict(arrays)
    moved["roi_centroid_deformed_mm"] = np.asarray(arrays["roi_centroid_deformed_mm"]) + 3.0
    observed = rep(**kw)
    np.testing.assert_array_equal(state_vector(observed.state_arrays(arrays)), state_vector(observed.state_arrays(moved)))
    clean = rep()
    assert np.abs(state_vector(clean.state_arrays(arrays)) - state_vector(clean.state_arrays(moved))).max() > 1.0
