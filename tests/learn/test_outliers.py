"""A camera's gross depth errors: observed (observation.outlier_fraction) and dropped (camera.grid.outlier_mm).

A stereo reconstruction puts some points at a wrong depth on their own line of sight (a specular highlight, a
texture-less patch, a pixel at a depth edge). The observation model can add such outliers; the cloud grid can drop
the points that lie farther than ``outlier_mm`` from the plane fitted at their nearest grid point and fit the
planes, and the dent, again without them. The compiled serving pass does the same as the reference.
"""

from __future__ import annotations

import numpy as np
import pytest

from liverforce.learn.cloud_features import CloudGridSpec, ReferenceSurface, cloud_grid
from liverforce.learn.observation import ObservationConfig, observe
from liverforce.learn import camera
from tests.learn.test_dent import R_TOOL, plate, spec

CFG = dict(n_points=(4000, 4000), noise_sd_mm=0.5, roi_radius_mm=30.0, tool_radius_mm=R_TOOL,
           instrument_in_cloud=True)


def test_outliers_move_that_share_of_the_points_along_their_line_of_sight_and_nothing_else():
    V, _, T = plate(3.0)
    tip = np.array([0.0, 0.0, -3.0])
    clean, rec0 = observe(V, T, tip, [0, 0, 1], ObservationConfig(**CFG), seed=5)
    cfg = ObservationConfig(**CFG, outlier_fraction=0.05, outlier_range_mm=8.0)
    dirty, rec = observe(V, T, tip, [0, 0, 1], cfg, seed=5)
    again, _ = observe(V, T, tip, [0, 0, 1], cfg, seed=5)
    np.testing.assert_array_equal(dirty, again)  # seeded
    assert rec0.n_outliers == 0 and rec.n_outliers == round(0.05 * len(clean)) > 0
    moved = np.flatnonzero(np.any(dirty != clean, axis=1))
    assert moved.size == rec.n_outliers  # every other point is the clean cloud's, bit for bit
    d = dirty[moved] - clean[moved]
    ray = clean[moved] - rec.camera_position_mm
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    along = np.einsum("ij,ij->i", d, ray)
    np.testing.assert_allclose(np.cross(d, ray), 0.0, atol=1e-9)  # along the line of sight
    assert np.abs(along).max() <= 8.0 and np.abs(along).max() > 6.0
    assert abs(np.mean(along)) < 1.5  # both ways


def test_the_outlier_stream_is_a_seventh_child_and_leaves_the_six_before_it():
    from liverforce.learn.observation import _streams
    from liverforce.seeds import spawn_rngs

    for s in (0, 7, [3, 11]):
        old, new = spawn_rngs(s, 6), _streams(s)
        assert len(new) == 7
        for a, b in zip(old, new[:6]):
            np.testing.assert_array_equal(a.random(5), b.random(5))


@pytest.mark.parametrize("bad", [dict(outlier_fraction=-0.1), dict(outlier_fraction=0.6),
                                 dict(outlier_range_mm=0.0)])
def test_impossible_outlier_settings_are_refused(bad):
    with pytest.raises(ValueError, match=list(bad)[0]):
        ObservationConfig(**bad)


def test_a_negative_outlier_threshold_is_refused():
    with pytest.raises(ValueError, match="outlier_mm"):
        CloudGridSpec(grid_size=12, half_width_mm=20.0, outlier_mm=-1.0)


def _case(depth=3.0):
    V, U0, T = plate(depth)
    return V, T, ReferenceSurface.for_case(U0, T, [0, 0, 0], np.eye(3), spec()), np.array([0.0, 0.0, -depth])


