"""A lab's own supports with ``mode: add`` lie over the auto-tagged regions: the regions checks of the built-in
supports run on the regions as auto-tagged (beneath the lab's supports), not on the lab's clamp taken for an IVC in
the wrong place (which told a right RAS liver it was probably LPS); a built-in region wholly covered by a lab
support of another kind is refused, naming both, and facets taken from one are listed."""

from __future__ import annotations

import json

import meshio
import numpy as np
import pytest

from liverforce.mesh.plausibility import BUILT_IN_SUPPORT_CHECKS, ImplausibleRegionsError
from liverforce.mesh.supports import SupportError, apply_supports, parse_supports
from liverforce.mesh.regions import tag_regions
from liverforce.mesh.types import REGION_CODES
from tests.mesh.lab_stage import mesh_stage


@pytest.fixture(scope="module")
def ras_file(tmp_path_factory, liver_surface):
    path = tmp_path_factory.mktemp("ras") / "liver.ply"
    meshio.write(path, meshio.Mesh(liver_surface.vertices, [("triangle", liver_surface.faces)]), binary=True)
    return path


def _anterior_top(V):
    return V[np.argmax(V[:, 1] + V[:, 2])].round(1).tolist()  # anterior-superior: where a clamp is no IVC


@pytest.mark.slow  # one of the default set's slowest (CI's --durations): run with -m slow
@pytest.mark.parametrize("mode", ["strict", "warn"])
def test_an_added_anterior_clamp_is_not_taken_for_a_misplaced_ivc(tmp_path, ras_file, liver_surface, mode, caplog):
    """Before: strict refused this right RAS liver ('ivc_posterior = 42.6 mm ... probably LPS, state frame: LPS'),
    warn logged that advice; following it would have mirrored the liver."""
    clamp = {"mode": "add", "list": [{"name": "clamp", "kind": "fixed",
                                      "sphere": {"center_mm": _anterior_top(liver_surface.vertices),
                                                 "radius_mm": 45.0}}]}
    out, run = mesh_stage(tmp_path, ras_file, clamp, mode)
    feats = run()
    assert not [r for r in caplog.records if "implausible" in r.getMessage()]
    rc = json.loads((out / "imp-lab.features.json").read_text())["regions_check"]
    assert rc["passed"] is True and "right_lobe" in {c["check"] for c in rc["checks"]}
    assert {c["check"] for c in rc["skipped"]} == set(BUILT_IN_SUPPORT_CHECKS)
    assert all("mode: add" in c["why"] and "regions_check.built_in" in c["why"] for c in rc["skipped"])
    built_in = {c["check"]: c for c in rc["built_in"]["checks"]}
    assert set(BUILT_IN_SUPPORT_CHECKS) <= set(built_in) and rc["built_in"]["passed"] is True
    assert built_in["ivc_posterior"]["value"] < 0  # the auto-tagged IVC: posterior, as anatomy has it
    took = feats["supports"][0].get("took_built_in", {})
    assert took and set(took) <= {"visceral", "rib", "ligament"}


def test_a_wrong_frame_is_still_refused_under_add(tmp_path, liver_surface):
    lps = tmp_path / "liver_lps.ply"
    meshio.write(lps, meshio.Mesh(liver_surface.vertices * [-1, -1, 1], [("triangle", liver_surface.faces)]),
                 binary=True)
    clamp = {"mode": "add", "list": [{"name": "clamp", "kind": "fixed",
                                      "sphere": {"center_mm": _anterior_top(liver_surface.vertices * [-1, -1, 1]),
                                                 "radius_mm": 30.0}}]}
    out, run = mesh_stage(tmp_path, lps, clamp, "strict")
    with pytest.raises(ImplausibleRegionsError, match=r"right_lobe = 0\.\d+.*frame: LPS"):
        run()
    assert not (out / "imp-lab.vtu").exists()


