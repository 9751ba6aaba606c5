"""A sphere or box support given in the wrong frame (RAS read as LPS, or the reverse) or in the wrong units.

A sphere whose centre was picked on the liver's surface in the other of RAS and LPS lies, as read, off the surface
and, mirrored in x and y, on it: warned naming both distances and the ``frame`` to state, refused under
``mesh.regions_check: strict``, recorded as the support's ``frame_check`` (``of: centre``). A sphere or box that
selects nothing is refused saying what it would select mirrored, or with its numbers in cm or m."""

from __future__ import annotations

import json
import logging

import meshio
import numpy as np
import pytest
import trimesh

from liverforce.mesh.supports import (SPHERE_OFF_SURFACE_MM, SPHERE_ON_SURFACE_MM, PointFrame, SupportError,
                                      TriangleSet, parse_supports, select_facets)
from tests.mesh.lab_stage import mesh_stage

MIRROR = np.array([-1.0, -1.0, 1.0])  # RAS <-> LPS
KEY = "geometry.imported[lab].supports"
AXES = np.array([125.0, 75.0, 55.0])


def _ellipsoid(centre):
    m = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    return np.asarray(m.vertices) * AXES + centre, np.asarray(m.faces, np.int64)


@pytest.fixture(scope="module")
def near_origin():
    """A liver-like ellipsoid centred 9 mm off the file's origin: mirrored, a surface point lands 0-19 mm off it."""
    return _ellipsoid([8.0, 4.0, 0.0])


@pytest.fixture(scope="module")
def off_origin():
    """The ellipsoid 150 mm right and 80 mm anterior of the origin (a CT's world): mirrored, it lands far away."""
    return _ellipsoid([150.0, 80.0, -40.0])


def _support(selector: dict, name="cava"):
    _, (s,) = parse_supports({"mode": "replace", "list": [{"name": name, "kind": "fixed", **selector}]}, where=KEY)
    return s


