"""Regions conform to the input surface; candidate exertion points are chosen before meshing and refined around."""

from __future__ import annotations

import numpy as np
import pytest

from liverforce.fem.boundary import region_areas
from liverforce.mesh.build import build_liver_mesh
from liverforce.mesh.quality import mesh_quality
from liverforce.mesh.regions import tag_regions
from liverforce.mesh.quality import signed_volumes

SAMPLING = {"n_points": 3, "min_spacing_mm": 15.0, "seed": 4}


@pytest.fixture(scope="module")
def refined(liver_surface):
    return build_liver_mesh(liver_surface, target_nodes=400, refine_radius_mm=10.0, refine_edge_mm=5.0,
                            exertion_sampling=SAMPLING)


def test_region_areas_do_not_depend_on_the_mesh_size(liver_surface):
    """Conforming regions cover the same surface at any size: support areas agree with the input surface's."""
    s_region, _ = tag_regions(liver_surface.vertices, liver_surface.faces)
    exact = region_areas(liver_surface.vertices, liver_surface.faces, s_region)
    for n in (600, 1500):
        m = build_liver_mesh(liver_surface, target_nodes=n)
        assert m.meta["regions_tagged_on"].startswith("input surface")
        got = region_areas(m.points, m.facets, m.facet_region)
        for r in (1, 2, 3, 4):  # ivc, ligament, visceral, rib
            # chords of a curved surface are a little shorter than the surface: under 3 % from 600 vertices
            assert got[r] == pytest.approx(exact[r], rel=0.04), (n, r, got[r], exact[r])


def test_candidates_are_sampled_on_the_visible_input_surface_and_stored(refined, liver_surface):
    cand = np.asarray(refined.meta["exertion_candidates_mm"])
    assert cand.shape == (3, 3)
    d = np.linalg.norm(cand[:, None] - cand[None], axis=2) + np.eye(3) * 1e9
    assert d.min() >= SAMPLING["min_spacing_mm"]
    # each candidate is on a visible facet of the mesh (within the chordal error of the mesh)
    vis = refined.facets[refined.facet_visible]
    cent = refined.points[vis].mean(axis=1)
    assert np.linalg.norm(cent[None] - cand[:, None], axis=2).min(axis=1).max() < 6.0
    again = build_liver_mesh(liver_surface, target_nodes=400, refine_radius_mm=10.0, refine_edge_mm=5.0,
                             exertion_sampling=SAMPLING)
    assert np.array_equal(np.asarray(again.meta["exertion_candidates_mm"]), cand)
    assert np.array_equal(again.points, refined.points)


def test_mesh_is_refined_around_each_candidate(refined):
    assert (signed_volumes(refined.points, refined.tets) > 0).all()
    cand = np.asarray(refined.meta["exertion_candidates_mm"])
    t = refined.tets
    edge = np.linalg.norm(refined.points[t[:, 0]] - refined.points[t[:, 1]], axis=1)
    centre = refined.points[t].mean(axis=1)
    dmin = np.linalg.norm(centre[:, None] - cand[None], axis=2).min(axis=1)
    for c in cand:
        near = np.linalg.norm(centre - c, axis=1) < 8.0
        assert near.sum() > 10
        assert edge[near].mean() < 7.0, edge[near].mean()
    assert edge[dmin > 50.0].mean() > 1.6 * edge[dmin < 8.0].mean()
    assert mesh_quality(refined.points, refined.tets)["radius_ratio_min"] > 0.1
    assert refined.meta["refine_points"] == {"n": 3, "radius_mm": 10.0, "edge_mm": 5.0}
