"""A lab's exertion point refused (too far from the surface, on a fixed support) is named as the lab gave it: the
file and its row, the numbers in the file's units and frame, then where it lies as meshed. Before, only the
converted RAS mm was shown ('exertion point 1 [149.78, 275.552, 1210.477] (mesh frame, mm)'), a point the lab's
file (LPS metres, a scanner origin a metre away) holds nowhere, and no file was named."""

from __future__ import annotations

import meshio
import numpy as np
import pytest

from liverforce.mesh.regions import tag_regions
from liverforce.mesh.supports import PointFrame, SupportError, exertion_points_mesh, snap_exertion_points
from liverforce.mesh.types import REGION_CODES

LPS_M = np.array([-1.0, -1.0, 1.0])
ORIGIN_MM = np.array([-150.0, -200.0, 1200.0])  # a CT scanner's origin


def to_file(ras_mm):
    return (np.asarray(ras_mm) * LPS_M + ORIGIN_MM) / 1000.0  # LPS metres, scanner frame


def test_a_far_point_in_a_file_is_named_by_file_row_and_value_at_the_mesh_stage(tmp_path, liver_surface):
    from liverforce.config import compose
    from liverforce.pipeline.geometry import make_geometry
    from liverforce.pipeline.mesh import make_mesh

    V, F = liver_surface.vertices, liver_surface.faces
    path = tmp_path / "liver_lps_m.vtu"
    meshio.write(path, meshio.Mesh(to_file(V), [("triangle", F)]))
    top = V[np.argsort(-(V[:, 1] + V[:, 2]))[[0, 40]]]
    pts = to_file(np.vstack([top[0], top[1] + [0.0, 20.0, 0.0]]))  # the second 20 mm in front of the liver
    tools = tmp_path / "tools.csv"
    np.savetxt(tools, pts, delimiter=",", header="x,y,z", comments="")
    spec = {"kind": "imported", "name": "ct", "path": str(path), "units": "m", "label": None, "frame": "LPS",
            "exertion_points": {"path": str(tools)}}
    surface = tmp_path / "geometry" / "imp-ct.ply"
    make_geometry(spec, surface, surface.with_suffix(".json"))
    cfg = {**compose(["experiment=smoke"])["mesh"], "target_nodes": 200, "refine_radius_mm": 0.0,
           "refine_ivc_edge_mm": 0.0}
    out = tmp_path / "mesh"
    given = ", ".join(f"{x:.6g}" for x in pts[1])
    with pytest.raises(SupportError, match=rf"exertion point 1 \(point 2 of {tools}: \[{given}\] in m .*RAS mm as "
                                           r"meshed\) is 1\d\.?\d* mm from the surface"):
        make_mesh(surface, cfg, 0, out / "imp-ct.vtu", out / "imp-ct.features.json", out / "imp-ct.regions.png")
    assert not (out / "imp-ct.vtu").exists() and not (out / "imp-ct.features.json").exists()


@pytest.mark.parametrize("spec_of", ["coordinates", "vertex_ids"])
def test_a_point_on_the_fixed_support_is_named_as_given(liver_surface, spec_of):
    V, F = liver_surface.vertices, liver_surface.faces
    region, _ = tag_regions(V, F)
    on_ivc = np.unique(F[region == REGION_CODES["ivc"]])
    vid = int(np.setdiff1d(on_ivc, F[region != REGION_CODES["ivc"]])[0])  # a vertex whose every facet is the IVC's
    if spec_of == "coordinates":
        spec, frame = {"coordinates_mm": [V[0].tolist(), V[vid].tolist()]}, PointFrame()
        names = rf"exertion_points\.coordinates_mm\[1\] \[{', '.join(f'{x:.6g}' for x in V[vid])}\] mm"
    else:
        spec, frame = {"vertex_ids": [0, vid]}, PointFrame()
        names = rf"exertion_points\.vertex_ids\[1\] = {vid}"
    labels = []
    xyz = exertion_points_mesh(spec, frame, (lambda: V) if spec_of == "vertex_ids" else None, labels=labels)
    with pytest.raises(SupportError, match=rf"exertion point 1 \({names}; .* RAS mm as meshed\) lies on a fixed "
                                           r"support, the built-in IVC region \(auto-tagged on the posterior"):
        snap_exertion_points(V, F, region, xyz, labels=labels)


