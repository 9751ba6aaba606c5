"""Tetrahedralisation: orientation, node count, quality, determinism, refinement."""

from __future__ import annotations

import numpy as np
import pytest

from liverforce.geometry.procedural import cube_phantom
from liverforce.mesh.boundary import boundary_facets
from liverforce.mesh.build import build_liver_mesh
from liverforce.mesh.quality import dihedral_angles, mesh_quality, radius_ratio, signed_volumes
from liverforce.mesh.sizing import NodeCountModel, inside_grid, refinement_zone
from liverforce.mesh.tetra import tetrahedralise, tetrahedralise_with_info

#: Quality bounds asserted for gmsh meshes (measured ≈ 0.2–0.3 / ≈ 8–12°).
MIN_RADIUS_RATIO = 0.1
MIN_DIHEDRAL_DEG = 5.0


def test_quality_measures_on_known_tets():
    regular = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=float)
    tet = np.array([[0, 1, 2, 3]])
    assert radius_ratio(regular, tet)[0] == pytest.approx(1.0)
    assert np.allclose(dihedral_angles(regular, tet), np.degrees(np.arccos(1 / 3)))
    right = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)
    assert sorted(np.round(dihedral_angles(right, tet)[0], 6)) == pytest.approx([54.7356, 54.7356, 54.7356, 90, 90, 90], abs=1e-3)
    sliver = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 1e-3]], dtype=float)
    assert radius_ratio(sliver, tet)[0] < 0.01
    q = mesh_quality(sliver, tet)
    assert q["n_below_bound"] == 1 and q["min_dihedral_deg"] < 1.0


def test_liver_mesh_contract(liver_surface):
    points, tets, info = tetrahedralise_with_info(liver_surface, target_nodes=1500)
    assert points.dtype == np.float64 and tets.dtype == np.int64
    vol = signed_volumes(points, tets)
    assert (vol > 0).all(), "all tets positively oriented"
    assert len(np.unique(tets)) == len(points), "no orphan nodes"
    assert abs(len(points) / 1500 - 1) < 0.3
    q = mesh_quality(points, tets)
    assert q["radius_ratio_min"] > MIN_RADIUS_RATIO and q["min_dihedral_deg"] > MIN_DIHEDRAL_DEG
    assert q["radius_ratio_mean"] > 0.7
    # the mesh fills the surface: volume within 3 % (chordal loss only), closed boundary
    assert vol.sum() == pytest.approx(liver_surface.volume_mm3, rel=0.03)
    f = boundary_facets(tets)
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert (counts == 2).all()
    assert info.route == "two_patch" and info.attempts


def test_default_target_is_5000_nodes(liver_surface):
    points, tets = tetrahedralise(liver_surface)
    assert abs(len(points) / 5000 - 1) < 0.3
    assert mesh_quality(points, tets)["radius_ratio_min"] > MIN_RADIUS_RATIO


def test_same_input_and_seed_give_the_same_mesh(liver_surface):
    a = tetrahedralise(liver_surface, edge_length_mm=14.0, seed=3)
    b = tetrahedralise(liver_surface, edge_length_mm=14.0, seed=3)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])


def test_edge_length_controls_the_size(liver_surface):
    coarse = mesh_quality(*tetrahedralise(liver_surface, edge_length_mm=16.0))
    fine = mesh_quality(*tetrahedralise(liver_surface, edge_length_mm=10.0))
    # gmsh's size is the target edge; the mean tet edge comes out 1.0-1.3 times it
    assert 0.9 * 16.0 < coarse["edge_mean_mm"] < 1.35 * 16.0
    assert 0.9 * 10.0 < fine["edge_mean_mm"] < 1.35 * 10.0
    assert coarse["edge_mean_mm"] / fine["edge_mean_mm"] == pytest.approx(1.6, rel=0.15)
    assert fine["n_nodes"] > 2.5 * coarse["n_nodes"]


def test_local_refinement_around_points(liver_surface):
    v = liver_surface.vertices
    target = v[np.argmax(v[:, 1] + v[:, 2])]  # a point on the anterior-superior surface
    points, tets = tetrahedralise(
        liver_surface, edge_length_mm=14.0, refine_points=[target], refine_radius_mm=12.0, refine_edge_mm=4.0
    )
    assert (signed_volumes(points, tets) > 0).all()
    centre = points[tets].mean(axis=1)
    d = np.linalg.norm(centre - target, axis=1)
    edge = np.linalg.norm(points[tets[:, 0]] - points[tets[:, 1]], axis=1)
    near, far = edge[d < 10.0].mean(), edge[d > 60.0].mean()
    assert near < 6.5 and far > 10.0, (near, far)
    assert mesh_quality(points, tets)["radius_ratio_min"] > MIN_RADIUS_RATIO


