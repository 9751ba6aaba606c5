"""Plausibility of auto-tagged regions for the stated frame: LPS imported as LPS is the RAS liver's
regions; LPS imported as RAS is flagged (warn), or refused (strict)."""

from __future__ import annotations

import json
import logging

import meshio
import numpy as np
import pytest

from liverforce.geometry import load_surface
from liverforce.mesh.plausibility import (
    ImplausibleRegionsError,
    PlausibilityThresholds,
    check_regions,
    closed_surface_centroid,
    regions_check,
)
from liverforce.mesh.regions import RegionParams, tag_regions

LPS = np.diag([-1.0, -1.0, 1.0])


@pytest.fixture(scope="module")
def lps_file(tmp_path_factory, liver_surface):
    """The procedural liver (seed 0) saved the way 3D Slicer saves models: in LPS."""
    path = tmp_path_factory.mktemp("lps") / "liver_lps.ply"
    meshio.write(path, meshio.Mesh(liver_surface.vertices @ LPS.T, [("triangle", liver_surface.faces)]), binary=True)
    return path


def by_name(checks):
    return {c["check"]: c for c in checks}


def test_centroid_of_a_closed_surface_is_the_solid_centroid(liver_mesh):
    from liverforce.mesh.features import volume_moments

    _, c, _ = volume_moments(liver_mesh.points, liver_mesh.tets)
    assert np.allclose(closed_surface_centroid(liver_mesh.points, liver_mesh.facets), c, atol=1e-6)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_procedural_livers_pass_every_check(seed, liver_surface):
    from liverforce.geometry.procedural import procedural_liver

    s = liver_surface if seed == 0 else procedural_liver(seed)
    region, visible = tag_regions(s.vertices, s.faces)
    checks = check_regions(s.vertices, s.faces, region, visible)
    assert all(c["passed"] for c in checks), [c for c in checks if not c["passed"]]
    assert {"right_lobe", "ivc_posterior", "visible_anterior", "ivc_area", "ligament_area", "visceral_area",
            "rib_area", "visible_area"} == set(by_name(checks))


def test_the_mesh_stage_regions_pass_too(liver_mesh):
    report = regions_check(liver_mesh.points, liver_mesh.facets, liver_mesh.facet_region,
                           liver_mesh.facet_visible, mode="strict")
    assert report["passed"] is True and report["warnings"] == []


def test_lps_file_stated_lps_gives_the_same_regions(lps_file, liver_surface):
    s, _ = load_surface(lps_file, frame="LPS")
    ref_region, ref_visible = tag_regions(liver_surface.vertices, liver_surface.faces)
    region, visible = tag_regions(s.vertices, s.faces)
    assert np.array_equal(region, ref_region) and np.array_equal(visible, ref_visible)
    # mirrored back: in the file's own LPS coordinates, with the LPS anatomical axes, the tags are the same
    lps_params = RegionParams(anterior=(0.0, -1.0, 0.0), superior=(0.0, 0.0, 1.0))
    region_lps, visible_lps = tag_regions(liver_surface.vertices @ LPS.T, liver_surface.faces, lps_params)
    assert (region_lps == ref_region).mean() > 0.999 and (visible_lps == ref_visible).mean() > 0.999
    assert regions_check(s.vertices, s.faces, region, visible, frame="LPS")["passed"] is True


def test_lps_file_stated_ras_is_flagged(lps_file, caplog):
    s, _ = load_surface(lps_file)  # frame RAS (the default): wrong
    region, visible = tag_regions(s.vertices, s.faces)
    with caplog.at_level(logging.WARNING, logger="liverforce.mesh.plausibility"):
        report = regions_check(s.vertices, s.faces, region, visible, frame="RAS", where="imp-slicer")
    assert report["passed"] is False
    right = by_name(report["checks"])["right_lobe"]
    assert not right["passed"] and right["value"] < 0.45
    assert len(report["warnings"]) >= 1
    msg = report["warnings"][0]
    assert msg.startswith("imp-slicer: implausible regions for the stated frame (RAS): right_lobe = 0.")
    assert "threshold 0.5" in msg and "frame: LPS" in msg
    assert "right_lobe" in caplog.text
    with pytest.raises(ImplausibleRegionsError, match=r"(?s)right_lobe = 0\.\d+ .*frame: LPS.*regions_check=strict"):
        regions_check(s.vertices, s.faces, region, visible, frame="RAS", mode="strict")
    assert regions_check(s.vertices, s.faces, region, visible, mode="off")["passed"] is None


