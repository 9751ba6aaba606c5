"""A support's file of points read in the wrong frame (RAS as LPS, or the reverse) is caught even when it lands
within the 5 mm snap limit: on a liver roughly symmetric about the superior axis through the file's origin, the
turned points still lie near the surface, on its other side, and the support was put there without a word (the
refusal of a patch that selects nothing even said "units and frame look right"). Points marked on a liver's
surface fit it within a fraction of a mm: mirrored in x and y they fit clearly better when the frame is wrong.
Warned naming the support and both fits, refused under ``mesh.regions_check: strict``, recorded on the support's
report in the features JSON (``supports[i].frame_check``)."""

from __future__ import annotations

import json
import logging
import time

import meshio
import numpy as np
import pytest
import trimesh

from liverforce.geometry.surface import Surface
from liverforce.mesh.build import build_liver_mesh
from liverforce.mesh.given import build_given_mesh
from liverforce.mesh.regions import tag_regions
from liverforce.mesh.supports import (PointFrame, SupportError, TriangleSet, assign_supports, parse_supports,
                                      select_facets)
from tests.mesh.lab_stage import mesh_stage

MIRROR = np.array([-1.0, -1.0, 1.0])  # RAS <-> LPS
KEY = "geometry.imported[lab].supports"
#: a liver-like ellipsoid (mm) whose centre lies a few mm off the file's origin: mirrored, the posterior patch
#: lands 2-3 mm from the surface, within the snap limit
AXES, CENTRE = np.array([125.0, 75.0, 55.0]), np.array([2.0, 1.0, 0.0])


@pytest.fixture(scope="module")
def ellipsoid():
    m = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    return np.asarray(m.vertices) * AXES + CENTRE, np.asarray(m.faces, np.int64)


def _on_surface(V, F, centre, radius_mm, n, noise_mm, seed):
    """``n`` points drawn uniformly on the facets within ``radius_mm`` of ``centre``, each moved by up to
    ``noise_mm`` (uniform in a ball): points marked on a segmentation's surface."""
    rng = np.random.default_rng(seed)
    tri = V[F]
    near = np.flatnonzero(np.linalg.norm(tri.mean(axis=1) - centre, axis=1) < radius_mm)
    area = np.linalg.norm(np.cross(tri[near, 1] - tri[near, 0], tri[near, 2] - tri[near, 0]), axis=1)
    f = rng.choice(near, n, p=area / area.sum())
    s, t = np.sqrt(rng.random(n)), rng.random(n)
    p = np.einsum("ij,ijk->ik", np.stack([1 - s, s * (1 - t), s * t], axis=1), tri[f])
    u = rng.normal(size=p.shape)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return p + u * noise_mm * rng.random((n, 1)) ** (1 / 3)


def _posterior_patch(V, F, noise_mm=1.0, seed=0, x_mm=-30.0):
    """40 points over 20 mm of the posterior face, ``x_mm`` right of the centre."""
    centre = V[np.argmin(np.linalg.norm(V - (CENTRE + [x_mm, -75.0, -10.0]), axis=1))]
    return _on_surface(V, F, centre, 20.0, 40, noise_mm, seed)


def _support(path, frame=None, name="cava"):
    spec = {"path": str(path), **({"frame": frame} if frame is not None else {})}
    _, (s,) = parse_supports({"mode": "replace", "list": [{"name": name, "kind": "fixed", "file": spec}]},
                             where=KEY)
    return s


def _frame_warnings(caplog):
    return [r.getMessage() for r in caplog.records if "looks read in the wrong frame" in r.getMessage()]


@pytest.mark.parametrize("noise_mm", [0.0, 0.5, 1.0])
def test_points_on_the_surface_in_the_right_frame_are_not_flagged(ellipsoid, tmp_path, caplog, noise_mm):
    V, F = ellipsoid
    np.savetxt(tmp_path / "cava.csv", _posterior_patch(V, F, noise_mm), delimiter=",")
    with caplog.at_level(logging.WARNING):
        mask, info = select_facets(V, F, _support(tmp_path / "cava.csv"), PointFrame(), regions_check="strict")
    assert mask.any() and not _frame_warnings(caplog)
    check = info["frame_check"]
    assert check["likely_mix_up"] is False and check["warning"] is None and check["read_in"] == "RAS"
    assert check["as_given_mm"]["max"] <= noise_mm + 0.05 and check["mirrored_mm"]["mean"] > 1.0


