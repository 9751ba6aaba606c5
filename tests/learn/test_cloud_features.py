"""Correspondence-free cloud features (liverforce.learn.cloud_features): invariances, recovery, noise, holes."""

import json
import math

import numpy as np
import pytest

from liverforce.learn.cloud_features import (
    CloudGridSpec,
    ReferenceSurface,
    cloud_feature_matrix,
    cloud_features,
    cloud_grid,
    references_from_arrays,
)
from liverforce.learn.observation import ObservationConfig, observe
from liverforce.learn.representation import Representation
from liverforce.learn.synthetic import random_rotation

SPEC = CloudGridSpec(grid_size=12, half_width_mm=30.0)
DEPTH, WIDTH = 5.0, 10.0  # Gaussian dent: depth and standard deviation, mm
FRAME = (np.zeros(3), np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))


def dent(u, v):
    return -DEPTH * np.exp(-(u**2 + v**2) / (2 * WIDTH**2))


def plate_points(half=50.0, n=51):
    s = np.linspace(-half, half, n)
    X, Y = np.meshgrid(s, s)
    return np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])


def dented_cloud(n, rng, noise=0.0, half=45.0):
    """n points uniform over the dented plate's footprint (a dense sample of the deformed surface)."""
    u, v = rng.uniform(-half, half, n), rng.uniform(-half, half, n)
    return np.column_stack([u, v, dent(u, v) + rng.normal(0.0, noise, n) if noise else dent(u, v)])


@pytest.fixture(scope="module")
def ref():
    return ReferenceSurface.build(plate_points(), *FRAME, SPEC)


def truth_grid(spec=SPEC):
    g = spec.grid()
    return dent(g[:, 0], g[:, 1])


def test_spec_round_trip_grid_convention_and_validation():
    s = CloudGridSpec(grid_size=9, half_width_mm=20.0, fill="nearest", min_points=2)
    d = s.to_dict()
    assert json.loads(json.dumps(d)) == d and CloudGridSpec.from_dict(d) == s
    assert np.array_equal(s.grid(), Representation(9, 20.0, features="deformed").grid())
    assert s.spacing_mm == pytest.approx(5.0) and s.n_features(True) == 162
    for bad in ({"grid_size": 2}, {"fill": "mean"}, {"min_points": 0}, {"half_width_mm": 0.0}):
        with pytest.raises(ValueError):
            CloudGridSpec(**{"grid_size": 9, "half_width_mm": 20.0, **bad})
    with pytest.raises(ValueError, match="unknown"):
        CloudGridSpec.from_dict({**d, "sigma": 1.0})


def test_independent_of_point_order_and_duplicates(ref):
    rng = np.random.default_rng(0)
    cloud = dented_cloud(3000, rng, noise=0.5)
    a = cloud_features(cloud, ref, SPEC, include_mask=True)
    b = cloud_features(cloud[rng.permutation(len(cloud))], ref, SPEC, include_mask=True)
    c = cloud_features(np.concatenate([cloud, cloud]), ref, SPEC, include_mask=True)  # every point twice
    some = cloud[rng.choice(len(cloud), 500)]  # some points repeated, several times, shuffled in
    d = cloud_features(rng.permutation(np.concatenate([cloud, some, some[:100]])), ref, SPEC, include_mask=True)
    assert np.array_equal(a, b) and np.array_equal(a, c) and np.array_equal(a, d)
    # and the grid really depends on the points: drop half of them
    assert not np.array_equal(a, cloud_features(cloud[::2], ref, SPEC, include_mask=True))


@pytest.mark.parametrize("estimator", ["linear", "mean"])
def test_dense_cloud_recovers_the_dent(ref, estimator):
    cloud = dented_cloud(40000, np.random.default_rng(1))
    for cells in (1.0, 0.6) if estimator == "linear" else (1.0,):
        spec = CloudGridSpec(12, 30.0, kernel_radius_cells=cells, estimator=estimator)
        G = cloud_grid(cloud, ref, spec)
        assert G.valid.all() and np.allclose(G.reference, 0.0)
        err = G.height.ravel() - truth_grid()
        # kernel bias ~ rho^2/16 x laplacian(dz): at the dent's centre rho^2 D / (8 s^2) (0.19 mm at one cell)
        bias = spec.kernel_radius_mm**2 * DEPTH / (8 * WIDTH**2)
        assert np.abs(err).max() < 1.15 * bias + 0.02
        assert np.sqrt(np.mean(err**2)) < 0.35 * bias + 0.01
    assert bias < 0.08 or estimator == "mean"  # the smaller kernel brings it down like rho^2


