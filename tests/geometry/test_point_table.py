"""The one reader of text point files (:mod:`liverforce.geometry.point_table`): what it reads, what it refuses,
and that both its callers (``liverforce predict`` and the mesh stage's point files) refuse the same files."""

from __future__ import annotations

import numpy as np
import pytest

from liverforce.geometry.point_table import TEXT_SUFFIXES, PointTableError, read_table
from liverforce.mesh.supports import POINT_FILE_SUFFIXES, SupportError, read_point_file
from liverforce.serve.errors import PredictionInputError
from liverforce.serve.files import read_points

XYZ = [[1.5, -2.0, 3.25], [4.0, 5.0, -6.5]]


@pytest.mark.parametrize("text, lines", [
    ("1.5,-2,3.25\n4,5,-6.5\n", [1, 2]),
    ("x,y,z\n1.5,-2,3.25\n4,5,-6.5\n", [2, 3]),
    ("x;y;z\n1.5;-2;3.25\n4;5;-6.5\n", [2, 3]),
    ("1.5\t-2\t3.25\n4\t\t5\t-6.5\n", [1, 2]),  # a run of separators is one
    ("# tool\n\n  1.5  -2  3.25\n  # moved\n4 , 5 , -6.5\n", [3, 5]),
    ("X, Y, Z\n1.5, -2, 3.25\n\n4, 5, -6.5\n", [2, 4]),
])
def test_separators_header_comments_and_blank_lines(tmp_path, text, lines):
    path = tmp_path / "p.csv"
    path.write_text(text)
    rows, got = read_table(path)
    np.testing.assert_array_equal(rows, XYZ)
    assert rows.dtype == np.float64 and got == lines


def test_one_column_and_the_widths_a_caller_accepts(tmp_path):
    path = tmp_path / "ids.txt"
    path.write_text("vertex_id\n3\n7\n")
    rows, lines = read_table(path, columns=(1, 3))
    assert rows.shape == (2, 1) and rows[:, 0].tolist() == [3, 7] and lines == [2, 3]
    with pytest.raises(PointTableError, match=r"ids\.txt, line 2: '3' \(1 value\)$"):
        read_table(path, columns=(3,))


def test_nan_and_inf_are_numbers_for_the_callers_to_judge(tmp_path):
    path = tmp_path / "p.xyz"
    path.write_text("1 nan 3\ninf 5 6\n")
    rows, _ = read_table(path)
    assert np.isnan(rows[0, 1]) and np.isinf(rows[1, 0])


@pytest.mark.parametrize("text, line, problem", [
    ("", None, "the file is empty (no points)"),
    ("# a comment\n\n   \n", None, "the file is empty (no points)"),
    ("x,y,z\n", None, "the file is empty (a header line, no points)"),
    ("1,2,abc\n4,5,6\n", 1, "'1,2,abc' is neither a header nor a row of numbers"),
    ("1;2;z\n", 1, "'1;2;z' is neither a header nor a row of numbers"),
    ("x,y,z\n1,2,3\n4,5\n", 3, "'4,5' (2 values, the rows above 3)"),
    ("1\t2\t3\n4\t5\t6\t7\n", 2, "'4\t5\t6\t7' (4 values, the rows above 3)"),
    ("x,y,z\n1,2,3\n4,5,six\n", 3, "'4,5,six' (3 values, not all numbers)"),
    ("# pts\n\n1,2\n3,4\n", 3, "'1,2' (2 values)"),
])
def test_refusals_name_the_file_and_the_line(tmp_path, text, line, problem):
    path = tmp_path / "pts.csv"
    path.write_text(text)
    with pytest.raises(PointTableError) as err:
        read_table(path, columns=(1, 3))
    e = err.value
    assert isinstance(e, ValueError) and e.path == path and e.line == line and problem in e.problem
    where = f"{path}, line {line}: " if line is not None else f"{path}: "
    assert str(e).startswith(where + problem), str(e)


def test_a_file_that_is_not_text(tmp_path):
    path = tmp_path / "p.csv"
    path.write_bytes(b"\xff\xfe\x00\x81garbage")
    with pytest.raises(PointTableError, match=r"p\.csv: cannot read the file as text"):
        read_table(path)


def test_the_suffixes_are_the_mesh_stages_text_suffixes():
    assert TEXT_SUFFIXES == (".csv", ".txt", ".xyz")
    assert set(TEXT_SUFFIXES) < set(POINT_FILE_SUFFIXES)


@pytest.mark.parametrize("text, line", [
    ("1,2,abc\n4,5,6\n", 1),  # garbled first line: both refuse it (predict once took it as a header)
    ("x,y,z\n1,2,3\n4,5\n", 3),
    ("x,y,z\n1,2,3\n4,5,six\n", 3),
    ("x,y,z\n", None),
    ("", None),  # predict once read an empty file as no points
])
def test_predict_and_the_mesh_stage_refuse_the_same_files_naming_the_line(tmp_path, text, line):
    path = tmp_path / "pts.csv"
    path.write_text(text)
    where = f"{path}, line {line}: " if line is not None else f"{path}: "
    with pytest.raises(PredictionInputError) as served:
        read_points(path)
    with pytest.raises(SupportError) as meshed:
        read_point_file(path, "mm")
    for msg in (str(served.value), str(meshed.value)):
        assert msg.startswith(where), msg
    assert "exactly x, y, z" in str(served.value) and "x, y, z in mm" in str(meshed.value)


def test_predict_requires_three_columns_where_the_mesh_stage_takes_vertex_ids(tmp_path):
    path = tmp_path / "ids.csv"
    path.write_text("id\n3\n7\n")
    assert read_point_file(path).tolist() == [3, 7]
    with pytest.raises(PredictionInputError, match=r"ids\.csv, line 2: '3' \(1 value\); expected exactly x, y, z"):
        read_points(path)
