"""Serving a camera-cloud model: exact from a cloud and the tool tip (no approximate flag), with its interval,
and every out-of-distribution input refused or flagged with the reason."""
from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from liverforce.cli import register_predict
from liverforce.learn.model import ForceModel, subset
from liverforce.learn.observation import observe
from liverforce.learn.synthetic import synthetic_surface_arrays
from liverforce.learn.train import train_scenario
from liverforce.serve import Predictor, Preop
from liverforce.serve.errors import PredictionInputError

from tests.serve.test_input_frame import rigid, to_input_arrays, to_inputs

MODEL = {"encoder": "pca", "code_size": 6, "state_vector": True, "grid_size": 8, "hidden": [32, 32],
         "dropout": 0.0, "occlusion": {"radius_mm": 0.0, "mode": "remove"}, "noise_mm": 0.0,
         "roi_features": "cloud", "force_scaling": "stiffness", "probe_force_radius_mm": 5.0,
         "indentation_strain": True,  # as the shipped camera model: the compiled path reads tip_n / h too
         "camera": {"observation": {"n_points": [300, 3000], "noise_sd_mm": 0.3}, "grid": {}, "tip_noise_mm": 0.1}}
TRAIN = {"test_fraction": 0.2, "epochs": 60, "batch_size": 32, "lr": 3e-3, "weight_decay": 0.0, "seed": 0,
         "interval": {"coverage": 0.9, "calibration_fraction": 0.25}}
NO_TUNE = {"enabled": False, "trials": 1, "folds": 2, "sobol_trials": 1, "epochs": 1}


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    arrays = synthetic_surface_arrays(200, n_geometries=4, seed=7, material_varies=True)
    res = train_scenario(arrays, MODEL, TRAIN, NO_TUNE, "IV", "cloud", out_dir=tmp_path_factory.mktemp("cam"))
    model = ForceModel.load(res["model_path"])
    assert model.pre.indentation_strain
    test = np.flatnonzero(np.isin(arrays["geometry_id"], res["split"]["test_geometries"]))
    return res["model_path"], model, subset(arrays, test)


def _case(arrays: dict, i: int, n_points: int = 3000, seed: int = 0):
    """Pre-operative context, a new camera cloud and the tool tip of case ``i`` (no node ids)."""
    V, T = arrays["surface_meshes"][arrays["geometry_id"][i]]
    u = np.asarray(arrays["surface_displacement_mm"][i], dtype=np.float64)
    p = arrays["exertion_point_mm"][i]
    tip = p + u[int(np.argmin(np.linalg.norm(V - p, axis=1)))]
    from liverforce.learn.observation import ObservationConfig

    cfg = ObservationConfig(n_points=(n_points, n_points), noise_sd_mm=0.3, roi_radius_mm=40.0)
    cloud, _ = observe(V + u, T, tip, arrays["frame_normal"][i], cfg, seed=seed)
    ctx = Preop.from_arrays({k: v for k, v in arrays.items() if k != "roi_deformed_mm"}, i)
    return ctx, cloud, tip


CONTEXT_COLUMNS = ("case_id", "exertion_point_mm", "frame_normal", "frame_t1", "frame_t2", "roi_undeformed_mm",
                   "roi_centroid_undeformed_mm", "liver_centroid_mm", "inertia_mm5", "tool_thickness_mm",
                   "probe_compliance_mm_per_n", "material_params_mpa", "roi_triangles")


def _context_columns(arrays: dict, n: int) -> dict:
    """The pre-operative context of the first ``n`` cases, as input-contract columns (no clouds, no node ids)."""
    return {k: [arrays[k][i] for i in range(n)] if isinstance(arrays[k], list) else np.asarray(arrays[k])[:n]
            for k in CONTEXT_COLUMNS}


def _context_in_metres(ctx, folder) -> dict:
    """A context file's document of ``ctx`` in metres (its ROI and triangles written beside it as .npy)."""
    np.save(folder / "roi.npy", ctx.roi_undeformed_mm / 1000.0)
    np.save(folder / "roi_tri.npy", ctx.roi_triangles)
    return {"units": "m", "exertion_point_mm": (ctx.exertion_point_mm / 1000).tolist(), "roi_undeformed": "roi.npy",
            "roi_triangles": "roi_tri.npy",
            "frame": {"normal": ctx.frame[2].tolist(), "t1": ctx.frame[0].tolist(), "t2": ctx.frame[1].tolist()},
            "material_params_mpa": ctx.material_params_mpa.tolist(),
            "liver_centroid_mm": (ctx.liver_centroid_mm / 1000).tolist(),
            "inertia_mm5": (ctx.inertia_mm5 / 1000**5).tolist(), "tool_thickness_mm": ctx.tool_thickness_mm / 1000,
            "probe_compliance_mm_per_n": (ctx.probe_compliance_mm_per_n / 1000).tolist()}


def test_a_camera_model_predicts_exactly_from_a_cloud_with_its_interval(served):
    path, model, a = served
    pred = Predictor.from_dir(path)
    assert pred.cloud_support == "exact"
    ctx, cloud, tip = _case(a, 0)
    force, info = pred.predict_cloud(cloud, ctx, tool_tip_mm=tip, return_info=True)
    # the cloud itself is like the training clouds; only the context (a liver of another size) may be outside
    assert info["mode"] == "exact" and info["warnings"] == pred.context_warnings(ctx)
    direct = model.predict({**{k: a[k][:1] if not isinstance(a[k], list) else a[k][:1] for k in
                               ("exertion_point_mm", "frame_normal", "frame_t1", "frame_t2", "roi_undeformed_mm",
                                "roi_centroid_undeformed_mm", "liver_centroid_mm", "inertia_mm5", "tool_thickness_mm",
                                "probe_compliance_mm_per_n", "material_params_mpa", "roi_triangles")},
                            "camera_cloud_mm": [cloud], "tool_tip_mm": tip[None]})[0]
    assert np.allclose(force, direct, atol=1e-9)
    iv = info["interval"]
    assert np.allclose(iv["force_n"], force) and all(h is not None and h > 0 for h in iv["half_width_local_n"])


def test_interval_coverage_on_held_out_livers(served):
    """The 90 % interval on cases of livers the model never saw, each observed by a new camera."""
    path, model, a = served
    pred = Predictor.from_dir(path)
    from liverforce.learn.frames import force_to_local

    hits = []
    for i in range(len(a["case_id"])):
        ctx, cloud, tip = _case(a, i, seed=100 + i)
        _, info = pred.predict_cloud(cloud, ctx, tool_tip_mm=tip, return_info=True)
        iv = info["interval"]
        true = force_to_local(a["force_n"][i][None], np.asarray(iv["frame"])[None])[0]
        hits.append(np.abs(true - np.asarray(iv["force_local_n"])) <= np.asarray(iv["half_width_local_n"]))
    cov = np.mean(hits, axis=0)
    # 40 cases: the binomial sd of a 90 % coverage is 4.7 points; two sd either side
    assert np.all(cov >= 0.80) and np.all(cov <= 1.0), cov


def test_out_of_distribution_inputs_are_refused_naming_the_reason(served):
    path, model, a = served
    pred = Predictor.from_dir(path)
    ctx, cloud, tip = _case(a, 1)
    with pytest.raises(PredictionInputError, match="tool tip"):
        pred.predict_cloud(cloud, ctx)  # no tool tip
    with pytest.raises(PredictionInputError, match=r"only \d of 5 points"):
        pred.predict_cloud(cloud[:5], ctx, tool_tip_mm=tip)  # too few points
    with pytest.raises(PredictionInputError, match="looks like metres read as mm; give --units m"):
        pred.predict_cloud(cloud / 1000.0, ctx, tool_tip_mm=tip)  # metres
    R = ctx.frame
    loc = (cloud - ctx.exertion_point_mm) @ R.T
    corner = cloud[(loc[:, 0] > 0.6 * model.representation.half_width_mm)
                   & (loc[:, 1] > 0.6 * model.representation.half_width_mm)]
    with pytest.raises(PredictionInputError, match="sees only"):
        pred.predict_cloud(corner, ctx, tool_tip_mm=tip)  # the camera sees a corner of the grid only
    top = model.meta["training_scale"]["camera"]["tip_displacement_max_mm"]
    far = ctx.exertion_point_mm - 0.9 * model.representation.half_width_mm * R[2]
    if 0.9 * model.representation.half_width_mm > 4 * top:
        with pytest.raises(PredictionInputError, match="tool tip displacement"):
            pred.predict_cloud(cloud, ctx, tool_tip_mm=far)
    with pytest.raises(PredictionInputError, match="beyond the model's grid"):
        pred.predict_cloud(cloud, ctx, tool_tip_mm=ctx.exertion_point_mm + 3 * model.representation.half_width_mm)
    # a mild departure is predicted, with a warning naming it
    push = ctx.exertion_point_mm - 1.3 * top * R[2]
    _, info = pred.predict_cloud(cloud, ctx, tool_tip_mm=push, return_info=True)
    assert any("tool tip displacement" in w for w in info["warnings"])