def test_rigid_motion_of_everything_leaves_features_unchanged(ref):
    rng = np.random.default_rng(2)
    cloud = dented_cloud(5000, rng, noise=0.3)
    Q, c = random_rotation(np.random.default_rng(7)), np.array([120.0, -40.0, 75.0])
    p, n, t1, t2 = FRAME
    moved = ReferenceSurface.build(plate_points() @ Q.T + c, p @ Q.T + c, Q @ n, Q @ t1, Q @ t2, SPEC)
    a = cloud_features(cloud, ref, SPEC)
    b = cloud_features(cloud @ Q.T + c, moved, SPEC)
    assert np.allclose(a, b, atol=1e-9)


def test_curved_preoperative_surface_is_subtracted():
    """An undeformed, strongly curved patch (sphere cap of radius 80 mm) gives zero height change everywhere."""
    Rs = 80.0
    s = np.linspace(-45, 45, 61)
    X, Y = np.meshgrid(s, s)
    Z = np.sqrt(Rs**2 - X**2 - Y**2) - Rs
    U = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    ref = ReferenceSurface.build(U, *FRAME, SPEC)
    rng = np.random.default_rng(3)
    u, v = rng.uniform(-40, 40, 30000), rng.uniform(-40, 40, 30000)
    cloud = np.column_stack([u, v, np.sqrt(Rs**2 - u**2 - v**2) - Rs])
    G = cloud_grid(cloud, ref, SPEC)
    assert G.valid.all() and np.abs(G.height).max() < 0.03
    assert G.reference.min() < -10.0  # the patch is far from flat


def test_noise_averages_down_with_density(ref):
    """Flat plate, noise sd 0.5 mm: the per-cell error falls like 1/sqrt(points per cell)."""
    sd = 0.5
    flat = ReferenceSurface.build(plate_points(), *FRAME, SPEC)
    err = {}
    for n in (2000, 20000, 200000):
        rng = np.random.default_rng(n)
        u, v = rng.uniform(-45, 45, n), rng.uniform(-45, 45, n)
        G = cloud_grid(np.column_stack([u, v, rng.normal(0.0, sd, n)]), flat, SPEC)
        assert G.valid.all()
        err[n] = float(np.sqrt(np.mean(G.height**2)))
        # biweight-weighted mean of the points within one spacing: sd_eff ~ 1.2 sd / sqrt(count)
        expect = 1.2 * sd / math.sqrt(np.mean(G.count))
        assert 0.6 * expect < err[n] < 1.5 * expect
    assert err[2000] > 2.5 * err[20000] > 2.5 * 2.5 * err[200000]


def test_hidden_cells_are_marked_and_filled(ref):
    rng = np.random.default_rng(4)
    cloud = dented_cloud(20000, rng)
    hole = 16.0  # the tool hides a disc of this radius
    cloud = cloud[np.hypot(cloud[:, 0], cloud[:, 1]) > hole]
    g = SPEC.grid()
    hidden = (np.hypot(g[:, 0], g[:, 1]) < hole - SPEC.kernel_radius_mm).reshape(12, 12)
    far = (np.hypot(g[:, 0], g[:, 1]) > hole + SPEC.kernel_radius_mm).reshape(12, 12)
    assert hidden.sum() >= 4
    truth = truth_grid().reshape(12, 12)
    out = {}
    for rule in ("laplace", "zero", "nearest"):
        spec = CloudGridSpec(12, 30.0, fill=rule)
        G = cloud_grid(cloud, ref, spec)
        assert not G.valid[hidden].any() and G.valid[far].all() and (G.count[hidden] == 0).all()
        assert np.isfinite(G.height).all()
        assert np.abs(G.height[far] - truth[far]).max() < 0.1
        # cells at the hole's edge see points on one side only: the local plane still gets them right
        edge = G.valid & ~far
        assert edge.any() and np.abs(G.height[edge] - truth[edge]).max() < 0.12
        out[rule] = G
    assert (out["zero"].height[~out["zero"].valid] == 0).all()
    valid_vals = out["nearest"].height[out["nearest"].valid]
    assert all(np.isclose(valid_vals, x).any() for x in out["nearest"].height[~out["nearest"].valid])
    lap = out["laplace"]
    # harmonic fill: no new extrema, and closer to the dent than "as pre-operative"
    assert lap.height[~lap.valid].min() >= lap.height[lap.valid].min() - 1e-9
    assert np.abs(lap.height[hidden] - truth[hidden]).mean() < np.abs(truth[hidden]).mean()
    # the mask channel says which cells were filled
    f = lap.features(include_mask=True)
    assert f.shape == (288,) and np.array_equal(f[144:], lap.valid.ravel().astype(float))