def test_the_same_file_read_in_the_wrong_frame_is_warned_with_both_fits(ellipsoid, tmp_path, caplog):
    V, F = ellipsoid
    np.savetxt(tmp_path / "cava_lps.csv", _posterior_patch(V, F) * MIRROR, delimiter=",")  # the file in LPS
    with caplog.at_level(logging.WARNING):
        mask, info = select_facets(V, F, _support(tmp_path / "cava_lps.csv"), PointFrame())
    (msg,) = _frame_warnings(caplog)
    check = info["frame_check"]
    assert check["likely_mix_up"] is True and check["refused_under_strict"] is True and check["warning"] == msg
    g, m = check["as_given_mm"], check["mirrored_mm"]
    assert g["max"] < 5.0  # within the snap limit: refused by distance before, never by frame
    assert m["mean"] < 0.5 * g["mean"] and g["mean"] - m["mean"] > 1.0
    assert msg.startswith("support 'cava' (") and "cava_lps.csv" in msg
    assert f"lie {g['mean']:.3g} mm from the surface on average (max {g['max']:.3g} mm)" in msg
    assert f"they would lie {m['mean']:.3g} mm (max {m['max']:.3g} mm) from it" in msg
    assert "read in mm, in the geometry file's frame (RAS)" in msg
    assert f"state {KEY}.list[0].file.frame: LPS" in msg
    # stated, the file's frame is read right: no warning
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        _, info = select_facets(V, F, _support(tmp_path / "cava_lps.csv", "LPS"), PointFrame(),
                                regions_check="strict")
    assert not _frame_warnings(caplog) and info["frame_check"]["likely_mix_up"] is False


def test_a_wrong_frame_is_refused_under_strict_naming_the_same(ellipsoid, tmp_path):
    V, F = ellipsoid
    np.savetxt(tmp_path / "cava.csv", _posterior_patch(V, F), delimiter=",")  # RAS points stated LPS
    with pytest.raises(SupportError) as err:
        select_facets(V, F, _support(tmp_path / "cava.csv", "LPS"), PointFrame(), regions_check="strict")
    msg = str(err.value)
    assert "support 'cava'" in msg and "looks read in the wrong frame" in msg and "in the stated frame LPS" in msg
    assert f"state {KEY}.list[0].file.frame: RAS; if LPS is right, the liver may be" in msg
    assert "mesh.regions_check=strict refuses" in msg and "set it to warn" in msg
    # off: not checked, nothing recorded
    _, info = select_facets(V, F, _support(tmp_path / "cava.csv", "LPS"), PointFrame(), regions_check="off")
    assert info["frame_check"] is None


def test_a_geometry_in_lps_mirrors_the_points_in_its_own_coordinates(ellipsoid, tmp_path, caplog):
    """The liver file in LPS (the mesh is its RAS turn): a point file in RAS, read in the geometry's LPS, is
    mirrored in the file's coordinates and flagged; its stated RAS is not."""
    V, F = ellipsoid
    lps = PointFrame(matrix=tuple(map(tuple, np.diag([-1.0, -1.0, 1.0, 1.0]))),
                     frame_label="the geometry file's frame (LPS)")
    mesh_v = V * MIRROR  # the liver as meshed, RAS; the file's coordinates are V
    np.savetxt(tmp_path / "ras.csv", _posterior_patch(V, F) * MIRROR, delimiter=",")  # RAS coordinates
    with caplog.at_level(logging.WARNING):
        _, info = select_facets(mesh_v, F, _support(tmp_path / "ras.csv"), lps)
    (msg,) = _frame_warnings(caplog)
    assert info["frame_check"]["read_in"] == "LPS" and f"{KEY}.list[0].file.frame: RAS" in msg
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        _, info = select_facets(mesh_v, F, _support(tmp_path / "ras.csv", "RAS"), lps, regions_check="strict")
    assert not _frame_warnings(caplog) and info["frame_check"]["likely_mix_up"] is False