def test_surface_outside_the_training_range_is_refused(served):
    path, model, a = served
    pred = Predictor.from_dir(path)
    ctx, cloud, tip = _case(a, 2)
    import dataclasses

    huge = dataclasses.replace(ctx, inertia_mm5=ctx.inertia_mm5 * 1e6)  # a liver far larger than any in training
    with pytest.raises(PredictionInputError):
        pred.predict_cloud(cloud, huge, tool_tip_mm=tip)


def test_cli_predicts_a_camera_cloud_with_the_tool_tip(served, tmp_path, capsys):
    path, model, a = served
    ctx, cloud, tip = _case(a, 3)
    np.save(tmp_path / "cloud.npy", cloud / 1000.0)  # in metres, as a camera pipeline may give it
    doc = _context_in_metres(ctx, tmp_path)
    (tmp_path / "ctx.json").write_text(json.dumps(doc))
    parser = argparse.ArgumentParser(prog="liverforce")
    register_predict(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["predict", "-m", str(path), str(tmp_path / "cloud.npy"), "--context",
                              str(tmp_path / "ctx.json"), "--units", "m", "--tool-tip", *map(str, tip / 1000)])
    assert args.func(args) == 0
    out = json.loads(capsys.readouterr().out)
    want = Predictor.from_dir(path).predict_cloud(cloud, ctx, tool_tip_mm=tip)
    assert np.allclose(out["force_n"], want, atol=1e-6)
    assert out["mode"] == "exact" and "interval" in out and out["warnings"] == Predictor.from_dir(path).context_warnings(ctx)
    args = parser.parse_args(["predict", "-m", str(path), str(tmp_path / "cloud.npy"), "--context",
                              str(tmp_path / "ctx.json"), "--units", "m"])
    assert args.func(args) == 2
    assert "tool tip" in capsys.readouterr().err
    args = parser.parse_args(["predict", "-m", str(path), "--describe"])  # what it needs says the tool tip
    assert args.func(args) == 0
    cli = json.loads(capsys.readouterr().out)["command_line"]
    assert cli[0].startswith("CLOUD") and cli[1].startswith("--tool-tip X Y Z")
    # the patch's triangles are what the pre-operative height is read from: without them, a named refusal
    (tmp_path / "ctx_nt.json").write_text(json.dumps({k: v for k, v in doc.items() if k != "roi_triangles"}))
    args = parser.parse_args(["predict", "-m", str(path), str(tmp_path / "cloud.npy"), "--context",
                              str(tmp_path / "ctx_nt.json"), "--units", "m", "--tool-tip", *map(str, tip / 1000)])
    assert args.func(args) == 2
    assert "roi_triangles" in capsys.readouterr().err


def _cli_in_metres(served, tmp_path, capsys):
    """``(run, path, ctx, cloud, tip)``: case 3's context written in metres, and ``run(*argv)`` calling ``liverforce
    predict -m <model> *argv --context <it> --units m``, giving ``(exit code, captured output)``."""
    path, model, a = served
    ctx, cloud, tip = _case(a, 3)
    (tmp_path / "ctx.json").write_text(json.dumps(_context_in_metres(ctx, tmp_path)))
    parser = argparse.ArgumentParser(prog="liverforce")
    register_predict(parser.add_subparsers(dest="command", required=True))

    def run(*argv):
        args = parser.parse_args(["predict", "-m", str(path), *map(str, argv), "--context", str(tmp_path / "ctx.json"),
                                  "--units", "m"])
        return args.func(args), capsys.readouterr()
    return run, path, ctx, cloud, tip


def test_cli_reads_clouds_tips_and_the_unloaded_view_in_the_units_their_header_names(served, tmp_path, capsys):
    """Camera clouds, a sequence's --tool-tips and the --unloaded view as CSV headed with a unit: read when it is the
    declared one (--units m), refused naming the file and its header when it is not (the lab's files in mm): a
    sequence's frame as its row, every frame so as the command."""
    run, path, ctx, cloud, tip = _cli_in_metres(served, tmp_path, capsys)

    def csv(name, header, pts):
        np.savetxt(tmp_path / name, pts, delimiter=",", header=header, comments="")
        return tmp_path / name

    said = "its header 'x_mm,y_mm,z_mm' says the coordinates are in mm, but they are read in m (1000 mm each)"
    frames = tmp_path / "frames"
    frames.mkdir()
    for k in range(2):
        np.savetxt(frames / f"f{k}.csv", cloud[k::2] / 1000.0, delimiter=",", header="x_m,y_m,z_m", comments="")
    one = csv("cloud.csv", "x_m,y_m,z_m", cloud / 1000.0)
    rc, out = run(one, "--tool-tip", *(tip / 1000.0))
    assert rc == 0, out.err
    np.testing.assert_allclose(json.loads(out.out)["force_n"], Predictor.from_dir(path).predict_cloud(
        cloud, ctx, tool_tip_mm=tip), atol=1e-6)
    rc, out = run(one, "--tool-tip", *(tip / 1000.0), "--unloaded", csv("before.csv", "x_mm,y_mm,z_mm", cloud))
    assert rc == 2 and f"{tmp_path / 'before.csv'}: {said}" in out.err
    rc, out = run(frames, "--tool-tips", csv("tips.csv", "x_mm,y_mm,z_mm", np.stack([tip, tip])))
    assert rc == 2 and f"--tool-tips: {tmp_path / 'tips.csv'}: {said}" in out.err
    rc, out = run(frames, "--tool-tips", csv("tips.csv", "x_m,y_m,z_m", np.stack([tip, tip]) / 1000.0))
    assert rc == 0, out.err
    assert json.loads(out.out)["clouds"] == 2
    np.savetxt(frames / "f1.csv", cloud[1::2], delimiter=",", header="x_mm,y_mm,z_mm", comments="")
    rc, out = run(frames, "--tool-tips", tmp_path / "tips.csv")
    assert rc == 0, out.err
    rows = json.loads(out.out)["rows"]
    assert not rows[0]["refused"] and rows[1]["refused"].startswith(f"{frames / 'f1.csv'}: {said}")
    np.savetxt(frames / "f0.csv", cloud[::2], delimiter=",", header="x_mm,y_mm,z_mm", comments="")
    rc, out = run(frames, "--tool-tips", tmp_path / "tips.csv")
    assert rc == 2 and f"none of the 2 files of the sequence could be read as a point cloud; the first: " \
                       f"{frames / 'f0.csv'}: {said}" in out.err


