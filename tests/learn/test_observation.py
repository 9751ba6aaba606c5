"""Camera observation model (liverforce.learn.observation) on real geometry: plates, slabs, a sphere, a liver.

Speed is not tested here (benchmarks/bench_observation.py).
"""

import json
import math

import numpy as np
import pytest
from scipy import stats

from liverforce.learn.observation import (
    DROP_REASONS,
    VISIBLE,
    ObservationConfig,
    _streams,
    SurfaceTopology,
    case_seed,
    draw_count,
    make_view,
    observe,
    observe_many,
    surface_from_mesh,
    surface_point_displacement,
    tool_axes_from_forces,
)
from liverforce.seeds import spawn_rngs

CODE = {r: 1 + i for i, r in enumerate(DROP_REASONS)}
UP = np.array([0.0, 0.0, 1.0])
TIP = np.zeros(3)


# --------------------------------------------------------------------------
# geometry
# --------------------------------------------------------------------------


def grid_plate(xe, ye, z=0.0, up=True):
    """Rectilinear plate at height z over the cell edges xe, ye: two triangles per cell, normal +z (or -z)."""
    xe, ye = np.asarray(xe, float), np.asarray(ye, float)
    X, Y = np.meshgrid(xe, ye, indexing="ij")
    V = np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, z)])
    ny = len(ye)
    i, j = np.meshgrid(np.arange(len(xe) - 1), np.arange(ny - 1), indexing="ij")
    a = (i * ny + j).ravel()
    b, c, d = a + ny, a + ny + 1, a + 1  # (x+1, y), (x+1, y+1), (x, y+1)
    T = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    return V, (T if up else T[:, ::-1])


def box(lo, hi, n=6):
    """Closed, outward-oriented box surface, each face an n x n grid."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    Vs, Ts, off = [], [], 0
    for axis in range(3):
        u, w = [k for k in range(3) if k != axis]
        for side, val in ((0, lo[axis]), (1, hi[axis])):
            V2, T2 = grid_plate(np.linspace(lo[u], hi[u], n + 1), np.linspace(lo[w], hi[w], n + 1), up=True)
            V = np.empty_like(V2)
            V[:, u], V[:, w], V[:, axis] = V2[:, 0], V2[:, 1], val
            # plate normal is e_u x e_w; flip to point outward
            nrm = np.cross(np.eye(3)[u], np.eye(3)[w])[axis]
            outward = 1.0 if side == 1 else -1.0
            T = T2 if nrm * outward > 0 else T2[:, ::-1]
            Vs.append(V)
            Ts.append(T + off)
            off += len(V)
    V, T = np.concatenate(Vs), np.concatenate(Ts)
    # merge duplicate vertices on shared edges so the surface is closed
    key, inv = np.unique(np.round(V, 9), axis=0, return_inverse=True)
    return key, inv.ravel()[T]


def merge(*parts):
    Vs, Ts, off = [], [], 0
    for V, T in parts:
        Vs.append(V)
        Ts.append(T + off)
        off += len(V)
    return np.concatenate(Vs), np.concatenate(Ts)


def icosphere(radius=40.0, subdivisions=4):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)


def cfg(**kw):
    base = dict(cone_half_angle_deg=0.0, camera_distance_mm=(100.0, 100.0), roi_radius_mm=30.0, tool_radius_mm=0.0,
                noise_sd_mm=0.0, n_points=(3000, 3000), require_tool_visible=False)
    return ObservationConfig(**{**base, **kw})


def shadow_radius(d, r, L):
    """Shadow radius on the plane z=0 of the capsule (tip sphere centre at height r, far end at r+L) seen from
    a camera on the axis at height d: the far end's rounded cap sets it."""
    return d * r / math.sqrt((d - r - L) ** 2 - r**2)


# --------------------------------------------------------------------------
# config
# --------------------------------------------------------------------------


