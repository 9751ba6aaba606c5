"""Supports given as another segment of the liver's segmentation: where the liver touches it.

A 3D Slicer segmentation in LPS holds the liver (an ellipsoid), an inferior vena cava (a cylinder lying in a
groove of the liver's posterior face, as the real one does) and a kidney that does not touch the liver.
The contact patch is worked out here from the shapes in RAS, not from the selector's code.
"""

from __future__ import annotations

import numpy as np
import pytest

from liverforce.geometry import load_surface
from liverforce.mesh.groups import read_volume_groups
from liverforce.mesh.supports import PointFrame, Support, SupportError, parse_supports, select_facets

SHAPE = (90, 70, 50)
SPACING = np.array([2.0, 2.0, 2.5])
IJK_TO_LPS = np.array([[-2.0, 0.0, 0.0, 80.0], [0.0, -2.0, 0.0, 60.0], [0.0, 0.0, 2.5, -100.0], [0, 0, 0, 1.0]])
IJK = np.indices(SHAPE).transpose(1, 2, 3, 0).astype(float)
LIVER_C, LIVER_R = np.array([45.0, 35.0, 25.0]), np.array([36.0, 26.0, 18.0])  # voxels: 144 x 104 x 90 mm
IVC_AXIS_IJ, IVC_R = np.array([45.0, 35.0 - 26.0 + 3.0]), 4.0  # along k, sunk 3 voxels into the liver's -j side


def masks():
    liver = (((IJK - LIVER_C) / LIVER_R) ** 2).sum(axis=-1) <= 1.0
    ivc = (np.linalg.norm(IJK[..., :2] - IVC_AXIS_IJ, axis=-1) <= IVC_R) & (np.abs(IJK[..., 2] - 25) <= 10)
    liver &= ~ivc  # the liver wraps round the cava: a groove, no overlap
    kidney = (np.linalg.norm(IJK - np.array([8.0, 8.0, 8.0]), axis=-1) <= 4.0)
    assert not (kidney & liver).any()
    return liver, ivc, kidney


def to_ras(ijk):
    lps = np.asarray(ijk, float) @ IJK_TO_LPS[:3, :3].T + IJK_TO_LPS[:3, 3]
    return lps * np.array([-1.0, -1.0, 1.0])


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    import slicerio

    path = tmp_path_factory.mktemp("seg") / "Segmentation.seg.nrrd"
    seg = slicerio.create_segmentation(SHAPE, IJK_TO_LPS)
    liver, ivc, kidney = masks()
    for k, (name, m) in enumerate([("liver", liver), ("inferior_vena_cava", ivc), ("kidney", kidney)], start=1):
        slicerio.add_segment(seg, m, {"id": f"Segment_{k}", "name": name})
    slicerio.write_segmentation(str(path), seg)
    surface, _ = load_surface(path, label="liver")
    assert surface.meta["label"] == 1 and surface.meta["segment"] == "Segment_1"
    groups = read_volume_groups(path, surface.meta["label"], surface.meta["segment"])
    return path, surface, groups


def select(scene, group, kind="fixed"):
    _, surface, groups = scene
    (support,) = parse_supports({"mode": "add", "list": [{"name": "cava", "kind": kind, "group": group}]})[1]
    frame = PointFrame.from_surface_meta(surface.meta)
    return select_facets(surface.vertices, surface.faces, support, frame, file_groups=lambda: groups)


def distance_to_cava_mm(points_ras):
    """Distance (mm) of RAS points from the cava's voxels as a solid cylinder (radius 4 voxels of 2 mm, ends at
    the outer faces of voxels k = 15 and 35), worked out from its axis in RAS."""
    end_lo, end_hi = to_ras([*IVC_AXIS_IJ, 14.5]), to_ras([*IVC_AXIS_IJ, 35.5])
    length = np.linalg.norm(end_hi - end_lo)
    u = (end_hi - end_lo) / length
    rel = points_ras - end_lo
    t = rel @ u
    radial = np.linalg.norm(rel - np.outer(t, u), axis=1)
    beyond = np.maximum(np.maximum(-t, t - length), 0.0)
    return np.hypot(np.maximum(radial - IVC_R * 2.0, 0.0), beyond)


