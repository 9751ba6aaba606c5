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
INTERVAL = {"coverage": 0.9, "calibration_fraction": 0.25, "scale": "force", "spread": 4.0, "distance_quantile": 0.9}
TRAIN = {"test_fraction": 0.2, "epochs": 1, "batch_size": 32, "lr": 3e-3, "weight_decay": 0.0, "seed": 0,
         "interval": INTERVAL}
NO_TUNE = {"enabled": False, "trials": 1, "folds": 2, "sobol_trials": 1, "epochs": 1}
FAR = "lies far from every training case"


def far(warnings) -> bool:
    hits = [w for w in warnings if FAR in w]
    assert len(hits) <= 1
    return bool(hits)


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
    assert model.distance_flag is not None and model.distance_flag["quantile"] == 0.9
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
    thr = float(np.median(d))
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
    meta = {k: v for k, v in model.meta.items() if k != "input_distance"}
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
    thr = float(np.median(d))
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
