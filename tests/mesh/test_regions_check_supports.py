"""A lab's own supports (``mode: replace``) skip only the regions checks of the built-in supports: the liver's
frame (``right_lobe``) is still checked, and refused under ``strict``; the report says what was skipped and why."""

from __future__ import annotations

import json

import meshio
import numpy as np
import pytest

from liverforce.mesh.plausibility import (
    BUILT_IN_SUPPORT_CHECKS,
    ImplausibleRegionsError,
    regions_check,
    skipped_checks,
)
from liverforce.mesh.regions import tag_regions, visible_facets
from tests.mesh.lab_stage import mesh_stage

LPS = np.diag([-1.0, -1.0, 1.0])
MIRROR = np.diag([-1.0, 1.0, 1.0])


def _own_regions(s):
    """Regions as a lab's replace supports leave them: a fixed patch only (no ligament, visceral, rib)."""
    region, _ = tag_regions(s.vertices, s.faces)
    own = np.where(region == 1, 1, 0).astype(np.int8)
    return own, visible_facets(s.vertices, s.faces, own)


def test_skipped_checks_name_the_built_in_supports_checks_and_why():
    assert skipped_checks(None) == {} and skipped_checks(None, True) == {}
    add = skipped_checks("add")  # checked on the auto-tagged regions beneath instead (tests/mesh/test_add_supports.py)
    assert set(add) == set(BUILT_IN_SUPPORT_CHECKS) == set(skipped_checks("add", True))
    assert all("mode: add" in why and "regions_check.built_in" in why for why in add.values())
    skip = skipped_checks("replace")
    assert set(skip) == set(BUILT_IN_SUPPORT_CHECKS) and "right_lobe" not in skip
    assert all("mode: replace" in why for why in skip.values())
    assert set(skipped_checks("replace", exertion_given=True)) == set(BUILT_IN_SUPPORT_CHECKS) | {"visible_area"}


def test_own_supports_on_a_right_liver_pass_strict_with_the_skipped_checks_listed(liver_surface):
    s = liver_surface
    region, visible = _own_regions(s)
    with pytest.raises(ImplausibleRegionsError, match="ligament_area"):  # the built-in checks would refuse it
        regions_check(s.vertices, s.faces, region, visible, mode="strict")
    report = regions_check(s.vertices, s.faces, region, visible, mode="strict", skip=skipped_checks("replace"))
    assert report["mode"] == "strict" and report["passed"] is True
    ran = {c["check"] for c in report["checks"]}
    assert ran == {"right_lobe", "visible_anterior", "visible_area"}
    assert {c["check"] for c in report["skipped"]} == set(BUILT_IN_SUPPORT_CHECKS)
    assert all("replace" in c["why"] for c in report["skipped"])
    json.dumps(report)


@pytest.mark.parametrize("wrong", ["mirror", "lps_as_ras"])
def test_a_wrong_frame_is_refused_under_strict_even_with_own_supports(liver_surface, wrong):
    s = liver_surface
    M = MIRROR if wrong == "mirror" else LPS
    V = s.vertices @ M.T
    F = s.faces[:, ::-1] if np.linalg.det(M) < 0 else s.faces  # keep the triangles outward
    region, visible = tag_regions(V, F)
    own = np.where(region == 1, 1, 0).astype(np.int8)
    skip = skipped_checks("replace", exertion_given=True)
    with pytest.raises(ImplausibleRegionsError, match=r"right_lobe = 0\.[0-4]\d* .*frame: LPS"):
        regions_check(V, F, own, visible, mode="strict", frame="RAS", skip=skip)
    report = regions_check(V, F, own, visible, mode="warn", frame="RAS", skip=skip)
    assert report["mode"] == "warn" and report["passed"] is False
    assert [w for w in report["warnings"] if "right_lobe" in w]
    assert "right_lobe" not in {c["check"] for c in report["skipped"]}


# --------------------------------------------------------------------------- the mesh stage
@pytest.fixture(scope="module")
def lps_file(tmp_path_factory, liver_surface):
    """The procedural liver (seed 0) as 3D Slicer saves it: LPS."""
    path = tmp_path_factory.mktemp("lps") / "liver_lps.ply"
    meshio.write(path, meshio.Mesh(liver_surface.vertices @ LPS.T, [("triangle", liver_surface.faces)]), binary=True)
    return path


def _stage(tmp_path, lps_file, liver_surface, frame, mode):
    V = liver_surface.vertices
    cava = (V[np.argmax(-V[:, 1] + V[:, 2])] * np.diag(LPS)).round(1).tolist()  # posterior-superior, file (LPS) mm
    supports = {"mode": "replace", "list": [{"name": "cava", "kind": "fixed",
                                             "sphere": {"center_mm": cava, "radius_mm": 25.0}}]}
    return mesh_stage(tmp_path, lps_file, supports, mode, frame)


def test_mesh_stage_refuses_an_lps_file_stated_ras_with_replace_supports(tmp_path, lps_file, liver_surface):
    out, run = _stage(tmp_path, lps_file, liver_surface, "RAS", "strict")
    with pytest.raises(ImplausibleRegionsError, match=r"imp-lab .*right_lobe = 0\.\d+.*frame: LPS"):
        run()
    assert not (out / "imp-lab.vtu").exists() and not (out / "imp-lab.features.json").exists()


@pytest.mark.slow  # one of the default set's slowest (CI's --durations): run with -m slow
def test_mesh_stage_checks_the_stated_lps_and_records_what_it_skipped(tmp_path, lps_file, liver_surface):
    out, run = _stage(tmp_path, lps_file, liver_surface, "LPS", "strict")
    feats = run()
    recorded = json.loads((out / "imp-lab.features.json").read_text())["regions_check"]
    assert recorded == json.loads(json.dumps(feats["regions_check"]))
    assert recorded["mode"] == "strict" and recorded["passed"] is True and recorded["frame"] == "LPS"
    assert "right_lobe" in {c["check"] for c in recorded["checks"]}
    assert {c["check"] for c in recorded["skipped"]} == set(BUILT_IN_SUPPORT_CHECKS)
    assert all("mode: replace" in c["why"] for c in recorded["skipped"])
