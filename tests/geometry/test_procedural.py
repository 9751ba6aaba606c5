"""Procedural livers and the cube phantom: topology, size, anatomy, seeds, controls."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from liverforce.geometry.procedural import LiverShapeParams, cube_phantom, procedural_liver

SEEDS = (0, 1, 2, 3)


@pytest.fixture(scope="module")
def livers():
    return {seed: procedural_liver(seed) for seed in SEEDS}


def volume_centroid(surface) -> np.ndarray:
    """Centroid of the enclosed volume (divergence theorem, exact for the polyhedron)."""
    v = surface.vertices - surface.vertices.mean(axis=0)
    a, b, c = (v[surface.faces[:, i]] for i in range(3))
    w = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0
    return (w[:, None] * (a + b + c) / 4.0).sum(axis=0) / w.sum() + surface.vertices.mean(axis=0)


def surface_distance(s1, s2) -> tuple[float, float]:
    """(Hausdorff, mean) vertex-to-vertex distance, mm (symmetric)."""
    d1, _ = cKDTree(s2.vertices).query(s1.vertices)
    d2, _ = cKDTree(s1.vertices).query(s2.vertices)
    return float(max(d1.max(), d2.max())), float(0.5 * (d1.mean() + d2.mean()))


@pytest.mark.parametrize("seed", SEEDS)
def test_closed_manifold_outward_genus0(livers, seed):
    s = livers[seed]
    m = trimesh.Trimesh(s.vertices, s.faces, process=False)
    assert m.is_watertight and m.is_winding_consistent
    edges = np.sort(m.edges, axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert (counts == 2).all(), "every edge must have exactly two triangles"
    assert m.euler_number == 2, "genus 0 (sphere-like)"
    assert s.volume_mm3 > 0, "outward orientation gives a positive signed volume"
    assert np.isclose(s.volume_mm3, m.volume, rtol=1e-9)
    # outward: normals at the extreme points point away from the centroid
    c = volume_centroid(s)
    n = m.vertex_normals
    for axis in range(3):
        for pick in (np.argmin, np.argmax):
            i = pick(s.vertices[:, axis])
            assert n[i] @ (s.vertices[i] - c) > 0


@pytest.mark.parametrize("seed", SEEDS)
def test_adult_size_and_volume(livers, seed):
    s = livers[seed]
    ext = s.extent_mm
    assert 200 <= ext[0] <= 300, ext  # right-left, about 250 mm
    assert 120 <= ext[1] <= 200, ext  # antero-posterior, about 160 mm
    assert 80 <= ext[2] <= 140, ext  # cranio-caudal thickness
    assert ext[0] == ext.max()
    assert 1.0e6 <= s.volume_mm3 <= 2.0e6, s.volume_mm3  # 1.0-2.0 L
    assert s.meta["seed"] == seed and s.meta["source"] == "procedural"


def test_liver_like_anatomy(livers):
    for s in livers.values():
        v = s.vertices
        lo, hi = s.bbox_mm
        w = hi[0] - lo[0]
        right = v[v[:, 0] > hi[0] - 0.35 * w]
        left = v[v[:, 0] < lo[0] + 0.2 * w]
        # right lobe thick and rounded, left lobe thin and flat
        assert np.ptp(right[:, 2]) > 1.8 * np.ptp(left[:, 2])
        # sharp anterior border: the most anterior 8 % of the right lobe is thin
        front = right[right[:, 1] > hi[1] - 0.08 * (hi[1] - lo[1])]
        assert np.ptp(front[:, 2]) < 0.5 * np.ptp(right[:, 2])


def test_same_seed_bitwise_identical():
    a, b = procedural_liver(11), procedural_liver(11)
    assert a.vertices.tobytes() == b.vertices.tobytes()
    assert a.faces.tobytes() == b.faces.tobytes()
    assert a.meta == b.meta


def test_different_seeds_give_different_shapes(livers):
    for i in SEEDS:
        for j in SEEDS:
            if i < j:
                haus, mean = surface_distance(livers[i], livers[j])
                assert haus > 10.0 and mean > 2.0, (i, j, haus, mean)
    vols = [livers[s].volume_mm3 for s in SEEDS]
    assert np.ptp(vols) > 0.05e6  # at least 50 mL spread over four seeds


def test_variation_zero_removes_seed_spread():
    p = LiverShapeParams(variation=0.0, undulation_mm=0.0)
    haus, _ = surface_distance(procedural_liver(1, p), procedural_liver(2, p))
    assert haus < 0.5


def test_size_scale_scales_linearly():
    base = procedural_liver(0)
    big = procedural_liver(0, LiverShapeParams(size_scale=1.2))
    assert np.allclose(big.extent_mm / base.extent_mm, 1.2, atol=0.05)
    assert big.volume_mm3 / base.volume_mm3 == pytest.approx(1.2**3, rel=0.08)


def test_thickness_changes_only_the_vertical_extent():
    base = procedural_liver(0)
    thick = procedural_liver(0, LiverShapeParams(thickness=1.25))
    thin = procedural_liver(0, LiverShapeParams(thickness=0.8))
    r_thick, r_thin = thick.extent_mm / base.extent_mm, thin.extent_mm / base.extent_mm
    assert r_thick[2] > 1.15 and r_thin[2] < 0.87
    assert abs(r_thick[0] - 1) < 0.03 and abs(r_thin[0] - 1) < 0.03
    assert thin.volume_mm3 < base.volume_mm3 < thick.volume_mm3


def test_lobe_ratio_grows_the_left_lobe():
    small = procedural_liver(0, LiverShapeParams(lobe_ratio=0.15))
    large = procedural_liver(0, LiverShapeParams(lobe_ratio=0.6))
    # the right end (right lobe) stays put relative to the body; the left lobe reaches further
    reach_small = small.bbox_mm[1][0] - volume_centroid(small)[0]
    reach_large = large.bbox_mm[1][0] - volume_centroid(large)[0]
    assert reach_large > reach_small + 15.0
    assert large.extent_mm[0] > small.extent_mm[0] + 25.0
    assert large.volume_mm3 > 1.2 * small.volume_mm3


def test_undulation_changes_the_surface():
    smooth = procedural_liver(0, LiverShapeParams(undulation_mm=0.0))
    wavy = procedural_liver(0, LiverShapeParams(undulation_mm=6.0))
    _, mean = surface_distance(smooth, wavy)
    assert mean > 2.0
    # a wavy surface has a larger area-to-volume^(2/3) ratio than the smooth one
    def roughness(s):
        return s.area_mm2 / s.volume_mm3 ** (2 / 3)

    assert roughness(wavy) > roughness(smooth)


@pytest.mark.parametrize("field, value", [("lobe_ratio", -1.0), ("thickness", 5.0), ("variation", 0.9)])
def test_invalid_shape_params_are_refused(field, value):
    with pytest.raises(ValueError, match=field):
        LiverShapeParams(**{field: value})


@pytest.mark.parametrize("edge, div", [(50.0, 1), (50.0, 4), (12.5, 3)])
def test_cube_phantom_is_exact(edge, div):
    c = cube_phantom(edge, divisions=div, centre_mm=(1.0, 2.0, 3.0))
    m = trimesh.Trimesh(c.vertices, c.faces, process=False)
    assert m.is_watertight and m.is_winding_consistent
    assert c.volume_mm3 == pytest.approx(edge**3, rel=1e-12)
    assert c.area_mm2 == pytest.approx(6 * edge**2, rel=1e-12)
    assert np.allclose(c.bbox_mm[0], np.array([1.0, 2.0, 3.0]) - edge / 2)
    assert np.allclose(c.bbox_mm[1], np.array([1.0, 2.0, 3.0]) + edge / 2)
    assert len(c.faces) == 12 * div**2


def test_volume_range_spreads_the_population_over_adult_volumes():
    """Each seed draws its own volume in the range (here 1.0-2.2 L) and the liver is scaled to it exactly."""
    p = LiverShapeParams(volume_range_l=[1.0, 2.2], voxel_mm=4.0, smoothing_iterations=5)
    vols = []
    for seed in range(8):
        s = procedural_liver(seed, p)
        assert s.volume_mm3 / 1e6 == pytest.approx(s.meta["volume_target_l"], rel=1e-9)
        vols.append(s.volume_mm3 / 1e6)
    assert 1.0 <= min(vols) and max(vols) <= 2.2
    assert max(vols) - min(vols) > 0.5  # a real spread, not a constant
    # the same seed without a range keeps its shape: scaling is the only change
    base = procedural_liver(3, LiverShapeParams(voxel_mm=4.0, smoothing_iterations=5))
    scaled = procedural_liver(3, p)
    k = (scaled.volume_mm3 / base.volume_mm3) ** (1 / 3)
    assert scaled.vertices == pytest.approx(base.vertices * k, abs=1e-6)
    with pytest.raises(ValueError, match="volume_range_l"):
        LiverShapeParams(volume_range_l=[2.0, 1.0])
