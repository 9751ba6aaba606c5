"""Every prediction path warns about the same cases when their inputs lie farther from the training cases than the
model's input-distance threshold (meta.input_distance, liverforce.learn.interval): Predictor.predict_cloud (whose
interval reports the distance), predict_arrays, the MLflow pyfunc, the compiled camera path alone and in a batch
(whose GP head reads the distance off its own kernel matrix) and, for a node model, predict_arrays with and
without the compiled node path and the CLI. The flagged cases are exactly those whose reference distance
(ForceModel.forward) lies above the threshold."""
from __future__ import annotations

import copy
import json

import numpy as np
import pytest

from liverforce.learn.model import ForceModel, subset
from liverforce.learn.observation import ObservationConfig, observe
from liverforce.learn.synthetic import synthetic_surface_arrays
from liverforce.learn.train import train_scenario
from liverforce.serve import Predictor, Preop

MODEL = {"encoder": "pca", "code_size": 6, "state_vector": True, "grid_size": 8, "hidden": [16], "dropout": 0.0,
         "occlusion": {"radius_mm": 0.0, "mode": "remove"}, "noise_mm": 0.0, "roi_features": "cloud",
         "force_scaling": "none", "probe_force_radius_mm": 5.0, "indentation_strain": True, "regressor": "gp",
         "gp": {"max_points": 2000, "iterations": 60, "code_members": [2, 4, 6]},
         "camera": {"observation": {"n_points": [300, 3000], "noise_sd_mm": 0.3},
                    "grid": {"kernel_radius_cells": 1.5}, "tip_noise_mm": 0.1}}
INTERVAL = {"coverage": 0.9, "calibration_fraction": 0.25, "folds": 3, "scale": "force", "spread": 4.0,
            "distance_quantile": 0.8, "far_widths": True}  # a fifth of the calibration far: enough for its width
TRAIN = {"test_fraction": 0.2, "epochs": 1, "batch_size": 32, "lr": 3e-3, "weight_decay": 0.0, "seed": 0,
         "interval": INTERVAL}
NO_TUNE = {"enabled": False, "trials": 1, "folds": 2, "sobol_trials": 1, "epochs": 1}
FAR = "lies far from every training case"


def far(warnings) -> bool:
    hits = [w for w in warnings if FAR in w]
    assert len(hits) <= 1
    return bool(hits)


