"""Importers: every format round-trips a known body; units; label volumes."""

from __future__ import annotations

import json
import logging

import meshio
import numpy as np
import pytest
import trimesh

from liverforce.geometry import GeometryError, load_surface
from liverforce.geometry.procedural import cube_phantom
from liverforce.geometry.readers import read_gmsh_v1, read_vtk_polydata

EDGE = 200.0  # a liver-sized cube (mm), so the size check passes
VOLUME = EDGE**3


@pytest.fixture(scope="module")
def cube():
    return cube_phantom(EDGE, divisions=2)


def cube_tets(edge: float = EDGE):
    """Points and 6 tets of a cube [0, edge]^3 (Kuhn split, mixed orientation)."""
    p = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], dtype=float) * edge
    tets = np.array([[0, 1, 3, 7], [0, 1, 7, 5], [0, 2, 7, 3], [0, 2, 6, 7], [0, 4, 5, 7], [0, 4, 7, 6]])
    return p, tets


def write_vtk_polydata(path, vertices, faces, binary: bool, new_layout: bool = False) -> None:
    """Hand-written legacy VTK POLYDATA (classic or 5.1 OFFSETS/CONNECTIVITY layout)."""
    n, k = len(vertices), len(faces)
    head = f"# vtk DataFile Version {'5.1' if new_layout else '3.0'}\ntest\n{'BINARY' if binary else 'ASCII'}\nDATASET POLYDATA\n"
    out = bytearray(head.encode())
    out += f"POINTS {n} double\n".encode()
    if binary:
        out += vertices.astype(">f8").tobytes() + b"\n"
    else:
        out += "\n".join(" ".join(repr(float(x)) for x in row) for row in vertices).encode() + b"\n"
    if new_layout:
        offsets = np.arange(0, 3 * k + 1, 3)
        out += f"POLYGONS {k + 1} {3 * k}\nOFFSETS vtktypeint64\n".encode()
        out += (offsets.astype(">i8").tobytes() + b"\n") if binary else (" ".join(map(str, offsets)) + "\n").encode()
        out += b"CONNECTIVITY vtktypeint64\n"
        out += (faces.astype(">i8").tobytes() + b"\n") if binary else (" ".join(map(str, faces.ravel())) + "\n").encode()
    else:
        cells = np.hstack([np.full((k, 1), 3), faces])
        out += f"POLYGONS {k} {4 * k}\n".encode()
        out += (cells.astype(">i4").tobytes() + b"\n") if binary else ("\n".join(" ".join(map(str, r)) for r in cells) + "\n").encode()
    out += f"CELL_DATA {k}\nSCALARS id int 1\nLOOKUP_TABLE default\n".encode()
    out += (np.arange(k).astype(">i4").tobytes()) if binary else (" ".join(map(str, range(k))) + "\n").encode()
    path.write_bytes(bytes(out))


def write_gmsh_v1(path, points, tets, triangles=None, first_id: int = 11) -> None:
    """Hand-written ASCII Gmsh v1 file with non-contiguous node numbers."""
    ids = np.arange(first_id, first_id + 2 * len(points), 2)
    lines = ["$NOD", str(len(points))]
    lines += [f"{i} {x!r} {y!r} {z!r}" for i, (x, y, z) in zip(ids, points.tolist())]
    lines += ["$ENDNOD", "$ELM"]
    elems = [f"{k + 1} 4 1 1 4 " + " ".join(str(ids[n]) for n in t) for k, t in enumerate(tets)]
    if triangles is not None:
        elems += [f"{len(elems) + k + 1} 2 2 2 3 " + " ".join(str(ids[n]) for n in t) for k, t in enumerate(triangles)]
    elems.append(f"{len(elems) + 1} 15 3 3 1 {ids[0]}")  # a point element, ignored
    lines += [str(len(elems))] + elems + ["$ENDELM"]
    path.write_text("\n".join(lines) + "\n")


def assert_is_cube(surface, messages, edge=EDGE, allow=()):
    assert surface.volume_mm3 == pytest.approx(edge**3, rel=1e-9)
    assert surface.area_mm2 == pytest.approx(6 * edge**2, rel=1e-9)
    assert np.allclose(surface.extent_mm, edge)
    m = surface.to_trimesh()
    assert m.is_watertight and m.is_winding_consistent
    unexpected = [msg for msg in messages if not any(a in msg for a in allow)]
    assert not unexpected, unexpected


@pytest.mark.parametrize("suffix", [".stl", ".obj", ".ply", ".off"])
def test_trimesh_formats_round_trip(tmp_path, cube, suffix):
    path = tmp_path / f"cube{suffix}"
    trimesh.Trimesh(cube.vertices, cube.faces, process=False).export(path)
    s, msgs = load_surface(path, units="mm", max_edge_mm=None)
    assert_is_cube(s, msgs)  # an STL's corners, stored apart for each triangle, are shared without a word
    assert s.meta["format"] == f"trimesh-{suffix[1:]}" and len(s.meta["sha256"]) == 64


