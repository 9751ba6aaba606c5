"""Serving a camera-cloud model when the camera's registration to the pre-operative surface is off: refined from
the camera's cloud of the same region before the tool pushed (``Predictor.refine_registration``, ``liverforce
predict --unloaded``)."""
from __future__ import annotations

import argparse
import json
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from liverforce.cli import register_predict
from liverforce.learn.observation import ObservationConfig, observe
from liverforce.serve import Predictor
from liverforce.serve.errors import PredictionInputError

from tests.serve.test_camera_serving import _case, _context_columns, _context_in_metres
from tests.serve.test_camera_serving import served  # noqa: F401 (the module's trained camera model)


def _unloaded(a: dict, i: int, seed: int = 11):
    """The camera's cloud of case ``i``'s undeformed surface, the tool touching at the exertion point."""
    V, T = a["surface_meshes"][a["geometry_id"][i]]
    cfg = ObservationConfig(n_points=(3000, 3000), noise_sd_mm=0.3, roi_radius_mm=40.0)
    cloud, _ = observe(V, T, a["exertion_point_mm"][i], a["frame_normal"][i], cfg, seed=seed)
    return cloud


def _misregistration(a: dict, i: int, shift_mm: float, turn_deg: float):
    """A shift in a seeded direction and a turn about a seeded axis through the liver's centroid."""
    rng = np.random.default_rng(i)
    d, ax = rng.normal(size=3), rng.normal(size=3)
    Q = Rotation.from_rotvec(math.radians(turn_deg) * ax / np.linalg.norm(ax)).as_matrix()
    c = np.asarray(a["liver_centroid_mm"][i], dtype=np.float64)
    b = c - Q @ c + shift_mm * d / np.linalg.norm(d)
    return lambda x: np.asarray(x, dtype=np.float64) @ Q.T + b


def test_a_misregistered_camera_is_put_back_by_the_unloaded_view(served):  # noqa: F811
    path, model, a = served
    pred = Predictor.from_dir(path)
    off, fixed, moved = [], [], []
    for i in range(6):
        ctx, cloud, tip = _case(a, i)
        want = pred.predict_cloud(cloud, ctx, tool_tip_mm=tip)
        move = _misregistration(a, i, 2.0, 2.0)
        try:
            bad = pred.predict_cloud(move(cloud), ctx, tool_tip_mm=move(tip))
        except PredictionInputError:  # so far off that the cloud is refused outright
            bad = None
        fix = pred.refine_registration(move(_unloaded(a, i)), ctx, contact_tip_mm=move(a["exertion_point_mm"][i]))
        assert fix.anchor == "contact tip"  # this model fits no instrument: the robot's tip at contact
        got, info = pred.predict_cloud(move(cloud), ctx, tool_tip_mm=move(tip), registration=fix, return_info=True)
        assert info["registration"]["anchor"] == "contact tip" and "along the normal" in info["registration"]["description"]
        fixed.append(np.linalg.norm(got - want))
        moved.append(np.linalg.norm(move(a["exertion_point_mm"][i]) - a["exertion_point_mm"][i]))
        if bad is not None:
            off.append(np.linalg.norm(bad - want))
    assert min(moved) > 0.5 and np.median(moved) > 1.5  # the camera side really was off
    # refined, the force is the one the well-registered camera gives, to a small part of the force itself
    assert max(fixed) < 0.02 * np.linalg.norm(a["force_n"][:6], axis=1).max()  # 0.023-0.038 N of 4.5 N here
    assert off and np.median(off) > 20 * np.median(fixed)  # as registered it was far off (or refused)


