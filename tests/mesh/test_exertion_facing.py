"""A lab's own exertion (tool) point off the visible area, facing away from the camera, is reported: a warning naming
the point as given (file and row, its numbers), its outward normal in RAS and the likely frame mix-up, recorded in
the features JSON under ``exertion_not_visible``; refused under ``mesh.regions_check: strict``. Before, only the
snap distance and the fixed supports were checked, so a posterior point (or an anterior point of a tool file in RAS
read as LPS, which mirrors x and y) was taken without a word and the camera model trained on views from behind
the liver."""

from __future__ import annotations

import json
import logging
import re

import meshio
import numpy as np
import pytest

from liverforce.mesh.regions import tag_regions
from liverforce.mesh.supports import SupportError, check_exertion_facing, closest_on_triangles, snap_exertion_points
from liverforce.mesh.types import REGION_CODES

MIRROR = np.array([-1.0, -1.0, 1.0])  # RAS <-> LPS


def _vertex_normals(V, F):
    raw = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    n = np.zeros_like(V)
    for k in range(3):
        np.add.at(n, F[:, k], raw)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def _all_facets(V, F, mask):
    """Vertices whose every facet is in ``mask``."""
    bad = np.zeros(len(V), bool)
    bad[F[~mask].ravel()] = True
    good = np.zeros(len(V), bool)
    good[F[mask].ravel()] = True
    return good & ~bad


@pytest.fixture(scope="module")
def points(liver_surface):
    """An anterior point on the visible area, a posterior one (free surface, normal -y) and an anterior one whose
    RAS/LPS mirror lands within the snap limit off the visible area and off the IVC."""
    V, F = liver_surface.vertices, liver_surface.faces
    region, visible = tag_regions(V, F)
    n = _vertex_normals(V, F)
    vis = np.flatnonzero(_all_facets(V, F, visible))
    anterior = V[vis[np.argmax(n[vis, 1])]]
    back = np.flatnonzero(_all_facets(V, F, (region == 0) & ~visible) & (n[:, 1] < -0.8))
    posterior = V[back[np.argmin(V[back, 1])]]
    mirrored = V[vis] * MIRROR
    _, d, facet = closest_on_triangles(V[F], mirrored)
    ok = np.flatnonzero((d < 4.0) & ~visible[facet] & (region[facet] != REGION_CODES["ivc"]))
    assert len(ok), "no visible point mirrors onto the surface"
    return {"anterior": anterior, "posterior": posterior, "mirror_of": V[vis[ok[np.argmax(n[vis[ok], 1])]]]}


def _stage(tmp_path, liver_surface, tools, mode, frame="RAS"):
    """``(out, run)``: the geometry stage of the liver (written in ``frame``, mm) with the tool file ``tools``;
    ``run()`` runs the mesh stage with ``mesh.regions_check = mode``."""
    from liverforce.config import compose
    from liverforce.pipeline.geometry import make_geometry
    from liverforce.pipeline.mesh import make_mesh

    V, F = liver_surface.vertices, liver_surface.faces
    path = tmp_path / "liver.ply"
    path.parent.mkdir(parents=True, exist_ok=True)
    meshio.write(path, meshio.Mesh(V * (MIRROR if frame == "LPS" else 1.0), [("triangle", F)]), binary=True)
    spec = {"kind": "imported", "name": "lab", "path": str(path), "units": "mm", "label": None, "frame": frame,
            "exertion_points": {"path": str(tools)}}
    surface = tmp_path / "geometry" / "imp-lab.ply"
    make_geometry(spec, surface, surface.with_suffix(".json"))
    cfg = {**compose(["experiment=smoke"])["mesh"], "target_nodes": 200, "refine_radius_mm": 0.0,
           "refine_ivc_edge_mm": 0.0, "regions_check": mode}
    out = tmp_path / "mesh"
    return out, lambda: make_mesh(surface, cfg, 0, out / "imp-lab.vtu", out / "imp-lab.features.json",
                                  out / "imp-lab.regions.png")


def _tools(tmp_path, rows):
    tools = tmp_path / "tools.csv"
    np.savetxt(tools, np.asarray(rows, float), delimiter=",", header="x,y,z", comments="")
    return tools