def between(d) -> float:
    """A threshold midway between the two middle distances of ``d``: no case sits on it, where rounding could put
    it on either side on different paths."""
    s = np.sort(np.asarray(d, dtype=np.float64))
    return float(0.5 * (s[len(s) // 2 - 1] + s[len(s) // 2]))


def with_threshold(model: ForceModel, threshold: float) -> ForceModel:
    """The model with its input-distance threshold moved (to flag some cases of a small test and not others)."""
    meta = copy.deepcopy(model.meta)
    meta["input_distance"]["threshold"] = float(threshold)
    return ForceModel(model.representation, model.pre, model.regressor_spec, model.regressor, meta)


@pytest.fixture(scope="module")
def camera(tmp_path_factory):
    """A small camera GP ensemble with an interval and the input-distance flag; clouds of one held-out context."""
    arrays = synthetic_surface_arrays(80, n_geometries=3, seed=3, material_varies=True)
    res = train_scenario(arrays, MODEL, TRAIN, NO_TUNE, "IV", "cloud", out_dir=tmp_path_factory.mktemp("far-cam"))
    model = ForceModel.load(res["model_path"])
    assert model.distance_flag is not None and model.distance_flag["quantile"] == 0.8
    assert model.interval.uses_distance and model.interval.far_threshold == model.distance_flag["threshold"]
    a = subset(arrays, np.flatnonzero(np.isin(arrays["geometry_id"], res["split"]["test_geometries"])))
    V, T = a["surface_meshes"][a["geometry_id"][0]]
    clouds, tips = [], []
    for k in range(8):  # case 0's context pressed to several depths (distances that differ)
        u = (0.4 + 0.5 * k) * np.asarray(a["surface_displacement_mm"][0], dtype=np.float64)
        p = a["exertion_point_mm"][0]
        tip = p + u[int(np.argmin(np.linalg.norm(V - p, axis=1)))]
        cfg = ObservationConfig(n_points=(2000, 2000), noise_sd_mm=0.3, roi_radius_mm=40.0)
        clouds.append(observe(V + u, T, tip, a["frame_normal"][0], cfg, seed=k)[0])
        tips.append(tip)
    ctx = Preop.from_arrays({k: v for k, v in a.items() if k != "roi_deformed_mm"}, 0)
    return model, ctx, clouds, np.array(tips)


def test_every_camera_path_flags_the_cases_beyond_the_threshold(camera):
    model, ctx, clouds, tips = camera
    ref = Predictor(model)
    infos = [ref.predict_cloud(c, ctx, tool_tip_mm=t, return_info=True)[1] for c, t in zip(clouds, tips)]
    d = np.array([i["interval"]["input_distance"] for i in infos])
    thr = between(d)
    want = d > thr
    assert 0 < want.sum() < len(d)
    pred = Predictor(with_threshold(model, thr))
    got = [pred.predict_cloud(c, ctx, tool_tip_mm=t, return_info=True)[1] for c, t in zip(clouds, tips)]
    assert [far(i["warnings"]) for i in got] == want.tolist()
    assert [far(i["warnings"]) for i in infos] == (d > model.distance_flag["threshold"]).tolist()
    fast = pred.compile_cloud(ctx)
    assert [far(fast.predict(c, t)[2]) for c, t in zip(clouds, tips)] == want.tolist()
    batch = fast.predict_batch(clouds, tips)
    assert [far(w) for w in batch.warnings] == want.tolist()
    X = np.stack([fast.features(c, t) for c, t in zip(clouds, tips)])
    np.testing.assert_allclose(fast._head(X)[2], d, rtol=1e-5)  # the head's distance is the reference's
    row = dict(ctx.to_arrays(ctx.roi_undeformed_mm))
    row = {k: v for k, v in row.items() if k not in ("roi_deformed_mm", "roi_centroid_deformed_mm")}
    n = len(clouds)
    arrays = {k: [v[0]] * n if isinstance(v, list) else np.repeat(np.asarray(v), n, axis=0) for k, v in row.items()}
    arrays.update(case_id=np.array([f"c{k}" for k in range(n)]), camera_cloud_mm=clouds, tool_tip_mm=tips)
    _, warnings = pred.predict_arrays(arrays, return_warnings=True)
    assert [far(w) for w in warnings] == want.tolist()
    from liverforce.tracking.model import ForceModelPyfunc, arrays_to_frame

    pf = ForceModelPyfunc()
    pf.model = pred.model
    out = pf.predict(None, arrays_to_frame(arrays, list(arrays)), params={"on_refused": "row"})
    assert [FAR in w for w in out["warnings"]] == want.tolist()


def test_without_a_record_no_path_warns(camera):
    model, ctx, clouds, tips = camera
    deep = clouds[-1], tips[-1]
    low = Predictor(with_threshold(model, 0.0))  # with a record any case above 0 warns, on both paths
    assert far(low.predict_cloud(deep[0], ctx, tool_tip_mm=deep[1], return_info=True)[1]["warnings"])
    assert far(low.compile_cloud(ctx).predict(*deep)[2])
    import dataclasses

    meta = {k: v for k, v in model.meta.items() if k != "input_distance"}
    meta["interval"] = dataclasses.replace(model.interval, far_threshold=None, far_factor=None,
                                           near_factor=None).to_dict()  # nor far widths: the head measures nothing
    bare = Predictor(ForceModel(model.representation, model.pre, model.regressor_spec, model.regressor, meta))
    assert bare.model.distance_flag is None
    assert not far(bare.predict_cloud(*deep[:1], ctx, tool_tip_mm=deep[1], return_info=True)[1]["warnings"])
    fast = bare.compile_cloud(ctx)
    assert fast._head(fast.features(*deep)[None])[2] is None
    assert not far(fast.predict(*deep)[2])


@pytest.fixture(scope="module")
def nodes(data, configs, tmp_path_factory):
    """A node GP ensemble (the correspondence reference) with the flag, and held-out cases."""
    base, train, tune = configs
    model_cfg = {**base, "regressor": "gp", "gp": {"max_points": 2000, "iterations": 60, "code_members": [2, 4]}}
    res = train_scenario(data, model_cfg, {**train, "interval": {**INTERVAL, "scale": "none"}}, tune, "III", "gp",
                         out_dir=tmp_path_factory.mktemp("far-nodes"))
    model = ForceModel.load(res["model_path"])
    test = subset(data, [list(data["case_id"]).index(c) for c in model.meta["test_case_ids"]])
    return res["model_path"], model, test


def test_the_node_paths_flag_the_same_cases(nodes, tmp_path, capsys):
    path, model, test = nodes
    d = model.forward(test).input_distance
    thr = between(d)
    pred = Predictor(with_threshold(model, thr))
    want = (d > thr).tolist()
    for fast in (True, False):  # the compiled node path takes its distances from one more reference pass
        _, warnings = pred.predict_arrays(test, fast=fast, return_warnings=True)
        assert [far(w) for w in warnings] == want
    # the CLI's node mode: its interval reports the distance, and the warning comes with it
    from tests.serve.test_predict_cli import context_doc, run

    moved = tmp_path / "model"
    pred.model.save(moved)
    i = int(np.argmax(d))
    ctx = Preop.from_arrays(test, i)
    (tmp_path / "roi.csv").write_text("".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in ctx.roi_undeformed_mm.tolist()))
    (tmp_path / "ctx.json").write_text(json.dumps(context_doc(ctx, "roi.csv")))
    np.save(tmp_path / "nodes.npy", np.asarray(test["roi_deformed_mm"][i]))
    rc, _, err = run(["-m", moved, tmp_path / "nodes.npy", "--mode", "nodes", "--context", tmp_path / "ctx.json",
                      "--out", tmp_path / "f.json"], capsys)
    assert rc == 0, err
    doc = json.loads((tmp_path / "f.json").read_text())
    assert doc["interval"]["input_distance"] == pytest.approx(d[i], rel=1e-6)
    assert far(doc["warnings"])


def test_the_far_widths_are_the_same_on_every_camera_path(camera):
    """An interval with far widths (a width of its own beyond the flag's threshold): the compiled path's
    half-widths, one cloud and a batch, equal the reference's (ForceModel.predict_interval) for clouds on both
    sides of the threshold, and a far cloud's are the far factor's multiple of what the one width would give."""
    import dataclasses

    model, ctx, clouds, tips = camera
    ref = Predictor(model)
    infos = [ref.predict_cloud(c, ctx, tool_tip_mm=t, return_info=True)[1]["interval"] for c, t in zip(clouds, tips)]
    d = np.array([i["input_distance"] for i in infos])
    srt = np.sort(d)
    line = float(0.5 * (srt[3] + srt[4]))  # between two clouds' distances: none on the line
    pred = Predictor(with_threshold(model, line))
    ci = dataclasses.replace(pred.model.interval, far_threshold=line)
    pred.model.meta["interval"] = ci.to_dict()
    got = [pred.predict_cloud(c, ctx, tool_tip_mm=t, return_info=True)[1]["interval"] for c, t in zip(clouds, tips)]
    h_ref = np.array([g["half_width_local_n"] for g in got])
    fast = pred.compile_cloud(ctx)
    h1 = np.array([fast.predict(c, t)[1] for c, t in zip(clouds, tips)])
    hb = fast.predict_batch(clouds, tips).half_width
    np.testing.assert_allclose(h1, h_ref, rtol=1e-5)
    np.testing.assert_allclose(hb, h_ref, rtol=1e-5)
    far = d > line
    one = dataclasses.replace(ci, far_threshold=None, far_factor=None, near_factor=None)
    X = np.stack([fast.features(c, t) for c, t in zip(clouds, tips)])
    F, S, D = fast._head(X)
    h_one = fast._kf * one.force_widths(F, S)
    np.testing.assert_allclose(h_ref[far], h_one[far] * np.asarray(ci.far_factor), rtol=1e-5)
    np.testing.assert_allclose(h_ref[~far], h_one[~far] * np.asarray(ci.near_factor), rtol=1e-5)


def test_the_compiled_node_path_gives_the_far_widths(nodes):
    """CompiledROI.predict_interval and predict_batch(with_interval=True) read the input distance for an interval
    with far widths, and equal the reference on rows both sides of the threshold."""
    import dataclasses

    from liverforce.serve.compiled import CompiledROI

    path, model, test = nodes
    assert model.interval.uses_distance
    i = 0
    ctx = Preop.from_arrays(test, i)
    D = np.asarray(test["roi_deformed_mm"][i])
    Ds = np.stack([ctx.roi_undeformed_mm + s * (D - ctx.roi_undeformed_mm) for s in (0.3, 0.7, 1.0, 1.6, 2.2)])
    each = np.sort([model.input_distances(ctx.to_arrays(x), rotations=ctx.rotation[None])[0] for x in Ds])
    line = float(0.5 * (each[2] + each[3]))  # between two rows' distances: no row on the line
    m2 = with_threshold(model, line)
    m2.meta["interval"] = dataclasses.replace(m2.interval, far_threshold=line).to_dict()
    comp = CompiledROI(m2, ctx)
    refs = [m2.predict_interval(ctx.to_arrays(x), rotations=ctx.rotation[None]) for x in Ds]
    h_ref = np.array([r["half_width_local_n"][0] for r in refs])
    dists = np.array([r["input_distance"][0] for r in refs])
    assert (dists > line).sum() == 2 and (dists < line).sum() == 3
    h1 = np.array([comp.predict_interval(x)[1] for x in Ds])
    _, hb = comp.predict_batch(Ds, with_interval=True)
    np.testing.assert_allclose(h1, h_ref, rtol=1e-5)
    np.testing.assert_allclose(hb, h_ref, rtol=1e-5)
