"""Predictor, correspondence mode (a): same force as the training model, contexts from arrays or a surface."""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial import Delaunay

from liverforce.learn.model import ForceModel
from liverforce.serve import Predictor, Preop
from liverforce.serve.preop import surface_moments


def test_correspondence_mode_equals_the_model(trained, test_cases):
    pred = Predictor.load(trained("disp"))
    ref = pred.model.predict(test_cases)
    got = np.array([pred.predict(test_cases["roi_deformed_mm"][i], Preop.from_arrays(test_cases, i))
                    for i in range(len(ref))])
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-6)  # float32 network: batch vs single rounding
    np.testing.assert_array_equal(pred.predict_arrays(test_cases), ref)
    # the force rotates with the liver: a rigid motion of every input rotates the prediction
    from liverforce.learn.synthetic import random_rotation, rigid_motion

    Q = random_rotation(np.random.default_rng(3))
    moved = rigid_motion(test_cases, Q, np.array([40.0, -250.0, 13.0]))
    np.testing.assert_allclose(pred.predict_arrays(moved), ref @ Q.T, atol=1e-5)


def test_describe_and_required_context(trained, test_cases):
    pred = Predictor.load(trained("disp"))
    d = pred.describe()
    assert d["uses_state_vector"] and d["n_material_params"] == 2
    assert d["representation"]["features"] == "displacement"
    assert d["cloud_support"] == "approximate"
    assert d["training_scale_source"] == "bundle meta training_scale"
    cli = d["command_line"]  # the options of liverforce predict this model needs, its 2 constants named
    assert cli[0].startswith("--mode nodes") and any(c.startswith("--material C1 C2: the 2 ") for c in cli)
    assert any(c.startswith("--mesh MESH") for c in cli) and not any("--tool-tip" in c for c in cli)
    ctx = Preop.from_arrays(test_cases, 0)
    from liverforce.serve import PredictionInputError

    with pytest.raises(PredictionInputError, match="state vector.*material_params_mpa"):
        pred.predict(test_cases["roi_deformed_mm"][0], Preop(ctx.exertion_point_mm, ctx.frame, ctx.roi_undeformed_mm))
    # a model without the state vector needs no liver features or material
    pdef = Predictor.load(trained("deformed"))
    f = pdef.predict(test_cases["roi_deformed_mm"][0], Preop(ctx.exertion_point_mm, ctx.frame, ctx.roi_undeformed_mm))
    # the same force as the model gives the full case (its liver features and material are ignored)
    np.testing.assert_array_equal(f, ForceModel.load(trained("deformed")).predict(
        {k: v[:1] for k, v in test_cases.items()})[0])


def test_surface_moments_match_tet_integration_and_the_ellipsoid(ellipsoid):
    pts, tri = ellipsoid()
    vol, cen, inertia = surface_moments(pts, tri)
    # the same polyhedron as tetrahedra (Delaunay of the convex point set)
    tets = Delaunay(pts).simplices
    v = pts[tets]
    sv = np.einsum("ti,ti->t", v[:, 1] - v[:, 0], np.cross(v[:, 2] - v[:, 0], v[:, 3] - v[:, 0])) / 6
    tot = np.abs(sv).sum()
    c_tet = (np.abs(sv)[:, None] * v.mean(axis=1)).sum(axis=0) / tot
    r = v - c_tet
    s = r.sum(axis=1)
    m = (np.einsum("t,tai,taj->ij", np.abs(sv), r, r) + np.einsum("t,ti,tj->ij", np.abs(sv), s, s)) / 20
    np.testing.assert_allclose(vol, tot, rtol=1e-12)
    np.testing.assert_allclose(cen, c_tet, atol=1e-9)
    np.testing.assert_allclose(inertia, np.trace(m) * np.eye(3) - m, rtol=1e-10, atol=1e-6 * np.abs(inertia).max())
    # and close to the smooth ellipsoid: V = 4/3 pi abc, I_xx = V (b² + c²) / 5
    a, b, c = 100.0, 70.0, 40.0
    V = 4 / 3 * np.pi * a * b * c
    assert vol == pytest.approx(V, rel=0.01)
    np.testing.assert_allclose(np.diag(inertia), V / 5 * np.array([b*b + c*c, a*a + c*c, a*a + b*b]), rtol=0.02)
    # inward facets give the same body
    v2, c2, i2 = surface_moments(pts, tri[:, [0, 2, 1]])
    assert v2 == pytest.approx(-vol) and np.allclose(c2, cen) and np.allclose(i2, inertia)