def test_a_clean_cloud_loses_no_point_and_a_cloud_with_outliers_comes_back_near_the_clean_one():
    """At 0.5 mm of noise a 3 mm threshold drops nothing (the features are those without the filter, bit for bit);
    with 5 % of the points 10 mm off along their rays the heights, the dent and the tip come back to within a
    fraction of what the outliers did to them."""
    V, T, ref, tip = _case()
    on, off = spec(outlier_mm=3.0), spec()
    kin = tip + np.array([0.3, -0.2, 0.1])
    worse, better = [], []
    for seed in range(4):
        clean, _ = observe(V, T, tip, [0, 0, 1], ObservationConfig(**CFG), seed=seed)
        dirty, rec = observe(V, T, tip, [0, 0, 1], ObservationConfig(**CFG, outlier_fraction=0.05), seed=seed)
        g_clean = cloud_grid(clean, ref, off, kin)
        g_kept = cloud_grid(clean, ref, on, kin)
        assert g_kept.n_outliers == 0
        np.testing.assert_array_equal(g_kept.features(include_mask=True), g_clean.features(include_mask=True))
        np.testing.assert_array_equal(g_kept.dent, g_clean.dent)
        raw, fixed = cloud_grid(dirty, ref, off, kin), cloud_grid(dirty, ref, on, kin)
        # the outliers beyond 3 mm of the surface and in reach of a grid point: most of them
        assert 0.4 * rec.n_outliers < fixed.n_outliers <= rec.n_outliers
        worse.append(np.abs(raw.height - g_clean.height).mean())
        better.append(np.abs(fixed.height - g_clean.height).mean())
        assert abs(fixed.dent[0] - g_clean.dent[0]) < 0.5 * abs(raw.dent[0] - g_clean.dent[0]) + 0.02
    assert np.mean(better) < 0.3 * np.mean(worse), (better, worse)


def _edge_cloud(seed=0, n=4000):
    """A flat surface seen up to ``v = 0`` only (0.3 mm noise; the 12 x 12 grid's row 6, at v = 1.8 mm, has no
    valid plane) and seven flying pixels 6 mm high at ``v = 0.6`` mm, beyond the edge: their nearest grid point is
    row 6's, row 5's (0.6 cells away) is valid. The reference surface (flat) and the spec without the instrument."""
    V, U0, T = plate(0.0)
    sp = spec(instrument_radius_mm=0.0, dent_radius_mm=0.0, outlier_mm=3.0)
    ref = ReferenceSurface.for_case(U0, T, [0, 0, 0], np.eye(3), sp)
    rng = np.random.default_rng(seed)
    clean = np.column_stack([rng.uniform(-24, 24, n), rng.uniform(-24, 0.0, n), rng.normal(0, 0.3, n)])
    fly = np.column_stack([np.linspace(-15, 15, 7), np.full(7, 0.6), np.full(7, 6.0)])
    return clean, np.vstack([clean, fly]), ref, sp


def test_a_flying_pixel_beyond_the_edge_of_the_view_is_tested_against_the_nearest_valid_plane():
    """A pixel at a depth edge lands where the camera sees little: its nearest grid point has no valid plane. It
    still pulls the valid neighbour's plane it falls in, so it is tested against that plane and dropped; the
    heights are then the clean cloud's, bit for bit."""
    clean, dirty, ref, sp = _edge_cloud()
    no_filter = spec(instrument_radius_mm=0.0, dent_radius_mm=0.0)
    g_clean, g_raw, g_fixed = cloud_grid(clean, ref, no_filter), cloud_grid(dirty, ref, no_filter), cloud_grid(
        dirty, ref, sp)
    assert g_raw.valid[5].all() and not g_raw.valid[6].any()  # the pixels' nearest grid points are not valid
    assert np.abs(g_raw.height - g_clean.height).max() > 0.05  # row 5's planes are pulled by them
    g_kept = cloud_grid(clean, ref, sp)
    assert g_kept.n_outliers == 0 and g_fixed.n_outliers == 7
    assert g_fixed.n_outlier_tested == g_kept.n_outlier_tested + 7  # the pixels are tested
    np.testing.assert_array_equal(g_fixed.height, g_clean.height)
    np.testing.assert_array_equal(g_fixed.valid, g_clean.valid)
    # a point within the support of no valid grid point is neither tested nor dropped
    far = np.vstack([dirty, [[0.0, 15.0, 6.0]]])
    g_far = cloud_grid(far, ref, sp)
    assert (g_far.n_outliers, g_far.n_outlier_tested) == (7, g_fixed.n_outlier_tested)


