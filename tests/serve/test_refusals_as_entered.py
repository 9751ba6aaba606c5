"""Refusals of an exertion point off the pre-operative surface: measured to the surface's triangles (not a fit
of the nearest nodes, which misjudges a coarse mesh), and said with the point as the user entered it, in the
units and frame the user declared, with the nearest surface point in the same units and frame."""
from __future__ import annotations

import argparse
import json
import re

import meshio
import numpy as np
import pytest

from liverforce.cli import register_predict
from liverforce.serve import PredictionInputError, Predictor
from liverforce.serve.input_frame import InputFrame

LPS = np.array([-1.0, -1.0, 1.0])


def _coarse(ellipsoid):
    """A coarse closed surface (150 vertices, facets ~30 mm) and a point on one facet's middle, where the fit of
    the nearest vertices (which lie on the ellipsoid, not on the facet) puts the surface 2.7 mm away."""
    pts, tri = ellipsoid(n=150)
    a, b, c = pts[tri[0]]
    n = np.cross(b - a, c - a)
    return pts, tri, (a + b + c) / 3.0, n / np.linalg.norm(n)


def _fmt(v) -> str:
    return "[" + ", ".join(f"{float(x):.6g}" for x in v) + "]"


def run(argv, capsys) -> tuple[int, str]:
    parser = argparse.ArgumentParser(prog="liverforce")
    register_predict(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["predict", *map(str, argv)])
    rc = args.func(args)
    return rc, capsys.readouterr().err


def test_a_point_on_a_coarse_surface_is_measured_to_its_triangles(trained, ellipsoid):
    """0.5 mm off a coarse facet: accepted (the nearest vertices' quadratic said 2.7 mm and refused it); 3 mm off:
    refused with the distance to the triangles, the point and its nearest surface point as given (RAS mm, none
    declared)."""
    pts, tri, mid, n = _coarse(ellipsoid)
    pred = Predictor.load(trained("deformed"))
    ctx = pred.preop_from_surface(pts, tri, mid + 0.5 * n)
    np.testing.assert_allclose(ctx.surface_point_mm, mid, atol=1e-9)
    with pytest.raises(PredictionInputError) as exc:
        pred.preop_from_surface(pts, tri, mid + 3.0 * n)
    msg = str(exc.value)
    assert msg.startswith("the exertion point is 3 mm off the pre-operative surface (at most 2 mm)"), msg
    assert f"it was given as {_fmt(mid + 3.0 * n)} mm RAS (no units or frame were declared" in msg, msg
    assert f"the nearest point of the surface is {_fmt(mid)} mm RAS" in msg, msg


def test_cli_names_the_point_off_the_surface_in_the_declared_units_and_frame(trained, ellipsoid, tmp_path, capsys):
    """A surface and exertion point in LPS metres (--frame LPS --units m): a point 3 mm off is refused with its
    value as entered and the nearest surface point, both in m LPS, and what was declared; given in mm instead,
    it is said to look like mm while m was declared, never told to give --frame."""
    pts, tri, mid, n = _coarse(ellipsoid)
    np.savez(tmp_path / "lps.npz", points=pts * LPS / 1000.0, facets=tri)
    np.save(tmp_path / "cloud.npy", pts * LPS / 1000.0)
    off = np.round((mid + 3.0 * n) * LPS / 1000.0, 6)
    base = ["-m", trained("deformed"), tmp_path / "cloud.npy", "--surface", tmp_path / "lps.npz", "--frame", "LPS",
            "--units", "m"]
    rc, err = run(base + ["--exertion-point", *off], capsys)
    assert rc == 2 and f"it was given as {_fmt(off)} m LPS (declared in m, LPS)" in err, err
    near = re.search(r"the nearest point of the surface is \[([^]]*)\] m LPS", err)
    np.testing.assert_allclose(np.array(near.group(1).split(", "), float), mid * LPS / 1000.0, atol=2e-6)
    d = np.linalg.norm(off * LPS * 1000.0 - mid)
    assert f"the exertion point is {d:.3g} mm off the pre-operative surface" in err, err
    on = (mid + 0.2 * n) * LPS
    rc, err = run(base + ["--exertion-point", *on], capsys)  # in mm, said to be in m
    assert rc == 2 and "it looks like mm while m, LPS was declared" in err and "--frame" not in err, err
    assert f"it was given as {_fmt(on)} m LPS" in err, err