def test_a_geometry_read_with_a_4x4_mirrors_the_points_in_the_files_coordinates(ellipsoid, tmp_path, caplog):
    """The liver file's coordinates taken to RAS by a 4x4 that shifts them 100 mm (a registration): the file's
    origin is not the mesh's, so the points are mirrored in the file's coordinates (in the mesh's they would
    land nowhere near the surface); the fix names the 4x4 with its first two columns negated, and works."""
    V, F = ellipsoid
    M = np.eye(4)
    M[:3, 3] = [100.0, 50.0, -20.0]
    frame = PointFrame(matrix=tuple(map(tuple, M)), frame_label="the geometry file's frame (a 4x4)",
                       frame_name="a 4x4")
    np.savetxt(tmp_path / "lps.csv", _posterior_patch(V, F) * MIRROR, delimiter=",")  # the file's coordinates
    with caplog.at_level(logging.WARNING):
        _, info = select_facets(V + M[:3, 3], F, _support(tmp_path / "lps.csv"), frame)
    (msg,) = _frame_warnings(caplog)
    assert info["frame_check"]["read_in"] == "a 4x4" and info["frame_check"]["mirrored_mm"]["max"] < 1.0
    assert f"state {KEY}.list[0].file.frame: that 4x4 with its first two columns negated" in msg
    stated = (M @ np.diag([-1.0, -1.0, 1.0, 1.0])).tolist()
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        _, info = select_facets(V + M[:3, 3], F, _support(tmp_path / "lps.csv", stated), frame,
                                regions_check="strict")
    assert not _frame_warnings(caplog) and info["frame_check"]["as_given_mm"]["max"] < 1.05


@pytest.mark.parametrize("stated, right", [("LPS", False), ("RAS", True)])
def test_a_markups_file_stating_the_wrong_system_is_flagged(ellipsoid, tmp_path, caplog, stated, right):
    """RAS control points in a markups file: stated RAS they are right, stated LPS they are turned."""
    V, F = ellipsoid
    pts = _posterior_patch(V, F)
    doc = {"markups": [{"type": "Fiducial", "coordinateSystem": stated, "coordinateUnits": "mm",
                        "controlPoints": [{"label": f"F-{i}", "position": p.tolist()} for i, p in enumerate(pts)]}]}
    (tmp_path / "cava.mrk.json").write_text(json.dumps(doc))
    with caplog.at_level(logging.WARNING):
        _, info = select_facets(V, F, _support(tmp_path / "cava.mrk.json"), PointFrame())
    assert info["frame_check"]["likely_mix_up"] is not right and info["frame_check"]["read_in"] == stated
    if not right:
        (msg,) = _frame_warnings(caplog)
        assert "The markups file states coordinateSystem LPS: if its points are in RAS, correct that" in msg


def test_on_the_procedural_liver(liver_surface, tmp_path, caplog):
    """A small patch where the procedural liver (seed 0) is near symmetric: mirrored it stays within 5 mm."""
    V, F = liver_surface.vertices, liver_surface.faces
    ts = TriangleSet(V[F])
    near = np.flatnonzero(ts.closest(V * MIRROR)[1] < 1.5)
    pts = None
    for c in near[::7]:
        p = _on_surface(V, F, V[c], 8.0, 20, 0.5, int(c))
        if ts.closest(p * MIRROR)[1].max() < 4.5 and ts.closest(p * MIRROR)[1].mean() > 1.0:
            pts = p
            break
    assert pts is not None, "no patch of the procedural liver mirrors within the snap limit"
    np.savetxt(tmp_path / "right.csv", pts, delimiter=",")
    np.savetxt(tmp_path / "wrong.csv", pts * MIRROR, delimiter=",")
    with caplog.at_level(logging.WARNING):
        _, right = select_facets(V, F, _support(tmp_path / "right.csv"), PointFrame(), regions_check="strict")
    assert right["frame_check"]["likely_mix_up"] is False and not _frame_warnings(caplog)
    with pytest.raises(SupportError, match=r"support 'cava' .*wrong\.csv\) looks read in the wrong frame"):
        select_facets(V, F, _support(tmp_path / "wrong.csv"), PointFrame(), regions_check="strict")