def test_cube_keeps_its_edges():
    c = cube_phantom(50.0)
    points, tets, info = tetrahedralise_with_info(c, target_nodes=400)
    assert info.route == "features"
    assert signed_volumes(points, tets).sum() == pytest.approx(125000.0, rel=1e-9)
    assert np.allclose(points.min(axis=0), -25.0) and np.allclose(points.max(axis=0), 25.0)
    assert mesh_quality(points, tets)["radius_ratio_min"] > MIN_RADIUS_RATIO


def test_tetgen_option_gives_a_valid_mesh():
    c = cube_phantom(50.0)
    points, tets = tetrahedralise(c, target_nodes=400, mesher="tetgen")
    assert (signed_volumes(points, tets) > 0).all()
    assert signed_volumes(points, tets).sum() == pytest.approx(125000.0, rel=1e-9)
    assert abs(len(points) / 400 - 1) < 0.3


def test_bad_arguments_are_refused(liver_surface):
    with pytest.raises(ValueError, match="either target_nodes or edge_length_mm"):
        tetrahedralise(liver_surface, target_nodes=1000, edge_length_mm=5.0)
    with pytest.raises(ValueError, match="unknown mesher"):
        tetrahedralise(liver_surface, mesher="netgen")
    with pytest.raises(ValueError, match="refine_radius_mm"):
        tetrahedralise(liver_surface, refine_points=[[0, 0, 0]])


def test_inside_grid_fills_a_closed_surface():
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=4, radius=40.0)
    for step in (2.0, 5.0):
        g = inside_grid(np.asarray(s.vertices), np.asarray(s.faces), step)
        assert len(g) * step**3 == pytest.approx(s.volume, rel=0.01)
        assert np.linalg.norm(g, axis=1).max() < 40.0


def test_node_count_model_integrates_the_size_field(liver_surface):
    s = liver_surface
    uniform = NodeCountModel(s.volume_mm3, s.area_mm2)
    # without zones: the former closed form plus the size-independent offset
    assert uniform.integral(12.0) == pytest.approx(s.volume_mm3 / (1.44 * 12.0**3) + s.area_mm2 / (1.19 * 12.0**2))
    assert uniform.expected(12.0) == pytest.approx(uniform.integral(12.0) + uniform.offset(12.0))
    v = s.vertices
    zone = refinement_zone(v[[np.argmax(v[:, 1] + v[:, 2])]], 10.0, 6.0, 0.6)
    refined = NodeCountModel(s.volume_mm3, s.area_mm2, [zone], v, s.faces)
    # a zone finer than h adds nodes, a zone no finer than h adds none
    assert refined.integral(15.0) > uniform.integral(15.0)
    assert refined.integral(6.0) == uniform.integral(6.0)
    # fewer nodes as h grows, and edge_for inverts expected
    counts = [refined.expected(h) for h in (8.0, 12.0, 16.0, 24.0)]
    assert all(a > b for a, b in zip(counts, counts[1:]))
    h = refined.edge_for(1000)
    assert refined.expected(h) == pytest.approx(1000, rel=1e-6)
    assert refined.edge_for(10, h_max=30.0) == 30.0  # unreachable: the cap


def test_pipeline_mesh_reaches_its_target_in_one_attempt(liver_surface):
    """The mesh stage's default (config/mesh/default.yaml + sweep.exertion): the node-count model,
    with the refinement zones and label patches, lands within tolerance on the first attempt."""
    mesh = build_liver_mesh(liver_surface, target_nodes=800, refine_radius_mm=10.0, refine_edge_mm=6.0,
                            refine_ivc_edge_mm=6.0, refine_growth=0.6,
                            exertion_sampling={"n_points": 8, "min_spacing_mm": 15.0, "seed": 0})
    meshing = mesh.meta["meshing"]
    assert meshing["route"] == "labelled"
    assert len(meshing["attempts"]) == 1, meshing["attempts"]
    assert abs(len(mesh.points) / 800 - 1) <= 0.15
    assert mesh.meta["quality"]["radius_ratio_min"] > MIN_RADIUS_RATIO