def test_the_refusal_says_where_the_sweep_pressed_on_the_meshed_liver(trained, ellipsoid, tmp_path, capsys):
    """The pre-operative surface is the mesh's own (results/<exp>/mesh/<gid>.vtu): a point 3 mm off it is refused
    naming the nearest point the model's scenario's sweep pressed at, in the units declared, and the files
    holding them (sweep.json, cases.parquet)."""
    pts, tri, mid, n = _coarse(ellipsoid)
    root = tmp_path / "res"
    (root / "mesh").mkdir(parents=True)
    (root / "sweep" / "III").mkdir(parents=True)
    meshio.write(root / "mesh" / "liv.vtu", meshio.Mesh(pts, [("triangle", tri)]))
    far = pts[tri[50]].mean(axis=0)
    (root / "sweep" / "III" / "sweep.json").write_text(json.dumps({"exertion_points_mm": {"liv": [far.tolist(),
                                                                                                  mid.tolist()]}}))
    np.save(tmp_path / "cloud.npy", pts)
    model = trained("deformed")
    assert Predictor.load(model).model.meta["scenario"] == "III"
    rc, err = run(["-m", model, tmp_path / "cloud.npy", "--mesh", root / "mesh" / "liv.vtu", "--units", "cm",
                   "--exertion-point", *((mid + 3.0 * n) / 10.0)], capsys)
    assert rc == 2 and "off the pre-operative surface" in err, err
    assert f"the nearest at {_fmt(mid / 10.0)} cm RAS" in err and "sweep of scenario III" in err, err
    assert str(root / "sweep" / "III" / "sweep.json") in err and str(root / "sweep" / "III" / "cases.parquet") in err


def test_the_probes_mesh_check_names_the_declared_units_not_frame_advice(monkeypatch, ellipsoid):
    """The stiffness probe's mesh check (5 mm): with units and frame declared (an import record), an exertion
    point given in mm is said to look like mm while m was declared, with its value as entered; never 'give
    --frame'. With nothing declared, the advice to declare the frame stays."""
    import types

    from liverforce.serve import probe
    from liverforce.serve.preop import Preop

    pts, tri, mid, n = _coarse(ellipsoid)

    class Stub:
        def __init__(self, *a, **k):
            self.surf = types.SimpleNamespace(points=pts, triangles=tri)

    monkeypatch.setattr(probe, "LiverProbe", Stub)
    monkeypatch.setattr(probe, "probe_settings", lambda meta: {})
    fr = InputFrame(scale=1000.0, units="m", label="LPS", matrix=np.diag([-1.0, -1.0, 1.0, 1.0]),
                    source="results/lab/geometry/imp-lab01.json")
    entered = mid * LPS  # in mm, declared in m
    ctx = Preop.from_surface(pts, tri, mid)
    import dataclasses

    wrong = dataclasses.replace(ctx, exertion_point_mm=fr.points(entered))
    with pytest.raises(PredictionInputError) as exc:
        probe.with_probe(wrong, "liver.vtu", {}, frame=fr)
    msg = str(exc.value)
    assert "off the mesh's surface (at most 5 mm)" in msg and f"it was given as {_fmt(entered)} m LPS" in msg, msg
    assert "declared in m, LPS by results/lab/geometry/imp-lab01.json" in msg, msg
    assert "it looks like mm while m, LPS was declared" in msg and "--frame" not in msg, msg
    assert "is it in mm" not in msg
    with pytest.raises(PredictionInputError) as exc:
        probe.with_probe(dataclasses.replace(ctx, exertion_point_mm=mid / 1000.0), "liver.vtu", {})
    msg = str(exc.value)
    assert "no units or frame were declared" in msg and "it looks like m, but no units or frame" in msg, msg
    assert "--units m" in msg, msg