def test_config_round_trip_and_validation():
    c = ObservationConfig(cone_axis=[0, 1, 0], n_points=[300, 4000], noise_mode="ray")
    d = c.to_dict()
    assert json.loads(json.dumps(d)) == d
    assert ObservationConfig.from_dict(d) == c
    assert ObservationConfig.from_dict({}) == ObservationConfig()
    assert c.cone_axis == (0.0, 1.0, 0.0) and c.n_points == (300, 4000)
    with pytest.raises(ValueError, match="unknown observation setting"):
        ObservationConfig.from_dict({"noise": 1.0})
    for bad in ({"n_points": (500, 100)}, {"noise_mode": "gauss"}, {"cone_half_angle_deg": 95},
                {"camera_distance_mm": (0.5, 10)}, {"tool_radius_mm": -1}, {"cone_axis": (0, 0, 0)},
                {"tool_tilt_deg": -1.0}, {"tool_tilt_deg": 90.0}):
        with pytest.raises(ValueError):
            ObservationConfig(**bad)


def test_topology_closed_and_orientation():
    V, T = box([-50, -50, -10], [50, 50, 0])
    assert SurfaceTopology.of(T).closed
    assert not SurfaceTopology.of(grid_plate(np.linspace(0, 1, 3), np.linspace(0, 1, 3))[1]).closed
    with pytest.raises(ValueError, match="inward"):
        observe(V, T[:, ::-1], [0, 0, 0], UP, cfg(), seed=0)


# --------------------------------------------------------------------------
# (a) a flat slab seen from above
# --------------------------------------------------------------------------


def test_slab_from_above_sees_only_the_top_outside_the_tool():
    V, T = box([-50, -50, -10], [50, 50, 0], n=10)
    r, L, d, R = 3.0, 40.0, 100.0, 30.0
    c = cfg(tool_radius_mm=r, tool_shaft_length_mm=L, roi_radius_mm=R)
    cloud, rec = observe(V, T, TIP, UP, c, seed=3)
    assert rec.n_points == rec.n_target == 3000 and len(cloud) == 3000
    assert np.abs(cloud[:, 2]).max() < 1e-9  # top face only: nothing from the underside
    rho = np.hypot(cloud[:, 0], cloud[:, 1])
    rs = shadow_radius(d, r, L)
    assert rho.min() >= rs * 0.99 and rho.max() <= R + 1e-9
    assert rec.dropped["backfacing"] > 0 and rec.dropped["tool_shadow"] > 0
    assert rec.dropped["self_occluded"] == 0 and rec.dropped["out_of_view"] == 0
    # uniform over the visible annulus: share of points inside radius 15 matches the area share
    share = ((rs**2 < rho**2) & (rho < 15.0)).mean()
    expect = (15.0**2 - rs**2) / (R**2 - rs**2)
    assert abs(share - expect) < 4 * math.sqrt(expect * (1 - expect) / 3000)
    # point by point: every top point in the ROI outside the shadow is visible, every bottom point back-facing
    view = make_view(V, T, TIP, [0, 0, d], c, normal=UP)
    g = np.linspace(-29, 29, 59)
    X, Y = np.meshgrid(g, g)
    top = np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])
    top = top[np.hypot(top[:, 0], top[:, 1]) < R - 0.01]
    code = view.classify_points(top, np.tile(UP, (len(top), 1)))
    rt = np.hypot(top[:, 0], top[:, 1])
    assert (code[rt > rs * 1.01] == VISIBLE).all()
    assert (code[rt < rs * 0.99] != VISIBLE).all()
    bottom = top[np.hypot(top[:, 0], top[:, 1]) < 25] + [0, 0, -10]
    code = view.classify_points(bottom, np.tile(-UP, (len(bottom), 1)))
    assert (code == CODE["backfacing"]).all()


# --------------------------------------------------------------------------
# (b) self-occlusion: the upper plate hides part of the lower one
# --------------------------------------------------------------------------


