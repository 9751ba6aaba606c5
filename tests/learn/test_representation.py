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


def test_top_sheet_interpolation_is_the_delaunay_one_on_a_height_field(arrays):
    """The synthetic ROI is a height field and its triangles are its tangent-plane Delaunay triangulation: the
    top sheet of the patch is then the points' interpolant itself."""
    top = rep(interpolation="surface")
    assert top.uses_triangles and not rep().uses_triangles and top.to_dict()["interpolation"] == "surface"
    np.testing.assert_allclose(top.features_of(arrays), rep().features_of(arrays), rtol=0, atol=1e-9)
    # the node order does not matter (the triangles follow their nodes)
    rng = np.random.default_rng(0)
    perm = dict(arrays, roi_undeformed_mm=[], roi_deformed_mm=[], roi_triangles=[])
    for u, d, t in zip(arrays["roi_undeformed_mm"], arrays["roi_deformed_mm"], arrays["roi_triangles"]):
        p = rng.permutation(len(u))
        inv = np.argsort(p)
        perm["roi_undeformed_mm"].append(u[p])
        perm["roi_deformed_mm"].append(d[p])
        perm["roi_triangles"].append(inv[t])
    np.testing.assert_allclose(top.features_of(perm), top.features_of(arrays), rtol=0, atol=1e-9)
    with pytest.raises(KeyError, match="roi_triangles"):
        top.features_of({k: v for k, v in arrays.items() if k != "roi_triangles"})
    # bundles written before the setting existed resample on the points
    d = top.to_dict()
    d.pop("interpolation")
    assert Representation.from_dict(d).interpolation == "points"


def flat_patch(half=30.0, n=31):
    """A flat, triangulated square patch (z = 0) of ``n x n`` nodes: ``(nodes, triangles)``."""
    s = np.linspace(-half, half, n)
    X, Y = np.meshgrid(s, s)
    a = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel()
    T = np.concatenate([np.column_stack([a, a + n, a + n + 1]), np.column_stack([a, a + n + 1, a + 1])])
    return np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)]), T


def test_top_sheet_interpolation_ignores_the_lobes_other_face():
    """An ROI that wraps round a thin edge: the lobe's lower face lies 8 mm under the upper one over half the
    grid and moves the other way. The top sheet reads the upper face's displacement only; the points'
    interpolant mixes the two."""
    up, T_up = flat_patch()
    s, n = np.linspace(-30, 30, 31), 31
    low = up[up[:, 1] <= 0] + [0.0, 0.0, -8.0]
    k = int((s <= 0).sum())
    b = (np.arange(k - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel() + len(up)
    T_low = np.concatenate([np.column_stack([b, b + n, b + n + 1]), np.column_stack([b, b + n + 1, b + 1])])
    U = np.vstack([up, low])
    disp_up = np.column_stack([0.1 * up[:, 0], -0.05 * up[:, 1], -np.exp(-(up[:, 0] ** 2 + up[:, 1] ** 2) / 200)])
    D = U + np.vstack([disp_up, np.tile([0.0, 0.0, 2.0], (len(low), 1))])  # the lower face moves up
    case = {"exertion_point_mm": np.zeros((1, 3)), "frame_normal": np.array([[0.0, 0.0, 1.0]]),
            "frame_t1": np.array([[1.0, 0.0, 0.0]]), "frame_t2": np.array([[0.0, 1.0, 0.0]]),
            "roi_undeformed_mm": [U], "roi_deformed_mm": [D], "roi_triangles": [np.vstack([T_up, T_low])]}
    r = rep(grid_size=7, half_width_mm=12.0, interpolation="surface")
    g = r.grid()
    want = np.column_stack([0.1 * g[:, 0], -0.05 * g[:, 1], -np.exp(-(g[:, 0] ** 2 + g[:, 1] ** 2) / 200)])
    got = r.features_of(case).reshape(3, -1).T
    # the linear parts exactly; the Gaussian to the 2 mm mesh's interpolation error
    np.testing.assert_allclose(got[:, :2], want[:, :2], atol=1e-12)
    assert np.abs(got[:, 2] - want[:, 2]).max() < 0.02
    mixed = rep(grid_size=7, half_width_mm=12.0).features_of(case).reshape(3, -1).T
    assert np.abs(mixed - want).max() > 0.5


def test_top_sheet_with_the_tool_hole_still_reads_one_face_only():
    """The tool's occlusion (remove) cuts a hole in the patch where the dent is; the hole's grid points are
    bridged from the top face's nodes alone. The lower face (shifted, so its nodes are not under the upper
    ones) must not leak in: the features equal those of the upper face by itself."""
    up, T_up = flat_patch()
    low = up + [0.7, 0.6, -8.0]
    U = np.vstack([up, low])
    T = np.vstack([T_up, T_up + len(up)])
    dent = -3.0 * np.exp(-(up[:, 0] ** 2 + up[:, 1] ** 2) / 60.0)
    D = U + np.vstack([np.column_stack([np.zeros((len(up), 2)), dent]), np.tile([0.0, 0.0, 2.0], (len(low), 1))])

    def case(U, D, T):
        return {"exertion_point_mm": np.zeros((1, 3)), "frame_normal": np.array([[0.0, 0.0, 1.0]]),
                "frame_t1": np.array([[1.0, 0.0, 0.0]]), "frame_t2": np.array([[0.0, 1.0, 0.0]]),
                "roi_undeformed_mm": [U], "roi_deformed_mm": [D], "roi_triangles": [T]}

    for radius in (0.0, 5.0, 7.0):
        r = rep(grid_size=9, half_width_mm=12.0, interpolation="surface", occlusion_radius_mm=radius)
        both = r.features_of(case(U, D, T))
        alone = r.features_of(case(up, D[: len(up)], T_up))
        np.testing.assert_allclose(both, alone, rtol=0, atol=1e-12)
    # the top-sheet nodes are chosen before the hole is cut: with the upper face's hole, the lower face's
    # nodes under it are still under the (removed) upper triangles
    from liverforce.learn.grid import top_sheet_nodes

    top = top_sheet_nodes(U, T)
    assert top[: len(up)].all() and not top[len(up):][np.abs(low[:, :2]).max(axis=1) < 29].any()


def test_a_camera_view_cone_inside_the_tool_is_refused():
    from liverforce.config import ConfigError, compose

    with pytest.raises(ConfigError, match="cone_half_angle_deg"):
        compose(["validate.camera_sensitivity.cone_half_angle_deg=[0.0,40.0]"])
    compose(["validate.camera_sensitivity.cone_half_angle_deg=[10.0,40.0]"])