def _picked(V, F, lo_mm, hi_mm):
    """A vertex picked on the surface whose mirror in x and y lies ``lo_mm``-``hi_mm`` from the surface."""
    d = TriangleSet(V[F]).closest(V * MIRROR)[1]
    i = np.flatnonzero((d > lo_mm) & (d < hi_mm))
    assert len(i), "no such vertex on the test liver"
    return V[i[len(i) // 2]], float(d[i[len(i) // 2]])


def _warnings(caplog):
    return [r.getMessage() for r in caplog.records if "looks read in the wrong frame" in r.getMessage()]


def test_a_sphere_picked_on_the_surface_in_the_other_frame_is_warned_and_refused_under_strict(near_origin, caplog):
    V, F = near_origin
    p, off = _picked(V, F, 8.0, 14.0)  # its mirror: off the surface, within the radius, so it selects facets
    sphere = {"sphere": {"center_mm": (p * MIRROR).tolist(), "radius_mm": 25.0}}  # given in LPS, read as RAS
    with caplog.at_level(logging.WARNING):
        mask, info = select_facets(V, F, _support(sphere), PointFrame())
    assert mask.any()  # it selects the wrong side of the liver: nothing but the frame check says so
    (msg,) = _warnings(caplog)
    check = info["frame_check"]
    assert check["of"] == "centre" and check["read_in"] == "RAS" and check["likely_mix_up"] is True
    assert check["refused_under_strict"] is True and check["warning"] == msg
    assert check["as_given_mm"]["mean"] == pytest.approx(off, abs=1e-3) and check["mirrored_mm"]["mean"] < 1e-6
    assert msg.startswith("support 'cava' (sphere r 25 mm) looks read in the wrong frame: its centre, read in mm, "
                          "in the geometry file's frame (RAS), lies ")
    assert f"lies {off:.3g} mm from the surface; mirrored in x and y" in msg
    assert f"state {KEY}.list[0].sphere.frame: LPS" in msg and "The sphere states no frame" in msg
    assert (f"if the centre is right (a point off the surface whose mirror lands on it by chance), state "
            f"{KEY}.list[0].sphere.frame: RAS to say so") in msg
    assert f"within {SPHERE_ON_SURFACE_MM:g} mm of the surface and, as read, {SPHERE_OFF_SURFACE_MM:g} mm" in msg
    with pytest.raises(SupportError, match="(?s)looks read in the wrong frame.*strict refuses"):
        select_facets(V, F, _support(sphere), PointFrame(), regions_check="strict")
    caplog.clear()
    assert select_facets(V, F, _support(sphere), PointFrame(), regions_check="off")[1].get("frame_check") is None
    # stated in the frame it was picked in: the same facets as the sphere given in RAS, and no warning
    right, info = select_facets(V, F, _support({"sphere": {**sphere["sphere"], "frame": "LPS"}}), PointFrame(),
                                regions_check="strict")
    ras, _ = select_facets(V, F, _support({"sphere": {"center_mm": p.tolist(), "radius_mm": 25.0}}), PointFrame())
    np.testing.assert_array_equal(right, ras)
    assert not (right & mask).any() and not _warnings(caplog)
    assert info["frame_check"]["likely_mix_up"] is False and info["frame_check"]["read_in"] == "LPS"
    assert info["frame_check"]["as_given_mm"]["mean"] < 1e-6


def test_a_stated_frame_that_looks_wrong_is_warned_never_refused(near_origin, caplog):
    """A sphere that states its frame has the lab's word for it: flagged, it is warned naming both settings, and
    under strict still only warned (a centre off the surface whose mirror lands on it by chance is kept so)."""
    V, F = near_origin
    p, _ = _picked(V, F, 8.0, 14.0)
    sphere = {"sphere": {"center_mm": p.tolist(), "radius_mm": 25.0, "frame": "LPS"}}  # RAS numbers stated LPS
    for check in ("warn", "strict"):
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            mask, info = select_facets(V, F, _support(sphere), PointFrame(), regions_check=check)
        (msg,) = _warnings(caplog)
        assert mask.any() and info["frame_check"]["likely_mix_up"] is True
        assert info["frame_check"]["refused_under_strict"] is False
        assert f"If the sphere's coordinates are in RAS, state {KEY}.list[0].sphere.frame: RAS; if LPS is right" in msg
        assert "to say so" not in msg


def test_sphere_centres_not_picked_on_the_surface_are_not_flagged(near_origin, caplog):
    """Centres in the right frame off the surface (the middle of a vessel beside the liver, a point inside it)
    whose mirror does not land on the surface: no warning, under strict too."""
    V, F = near_origin
    tri = TriangleSet(V[F])
    n = np.asarray(trimesh.Trimesh(V, F, process=False).vertex_normals)
    checked = 0
    for i, shift in ((100, 10.0), (2000, -8.0), (5000, 12.0), (9000, 0.0), (7000, -6.0)):
        c = V[i] + shift * n[i]
        if tri.closest((c * MIRROR)[None])[1][0] <= SPHERE_ON_SURFACE_MM:
            continue  # the rule's measured false alarms (benchmarks/experiment_sphere_frame.py): not these
        checked += 1
        with caplog.at_level(logging.WARNING):
            _, info = select_facets(V, F, _support({"sphere": {"center_mm": c.tolist(), "radius_mm": 20.0}}),
                                    PointFrame(), regions_check="strict")
        assert info["frame_check"]["likely_mix_up"] is False and info["frame_check"]["warning"] is None
        assert info["frame_check"]["as_given_mm"]["mean"] == pytest.approx(abs(shift), abs=0.6)
    assert checked >= 4 and not _warnings(caplog)


def test_a_sphere_that_selects_nothing_says_it_would_mirrored(off_origin):
    V, F = off_origin
    p = V[np.argmin(V[:, 1])]  # the posterior point
    with pytest.raises(SupportError) as err:
        select_facets(V, F, _support({"sphere": {"center_mm": (p * MIRROR).tolist(), "radius_mm": 15.0}}),
                      PointFrame())
    msg = str(err.value)
    assert "selects no surface facet" in msg
    n = int((np.linalg.norm(V[F].mean(axis=1) - p, axis=1) <= 15.0).sum())
    assert f"Mirrored in x and y (coordinates in RAS read as LPS, or in LPS read as RAS" in msg
    assert f"it would select {n} facets, so its coordinates are likely in LPS" in msg
    assert f"state {KEY}.list[0].sphere.frame: LPS" in msg and "taken in" not in msg


@pytest.mark.parametrize("unit, mm", [("cm", 10.0), ("m", 1000.0)])
def test_a_box_or_sphere_in_other_units_says_which(off_origin, unit, mm):
    V, F = off_origin
    cent = V[F].mean(axis=1)
    lo, hi = np.array([100.0, 0.0, -100.0]), np.array([300.0, 80.0, 100.0])  # the liver's right, posterior half
    n = int(((cent >= lo) & (cent <= hi)).all(axis=1).sum())
    box = {"box": {"min_mm": (lo / mm).tolist(), "max_mm": (hi / mm).tolist()}}
    with pytest.raises(SupportError) as err:
        select_facets(V, F, _support(box), PointFrame())
    msg = str(err.value)
    assert f"Its numbers taken in {unit} (x{mm:g}) would select {n} facets, so they are likely in {unit}" in msg
    assert "a box's numbers (min_mm, max_mm) are mm, so give them in mm" in msg and "Mirrored" not in msg
    p = V[np.argmin(V[:, 1])]
    with pytest.raises(SupportError, match=f"(?s)taken in {unit} .x{mm:g}. would select .* sphere's numbers "
                                           r"\(center_mm, radius_mm\) are mm"):
        select_facets(V, F, _support({"sphere": {"center_mm": (p / mm).tolist(), "radius_mm": 20.0 / mm}}),
                      PointFrame())


@pytest.mark.parametrize("shape", [{"sphere": {"center_mm": [0.0, 0.0, 0.0], "radius_mm": 20.0}},
                                   {"sphere": {"center_mm": [10.0, 0.0, 0.0], "radius_mm": 30.0}},
                                   {"box": {"min_mm": [-20.0, -20.0, -20.0], "max_mm": [20.0, 20.0, 20.0]}}])
def test_a_small_shape_at_the_origin_is_not_said_to_be_in_cm_or_m(off_origin, shape):
    """Scaled by 10 or 1000 about the origin, a small sphere or box left there would swallow most of the liver:
    that reading is not named (it selects more than half the surface)."""
    V, F = off_origin
    with pytest.raises(SupportError) as err:
        select_facets(V, F, _support(shape), PointFrame())
    assert "would select" not in str(err.value) and str(err.value).endswith("enlarge it or check the frame")


def test_a_sphere_nothing_would_rescue_is_refused_as_before(off_origin):
    V, F = off_origin
    with pytest.raises(SupportError) as err:
        select_facets(V, F, _support({"sphere": {"center_mm": [0.0, 0.0, 900.0], "radius_mm": 5.0}}), PointFrame())
    msg = str(err.value)
    assert msg.endswith("enlarge it or check the frame") and "would select" not in msg


def test_the_features_json_and_the_report_record_the_sphere_check(near_origin, tmp_path, caplog):
    V, F = near_origin
    path = tmp_path / "liver.ply"
    meshio.write(path, meshio.Mesh(V, [("triangle", F)]), binary=True)
    p, _ = _picked(V, F, 8.0, 14.0)
    q = V[np.argmax(V[:, 1])]  # the anterior point, given in RAS as the file
    supports = {"mode": "replace", "list": [
        {"name": "cava", "kind": "fixed", "sphere": {"center_mm": (p * MIRROR).tolist(), "radius_mm": 25.0}},
        {"name": "clamp", "kind": "fixed", "sphere": {"center_mm": q.tolist(), "radius_mm": 15.0}}]}
    out, run = mesh_stage(tmp_path, path, supports, "warn")
    with caplog.at_level(logging.WARNING):
        run()
    feats = json.loads((out / "imp-lab.features.json").read_text())
    wrong, right = (s["frame_check"] for s in feats["supports"])
    assert wrong["of"] == "centre" and wrong["likely_mix_up"] is True and wrong["warning"] in _warnings(caplog)
    assert right["likely_mix_up"] is False and right["warning"] is None
    from liverforce.report.imported import _supports_block

    block = _supports_block(supports, feats)
    assert block.count("<tr class='frame-flag'>") == 1 and "⚠ cava: likely read in the wrong frame" in block
    assert "mirrored, its centre lies 0 mm from the surface" in block and "centre 0 as read" in block
    assert "Frame check of a sphere" in block and "Frame check of a file of points" not in block


def test_the_shipped_rule_flags_no_centre_picked_on_the_surface_in_the_right_frame():
    """The measurement behind the thresholds (benchmarks/experiment_sphere_frame.py), smaller: on the procedural
    livers and shifted ellipsoids no centre picked on the surface and read in the right frame is flagged, few
    centres off the surface are, and the silent wrong-frame spheres picked on the surface are found often."""
    from benchmarks.experiment_sphere_frame import distances, rates

    r = rates(distances(200, seed=3), SPHERE_ON_SURFACE_MM, SPHERE_OFF_SURFACE_MM)
    assert r["click"][0] == 0.0 and r["click_noisy"][0] == 0.0 and r["offset"][0] < 3.0
    assert r["click"][1] > 35.0 and r["click_noisy"][1] > 35.0 and min(r[m][2] for m in r) > 1000