def _named(tools, row, xyz):
    given = ", ".join(f"{x:.6g}" for x in np.asarray(xyz, float))
    return rf"exertion point {row - 1} \(point {row} of {tools}: \[{given}\] in mm[^;]*; .* RAS mm as meshed\)"


def _facing_warnings(caplog):
    return [r.getMessage() for r in caplog.records
            if r.levelno == logging.WARNING and "facing away from the camera" in r.getMessage()]


def test_a_posterior_point_is_warned_naming_its_file_row_and_normal(tmp_path, liver_surface, points, caplog):
    tools = _tools(tmp_path, [points["anterior"], points["posterior"]])
    out, run = _stage(tmp_path, liver_surface, tools, "warn")
    with caplog.at_level(logging.WARNING):
        run()
    warned = _facing_warnings(caplog)
    assert len(warned) == 1
    assert re.search(_named(tools, 2, points["posterior"]) + r" lies on the surface facing away from the camera, off "
                     r"the visible area .*outward normal there is \[-?[\d.]+, -[01]\.\d+, -?[\d.]+\] \(RAS", warned[0])
    assert "trained on views along the outward normal" in warned[0] and "from behind the liver" in warned[0]
    # its mirror (x, y) lands nowhere near the visible area: the point file's frame is not suggested, the liver's is
    assert "reading the point file in the other frame would not help" in warned[0]
    assert "If the liver itself was given in the wrong frame" in warned[0] and "fix the geometry's frame" in warned[0]
    assert "not that frame mix-up" not in warned[0] and "Likely a frame mix-up" not in warned[0]
    feats = json.loads((out / "imp-lab.features.json").read_text())
    rec = feats["exertion_not_visible"]
    assert [r["point"] for r in rec] == [1] and rec[0]["normal_ras"][1] < -0.5
    assert rec[0]["facing"] == "away" and rec[0]["frame_mix_up"] is None and rec[0]["refused_under_strict"]
    assert rec[0]["as_given"].startswith("point 2 of") and rec[0]["warning"] == warned[0]
    assert (out / "imp-lab.vtu").exists()


def test_a_posterior_point_is_refused_under_strict(tmp_path, liver_surface, points):
    tools = _tools(tmp_path, [points["anterior"], points["posterior"]])
    out, run = _stage(tmp_path, liver_surface, tools, "strict")
    with pytest.raises(SupportError, match=_named(tools, 2, points["posterior"]) + r" lies on the surface facing "
                       r"away from the camera, .* more than 90 deg\. (.|\n)*fix the geometry's frame(.|\n)*"
                       r"mesh\.regions_check=strict refuses exertion points facing away"):
        run()
    assert not (out / "imp-lab.vtu").exists() and not (out / "imp-lab.features.json").exists()


def test_an_anterior_visible_point_gives_no_warning(tmp_path, liver_surface, points, caplog):
    tools = _tools(tmp_path, [points["anterior"]])
    out, run = _stage(tmp_path, liver_surface, tools, "strict")
    with caplog.at_level(logging.WARNING):
        run()
    assert not _facing_warnings(caplog)
    assert json.loads((out / "imp-lab.features.json").read_text())["exertion_not_visible"] == []


@pytest.mark.slow  # one of the default set's slowest (CI's --durations): run with -m slow
def test_a_ras_tool_file_read_as_lps_is_caught_at_the_mesh_stage(tmp_path, liver_surface, points, caplog):
    """The lab's liver is in LPS (declared), its tool file in RAS without saying so: read in the liver's frame, the
    intended anterior point is mirrored in x and y onto the posterior-left surface, within the snap limit."""
    intended = points["mirror_of"]  # RAS: what the lab meant
    tools = _tools(tmp_path, [intended])
    out, run = _stage(tmp_path, liver_surface, tools, "warn", frame="LPS")
    with caplog.at_level(logging.WARNING):
        run()
    rec = json.loads((out / "imp-lab.features.json").read_text())["exertion_not_visible"]
    assert [r["point"] for r in rec] == [0] and rec[0]["normal_ras"][1] < 0
    assert rec[0]["frame_mix_up"]["distance_mm"] <= 5.0 and rec[0]["refused_under_strict"]
    assert np.allclose(rec[0]["frame_mix_up"]["mirrored_mm"], intended, atol=5.0)
    warned = _facing_warnings(caplog)
    assert len(warned) == 1
    assert "Likely a frame mix-up: mirrored in x and y (the point file in RAS read as LPS" in warned[0]
    _, run2 = _stage(tmp_path / "strict", liver_surface, tools, "strict", frame="LPS")
    with pytest.raises(SupportError, match=_named(tools, 1, intended) + r" lies on the surface facing away(.|\n)*"
                       r"Likely a frame mix-up"):
        run2()


