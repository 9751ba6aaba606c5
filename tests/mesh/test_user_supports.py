"""User supports: each selector selects exactly the expected facets; the mesh conforms; FE equilibrium."""

from __future__ import annotations

import numpy as np
import pytest

from liverforce.geometry.procedural import cube_phantom
from liverforce.mesh.build import build_liver_mesh
from liverforce.mesh.supports import (PointFrame, SupportError, apply_supports, parse_supports, select_facets,
                                      support_stiffness)
from liverforce.mesh.types import REGION_CODES

A = 50.0  # cube edge, mm, centred at the origin: faces at ±25


@pytest.fixture(scope="module")
def cube():
    return cube_phantom(A, divisions=4)


def _one(selector: dict, kind="fixed", **extra):
    _, (s,) = parse_supports({"mode": "replace", "list": [{"name": "s", "kind": kind, **selector, **extra}]})
    return s


def _bottom(cube):
    return cube.vertices[cube.faces].mean(axis=1)[:, 2] < -A / 2 + 1e-9


def test_box_selects_the_bottom_face_exactly(cube):
    s = _one({"box": {"min_mm": [-30, -30, -26], "max_mm": [30, 30, -24]}})
    mask, info = select_facets(cube.vertices, cube.faces, s)
    np.testing.assert_array_equal(mask, _bottom(cube))
    assert info["n_facets"] == 32  # 4 x 4 squares, 2 triangles each


def test_sphere_selects_centroids_inside(cube):
    cent = cube.vertices[cube.faces].mean(axis=1)
    s = _one({"sphere": {"center_mm": [0, 0, -25], "radius_mm": 13.0}})
    mask, _ = select_facets(cube.vertices, cube.faces, s)
    np.testing.assert_array_equal(mask, np.linalg.norm(cent - [0, 0, -25], axis=1) <= 13.0)
    assert 0 < mask.sum() < 32 and _bottom(cube)[mask].all()


def test_sphere_selecting_nothing_is_refused(cube):
    s = _one({"sphere": {"center_mm": [0, 0, 0], "radius_mm": 5.0}})  # inside the cube, far from any facet
    with pytest.raises(SupportError, match="selects no surface facet"):
        select_facets(cube.vertices, cube.faces, s)


@pytest.mark.parametrize("suffix", [".npy", ".txt", ".csv"])
def test_file_of_coordinates_is_snapped_and_selects_facets_with_all_vertices(cube, tmp_path, suffix):
    top = np.flatnonzero(np.isclose(cube.vertices[:, 2], A / 2))
    xyz = cube.vertices[top] + [0.3, -0.2, 0.4]  # off the nodes: snapped back
    path = tmp_path / f"pts{suffix}"
    if suffix == ".npy":
        np.save(path, xyz)
    else:
        np.savetxt(path, xyz, delimiter="," if suffix == ".csv" else " ")
    s = _one({"file": {"path": str(path)}}, kind="sliding")
    mask, info = select_facets(cube.vertices, cube.faces, s)
    expected = np.isclose(cube.vertices[cube.faces][:, :, 2], A / 2).all(axis=1)
    np.testing.assert_array_equal(mask, expected)
    assert info["snap_mm"]["max"] == pytest.approx(np.linalg.norm([0.3, -0.2, 0.4]))


def test_file_of_vertex_ids_uses_the_files_vertices(cube, tmp_path):
    ids = np.flatnonzero(np.isclose(cube.vertices[:, 0], A / 2))
    np.savetxt(tmp_path / "ids.txt", ids, fmt="%d")
    s = _one({"file": {"path": str(tmp_path / "ids.txt")}})
    # the file is in metres and LPS: its vertices map to the surface through the frame
    lps = np.diag([-1.0, -1.0, 1.0, 1.0])
    frame = PointFrame(scale=1000.0, matrix=tuple(map(tuple, lps)))
    file_v = (cube.vertices * [-1, -1, 1]) / 1000.0
    mask, info = select_facets(cube.vertices, cube.faces, s, frame, file_vertices=lambda: file_v)
    np.testing.assert_array_equal(mask, np.isclose(cube.vertices[cube.faces][:, :, 0], A / 2).all(axis=1))
    assert info["snap_mm"]["max"] < 1e-9


