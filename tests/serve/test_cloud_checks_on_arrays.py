"""A camera cloud in the wrong units (or off the grid, or a tip beyond it) is refused by ``predict_arrays`` and
the MLflow pyfunc as ``predict_cloud`` (and so ``liverforce predict``) refuses it: the same checks, the same
words, the row named. Before, ``predict_arrays`` lacked the points-over-the-grid and the far-tip checks, and
a cloud in mm sent as metres came back from the pyfunc as a force."""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from liverforce.learn.model import ForceModel, subset
from liverforce.learn.observation import ObservationConfig, observe
from liverforce.learn.synthetic import synthetic_surface_arrays
from liverforce.learn.train import train_scenario
from liverforce.serve import Predictor, Preop
from liverforce.serve.errors import PredictionInputError
from liverforce.serve.input_frame import InputFrame

from tests.serve.test_input_frame import to_input_arrays

MODEL = {"encoder": "pca", "code_size": 6, "state_vector": True, "grid_size": 8, "hidden": [16, 16],
         "dropout": 0.0, "occlusion": {"radius_mm": 0.0, "mode": "remove"}, "noise_mm": 0.0,
         "roi_features": "cloud", "force_scaling": "stiffness", "probe_force_radius_mm": 5.0,
         "camera": {"observation": {"n_points": [300, 3000], "noise_sd_mm": 0.3}, "grid": {}, "tip_noise_mm": 0.1}}
TRAIN = {"test_fraction": 0.2, "epochs": 8, "batch_size": 32, "lr": 3e-3, "weight_decay": 0.0, "seed": 0,
         "interval": {"coverage": 0.9, "calibration_fraction": 0.25}}
NO_TUNE = {"enabled": False, "trials": 1, "folds": 2, "sobol_trials": 1, "epochs": 1}
LPS = np.diag([-1.0, -1.0, 1.0, 1.0])


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """A small camera model, a held-out case's context, a camera cloud of it and its tool tip (RAS mm)."""
    arrays = synthetic_surface_arrays(80, n_geometries=3, seed=3, material_varies=True)
    res = train_scenario(arrays, MODEL, TRAIN, NO_TUNE, "IV", "cloud", out_dir=tmp_path_factory.mktemp("a96-cam"))
    pred = Predictor(ForceModel.load(res["model_path"]))
    a = subset(arrays, np.flatnonzero(np.isin(arrays["geometry_id"], res["split"]["test_geometries"])))
    V, T = a["surface_meshes"][a["geometry_id"][0]]
    u = np.asarray(a["surface_displacement_mm"][0], dtype=np.float64)
    p = a["exertion_point_mm"][0]
    tip = p + u[int(np.argmin(np.linalg.norm(V - p, axis=1)))]
    cfg = ObservationConfig(n_points=(2000, 2000), noise_sd_mm=0.3, roi_radius_mm=40.0)
    cloud = observe(V + u, T, tip, a["frame_normal"][0], cfg, seed=0)[0]
    ctx = Preop.from_arrays({k: v for k, v in a.items() if k != "roi_deformed_mm"}, 0)
    row = dict(ctx.to_arrays(ctx.roi_undeformed_mm), case_id=np.array(["lab-1"]))
    row = {k: v for k, v in row.items() if k not in ("roi_deformed_mm", "roi_centroid_deformed_mm")}
    return pred, ctx, cloud, tip, row


def _refusal(call) -> str:
    with pytest.raises(PredictionInputError) as exc:
        call()
    return str(exc.value)


def _lab(row: dict, cloud_lab: np.ndarray, tip_ras_mm: np.ndarray) -> dict:
    """The row in LPS metres (a lab's inputs), with the cloud ``cloud_lab`` as the lab sent it."""
    lab = to_input_arrays(LPS, 1000.0, {**row, "tool_tip_mm": tip_ras_mm[None]})
    lab["camera_cloud_mm"] = [cloud_lab]
    return lab


def _pyfunc(pred: Predictor, arrays: dict, **params):
    from liverforce.tracking.model import ForceModelPyfunc, arrays_to_frame

    pf = ForceModelPyfunc()
    pf.model = pred.model
    return pf.predict(None, arrays if isinstance(arrays, pd.DataFrame) else arrays_to_frame(arrays, list(arrays)),
                      params={"on_refused": "row", **params})  # as MLflow calls a model logged with the param


def _pyfunc_refusal(pred: Predictor, arrays: dict, **params) -> str:
    """The pyfunc's refusal of a one-row request: raised with ``on_refused="request"``, and by default the row's
    ``refused`` column in the same words, its forces NaN."""
    raised = _refusal(lambda: _pyfunc(pred, arrays, on_refused="request", **params))
    out = _pyfunc(pred, arrays, **params)
    assert list(out["refused"]) == [raised] and out[["fx_n", "fy_n", "fz_n"]].isna().all().all()
    return raised


