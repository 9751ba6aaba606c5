"""Frames and units of imported files: RAS, LPS, a 4x4 transform, metres; all end as RAS mm."""

from __future__ import annotations

import json
import logging

import meshio
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from liverforce.geometry import GeometryError, load_surface
from liverforce.geometry.frames import frame_matrix, to_ras
from liverforce.geometry.procedural import procedural_liver

LPS = np.diag([-1.0, -1.0, 1.0])


@pytest.fixture(scope="module")
def liver():
    return procedural_liver(0)


def export(path, vertices, faces):
    """Binary PLY with float64 coordinates (trimesh would write float32)."""
    meshio.write(path, meshio.Mesh(np.asarray(vertices, float), [("triangle", np.asarray(faces))]), binary=True)
    return path


def same_surface(s, ref, atol=1e-9):
    assert np.array_equal(s.faces, ref.faces)
    assert np.allclose(s.vertices, ref.vertices, rtol=0, atol=atol)
    assert s.volume_mm3 == pytest.approx(ref.volume_mm3, rel=1e-9) and s.volume_mm3 > 0


# ------------------------------------------------------------------ parsing
def test_named_frames_and_matrices_parse():
    assert np.array_equal(frame_matrix("RAS")[0], np.eye(4)) and frame_matrix(None)[1] == "RAS"
    m, label = frame_matrix(" lps ")
    assert label == "LPS" and np.array_equal(m[:3, :3], LPS) and not m[:3, 3].any()
    given = [[0, 1, 0, 10], [-1, 0, 0, 0], [0, 0, 1, -5], [0, 0, 0, 1]]
    m, label = frame_matrix(given)
    assert label == "matrix" and np.array_equal(m, given)


@pytest.mark.parametrize("frame, match", [
    ("LSP", "unknown frame 'LSP'"),
    ([[1, 0, 0], [0, 1, 0], [0, 0, 1]], r"shape \(3, 3\), expected 4x4"),
    ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]], "last row"),
    ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 0], [0, 0, 0, 1]], "singular"),
    ([["a", 0, 0, 0]] * 4, "neither a name nor a 4x4"),
    ([[np.nan, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "NaN"),
])
def test_bad_frames_are_refused(frame, match):
    with pytest.raises(GeometryError, match=match):
        frame_matrix(frame, "liver.stl")


def test_a_reflection_reverses_the_winding_to_stay_outward(liver):
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])
    v, f, info = to_ras(liver.vertices, liver.faces, mirror)
    assert info["winding_reversed"] and info["rigid"] and info["determinant"] == -1.0
    assert np.array_equal(f, liver.faces[:, ::-1])
    v2, f2, info2 = to_ras(liver.vertices, liver.faces, frame_matrix("LPS")[0])
    assert not info2["winding_reversed"] and np.array_equal(f2, liver.faces)  # a rotation: kept


# ------------------------------------------------------------------ importing
def test_lps_file_imported_as_lps_is_the_ras_liver(tmp_path, liver, caplog):
    path = export(tmp_path / "liver_lps.ply", liver.vertices @ LPS.T, liver.faces)  # as 3D Slicer saves it
    with caplog.at_level(logging.INFO, logger="liverforce.geometry.importers"):
        s, msgs = load_surface(path, frame="LPS")
    same_surface(s, liver)
    assert msgs == []  # a conversion, not a repair
    conv = s.meta["conversion"]
    assert s.meta["frame"] == conv["frame"] == "LPS" and conv["winding_reversed"] is False
    assert np.array_equal(np.array(conv["to_ras_mm"])[:3, :3], LPS)
    assert "frame LPS: x and y negated" in conv["summary"] and "frame LPS" in caplog.text