def test_empty_and_far_clouds(ref):
    G = cloud_grid(np.empty((0, 3)), ref, SPEC)
    assert not G.valid.any() and (G.height == 0).all() and G.n_points == 0
    far = dented_cloud(1000, np.random.default_rng(5)) + [0.0, 0.0, 80.0]  # another sheet, 80 mm away
    G = cloud_grid(far, ref, SPEC)
    assert G.n_points == 0 and not G.valid.any()


def test_camera_cloud_of_a_dented_plate_gives_the_dent_outside_the_tool():
    """End to end, no correspondence: observation model -> cloud -> grid, against the analytic dent."""
    s = np.linspace(-60, 60, 61)
    X, Y = np.meshgrid(s, s, indexing="ij")
    V0 = np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])
    a = (np.arange(60)[:, None] * 61 + np.arange(60)[None, :]).ravel()
    T = np.concatenate([np.column_stack([a, a + 61, a + 62]), np.column_stack([a, a + 62, a + 1])])
    Vd = V0 + np.column_stack([np.zeros((len(V0), 2)), dent(V0[:, 0], V0[:, 1])])
    tip = np.array([0.0, 0.0, -DEPTH])
    cfg = ObservationConfig(n_points=(20000, 20000), noise_sd_mm=0.3, tool_radius_mm=2.5, roi_radius_mm=50.0)
    ref = ReferenceSurface.build(V0, *FRAME, SPEC)
    truth = truth_grid().reshape(12, 12)
    arrays = {"roi_undeformed_mm": [V0, V0], "roi_triangles": [T, T], "exertion_point_mm": np.zeros((2, 3)),
              "frame_normal": np.tile(FRAME[1], (2, 1)), "frame_t1": np.tile(FRAME[2], (2, 1)),
              "frame_t2": np.tile(FRAME[3], (2, 1))}
    refs = references_from_arrays(arrays, SPEC)
    clouds = []
    for seed in (0, 1):
        cloud, rec = observe(Vd, T, tip, FRAME[1], cfg, seed=seed)
        assert rec.n_points == 20000
        clouds.append(cloud)
        G = cloud_grid(cloud, ref, SPEC)
        assert G.valid.mean() > 0.8
        # a 5 mm dent 10 mm wide; the discretised plate (2 mm cells) and the kernel both smooth it a little
        assert np.abs(G.height[G.valid] - truth[G.valid]).max() < 0.35
    M = cloud_feature_matrix(clouds, refs, SPEC)
    assert M.shape == (2, 144) and np.array_equal(M[0], cloud_features(clouds[0], ref, SPEC))