def test_the_inputs_in_lps_metres_are_predicted_alike(served):
    """The check is no refusal of good inputs: the lab's row in LPS metres gives predict_cloud's force, through
    predict_arrays and the pyfunc."""
    pred, ctx, cloud, tip, row = served
    want = pred.predict_cloud(cloud, ctx, tool_tip_mm=tip)
    lab = _lab(row, (cloud * [-1, -1, 1]) / 1000.0, tip)
    fr = InputFrame.resolve("LPS", "m")
    got = pred.predict_arrays(fr.arrays(lab), input_frame=fr)
    np.testing.assert_allclose(got[0], want, rtol=1e-5, atol=1e-7)
    out = _pyfunc(pred, lab, input_frame="LPS", units="m")
    np.testing.assert_allclose(out[["fx_n", "fy_n", "fz_n"]].to_numpy()[0], want * [-1, -1, 1], rtol=1e-5, atol=1e-7)


def test_a_cloud_in_mm_sent_as_metres_is_refused_as_the_cli_refuses_it(served):
    """A lab's cloud in mm (LPS) sent with units m: 1000x too far once converted, no point over the grid.
    predict_cloud (the CLI's path) refuses it naming the points over the grid and the units it looks like; so do
    predict_arrays and the pyfunc, word for word, with the row named."""
    pred, ctx, cloud, tip, row = served
    fr = InputFrame.resolve("LPS", "m")
    lab = _lab(row, cloud * [-1, -1, 1], tip)  # mm, while m was declared
    conv = fr.arrays(lab)
    cli = _refusal(lambda: pred.predict_cloud(conv["camera_cloud_mm"][0], ctx, tool_tip_mm=conv["tool_tip_mm"][0],
                                              input_frame=fr))
    assert "points lie over the model's" in cli and "it looks like mm while m, LPS was declared" in cli
    assert _pyfunc_refusal(pred, lab, input_frame="LPS", units="m") == "case lab-1: " + cli
    assert _refusal(lambda: pred.predict_arrays(conv, input_frame=fr)) == "case lab-1: " + cli


def test_the_reverse_a_cloud_in_metres_sent_as_mm_is_refused_alike(served):
    """The reverse: the context in mm and the cloud in metres (read as mm). Refused by every path with one
    message, naming metres."""
    pred, ctx, cloud, tip, row = served
    arrays = {**row, "camera_cloud_mm": [cloud / 1000.0], "tool_tip_mm": tip[None]}
    cli = _refusal(lambda: pred.predict_cloud(cloud / 1000.0, ctx, tool_tip_mm=tip))
    assert "metres" in cli
    assert _refusal(lambda: pred.predict_arrays(arrays)) == "case lab-1: " + cli
    assert _pyfunc_refusal(pred, arrays) == "case lab-1: " + cli


def test_a_cloud_off_the_grid_and_a_tip_beyond_it_are_refused_alike(served):
    """A cloud in mm lying beside the grid (too few points over it), and a tool tip beyond the grid: refused by
    predict_arrays and the pyfunc with predict_cloud's reasons, not predicted."""
    pred, ctx, cloud, tip, row = served
    h = pred.model.representation.half_width_mm
    beside = cloud + 3 * h * ctx.frame[0]
    far = tip + 3 * h * ctx.frame[0]
    for c, t, what in ((beside, tip, "points lie over the model's"), (cloud, far, "from the exertion point along the "
                                                                                  "surface, beyond the model's grid")):
        cli = _refusal(lambda: pred.predict_cloud(c, ctx, tool_tip_mm=t))
        assert what in cli
        arrays = {**row, "camera_cloud_mm": [c], "tool_tip_mm": t[None]}
        assert _refusal(lambda: pred.predict_arrays(arrays)) == "case lab-1: " + cli
        assert _pyfunc_refusal(pred, arrays) == "case lab-1: " + cli