@pytest.mark.parametrize("file_type", ["stl", "stl_ascii"])
def test_an_stl_s_shared_corners_are_no_repair_but_its_real_repairs_are(tmp_path, cube, file_type, caplog):
    """STL writes each triangle's three corners apart, so every STL 'merged N duplicate vertices' as a repair,
    in the log and the geometry JSON's repairs, hiding the real ones among a repair no file lacked."""
    from liverforce.geometry.procedural import procedural_liver
    from liverforce.pipeline.geometry import make_geometry

    clean, inward = tmp_path / "clean.stl", tmp_path / "inward.stl"
    liver = procedural_liver(0)  # fine enough to be kept as read (no Loop subdivision)
    trimesh.Trimesh(liver.vertices, liver.faces, process=False).export(clean, file_type=file_type)
    trimesh.Trimesh(cube.vertices, cube.faces[:, ::-1], process=False).export(inward, file_type=file_type)
    with caplog.at_level(logging.DEBUG):
        record = make_geometry({"kind": "imported", "name": "clean", "path": str(clean), "units": "mm"},
                               tmp_path / "imp-clean.ply", tmp_path / "imp-clean.json")
    assert record["repairs"] == []
    assert json.loads((tmp_path / "imp-clean.json").read_text())["repairs"] == []
    assert not [r for r in caplog.records if "merged" in r.getMessage() or r.levelno >= logging.WARNING]
    s, msgs = load_surface(inward, units="mm", max_edge_mm=None)  # a real repair is still reported
    assert msgs == ["normals flipped (all triangles faced inward)"] == s.meta["repairs"]
    assert s.volume_mm3 == pytest.approx(VOLUME, rel=1e-9)
    twice = tmp_path / "twice.ply"  # an indexed file that does hold each vertex twice: merged and reported
    n = len(cube.vertices)
    faces = np.vstack([cube.faces[::2], cube.faces[1::2] + n])  # the odd triangles on the second copy
    trimesh.Trimesh(np.vstack([cube.vertices, cube.vertices]), faces, process=False).export(twice)
    both = len(np.intersect1d(cube.faces[::2], cube.faces[1::2]))  # vertices the two halves share
    s, msgs = load_surface(twice, units="mm", max_edge_mm=None)
    assert both > 0 and msgs == [f"merged {both} duplicate vertices"] and s.volume_mm3 == pytest.approx(VOLUME)


@pytest.mark.parametrize("binary", [False, True])
@pytest.mark.parametrize("new_layout", [False, True])
def test_legacy_vtk_polydata_own_reader(tmp_path, cube, binary, new_layout):
    path = tmp_path / "cube.vtk"
    write_vtk_polydata(path, cube.vertices, cube.faces, binary, new_layout)
    raw = read_vtk_polydata(path)
    assert np.array_equal(raw.points, cube.vertices) and np.array_equal(raw.triangles, cube.faces)
    s, msgs = load_surface(path, max_edge_mm=None)
    assert_is_cube(s, msgs)
    assert s.meta["format"] == "vtk-polydata"


def test_legacy_vtk_quads_are_fan_triangulated(tmp_path):
    p, _ = cube_tets()
    quads = np.array([[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]])
    text = "# vtk DataFile Version 2.0\nq\nASCII\nDATASET POLYDATA\nPOINTS 8 float\n"
    text += "\n".join(" ".join(map(str, r)) for r in p.astype(int)) + "\n"
    text += "POLYGONS 6 30\n" + "\n".join("4 " + " ".join(map(str, q)) for q in quads) + "\n"
    (tmp_path / "q.vtk").write_text(text)
    s, msgs = load_surface(tmp_path / "q.vtk", max_edge_mm=None)
    assert_is_cube(s, msgs, allow=("normals flipped",))


def test_gmsh_v1_own_reader_extracts_the_boundary(tmp_path):
    p, tets = cube_tets()
    path = tmp_path / "cube.msh"
    write_gmsh_v1(path, p, tets, triangles=[[0, 1, 2]])
    raw = read_gmsh_v1(path)
    assert raw.tets.shape == (6, 4) and raw.triangles.shape == (1, 3)
    assert np.allclose(raw.points, p)
    s, msgs = load_surface(path, max_edge_mm=None)
    assert_is_cube(s, msgs)  # boundary of the tets (mixed orientation), 12 triangles
    assert len(s.faces) == 12 and s.meta["format"] == "gmsh-v1"