def folded_patch(gap=12.0, half=40.0, n=41):
    """A patch that wraps round a thin edge: the top sheet z = 0 over the whole square and, under its half
    v < 0, the other face of the lobe at z = -gap (the ROI of a point near the liver's edge)."""
    s = np.linspace(-half, half, n)
    X, Y = np.meshgrid(s, s)
    top = np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])
    a = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel()
    T = np.concatenate([np.column_stack([a, a + n, a + n + 1]), np.column_stack([a, a + n + 1, a + 1])])
    k = n // 2 + 1  # rows with v <= 0
    low = top[: k * n] + [0.0, 0.0, -gap]
    b = (np.arange(k - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel() + len(top)
    Tl = np.concatenate([np.column_stack([b, b + n, b + n + 1]), np.column_stack([b, b + n + 1, b + 1])])
    return np.vstack([top, low]), np.vstack([T, Tl])


def test_the_patch_reference_is_the_top_sheet_where_the_roi_wraps_round_an_edge():
    """The ROI of a point near a thin edge holds both faces of the lobe. The camera sees the top one; the
    patch's z-buffer reads it, and a cloud of the top sheet pushed 1 mm in reads -1 mm everywhere. The ROI
    points' interpolant cannot tell the faces apart and is off by up to the lobe's thickness."""
    V, T = folded_patch(gap=12.0)
    spec = CloudGridSpec(grid_size=12, half_width_mm=30.0)
    R = np.eye(3)
    patch = ReferenceSurface.from_patch(V, T, np.zeros(3), R, spec)
    assert np.abs(patch.raster).max() < 1e-12 and np.abs(patch.grid_height).max() < 1e-12
    points = ReferenceSurface.from_rotation(V, np.zeros(3), R, spec)
    assert points.grid_height.min() < -3.0  # the lower face leaks into the points' interpolant
    rng = np.random.default_rng(0)
    u, v = rng.uniform(-36, 36, 20000), rng.uniform(-36, 36, 20000)
    cloud = np.column_stack([u, v, np.full(u.size, -1.0)])
    G = cloud_grid(cloud, patch, spec)
    assert G.valid.all() and np.allclose(G.height, -1.0, atol=1e-9)
    assert np.abs(cloud_grid(cloud, points, spec).height + 1.0).max() > 3.0
    # both rasters on the nodes bundles before format 7 used (their features must stay bit for bit)
    for r in (patch, points):
        assert r.step == spec.spacing_mm / spec.reference_oversample and r.lo == -r.step * (r.raster.shape[0] // 2)
    # for_case dispatches on spec.reference
    assert np.array_equal(ReferenceSurface.for_case(V, T, np.zeros(3), R, spec).raster, patch.raster)
    pts = CloudGridSpec(grid_size=12, half_width_mm=30.0, reference="points")
    assert np.array_equal(ReferenceSurface.for_case(V, None, np.zeros(3), R, pts).raster, points.raster)


def test_the_patch_reference_of_a_tilted_plane_is_exact_and_fills_past_the_patch_edge():
    """A plane z = 0.3 u - 0.2 v, triangulated, in a rotated and shifted source frame: the z-buffer is the
    plane (piecewise-linear interpolation of a linear function is exact). Where the patch ends (u > 10 here),
    each raster node takes the nearest covered node's height."""
    s = np.linspace(-40, 10, 51)
    t = np.linspace(-40, 40, 81)
    X, Y = np.meshgrid(s, t)
    U = np.column_stack([X.ravel(), Y.ravel(), 0.3 * X.ravel() - 0.2 * Y.ravel()])
    n = len(s)
    a = (np.arange(len(t) - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel()
    T = np.concatenate([np.column_stack([a, a + n, a + n + 1]), np.column_stack([a, a + n + 1, a + 1])])
    Q = random_rotation(np.random.default_rng(4))
    c = np.array([5.0, -7.0, 30.0])
    spec = CloudGridSpec(grid_size=12, half_width_mm=30.0)
    ref = ReferenceSurface.from_patch(U @ Q.T + c, T, c, Q.T, spec)  # x = Q u + c, so R (x - c) = u for R = Q^T
    g = spec.grid()
    inside = g[:, 0] <= 10.0 - 1e-9
    want = 0.3 * g[:, 0] - 0.2 * g[:, 1]
    assert np.allclose(ref.grid_height.ravel()[inside], want[inside], atol=1e-9)
    axis = ref.lo + ref.step * np.arange(ref.raster.shape[0])
    jlast = np.flatnonzero(axis <= 10.0 + 1e-9)[-1]
    assert np.array_equal(ref.raster[:, jlast + 1:], np.repeat(ref.raster[:, jlast:jlast + 1],
                                                                ref.raster.shape[1] - jlast - 1, axis=1))


def test_the_patch_reference_refuses_what_it_cannot_use():
    V, T = folded_patch()
    spec = CloudGridSpec(grid_size=12, half_width_mm=30.0)
    with pytest.raises(ValueError, match="roi_triangles"):
        ReferenceSurface.for_case(V, None, np.zeros(3), np.eye(3), spec, label="case X")
    with pytest.raises(ValueError, match="index points"):
        ReferenceSurface.from_patch(V, T + len(V), np.zeros(3), np.eye(3), spec)
    with pytest.raises(ValueError, match="whole numbers"):
        ReferenceSurface.from_patch(V, T[:, :2], np.zeros(3), np.eye(3), spec)
    with pytest.raises(ValueError, match="whole numbers"):
        ReferenceSurface.from_patch(V, T + 0.5, np.zeros(3), np.eye(3), spec)
    with pytest.raises(ValueError, match="covers no point"):
        ReferenceSurface.from_patch(V + [500.0, 0.0, 0.0], T, np.zeros(3), np.eye(3), spec)
    with pytest.raises(ValueError, match="reference"):
        CloudGridSpec(grid_size=12, half_width_mm=30.0, reference="mesh")