# --------------------------------------------------------------------------- which fixed support
@pytest.mark.parametrize("on", ["lab_clamp", "built_in_ivc"])
def test_a_point_on_a_fixed_support_names_which_support_at_the_mesh_stage(tmp_path, liver_surface, on):
    """Before, 'lies on a fixed support' named none: with a lab's clamp added to the built-in IVC (mode add)
    the lab could not tell which of the two its tool position hit."""
    from liverforce.config import compose
    from liverforce.pipeline.geometry import make_geometry
    from liverforce.pipeline.mesh import make_mesh

    V, F = liver_surface.vertices, liver_surface.faces
    path = tmp_path / "liver.ply"
    meshio.write(path, meshio.Mesh(V, [("triangle", F)]), binary=True)
    clamp = V[np.argmax(V[:, 1] + V[:, 2])]  # anterior-superior, far from the IVC's posterior patch
    region, _ = tag_regions(V, F)
    on_ivc = np.setdiff1d(np.unique(F[region == REGION_CODES["ivc"]]), F[region != REGION_CODES["ivc"]])
    point = clamp if on == "lab_clamp" else V[on_ivc[0]]
    spec = {"kind": "imported", "name": "lab", "path": str(path), "units": "mm", "label": None, "frame": "RAS",
            "supports": {"mode": "add", "list": [{"name": "clamp", "kind": "fixed",
                                                   "sphere": {"center_mm": clamp.tolist(), "radius_mm": 15.0}}]},
            "exertion_points": {"coordinates_mm": [point.tolist()]}}
    surface = tmp_path / "geometry" / "imp-lab.ply"
    make_geometry(spec, surface, surface.with_suffix(".json"))
    cfg = {**compose(["experiment=smoke"])["mesh"], "target_nodes": 200, "refine_radius_mm": 0.0,
           "refine_ivc_edge_mm": 0.0, "regions_check": "off"}
    out = tmp_path / "mesh"
    given = rf"exertion point 0 \(exertion_points\.coordinates_mm\[0\] \[{', '.join(f'{x:.6g}' for x in point)}\] mm"
    which = (r"a fixed support, the lab's 'clamp' \(geometry\.imported\[lab\]\.supports\.list\[0\], selected by "
             r"sphere\).*shrink or move the support 'clamp'" if on == "lab_clamp" else
             r"a fixed support, the built-in IVC region \(auto-tagged .*mesh\.regions\.ivc_radius_mm")
    with pytest.raises(SupportError, match=rf"{given}; .* RAS mm as meshed\) lies on {which}"):
        make_mesh(surface, cfg, 0, out / "imp-lab.vtu", out / "imp-lab.features.json", out / "imp-lab.regions.png")
    assert not (out / "imp-lab.vtu").exists()


# --------------------------------------------------------------------------- too far: the other readings
def _anterior(V, k=3):
    """``k`` vertices on the liver's front, well apart."""
    order = np.argsort(-V[:, 1])
    return V[order[[0, 60, 120][:k]]]


def _refusal(V, F, spec, frame=PointFrame(), base_dir=None) -> str:
    """The refusal of the exertion points ``spec`` as the mesh stage reads and snaps them."""
    labels, reading = [], []
    xyz = exertion_points_mesh(spec, frame, lambda: V, base_dir=base_dir, labels=labels, reading=reading)
    with pytest.raises(SupportError) as err:
        snap_exertion_points(V, F, None, xyz, labels=labels, frame=frame, reading=reading[0])
    msg = str(err.value)
    assert "mm from the surface (limit 5.0 mm): check its units and frame" in msg
    return msg


def test_far_points_that_fit_mirrored_say_to_state_the_frame(liver_surface):
    """Points given in LPS for a liver in RAS 150 mm off the origin land far off it: the refusal says that,
    mirrored in x and y, all would lie on the surface, and which setting states their frame."""
    V, F = liver_surface.vertices + [150.0, 80.0, 0.0], liver_surface.faces
    msg = _refusal(V, F, {"coordinates_mm": (_anterior(V) * LPS_M).tolist()})
    assert "exertion point 0 (exertion_points.coordinates_mm[0]" in msg
    assert ". Mirrored in x and y (coordinates in RAS read as LPS, or in LPS read as RAS" in msg
    assert "all 3 given points would lie within 5 mm of the surface (0 mm on average, max 0 mm), so they are " \
           "likely in LPS: they state no frame, so they are read in the geometry's: state exertion_points.frame: " \
           "LPS (changing geometry.imported[].frame would turn the liver and the points alike)" in msg
    assert "Scaled by" not in msg