def test_the_compiled_pass_tests_the_edge_of_the_view_as_the_reference():
    clean, dirty, ref, sp = _edge_cloud(seed=1)
    rng = np.random.default_rng(1)
    for cloud in (dirty, clean):
        cloud = np.ascontiguousarray(cloud[rng.permutation(len(cloud))])
        want = cloud_grid(cloud, ref, sp)
        x, counts = _compiled(cloud, ref, sp, np.zeros(3))
        assert (counts[3], counts[4]) == (want.n_outliers, want.n_outlier_tested)
        np.testing.assert_allclose(x[:2 * sp.grid_size**2], want.features(include_mask=True), atol=1e-9)
    assert want.n_outliers == 0 and counts[3] == 0


def _compiled(cloud, ref, sp, kin):
    """One cloud through the compiled gridding pass: its feature row and its counts (``n_tool``: shaft points,
    instrument points fitted, their noise, points dropped as gross depth errors, points tested for them)."""
    from liverforce.serve.compiled_cloud import _FILL_CODES, _grid_clouds, instrument_params

    g = sp.grid_size
    X = np.empty((1, camera.n_features(g, sp.dent_radius_mm > 0)))
    n_used, n_bad, n_tool = np.zeros(1, np.int64), np.zeros(1, np.int64), np.zeros((1, 5))
    _grid_clouds(cloud, np.zeros(1, np.int64), np.array([len(cloud)]), kin[None], ref.origin, ref.R,
                 np.ascontiguousarray(ref.raster), ref.lo, ref.step, g, sp.half_width_mm, sp.spacing_mm,
                 sp.kernel_radius_cells, sp.max_abs_height_mm, sp.min_points, sp.max_leverage,
                 sp.estimator == "linear", _FILL_CODES["laplace"], sp.half_width_mm * (1 + 2 / (g - 1)), np.zeros(4),
                 instrument_params(sp), X, n_used, n_bad, n_tool)
    return X[0], n_tool[0]


@pytest.mark.parametrize("tilt,noise,estimator", [(0.0, 0.5, "linear"), (30.0, 0.5, "linear"), (0.0, 1.0, "linear"),
                                                  (0.0, 0.5, "mean")])
def test_the_compiled_pass_drops_the_same_points_as_the_reference(tilt, noise, estimator):
    """The numba pass (sorted points, the instrument's moved off the grid) against cloud_grid, with outliers, the
    tool in view and a kinematic tip off by up to 1.5 mm: the same features, dent and tip, and the same points
    dropped and tested (the counts the serving warning reads)."""
    V, U0, T = plate(3.0)
    sp = spec(instrument_max_tilt_deg=tilt, outlier_mm=2.5, estimator=estimator)
    ref = ReferenceSurface.for_case(U0, T, [0, 0, 0], np.eye(3), sp)
    tip = np.array([0.0, 0.0, -3.0])
    rng = np.random.default_rng(3)
    g2 = 2 * sp.grid_size**2
    dropped = 0
    for seed in range(4):
        n = 500 + 2000 * seed
        cfg = ObservationConfig(**{**CFG, "n_points": (n, n), "noise_sd_mm": noise, "outlier_fraction": 0.04})
        cloud, _ = observe(V, T, tip, [0, 0, 1], cfg, seed=seed)
        cloud = np.ascontiguousarray(cloud[rng.permutation(len(cloud))])
        kin = tip + rng.uniform(-1.5, 1.5, 3)
        want = cloud_grid(cloud, ref, sp, kin)
        dropped += want.n_outliers
        x, counts = _compiled(cloud, ref, sp, kin)
        assert (counts[3], counts[4]) == (want.n_outliers, want.n_outlier_tested) and counts[4] > 0
        np.testing.assert_allclose(x[:g2], want.features(include_mask=True), atol=1e-9)
        np.testing.assert_allclose(x[g2:g2 + 2], want.dent, atol=1e-9)
        np.testing.assert_allclose(x[-3:], want.tip_local, atol=1e-9)
    assert dropped > 0
