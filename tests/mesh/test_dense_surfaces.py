"""A very dense lab surface (a CT liver exported at 300k+ triangles) is tagged in bounded memory: the facet
normals' smoothing asked for every facet pair within 8 mm at once (about 5e8 pairs, 22 GB, for 630k triangles:
the mesh job was killed by the kernel without a message). Above a bound it now smooths over cells of facets, and
gives the regions the facet-by-facet smoothing gives."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
import trimesh

import liverforce.mesh.regions as regions
from liverforce.geometry.procedural import procedural_liver


def _area(v, f, mask):
    t = v[f[mask]]
    return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum()


def test_a_dense_surface_is_smoothed_in_bounded_memory():
    s = procedural_liver(0)
    v, f = trimesh.remesh.subdivide(s.vertices, s.faces)  # 158k triangles: about 3e7 facet pairs within 8 mm
    t = v[f]
    raw = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    tracemalloc.start()
    try:
        n = regions._smoothed_normals(t.mean(axis=1), raw, 8.0)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 700e6, f"{peak / 1e6:.0f} MB for {len(f)} facets"  # the facet pairs alone took about 2 GB
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    assert (np.einsum("ij,ij->i", n, raw) > 0).mean() > 0.97  # outward, as the facets are


def test_cell_smoothing_tags_the_regions_the_facet_smoothing_tags(monkeypatch):
    s = procedural_liver(0)
    exact_region, exact_visible = regions.tag_regions(s.vertices, s.faces)
    monkeypatch.setattr(regions, "SMOOTHING_PAIRS_AT_ONCE", 1_000_000)  # this liver's 2e6 pairs: cells (2.4 mm)
    region, visible = regions.tag_regions(s.vertices, s.faces)
    total = _area(s.vertices, s.faces, np.ones(len(s.faces), bool))
    assert _area(s.vertices, s.faces, region != exact_region) / total < 0.01
    assert _area(s.vertices, s.faces, visible != exact_visible) / total < 0.01
    for code in (1, 2, 3, 4):
        assert _area(s.vertices, s.faces, region == code) == pytest.approx(
            _area(s.vertices, s.faces, exact_region == code), rel=0.05)
