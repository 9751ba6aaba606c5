"""A point file whose header names a unit (``x_mm``, ``X [m]``) is read in that unit or refused: the lab's tool
positions as ``x_mm,y_mm,z_mm`` declared ``units: m`` were a thousand times off and only refused, if at all, for
lying far from the liver, without a word about the header that said so."""
from __future__ import annotations

import numpy as np
import pytest

from liverforce.geometry.point_table import header_units
from liverforce.mesh.supports import PointFrame, SupportError, exertion_points_mesh


@pytest.mark.parametrize("header, unit", [
    ("x_mm,y_mm,z_mm", "mm"), ("X [m], Y [m], Z [m]", "m"), ("x(mm)\ty(mm)\tz(mm)", "mm"), ("r_um;a_um;s_um", "um"),
    ("x mm, y mm, z mm", "mm"), ("L_cm,P_cm,S_cm", "cm")])
def test_the_unit_a_header_names_for_every_column(tmp_path, header, unit):
    path = tmp_path / "tools.csv"
    path.write_text(f"{header}\n1,2,3\n")
    assert header_units(path) == (unit, header)


@pytest.mark.parametrize("text", ["x,y,z\n1,2,3\n", "1,2,3\n4,5,6\n", "x_mm,y_mm,z\n1,2,3\n",
                                  "x_mm,y_m,z_mm\n1,2,3\n", "# x_mm\nname,mm,value\n1,2,3\n", "x_mmm,y,z\n1,2,3\n"])
def test_no_unit_when_a_column_names_none_or_they_differ(tmp_path, text):
    path = tmp_path / "tools.csv"
    path.write_text(text)
    assert header_units(path) is None


def test_tool_positions_read_in_another_unit_than_their_header_says_are_refused(tmp_path):
    """A liver in metres: the tool file's header says mm. Declared m, or not declared (the geometry's m): refused
    naming the header and the fix; declared mm: read as mm. A header naming no unit is read as declared."""
    path = tmp_path / "tools_lps_mm.csv"
    path.write_text("x_mm,y_mm,z_mm\n-31.0,24.0,29.0\n")
    frame = PointFrame(scale=1000.0, units="m")
    for spec in ({"path": str(path), "units": "m"}, {"path": str(path)}):
        with pytest.raises(SupportError, match=r"tools_lps_mm\.csv: its header 'x_mm,y_mm,z_mm' says the coordinates "
                                               r"are in mm, but they are read in m.* \(1000 mm each\): declare units: "
                                               r"mm for this file \(or correct its header\)"):
            exertion_points_mesh(spec, frame)
    np.testing.assert_allclose(exertion_points_mesh({"path": str(path), "units": "mm"}, frame), [[-31.0, 24.0, 29.0]])
    path.write_text("x,y,z\n-0.031,0.024,0.029\n")
    np.testing.assert_allclose(exertion_points_mesh({"path": str(path), "units": "m"}, frame), [[-31.0, 24.0, 29.0]])