@pytest.mark.parametrize("closed", [False, True])
def test_upper_plate_hides_lower_plate(closed):
    if closed:  # two closed slabs: only front faces are rasterised
        V, T = merge(box([-20, -20, -4], [20, 20, 0], n=8), box([-60, -60, -20], [60, 60, -10], n=12))
    else:  # two open, upward plates: every triangle occludes
        V, T = merge(grid_plate(np.linspace(-20, 20, 9), np.linspace(-20, 20, 9), 0.0),
                     grid_plate(np.linspace(-60, 60, 13), np.linspace(-60, 60, 13), -10.0))
    assert SurfaceTopology.of(T).closed == closed
    c = cfg(roi_radius_mm=80.0, n_points=(6000, 6000))
    d = 100.0
    edge = 20.0 * (d + 10.0) / d  # the upper plate's shadow on the lower plane: |x|, |y| < 22
    view = make_view(V, T, TIP, [0, 0, d], c, normal=UP)
    g = np.linspace(-59.5, 59.5, 120)
    X, Y = np.meshgrid(g, g)
    low = np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, -10.0)])
    low = low[np.linalg.norm(low, axis=1) < 79.0]
    code = view.classify_points(low, np.tile(UP, (len(low), 1)))
    cheb = np.abs(low[:, :2]).max(axis=1)
    assert (code[cheb < edge - 0.5] == CODE["self_occluded"]).all()
    assert (code[cheb > edge + 0.5] == VISIBLE).all()
    up = np.column_stack([X.ravel() / 3, Y.ravel() / 3, np.zeros(X.size)])
    assert (view.classify_points(up, np.tile(UP, (len(up), 1))) == VISIBLE).all()
    cloud, rec = observe(V, T, TIP, UP, c, seed=11)
    assert rec.n_points == 6000 and rec.dropped["self_occluded"] > 0
    lower = cloud[cloud[:, 2] < -5]
    assert len(lower) > 1000 and np.abs(lower[:, 2] + 10).max() < 1e-9
    assert np.abs(lower[:, :2]).max(axis=1).min() > edge - 0.5


# --------------------------------------------------------------------------
# (c) tool occlusion: tip sphere + shaft
# --------------------------------------------------------------------------


def test_tool_shadow_matches_the_analytic_disc():
    V, T = grid_plate(np.linspace(-40, 40, 21), np.linspace(-40, 40, 21))
    d = 100.0
    for r, L in ((2.5, 50.0), (3.0, 40.0), (4.0, 0.0)):
        c = cfg(tool_radius_mm=r, tool_shaft_length_mm=L)
        view = make_view(V, T, TIP, [0, 0, d], c, normal=UP)
        rs = shadow_radius(d, r, L)
        rho = np.linspace(0.0, 12.0, 1201)
        phi = np.linspace(0, 2 * np.pi, 13)[:-1]
        P = np.array([[q * np.cos(f), q * np.sin(f), 0.0] for q in rho for f in phi])
        code = view.classify_points(P, np.tile(UP, (len(P), 1)))
        rr = np.hypot(P[:, 0], P[:, 1])
        assert (code[rr < r] != VISIBLE).all()  # within r of the axis: always gone
        assert (code[rr < rs * 0.995] == CODE["tool_shadow"]).all()
        assert (code[rr > rs * 1.005] == VISIBLE).all()
    # a point inside the tip sphere is removed as inside the tool
    c = cfg(tool_radius_mm=3.0, tool_shaft_length_mm=40.0)
    view = make_view(V, T, TIP, [0, 0, d], c, normal=UP)
    assert view.classify_points([[0.0, 0.0, 2.0], [0.0, 0.0, 20.0]], [UP, UP]).tolist() == [CODE["inside_tool"]] * 2


def test_tilted_shaft_casts_a_strip():
    V, T = grid_plate(np.linspace(-40, 40, 21), np.linspace(-40, 40, 21))
    axis = np.array([1.0, 0.0, 1.0]) / math.sqrt(2)
    c = cfg(tool_radius_mm=2.0, tool_shaft_length_mm=40.0, roi_radius_mm=45.0)
    view = make_view(V, T, TIP, [0, 0, 100.0], c, normal=UP, tool_axis=axis)
    xs = np.linspace(3.0, 35.0, 33)
    on = np.column_stack([xs, np.zeros_like(xs), np.zeros_like(xs)])
    assert (view.classify_points(on, np.tile(UP, (len(on), 1))) == CODE["tool_shadow"]).all()
    off = np.concatenate([on + [0, 8.0, 0], on + [0, -8.0, 0], -on])
    assert (view.classify_points(off, np.tile(UP, (len(off), 1))) == VISIBLE).all()
    cloud, rec = observe(V, T, TIP, UP, c, seed=2, tool_axis=axis)
    strip = (cloud[:, 0] > 3) & (cloud[:, 0] < 35) & (np.abs(cloud[:, 1]) < 1.5)
    assert not strip.any() and rec.dropped["tool_shadow"] > 0


