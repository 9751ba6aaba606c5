"""A lab's supports must hold the liver against every rigid motion (:func:`liverforce.mesh.supports.check_held`).

Without a fixed support, sliding supports and foundations without tangential stiffness resist motion along their
normals only: on a 50 mm cube, a sliding bottom face leaves the cube free to slide sideways (a rigid motion no
support resists: the FE cases of such a liver failed after 30 s each), while a foundation with springs both ways,
or sliding supports on every face, hold it. The mesh stage refuses the first before writing anything.
"""

from __future__ import annotations

import numpy as np
import pytest

from liverforce.fem.boundary import region_areas
from liverforce.geometry.procedural import cube_phantom, procedural_liver
from liverforce.mesh.build import build_liver_mesh
from liverforce.mesh.supports import SupportError, check_held, parse_supports, support_stiffness

A = 50.0
FACES = {"bottom": ([-30, -30, -26], [30, 30, -24]), "top": ([-30, -30, 24], [30, 30, 26]),
         "right": ([24, -30, -30], [26, 30, 30]), "left": ([-26, -30, -30], [-24, 30, 30]),
         "front": ([-30, 24, -30], [30, 26, 30]), "back": ([-30, -26, -30], [30, -24, 30])}


@pytest.fixture(scope="module")
def cube():
    return cube_phantom(A, divisions=4)


def _held(cube, *supports):
    """check_held on the cube meshed with ``supports`` (kind, face[, stiffness]) in mode replace."""
    items = []
    for kind, face, *stiffness in supports:
        lo, hi = FACES[face]
        items.append({"name": face, "kind": kind, "box": {"min_mm": lo, "max_mm": hi},
                      **({"region": "visceral", "stiffness": stiffness[0]} if kind == "foundation" else {})})
    mode, sup = parse_supports({"mode": "replace", "list": items})
    mesh = build_liver_mesh(cube, target_nodes=300, supports=(mode, sup))
    sb = support_stiffness(sup, region_areas(mesh.points, mesh.facets, mesh.facet_region))
    return check_held(mesh.points, mesh.facets, mesh.facet_region, sb, sup, where="lab.supports")


def test_a_sliding_face_alone_leaves_the_cube_free_to_slide_along_it(cube):
    # sideways in x and y, and turning about z: three free motions, the message names one of them
    with pytest.raises(SupportError, match=r"lab.supports: the supports do not hold the liver: no support is fixed, "
                                           r"and a (translation along|rotation about the axis) \[.*\] .*\(RAS\) is "
                                           r"resisted at 0 % of the supports' area \(below 0.5 %; 3 independent "
                                           r"rigid motions are as free\); the supports: 'bottom' \(sliding\).*"
                                           r"Add a fixed support"):
        _held(cube, ("sliding", "bottom"))


def test_normal_only_supports_on_two_faces_leave_the_third_direction_free(cube):
    with pytest.raises(SupportError, match=r"translation along \[(-?0\.0, -?1\.0|-?0\.0, 1\.0), -?0\.0\].*"
                                           r"'bottom' \(foundation visceral, no tangential stiffness\), "
                                           r"'right' \(sliding\)"):
        _held(cube, ("foundation", "bottom", {"normal_n_per_mm3": 0.02, "tangential_n_per_mm3": 0.0}),
              ("sliding", "right"))


def test_a_foundation_of_zero_stiffness_holds_nothing(cube):
    with pytest.raises(SupportError, match=r"none has any stiffness: nothing resists any motion; the supports: "
                                           r"'bottom' \(foundation visceral, no stiffness\)"):
        _held(cube, ("foundation", "bottom", {"total_n_per_mm": 0.0}))


@pytest.mark.parametrize("supports, held_by", [
    ((("fixed", "bottom"),), "fixed"),
    ((("foundation", "bottom", {"normal_n_per_mm3": 0.02, "tangential_n_per_mm3": 0.005}),), "springs"),
    (tuple(("sliding", f) for f in FACES), "springs"),  # sliding on every face: nothing can move
])
def test_supports_that_hold_the_cube_pass(cube, supports, held_by):
    report = _held(cube, *supports)
    assert report["held_by"] == held_by
    assert report["weakest"] is None if held_by == "fixed" else report["weakest"] > 0.1


def test_the_mesh_stage_refuses_a_liver_on_a_sliding_patch_before_writing(tmp_path):
    import trimesh

    from tests.mesh.lab_stage import mesh_stage

    liver = procedural_liver(0)
    trimesh.Trimesh(liver.vertices, liver.faces, process=False).export(tmp_path / "lab.stl")
    ribs = {"mode": "replace", "list": [{"name": "ribs", "kind": "sliding",
                                         "sphere": {"center_mm": [60, -77, 11], "radius_mm": 25}}]}
    out, run = mesh_stage(tmp_path, tmp_path / "lab.stl", ribs, "warn")
    with pytest.raises(SupportError, match=r"^geometry.imported\[lab\].supports: the supports do not hold "
                                           r"the liver: no support is fixed, and a (translation|rotation) .* is "
                                           r"resisted at 0\.\d+ % of the supports' area \(below 0\.5 %.*\); the "
                                           r"supports: 'ribs' \(sliding\)"):
        run()
    assert not (out / "imp-lab.vtu").exists() and not (out / "imp-lab.features.json").exists()
    np.testing.assert_equal(list(out.glob("*")), [])