def test_a_patch_that_selects_nothing_does_not_call_a_doubtful_frame_right(ellipsoid, tmp_path, caplog):
    V, F = ellipsoid
    pts = _posterior_patch(V, F, 0.0)
    line = pts[np.argsort(pts[:, 0])][[0, -1]]  # two points make no patch
    np.savetxt(tmp_path / "two.csv", line * MIRROR, delimiter=",")
    with caplog.at_level(logging.WARNING), pytest.raises(SupportError) as err:
        select_facets(V, F, _support(tmp_path / "two.csv"), PointFrame())
    msg = str(err.value)
    assert "selects no surface facet" in msg and "frame look right" not in msg and "frame looks right" not in msg
    assert "the frame does not: mirrored in x and y (the other of RAS and LPS) they fit it better" in msg
    np.savetxt(tmp_path / "two_right.csv", line, delimiter=",")
    with pytest.raises(SupportError) as err:
        select_facets(V, F, _support(tmp_path / "two_right.csv"), PointFrame())
    assert "they fit it worse" in str(err.value) and "so the frame looks right too" in str(err.value)


def test_the_build_and_the_given_mesh_pass_the_regions_check_on(ellipsoid, tmp_path):
    V, F = ellipsoid
    np.savetxt(tmp_path / "cava.csv", _posterior_patch(V, F) * MIRROR, delimiter=",")
    surface = Surface(V, F, {"source": "ellipsoid"})
    with pytest.raises(SupportError, match="support 'cava' .* looks read in the wrong frame"):
        build_liver_mesh(surface, target_nodes=200, supports=("replace", [_support(tmp_path / "cava.csv")]),
                         regions_check="strict")
    mesh = build_liver_mesh(surface, target_nodes=800, conforming_regions=False)
    # a mesh given as is: the points marked on its own (coarser) boundary
    pts = _posterior_patch(mesh.points, mesh.facets, 0.5)
    np.savetxt(tmp_path / "given.csv", pts * MIRROR, delimiter=",")
    supports = ("replace", [_support(tmp_path / "given.csv")])
    with pytest.raises(SupportError, match="support 'cava' .* looks read in the wrong frame"):
        build_given_mesh(mesh.points, mesh.tets, {"source": "ellipsoid"}, supports=supports, regions_check="strict")
    given = build_given_mesh(mesh.points, mesh.tets, {"source": "ellipsoid"}, supports=supports)
    assert given.meta["supports"][0]["frame_check"]["likely_mix_up"] is True