def test_mirrored_file_with_a_reflecting_matrix(tmp_path, liver):
    """A file with x mirrored (a left-handed frame): det < 0, the winding is fixed silently and recorded."""
    flip = np.diag([-1.0, 1.0, 1.0])
    path = export(tmp_path / "liver_las.ply", liver.vertices @ flip.T, liver.faces[:, ::-1])  # outward in file
    frame = [[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    s, msgs = load_surface(path, frame=frame)
    assert np.allclose(s.vertices, liver.vertices, atol=1e-9) and s.volume_mm3 > 0
    assert np.array_equal(s.faces, liver.faces)
    assert not any("normals flipped" in m for m in msgs)
    assert s.meta["conversion"]["winding_reversed"] is True
    assert "reflection: triangle winding reversed" in s.meta["conversion"]["summary"]


def test_rigid_matrix_with_translation_in_mm_after_unit_scaling(tmp_path, liver):
    """File in metres in a rotated, shifted frame; M maps file mm (after scaling) to RAS mm."""
    rot = Rotation.from_euler("zyx", [30.0, -50.0, 100.0], degrees=True).as_matrix()
    t = np.array([120.0, -40.0, 15.0])  # mm
    file_m = ((liver.vertices - t) @ rot) / 1000.0  # rot^T (x - t), in metres
    path = export(tmp_path / "liver_rotated_m.ply", file_m, liver.faces)
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = rot, t
    s, _ = load_surface(path, units="m", frame=M.tolist())
    same_surface(s, liver, atol=1e-6)
    conv = s.meta["conversion"]
    assert conv["scale_to_mm"] == 1000.0 and conv["frame"] == "matrix" and conv["rigid"]
    assert np.allclose(np.array(conv["to_ras_mm"])[:3, :3], 1000.0 * rot)  # file units -> RAS mm


def test_the_same_liver_in_m_and_in_mm_gives_the_same_surface_in_mm(tmp_path, liver):
    mm = export(tmp_path / "liver_mm.ply", liver.vertices, liver.faces)
    m = export(tmp_path / "liver_m.ply", liver.vertices / 1000.0, liver.faces)
    s_mm, _ = load_surface(mm, units="mm")
    s_m, msgs = load_surface(m, units="m")
    assert msgs == []
    same_surface(s_m, s_mm, atol=1e-9)
    assert s_m.meta["units"] == "m" and s_m.meta["scale_to_mm"] == 1000.0
    s_auto, msgs = load_surface(m, units="auto")
    same_surface(s_auto, s_mm, atol=1e-9)
    assert any("units guessed as 'm'" in x for x in msgs)


def test_lps_is_refused_for_a_label_volume(tmp_path):
    import nibabel as nib

    data = np.zeros((20, 20, 20), dtype=np.uint8)
    data[4:16, 4:16, 4:16] = 1
    path = tmp_path / "seg.nii.gz"
    nib.save(nib.Nifti1Image(data, np.diag([12.0, 12.0, 12.0, 1.0])), path)
    with pytest.raises(GeometryError, match=r"seg\.nii\.gz: frame LPS given for a label volume.*Leave frame at RAS"):
        load_surface(path, frame="LPS")
    s, _ = load_surface(path)
    assert s.meta["frame"] == "RAS" and "header frame converted to RAS" in s.meta["conversion"]["summary"]


def test_geometry_stage_records_the_conversion(tmp_path, liver):
    from liverforce.pipeline.geometry import make_geometry

    path = export(tmp_path / "liver_lps_m.ply", (liver.vertices @ LPS.T) / 1000.0, liver.faces)
    spec = {"kind": "imported", "name": "x", "path": str(path), "units": "m", "label": None, "frame": "LPS"}
    make_geometry(spec, tmp_path / "out" / "imp-x.ply", tmp_path / "out" / "imp-x.json")
    meta = json.loads((tmp_path / "out" / "imp-x.json").read_text())
    conv = meta["conversion"]
    assert (conv["units"], conv["scale_to_mm"], conv["frame"]) == ("m", 1000.0, "LPS")
    assert np.allclose(conv["to_ras_mm"], np.diag([-1000.0, -1000.0, 1000.0, 1.0]))
    assert meta["frame"] == "LPS" and meta["spec"]["frame"] == "LPS"
    assert meta["volume_mm3"] == pytest.approx(liver.volume_mm3, rel=1e-9)


# ------------------------------------------------------------------ config
def test_config_takes_a_frame_and_names_the_key_when_it_is_wrong():
    from liverforce.config import ConfigError, compose

    four = "[[-1,0,0,0],[0,0,1,0],[0,1,0,0],[0,0,0,1]]"
    imported = f"[{{name:a,path:/x.stl,units:m,frame:LPS}},{{name:b,path:/y.stl,frame:{four}}}]"
    a, b = compose([f"geometry.imported={imported}"])["geometry"]["imported"]
    assert (a["frame"], a["units"]) == ("LPS", "m")
    assert b["frame"] == [[-1, 0, 0, 0], [0, 0, 1, 0], [0, 1, 0, 0], [0, 0, 0, 1]]
    assert compose(["geometry.imported=[{name:c,path:/z.stl}]"])["geometry"]["imported"][0]["frame"] == "RAS"
    with pytest.raises(ConfigError, match=r"config key 'geometry\.imported\[0\]\.frame': unknown frame 'LSP'"):
        compose(["geometry.imported=[{name:a,path:/x.stl,frame:LSP}]"])
    with pytest.raises(ConfigError, match=r"'geometry\.imported\[0\]\.frame': frame matrix is singular"):
        compose(["geometry.imported=[{name:a,path:/x.stl,frame:[[0,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]"])