def test_a_tilted_tool_is_tilted_by_the_angle_at_a_random_azimuth_and_nothing_else_changes():
    """tool_tilt_deg: the tool's axis that far from the normal, towards an azimuth drawn from its own stream
    (different per seed); with the tilt 0 the cloud is bit-identical to the tool along the normal given
    explicitly; a tilted tool's shadow moves with it (it hides other points)."""
    V, T = grid_plate(np.linspace(-40, 40, 41), np.linspace(-40, 40, 41))
    base = dict(tool_radius_mm=2.5, n_points=(2000, 2000), noise_sd_mm=0.3, require_tool_visible=False)
    az = []
    for s in range(8):
        straight, rec0 = observe(V, T, TIP, UP, ObservationConfig(**base), seed=s)
        given, _ = observe(V, T, TIP, UP, ObservationConfig(**base), seed=s, tool_axis=UP)
        np.testing.assert_array_equal(straight, given)
        tilted, rec = observe(V, T, TIP, UP, ObservationConfig(**base, tool_tilt_deg=25.0), seed=s)
        a = rec.tool_axis
        assert math.degrees(math.acos(float(a @ UP))) == pytest.approx(25.0, abs=1e-9)
        np.testing.assert_array_equal(rec.camera_position_mm, rec0.camera_position_mm)  # same camera pose draw
        az.append(math.atan2(a[1], a[0]))
        assert not np.array_equal(tilted, straight)
    assert np.ptp(np.cos(az)) > 1.0  # azimuths spread round the normal
    # a range: an angle drawn between its ends per observation
    tilts = [math.degrees(math.acos(float(observe(V, T, TIP, UP, ObservationConfig(**base, tool_tilt_deg=(5.0, 30.0)),
                                                  seed=s)[1].tool_axis @ UP))) for s in range(12)]
    assert 5.0 - 1e-9 <= min(tilts) and max(tilts) <= 30.0 + 1e-9 and np.ptp(tilts) > 10.0


def test_camera_is_never_placed_inside_the_tool():
    V, T = grid_plate(np.linspace(-40, 40, 21), np.linspace(-40, 40, 21))
    c = ObservationConfig(tool_radius_mm=2.5, camera_tool_clearance_mm=5.0, n_points=(300, 300),
                          cone_half_angle_deg=5.0, require_tool_visible=False)
    for s in range(30):
        _, rec = observe(V, T, TIP, UP, c, seed=s)
        C = rec.camera_position_mm
        off_axis = math.hypot(C[0], C[1])  # tool along +z from the tip
        assert rec.camera_ok and off_axis > 2.5 + 5.0 - 1e-9
        assert 60.0 <= rec.camera_distance_mm <= 120.0 and rec.view_angle_deg <= 5.0 + 1e-9


# --------------------------------------------------------------------------
# a convex sphere: no false self-occlusion, only the cap the camera faces
# --------------------------------------------------------------------------


def test_sphere_visible_cap_and_no_false_occlusion():
    Rs = 40.0
    V, T = icosphere(Rs, 4)
    tip = np.array([0.0, 0.0, Rs])
    c = ObservationConfig(roi_radius_mm=100.0, tool_radius_mm=0.0, noise_sd_mm=0.0, n_points=(20000, 20000),
                          cone_half_angle_deg=40.0)
    for s in range(3):
        cloud, rec = observe(V, T, tip, UP, c, seed=s)
        C = rec.camera_position_mm
        assert rec.n_points == 20000
        assert rec.dropped["self_occluded"] < 0.003 * rec.candidates
        # the cap visible from C: x . C >= Rs^2, up to the polygonal approximation (facet normals are
        # within ~2 deg of the radial direction on this icosphere)
        assert (cloud @ C).min() >= Rs**2 - Rs * np.linalg.norm(C) * math.sin(math.radians(3.0))
        assert (cloud @ C / np.linalg.norm(C) > Rs**2 / np.linalg.norm(C) + 2.0).mean() > 0.9


