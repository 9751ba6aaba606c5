"""Supports selected by a Gmsh physical group or a VTU/VTK cell-data tag of the geometry file.

On a mesh imported as given the selected facets must be exactly the tagged
boundary triangles; on another surface of the same body (a remeshed one) the
group is transferred to the facets lying on the tagged faces.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_byo_volume_files import shuffled_box, write_gmsh, write_volume

from liverforce.fem.testing import box_mesh
from liverforce.geometry.volume_mesh import load_volume_mesh
from liverforce.mesh.boundary import boundary_facets
from liverforce.mesh.groups import read_file_groups
from liverforce.mesh.supports import PointFrame, SupportError, parse_supports, select_facets

SIZE = (30.0, 20.0, 20.0)


def _support(group, kind="fixed"):
    _, (s,) = parse_supports({"mode": "replace", "list": [{"name": "s", "kind": kind, "group": group}]})
    return s


def _on(points, facets, axis, value):
    return np.isclose(points[facets][:, :, axis], value).all(axis=1)


@pytest.fixture(scope="module")
def box():
    points, tets, _ = shuffled_box(seed=1)
    f = boundary_facets(tets)
    return points, tets, f[_on(points, f, 2, SIZE[2])], f[_on(points, f, 0, 0.0)]


@pytest.mark.parametrize("fmt, top, side", [
    ("msh22", "top", 4), ("msh41", "top", 4),  # Gmsh: a physical name, a physical tag
    ("vtu", 3, {"array": "tag", "value": 4}), ("vtk", 3, {"array": "tag", "value": 4}),  # cell-data tags
])
def test_group_selects_exactly_the_tagged_faces_of_a_mesh_as_given(tmp_path, box, fmt, top, side):
    points, tets, top_tri, side_tri = box
    path = tmp_path / f"box.{'msh' if fmt.startswith('msh') else fmt}"
    write_volume(path, fmt, points, tets, {"top": (3, top_tri), "side": (4, side_tri)})
    vm, _ = load_volume_mesh(path, size_range_mm=None)
    facets = boundary_facets(vm.tets)
    groups = read_file_groups(path)
    for group, axis, value in ((top, 2, SIZE[2]), (side, 0, 0.0)):
        mask, info = select_facets(vm.points, facets, _support(group), file_groups=lambda: groups)
        np.testing.assert_array_equal(mask, _on(vm.points, facets, axis, value))
        assert info["transfer_mm"] < 1e-12 and info["n_facets"] == mask.sum() > 0


def test_group_in_a_file_in_metres_and_lps_lands_on_the_ras_mm_surface(tmp_path, box):
    points, tets, top_tri, _ = box
    write_volume(tmp_path / "m.vtu", "vtu", points * [-1, -1, 1] / 1000.0, tets, {"top": (3, top_tri)})
    vm, _ = load_volume_mesh(tmp_path / "m.vtu", units="m", frame="LPS", size_range_mm=None)
    facets = boundary_facets(vm.tets)
    frame = PointFrame(scale=1000.0, matrix=tuple(map(tuple, np.diag([-1.0, -1.0, 1.0, 1.0]))))
    groups = read_file_groups(tmp_path / "m.vtu")
    mask, _ = select_facets(vm.points, facets, _support(3), frame, file_groups=lambda: groups)
    np.testing.assert_array_equal(mask, _on(vm.points, facets, 2, SIZE[2]))


def test_a_group_of_nodes_selects_the_facets_with_all_three_nodes(tmp_path, box):
    points, tets, top_tri, _ = box
    write_gmsh(tmp_path / "n.msh", points, tets, {"top_nodes": (9, np.unique(top_tri))}, 4.1)
    groups = read_file_groups(tmp_path / "n.msh")
    facets = boundary_facets(tets)
    mask, info = select_facets(points, facets, _support("top_nodes", "sliding"), file_groups=lambda: groups)
    np.testing.assert_array_equal(mask, _on(points, facets, 2, SIZE[2]))
    assert info["snap_mm"]["max"] == 0.0 and info["group_nodes"] == len(np.unique(top_tri))


def test_a_group_is_transferred_onto_a_finer_surface_of_the_same_body(tmp_path, box):
    """The remesh path: the group's faces select the facets of a different (finer) mesh lying on them."""
    points, tets, top_tri, side_tri = box
    write_volume(tmp_path / "b.msh", "msh41", points, tets, {"top": (3, top_tri), "side": (4, side_tri)})
    groups = read_file_groups(tmp_path / "b.msh")
    fp, ft, _ = box_mesh((6, 4, 4), size=SIZE)
    ff = boundary_facets(ft)
    for name, axis, value in (("top", 2, SIZE[2]), ("side", 0, 0.0)):
        mask, info = select_facets(fp, ff, _support(name), file_groups=lambda: groups)
        np.testing.assert_array_equal(mask, _on(fp, ff, axis, value))
        assert info["transfer_mm"] < 1e-9


