"""build_given_mesh: a tet mesh as given, its vertex ids valid for supports files and exertion points."""

from __future__ import annotations

import numpy as np
import pytest
from test_byo_volume_files import shuffled_box, write_volume

from liverforce.geometry.volume_mesh import load_volume_mesh
from liverforce.mesh.given import build_given_mesh
from liverforce.mesh.supports import PointFrame, exertion_points_mesh, parse_supports
from liverforce.mesh.types import REGION_CODES

SIZE = (30.0, 20.0, 20.0)
M_TO_MM = PointFrame(scale=1000.0)


@pytest.fixture()
def given(tmp_path):
    points, tets, _ = shuffled_box(seed=3)
    write_volume(tmp_path / "box.vtu", "vtu", points / 1000.0, tets)  # metres
    vm, _ = load_volume_mesh(tmp_path / "box.vtu", units="m", size_range_mm=None)
    file_points = points / 1000.0
    return vm, (lambda: file_points), tmp_path


def test_a_supports_file_of_vertex_ids_selects_exactly_their_facets(given):
    vm, file_vertices, tmp = given
    top = np.flatnonzero(np.isclose(vm.points[:, 2], SIZE[2]))  # ids of the file = ids of the mesh
    np.savetxt(tmp / "top_ids.txt", top, fmt="%d")
    sup = parse_supports({"mode": "replace", "list": [
        {"name": "lid", "kind": "fixed", "file": {"path": str(tmp / "top_ids.txt")}}]})
    mesh = build_given_mesh(vm.points, vm.tets, vm.meta, supports=sup, support_frame=M_TO_MM,
                            file_vertices=file_vertices)
    np.testing.assert_array_equal(mesh.points, vm.points)  # nothing renumbered, nothing added
    on_top = np.isclose(mesh.points[mesh.facets][:, :, 2], SIZE[2]).all(axis=1)
    np.testing.assert_array_equal(mesh.facet_region == REGION_CODES["ivc"], on_top)
    assert mesh.meta["supports"][0]["snap_mm"]["max"] < 1e-9
    assert mesh.meta["node_numbering"] == "file" and mesh.meta["meshing"]["mesher"] == "as_given"
    mesh.validate()


def test_exertion_points_by_vertex_id_are_those_nodes(given):
    vm, file_vertices, _ = given
    top = np.flatnonzero(np.isclose(vm.points[:, 2], SIZE[2]))
    ids = [int(top[0]), int(top[-1])]
    pts = exertion_points_mesh({"vertex_ids": ids}, M_TO_MM, file_vertices)
    floor = parse_supports({"mode": "replace", "list": [
        {"name": "floor", "kind": "fixed", "box": {"min_mm": [-1, -1, -1], "max_mm": [31, 21, 1]}}]})
    mesh = build_given_mesh(vm.points, vm.tets, vm.meta, supports=floor, support_frame=M_TO_MM, exertion_points=pts)
    np.testing.assert_array_equal(np.asarray(mesh.meta["exertion_candidates_mm"]), vm.points[ids])
    assert mesh.meta["exertion_given"] and max(mesh.meta["exertion_snap_mm"]) == 0.0


def test_without_given_points_candidates_are_sampled_on_the_visible_facets(given):
    vm, _, _ = given
    mesh = build_given_mesh(vm.points, vm.tets, vm.meta, exertion_sampling={"n_points": 2, "min_spacing_mm": 5.0,
                                                                             "seed": 1})
    cand = np.asarray(mesh.meta["exertion_candidates_mm"])
    assert cand.shape == (2, 3)
    vis = mesh.points[mesh.facets[mesh.facet_visible]].reshape(-1, 3)
    lo, hi = vis.min(axis=0), vis.max(axis=0)
    assert ((cand >= lo - 1e-9) & (cand <= hi + 1e-9)).all()


def test_tets_given_in_either_orientation_are_reoriented_and_counted(given):
    vm, _, _ = given
    flipped = vm.tets.copy()
    flipped[:5] = flipped[:5][:, [0, 1, 3, 2]]
    mesh = build_given_mesh(vm.points, flipped, vm.meta)
    assert mesh.meta["meshing"]["reoriented_here"] == 5
    mesh.validate()


def test_supports_leaving_no_visible_facet_are_refused_when_the_tool_positions_are_sampled(given):
    """Not a mesh without candidates, refused at the sweep as a geometry with no visible facets."""
    from liverforce.mesh.supports import SupportError

    vm, _, _ = given
    mould = parse_supports({"mode": "replace", "list": [
        {"name": "mould", "kind": "fixed", "box": {"min_mm": [-1, -1, -1], "max_mm": [31, 21, 21]}}]})
    with pytest.raises(SupportError, match=r"the lab's supports 'mould' \(fixed, box, \d+ facets\) leave no free "
                                           r"surface facing the camera.*\(geometry.imported\[\].exertion_points\)"):
        build_given_mesh(vm.points, vm.tets, vm.meta, supports=mould,
                         exertion_sampling={"n_points": 2, "min_spacing_mm": 5.0, "seed": 1})


def test_a_given_mesh_on_a_sliding_face_alone_is_refused_when_asked(given):
    from liverforce.mesh.supports import SupportError

    vm, _, _ = given
    floor = parse_supports({"mode": "replace", "list": [
        {"name": "floor", "kind": "sliding", "box": {"min_mm": [-1, -1, -1], "max_mm": [31, 21, 1]}}]})
    with pytest.raises(SupportError, match=r"^lab: the supports do not hold the liver: .*'floor' \(sliding\)"):
        build_given_mesh(vm.points, vm.tets, vm.meta, supports=floor, require_held="lab")
    build_given_mesh(vm.points, vm.tets, vm.meta, supports=floor)  # not asked: the Python API as before