def test_a_stated_frame_is_mirrored_in_its_own_coordinates(liver_surface):
    """Points stating frame: LPS beside a liver whose frame is a 4x4 with a translation are read in the world's
    RAS (the translation does not apply to them): they are mirrored there, not about the 4x4's origin."""
    V, F = liver_surface.vertices + [150.0, 80.0, 0.0], liver_surface.faces
    shift = np.eye(4)
    shift[:3, 3] = [100.0, 50.0, 0.0]  # the geometry file's frame: RAS mm shifted
    frame = PointFrame(matrix=tuple(map(tuple, shift)), frame_name=None)
    msg = _refusal(V, F, {"coordinates_mm": _anterior(V).tolist(), "frame": "LPS"}, frame)  # RAS numbers
    assert "all 3 given points would lie within 5 mm of the surface (0 mm on average" in msg
    assert "so they are likely in RAS: if they are in RAS, state exertion_points.frame: RAS; if LPS is right" in msg
    cm = _refusal(V, F, {"coordinates_mm": (_anterior(V) / 10.0).tolist(), "frame": "RAS"}, frame)
    assert "Scaled by 10 (their numbers in cm, read in mm) all 3 given points would lie within 5 mm" in cm
    assert "so they are likely in cm: coordinates_mm are mm: give them in mm" in cm and "Mirrored" not in cm


@pytest.mark.parametrize("factor, unit", [(0.001, "m"), (0.1, "cm")])
def test_far_points_in_other_units_say_which(liver_surface, tmp_path, factor, unit):
    """A point file in m (or cm) read in mm, stated or as the geometry's units: the refusal names the units that
    fit and the setting; a liver in m with a file of mm numbers read in its m likewise."""
    V, F = liver_surface.vertices, liver_surface.faces
    path = tmp_path / "tools.csv"
    np.savetxt(path, _anterior(V) * factor, delimiter=",")
    msg = _refusal(V, F, {"path": str(path), "units": "mm"})
    assert (f"Scaled by {1 / factor:g} (their numbers in {unit}, read in mm) all 3 given points would lie within "
            f"5 mm of the surface") in msg
    assert f"so they are likely in {unit}: state exertion_points.units: {unit}" in msg and "Mirrored" not in msg
    np.savetxt(path, _anterior(V), delimiter=",")  # mm numbers, read in the geometry's m
    msg = _refusal(V, F, {"path": str(path)}, PointFrame(scale=1000.0, units="m"))
    assert ("Scaled by 0.001 (their numbers in mm, read in m) all 3 given points would lie within 5 mm of the "
            "surface") in msg
    assert ("so they are likely in mm: the file states no units, so its numbers are read in the geometry's: state "
            "exertion_points.units: mm") in msg


def test_a_markups_file_is_told_to_correct_its_coordinate_system_not_given_settings(liver_surface, tmp_path):
    """A 3D Slicer markups file states its frame and units: the hint says to correct its coordinateSystem (the
    config refuses frame and units beside one), and names no units."""
    import json

    V, F = liver_surface.vertices + [150.0, 80.0, 0.0], liver_surface.faces
    pts = _anterior(V)  # RAS numbers in a file that says LPS
    doc = {"markups": [{"type": "Fiducial", "coordinateSystem": "LPS", "coordinateUnits": "mm",
                        "controlPoints": [{"label": f"T{i}", "position": p.tolist(), "positionStatus": "defined"}
                                          for i, p in enumerate(pts)]}]}
    path = tmp_path / "tools.mrk.json"
    path.write_text(json.dumps(doc))
    msg = _refusal(V, F, {"path": str(path)})
    assert ("so they are likely in RAS: the markups file states coordinateSystem LPS: if its points are in RAS, "
            "correct that in the file (export it again from 3D Slicer)") in msg
    assert "exertion_points.frame" not in msg and "exertion_points.units" not in msg


def test_units_beside_coordinates_or_vertex_ids_are_refused(liver_surface):
    V = liver_surface.vertices
    for spec in ({"coordinates_mm": [V[0].tolist()], "units": "m"}, {"vertex_ids": [0], "units": "m"}):
        with pytest.raises(SupportError, match=r"exertion_points\.units: .* take no units .* applies to a point "
                                               r"file \(path\)"):
            exertion_points_mesh(spec, PointFrame(), lambda: V)


def test_a_point_truly_off_the_liver_gets_no_other_reading(liver_surface):
    V, F = liver_surface.vertices, liver_surface.faces
    msg = _refusal(V, F, {"coordinates_mm": (_anterior(V) + [0.0, 30.0, 0.0]).tolist()})  # 30 mm in front
    assert msg.endswith("or move it onto the liver")