def test_the_mirror_is_caught_by_snap_exertion_points(liver_surface, points):
    V, F = liver_surface.vertices, liver_surface.faces
    region, visible = tag_regions(V, F)
    q = np.vstack([points["anterior"], points["mirror_of"] * MIRROR])
    found = []
    pts, d = snap_exertion_points(V, F, region, q, visible=visible, not_visible=found)
    assert d.max() < 5.0 and [r["point"] for r in found] == [1]
    assert found[0]["angle_to_view_deg"] > 90 and "facing away from the camera" in found[0]["warning"]
    assert "Likely a frame mix-up: mirrored in x and y" in found[0]["warning"]
    with pytest.raises(SupportError, match=r"exertion point 1 \[.*\] \(mesh frame, mm\) lies on the surface facing"):
        snap_exertion_points(V, F, region, q, visible=visible, regions_check="strict")
    before = snap_exertion_points(V, F, region, q[:1], visible=visible, regions_check="strict", not_visible=found)
    assert len(found) == 1 and np.allclose(before[0], snap_exertion_points(V, F, region, q[:1])[0])


@pytest.mark.parametrize("mode", ["warn", "strict"])
def test_a_posterior_vertex_of_a_mesh_taken_as_given_is_reported(tmp_path, mode, caplog):
    """A tet mesh taken as given is not remeshed: its points are checked on its own visible facets."""
    from liverforce.config import compose
    from liverforce.geometry.procedural import procedural_liver
    from liverforce.mesh.build import build_liver_mesh
    from liverforce.pipeline.geometry import make_geometry
    from liverforce.pipeline.mesh import make_mesh

    orig = build_liver_mesh(procedural_liver(0), target_nodes=400, seed=0)
    P, Fb = orig.points, orig.facets
    n = _vertex_normals(P, Fb)
    vis = np.flatnonzero(_all_facets(P, Fb, orig.facet_visible))
    back = np.flatnonzero(_all_facets(P, Fb, (orig.facet_region == 0) & ~orig.facet_visible) & (n[:, 1] < -0.8))
    ids = [int(vis[np.argmax(n[vis, 1])]), int(back[np.argmin(P[back, 1])])]
    path = tmp_path / "liver.vtu"
    meshio.write(path, meshio.Mesh(P, [("tetra", orig.tets)]))
    spec = {"kind": "imported", "name": "lab", "path": str(path), "units": "mm", "label": None, "frame": "RAS",
            "mesh": "as_given", "exertion_points": {"vertex_ids": ids}}
    surface = tmp_path / "geometry" / "imp-lab.ply"
    make_geometry(spec, surface, surface.with_suffix(".json"))
    cfg = {**compose(["experiment=smoke"])["mesh"], "regions_check": mode}
    out = tmp_path / "mesh"
    run = lambda: make_mesh(surface, cfg, 0, out / "imp-lab.vtu", out / "imp-lab.features.json",  # noqa: E731
                            out / "imp-lab.regions.png")
    named = rf"exertion point 1 \(exertion_points\.vertex_ids\[1\] = {ids[1]}; .*\) lies on the surface facing away"
    if mode == "strict":
        with pytest.raises(SupportError, match=named):
            run()
        assert not (out / "imp-lab.vtu").exists()
        return
    with caplog.at_level(logging.WARNING):
        feats = run()
    assert [r["point"] for r in feats["exertion_not_visible"]] == [1]
    assert re.search(named, _facing_warnings(caplog)[0])