@pytest.mark.parametrize("fmt, suffix", [("vtu", ".vtu"), ("gmsh22", ".msh"), ("gmsh", ".msh"), ("vtk", ".vtk")])
def test_meshio_volume_formats_give_the_boundary(tmp_path, fmt, suffix):
    p, tets = cube_tets()
    path = tmp_path / f"cube_{fmt}{suffix}"
    meshio.write(path, meshio.Mesh(p, [("tetra", tets)]), file_format=fmt)
    s, msgs = load_surface(path, max_edge_mm=None)
    assert_is_cube(s, msgs)
    assert len(s.faces) == 12


def test_units_and_scale(tmp_path):
    c = cube_phantom(20.0, divisions=1)  # 20 cm cube
    path = tmp_path / "cube_cm.stl"
    trimesh.Trimesh(c.vertices, c.faces, process=False).export(path)
    for units, scale in (("cm", 10.0), (10, 10.0), ("10", 10.0)):
        s, _ = load_surface(path, units=units, max_edge_mm=None)
        assert s.volume_mm3 == pytest.approx(200.0**3, rel=1e-9)
        assert s.meta["scale_to_mm"] == scale
    m = cube_phantom(0.2, divisions=1)  # 0.2 m cube
    trimesh.Trimesh(m.vertices, m.faces, process=False).export(tmp_path / "cube_m.stl")
    s, _ = load_surface(tmp_path / "cube_m.stl", units="m", max_edge_mm=None)
    assert s.extent_mm == pytest.approx([200.0] * 3)


def test_auto_units_guess_is_reported_and_logged(tmp_path, caplog):
    c = cube_phantom(0.25, divisions=1)  # metres
    path = tmp_path / "cube.ply"
    trimesh.Trimesh(c.vertices, c.faces, process=False).export(path)
    with caplog.at_level(logging.INFO, logger="liverforce.geometry.importers"):
        s, msgs = load_surface(path, units="auto", max_edge_mm=None)
    assert s.meta["units"] == "m" and s.meta["scale_to_mm"] == 1000.0
    assert any("units guessed as 'm'" in m for m in msgs)
    assert "units guessed" in caplog.text


def test_coarse_surfaces_are_refined_and_reported(tmp_path):
    c = cube_phantom(200.0, divisions=1)  # 100-200 mm edges
    path = tmp_path / "coarse.stl"
    trimesh.Trimesh(c.vertices, c.faces, process=False).export(path)
    s, msgs = load_surface(path)
    assert any("Loop subdivision" in m for m in msgs)
    assert np.linalg.norm(s.vertices[s.faces] - s.vertices[np.roll(s.faces, 1, axis=1)], axis=2).mean() <= 5.0
    assert s.to_trimesh().is_watertight and s.volume_mm3 > 0


# ------------------------------------------------------------ label volumes
def ellipsoid_labels(shape=(70, 60, 50), centre=(35, 28, 24), axes_vox=(28, 22, 15)):
    """Label 2 = ellipsoid, label 1 = a small box elsewhere, 0 = background."""
    idx = np.indices(shape).transpose(1, 2, 3, 0).astype(float)
    q = (idx - np.array(centre)) / np.array(axes_vox)
    data = np.zeros(shape, dtype=np.uint8)
    data[(q**2).sum(axis=-1) <= 1.0] = 2
    data[1:4, 1:4, 1:4] = 1
    return data


def test_nifti_label_volume_in_physical_mm(tmp_path):
    import nibabel as nib

    data = ellipsoid_labels()
    spacing = np.array([2.0, 2.5, 3.0])
    affine = np.diag([*spacing, 1.0])
    affine[:3, 3] = [-50.0, 20.0, 5.0]
    path = tmp_path / "seg.nii.gz"
    nib.save(nib.Nifti1Image(data, affine), path)
    s, msgs = load_surface(path, units="mm", label=2)
    a, b, c = np.array([28, 22, 15]) * spacing
    assert s.volume_mm3 == pytest.approx(4 / 3 * np.pi * a * b * c, rel=0.03)
    centre = affine[:3, :3] @ np.array([35, 28, 24]) + affine[:3, 3]
    assert np.allclose(s.vertices.mean(axis=0), centre, atol=1.5)
    assert np.allclose(s.extent_mm, 2 * np.array([a, b, c]), rtol=0.06)
    assert s.meta["label"] == 2 and s.meta["format"] == "nifti"
    # units from the header ("auto" -> the NIfTI default unit, mm)
    s2, msgs2 = load_surface(path, units="auto", label=2)
    assert s2.meta["scale_to_mm"] == 1.0 and any("units" in m for m in msgs2)


