"""ROI extraction: area fraction, geodesic growth, local frame."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from liverforce.dataset.roi import extract_roi, local_frame, roi_triangles, surface_graph


@pytest.fixture(scope="module")
def sphere():
    s = trimesh.creation.icosphere(subdivisions=4, radius=50.0)
    return np.asarray(s.vertices), np.asarray(s.faces)


def test_node_areas_sum_to_surface_area(sphere):
    pts, tri = sphere
    g = surface_graph(pts, tri)
    assert g.total_area == pytest.approx(trimesh.Trimesh(pts, tri).area, rel=1e-12)


@pytest.mark.parametrize("fraction", [0.05, 0.18, 0.5])
def test_roi_area_within_2_percent_and_a_spherical_cap(sphere, fraction):
    pts, tri = sphere
    g = surface_graph(pts, tri)
    p = np.array([0, 0, 50.0])
    ids, achieved = extract_roi(g, p, fraction)
    assert abs(achieved - fraction) < 0.02 * fraction + 1e-3
    # on a sphere the geodesic patch is a cap: height h = 2 R f, so z >= R (1 - 2 f) (one ring of slack)
    z = g.points[ids, 2]
    assert z.min() > 50.0 * (1 - 2 * fraction) - 4.0


def test_roi_grows_along_surface_not_through_space():
    # a thin plate: the bottom face is 2 mm below the top face in space, but
    # more than 50 mm away along the surface from the centre of the top face
    plate = trimesh.creation.box(extents=[100, 100, 2])
    for _ in range(4):
        plate = plate.subdivide()
    g = surface_graph(np.asarray(plate.vertices), np.asarray(plate.faces))
    ids, achieved = extract_roi(g, np.array([0.0, 0.0, 1.0]), 0.1)
    assert achieved == pytest.approx(0.1, abs=0.005)
    assert np.all(g.points[ids, 2] > 0.0)  # only the touched (top) face
    r = np.linalg.norm(g.points[ids, :2], axis=1)
    assert r.max() < 30.0  # a disc of ~26 mm radius (10 % of 20,800 mm^2)


def test_local_frame_is_right_handed_orthonormal(sphere):
    pts, tri = sphere
    g = surface_graph(pts, tri)
    for p in ([0, 0, 50.0], [50.0, 0, 0], [0, -50.0, 0], [28.9, 28.9, 28.9]):
        f = local_frame(g, np.array(p), radius_mm=6.0)
        np.testing.assert_allclose(f @ f.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(f) == pytest.approx(1.0)
        np.testing.assert_allclose(f[2], np.array(p) / np.linalg.norm(p), atol=0.01)  # outward normal


def test_bad_fraction_refused(sphere):
    g = surface_graph(*sphere)
    with pytest.raises(ValueError, match="fraction"):
        extract_roi(g, np.zeros(3), 0.0)


def test_thickness_along_the_inward_normal_is_the_chord():
    """Cube: its edge from the centre of a face; sphere: the diameter from any point; open surface: nan."""
    import trimesh

    from liverforce.dataset.roi import thickness_along_normal
    from liverforce.geometry.procedural import cube_phantom

    cube = cube_phantom(50.0, divisions=6)
    assert thickness_along_normal(cube.vertices, cube.faces, [0, 0, 25.0], [0, 0, 1.0]) == pytest.approx(50.0)
    # off-centre and tilted: the chord of a tilted ray through the cube
    n = np.array([0.0, 0.3, 1.0]) / np.linalg.norm([0.0, 0.3, 1.0])
    assert thickness_along_normal(cube.vertices, cube.faces, [5.0, 0, 25.0], n) == pytest.approx(50.0 / n[2])
    s = trimesh.creation.icosphere(subdivisions=4, radius=40.0)
    for v in s.vertices[[0, 17, 300]]:
        t = thickness_along_normal(s.vertices, s.faces, v, v / np.linalg.norm(v))
        assert t == pytest.approx(80.0, rel=2e-3)  # the polyhedron's chord is a hair shorter than 2 R
    top = s.faces[s.vertices[s.faces].mean(axis=1)[:, 2] > -20.0]  # a bowl: open at the bottom
    assert np.isnan(thickness_along_normal(s.vertices, top, [0, 0, 40.0], [0, 0, 1.0]))


def test_thickness_counts_where_the_ray_leaves_the_liver():
    """A point a millimetre off the surface (snapped onto the FE mesh, given with the segmented surface): the
    chord to the far side, not the millimetre to the near one; the triangles' winding does not matter."""
    from liverforce.dataset.roi import thickness_along_normal
    from liverforce.geometry.procedural import cube_phantom

    cube = cube_phantom(50.0, divisions=6)
    up = [0, 0, 1.0]
    for faces in (cube.faces, cube.faces[:, ::-1]):  # wound outward, then inward
        assert thickness_along_normal(cube.vertices, faces, [3.0, -2.0, 26.0], up) == pytest.approx(51.0)
        assert thickness_along_normal(cube.vertices, faces, [3.0, -2.0, 24.0], up) == pytest.approx(49.0)
        assert thickness_along_normal(cube.vertices, faces, [3.0, -2.0, 25.0], up) == pytest.approx(50.0)


def test_roi_triangles_are_the_facets_inside_the_roi_and_a_wrapped_roi_keeps_the_camera_side_on_top():
    """Round a thin plate's edge the ROI holds both faces. Its triangles are the facets with three ROI nodes
    (indices into the ROI's own order); the z-buffer of them along the top face's normal is the top face."""
    from liverforce.learn.cloud_features import CloudGridSpec, ReferenceSurface

    plate = trimesh.creation.box(extents=[100, 100, 2])
    for _ in range(4):
        plate = plate.subdivide()
    pts, faces = np.asarray(plate.vertices), np.asarray(plate.faces)
    g = surface_graph(pts, faces)
    p = np.array([45.0, 0.0, 1.0])  # 5 mm from the edge x = 50 on the top face
    ids, _ = extract_roi(g, p, 0.08)
    point_ids = g.node_ids[ids]
    assert (pts[point_ids, 2] < 0).any()  # wrapped round the edge onto the bottom face
    T = roi_triangles(faces, point_ids)
    inside = np.isin(faces, point_ids).all(axis=1)
    assert len(T) == inside.sum() and T.min() >= 0 and T.max() < len(point_ids)
    assert {tuple(t) for t in point_ids[T].tolist()} == {tuple(t) for t in faces[inside].tolist()}
    # the same triangles from the surface graph's own (local) indices, as ROI re-growing computes them
    assert np.array_equal(roi_triangles(g.triangles, ids), T)
    spec = CloudGridSpec(grid_size=9, half_width_mm=8.0)
    ref = ReferenceSurface.from_patch(pts[point_ids], T, p, np.eye(3), spec)
    assert np.abs(ref.grid_height).max() < 1e-9  # the top face, although the bottom face lies 2 mm under it