def test_the_given_mesh_builder_checks_its_points_itself():
    """build_given_mesh checks given points on its own visible facets as build_liver_mesh does on its surface:
    recorded under warn, refused under strict, not checked under off (a caller need not check again)."""
    from liverforce.geometry.procedural import procedural_liver
    from liverforce.mesh.build import build_liver_mesh
    from liverforce.mesh.given import build_given_mesh

    orig = build_liver_mesh(procedural_liver(0), target_nodes=400, seed=0)
    P, Fb = orig.points, orig.facets
    n = _vertex_normals(P, Fb)
    vis = np.flatnonzero(_all_facets(P, Fb, orig.facet_visible))
    back = np.flatnonzero(_all_facets(P, Fb, (orig.facet_region == 0) & ~orig.facet_visible) & (n[:, 1] < -0.8))
    q = P[[int(vis[np.argmax(n[vis, 1])]), int(back[np.argmin(P[back, 1])])]]
    warned = build_given_mesh(P, orig.tets, exertion_points=q)
    assert [r["point"] for r in warned.meta["exertion_not_visible"]] == [1]
    with pytest.raises(SupportError, match=r"exertion point 1 .* lies on the surface facing away"):
        build_given_mesh(P, orig.tets, exertion_points=q, regions_check="strict")
    off = build_given_mesh(P, orig.tets, exertion_points=q, regions_check="off")
    assert off.meta["exertion_not_visible"] is None and np.allclose(off.meta["exertion_candidates_mm"], q)


#: oblique facets of procedural_liver(0), off the visible area but facing the camera (60-90 deg from the view):
#: anterior-inferior, right-lateral, the superior dome (outward normals, RAS, and their angles to the view)
OBLIQUE = {"anterior-inferior": ([-0.48, 0.73, -0.48], 67), "right-lateral": ([0.96, 0.2, -0.2], 86),
           "dome": ([-0.29, -0.12, 0.95], 68)}


def _classified(V, F):
    """The smoothed normals and view direction the visible area is classified with, computed here as
    ``liverforce.mesh.regions`` computes them (normals averaged over 8 mm; anterior tilted 30 deg up)."""
    from liverforce.mesh.boundary import facet_normals
    from liverforce.mesh.regions import RegionParams, _smoothed_normals

    n = _smoothed_normals(V[F].mean(axis=1), facet_normals(V, F, unit=False), 8.0)
    view = RegionParams().frame().T @ np.array([0.0, np.cos(np.pi / 6), np.sin(np.pi / 6)])
    return n, view


@pytest.fixture(scope="module")
def oblique(liver_surface):
    """The centroid of the facet off the visible area whose classified normal is each of ``OBLIQUE``'s."""
    V, F = liver_surface.vertices, liver_surface.faces
    _, visible = tag_regions(V, F)
    n, _ = _classified(V, F)
    off = np.flatnonzero(~visible)
    out = {}
    for name, (normal, _) in OBLIQUE.items():
        t = np.asarray(normal) / np.linalg.norm(normal)
        j = off[np.argmax(n[off] @ t)]
        assert n[j] @ t > 0.999, name
        out[name] = V[F[j]].mean(axis=0)
    return out


def _snap_oblique(liver_surface, oblique, caplog, **kw):
    """The three oblique points snapped on the liver's auto-tagged regions: ``(points, records)``."""
    V, F = liver_surface.vertices, liver_surface.faces
    region, visible = tag_regions(V, F)
    found = []
    with caplog.at_level(logging.WARNING):
        pts, _ = snap_exertion_points(V, F, region, np.vstack(list(oblique.values())), visible=visible,
                                      not_visible=found, **kw)
    return pts, found


def test_oblique_points_are_warned_as_oblique_not_as_facing_away(liver_surface, oblique, caplog):
    _, found = _snap_oblique(liver_surface, oblique, caplog)
    assert [r["point"] for r in found] == [0, 1, 2]
    for r, (normal, angle) in zip(found, OBLIQUE.values()):
        assert np.allclose(r["normal_ras"], normal, atol=0.01) and abs(r["angle_to_view_deg"] - angle) < 1
        assert r["facing"] == "oblique" and r["frame_mix_up"] is None and not r["refused_under_strict"]
        w = r["warning"]
        assert re.match(r"exertion point \d \[.*\] \(mesh frame, mm\) lies on an oblique part of the surface, off the "
                        r"visible area .* so it faces the camera, but from the side: outside "
                        r"mesh\.regions\.visible_cone_deg, under 90 deg\. .*would come from the side of the liver\. "
                        r"If the point is meant, widen mesh\.regions\.visible_cone_deg \(to at least \d+\)$", w), w
        assert "facing away" not in w and "behind" not in w and "mix-up" not in w and "LPS" not in w
    assert [m.getMessage() for m in caplog.records if m.levelno == logging.WARNING] == [r["warning"] for r in found]