# --------------------------------------------------------------------------
# (d) noise
# --------------------------------------------------------------------------


@pytest.mark.parametrize("mode", ["isotropic", "ray"])
def test_noise_sd_matches_config(mode):
    V, T = grid_plate(np.linspace(-40, 40, 21), np.linspace(-40, 40, 21))
    sd = 0.7
    base = dict(n_points=(20000, 20000), cone_half_angle_deg=40.0, camera_distance_mm=(60.0, 120.0))
    clean, rc = observe(V, T, TIP, UP, cfg(**base), seed=5)
    noisy, rn = observe(V, T, TIP, UP, cfg(**base, noise_sd_mm=sd, noise_mode=mode), seed=5)
    drop = lambda d: {k: v for k, v in d.items() if k != "noise_sd_mm"}  # noqa: E731
    assert drop(rc.to_dict()) == drop(rn.to_dict())  # noise has its own stream: same camera, same points
    assert (rc.noise_sd_mm, rn.noise_sd_mm) == (0.0, sd)
    e = noisy - clean
    tol = 4 * sd / math.sqrt(2 * 20000)  # ~4 standard errors of a sd estimate
    if mode == "isotropic":
        assert np.allclose(e.std(axis=0), sd, atol=tol * 1.5)
        assert np.abs(e.mean(axis=0)).max() < 4 * sd / math.sqrt(20000)
        assert abs(noisy[:, 2].std() - sd) < tol * 1.5  # measured from the plate alone
    else:
        ray = clean - rc.camera_position_mm
        ray /= np.linalg.norm(ray, axis=1, keepdims=True)
        along = np.einsum("ij,ij->i", e, ray)
        assert np.abs(e - along[:, None] * ray).max() < 1e-9
        assert abs(along.std() - sd) < tol


def test_a_noise_range_draws_one_sd_per_observation_and_nothing_else_changes():
    """noise_sd_mm = (lo, hi): each observation's sd drawn uniformly between them from a stream of its own
    (recorded); the cloud is the noise-free one plus Gaussian noise of that sd, with the same camera and points;
    a range of one value gives exactly the clouds of that single value."""
    V, T = grid_plate(np.linspace(-40, 40, 21), np.linspace(-40, 40, 21))
    base = dict(n_points=(20000, 20000), cone_half_angle_deg=40.0)
    sds = []
    for s in range(10):
        clean, rc = observe(V, T, TIP, UP, cfg(**base, noise_sd_mm=0.0), seed=s)
        noisy, rn = observe(V, T, TIP, UP, cfg(**base, noise_sd_mm=(0.4, 1.2)), seed=s)
        np.testing.assert_array_equal(rc.camera_position_mm, rn.camera_position_mm)
        assert 0.4 <= rn.noise_sd_mm <= 1.2
        e = noisy - clean
        assert np.allclose(e.std(axis=0), rn.noise_sd_mm, rtol=0.03)  # 20,000 points: ~0.5 % standard error
        sds.append(rn.noise_sd_mm)
        fixed, _ = observe(V, T, TIP, UP, cfg(**base, noise_sd_mm=(0.7, 0.7)), seed=s)
        np.testing.assert_array_equal(fixed, observe(V, T, TIP, UP, cfg(**base, noise_sd_mm=0.7), seed=s)[0])
        # the noise stream's own normals, scaled by the drawn sd (the sd comes from another stream)
        unit, _ = observe(V, T, TIP, UP, cfg(**base, noise_sd_mm=1.0), seed=s)
        np.testing.assert_allclose(e / rn.noise_sd_mm, unit - clean, rtol=0, atol=1e-12)
    assert np.ptp(sds) > 0.4 and len(set(sds)) == 10  # spread over the range, a new draw per seed
    for s in (0, 7, [3, 11]):  # the five streams before the noise level's are those of five children
        old, new = spawn_rngs(s, 5), _streams(s)
        assert [g.random() for g in old] == [g.random() for g in new[:5]]
    assert ObservationConfig(noise_sd_mm=0.5).noise_sd_mm == (0.5, 0.5)
    for bad in ((1.0, 0.5), (-0.1, 0.5), (0.5, float("inf")), (0.1, 0.2, 0.3)):
        with pytest.raises(ValueError, match="noise_sd_mm"):
            ObservationConfig(noise_sd_mm=bad)