@pytest.mark.parametrize("group", ["inferior_vena_cava", "Segment_2", 2])
def test_the_cava_segment_selects_the_groove_it_lies_in(scene, group):
    _, surface, _ = scene
    mask, info = select(scene, group)
    cent = surface.vertices[surface.faces].mean(axis=1)
    d = distance_to_cava_mm(cent)
    assert info["segment"].startswith("segment 'inferior_vena_cava' (ID Segment_2, label 2")
    assert info["contact_mm"] == pytest.approx([3.0, 3.0, 3.75]) and info["n_facets"] == mask.sum() > 50
    # every selected facet hugs the cylinder; every facet hugging it is selected
    assert d[mask].max() < 1.5 * 2.5 + 1.5
    assert mask[d < 0.5].all() and (d < 0.5).sum() > 0.5 * mask.sum()
    # on the posterior side, where the cava is (RAS: -y is posterior; LPS +j is posterior too)
    assert cent[mask, 1].max() < to_ras(LIVER_C)[1] - 30.0


def test_a_segment_the_liver_does_not_touch_is_refused_with_the_distance(scene):
    with pytest.raises(SupportError, match=r"segment 'kidney' \(ID Segment_3, label 3\) of .*Segmentation\.seg\.nrrd "
                                           r"does not touch the liver \(its nearest surface facet is [0-9.]+ "
                                           r"voxels away, beyond 1\.5\)"):
        select(scene, "kidney")


@pytest.mark.parametrize("group, message", [
    ("liver", r"segment 'liver' \(ID Segment_1, label 1\) is the liver itself"),
    ("spleen", r"no segment is named or has ID 'spleen'.*'inferior_vena_cava' \(label 2\)"),
    ({"array": "labels", "value": 2}, r"is a label volume, it has no cell-data arrays"),
    (0, r"label 0 is the background"),
])
def test_a_wrong_segment_is_refused_by_name(scene, group, message):
    with pytest.raises(SupportError, match=rf"support 'cava' group .*{message}"):
        select(scene, group)


def test_a_plain_label_volume_takes_a_label_value(tmp_path):
    import nibabel as nib

    liver, ivc, _ = masks()
    data = np.zeros(SHAPE, np.uint8)
    data[liver], data[ivc] = 5, 9
    path = tmp_path / "seg.nii.gz"
    affine = np.diag([-1.0, -1.0, 1.0, 1.0]) @ IJK_TO_LPS  # NIfTI is RAS: the same world as the LPS file
    nib.save(nib.Nifti1Image(data, affine), path)
    surface, _ = load_surface(path, label=5)
    groups = read_volume_groups(path, 5)
    mask, info = select_facets(surface.vertices, surface.faces, Support("cava", "fixed", ("group", {"value": 9})),
                               PointFrame.from_surface_meta(surface.meta), file_groups=lambda: groups)
    d = distance_to_cava_mm(surface.vertices[surface.faces].mean(axis=1))
    assert info["segment"] == "label 9" and mask.sum() > 50 and d[mask].max() < 1.5 * 2.5 + 1.5
    with pytest.raises(SupportError, match=r"'cava' names a segment, but the file names none"):
        select_facets(surface.vertices, surface.faces, Support("x", "fixed", ("group", {"name": "cava"})),
                      PointFrame.from_surface_meta(surface.meta), file_groups=lambda: groups)