def test_cli_refines_the_registration_from_the_unloaded_cloud(served, tmp_path, capsys):  # noqa: F811
    path, model, a = served
    i = 2
    ctx, cloud, tip = _case(a, i)
    move = _misregistration(a, i, 1.5, 1.0)
    np.save(tmp_path / "cloud.npy", move(cloud) / 1000.0)  # in metres
    np.save(tmp_path / "before.npy", move(_unloaded(a, i)) / 1000.0)
    doc = _context_in_metres(ctx, tmp_path)
    (tmp_path / "ctx.json").write_text(json.dumps(doc))
    parser = argparse.ArgumentParser(prog="liverforce")
    register_predict(parser.add_subparsers(dest="command", required=True))
    base = ["predict", "-m", str(path), str(tmp_path / "cloud.npy"), "--context", str(tmp_path / "ctx.json"),
            "--units", "m", "--tool-tip", *map(str, move(tip) / 1000)]
    contact = ["--contact-tip", *map(str, move(ctx.exertion_point_mm) / 1000)]
    args = parser.parse_args(base + ["--unloaded", str(tmp_path / "before.npy")] + contact)
    assert args.func(args) == 0
    out = json.loads(capsys.readouterr().out)
    pred = Predictor.from_dir(path)
    fix = pred.refine_registration(move(_unloaded(a, i)), ctx, contact_tip_mm=move(ctx.exertion_point_mm))
    want = pred.predict_cloud(move(cloud), ctx, tool_tip_mm=move(tip), registration=fix)
    np.testing.assert_allclose(out["force_n"], want, atol=1e-6)
    reg = out["registration"]
    assert reg["anchor"] == "contact tip" and reg["rms_mm"] < reg["rms_before_mm"]
    np.testing.assert_allclose(np.asarray(reg["matrix"]), fix.matrix, atol=1e-9)
    assert np.linalg.norm(out["force_n"] - pred.predict_cloud(cloud, ctx, tool_tip_mm=tip)) < 0.1
    assert reg["shape_degree"] == 3 and len(reg["shape_coefficients"]) == 10 and len(reg["shape_R"]) == 3
    # the unloaded view as a PCD with points of no measurement (NaN): the same refinement, and said
    from tests.serve.test_read_pcd import write_pcd, xyz

    before = np.vstack([np.full((20, 3), np.nan), move(_unloaded(a, i)) / 1000.0])
    pcd = write_pcd(tmp_path / "before.pcd", xyz(before), "binary")
    args = parser.parse_args(base + ["--unloaded", str(pcd)] + contact)
    assert args.func(args) == 0
    got = json.loads(capsys.readouterr().out)
    np.testing.assert_allclose(got["force_n"], out["force_n"], atol=1e-9)
    assert got["warnings"][0].startswith(f"{pcd}: 20 of {len(before)} points dropped, their coordinates NaN")
    # rigid only on request; --shape-degree without --unloaded is refused
    args = parser.parse_args(base + ["--unloaded", str(tmp_path / "before.npy"), "--shape-degree", "0"] + contact)
    assert args.func(args) == 0
    reg0 = json.loads(capsys.readouterr().out)["registration"]
    assert reg0["shape_degree"] == 0 and reg0["shape_coefficients"] == [] and reg0["shape_R"] is None
    args = parser.parse_args(base + ["--shape-degree", "2"])
    assert args.func(args) == 2 and "--shape-degree goes with --unloaded" in capsys.readouterr().err
    # --contact-tip alone, and an unloaded cloud of another place, are refused with the reason
    assert parser.parse_args(base + contact).func(parser.parse_args(base + contact)) == 2
    assert "--unloaded" in capsys.readouterr().err
    np.save(tmp_path / "far.npy", (move(_unloaded(a, i)) + 40.0 * ctx.frame[0]) / 1000.0)
    args = parser.parse_args(base + ["--unloaded", str(tmp_path / "far.npy")])
    assert args.func(args) == 2
    assert "registration refinement" in capsys.readouterr().err


def test_a_node_model_has_no_registration_to_refine(trained):
    pred = Predictor.from_dir(trained("disp"))
    with pytest.raises(PredictionInputError, match="camera-cloud"):
        pred.refine_registration(np.zeros((10, 3)), None)  # refused before the context is read


def test_the_compiled_path_applies_the_refinement_as_the_reference_does(served):  # noqa: F811
    path, model, a = served
    pred = Predictor.from_dir(path)
    i = 1
    ctx, cloud, tip = _case(a, i)
    move = _misregistration(a, i, 2.0, 2.0)
    fix = pred.refine_registration(move(_unloaded(a, i)), ctx, contact_tip_mm=move(a["exertion_point_mm"][i]))
    want = pred.predict_cloud(move(cloud), ctx, tool_tip_mm=move(tip), registration=fix)
    got = pred.compile_cloud(ctx, registration=fix).predict(move(cloud), move(tip))[0]
    np.testing.assert_allclose(got, want, atol=1e-6)
    # clouds in LPS metres: the frame first, then the refinement; the force back in LPS
    lps = np.diag([-1.0, -1.0, 1.0])
    fast = pred.compile_cloud(ctx, frame="LPS", units="m", registration=fix)
    got = fast.predict(move(cloud) @ lps / 1000.0, lps @ move(tip) / 1000.0)[0]
    np.testing.assert_allclose(got, lps @ want, atol=1e-6)
    assert np.linalg.norm(pred.compile_cloud(ctx).predict(move(cloud), move(tip))[0] - want) > 0.1  # it mattered


