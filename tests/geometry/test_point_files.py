"""Point files of an imported liver (exertion points, support files) are read as ``liverforce predict`` reads
a point file: comma, semicolon, tab or space separated, one optional header line, any-case suffix; a refused
file is named with its line and what was expected, an empty one is said to be."""

from __future__ import annotations

import meshio
import numpy as np
import pytest

from liverforce.mesh.supports import PointFrame, SupportError, exertion_points_mesh, read_point_file
from liverforce.serve.files import read_points

MM = np.array([[-5.926, -79.584, -1.565], [39.83, -72.039, -7.832], [-19.999, -64.457, -38.273]])


def _rows(xyz, sep):
    return "\n".join(sep.join(f"{v:.6f}" for v in p) for p in xyz) + "\n"


TEXTS = {
    "comma.csv": lambda x: _rows(x, ","),
    "header.csv": lambda x: "x,y,z\n" + _rows(x, ","),
    "semicolon.csv": lambda x: "x;y;z\n" + _rows(x, ";"),
    "tabs.txt": lambda x: _rows(x, "\t"),
    "spaces.xyz": lambda x: "# tool positions\n\n" + _rows(x, "  "),
    "UPPER.CSV": lambda x: "X, Y, Z\n" + _rows(x, ", "),
}


@pytest.mark.parametrize("name", sorted(TEXTS))
@pytest.mark.parametrize("units", ["mm", "m"])
def test_text_files_give_the_same_points_in_mm_and_m_as_predict_reads_them(tmp_path, name, units):
    scale = 1000.0 if units == "m" else 1.0
    path = tmp_path / name
    path.write_text(TEXTS[name](MM / scale))
    a = read_point_file(path, units)
    np.testing.assert_allclose(a * scale, MM, atol=1e-6)
    np.testing.assert_array_equal(a, read_points(path, units="mm"))  # the predict reader: the same numbers
    got = exertion_points_mesh({"path": str(path), "units": units}, PointFrame())
    np.testing.assert_allclose(got, MM, atol=1e-6)


def test_the_geometrys_units_and_frame_apply_as_before(tmp_path):
    path = tmp_path / "pts.csv"
    path.write_text("x;y;z\n" + _rows(MM * [-1, -1, 1] / 1000.0, ";"))  # LPS metres, no units stated
    lps_m = PointFrame(scale=1000.0, matrix=tuple(map(tuple, np.diag([-1.0, -1.0, 1.0, 1.0]))))
    np.testing.assert_allclose(exertion_points_mesh({"path": str(path)}, lps_m), MM, atol=1e-6)


def test_npy_and_ply_files(tmp_path):
    with open(tmp_path / "p.NPY", "wb") as fh:  # np.save would add .npy to a name ending .NPY
        np.save(fh, MM)
    meshio.write(tmp_path / "p.ply", meshio.Mesh(MM, []), binary=True)
    for name in ("p.NPY", "p.ply"):
        np.testing.assert_allclose(read_point_file(tmp_path / name), MM, atol=1e-5)
        np.testing.assert_allclose(read_points(tmp_path / name), MM, atol=1e-5)


def test_vertex_ids_one_column_with_or_without_a_header(tmp_path):
    (tmp_path / "ids.txt").write_text("3\n7\n11\n")
    (tmp_path / "ids.csv").write_text("vertex_id\n3\n7\n11\n")
    np.save(tmp_path / "ids.npy", np.array([3, 7, 11]))
    for name in ("ids.txt", "ids.csv", "ids.npy"):
        a = read_point_file(tmp_path / name)
        assert a.dtype == np.int64 and a.tolist() == [3, 7, 11]


@pytest.mark.parametrize("text, line, what", [
    ("", None, "the file is empty"),
    ("# only a comment\n\n", None, "the file is empty"),
    ("x,y,z\n", None, "the file is empty (a header line, no points"),
    ("x,y,z\n1,2,3\n4,5\n", 3, "2 values, the rows above 3"),
    ("x,y,z\n1,2,3\n4,5,six\n", 3, "3 values, not all numbers"),
    ("1;2;3\n4;5;6;7\n", 2, "4 values, the rows above 3"),
    ("1,2,abc\n4,5,6\n", 1, "is neither a header nor"),
    ("1,2\n3,4\n", 1, "2 values"),
    ("x,y,z\n1,2,3\n\n# moved\n4,nan,6\n", 5, "not a finite number"),
    ("id\n3\n-1\n", 3, "non-negative integer vertex ids"),
])
def test_garbled_or_empty_files_are_named_with_the_line_and_what_was_expected(tmp_path, text, line, what):
    path = tmp_path / "points.csv"
    path.write_text(text)
    with pytest.raises(SupportError) as err:
        read_point_file(path, "m")
    msg = str(err.value)
    assert msg.startswith(str(path)) and what in msg, msg
    if line is not None:
        assert f", line {line}:" in msg, msg
    if "vertex ids" not in what and "empty" not in what:
        assert "3 numbers per row (x, y, z in m)" in msg, msg


def test_an_empty_exertion_file_says_it_is_empty_not_a_vertex_range(tmp_path):
    path = tmp_path / "points_empty.csv"
    path.write_text("")
    with pytest.raises(SupportError, match=r"points_empty\.csv: the file is empty"):
        exertion_points_mesh({"path": str(path), "units": "m"}, PointFrame(), file_vertices=lambda: MM)


def test_the_geometrys_units_are_named_when_none_is_declared(tmp_path):
    path = tmp_path / "pts.csv"
    path.write_text("1,2,3\n4,5\n")
    with pytest.raises(SupportError, match=r"line 2: .*x, y, z in m \(the geometry's units\)"):
        exertion_points_mesh({"path": str(path)}, PointFrame(scale=1000.0, units="m"))
    with pytest.raises(SupportError, match=r"line 2: .*x, y, z in the geometry's units \(40 mm each\)"):
        exertion_points_mesh({"path": str(path)}, PointFrame(scale=40.0, units="40"))


def test_unknown_suffix_and_missing_file(tmp_path):
    (tmp_path / "p.dat").write_text("1,2,3\n")
    with pytest.raises(SupportError, match=r"p\.dat: use \.npy, \.csv, \.txt, \.xyz, \.ply \(any case\)"):
        read_point_file(tmp_path / "p.dat")
    with pytest.raises(SupportError, match=r"nope\.csv: file not found"):
        read_point_file(tmp_path / "nope.csv")


def test_a_support_file_uses_the_same_reader(tmp_path):
    from liverforce.geometry.procedural import cube_phantom
    from liverforce.mesh.supports import parse_supports, select_facets

    cube = cube_phantom(50.0, divisions=4)
    top = np.flatnonzero(np.isclose(cube.vertices[:, 2], 25.0))
    path = tmp_path / "RIBS.CSV"
    path.write_text("x;y;z\n" + _rows(cube.vertices[top] / 1000.0, ";"))
    _, (s,) = parse_supports({"mode": "replace", "list": [{"name": "ribs", "kind": "sliding",
                                                           "file": {"path": str(path), "units": "m"}}]})
    mask, info = select_facets(cube.vertices, cube.faces, s)
    assert info["n_facets"] == 32 and info["snap_mm"]["max"] < 1e-3
    path.write_text("x;y;z\n1;2;3\n1;2\n")
    with pytest.raises(SupportError, match=r"RIBS\.CSV, line 3: .*x, y, z in m"):
        select_facets(cube.vertices, cube.faces, s)