def test_points_beside_a_label_volume_state_their_frame(scene, tmp_path):
    """A label volume's points are RAS (its header's world, converted); LPS ones (DICOM, ITK, Slicer markups
    files) say frame: LPS, on exertion points and on coordinate selectors alike."""
    from liverforce.mesh.supports import exertion_points_mesh, snap_exertion_points

    _, surface, _ = scene
    frame = PointFrame.from_surface_meta(surface.meta)
    side_ras = surface.vertices[np.argmax(surface.vertices[:, 0])]  # the liver's rightmost point, RAS mm
    side_lps_m = side_ras * np.array([-1.0, -1.0, 1.0]) / 1000.0
    np.savetxt(tmp_path / "points_lps_m.csv", [side_lps_m], delimiter=",")
    for spec in ({"coordinates_mm": [(side_lps_m * 1000).tolist()], "frame": "LPS"},
                 {"path": str(tmp_path / "points_lps_m.csv"), "units": "m", "frame": "LPS"}):
        q = exertion_points_mesh(spec, frame)
        assert np.allclose(q, side_ras, atol=1e-9)
        snap_exertion_points(surface.vertices, surface.faces, None, q)
    with pytest.raises(SupportError, match=r"from the surface .*a label volume's being its header's world in RAS "
                                           r"then the geometry's frame, unless they state frame: LPS"):
        snap_exertion_points(surface.vertices, surface.faces, None,
                             exertion_points_mesh({"coordinates_mm": [(side_lps_m * 1000).tolist()]}, frame))
    with pytest.raises(SupportError, match=r"exertion_points.frame: vertex ids have no frame"):
        exertion_points_mesh({"vertex_ids": [0], "frame": "LPS"}, frame)
    # a sphere stated in LPS takes the facets the same sphere takes in RAS
    ras = Support("s", "fixed", ("sphere", {"center_mm": side_ras.tolist(), "radius_mm": 20.0}))
    lps = Support("s", "fixed", ("sphere", {"center_mm": (side_ras * [-1, -1, 1]).tolist(), "radius_mm": 20.0,
                                            "frame": "LPS"}))
    m_ras, _ = select_facets(surface.vertices, surface.faces, ras, frame)
    m_lps, _ = select_facets(surface.vertices, surface.faces, lps, frame)
    assert m_ras.sum() > 20 and (m_ras == m_lps).all()
    with pytest.raises(SupportError, match=r"supports.list\[0\].sphere.frame: unknown frame 'XYZ'"):
        parse_supports({"list": [{"name": "cava", "kind": "fixed",
                                  "sphere": {"center_mm": [0, 0, 0], "radius_mm": 5, "frame": "XYZ"}}]})


def test_the_config_takes_a_frame_on_points_and_refuses_a_bad_one():
    from liverforce.config import ConfigError, compose

    base = "geometry.imported=[{name:a,path:/x/seg.seg.nrrd,label:liver,exertion_points:{coordinates_mm:[[1,2,3]]"
    compose([base + ",frame:LPS}}]"])
    with pytest.raises(ConfigError, match=r"'geometry.imported\[0\].exertion_points.frame'"):
        compose([base + ",frame:XYZ}}]"])


def _mrk_json(path, points, system="LPS", status=None):
    import json

    cps = [{"id": str(k + 1), "label": f"F-{k + 1}", "position": list(map(float, p)),
            **({"positionStatus": status[k]} if status else {})} for k, p in enumerate(points)]
    doc = {"@schema": "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/Resources/"
                      "Schema/markups-schema-v1.0.3.json#",
           "markups": [{"type": "Fiducial", "coordinateSystem": system, "coordinateUnits": "mm",
                        "controlPoints": cps}]}
    path.write_text(json.dumps(doc))
    return path


def _fcsv(path, points, system_line):
    rows = [f"vtkMRMLMarkupsFiducialNode_{k},{p[0]},{p[1]},{p[2]},0,0,0,1,1,1,0,F-{k + 1},,"
            for k, p in enumerate(points)]
    path.write_text("# Markups fiducial file version = 4.11\n" + system_line + "\n"
                    "# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID\n"
                    + "\n".join(rows) + "\n")
    return path


def test_slicer_markups_files_give_points_in_their_own_coordinate_system(scene, tmp_path):
    """Tool positions placed in 3D Slicer and saved as .mrk.json (LPS, Slicer's default since 4.11) or as a
    legacy .fcsv (LPS, or RAS written as 0) land where they were placed, with no units or frame to give."""
    from liverforce.mesh.supports import exertion_points_mesh, snap_exertion_points

    _, surface, _ = scene
    frame = PointFrame.from_surface_meta(surface.meta)
    ras = surface.vertices[[np.argmax(surface.vertices[:, 0]), np.argmax(surface.vertices[:, 2])]]
    lps = ras * np.array([-1.0, -1.0, 1.0])
    files = [_mrk_json(tmp_path / "tool.mrk.json", lps), _mrk_json(tmp_path / "tool_ras.mrk.json", ras, "RAS"),
             _fcsv(tmp_path / "tool.fcsv", lps, "# CoordinateSystem = LPS"),
             _fcsv(tmp_path / "old.fcsv", ras, "# CoordinateSystem = 0")]
    for path in files:
        q = exertion_points_mesh({"path": str(path)}, frame)
        assert np.allclose(q, ras, atol=1e-9), path.name
        snap_exertion_points(surface.vertices, surface.faces, None, q)
    # a support selected by a markups file of points round the cava's groove
    cent = surface.vertices[surface.faces].mean(axis=1)
    near = surface.vertices[np.unique(surface.faces[distance_to_cava_mm(cent) < 0.5])]
    support = Support("cava", "fixed", ("file", {"path": str(_mrk_json(tmp_path / "cava.mrk.json",
                                                                           near * [-1, -1, 1]))}))
    mask, info = select_facets(surface.vertices, surface.faces, support, frame)
    assert info["snap_mm"]["max"] < 1e-9 and mask.sum() > 50 and distance_to_cava_mm(cent[mask]).max() < 0.5 + 4.0