def test_the_mlflow_pyfunc_refines_rows_that_bring_their_unloaded_cloud(served, tmp_path):  # noqa: F811
    from liverforce.tracking import Tracker, load_pyfunc, predict_pyfunc

    path, model, a = served
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    tracker = Tracker(uri, "camera-registration")
    run_id = tracker.start_run("cloud", params={}, tags={})
    tracker.log_force_model(run_id, path, {k: v[:1] if not isinstance(v, dict) else v for k, v in a.items()})
    tracker.end_run(run_id)
    pf = load_pyfunc(f"runs:/{run_id}/model", uri)
    assert {"unloaded_cloud_mm", "contact_tip_mm"} <= set(pf.metadata.get_input_schema().input_names())
    rows = [_case(a, i, seed=70 + i) for i in range(3)]
    moves = [_misregistration(a, i, 2.0, 2.0) for i in range(3)]
    cases = _context_columns(a, 3)
    cases["roi_centroid_undeformed_mm"] = np.stack([r[0].roi_undeformed_mm.mean(axis=0) for r in rows])
    cases["camera_cloud_mm"] = [m(r[1]) for m, r in zip(moves, rows)]
    cases["tool_tip_mm"] = np.stack([m(r[2]) for m, r in zip(moves, rows)])
    cases["unloaded_cloud_mm"] = [m(_unloaded(a, i)) for i, m in enumerate(moves)]
    cases["unloaded_cloud_mm"][2] = np.zeros((0, 3))  # this row brings none: predicted as registered
    cases["contact_tip_mm"] = np.stack([m(a["exertion_point_mm"][i]) for i, m in enumerate(moves)])
    got = predict_pyfunc(pf, cases)
    pred = Predictor.from_dir(path)
    for i, (ctx, cloud, tip) in enumerate(rows):
        fix = None if i == 2 else pred.refine_registration(cases["unloaded_cloud_mm"][i], ctx,
                                                           contact_tip_mm=cases["contact_tip_mm"][i])
        want = pred.predict_cloud(moves[i](cloud), ctx, tool_tip_mm=moves[i](tip), registration=fix)
        np.testing.assert_allclose(got[i], want, rtol=1e-5, atol=1e-6)
    honest = [pred.predict_cloud(c, ctx, tool_tip_mm=t) for ctx, c, t in rows]
    assert np.linalg.norm(got[0] - honest[0]) < 0.1 and np.linalg.norm(got[2] - honest[2]) > 0.3
    with pytest.raises(PredictionInputError, match="goes with unloaded_cloud_mm"):
        predict_pyfunc(pf, {k: v for k, v in cases.items() if k != "unloaded_cloud_mm"})
    # a refused row's tip is given back as the user sent it, not as the refined registration moved it
    far = cases["tool_tip_mm"].copy()
    far[0] = far[0] + 3.0 * model.representation.half_width_mm * np.asarray(cases["frame_t1"][0])
    with pytest.raises(PredictionInputError) as exc:
        predict_pyfunc(pf, {**cases, "tool_tip_mm": far})
    sent = ", ".join(f"{x:.6g}" for x in far[0])
    assert "from the exertion point along the surface" in str(exc.value) and f"[{sent}]" in str(exc.value), \
        str(exc.value)