def test_the_features_json_records_the_check(ellipsoid, tmp_path, caplog):
    V, F = ellipsoid
    path = tmp_path / "liver.ply"
    meshio.write(path, meshio.Mesh(V, [("triangle", F)]), binary=True)
    np.savetxt(tmp_path / "cava_lps.csv", _posterior_patch(V, F) * MIRROR, delimiter=",")
    np.savetxt(tmp_path / "bed_lps.csv", _posterior_patch(V, F, x_mm=40.0) * MIRROR, delimiter=",")
    supports = {"mode": "replace", "list": [
        {"name": "cava", "kind": "fixed", "file": {"path": str(tmp_path / "cava_lps.csv")}},
        {"name": "bed", "kind": "fixed", "file": {"path": str(tmp_path / "bed_lps.csv"), "frame": "LPS"}}]}
    out, run = mesh_stage(tmp_path, path, supports, "warn")
    with caplog.at_level(logging.WARNING):
        run()
    feats = json.loads((out / "imp-lab.features.json").read_text())
    wrong, right = (s["frame_check"] for s in feats["supports"])
    assert wrong["likely_mix_up"] is True and wrong["read_in"] == "RAS"
    assert wrong["warning"] in _frame_warnings(caplog) and "support 'cava'" in wrong["warning"]
    assert f"{KEY}.list[0].file.frame: LPS" in wrong["warning"]
    assert wrong["as_given_mm"]["mean"] > 2 * wrong["mirrored_mm"]["mean"]
    assert right["likely_mix_up"] is False and right["read_in"] == "LPS" and right["warning"] is None
    # the advice (what to state) is recorded apart for the report, whose supports table flags the support with it
    assert wrong["advice"].startswith("The file states no frame") and f"{wrong['advice']}. (Flagged" in wrong["warning"]
    assert right["advice"] is None
    from liverforce.report.imported import _supports_block

    block = _supports_block(supports, feats)
    assert block.count("<tr class='frame-flag'>") == 1 and "⚠ cava: likely read in the wrong frame" in block
    assert f"state {KEY}.list[0].file.frame: LPS" in block
    assert block.index("cava_lps.csv") < block.index("frame-flag") < block.index("bed_lps.csv")  # under cava's row


def test_the_check_costs_two_queries_of_the_points_on_a_large_surface(tmp_path, monkeypatch):
    """No loop over facets: on a surface of 330 000 facets, select_facets builds one search tree over them, for
    the patch and the frame check alike; the check only queries the file's points (as read and mirrored)."""
    m = trimesh.creation.icosphere(subdivisions=7, radius=1.0)
    V, F = np.asarray(m.vertices) * AXES + CENTRE, np.asarray(m.faces, np.int64)
    np.savetxt(tmp_path / "cava.csv", _posterior_patch(V, F) * MIRROR, delimiter=",")
    import scipy.spatial

    from liverforce.mesh import supports

    built, queried = [], []
    real_tree, real_fits = scipy.spatial.cKDTree, supports.frame_fits
    monkeypatch.setattr(scipy.spatial, "cKDTree", lambda *a, **k: built.append(len(a[0])) or real_tree(*a, **k))
    closest = TriangleSet.closest
    monkeypatch.setattr(TriangleSet, "closest", lambda self, q, k=16: queried.append(len(q)) or closest(self, q, k))
    timed = []

    def fits(*a, **k):
        t0 = time.perf_counter()
        out = real_fits(*a, **k)
        timed.append(time.perf_counter() - t0)
        return out

    monkeypatch.setattr(supports, "frame_fits", fits)
    _, info = select_facets(V, F, _support(tmp_path / "cava.csv"), PointFrame())
    assert info["frame_check"]["likely_mix_up"] is True
    assert built.count(len(F)) == 1, f"trees over the facets: {built}"
    assert queried == [40, 40, 40], "the patch, then the check as read and mirrored: the 40 points each"
    assert timed[0] < 0.5, f"{timed[0]:.3g} s for 40 points on {len(F)} facets"


def test_assign_supports_passes_strict_on(ellipsoid, tmp_path):
    V, F = ellipsoid
    np.savetxt(tmp_path / "cava.csv", _posterior_patch(V, F) * MIRROR, delimiter=",")
    region, _ = tag_regions(V, F)
    with pytest.raises(SupportError, match="looks read in the wrong frame"):
        assign_supports(V, F, region, "replace", [_support(tmp_path / "cava.csv")], PointFrame(),
                        regions_check="strict")


#: the ellipsoid moved off the file's origin: mirrored in x and y, or scaled, its points land far off the surface
SHIFT = np.array([30.0, 20.0, 0.0])


def _far(V, F, path, geometry=PointFrame(), **spec) -> str:
    """The refusal of the support's file at ``path`` (``spec``: its ``frame``, ``units``; ``geometry``: how the
    geometry file's coordinates map to the mesh), some of its points beyond the 5 mm snap limit."""
    _, (s,) = parse_supports({"mode": "replace", "list": [{"name": "cava", "kind": "fixed",
                                                           "file": {"path": str(path), **spec}}]}, where=KEY)
    with pytest.raises(SupportError) as err:
        select_facets(V, F, s, geometry, regions_check="strict")
    msg = str(err.value)
    assert "mm from the surface (limit 5.0 mm): check its units and frame" in msg
    return msg