def test_far_coordinates_are_refused(cube, tmp_path):
    np.savetxt(tmp_path / "far.csv", [[0, 0, 40.0]], delimiter=",")
    with pytest.raises(SupportError, match="15 mm from the surface"):
        select_facets(cube.vertices, cube.faces, _one({"file": {"path": str(tmp_path / "far.csv")}}))


def test_box_in_an_lps_file_frame(cube):
    # the box is in the file frame (LPS): x_file = -x_ras; bottom face selected as in RAS
    frame = PointFrame(matrix=tuple(map(tuple, np.diag([-1.0, -1.0, 1.0, 1.0]))))
    s = _one({"box": {"min_mm": [-30, -30, -26], "max_mm": [0, 30, -24]}})  # x_file <= 0 = x_ras >= 0
    mask, _ = select_facets(cube.vertices, cube.faces, s, frame)
    cent = cube.vertices[cube.faces].mean(axis=1)
    np.testing.assert_array_equal(mask, _bottom(cube) & (cent[:, 0] >= 0))


def test_replace_and_add_modes_and_kind_codes(cube):
    auto = np.full(len(cube.faces), REGION_CODES["visceral"], np.int8)
    cfg = {"list": [{"kind": "foundation", "region": "ligament", "stiffness": {"total_n_per_mm": 10.0},
                     "box": {"min_mm": [-30, -30, 24], "max_mm": [30, 30, 26]}},
                    {"kind": "sliding", "box": {"min_mm": [24, -30, -30], "max_mm": [26, 30, 30]}}]}
    mode, sup = parse_supports({"mode": "replace", **cfg})
    reg, report = apply_supports(cube.vertices, cube.faces, auto, mode, sup)
    assert set(np.unique(reg)) == {0, REGION_CODES["ligament"], REGION_CODES["rib"]}
    assert [r["n_facets"] for r in report] == [32, 32]
    _, sup = parse_supports({"mode": "add", **cfg})
    reg_add, _ = apply_supports(cube.vertices, cube.faces, auto, "add", sup)
    assert (reg_add == REGION_CODES["visceral"]).sum() == len(auto) - 64
    k = support_stiffness(sup, {REGION_CODES["ligament"]: 2500.0})
    assert k == {"ligament_kn": pytest.approx(10.0 / 2500), "ligament_kt": pytest.approx(10.0 / 2500)}


@pytest.mark.parametrize("bad, key", [
    ({"kind": "glued", "sphere": {"center_mm": [0, 0, 0], "radius_mm": 1}}, "list[0].kind"),
    ({"kind": "fixed"}, "exactly one selector"),
    ({"kind": "foundation", "sphere": {"center_mm": [0, 0, 0], "radius_mm": 1}}, "list[0].stiffness"),
    ({"kind": "fixed", "box": {"min_mm": [0, 0, 0], "max_mm": [0, 1, 1]}}, "list[0].box"),
])
def test_bad_supports_name_the_key(bad, key):
    with pytest.raises(SupportError, match=key.replace("[", r"\[").replace("]", r"\]")):
        parse_supports({"mode": "replace", "list": [bad]}, where="geometry.imported[0].supports")


def test_fixed_box_on_a_cube_mesh_balances_a_tool_load(cube):
    """Fixed patch (by a box) under the cube, downward tool at the top: the fixed reaction is equal and opposite.

    The box holds the middle 2 x 2 squares of the bottom face (25 x 25 mm, 625 mm²). On the mesh the
    patch covers the same area up to the mesher's rounding of its border (exact when the labelled
    route conforms, within an element otherwise).
    """
    from liverforce.fem import BoundaryParams, LiverModel, SolverOptions, ToolLoad, make_material
    from liverforce.fem.boundary import region_areas

    sup = parse_supports({"mode": "replace", "list": [
        {"name": "table", "kind": "fixed", "box": {"min_mm": [-13, -13, -26], "max_mm": [13, 13, -24]}}]})
    mesh = build_liver_mesh(cube, target_nodes=300, supports=sup)
    fixed = mesh.facet_region == REGION_CODES["ivc"]
    assert np.isclose(mesh.points[mesh.facets[fixed]][..., 2], -A / 2).all()
    assert region_areas(mesh.points, mesh.facets, mesh.facet_region)[REGION_CODES["ivc"]] == pytest.approx(625, rel=0.1)
    assert set(np.unique(mesh.facet_region)) == {0, REGION_CODES["ivc"]}
    assert mesh.meta["supports"][0]["n_facets"] == 8
    mat = make_material("neo_hookean", {"C10": 1e-3}, nu=0.45)
    model = LiverModel.from_mesh(mesh, mat, BoundaryParams(), SolverOptions(formulation="p1"))
    F = np.array([0.0, 0.0, -0.5])
    res = model.solve(ToolLoad([0.0, 0.0, A / 2], F, 4.0))
    assert res.converged
    np.testing.assert_allclose(res.reactions["tool"], F, rtol=1e-12)
    np.testing.assert_allclose(res.reactions["ivc"], -F, rtol=0, atol=1e-6 * np.linalg.norm(F))
    assert res.u_nodes[:, 2].min() < 0