def test_without_the_tip_at_contact_only_the_height_is_refined_and_a_warning_says_so(served):  # noqa: F811
    path, model, a = served
    pred = Predictor.from_dir(path)
    i = 4
    ctx, cloud, tip = _case(a, i)
    move = _misregistration(a, i, 0.0, 0.0)  # registered: only the warning is at stake
    fix = pred.refine_registration(move(_unloaded(a, i)), ctx)
    assert fix.anchor == "none" and fix.tangential_mm < 1e-3  # tilts about the exertion point only
    _, info = pred.predict_cloud(cloud, ctx, tool_tip_mm=tip, registration=fix, return_info=True)
    assert any("along the normal only" in w and "--contact-tip" in w for w in info["warnings"])
    # the same warnings, in the same order, on the compiled path and on rows bringing their unloaded cloud
    fast = pred.compile_cloud(ctx, registration=fix)
    assert fast.predict(cloud, tip)[2] == info["warnings"] == fast.predict_batch([cloud], tip[None]).warnings[0]
    rows = {k: [v[0]] if isinstance(v, list) else np.asarray(v)
            for k, v in ctx.to_arrays(ctx.roi_undeformed_mm).items()}
    rows.update({"camera_cloud_mm": [cloud], "tool_tip_mm": tip[None], "unloaded_cloud_mm": [move(_unloaded(a, i))]})
    assert pred.predict_arrays(rows, return_warnings=True)[1] == [info["warnings"]]


def test_unloaded_columns_on_arrays_are_checked_row_by_row(served, trained):  # noqa: F811
    path, model, a = served
    pred = Predictor.from_dir(path)
    rows = [_case(a, i) for i in range(2)]
    cases = _context_columns(a, 2)
    cases["camera_cloud_mm"] = [r[1] for r in rows]
    cases["tool_tip_mm"] = np.stack([r[2] for r in rows])
    plain = pred.predict_arrays(cases)
    # empty or None rows: nothing to refine; a missing contact tip (None, NaN): the height only
    got = pred.predict_arrays({**cases, "unloaded_cloud_mm": [[], None], "contact_tip_mm": [None, np.nan]})
    np.testing.assert_allclose(got, plain, atol=1e-12)
    bad = {**cases, "unloaded_cloud_mm": [np.zeros((50, 2)), None]}
    with pytest.raises(PredictionInputError, match=f"case {cases['case_id'][0]}: unloaded_cloud_mm"):
        pred.predict_arrays(bad)
    bad = {**cases, "unloaded_cloud_mm": [_unloaded(a, 0), None], "contact_tip_mm": [[1.0, 2.0], None]}
    with pytest.raises(PredictionInputError, match="contact_tip_mm") as exc:
        pred.predict_arrays(bad)
    # return_refused: the row whose registration step is refused gets NaN and that reason; the other is predicted
    force, refused = pred.predict_arrays(bad, return_refused=True)
    assert refused == [str(exc.value), ""] and np.isnan(force[0]).all()
    np.testing.assert_allclose(force[1], plain[1], atol=1e-6)  # a batch of one row: float32 sums in another order
    with pytest.raises(PredictionInputError, match="refines a camera-cloud model"):
        Predictor.from_dir(trained("disp")).refine_arrays({**cases, "unloaded_cloud_mm": [None, None]})


def _bent(a: dict, i: int, amplitude_mm: float = 3.0) -> dict:
    """The arrays with case ``i``'s liver bent along its normal round the exertion point since the scan (a smooth
    height change of the tangent coordinates, up to ``amplitude_mm``), the tool's dent turned with the surface
    there (as the validation's ``changed_shape`` carries it)."""
    from liverforce.pipeline.validate import local_turn

    g = a["geometry_id"][i]
    V, T = a["surface_meshes"][g]
    R = np.stack([a["frame_t1"][i], a["frame_t2"][i], a["frame_normal"][i]])
    p = np.asarray(a["exertion_point_mm"][i], dtype=np.float64)

    def bend(x):
        L = (np.atleast_2d(x) - p) @ R.T
        return np.atleast_2d(x) + amplitude_mm * (np.sin(L[:, 0] / 24.0 + 0.3) * np.cos(L[:, 1] / 30.0))[:, None] * R[2]

    P = np.array(a["exertion_point_mm"], dtype=np.float64)
    P[i] = bend(p)[0]
    Rw = local_turn(lambda x: bend(x)[0], p, R[2], R[0])
    disp = list(a["surface_displacement_mm"])
    disp[i] = np.asarray(disp[i], dtype=np.float64) @ Rw.T
    frame = {k: np.array(a[k], dtype=np.float64) for k in ("frame_normal", "frame_t1", "frame_t2")}
    for k in frame:
        frame[k][i] = Rw @ frame[k][i]
    return {**a, "surface_meshes": {**a["surface_meshes"], g: (bend(V), T)}, "exertion_point_mm": P,
            "surface_displacement_mm": disp, **frame}