def test_refused_camera_rows_go_on_with_the_reason_they_would_raise(served):
    """``predict_arrays(return_refused=True)`` on camera rows: rows refused before the features (a cloud beside the
    grid, a tip beyond it) and after them (a cloud that sees a quarter of the grid) get NaN, no warnings and the
    words predict_arrays raises for each alone; the rows between are predicted as on their own. By default, and
    in the pyfunc with ``on_refused="request"``, the first refused row still refuses the call."""
    pred, ctx, cloud, tip, row = served
    h = pred.model.representation.half_width_mm
    loc = (cloud - ctx.exertion_point_mm) @ ctx.rotation.T
    clouds = [cloud, cloud + 3 * h * ctx.frame[0], cloud, cloud[(loc[:, 0] > 0) & (loc[:, 1] > 0)], cloud[::2]]
    tips = [tip, tip, tip + 3 * h * ctx.frame[0], tip, tip]
    n = len(clouds)
    arrays = {k: [v[0]] * n if isinstance(v, list) else np.repeat(np.asarray(v), n, axis=0) for k, v in row.items()}
    arrays.update(case_id=np.array([f"lab-{k}" for k in range(n)]), camera_cloud_mm=clouds, tool_tip_mm=np.stack(tips))
    alone = [_refusal(lambda: pred.predict_arrays(subset(arrays, [k]))) for k in (1, 2, 3)]
    assert "points lie over the model's" in alone[0] and "beyond the model's grid" in alone[1]
    assert "sees only" in alone[2] and all(a.startswith(f"case lab-{k}: ") for a, k in zip(alone, (1, 2, 3)))
    force, warned, refused = pred.predict_arrays(arrays, return_warnings=True, return_refused=True)
    assert refused == ["", *alone, ""]
    assert np.isnan(force[1:4]).all() and warned[1:4] == [[], [], []]
    good, good_warned = pred.predict_arrays(subset(arrays, [0, 4]), return_warnings=True)
    np.testing.assert_allclose(force[[0, 4]], good, atol=1e-12)
    assert [warned[0], warned[4]] == good_warned
    assert _refusal(lambda: pred.predict_arrays(arrays)) == alone[0]
    force, why = pred.predict_arrays(subset(arrays, [1, 2]), return_refused=True)  # every row refused before
    assert np.isnan(force).all() and why == alone[:2]  # the features (subset() of no rows indexed with floats)
    assert _refusal(lambda: _pyfunc(pred, arrays, on_refused="request")) == alone[0]


def test_the_pyfunc_answers_refused_camera_rows_and_predicts_the_others(served):
    """The pyfunc's default (``on_refused="row"``) on camera rows: a cloud with a NaN point, a cloud too sparse
    over the grid, a tip above the liver, a flattened cloud not 3 k long and an unloaded cloud with a NaN point
    (its registration refused) get NaN forces and interval, no warnings, and the reason the pyfunc raises for each
    alone; the good rows every column as in a request of them alone. ``on_refused="request"``: the first refused
    row, the unreadable cloud (read before any check), refuses the request."""
    from liverforce.tracking.model import PyfuncInputError, arrays_to_frame

    pred, ctx, cloud, tip, row = served
    bad_point = cloud.copy()
    bad_point[7] = np.nan
    clouds = [cloud, bad_point, cloud[::80], cloud, cloud, cloud, cloud[::2]]
    tips = [tip, tip, tip, tip + 30.0 * ctx.frame[2], tip, tip, tip]  # frame: rows t1, t2, n
    n = len(clouds)
    arrays = {k: [v[0]] * n if isinstance(v, list) else np.repeat(np.asarray(v), n, axis=0) for k, v in row.items()}
    arrays.update(case_id=np.array([f"lab-{k}" for k in range(n)]), camera_cloud_mm=clouds, tool_tip_mm=np.stack(tips),
                  unloaded_cloud_mm=[np.zeros((0, 3))] * 5 + [bad_point, np.zeros((0, 3))])
    df = arrays_to_frame(arrays, list(arrays))
    df.at[4, "camera_cloud_mm"] = df.at[4, "camera_cloud_mm"][:-2]
    out = _pyfunc(pred, df)
    good, bad = [0, 6], [1, 2, 3, 4, 5]
    alone = {i: _refusal(lambda: _pyfunc(pred, df.iloc[[i]].reset_index(drop=True), on_refused="request"))
             for i in bad}
    assert "cloud: 1 of " in alone[1] and "NaN or inf" in alone[1]
    assert "the camera sees only" in alone[2] and "above the liver" in alone[3]
    assert alone[4] == f"case lab-4: camera_cloud_mm: {3 * len(cloud) - 2} numbers, not a multiple of 3 (x, y, z " \
                       "per point, flattened)"
    assert "unloaded_cloud_mm: 1 of " in alone[5]
    assert all(alone[i].startswith(f"case lab-{i}: ") for i in bad)
    assert list(out["refused"]) == [alone.get(i, "") for i in range(n)]
    values = [c for c in out.columns if c not in ("refused", "warnings")]
    assert len(values) == 9 and out.loc[bad, values].isna().all().all() and (out.loc[bad, "warnings"] == "").all()
    ok = _pyfunc(pred, df.iloc[good].reset_index(drop=True))
    assert np.isfinite(ok[values].to_numpy()).all()
    pd.testing.assert_frame_equal(out.iloc[good].reset_index(drop=True), ok)
    with pytest.raises(PyfuncInputError) as exc:
        _pyfunc(pred, df, on_refused="request")
    assert str(exc.value) == alone[4]