# --------------------------------------------------------------------------
# (e) density: count range and area-uniform sampling
# --------------------------------------------------------------------------


def test_count_is_log_uniform_in_range():
    c = ObservationConfig()
    rng = np.random.default_rng(0)
    k = np.array([draw_count(rng, c) for _ in range(4000)])
    assert k.min() >= 200 and k.max() <= 20000
    lo, hi = math.log(200), math.log(20000)
    assert stats.kstest((np.log(k) - lo) / (hi - lo), "uniform").pvalue > 1e-3
    V, T = grid_plate(np.linspace(-60, 60, 31), np.linspace(-60, 60, 31))
    for s in range(4):
        cloud, rec = observe(V, T, TIP, UP, ObservationConfig(), seed=s)
        assert 200 <= rec.n_target <= 20000 and len(cloud) == rec.n_points == rec.n_target


def test_sampling_is_uniform_by_area_over_cells_of_different_sizes():
    xe = np.concatenate([-np.geomspace(30, 1, 8), [0.0], np.geomspace(1, 30, 8)])  # cells 0.5 .. 9 mm wide
    ye = np.linspace(-30, 30, 7)
    V, T = grid_plate(xe, ye)
    n = 20000
    cloud, rec = observe(V, T, TIP, UP, cfg(roi_radius_mm=50.0, n_points=(n, n), camera_distance_mm=(150.0, 150.0)),
                         seed=9)
    assert rec.n_points == n and sum(rec.dropped.values()) == 0
    ix = np.searchsorted(xe, cloud[:, 0]) - 1
    iy = np.searchsorted(ye, cloud[:, 1]) - 1
    counts = np.bincount(ix * (len(ye) - 1) + iy, minlength=(len(xe) - 1) * (len(ye) - 1))
    area = np.outer(np.diff(xe), np.diff(ye)).ravel()
    expected = n * area / area.sum()
    assert stats.chisquare(counts, expected).pvalue > 1e-4
    small, large = area < 2 * area.min(), area > 0.5 * area.max()
    ratio = (counts[small].sum() / area[small].sum()) / (counts[large].sum() / area[large].sum())
    assert 0.8 < ratio < 1.25


# --------------------------------------------------------------------------
# (f) determinism
# --------------------------------------------------------------------------


def test_same_seed_same_cloud_different_seed_different():
    V, T = grid_plate(np.linspace(-60, 60, 31), np.linspace(-60, 60, 31))
    c = ObservationConfig(n_points=(500, 5000))
    a, ra = observe(V, T, TIP, UP, c, seed=[7, 123])
    b, rb = observe(V, T, TIP, UP, c, seed=[7, 123])
    assert np.array_equal(a, b) and ra.to_dict() == rb.to_dict()
    assert json.loads(json.dumps(ra.to_dict())) == ra.to_dict()
    d, rd = observe(V, T, TIP, UP, c, seed=[7, 124])
    assert rd.camera_position_mm.tolist() != ra.camera_position_mm.tolist()
    assert len(d) != len(a) or not np.array_equal(a, d)
    from liverforce.seeds import derive

    assert case_seed(7, "II-000001") == derive(7, "observation.camera", "II-000001")
    assert case_seed(7, "II-000001") != case_seed(7, "II-000002") and case_seed(7, 3) == case_seed(7, "3")