def test_a_built_in_region_wholly_covered_by_another_kind_is_refused(liver_surface):
    V, F = liver_surface.vertices, liver_surface.faces
    auto, _ = tag_regions(V, F)
    bed = {"mode": "add", "list": [{"name": "bed", "kind": "sliding",
                                    "box": {"min_mm": [-400, -400, -400], "max_mm": [400, 0, 400]}}]}
    mode, sup = parse_supports(bed)
    with pytest.raises(SupportError, match=r"built-in ivc region \(fixed, \d+ facets auto-tagged\) is wholly covered "
                                           r"by the lab's support\(s\) 'bed' \(sliding: \d+ facets\).*mode: replace"):
        apply_supports(V, F, auto, mode, sup)
    region, _ = apply_supports(V, F, auto, "replace", sup)  # replace: the lab says what the liver has
    assert not (region == REGION_CODES["ivc"]).any()
    ivc = V[F[auto == REGION_CODES["ivc"]]].reshape(-1, 3)
    box = {"min_mm": (ivc.min(0) - 1).tolist(), "max_mm": (ivc.max(0) + 1).tolist()}
    same = {"mode": "add", "list": [{"name": "cava", "kind": "fixed", "box": box}]}  # round the IVC: still fixed
    region, report = apply_supports(V, F, auto, *parse_supports(same))
    assert (region[auto == REGION_CODES["ivc"]] == REGION_CODES["ivc"]).all()
    assert "ivc" not in report[0].get("took_built_in", {})


@pytest.mark.slow  # one of the default set's slowest (CI's --durations): run with -m slow
@pytest.mark.parametrize("mode", ["warn", "strict"])
def test_the_mesh_stage_tags_the_regions_once_with_the_same_results(tmp_path, ras_file, liver_surface, mode,
                                                                     monkeypatch):
    """Before, with supports mode add and the regions check on, the stage tagged the input surface twice: once to
    check the built-in regions, then again in build_liver_mesh, the same work on the same surface."""
    import liverforce.mesh.build as build
    import liverforce.mesh.regions as regions
    from liverforce.mesh.io import read_mesh

    clamp = {"mode": "add", "list": [{"name": "clamp", "kind": "fixed",
                                      "sphere": {"center_mm": _anterior_top(liver_surface.vertices),
                                                 "radius_mm": 45.0}}]}
    calls = []

    def counted(points, facets, params=None):
        calls.append(len(facets))
        return tag_regions(points, facets, params)

    monkeypatch.setattr(regions, "tag_regions", counted)
    monkeypatch.setattr(build, "tag_regions", counted)
    out, run = mesh_stage(tmp_path / "once", ras_file, clamp, mode)
    run()
    assert calls == [len(liver_surface.faces)]  # the input surface, once (the mesh conforms to its regions)

    def tagging_again(surface, *args, auto_regions=None, **kw):  # the stage as it was: the build tags again
        return build_liver_mesh(surface, *args, **kw)

    build_liver_mesh = build.build_liver_mesh
    monkeypatch.setattr(build, "build_liver_mesh", tagging_again)
    calls.clear()
    ref_out, ref_run = mesh_stage(tmp_path / "twice", ras_file, clamp, mode)
    ref_run()
    assert calls == [len(liver_surface.faces)] * 2
    feats, ref = (json.loads((o / "imp-lab.features.json").read_text()) for o in (out, ref_out))
    assert feats["regions_check"] == ref["regions_check"] and feats["regions_check"]["built_in"]["checks"]
    assert feats["supports"] == ref["supports"]
    mesh, ref_mesh = (read_mesh(o / "imp-lab.vtu") for o in (out, ref_out))
    assert np.array_equal(mesh.facets, ref_mesh.facets) and np.array_equal(mesh.facet_region, ref_mesh.facet_region)
    assert np.array_equal(mesh.facet_visible, ref_mesh.facet_visible)


def test_auto_regions_of_another_surface_are_refused(liver_surface):
    from liverforce.mesh.build import build_liver_mesh

    with pytest.raises(ValueError, match=rf"auto_regions: 3 region codes and 3 visible flags for the "
                                         rf"{len(liver_surface.faces)} facets .*pass tag_regions"):
        build_liver_mesh(liver_surface, target_nodes=200, auto_regions=(np.zeros(3, np.int8), np.zeros(3, bool)))