def test_points_beyond_the_limit_that_fit_mirrored_are_said_to_be_in_the_other_frame(ellipsoid, tmp_path):
    """Far off the file's origin a file in LPS read as RAS lands 50 mm off the surface: refused by distance, the
    refusal now says that mirrored they all fit, so the file is likely in LPS, and which setting states it."""
    V, F = ellipsoid[0] + SHIFT, ellipsoid[1]
    pts = _posterior_patch(V, F, 0.5)
    np.savetxt(tmp_path / "lps.csv", pts * MIRROR, delimiter=",")
    msg = _far(V, F, tmp_path / "lps.csv")
    assert "Mirrored in x and y (coordinates in RAS read as LPS, or in LPS read as RAS" in msg
    assert "all 40 points would lie within 5 mm of the surface" in msg and "so the file is likely in LPS" in msg
    assert f"The file states no frame, so its points are read in the geometry's: if the file is in LPS, state " \
           f"{KEY}.list[0].file.frame: LPS" in msg
    assert "scaled by" not in msg.lower()  # no unit lands them on the surface
    # the frame stated wrong: the same, with the stated frame's advice
    msg = _far(V, F, tmp_path / "lps.csv", frame="RAS")
    assert f"If the file is in LPS, state {KEY}.list[0].file.frame: LPS; if RAS is right, the liver may be" in msg
    # points off the surface for another reason (20 mm above it) get no guess
    np.savetxt(tmp_path / "off.csv", pts + [0.0, 0.0, 20.0], delimiter=",")
    assert _far(V, F, tmp_path / "off.csv").endswith("check its units and frame")


def test_the_mirror_beyond_the_limit_is_taken_in_the_files_own_coordinates(ellipsoid, tmp_path):
    """The liver file read with a 4x4 shifting it 100 mm (a registration): the file's points are mirrored about
    the file's origin, not the mesh's (there they would land nowhere near the surface)."""
    V, F = ellipsoid[0] + SHIFT, ellipsoid[1]
    M = np.eye(4)
    M[:3, 3] = [100.0, 50.0, -20.0]
    frame = PointFrame(matrix=tuple(map(tuple, M)), frame_label="the geometry file's frame (a 4x4)",
                       frame_name="a 4x4")
    np.savetxt(tmp_path / "lps.csv", _posterior_patch(V, F, 0.5) * MIRROR, delimiter=",")  # the file's own
    msg = _far(V + M[:3, 3], F, tmp_path / "lps.csv", frame)
    assert "so the file is likely in the other of RAS and LPS" in msg
    assert f"state {KEY}.list[0].file.frame: that 4x4 with its first two columns negated" in msg


@pytest.mark.parametrize("numbers, spec, frame, unit, words", [
    (1e-3, {}, PointFrame(), "m", "scaled by 1000 (its numbers in m, read in mm)"),  # metres read in mm
    (0.1, {"units": "m"}, PointFrame(), "cm", "scaled by 0.01 (its numbers in cm, read in m)"),  # cm stated m
    (1.0, {}, PointFrame(scale=1000.0, units="m"), "mm", "scaled by 0.001 (its numbers in mm, read in m)"),
    (1.0, {"units": "cm"}, PointFrame(), "mm", "scaled by 0.1 (its numbers in mm, read in cm)"),
])
def test_points_beyond_the_limit_that_fit_in_other_units_name_the_unit(ellipsoid, tmp_path, numbers, spec, frame,
                                                                       unit, words):
    """A file in m read in mm (its own units not stated, or the geometry's in m), in cm stated m, in mm stated cm:
    scaled to the unit that fits, all its points land on the surface; the refusal names that unit and the setting
    (``units`` of the support's file)."""
    V, F = ellipsoid[0] + SHIFT, ellipsoid[1]
    np.savetxt(tmp_path / "cava.csv", _posterior_patch(V, F, 0.5) * numbers, delimiter=",")
    msg = _far(V, F, tmp_path / "cava.csv", frame, **spec)
    assert f"{words.capitalize()} all 40 points would lie within 5 mm of the surface" in msg
    assert f"so the file is likely in {unit}: " in msg and msg.endswith(f"state {KEY}.list[0].file.units: {unit}")
    assert ("the file states no units, so its numbers are read in the geometry's" in msg) is ("units" not in spec)
    assert "Mirrored" not in msg