def test_observe_many_matches_observe_and_moves_the_tip_with_the_surface():
    V, T = grid_plate(np.linspace(-60, 60, 31), np.linspace(-60, 60, 31))
    rng = np.random.default_rng(1)
    P = np.column_stack([rng.uniform(-10, 10, 3), rng.uniform(-10, 10, 3), np.zeros(3)])
    disp = []
    for p, depth in zip(P, (2.0, 4.0, 6.0)):
        u = np.zeros_like(V)
        u[:, 2] = -depth * np.exp(-np.sum((V[:, :2] - p[:2]) ** 2, axis=1) / (2 * 10.0**2))
        u[:, 0] = 0.05 * V[:, 1]  # some shear, so the tip moves sideways too
        disp.append(u)
    c = ObservationConfig(n_points=(300, 3000), tool_radius_mm=2.0)
    keys = ["c-a", "c-b", "c-c"]
    clouds, recs = observe_many(V, T, np.stack(disp), P, np.tile(UP, (3, 1)), c, seed=4, case_keys=keys)
    for i in range(3):
        tip = P[i] + surface_point_displacement(V, T, P[i:i + 1], disp[i:i + 1])[0]
        assert np.allclose(recs[i].tool_tip_mm, tip)
        one, r1 = observe(V + disp[i], T, tip, UP, c, seed=case_seed(4, keys[i]))
        assert np.array_equal(one, clouds[i]) and r1.to_dict() == recs[i].to_dict()
    # row order does not change a case's cloud
    c2, _ = observe_many(V, T, np.stack(disp)[::-1], P[::-1], np.tile(UP, (3, 1)), c, seed=4, case_keys=keys[::-1])
    assert np.array_equal(c2[2], clouds[0])


def test_surface_point_displacement_is_exact_for_linear_fields():
    V, T = grid_plate(np.linspace(-30, 30, 7), np.linspace(-30, 30, 9))
    A = np.array([[0.1, -0.2, 0.0], [0.3, 0.05, 0.0], [0.02, 0.0, -0.1]])
    u = V @ A.T + [1.0, 2.0, 3.0]
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-29, 29, 20), rng.uniform(-29, 29, 20), np.zeros(20)])
    got = surface_point_displacement(V, T, pts, [u] * 20)
    assert np.allclose(got, pts @ A.T + [1.0, 2.0, 3.0])


def test_helpers():
    pts = np.arange(30, dtype=float).reshape(10, 3)
    facets = np.array([[9, 3, 5], [5, 3, 7]])
    Vs, Ts = surface_from_mesh(pts, facets)
    assert np.array_equal(Vs, pts[[3, 5, 7, 9]]) and np.array_equal(Vs[Ts], pts[facets])
    assert np.allclose(tool_axes_from_forces([[0, 0, -3.0], [1.0, 0, 0]]), [[0, 0, 1], [-1, 0, 0]])


# --------------------------------------------------------------------------
# a procedural liver (realistic surface; no timing)
# --------------------------------------------------------------------------


def test_procedural_liver_observation():
    from liverforce.dataset.roi import local_frame, surface_graph
    from liverforce.geometry.procedural import LiverShapeParams, procedural_liver

    s = procedural_liver(0, LiverShapeParams(voxel_mm=6.0, smoothing_iterations=5))
    V, T = s.vertices, s.faces
    topo = SurfaceTopology.of(T, V)
    assert topo.closed and topo.orientation_checked
    i = int(np.argmax(V[:, 1] + 0.3 * V[:, 2]))  # an anterior-superior point
    n = local_frame(surface_graph(V, T), V[i])[2]
    c = ObservationConfig(n_points=(2000, 2000))
    for seed in range(3):
        cloud, rec = observe(V, topo, V[i], n, c, seed=seed)
        assert rec.camera_ok and rec.n_points == 2000
        assert 0.2 < rec.visible_fraction < 1.0
        assert np.linalg.norm(cloud - V[i], axis=1).max() < c.roi_radius_mm + 5 * c.noise_sd_mm[1]
        assert sum(rec.dropped.values()) + rec.n_points <= rec.candidates
    # looking from the anterior axis instead of the normal
    cloud, rec = observe(V, topo, V[i], n, ObservationConfig(cone_axis=(0, 1, 0), n_points=(500, 500)), seed=0)
    assert rec.n_points == 500