def test_oblique_points_are_not_refused_under_strict(liver_surface, oblique, caplog):
    pts, found = _snap_oblique(liver_surface, oblique, caplog, regions_check="strict")
    assert len(pts) == 3 and [r["facing"] for r in found] == ["oblique"] * 3
    assert len([m for m in caplog.records if "oblique part of the surface" in m.getMessage()]) == 3


@pytest.mark.slow  # one of the default set's slowest (CI's --durations): run with -m slow
def test_oblique_points_pass_a_strict_mesh_stage_a_posterior_one_does_not(tmp_path, liver_surface, points, oblique):
    rows = [points["anterior"], *oblique.values()]
    tools = _tools(tmp_path, rows)
    out, run = _stage(tmp_path, liver_surface, tools, "strict")
    feats = run()
    assert (out / "imp-lab.vtu").exists()
    rec = feats["exertion_not_visible"]
    assert [r["point"] for r in rec] == [1, 2, 3] and {r["facing"] for r in rec} == {"oblique"}
    (tmp_path / "b").mkdir()
    tools2 = _tools(tmp_path / "b", [*rows, points["posterior"]])
    _, run2 = _stage(tmp_path / "b", liver_surface, tools2, "strict")
    with pytest.raises(SupportError) as err:
        run2()
    msg = str(err.value)
    assert re.match(_named(tools2, 5, points["posterior"]) + " lies on the surface facing away from the camera", msg)
    assert msg.count("exertion point ") == 1 and "oblique part" not in msg  # the oblique ones are only warned


def test_regions_check_off_skips_the_check(tmp_path, liver_surface, points, caplog):
    V, F = liver_surface.vertices, liver_surface.faces
    region, visible = tag_regions(V, F)
    q = np.vstack([points["anterior"], points["posterior"]])
    found = []
    with caplog.at_level(logging.WARNING):
        snap_exertion_points(V, F, region, q, visible=visible, regions_check="off", not_visible=found)
        assert check_exertion_facing(V, F, visible, q, regions_check="off") is None
    assert found == [] and not caplog.records
    tools = _tools(tmp_path, q)
    out, run = _stage(tmp_path, liver_surface, tools, "off")
    with caplog.at_level(logging.WARNING):
        feats = run()
    assert not [m for m in caplog.records if "exertion point" in m.getMessage()]
    assert not feats["exertion_not_visible"]  # no record (null where the check is skipped outright)


def test_the_reported_angle_is_the_one_that_classified_the_facet(liver_surface, points, oblique, monkeypatch):
    """On a dense surface the classification smooths normals over cells of facets: the warning reports that
    normal and angle, not a ball average of its own."""
    from liverforce.mesh import regions

    monkeypatch.setattr(regions, "SMOOTHING_PAIRS_AT_ONCE", 400_000)  # as for a CT surface: cell-binned
    V, F = liver_surface.vertices, liver_surface.faces
    region, visible = tag_regions(V, F)
    n, view = _classified(V, F)
    angle = np.degrees(np.arccos(np.clip(n @ view, -1.0, 1.0)))
    q = np.vstack([points["posterior"], *oblique.values()])
    _, _, facet = closest_on_triangles(V[F], q)
    found = check_exertion_facing(V, F, visible, q)
    assert [r["point"] for r in found] == [0, 1, 2, 3]
    for r, j in zip(found, facet):
        assert r["angle_to_view_deg"] == round(float(angle[j]), 1)
        assert r["normal_ras"] == [round(float(x), 3) for x in n[j]]
        assert (r["angle_to_view_deg"] > 60) == (not visible[j])