def test_cli_reads_a_depth_cameras_pcd_frames_dropping_their_nan_pixels(served, tmp_path, capsys):
    """One cloud and a sequence folder of PCD frames (metres, NaN where a pixel had no depth): the forces of their
    finite points, and each output says how many points were dropped from which file."""
    from tests.serve.test_read_pcd import write_pcd, xyz

    run, path, ctx, cloud, tip = _cli_in_metres(served, tmp_path, capsys)

    def organised(points, holes):  # 50 pixels a row, the holes' rows of NaN first
        grid = np.vstack([np.full((holes, 3), np.nan), points / 1000.0])
        return xyz(grid[: len(grid) // 50 * 50]), len(grid) // 50

    pred = Predictor.from_dir(path)
    columns, rows = organised(cloud, 100)
    one = write_pcd(tmp_path / "cloud.pcd", columns, "binary_compressed", width=50, height=rows)
    kept = rows * 50 - 100
    rc, out = run(one, "--tool-tip", *(tip / 1000.0))
    assert rc == 0, out.err
    doc = json.loads(out.out)
    np.testing.assert_allclose(doc["force_n"], pred.predict_cloud(cloud[:kept], ctx, tool_tip_mm=tip), atol=1e-6)
    assert doc["warnings"][0] == (f"{one}: 100 of {rows * 50} points dropped, their coordinates NaN (PCL's mark of "
                                  f"a pixel without depth in an organised cloud, here 50 x {rows}); {kept} read")
    frames = tmp_path / "frames"
    frames.mkdir()
    halves = [cloud[k::2] for k in range(2)]
    write_pcd(frames / "f10.pcd", xyz(halves[1] / 1000.0), "binary")
    columns, rows = organised(halves[0], 50)
    write_pcd(frames / "f9.pcd", columns, "ascii", width=50, height=rows)
    kept = rows * 50 - 50
    write_pcd(frames / "f11.pcd", xyz(np.full((100, 3), np.nan)), "binary", width=50, height=2)  # nothing seen
    rc, out = run(frames, "--tool-tip", *(tip / 1000.0))
    assert rc == 0, out.err
    got = json.loads(out.out)["rows"]
    assert [r["cloud"] for r in got] == ["f9.pcd", "f10.pcd", "f11.pcd"]
    assert got[2]["refused"] and got[2]["fx_n"] is None  # that frame's row only: the others go on
    assert got[2]["warnings"].startswith(f"{frames / 'f11.pcd'}: every one of its 100 points is NaN")
    assert not got[0]["refused"] and not got[1]["refused"]
    got = got[:2]
    for r, c in zip(got, (halves[0][:kept], halves[1])):
        np.testing.assert_allclose([r["fx_n"], r["fy_n"], r["fz_n"]], pred.predict_cloud(c, ctx, tool_tip_mm=tip),
                                   atol=1e-6)
    assert got[0]["warnings"].startswith(f"{frames / 'f9.pcd'}: 50 of {rows * 50} points dropped")
    assert "dropped" not in got[1]["warnings"]


def test_the_mlflow_pyfunc_serves_the_camera_model_from_clouds(served, tmp_path):
    """Logged with an observed cloud as its input example; predicts from camera_cloud_mm + tool_tip_mm rows."""
    from liverforce.tracking import Tracker, load_pyfunc, predict_pyfunc

    path, model, a = served
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    tracker = Tracker(uri, "camera-serve")
    run_id = tracker.start_run("cloud", params={}, tags={})
    tracker.log_force_model(run_id, path, subset(a, [0]))  # simulated case: observed for the example
    tracker.end_run(run_id)
    pf = load_pyfunc(f"runs:/{run_id}/model", uri)
    inputs = set(pf.metadata.get_input_schema().input_names())
    assert {"camera_cloud_mm", "tool_tip_mm"} <= inputs and "roi_deformed_mm" not in inputs
    rows = [_case(a, i, seed=50 + i) for i in range(3)]
    cases = _context_columns(a, 3)
    cases["camera_cloud_mm"] = [r[1] for r in rows]
    cases["tool_tip_mm"] = np.stack([r[2] for r in rows])
    # the centroid as the context computes it (from the float32 ROI points; the synthetic row's is from float64)
    cases["roi_centroid_undeformed_mm"] = np.stack([r[0].roi_undeformed_mm.mean(axis=0) for r in rows])
    got = predict_pyfunc(pf, cases)
    want = [Predictor.from_dir(path).predict_cloud(c, ctx, tool_tip_mm=t) for ctx, c, t in rows]
    # the same float32 MLP over a batch of 3 rows and over single rows: equal to float32 rounding (the BLAS
    # kernel, and so the summation order, may depend on the batch size and on the CPU)
    np.testing.assert_allclose(got, np.stack(want), rtol=1e-6, atol=1e-9)
    for axis, says in (("frame_t1", "tool_tip_mm is .* mm from the exertion point along the surface, beyond the "
                                    "model's"),
                       ("frame_normal", "tool_tip_mm lies .* mm above the liver at the exertion point")):
        far = dict(cases, tool_tip_mm=cases["tool_tip_mm"] + 100.0 * np.asarray(cases[axis]))
        with pytest.raises(PredictionInputError, match=says):
            predict_pyfunc(pf, far)  # predict_cloud's refusal of a tip beyond the grid or above the liver
    # the warnings column: each row's, as predict_cloud gives them (a tip pushed past every training case's is
    # predicted with the cloud's own warning, which the column once dropped)
    top = model.meta["training_scale"]["camera"]["tip_displacement_max_mm"]
    deep = dict(cases, tool_tip_mm=cases["tool_tip_mm"].copy())
    deep["tool_tip_mm"][1] = rows[1][0].exertion_point_mm - 1.3 * top * rows[1][0].frame[2]
    from liverforce.tracking.model import arrays_to_frame

    out = pf.predict(arrays_to_frame(deep, [k for k in deep if k in inputs]), params={"observation_seed": -1})
    infos = [Predictor.from_dir(path).predict_cloud(c, ctx, tool_tip_mm=t, return_info=True)[1]
             for (ctx, c, _), t in zip(rows, deep["tool_tip_mm"])]
    assert list(out["warnings"]) == ["; ".join(info["warnings"]) for info in infos]
    assert "tool tip displacement" in out["warnings"][1] and "tool tip displacement" not in out["warnings"][0]
    # a lab's columns in metres and a registration's frame (params input_frame, units): the force of the same
    # inputs in RAS mm, given back in the inputs' frame; the interval's local columns unchanged
    assert {"input_frame", "units"} <= {p.name for p in pf.metadata.get_params_schema().params}
    M = rigid(False)
    lab = to_input_arrays(M, 1000.0, cases)
    got_lab = predict_pyfunc(pf, lab, input_frame=json.dumps(M.tolist()), units="m")
    np.testing.assert_allclose(got_lab, got @ M[:3, :3], rtol=1e-5, atol=1e-7)
    same = predict_pyfunc(pf, lab, input_frame=json.dumps({"matrix": M.tolist(), "units": "m"}))
    np.testing.assert_allclose(same, got_lab, atol=1e-12)
    record = {"conversion": {"units": "m", "scale_to_mm": 1000.0, "frame": "matrix", "frame_matrix": M.tolist()}}
    np.testing.assert_allclose(predict_pyfunc(pf, lab, input_frame=json.dumps(record)), got_lab, atol=1e-12)
    (tmp_path / "imp-lab.json").write_text(json.dumps(record))
    for frame, units, why in [("[[1, 0]]", "m", "4x4"), ("{not json", "m", "not valid JSON"),
                              (json.dumps(M.tolist()), "furlong", "units"), ("LPS", "mm", "only"),
                              (json.dumps(record), "mm", "contradict the units said apart"),
                              (str(tmp_path / "imp-lab.json"), "", "reads no file")]:
        with pytest.raises(PredictionInputError, match=why):  # LPS mm: the clouds land off the liver
            predict_pyfunc(pf, lab, input_frame=frame, units=units)
    bad = dict(lab, exertion_point_mm=np.asarray(lab["exertion_point_mm"])[:, :2])
    with pytest.raises(PredictionInputError, match="exertion_point_mm"):
        predict_pyfunc(pf, bad, input_frame=json.dumps(M.tolist()), units="m")


def test_predict_pyfunc_will_not_send_a_frame_to_a_model_that_would_drop_it():
    """A model logged before the pyfunc took input_frame and units: MLflow would drop them with a warning and read
    the inputs as RAS mm, so predict_pyfunc refuses to send them (and sends none when none is said)."""
    from types import SimpleNamespace

    from liverforce.tracking import predict_pyfunc

    seen = []

    class Old:
        metadata = SimpleNamespace(get_input_schema=lambda: None,
                                   get_params_schema=lambda: SimpleNamespace(params=[SimpleNamespace(
                                       name="observation_seed")]))

        def predict(self, df, params):
            seen.append(params)
            return {"fx_n": [], "fy_n": [], "fz_n": []}

    with pytest.raises(PredictionInputError, match="logged before it took input_frame and units"):
        predict_pyfunc(Old(), {}, input_frame="LPS", units="m")
    assert predict_pyfunc(Old(), {}).shape == (0, 3) and seen == [{"observation_seed": -1}]


def test_the_compiled_cloud_path_equals_the_reference(served):
    path, model, a = served
    pred = Predictor.from_dir(path)
    ctx, _, _ = _case(a, 4)
    fast = pred.compile_cloud(ctx)
    for seed in range(4):
        _, cloud, tip = _case(a, 4, n_points=500 + 1500 * seed, seed=seed)
        want, info = pred.predict_cloud(cloud, ctx, tool_tip_mm=tip, return_info=True)
        got, half, warnings = fast.predict(cloud, tip)
        np.testing.assert_allclose(got, want, atol=1e-6)
        np.testing.assert_allclose(half, info["interval"]["half_width_local_n"], rtol=1e-12)
        assert warnings == info["warnings"]
    with pytest.raises(PredictionInputError, match="only"):
        fast.predict(cloud[:4], tip)


@pytest.mark.parametrize("reflect", [False, True])
def test_the_compiled_cloud_path_takes_clouds_in_a_labs_frame_and_units(served, reflect):
    """Compiled with an input frame (a registration's rotation and shift, in metres; with a reflection too):
    clouds and tips in that frame give the force of the same clouds in RAS mm, turned into the inputs' frame, one
    by one and in a batch (a list or a padded float32 array); a cloud off the grid is still refused with its
    reason."""
    from liverforce.serve.input_frame import InputFrame

    path, model, a = served
    pred = Predictor.from_dir(path)
    ctx, _, _ = _case(a, 4)
    M = rigid(reflect)
    fast, lab = pred.compile_cloud(ctx), pred.compile_cloud(ctx, frame=InputFrame.resolve(M.tolist(), "m"))
    clouds, tips = zip(*[_case(a, 4, n_points=800 + 700 * s, seed=s)[1:] for s in range(3)])
    cl_in = [to_inputs(M, 1000.0, c) for c in clouds]
    tip_in = to_inputs(M, 1000.0, np.stack(tips))
    for c, t, ci, ti in zip(clouds, tips, cl_in, tip_in):
        want, want_half, want_warn = fast.predict(c, t)
        got, half, warnings = lab.predict(ci, ti)
        np.testing.assert_allclose(got, want @ M[:3, :3], atol=1e-6)
        np.testing.assert_allclose(half, want_half, rtol=1e-9)
        assert warnings == want_warn
    want = fast.predict_batch(list(clouds), np.stack(tips))
    full = lab.predict_batch(cl_in + [cl_in[0][:3]], np.vstack([tip_in, tip_in[:1]]))
    np.testing.assert_allclose(full.force[:3], want.force @ M[:3, :3], atol=1e-6)
    np.testing.assert_allclose(full.half_width[:3], want.half_width, rtol=1e-9)
    assert full.refused[:3] == [None] * 3 and "only" in full.refused[3] and np.isnan(full.force[3]).all()
    padded = np.zeros((3, 2200, 3))  # one (B, N, 3) array, each cloud's rows [:counts[b]]
    for b, c in enumerate(cl_in):
        padded[b, :len(c)] = c
    got = lab.predict_batch(padded, tip_in, counts=np.array([len(c) for c in cl_in]))
    np.testing.assert_allclose(got.force, full.force[:3], atol=1e-9)
    # float32 (metres in float32: ~0.03 um) and one tip for every cloud, the frame and units given apart
    lab_m = pred.compile_cloud(ctx, frame=M.tolist(), units="m")
    one = lab_m.predict_batch(padded.astype(np.float32), tip_in[0], counts=np.array([len(c) for c in cl_in]))
    ref = lab.predict_batch([c.astype(np.float32).astype(np.float64) for c in cl_in], tip_in[0])
    np.testing.assert_allclose(one.force, ref.force, atol=1e-9)
    assert np.isfinite(one.force).all() and len(lab.predict_batch([], np.zeros((0, 3))).force) == 0
    # a registration printed to 6 decimals (orthogonal to ~1e-6) with a scanner's shift: the features of the
    # clouds read in place equal those of the clouds converted first (the fold inverts A, it does not transpose it)
    M6 = np.round(M, 6)
    fr6 = InputFrame.resolve(M6.tolist(), "m")
    lab6 = pred.compile_cloud(ctx, frame=fr6)
    for c, t in zip(clouds, tips):
        c6 = np.linalg.solve(M6[:3, :3], (c - M6[:3, 3]).T).T / 1000.0
        t6 = np.linalg.solve(M6[:3, :3], t - M6[:3, 3]) / 1000.0
        np.testing.assert_allclose(lab6.features(c6, t6), fast.features(fr6.points(c6), fr6.points(t6)), atol=1e-9)
    # refusals name the inputs as given: a NaN tip as it came, alone and in a batch
    with pytest.raises(PredictionInputError, match="tool_tip_mm: need 3 finite") as exc:
        lab.predict(cl_in[0], [0.1, np.nan, 0.2])
    assert "0.1" in str(exc.value)
    why = lab.predict_batch([cl_in[0]], [[0.1, np.nan, 0.2]]).refused[0]
    assert why.startswith("tool_tip_mm: need 3 finite") and "0.1, nan, 0.2" in why
    padded[1, 5] = np.nan  # a NaN point in one padded cloud: that cloud refused, the others predicted
    got = lab.predict_batch(padded, tip_in, counts=np.array([len(c) for c in cl_in]))
    assert "NaN" in got.refused[1] and got.refused[0] is None and np.isnan(got.force[1]).all()
    np.testing.assert_allclose(got.force[[0, 2]], full.force[[0, 2]], atol=1e-9)
    with pytest.raises(PredictionInputError, match="only"):
        lab.predict(cl_in[0] * 1000.0, tip_in[0])  # given in mm, said to be in m: off the grid, refused


def test_a_context_outside_the_training_range_comes_with_its_warning_on_every_path(served, mid_range):
    """Tissue thinner and a liver softer than every training case (not so far as to be refused): the reference
    and the compiled cloud paths predict, each with the same warnings naming both inputs. In the middle of
    every range: no warning."""
    from dataclasses import replace

    path, model, a = served
    pred = Predictor.from_dir(path)
    ctx, cloud, tip = _case(a, 5)
    rec = model.meta["training_scale"]
    ctx = mid_range(ctx, rec)
    _, info = pred.predict_cloud(cloud, ctx, tool_tip_mm=tip, return_info=True)
    assert info["warnings"] == [] and pred.compile_cloud(ctx).predict(cloud, tip)[2] == []
    C = ctx.probe_compliance_mm_per_n.reshape(3, 3)
    soft = C * (1.3 * rec["probe_compliance_mm_per_n"][1] / np.trace(C))
    odd = replace(ctx, tool_thickness_mm=0.7 * rec["tool_thickness_mm"][0], probe_compliance_mm_per_n=soft)
    force, info = pred.predict_cloud(cloud, odd, tool_tip_mm=tip, return_info=True)
    assert np.isfinite(force).all()
    named = [w for w in info["warnings"] if "thinner than in every training case" in w or "softer than" in w]
    assert len(named) == 2
    got, _, warnings = pred.compile_cloud(odd).predict(cloud, tip)
    np.testing.assert_allclose(got, force, atol=1e-6)
    assert warnings == info["warnings"]
    batch = pred.compile_cloud(odd).predict_batch([cloud, cloud[:3]], np.stack([tip, tip]))
    assert batch.warnings[0] == info["warnings"] and batch.refused[1] is not None and batch.warnings[1] == []


def test_cli_takes_a_labs_cloud_in_lps_metres_through_the_livers_import_record(served, tmp_path, capsys):
    """A lab's liver imported from LPS metres: its surface, camera cloud, exertion point and tool tip come in
    that frame and unit. With the geometry stage's record (``--frame .../imp-<name>.json``) they give the force
    of the same inputs in RAS mm, returned in LPS (x and y negated), the interval's axes too."""
    path, model, a = served
    ctx, cloud, tip = _case(a, 4)
    V, T = a["surface_meshes"][a["geometry_id"][4]]
    lps = np.array([-1.0, -1.0, 1.0])
    rec = {"frame": "LPS", "conversion": {"units": "m", "scale_to_mm": 1000.0, "frame": "LPS",
                                          "frame_matrix": np.diag([-1.0, -1.0, 1.0, 1.0]).tolist()}}
    (tmp_path / "imp-lab.json").write_text(json.dumps(rec))
    probe = {"probe_compliance_mm_per_n": ctx.probe_compliance_mm_per_n.tolist(),
             "material_params_mpa": ctx.material_params_mpa.tolist()}
    (tmp_path / "ras.json").write_text(json.dumps({**probe, "surface": "ras.npz"}))
    np.savez(tmp_path / "ras.npz", points=V, facets=T)
    np.save(tmp_path / "ras_cloud.npy", cloud)
    (tmp_path / "lps.json").write_text(json.dumps({**probe, "surface": "lps.npz", "probe_compliance_mm_per_n": (
        ctx.probe_compliance_mm_per_n / 1000).tolist()}))  # local frame: only the units change (m/N)
    np.savez(tmp_path / "lps.npz", points=V * lps / 1000, facets=T)
    np.save(tmp_path / "lps_cloud.npy", cloud * lps / 1000)
    parser = argparse.ArgumentParser(prog="liverforce")
    register_predict(parser.add_subparsers(dest="command", required=True))

    def run(*argv):
        args = parser.parse_args(["predict", "-m", str(path), *map(str, argv)])
        rc = args.func(args)
        out, err = capsys.readouterr()
        assert rc == 0, err
        return json.loads(out)

    ras = run(tmp_path / "ras_cloud.npy", "--context", tmp_path / "ras.json", "--exertion-point",
              *ctx.exertion_point_mm, "--tool-tip", *tip)
    got = run(tmp_path / "lps_cloud.npy", "--context", tmp_path / "lps.json", "--exertion-point",
              *(ctx.exertion_point_mm * lps / 1000), "--tool-tip", *(tip * lps / 1000),
              "--frame", tmp_path / "imp-lab.json", "--out", tmp_path / "f.csv")
    want = Predictor.from_dir(path).predict_cloud(
        cloud, Preop.from_surface(V, T, ctx.exertion_point_mm, ctx.material_params_mpa).with_compliance(
            ctx.probe_compliance_mm_per_n), tool_tip_mm=tip)
    np.testing.assert_allclose(ras["force_n"], want, atol=1e-9)
    np.testing.assert_allclose(got["force_n_model"], want, atol=1e-6)
    np.testing.assert_allclose(got["force_n"], want * lps, atol=1e-6)
    np.testing.assert_allclose(got["interval"]["frame"], np.asarray(ras["interval"]["frame"]) * lps, atol=1e-9)
    np.testing.assert_allclose(got["interval"]["force_n"], want * lps, atol=1e-6)
    np.testing.assert_allclose(np.loadtxt(tmp_path / "f.csv", delimiter=",", skiprows=1), want * lps, atol=1e-6)
    np.testing.assert_allclose(got["interval"]["half_width_local_n"], ras["interval"]["half_width_local_n"], rtol=1e-6)
    assert got["mode"] == "exact" and got["points_used"] == ras["points_used"]
    assert "frame LPS" in got["input_frame"] and "imp-lab.json" in got["input_frame"]


def test_a_cloud_with_the_instrument_in_it_is_refused_by_a_model_trained_without(served):
    """The tool's own points in the cloud (a reconstruction that did not mask it out) would raise the cells round
    the tool by millimetres: a model trained on clouds without them refuses, naming the remedy; the same cloud
    with the instrument masked out is predicted."""
    from liverforce.learn.observation import ObservationConfig

    path, model, a = served
    pred = Predictor.from_dir(path)
    V, T = a["surface_meshes"][a["geometry_id"][2]]
    u = np.asarray(a["surface_displacement_mm"][2], dtype=np.float64)
    p = a["exertion_point_mm"][2]
    tip = p + u[int(np.argmin(np.linalg.norm(V - p, axis=1)))]
    ctx = Preop.from_arrays({k: v for k, v in a.items() if k != "roi_deformed_mm"}, 2)
    cfg = ObservationConfig(n_points=(3000, 3000), noise_sd_mm=0.3, roi_radius_mm=40.0, instrument_in_cloud=True)
    cloud, rec = observe(V + u, T, tip, a["frame_normal"][2], cfg, seed=4)
    assert rec.n_instrument_points > 50
    with pytest.raises(PredictionInputError, match="instrument is in the cloud.*Mask the instrument out"):
        pred.predict_cloud(cloud, ctx, tool_tip_mm=tip)
    force, info = pred.predict_cloud(cloud[: len(cloud) - rec.n_instrument_points], ctx, tool_tip_mm=tip,
                                     return_info=True)
    assert np.isfinite(force).all() and info["instrument_points"] < 8
    # arrays of clouds (the pyfunc's path): the same check, the case named
    rows = {**ctx.to_arrays(ctx.roi_undeformed_mm), "case_id": np.array(["c2"]), "tool_tip_mm": tip[None]}
    with pytest.raises(PredictionInputError, match="case c2: .*instrument is in the cloud"):
        pred.predict_arrays({**rows, "camera_cloud_mm": [cloud]})
    masked = cloud[: len(cloud) - rec.n_instrument_points]
    np.testing.assert_allclose(pred.predict_arrays({**rows, "camera_cloud_mm": [masked]})[0], force, atol=1e-9)


def test_the_compiled_path_refuses_the_instrument_in_the_cloud_as_the_reference_does(served):
    from liverforce.learn.observation import ObservationConfig

    path, model, a = served
    pred = Predictor.from_dir(path)
    ctx, _, _ = _case(a, 3)
    fast = pred.compile_cloud(ctx)
    V, T = a["surface_meshes"][a["geometry_id"][3]]
    u = np.asarray(a["surface_displacement_mm"][3], dtype=np.float64)
    p = a["exertion_point_mm"][3]
    tip = p + u[int(np.argmin(np.linalg.norm(V - p, axis=1)))]
    cfg = ObservationConfig(n_points=(3000, 3000), noise_sd_mm=0.3, roi_radius_mm=40.0, instrument_in_cloud=True)
    cloud, rec = observe(V + u, T, tip, a["frame_normal"][3], cfg, seed=9)
    clean = cloud[: len(cloud) - rec.n_instrument_points]
    with pytest.raises(PredictionInputError) as ref:
        pred.predict_cloud(cloud, ctx, tool_tip_mm=tip)
    with pytest.raises(PredictionInputError) as got:
        fast.predict(cloud, tip)
    assert str(got.value) == str(ref.value) and "instrument is in the cloud" in str(got.value)
    batch = fast.predict_batch([clean, cloud, clean], np.stack([tip] * 3))
    assert batch.refused[1] == str(ref.value) and batch.refused[0] is None and batch.refused[2] is None
    np.testing.assert_allclose(batch.force[0], pred.predict_cloud(clean, ctx, tool_tip_mm=tip), atol=1e-6)


def test_clean_clouds_are_not_taken_for_the_instrument(served):
    """No clean cloud of the held-out livers is refused as holding the instrument, with the kinematic tip's
    noise, 1 mm point noise, or the whole cloud 8 mm off along the normal (a registration error: the check
    measures the shaft against the surface round it, not against the pre-operative surface)."""
    from liverforce.learn.observation import ObservationConfig

    path, model, a = served
    pred = Predictor.from_dir(path)
    rng = np.random.default_rng(0)
    checked = 0
    for i in range(0, len(a["case_id"]), 2):
        V, T = a["surface_meshes"][a["geometry_id"][i]]
        u = np.asarray(a["surface_displacement_mm"][i], dtype=np.float64)
        p = a["exertion_point_mm"][i]
        tip = p + u[int(np.argmin(np.linalg.norm(V - p, axis=1)))]
        ctx = Preop.from_arrays({k: v for k, v in a.items() if k != "roi_deformed_mm"}, i)
        cfg = ObservationConfig(n_points=(8000, 8000), noise_sd_mm=1.0, roi_radius_mm=40.0)
        cloud, _ = observe(V + u, T, tip, a["frame_normal"][i], cfg, seed=i)
        kin = tip + rng.normal(0.0, 0.5, 3)
        fast = pred.compile_cloud(ctx)
        for shift in (0.0, 8.0):
            moved, k_moved = cloud + shift * ctx.rotation[2], kin + shift * ctx.rotation[2]
            batch = fast.predict_batch([moved], k_moved[None])  # the compiled path's check: the same decision
            try:
                _, info = pred.predict_cloud(moved, ctx, tool_tip_mm=k_moved, return_info=True)
                checked += "instrument_points" in info  # the check ran and let it through
                assert batch.refused[0] is None
            except PredictionInputError as exc:
                assert "instrument" not in str(exc), (i, shift, str(exc))
                assert batch.refused[0] == str(exc)
    assert checked >= 20


def test_cli_predicts_a_recorded_sequence_of_clouds(served, tmp_path, capsys, trained):
    """``liverforce predict -m M frames/ --tool-tips tips.csv``: a folder of clouds in LPS metres (natural name
    order), the tip of each from a file; one row per cloud equal to the reference path's force and interval, a
    cloud of 5 points refused with the reference's reason while the rest are predicted; the same from one
    (T, N, 3) .npy, in 2 threads and on the reference path; the rows written as .csv, .parquet and .json."""
    import pandas as pd

    path, model, a = served
    pred = Predictor.from_dir(path)
    lps = np.array([-1.0, -1.0, 1.0])
    case, _, _ = _case(a, 3)
    V, T = a["surface_meshes"][a["geometry_id"][3]]
    ctx = Preop.from_surface(V, T, case.exertion_point_mm, case.material_params_mpa).with_compliance(
        case.probe_compliance_mm_per_n)  # what the context file below gives, in RAS mm
    seq = [_case(a, 3, n_points=n, seed=s)[1:] for s, n in enumerate([3000, 1500, 2500, 800])]
    clouds = [c for c, _ in seq]
    tips = np.stack([t for _, t in seq]) + np.random.default_rng(2).normal(0.0, 0.1, (len(seq), 3))
    clouds.append(clouds[0][:5])  # too few points: refused, the rest predicted
    tips = np.vstack([tips, tips[:1]])
    frames = tmp_path / "frames"
    frames.mkdir()
    for k, c in enumerate(clouds):  # f2 before f10: natural order
        np.save(frames / f"f{[1, 2, 10, 11, 20][k]}.npy", c * lps / 1000.0)
    (frames / "notes.md").write_text("not a cloud")
    np.savetxt(tmp_path / "tips.csv", tips * lps / 1000.0, delimiter=",", header="x,y,z")
    np.savez(tmp_path / "lps.npz", points=V * lps / 1000, facets=T)
    (tmp_path / "ctx.json").write_text(json.dumps({  # the local frame's compliance: only its units change (m/N)
        "surface": "lps.npz", "probe_compliance_mm_per_n": (case.probe_compliance_mm_per_n / 1000).tolist(),
        "material_params_mpa": case.material_params_mpa.tolist()}))
    parser = argparse.ArgumentParser(prog="liverforce")
    register_predict(parser.add_subparsers(dest="command", required=True))

    errs = []

    def run(*argv, rc=0):
        args = parser.parse_args(["predict", "-m", str(path), *map(str, argv)])
        got = args.func(args)
        out, err = capsys.readouterr()
        errs.append(err)
        assert got == rc, err
        return json.loads(out) if rc == 0 else err

    base = ("--context", tmp_path / "ctx.json", "--units", "m", "--frame", "LPS", "--exertion-point",
            *(ctx.exertion_point_mm * lps / 1000))
    out = run(frames, "--tool-tips", tmp_path / "tips.csv", *base)
    assert [r["cloud"] for r in out["rows"]] == ["f1.npy", "f2.npy", "f10.npy", "f11.npy", "f20.npy"]
    assert out["clouds"] == 5 and out["predicted"] == 4 and out["refused"] == 1 and out["path"] == "compiled"
    # the refused cloud said on stderr as --shards says it (exit 0: the others were predicted)
    assert "1 of 5 rows refused" in errs[-1] and "the other rows were predicted" in errs[-1]
    assert "in its row's 'refused'" in errs[-1] and out["rows"][4]["refused"][:40] in errs[-1]
    # every cloud refused by the checks: the rows still printed, and exit 2
    few = tmp_path / "few"
    few.mkdir()
    np.save(few / "only.npy", clouds[4] * lps / 1000.0)
    every = run(few, "--tool-tip", *(tips[4] * lps / 1000), *base, rc=2)
    assert "error: 1 of 1 rows refused" in every and "every row" in every
    assert "frame LPS" in out["input_frame"]
    for k, (c, t) in enumerate(zip(clouds[:4], tips)):
        want, info = pred.predict_cloud(c, ctx, tool_tip_mm=t, return_info=True)
        row = out["rows"][k]
        np.testing.assert_allclose([row["fx_n"], row["fy_n"], row["fz_n"]], want * lps, atol=1e-6)
        np.testing.assert_allclose([row[f"half_width_{j}_n"] for j in ("t1", "t2", "n")],
                                   info["interval"]["half_width_local_n"], rtol=1e-6)
        assert row["refused"] == "" and row["warnings"] == "; ".join(info["warnings"])
    from liverforce.serve.input_frame import InputFrame

    with pytest.raises(PredictionInputError) as exc:  # the reasons name the units and frame declared
        pred.predict_cloud(clouds[4], ctx, tool_tip_mm=tips[4], input_frame=InputFrame.resolve("LPS", "m"))
    last = out["rows"][4]
    assert last["refused"] == str(exc.value) and last["fx_n"] is None and last["half_width_n_n"] is None
    assert "declared in m, LPS" in last["refused"]
    # one (T, N, 3) stack, 2 threads, the reference path: the same rows
    np.save(tmp_path / "stack.npy", np.stack([c[:800] for c in clouds[:4]]) * lps / 1000.0)
    stack = run(tmp_path / "stack.npy", "--tool-tips", tmp_path / "tips4.npy", *base, rc=2)
    assert "--tool-tips" in stack and "no such file of tool tips" in stack
    np.save(tmp_path / "tips4.npy", tips[:4] * lps / 1000.0)
    stack = run(tmp_path / "stack.npy", "--tool-tips", tmp_path / "tips4.npy", *base, "--threads", "2")
    ref = run(tmp_path / "stack.npy", "--tool-tips", tmp_path / "tips4.npy", *base, "--reference")
    assert [r["cloud"] for r in stack["rows"]] == [f"stack.npy[{k}]" for k in range(4)]
    assert stack["threads"] == 2 and ref["path"] == "reference"
    for r, q, c, t in zip(stack["rows"], ref["rows"], clouds, tips):
        want = pred.predict_cloud(c[:800], ctx, tool_tip_mm=t)
        np.testing.assert_allclose([r["fx_n"], r["fy_n"], r["fz_n"]], want * lps, atol=1e-6)
        np.testing.assert_allclose([q["fx_n"], q["fy_n"], q["fz_n"]], want * lps, atol=1e-9)
        assert r["warnings"] == q["warnings"]
    # a stack with one tip for every cloud (the tool held still) is a sequence too
    still = run(tmp_path / "stack.npy", "--tool-tip", *(tips[0] * lps / 1000), *base)
    assert still["clouds"] == 4 and [r["cloud"] for r in still["rows"]] == [r["cloud"] for r in stack["rows"]]
    # the rows written: .csv, .parquet, .json; the tips and the rows kept in the clouds' folder are not clouds
    files = [run(frames, "--tool-tips", tmp_path / "tips.csv", *base, "--out", tmp_path / f"rows.{e}")["out"]
             for e in ("csv", "parquet", "json")]
    (frames / "tips.csv").write_text((tmp_path / "tips.csv").read_text())
    for _ in range(2):  # run again: the rows it wrote are skipped too
        again = run(frames, "--tool-tips", frames / "tips.csv", *base, "--out", frames / "rows.csv")
        assert again["clouds"] == 5 and (frames / "rows.csv").read_text() == (tmp_path / "rows.csv").read_text()
    err = run(frames, "--tool-tips", frames / "tips.csv", *base, rc=2)  # another file there: named, and what to do
    assert "5 tips for 6 clouds" in err and "(rows.csv)" in err and "move it out of the clouds' folder" in err
    (frames / "rows.csv").unlink()
    (frames / "tips.csv").unlink()
    for f in files[:2]:
        df = pd.read_csv(f) if f.endswith(".csv") else pd.read_parquet(f)
        assert list(df["cloud"]) == [r["cloud"] for r in out["rows"]]
        np.testing.assert_allclose(df[["fx_n", "fy_n", "fz_n"]].to_numpy()[:4],
                                   [[r["fx_n"], r["fy_n"], r["fz_n"]] for r in out["rows"][:4]], atol=1e-8)
        assert df["refused"].fillna("").tolist()[4] == last["refused"]
    assert json.loads((tmp_path / "rows.json").read_text())["rows"] == out["rows"]
    # refused inputs, by name
    np.savetxt(tmp_path / "tips2.csv", tips[:2], delimiter=",")
    assert "2 tips for 5 clouds" in run(frames, "--tool-tips", tmp_path / "tips2.csv", *base, rc=2)
    assert "--tool-tips FILE" in run(frames, *base, rc=2)
    assert "not both" in run(frames, "--tool-tips", tmp_path / "tips.csv", "--tool-tip", 0, 0, 0, *base, rc=2)
    assert "--mode cloud" in run(frames, "--tool-tips", tmp_path / "tips.csv", "--mode", "nodes", *base, rc=2)
    assert "--threads" in run(frames, "--tool-tips", tmp_path / "tips.csv", "--threads", 0, *base, rc=2)
    assert "one cloud is predicted on one thread" in run(frames / "f1.npy", "--tool-tip", 0, 0, 0, "--threads", 2,
                                                          *base, rc=2)
    np.save(tmp_path / "none.npy", np.zeros((0, 10, 3)))
    assert "T >= 1" in run(tmp_path / "none.npy", "--tool-tip", 0, 0, 0, *base, rc=2)
    assert ".csv, .parquet or .json" in run(frames, "--tool-tips", tmp_path / "tips.csv", *base, "--out",
                                            tmp_path / "rows.txt", rc=2)
    empty = tmp_path / "empty"
    empty.mkdir()
    assert "no point-cloud files" in run(empty, "--tool-tips", tmp_path / "tips.csv", *base, rc=2)
    node = parser.parse_args(["predict", "-m", trained("disp"), str(frames), "--tool-tips", str(tmp_path / "tips.csv"),
                              "--exertion-point", "0", "0", "0", "--material", "0.002", "0.01"])
    assert node.func(node) == 2 and "camera-cloud model" in capsys.readouterr().err


def test_cli_predicts_a_sequence_around_its_damaged_frames(served, tmp_path, capsys):
    """A frame that cannot be read (a PCD cut short, a CSV with a broken line; among files named, a PLY cut short)
    is its own refused row in its place, naming the file in ``read_cloud``'s words, its tip kept: the other rows are
    the folder's without it, on the compiled and the reference path, and the rows written keep it (NaN; null in
    JSON). Every frame unreadable is refused; a tips count that does not match names the files not read."""
    import pandas as pd

    from liverforce.serve.files import read_cloud
    from liverforce.serve.input_frame import InputFrame
    from tests.serve.test_predict_cli import write_ply
    from tests.serve.test_read_pcd import write_pcd, xyz

    run, path, ctx, cloud, tip = _cli_in_metres(served, tmp_path, capsys)
    seq = [_case(served[2], 3, n_points=n, seed=s)[1:] for s, n in enumerate([900, 700, 800])]
    good, full = tmp_path / "good", tmp_path / "full"
    good.mkdir()
    full.mkdir()
    for k, (c, _) in zip((0, 2, 4), seq):
        for folder in (good, full):
            np.save(folder / f"f{k}.npy", c / 1000.0)
    pcd = write_pcd(full / "f1.pcd", xyz(cloud[:500] / 1000.0), "binary")
    pcd.write_bytes(pcd.read_bytes()[:-100])  # the camera's driver cut it short
    np.savetxt(full / "f3.csv", cloud[:50] / 1000.0, delimiter=",")
    lines = (full / "f3.csv").read_text().splitlines()
    (full / "f3.csv").write_text("\n".join(lines[:20] + [lines[20][:12]] + lines[21:]) + "\n")  # a line broken
    tips = np.stack([t for _, t in seq]) / 1000.0
    np.savetxt(tmp_path / "tips3.csv", tips, delimiter=",")
    np.savetxt(tmp_path / "tips5.csv", np.vstack([tips[0], tip / 1000.0, tips[1], tip / 1000.0, tips[2]]),
               delimiter=",")
    metres = InputFrame.resolve(None, "m")
    said = {}
    for name in ("f1.pcd", "f3.csv"):  # what one cloud's predict would say of each
        with pytest.raises(PredictionInputError) as exc:
            read_cloud(full / name, frame=metres)
        said[name] = str(exc.value)
    assert "truncated" in said["f1.pcd"] and "line 21" in said["f3.csv"]

    def rows(rc, out, damaged=()):
        assert rc == 0, out.err
        doc = json.loads(out.out)
        assert doc["unreadable"] == len(damaged) and doc["refused"] == len(damaged)
        assert doc["clouds"] == doc["predicted"] + len(damaged) and doc["predicted"] == 3
        return doc["rows"]

    paths = {}
    for flags in ((), ("--reference",)):
        want = rows(*run(good, "--tool-tips", tmp_path / "tips3.csv", *flags))
        assert [r["cloud"] for r in want] == ["f0.npy", "f2.npy", "f4.npy"] and not any(r["refused"] for r in want)
        rc, out = run(full, "--tool-tips", tmp_path / "tips5.csv", *flags)
        got = rows(rc, out, damaged=(1, 3))
        assert [r["cloud"] for r in got] == ["f0.npy", "f1.pcd", "f2.npy", "f3.csv", "f4.npy"]
        assert [got[k] for k in (0, 2, 4)] == want  # the same rows as the folder without the damaged frames
        for k, name in ((1, "f1.pcd"), (3, "f3.csv")):
            assert got[k]["refused"].startswith(said[name]) and str(full / name) in got[k]["refused"]
            assert "remove it and its row of tool tips" in got[k]["refused"]
            assert all(got[k][c] is None for c in ("fx_n", "fy_n", "fz_n", "magnitude_n", "half_width_t1_n",
                                                  "half_width_t2_n", "half_width_n_n"))
        assert "2 of 5 files could not be read as clouds" in out.err and said["f1.pcd"] in out.err
        paths[flags] = want, got
    want, got = paths[()]  # the compiled path's
    # the rows written: the damaged ones in their places, NaN (null in JSON) with their reasons
    for ext in ("csv", "parquet", "json"):
        rc, out = run(full, "--tool-tips", tmp_path / "tips5.csv", "--out", tmp_path / f"rows.{ext}")
        assert rc == 0, out.err
        assert f"in the 'refused' column of {tmp_path / f'rows.{ext}'}" in out.err
        if ext == "json":
            assert json.loads((tmp_path / "rows.json").read_text())["rows"] == got
            continue
        df = pd.read_csv(tmp_path / "rows.csv") if ext == "csv" else pd.read_parquet(tmp_path / "rows.parquet")
        assert list(df["cloud"]) == [r["cloud"] for r in got]
        assert df["refused"].fillna("").tolist() == [r["refused"] for r in got]
        assert df[["fx_n", "fy_n", "fz_n"]].isna().all(axis=1).tolist() == [False, True, False, True, False]
    # files named one by one: a PLY cut short among them
    write_ply(tmp_path / "cut.ply", cloud[:300] / 1000.0, binary=True)
    (tmp_path / "cut.ply").write_bytes((tmp_path / "cut.ply").read_bytes()[:-50])
    with pytest.raises(PredictionInputError) as exc:
        read_cloud(tmp_path / "cut.ply", frame=metres)
    np.savetxt(tmp_path / "tips4.csv", np.vstack([tips[0], tip / 1000.0, tips[1:]]), delimiter=",")
    named = rows(*run(good / "f0.npy", tmp_path / "cut.ply", good / "f2.npy", good / "f4.npy", "--tool-tips",
                      tmp_path / "tips4.csv"), damaged=(1,))
    assert [named[k] for k in (0, 2, 3)] == want and named[1]["refused"].startswith(str(exc.value))
    # every frame unreadable: refused, the first file's problem said with the count
    bad = tmp_path / "bad"
    bad.mkdir()
    for name in ("f1.pcd", "f3.csv"):
        (bad / name).write_bytes((full / name).read_bytes())
    rc, out = run(bad, "--tool-tips", tmp_path / "tips3.csv")
    assert rc == 2 and "none of the 2 files of the sequence could be read" in out.err
    assert said["f1.pcd"].replace(str(full), str(bad)) in out.err and "keep only the clouds" in out.err
    # a stray file in the folder counts as a frame: a tips count that does not match names it, and what to do
    (full / "notes.txt").write_text("frames 0-4, the tool pressed twice\n")
    rc, out = run(full, "--tool-tips", tmp_path / "tips5.csv")
    assert rc == 2 and "5 tips for 6 clouds" in out.err
    assert "3 of the 6 files could not be read as clouds (f1.pcd, f3.csv, notes.txt)" in out.err
    assert "if one is not a frame of the recording, move it out of the clouds' folder" in out.err


def test_a_sequences_stderr_counts_the_clouds_the_checks_refused_beside_the_unreadable(served, tmp_path, capsys):
    """Beside a damaged frame (first) and an empty one (last), a frame the model's checks refuse (too few points) is
    not predicted: stderr counts the other clouds as they went (it said 'the other clouds were predicted'), on
    either path, and all but the unreadable predicted says so in its words; the stdout JSON is strict."""
    run, path, ctx, cloud, tip = _cli_in_metres(served, tmp_path, capsys)
    frames = tmp_path / "frames"
    frames.mkdir()
    np.save(frames / "f0.npy", cloud / 1000.0)
    (frames / "f0.npy").write_bytes((frames / "f0.npy").read_bytes()[:-200])  # cut short
    np.save(frames / "f1.npy", cloud / 1000.0)
    np.save(frames / "f2.npy", cloud[:5] / 1000.0)  # five points: refused by the checks
    np.save(frames / "f3.npy", cloud[::2] / 1000.0)
    (frames / "f4.npy").write_bytes(b"")
    np.savetxt(tmp_path / "tips.csv", np.tile(tip / 1000.0, (5, 1)), delimiter=",")

    def strict(text):
        return json.loads(text, parse_constant=lambda token: pytest.fail(f"not strict JSON: {token}"))

    for flags in ((), ("--reference",), ("--threads", "2")):
        rc, out = run(frames, "--tool-tips", tmp_path / "tips.csv", *flags)
        assert rc == 0, out.err
        doc = strict(out.out)
        assert (doc["clouds"], doc["predicted"], doc["refused"], doc["unreadable"]) == (5, 2, 3, 2)
        assert [bool(r["refused"]) for r in doc["rows"]] == [True, False, True, False, True]
        assert "of 5 points" in doc["rows"][2]["refused"]
        assert out.err.startswith("liverforce predict: 2 of 5 files could not be read as clouds, their rows refused "
                                  "with NaN forces (of the other 3, 2 predicted and 1 refused by the model's checks; "
                                  "each reason in its row's 'refused'). The first: " + str(frames / "f0.npy"))
    (frames / "f2.npy").unlink()
    np.savetxt(tmp_path / "tips.csv", np.tile(tip / 1000.0, (4, 1)), delimiter=",")
    rc, out = run(frames, "--tool-tips", tmp_path / "tips.csv", "--out", tmp_path / "rows.json")
    assert rc == 0 and strict(out.out)["predicted"] == 2 and strict((tmp_path / "rows.json").read_text())["rows"]
    assert "2 of 4 files could not be read as clouds, their rows refused with NaN forces (the other 2 predicted; " \
           f"each reason in the 'refused' column of {tmp_path / 'rows.json'})" in out.err


def test_refusals_give_the_tip_and_cloud_back_as_entered_on_every_path(served):
    """A tool tip or a cloud in mm while m and LPS were declared, and a tip in metres with nothing declared: the
    reference path, the compiled path (compiled with the frame, or given points converted already with the frame
    declared, as a sequence does) refuse each with the same reason, which gives the value as entered with the
    units and frame declared and says which units it looks like (never 'is it in mm', never 'give --frame' to a
    user who declared one)."""
    from liverforce.serve.input_frame import InputFrame

    path, model, a = served
    pred = Predictor.from_dir(path)
    ctx, cloud, tip = _case(a, 4)
    fr = InputFrame.resolve("LPS", "m")
    lps = np.array([-1.0, -1.0, 1.0])
    cloud_in, tip_in = cloud * lps / 1000.0, tip * lps / 1000.0
    with_frame, declared = pred.compile_cloud(ctx, frame=fr), pred.compile_cloud(ctx, declared=fr)
    for c, t, what in ((cloud_in, tip_in * 1000.0, "tool_tip_mm is"), (cloud_in * 1000.0, tip_in, "cloud: only")):
        with pytest.raises(PredictionInputError) as exc:
            pred.predict_cloud(fr.points(c), ctx, tool_tip_mm=fr.points(t), input_frame=fr)
        why = str(exc.value)
        assert why.startswith(what) and "it looks like mm while m, LPS was declared" in why, why
        assert "declared in m, LPS" in why and "is it in mm" not in why and "--frame" not in why, why
        assert with_frame.predict_batch([c], t[None]).refused == [why]
        assert declared.predict_batch([fr.points(c)], fr.points(t)[None]).refused == [why]
    tip_given = fr.points(tip_in * 1000.0)
    with pytest.raises(PredictionInputError) as exc:
        pred.predict_cloud(cloud, ctx, tool_tip_mm=tip_given, input_frame=fr)
    assert "it was given as [" + ", ".join(f"{x:.6g}" for x in tip_in * 1000.0) + "] m LPS" in str(exc.value)
    with pytest.raises(PredictionInputError) as exc:  # nothing declared: read as RAS mm; the tip in metres
        pred.predict_cloud(cloud, ctx, tool_tip_mm=tip / 1000.0)
    why = str(exc.value)
    assert "no units or frame were declared" in why and "it looks like m, but" in why and "--units m" in why, why
    assert pred.compile_cloud(ctx).predict_batch([cloud], (tip / 1000.0)[None]).refused == [why]


def test_a_point_finite_as_given_but_not_in_the_models_frame_is_refused_on_both_paths(served):
    """A cloud point of 1e306 m is finite as given and infinite in mm: the reference path converts first, then
    refuses the point; the compiled path, which reads clouds in the lab's frame, refuses it in the same words."""
    from liverforce.serve.input_frame import InputFrame

    path, model, a = served
    pred = Predictor.from_dir(path)
    ctx, cloud, tip = _case(a, 4)
    fr = InputFrame.resolve("LPS", "m")
    cloud_in, tip_in = fr.points_out(cloud), fr.points_out(tip)
    bad = np.vstack([cloud_in, [[1e306, 0.0, 0.0]]])
    assert np.isfinite(bad).all()
    with np.errstate(over="ignore", invalid="ignore"), pytest.raises(PredictionInputError) as exc:
        pred.predict_cloud(fr.points(bad), ctx, tool_tip_mm=fr.points(tip_in), input_frame=fr)
    why = str(exc.value)
    assert why.startswith(f"cloud: 1 of {len(bad)} points contain NaN or inf (first at row {len(cloud)})"), why
    with np.errstate(over="ignore", invalid="ignore"):
        got = pred.compile_cloud(ctx, frame=fr).predict_batch([bad], tip_in[None])
    assert got.refused == [why] and not np.isfinite(got.force).any()


def test_a_deep_press_along_the_normal_keeps_the_tip_over_the_grid(served):
    """The grid sees the tool while its tip lies within the grid's half-width along the surface: a press deeper
    than the half-width along the normal (the hardest presses of the default data move the tip 20-30 mm along
    the normal, 5-10 mm along the surface) is predicted (within 4 x the training tips' largest displacement);
    a tip the half-width off along the surface, or 9 mm above the liver (not touching it), is refused, on the
    reference and the compiled path alike, with its offset."""
    from liverforce.serve.cloud import check_camera_cloud

    path, model, arrays = served
    pred = Predictor.from_dir(path)
    ctx, cloud, _ = _case(arrays, 0)
    hw = model.representation.half_width_mm
    p, R = ctx.exertion_point_mm, ctx.frame  # rows t1, t2, n
    deep = p - 1.3 * hw * R[2] + 0.2 * hw * R[0]
    top = model.meta["training_scale"]["camera"]["tip_displacement_max_mm"]
    assert np.linalg.norm(deep - p) > hw and np.linalg.norm(deep - p) < 4 * top  # beyond the old limit, in range
    assert check_camera_cloud(model.representation, cloud, deep, p, R, pred.limits) > 0  # not refused
    fast = pred.compile_cloud(ctx)
    side, above = p + 1.1 * hw * R[1] - 0.1 * hw * R[2], p + 9.0 * R[2]
    for tip in (deep, side, above):
        ref_why = fast_why = None
        try:
            pred.predict_cloud(cloud, ctx, tool_tip_mm=tip)
        except PredictionInputError as exc:
            ref_why = str(exc)
        try:
            fast.predict(cloud, tip)
        except PredictionInputError as exc:
            fast_why = str(exc)
        assert ref_why == fast_why
        if tip is deep:
            assert ref_why is None, ref_why
        elif tip is side:
            assert ref_why.startswith(f"tool_tip_mm is {1.1 * hw:.4g} mm from the exertion point along the surface, "
                                      f"beyond the model's grid (+-{hw:.3g} mm)"), ref_why
        else:
            assert ref_why.startswith("tool_tip_mm lies 9 mm above the liver at the exertion point (outward along "
                                      "its normal; at most 5 mm): the tool does not touch it there"), ref_why
