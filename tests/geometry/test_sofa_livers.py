"""The SOFA livers in ../shared/data/livers (read in place, never copied).

Their coordinates are in arbitrary units: liver-smooth.obj and liver.msh are
about 6.4 units across (units=40 gives ~255 mm), liver2.msh only about 2.1
units across (units=120 gives ~255 mm; units=40 would give an 86 mm liver
and is refused).  The ``shared_livers`` fixture (tests/conftest.py) skips
these tests with a reason when the folder is absent.
"""

from __future__ import annotations

import numpy as np
import pytest

from liverforce.geometry import GeometryError, load_surface
from liverforce.mesh.build import build_liver_mesh
from liverforce.mesh.quality import signed_volumes
from liverforce.mesh.types import REGION_CODES


def check_closed_liver(surface, lo=230.0, hi=290.0):
    m = surface.to_trimesh()
    assert m.is_watertight and m.is_winding_consistent and surface.volume_mm3 > 0
    assert lo < surface.extent_mm.max() < hi
    assert 1.0e6 < surface.volume_mm3 < 3.0e6


def test_broken_vtk_is_refused(shared_livers):
    path = shared_livers / "liver_for_test_broken.vtk"
    with pytest.raises(GeometryError) as err:
        load_surface(path, units=40)
    msg = str(err.value)
    assert str(path) in msg and "corrupted" in msg and "Re-export" in msg


def test_liver_smooth_obj(shared_livers):
    s, msgs = load_surface(shared_livers / "liver-smooth.obj", units=40)
    check_closed_liver(s)
    # the SOFA surface folds over itself in one place: repaired there only, and reported
    assert any(m.startswith("self-intersections removed locally (5 intersecting triangle pairs")
               and "8 triangles round them replaced by 6" in m for m in msgs), msgs
    assert s.meta["scale_to_mm"] == 40.0 and len(s.meta["sha256"]) == 64


def test_liver_msh_gmsh_v1(shared_livers):
    s, msgs = load_surface(shared_livers / "liver.msh", units=40)
    check_closed_liver(s)
    assert s.meta["format"] == "gmsh-v1"
    assert any("Loop subdivision" in m for m in msgs)  # 596-tet toy mesh: facets smoothed


def test_liver2_msh_needs_its_own_scale(shared_livers):
    with pytest.raises(GeometryError, match=r"liver2\.msh: with units x40 .* 8\d\.\d+ mm across"):
        load_surface(shared_livers / "liver2.msh", units=40)
    s, _ = load_surface(shared_livers / "liver2.msh", units=120)
    check_closed_liver(s)


@pytest.mark.parametrize("name, units", [("liver2.msh", 120), ("liver-smooth.obj", 40)])
def test_sofa_livers_mesh_and_tag(shared_livers, name, units):
    s, _ = load_surface(shared_livers / name, units=units)
    mesh = build_liver_mesh(s, target_nodes=1500)
    mesh.validate()
    assert (signed_volumes(mesh.points, mesh.tets) > 0).all()
    assert abs(mesh.n_nodes / 1500 - 1) < 0.3
    assert mesh.meta["quality"]["radius_ratio_min"] > 0.1
    assert np.isclose(signed_volumes(mesh.points, mesh.tets).sum(), s.volume_mm3, rtol=0.03)
    for code in REGION_CODES.values():
        assert (mesh.facet_region == code).any(), code
    assert mesh.facet_visible.any()
