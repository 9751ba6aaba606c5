"""Geometric features: exact on a cube, analytic on an ellipsoid, invariances."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from liverforce.geometry.procedural import cube_phantom
from liverforce.geometry.surface import Surface
from liverforce.mesh.build import build_liver_mesh
from liverforce.mesh.features import compute_features, volume_moments
from liverforce.mesh.tetra import tetrahedralise


def test_cube_features_are_exact():
    a, centre = 50.0, np.array([10.0, -20.0, 30.0])
    mesh = build_liver_mesh(cube_phantom(a, centre_mm=centre), target_nodes=300)
    f = compute_features(mesh)
    assert f["volume_mm3"] == pytest.approx(a**3, rel=1e-12)
    assert f["surface_area_mm2"] == pytest.approx(6 * a**2, rel=1e-12)
    assert np.allclose(f["centroid_mm"], centre, atol=1e-9)
    # unit density: J = diag(M a²/6) with M = a³, i.e. a⁵/6 (mm⁵)
    assert np.allclose(f["inertia_mm5"], np.eye(3) * a**5 / 6, rtol=1e-12, atol=1e-6 * a**5)
    assert np.allclose(f["bbox_min_mm"], centre - a / 2) and np.allclose(f["extent_mm"], a)


def test_ellipsoid_features_match_the_analytic_values():
    axes, centre = np.array([60.0, 40.0, 30.0]), np.array([5.0, -7.0, 11.0])
    ico = trimesh.creation.icosphere(subdivisions=5)
    surface = Surface(np.asarray(ico.vertices) * axes + centre, np.asarray(ico.faces))
    points, tets = tetrahedralise(surface, edge_length_mm=6.0)
    vol, c, J = volume_moments(points, tets)
    a, b, cc = axes
    v_exact = 4.0 / 3.0 * np.pi * a * b * cc
    assert vol == pytest.approx(v_exact, rel=0.01)  # inscribed polyhedron: chordal loss < 1 %
    assert np.allclose(c, centre, atol=0.1)
    J_exact = v_exact / 5.0 * np.diag([b**2 + cc**2, a**2 + cc**2, a**2 + b**2])
    assert np.allclose(np.diag(J), np.diag(J_exact), rtol=0.02)
    assert np.abs(J - np.diag(np.diag(J))).max() < 1e-3 * np.abs(J_exact).max()


def test_moments_are_translation_and_rotation_covariant(liver_mesh):
    v0, c0, J0 = volume_moments(liver_mesh.points, liver_mesh.tets)
    q, _ = np.linalg.qr(np.random.default_rng(1).normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))  # proper rotation keeps the tets positive
    shift = np.array([100.0, -50.0, 7.0])
    v1, c1, J1 = volume_moments(liver_mesh.points @ q.T + shift, liver_mesh.tets)
    assert v1 == pytest.approx(v0, rel=1e-12)
    assert np.allclose(c1, q @ c0 + shift, atol=1e-8)
    assert np.allclose(J1, q @ J0 @ q.T, rtol=1e-10, atol=1e-12 * np.abs(J0).max())


def test_liver_features_json_and_units(liver_mesh, liver_surface):
    f = compute_features(liver_mesh)
    text = json.dumps(f)
    assert json.loads(text)["volume_mm3"] == f["volume_mm3"]
    for key in ("volume_mm3", "surface_area_mm2", "centroid_mm", "inertia_mm5", "bbox_min_mm", "bbox_max_mm",
                "n_nodes", "n_tets", "quality", "provenance", "region_area_mm2", "visible_area_mm2"):
        assert key in f, key
    assert f["volume_mm3"] == pytest.approx(liver_surface.volume_mm3, rel=0.03)
    assert f["n_nodes"] == liver_mesh.n_nodes and f["n_tets"] == liver_mesh.n_tets
    assert sum(f["region_area_mm2"].values()) == pytest.approx(f["surface_area_mm2"], rel=1e-12)
    prov = f["provenance"]
    assert prov["surface"]["seed"] == 0 and prov["surface"]["source"] == "procedural"
    assert prov["meshing"]["mesher"] == "gmsh" and prov["region_params"]["ivc_radius_mm"] == 20.0
    assert np.all(np.linalg.eigvalsh(np.array(f["inertia_mm5"])) > 0)