def test_foundation_and_sliding_supports_carry_the_load(cube):
    """Foundation under the cube (given as N/mm³), sliding sides: the supports balance the tool load."""
    from liverforce.fem import BoundaryParams, LiverModel, SolverOptions, ToolLoad, make_material
    from liverforce.fem.boundary import region_areas

    mode, sup = parse_supports({"mode": "replace", "list": [
        {"name": "bed", "kind": "foundation", "region": "visceral",
         "stiffness": {"normal_n_per_mm3": 0.02, "tangential_n_per_mm3": 0.005},
         "box": {"min_mm": [-30, -30, -26], "max_mm": [30, 30, -24]}},
        {"name": "wall", "kind": "sliding", "box": {"min_mm": [24, -30, -30], "max_mm": [26, 30, 30]}}]})
    mesh = build_liver_mesh(cube, target_nodes=300, supports=(mode, sup))
    k = support_stiffness(sup, region_areas(mesh.points, mesh.facets, mesh.facet_region))
    assert k == {"visceral_kn": 0.02, "visceral_kt": 0.005}
    bp = BoundaryParams().with_supports(k)
    assert (bp.visceral_kn, bp.visceral_kt, bp.ligament_kn) == (0.02, 0.005, BoundaryParams().ligament_kn)
    mat = make_material("neo_hookean", {"C10": 1e-3}, nu=0.45)
    model = LiverModel.from_mesh(mesh, mat, bp, SolverOptions(formulation="p1"))
    F = np.array([0.1, 0.0, -0.5])
    res = model.solve(ToolLoad([0.0, 0.0, A / 2], F, 4.0))
    assert res.converged
    carried = res.reactions["visceral"] + res.reactions["rib"]
    np.testing.assert_allclose(carried, -F, rtol=0, atol=1e-6 * np.linalg.norm(F))
    assert res.reactions["visceral"][2] > 0.9 * 0.5  # the bed takes the vertical load
    with pytest.raises(ValueError, match="unknown BoundaryParams fields"):
        BoundaryParams().with_supports({"kidney_kn": 1.0})


def test_simulate_uses_a_livers_own_foundation_stiffness(monkeypatch):
    """simulate_cases builds each liver's FE model with its support_boundary in place of the config's."""
    import numpy as np

    from liverforce.config import compose
    from liverforce.fem.problem import LiverModel
    from liverforce.pipeline import simulate as sim_stage

    cfg = compose(["experiment=smoke"])
    seen = {}

    def spy(self, points, tets, facets, region, material, bp, options=None, *a, **kw):
        seen["bp"] = bp
        raise RuntimeError("stop after the model is built")

    class Mesh:  # the smallest LiverMesh stand-in simulate_cases reads before solving
        points = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
        tets = np.array([[0, 1, 2, 3]])
        facets = np.array([[1, 2, 3], [0, 2, 1], [0, 1, 3], [0, 3, 2]])
        facet_region = np.array([2, 3, 0, 0], np.int8)

    case = {"geometry_id": "g", "material_model": "neo_hookean", "material_param_names": ["C10"],
            "material_params_mpa": [0.002], "bulk_modulus_mpa": 0.1}
    monkeypatch.setattr(LiverModel, "__init__", spy)
    for own in ({}, {"ligament_kn": 0.123, "visceral_kt": 0.0456}):
        with pytest.raises(RuntimeError, match="stop after the model is built"):
            sim_stage.simulate_cases([case], {"g": Mesh()}, dict(cfg["simulate"]), cfg["boundary"],
                                     cfg["dataset"], supports={"g": own})
        if own:
            assert seen["bp"].ligament_kn == 0.123 and seen["bp"].visceral_kt == 0.0456
        else:
            assert seen["bp"].ligament_kn != 0.123