@pytest.mark.parametrize("spec, message", [
    ({"units": "m"}, r"tool\.mrk\.json is a 3D Slicer markups file, which states its own coordinate system and "
                     r"units: leave out units"),
    ({"frame": "LPS"}, r"leave out frame"),
])
def test_a_markups_file_takes_no_units_or_frame(tmp_path, spec, message):
    from liverforce.mesh.supports import exertion_points_mesh

    path = _mrk_json(tmp_path / "tool.mrk.json", [[1.0, 2.0, 3.0]])
    with pytest.raises(SupportError, match=message):
        exertion_points_mesh({"path": str(path), **spec})


def test_an_unplaced_or_broken_markups_point_is_refused_by_its_label(tmp_path):
    from liverforce.mesh.supports import exertion_points_mesh

    path = _mrk_json(tmp_path / "tool.mrk.json", [[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]], status=["defined", "undefined"])
    with pytest.raises(SupportError, match=r"control point 'F-2' has no position \(positionStatus undefined\)"):
        exertion_points_mesh({"path": str(path)})
    (tmp_path / "bad.mrk.json").write_text("{\"markups\": ")
    with pytest.raises(SupportError, match=r"bad\.mrk\.json: not a readable 3D Slicer markups file"):
        exertion_points_mesh({"path": str(tmp_path / "bad.mrk.json")})