def test_a_liver_changed_in_shape_since_the_scan_is_read_against_its_unloaded_view(served):  # noqa: F811
    """Each case's liver bent along its normal round the exertion point since the scan (3 mm), the tool's
    dent on top: refined with the change of shape the force is the scanned liver's again, refined rigidly the
    bend is read as a dent. The compiled path reshapes the clouds as the reference path does (RAS mm, LPS m)."""
    path, model, a = served
    pred = Predictor.from_dir(path)
    rigid, shaped, force = [], [], []
    for i in range(6):
        ctx, cloud, tip = _case(a, i)
        want = pred.predict_cloud(cloud, ctx, tool_tip_mm=tip)
        bent = _bent(a, i)
        _, cloud2, tip2 = _case(bent, i)
        un, contact = _unloaded(bent, i), bent["exertion_point_mm"][i]
        fix = pred.refine_registration(un, ctx, contact_tip_mm=contact)
        fix0 = pred.refine_registration(un, ctx, contact_tip_mm=contact, shape_degree=0)
        assert not fix.rigid and fix0.rigid and fix.shape_mm > 0.2
        got = pred.predict_cloud(cloud2, ctx, tool_tip_mm=tip2, registration=fix)
        shaped.append(np.linalg.norm(got - want))
        rigid.append(np.linalg.norm(pred.predict_cloud(cloud2, ctx, tool_tip_mm=tip2, registration=fix0) - want))
        force.append(np.linalg.norm(want))
        if i == 0:
            fast = pred.compile_cloud(ctx, registration=fix)
            np.testing.assert_allclose(fast.predict(cloud2, tip2)[0], got, atol=1e-6)
            batch = fast.predict_batch(np.stack([cloud2, cloud2]), [tip2, tip2])
            np.testing.assert_allclose(batch.force, [got, got], atol=1e-6)
            # float32 padded (a cloud with a NaN point and padding), a list; a refused cloud keeps its message
            with_nan = np.vstack([cloud2, [[np.nan, 0.0, 0.0]]])
            pad = np.zeros((3, len(with_nan) + 5, 3), np.float32)
            pad[0, :len(cloud2)], pad[1, :len(with_nan)], pad[2, :3] = cloud2, with_nan, cloud2[:3]
            b32 = fast.predict_batch(pad, [tip2] * 3, counts=[len(cloud2), len(with_nan), 3])
            want32 = pred.predict_cloud(cloud2.astype(np.float32).astype(np.float64), ctx, tool_tip_mm=tip2,
                                        registration=fix)
            np.testing.assert_allclose(b32.force[0], want32, atol=1e-6)
            assert "NaN" in b32.refused[1] and "at least" in b32.refused[2] and b32.refused[0] is None
            blist = fast.predict_batch([cloud2, cloud2[:3]], [tip2, tip2])
            np.testing.assert_allclose(blist.force[0], got, atol=1e-6)
            with pytest.raises(PredictionInputError) as why:
                pred.predict_cloud(cloud2[:3], ctx, tool_tip_mm=tip2, registration=fix)
            assert blist.refused[1] == b32.refused[2] == str(why.value)
            # in threads each part is reshaped in its own thread: the same bits
            for clouds, kw in ((pad, {"counts": [len(cloud2), len(with_nan), 3]}), ([cloud2, cloud2[:3], cloud2], {})):
                one, two = (fast.predict_batch(clouds, [tip2] * 3, threads=n, **kw) for n in (1, 2))
                np.testing.assert_array_equal(two.force, one.force)
                assert two.refused == one.refused
            lps = np.diag([-1.0, -1.0, 1.0])
            fast = pred.compile_cloud(ctx, frame="LPS", units="m", registration=fix)
            np.testing.assert_allclose(fast.predict(cloud2 @ lps / 1000.0, lps @ tip2 / 1000.0)[0], lps @ got,
                                       atol=1e-6)
    # 0.02-0.14 N against 0.07-0.24 N rigidly, on forces of 2-4.4 N
    assert np.median(shaped) < 0.5 * np.median(rigid) and max(shaped) < 0.04 * max(force)