def test_units_beyond_the_limit_are_scaled_in_the_files_own_coordinates(ellipsoid, tmp_path):
    """A file in m read in mm through a 4x4 that shifts it 100 mm: scaled about the file's origin (its numbers
    times 1000, then the 4x4) its points fit; scaled about the mesh's they would land 100 m away."""
    V, F = ellipsoid[0] + SHIFT, ellipsoid[1]
    M = np.eye(4)
    M[:3, 3] = [100.0, 50.0, -20.0]
    frame = PointFrame(matrix=tuple(map(tuple, M)), frame_label="the geometry file's frame (a 4x4)",
                       frame_name="a 4x4")
    np.savetxt(tmp_path / "m.csv", _posterior_patch(V, F, 0.5) / 1000.0, delimiter=",")
    msg = _far(V + M[:3, 3], F, tmp_path / "m.csv", frame)
    assert "Scaled by 1000 (its numbers in m, read in mm) all 40 points would lie within 5 mm" in msg


def test_a_markups_file_beyond_the_limit_is_said_to_state_the_wrong_system(ellipsoid, tmp_path):
    """RAS control points in a markups file stating LPS, on the shifted liver: refused by distance, the refusal
    says to correct the file's coordinateSystem (a markups file states its own units: no other unit is tried)."""
    V, F = ellipsoid[0] + SHIFT, ellipsoid[1]
    pts = _posterior_patch(V, F, 0.5)
    doc = {"markups": [{"type": "Fiducial", "coordinateSystem": "LPS", "coordinateUnits": "mm",
                        "controlPoints": [{"label": f"F-{i}", "position": p.tolist()} for i, p in enumerate(pts)]}]}
    (tmp_path / "cava.mrk.json").write_text(json.dumps(doc))
    msg = _far(V, F, tmp_path / "cava.mrk.json")
    assert "so the file is likely in RAS. The markups file states coordinateSystem LPS: if its points are in RAS, " \
           "correct that in the file" in msg and "Scaled" not in msg


def test_the_refusal_beyond_the_limit_builds_no_second_search_tree(tmp_path, monkeypatch):
    """The other readings of a refused file are measured on the surface's one search tree (built for the patch):
    its points once each more, mirrored and in each other unit, no loop over the facets."""
    m = trimesh.creation.icosphere(subdivisions=6, radius=1.0)
    V, F = np.asarray(m.vertices) * AXES + CENTRE + SHIFT, np.asarray(m.faces, np.int64)
    np.savetxt(tmp_path / "lps.csv", _posterior_patch(V, F, 0.5) * MIRROR, delimiter=",")
    import scipy.spatial

    built, queried = [], []
    real_tree = scipy.spatial.cKDTree
    monkeypatch.setattr(scipy.spatial, "cKDTree", lambda *a, **k: built.append(len(a[0])) or real_tree(*a, **k))
    closest = TriangleSet.closest
    monkeypatch.setattr(TriangleSet, "closest", lambda self, q, k=16: queried.append(len(q)) or closest(self, q, k))
    msg = _far(V, F, tmp_path / "lps.csv")
    assert "so the file is likely in LPS" in msg
    assert built.count(len(F)) == 1, f"trees over the facets: {built}"
    assert queried[0] == 40 and sum(queried) == 4 * 40, f"as read, then mirrored, in cm and in m: {queried}"