def test_nrrd_lps_space_is_converted_to_ras(tmp_path):
    import nrrd

    data = ellipsoid_labels()
    header = {
        "space": "left-posterior-superior",
        "space directions": np.diag([2.5, 2.5, 3.0]),
        "space origin": np.array([10.0, 20.0, 30.0]),
    }
    path = tmp_path / "seg.nrrd"
    nrrd.write(str(path), data, header)
    s, _ = load_surface(path, label=2)
    lps_centre = np.array([10.0, 20.0, 30.0]) + np.diag([2.5, 2.5, 3.0]) @ np.array([35, 28, 24])
    ras_centre = lps_centre * np.array([-1.0, -1.0, 1.0])
    assert np.allclose(s.vertices.mean(axis=0), ras_centre, atol=1.5)
    assert s.volume_mm3 > 0 and s.to_trimesh().is_watertight


def _nrrd_seg(tmp_path, space):
    import nrrd

    header = {"space directions": np.diag([2.5, 2.5, 3.0]), "space origin": np.array([10.0, 20.0, 30.0])}
    if space is not None:
        header["space"] = space
    path = tmp_path / "seg.nrrd"
    nrrd.write(str(path), ellipsoid_labels(), header)
    return path, np.array([10.0, 20.0, 30.0]) + np.diag([2.5, 2.5, 3.0]) @ np.array([35, 28, 24])


@pytest.mark.parametrize("space, to_ras", [
    ("right-anterior-superior", (1, 1, 1)), ("left-anterior-superior", (-1, 1, 1)),
    ("LPS", (-1, -1, 1)), ("LAS", (-1, 1, 1)), ("RAS", (1, 1, 1)),
])
def test_every_anatomical_nrrd_space_is_converted_to_ras_without_a_warning(tmp_path, caplog, space, to_ras):
    path, centre = _nrrd_seg(tmp_path, space)
    with caplog.at_level(logging.WARNING, logger="liverforce.geometry.importers"):
        s, msgs = load_surface(path, label=2)
    assert np.allclose(s.vertices.mean(axis=0), centre * np.array(to_ras), atol=1.5)
    assert s.volume_mm3 > 0 and s.to_trimesh().is_watertight
    assert not any("frame" in m for m in msgs) and not caplog.records


@pytest.mark.parametrize("space, said", [(None, "states no 'space'"),
                                         ("scanner-xyz", "space 'scanner-xyz', which has no anatomical frame"),
                                         ("3D-right-handed", "space '3D-right-handed', which has no anatomical")])
def test_a_nrrd_with_no_anatomical_space_is_read_as_ras_and_says_so(tmp_path, caplog, space, said):
    path, centre = _nrrd_seg(tmp_path, space)
    with caplog.at_level(logging.WARNING, logger="liverforce.geometry.importers"):
        s, msgs = load_surface(path, label=2)
    assert np.allclose(s.vertices.mean(axis=0), centre, atol=1.5)
    assert any(said in m and "read as RAS" in m and "frame=<4x4>" in m for m in msgs)
    assert any(said in r.getMessage() for r in caplog.records if r.levelno == logging.WARNING)


@pytest.mark.parametrize("space, message", [("3D-left-handed", r"3D-left-handed.*mirrored"),
                                            ("left-posterior", r"space 'left-posterior' is not one"),
                                            ("left-posterior-superior-time", r"is a time series")])
def test_a_nrrd_in_a_left_handed_or_unknown_space_is_refused(tmp_path, space, message):
    path, _ = _nrrd_seg(tmp_path, space)
    with pytest.raises(GeometryError, match=rf"seg\.nrrd.*{message}"):
        load_surface(path, label=2)


def test_a_nifti_with_no_orientation_says_its_frame_was_assumed(tmp_path):
    import nibabel as nib

    coded, bare = tmp_path / "coded.nii", tmp_path / "bare.nii"
    nib.save(nib.Nifti1Image(ellipsoid_labels(), np.diag([3.0, 3.0, 3.0, 1.0])), coded)
    img = nib.Nifti1Image(ellipsoid_labels(), None)
    img.header.set_zooms((3.0, 3.0, 3.0))
    nib.save(img, bare)
    _, msgs = load_surface(coded, label=2)
    assert not any("states no frame" in m for m in msgs)
    s, msgs = load_surface(bare, label=2)
    assert any("states no frame (sform and qform codes 0)" in m and "frame=<4x4>" in m for m in msgs)
    assert np.allclose(s.extent_mm, 2 * 3.0 * np.array([28, 22, 15]), rtol=0.06)


def test_label_volume_label_choice_is_checked(tmp_path):
    import nibabel as nib

    path = tmp_path / "seg.nii"
    nib.save(nib.Nifti1Image(ellipsoid_labels(), np.diag([3.0, 3.0, 3.0, 1.0])), path)
    with pytest.raises(GeometryError, match=r"seg\.nii.*label 5 is not present.*labels present: \[1, 2\]"):
        load_surface(path, label=5)
    with pytest.raises(GeometryError, match=r"seg\.nii.*2 labels.*label="):
        load_surface(path)