def test_a_refused_point_builds_one_search_tree_for_all_its_readings(monkeypatch, trained, ellipsoid):
    """The hint of a point off the surface reads it in every other units and frame (six readings for m LPS
    declared): all of them are measured to the surface in one query, on the one search tree over the surface's
    triangles that also measured the context's own distance to it (not one a reading: seconds a refusal on a CT
    surface), and the reading that fits is still named."""
    import dataclasses
    import types

    import scipy.spatial

    from liverforce.serve import probe

    pts, tri, mid, n = _coarse(ellipsoid)
    pred = Predictor.load(trained("deformed"))
    fr = InputFrame.resolve("LPS", "m")
    ctx = pred.preop_from_surface(pts, tri, mid + 0.5 * n)
    real = scipy.spatial.cKDTree

    def refused(call) -> tuple[int, str]:
        """How many search trees ``call`` builds before it refuses, and why it refuses."""
        builds = []

        def counted(*args, **kwargs):
            builds.append(1)
            return real(*args, **kwargs)

        with monkeypatch.context() as m:
            m.setattr(scipy.spatial, "cKDTree", counted)
            with pytest.raises(PredictionInputError) as exc:
                call()
        return len(builds), str(exc.value)

    for entered, said in ((mid * LPS, "it looks like mm while m, LPS was declared"),  # mm, declared m: found
                          ((mid + 40.0 * n) * LPS / 1000.0, "put the exertion point on the surface")):  # no reading
        wrong = dataclasses.replace(ctx, exertion_point_mm=fr.points(entered))
        # the context's distance to its surface (cached), then the refusal's readings: one tree for both
        builds, why = refused(lambda: (wrong.surface_point_mm, pred.check_preop(wrong, frame=fr)))
        assert builds == 1 and said in why, (builds, why)
    # the probe's mesh check: its distance, then one query for every reading, on one tree
    monkeypatch.setattr(probe, "LiverProbe", lambda *a, **k: types.SimpleNamespace(
        surf=types.SimpleNamespace(points=pts, triangles=tri)))
    monkeypatch.setattr(probe, "probe_settings", lambda meta: {})
    wrong = dataclasses.replace(ctx, exertion_point_mm=fr.points(mid * LPS))
    builds, why = refused(lambda: probe.with_probe(wrong, "liver.vtu", {}, frame=fr))
    assert builds == 1 and "it looks like mm while m, LPS was declared" in why, (builds, why)



def test_units_without_a_frame_are_told_how_to_give_one(ellipsoid):
    """A point given with units and no frame, off the surface under every reading (a lab's own frame, here the
    surface shifted 200 mm, which neither RAS nor LPS nor other units undo): the refusal says no frame was given
    and how to give one; with a frame declared (LPS) it does not repeat that advice; with nothing declared it
    says so and gives the advice too."""
    from liverforce.serve.checks import off_surface

    pts, tri, mid, n = _coarse(ellipsoid)
    surface = pts[tri]
    shifted = mid + np.array([200.0, 0.0, 0.0])  # RAS mm, as the model reads it
    nearest = mid
    d = float(np.linalg.norm(shifted - nearest))
    msg = off_surface(d, shifted, nearest, 2.0, InputFrame.resolve(None, "m"), surface)
    assert "(declared in m, no frame given, so read as RAS)" in msg and "give it with --frame" in msg, msg
    msg = off_surface(d, shifted, nearest, 2.0, InputFrame.resolve("LPS", "m"), surface)
    assert "(declared in m, LPS)" in msg and "--frame" not in msg, msg
    msg = off_surface(d, shifted, nearest, 2.0, None, surface)
    assert "no units or frame were declared" in msg and "give it with --frame" in msg, msg