def test_context_from_surface_is_the_data_factorys(trained, ellipsoid):
    from liverforce.serve import PredictionInputError

    pts, tri = ellipsoid()
    p = pts[123]  # a vertex on the upper half
    ctx = Preop.from_surface(pts, tri[:, [0, 2, 1]], p, [0.0016, 0.0125], roi_fraction=0.05, frame_radius_mm=5.0)
    from liverforce.dataset.roi import extract_roi, local_frame, surface_graph

    surf = surface_graph(pts, tri)
    np.testing.assert_allclose(ctx.frame, local_frame(surf, p, 5.0), atol=1e-12)
    ids, _ = extract_roi(surf, p, 0.05)
    np.testing.assert_array_equal(ctx.roi_point_ids, surf.node_ids[ids])
    np.testing.assert_array_equal(ctx.roi_undeformed_mm, pts[surf.node_ids[ids]])
    # the patch's own triangles (camera models read the pre-operative height from them): exactly the facets
    # whose three vertices are ROI vertices, indexing roi_undeformed_mm
    in_roi = np.isin(tri, ctx.roi_point_ids).all(axis=1)
    assert len(ctx.roi_triangles) == in_roi.sum() > 0
    got = {tuple(sorted(t)) for t in ctx.roi_point_ids[ctx.roi_triangles].tolist()}
    assert got == {tuple(sorted(t)) for t in tri[in_roi].tolist()}
    assert np.dot(ctx.frame[2], p) > 0  # outward normal although the facets were given inward
    np.testing.assert_allclose(ctx.liver_centroid_mm, 0.0, atol=1e-3)  # Fibonacci points: nearly symmetric
    # a deformed copy of the whole surface -> its ROI rows -> a finite force, through the checks
    pred = Predictor.load(trained("disp"))
    with pytest.raises(PredictionInputError, match=r"lacks \['probe_compliance_mm_per_n'\].*--mesh"):
        pred.check_preop(ctx)  # a state-vector model needs the stiffness probe too
    ctx = ctx.with_compliance(np.diag([0.8, 0.8, 1.5]))  # the synthetic training data's, mm/N
    pred.check_preop(ctx)
    dent = pts + 0.0
    dent[ctx.roi_point_ids] -= 2.0 * ctx.frame[2] * np.exp(-np.sum((pts[ctx.roi_point_ids] - p) ** 2, 1) / 200)[:, None]
    f = pred.predict(ctx.roi_of_surface(dent), ctx)
    assert np.isfinite(f).all() and f @ ctx.frame[2] < 0  # a dent along -n: the tool pushes into the surface
    # an open surface has no volume features: a state-vector model refuses it
    open_ctx = Preop.from_surface(pts, tri[10:], p, [0.0016, 0.0125], roi_fraction=0.05)
    assert open_ctx.liver_centroid_mm is None
    with pytest.raises(PredictionInputError, match="liver_centroid_mm"):
        pred.check_preop(open_ctx)


def test_preop_round_trips_through_a_dict(test_cases):
    ctx = Preop.from_arrays(test_cases, 1)
    back = Preop.from_dict(ctx.to_dict())
    for k in ("exertion_point_mm", "frame", "roi_undeformed_mm", "material_params_mpa", "liver_centroid_mm",
              "inertia_mm5", "tool_thickness_mm", "probe_compliance_mm_per_n"):
        np.testing.assert_array_equal(getattr(back, k), getattr(ctx, k))


def test_preop_keeps_and_checks_the_roi_patchs_triangles(ellipsoid):
    from liverforce.serve import PredictionInputError

    pts, tri = ellipsoid()
    ctx = Preop.from_surface(pts, tri, pts[123], [0.0016, 0.0125], roi_fraction=0.05)
    back = Preop.from_dict(json.loads(json.dumps(ctx.to_dict())))
    np.testing.assert_array_equal(back.roi_triangles, ctx.roi_triangles)
    assert back.roi_triangles.dtype == np.int64
    np.testing.assert_array_equal(ctx.to_arrays(ctx.roi_undeformed_mm)["roi_triangles"][0], ctx.roi_triangles)
    import dataclasses

    k = len(ctx.roi_undeformed_mm)
    for bad, why in ((ctx.roi_triangles + k, "index points"), (ctx.roi_triangles + 0.5, "whole numbers"),
                     (ctx.roi_triangles[:, :2], "whole numbers")):
        with pytest.raises(PredictionInputError, match=why):
            dataclasses.replace(ctx, roi_triangles=bad)