def test_tiny_or_empty_regions_are_flagged(liver_surface):
    s = liver_surface
    region, visible = tag_regions(s.vertices, s.faces)
    no_rib = np.where(region == 4, 0, region)
    checks = by_name(check_regions(s.vertices, s.faces, no_rib, visible))
    assert not checks["rib_area"]["passed"] and checks["rib_area"]["value"] == 0.0
    strict = PlausibilityThresholds(min_area_percent=5.0)  # the IVC patch is ~1.5 % of the surface
    checks = by_name(check_regions(s.vertices, s.faces, region, visible, thresholds=strict))
    assert not checks["ivc_area"]["passed"] and 0.5 < checks["ivc_area"]["value"] < 5.0
    report = regions_check(s.vertices, s.faces, no_rib, visible, frame="RAS")
    assert any("rib_area = 0 %" in w and "empty or tiny" in w for w in report["warnings"]), report["warnings"]


def _geometry(tmp_path, lps_file, frame):
    from liverforce.pipeline.geometry import make_geometry

    spec = {"kind": "imported", "name": "slicer", "path": str(lps_file), "units": "mm", "label": None,
            "frame": frame}
    surface = tmp_path / "geometry" / "imp-slicer.ply"
    make_geometry(spec, surface, surface.with_suffix(".json"))
    return surface


def _mesh_cfg(mode):
    from liverforce.config import compose

    cfg = compose(["experiment=smoke"])["mesh"]
    return {**cfg, "target_nodes": 200, "refine_radius_mm": 0.0, "refine_ivc_edge_mm": 0.0, "regions_check": mode}


@pytest.mark.slow  # one of the default set's slowest (CI's --durations): run with -m slow
def test_mesh_stage_warns_and_records_then_strict_refuses(tmp_path, lps_file):
    from liverforce.pipeline.mesh import make_mesh

    surface = _geometry(tmp_path, lps_file, "RAS")
    out = tmp_path / "mesh"
    feats = make_mesh(surface, _mesh_cfg("warn"), 0, out / "imp-slicer.vtu", out / "imp-slicer.features.json",
                      out / "imp-slicer.regions.png")
    recorded = json.loads((out / "imp-slicer.features.json").read_text())["regions_check"]
    assert recorded == json.loads(json.dumps(feats["regions_check"]))
    assert recorded["mode"] == "warn" and recorded["passed"] is False and recorded["frame"] == "RAS"
    assert any("right_lobe" in w and "frame: LPS" in w for w in recorded["warnings"])

    strict = tmp_path / "strict"
    with pytest.raises(ImplausibleRegionsError, match=r"imp-slicer .*right_lobe = 0\.\d+"):
        make_mesh(surface, _mesh_cfg("strict"), 0, strict / "imp-slicer.vtu", strict / "imp-slicer.features.json",
                  strict / "imp-slicer.regions.png")
    assert not (strict / "imp-slicer.vtu").exists() and not (strict / "imp-slicer.features.json").exists()


def test_mesh_stage_strict_accepts_the_stated_lps(tmp_path, lps_file):
    from liverforce.pipeline.mesh import make_mesh

    surface = _geometry(tmp_path, lps_file, "LPS")
    out = tmp_path / "mesh"
    feats = make_mesh(surface, _mesh_cfg("strict"), 0, out / "imp-slicer.vtu", out / "imp-slicer.features.json",
                      out / "imp-slicer.regions.png")
    assert feats["regions_check"]["passed"] is True and feats["regions_check"]["frame"] == "LPS"


def test_config_regions_check_is_validated():
    from liverforce.config import ConfigError, compose

    assert compose([])["mesh"]["regions_check"] == "warn"
    assert compose(["mesh.regions_check=strict"])["mesh"]["regions_check"] == "strict"
    with pytest.raises(ConfigError, match=r"'mesh\.regions_check': unknown 'loud' — choose one of warn, strict, off"):
        compose(["mesh.regions_check=loud"])