def test_a_registration_frame_moves_stated_and_markups_points_with_the_liver(tmp_path):
    """A label volume imported with a 4x4 frame (a registration after its header's map): points in the
    image's world, stated LPS or RAS or from a markups file, land where that frame puts the liver."""
    import nibabel as nib

    from liverforce.mesh.supports import exertion_points_mesh

    liver, _, _ = masks()
    data = np.zeros(SHAPE, np.uint8)
    data[liver] = 5
    path = tmp_path / "seg.nii.gz"
    nib.save(nib.Nifti1Image(data, np.diag([-1.0, -1.0, 1.0, 1.0]) @ IJK_TO_LPS), path)
    shift = [[1, 0, 0, 4.0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    plain, _ = load_surface(path, label=5)
    moved, _ = load_surface(path, label=5, frame=shift)
    assert np.allclose(moved.vertices, plain.vertices + [4.0, 0, 0])
    frame = PointFrame.from_surface_meta(moved.meta)
    world_ras = plain.vertices[np.argmax(plain.vertices[:, 0])]  # a point of the image's world, RAS mm
    mrk = _mrk_json(tmp_path / "p.mrk.json", [world_ras * [-1, -1, 1]])
    for spec in ({"coordinates_mm": [world_ras.tolist()]},  # the file's frame: the header's world, then shift
                 {"coordinates_mm": [world_ras.tolist()], "frame": "RAS"},
                 {"coordinates_mm": [(world_ras * [-1, -1, 1]).tolist()], "frame": "LPS"},
                 {"path": str(mrk)}):
        assert np.allclose(exertion_points_mesh(spec, frame), world_ras + [4.0, 0, 0], atol=1e-9), spec


def test_beside_a_surface_in_a_4x4_frame_world_points_are_the_meshs_ras(tmp_path):
    """An STL's 4x4 frame maps its coordinates to RAS mm: points that state a frame, or come from a markups
    file, are in that RAS (the mesh's), and points without one go through the 4x4 as the file's do."""
    from liverforce.geometry.procedural import cube_phantom
    from liverforce.mesh.supports import exertion_points_mesh

    cube = cube_phantom(120.0)
    path = tmp_path / "cube.stl"
    cube.to_trimesh().export(path)
    m = [[0, -1, 0, 10.0], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    s, _ = load_surface(path, units="mm", frame=m, size_range_mm=None)
    frame = PointFrame.from_surface_meta(s.meta)
    p_ras = np.array([[1.0, 2.0, 3.0]])
    for spec in ({"coordinates_mm": (p_ras * [-1, -1, 1]).tolist(), "frame": "LPS"},
                 {"coordinates_mm": p_ras.tolist(), "frame": "RAS"},
                 {"path": str(_mrk_json(tmp_path / "p.mrk.json", p_ras * [-1, -1, 1]))}):
        assert np.allclose(exertion_points_mesh(spec, frame), p_ras), spec
    assert np.allclose(exertion_points_mesh({"coordinates_mm": p_ras.tolist()}, frame), [[8.0, 1.0, 3.0]])


def test_a_file_of_vertex_ids_with_a_frame_is_refused(tmp_path):
    from liverforce.mesh.supports import exertion_points_mesh

    np.savetxt(tmp_path / "ids.txt", [3, 4], fmt="%d")
    with pytest.raises(SupportError, match=r"exertion_points.frame: vertex ids have no frame"):
        exertion_points_mesh({"path": str(tmp_path / "ids.txt"), "frame": "LPS"}, PointFrame(),
                             file_vertices=lambda: np.zeros((10, 3)))
    support = Support("ids", "fixed", ("file", {"path": str(tmp_path / "ids.txt"), "frame": "LPS"}))
    with pytest.raises(SupportError, match=r"support 'ids' file.frame: vertex ids have no frame"):
        select_facets(np.zeros((10, 3)), np.array([[0, 1, 2]]), support, file_vertices=lambda: np.zeros((10, 3)))


def test_markups_units_as_a_ucum_code_and_markups_with_units_refused_in_the_config(tmp_path):
    import json

    from liverforce.config import ConfigError, compose
    from liverforce.mesh.supports import exertion_points_mesh

    path = tmp_path / "p.mrk.json"
    path.write_text(json.dumps({"markups": [{"type": "Fiducial", "coordinateSystem": "RAS", "coordinateUnits": {
        "CodeValue": "um", "CodingSchemeDesignator": "UCUM", "CodeMeaning": "micrometer"},
        "controlPoints": [{"label": "F-1", "position": [1000.0, 2000.0, 3000.0]}]}]}))
    assert np.allclose(exertion_points_mesh({"path": str(path)}), [[1.0, 2.0, 3.0]])
    base = "geometry.imported=[{name:a,path:/x/seg.seg.nrrd,label:liver,"
    with pytest.raises(ConfigError, match=r"'geometry.imported\[0\].exertion_points'.*markups file.*leave out units"):
        compose([base + "exertion_points:{path:/x/t.mrk.json,units:m}}]"])
    with pytest.raises(ConfigError, match=r"supports.list\[0\].file.*markups file.*leave out frame"):
        compose([base + "supports:{list:[{name:c,kind:fixed,file:{path:/x/t.fcsv,frame:LPS}}]}}]"])


def test_digits_for_a_group_that_also_name_a_segment_are_refused(tmp_path):
    import slicerio

    seg = slicerio.create_segmentation(SHAPE, IJK_TO_LPS)
    liver, ivc, _ = masks()
    slicerio.add_segment(seg, liver, {"id": "Segment_1", "name": "liver"})
    slicerio.add_segment(seg, ivc, {"id": "Segment_2", "name": "1"})  # a segment named "1", label 2
    path = tmp_path / "s.seg.nrrd"
    slicerio.write_segmentation(str(path), seg)
    surface, _ = load_surface(path)
    groups = read_volume_groups(path, surface.meta["label"], surface.meta["segment"])
    (support,) = parse_supports({"list": [{"name": "cava", "kind": "fixed", "group": "1"}]})[1]
    with pytest.raises(SupportError, match=r"'1' is a label value and also the name or ID of segment '1' "
                                           r"\(label 2\)"):
        select_facets(surface.vertices, surface.faces, support, PointFrame.from_surface_meta(surface.meta),
                      file_groups=lambda: groups)