def test_unknown_group_names_what_the_file_holds(tmp_path, box):
    points, tets, top_tri, _ = box
    write_volume(tmp_path / "b.msh", "msh22", points, tets, {"top": (3, top_tri)})
    groups = read_file_groups(tmp_path / "b.msh")
    with pytest.raises(SupportError, match=r"'cava' is no group of .*b\.msh; it holds Gmsh physical names "
                                           r"\['liver', 'top'\].*values of gmsh:physical: \[1, 3\]"):
        select_facets(points, boundary_facets(tets), _support("cava"), file_groups=lambda: groups)


def test_a_bare_tag_with_two_integer_arrays_asks_for_the_array(tmp_path, box):
    import meshio

    points, tets, top_tri, _ = box
    meshio.write(tmp_path / "two.vtu", meshio.Mesh(points, [("tetra", tets), ("triangle", top_tri)], cell_data={
        "tag": [np.zeros(len(tets), int), np.full(len(top_tri), 3)],
        "material": [np.ones(len(tets), int), np.zeros(len(top_tri), int)]}))
    groups = read_file_groups(tmp_path / "two.vtu")
    with pytest.raises(SupportError, match=r"has \['tag', 'material'\]: give group: \{array: <name>, value: 3\}"):
        select_facets(points, boundary_facets(tets), _support(3), file_groups=lambda: groups)
    mask, _ = select_facets(points, boundary_facets(tets), _support({"array": "tag", "value": 3}),
                            file_groups=lambda: groups)
    assert mask.sum() == len(top_tri)


def test_a_group_inside_the_body_is_refused(tmp_path):
    points, tets, _ = shuffled_box(seed=2)
    interior = tets[:, [0, 1, 2]]
    f = boundary_facets(tets)
    keys = {tuple(sorted(t)) for t in f}
    inner = np.array([t for t in interior if tuple(sorted(t)) not in keys][:5])
    write_volume(tmp_path / "i.vtu", "vtu", points, tets, {"inner": (5, inner)})
    groups = read_file_groups(tmp_path / "i.vtu")
    with pytest.raises(SupportError, match="none on the boundary of the mesh"):
        select_facets(points, f, _support(5), file_groups=lambda: groups)


def test_a_group_on_a_surface_file_without_tags_is_refused_clearly():
    s = _support("cava")
    with pytest.raises(SupportError, match="a group selector needs the geometry's mesh file"):
        select_facets(np.eye(3), np.array([[0, 1, 2]]), s)


@pytest.mark.parametrize("group, message", [
    (True, "must be a group name, a tag number"),
    ({"value": 2.5}, "must be an integer tag"),
    ({"colour": 1}, r"give a name, a number, or \{array"),
    ({"name": "a", "value": 1}, r"give a name, a number, or \{array"),
])
def test_group_syntax_is_checked_when_the_config_is_read(group, message):
    with pytest.raises(SupportError, match=message):
        _support(group)


def test_group_forms_parse_to_name_value_or_array():
    assert _support("cava").selector == ("group", {"name": "cava"})
    assert _support(7).selector == ("group", {"value": 7})
    assert _support("7").selector == ("group", {"value": 7})
    assert _support({"array": "CellEntityIds", "value": 2}).selector == ("group", {"array": "CellEntityIds", "value": 2})