def test_load_refuses_a_file_and_names_missing_dirs(tmp_path, trained):
    from liverforce.serve import PredictionInputError

    f = tmp_path / "model.json"
    f.write_text("{}")
    with pytest.raises(PredictionInputError, match="a file, not a model directory"):
        Predictor.load(f)
    with pytest.raises(PredictionInputError, match="format 'None' is not 'liverforce.force_model'"):
        Predictor.from_dir(tmp_path)
    (tmp_path / "empty").mkdir()
    with pytest.raises(PredictionInputError, match="no model.json"):
        Predictor.from_dir(tmp_path / "empty")
    assert isinstance(Predictor.load(trained("disp")).model, ForceModel)


def test_a_context_of_the_mesh_alone_takes_the_meshs_own_surface(trained, ellipsoid, tmp_path):
    """`mesh` without `surface`: the pre-operative surface is the tet mesh's boundary, in RAS mm whatever frame
    the other inputs come in (the mesh stage wrote it so); liver features and a surface are refused beside it,
    before anything else is read."""
    import meshio

    from liverforce.serve import PredictionInputError
    from liverforce.serve.files import read_context

    pts, tri = ellipsoid()
    pts = pts + np.array([30.0, -20.0, 140.0])  # off the origin, as a liver in RAS is
    tets = Delaunay(pts).simplices  # convex: the hull's facets are the boundary
    a, b, c, d = (pts[tets[:, k]] for k in range(4))
    neg = np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) < 0
    tets[neg] = tets[neg][:, [0, 2, 1, 3]]
    meshio.write(tmp_path / "liver.vtu", meshio.Mesh(pts, [("tetra", tets)]))
    pred = Predictor.load(trained("deformed"))  # no state vector: no stiffness probe needed
    p = pts[123]
    ctx, _ = read_context({"exertion_point_mm": p.tolist(), "mesh": str(tmp_path / "liver.vtu"),
                           "input_frame": "RAS"}, pred)
    ref = Preop.from_surface(pts, tri, p, None, roi_fraction=pred.roi_fraction, frame_radius_mm=pred.frame_radius_mm)
    np.testing.assert_allclose(ctx.frame, ref.frame, atol=1e-12)
    np.testing.assert_array_equal(ctx.roi_undeformed_mm, ref.roi_undeformed_mm)
    assert ctx.tool_thickness_mm == pytest.approx(ref.tool_thickness_mm, rel=1e-12)
    np.testing.assert_allclose(ctx.liver_centroid_mm, ref.liver_centroid_mm, atol=1e-9)
    # the exertion point in LPS metres: converted; the mesh is not
    lps, _ = read_context({"exertion_point_mm": (p * [-1.0, -1.0, 1.0] / 1000.0).tolist(),
                           "mesh": str(tmp_path / "liver.vtu"), "input_frame": "LPS", "units": "m"}, pred)
    np.testing.assert_array_equal(lps.roi_point_ids, ctx.roi_point_ids)
    assert lps.tool_thickness_mm == pytest.approx(ctx.tool_thickness_mm, rel=1e-9)
    # liver features beside the mesh: refused by name, even with an exertion point nowhere near the liver
    with pytest.raises(PredictionInputError, match=r"either the tet 'mesh' alone .*tool_thickness_mm"):
        read_context({"exertion_point_mm": [0.0, 0.0, 9e3], "mesh": str(tmp_path / "liver.vtu"),
                      "input_frame": "RAS", "tool_thickness_mm": 60.0}, pred)
    with pytest.raises(PredictionInputError, match=r"either a surface or inertia_mm5"):
        read_context({"exertion_point_mm": [0.0, 0.0, 9e3], "surface": str(tmp_path / "liver.vtu"),
                      "input_frame": "RAS", "inertia_mm5": np.eye(3).tolist()}, pred)
