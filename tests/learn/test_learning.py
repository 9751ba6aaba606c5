"""End-to-end learning on synthetic cases with a known linear force -> dent map."""

import json

import numpy as np
import pytest

from liverforce.learn.frames import force_to_local, local_rotations
from liverforce.learn.metrics import force_metrics
from liverforce.learn.model import ForceModel, ModelFormatError, subset
from liverforce.learn.synthetic import random_rotation, rigid_motion, synthetic_arrays
from liverforce.learn.train import train_scenario

# The dent is linear in the local force; with 350-500 scattered nodes and a
# 12 mm wide dent the grid's interpolation noise caps a linear read-out at
# ~99.7 % accuracy, so > 99 % tests the encoder + MLP, not the data.
N_CASES = 400
MODEL = {
    "encoder": "pca", "code_size": 3, "state_vector": False, "grid_size": 10, "hidden": [128, 128],
    "dropout": 0.0, "occlusion": {"radius_mm": 0.0, "mode": "remove"}, "noise_mm": 0.0,
}
TRAIN = {"test_fraction": 0.2, "epochs": 300, "batch_size": 32, "lr": 3e-3, "weight_decay": 0.0, "seed": 0}
NO_TUNE = {"enabled": False, "trials": 1, "folds": 2, "sobol_trials": 1, "epochs": 1}


@pytest.fixture(scope="module")
def data():
    return synthetic_arrays(N_CASES, seed=1, nodes=(350, 500), dent_width_mm=12.0)


@pytest.fixture(scope="module")
def fitted(data, tmp_path_factory):
    results = {}

    def get(encoder: str) -> dict:
        if encoder not in results:
            out = tmp_path_factory.mktemp(f"learn-{encoder}")
            results[encoder] = train_scenario(data, {**MODEL, "encoder": encoder}, TRAIN, NO_TUNE, "II", encoder,
                                              out_dir=out)
        return results[encoder]

    return get


@pytest.mark.slow  # one of the default set's slowest (CI's --durations): run with -m slow
@pytest.mark.parametrize("encoder", ["pca", "ae", "dae"])
def test_linear_force_map_is_learned_to_one_percent(fitted, encoder):
    res = fitted(encoder)
    m = res["metrics"]
    assert m["accuracy_pct"] > 99.0, m
    assert res["n_test"] == 80 and res["n_train"] == 320
    # forces are 1-5 N: an MAE of the vector below 0.05 N
    assert m["mae_vec"] < 0.05


def test_saved_model_reproduces_metrics_exactly(fitted, data):
    res = fitted("pca")
    model = ForceModel.load(res["model_path"])
    test = subset(data, [list(data["case_id"]).index(c) for c in model.meta["test_case_ids"]])
    pred = model.predict(test, observation_seed=res["eval_observation_seed"])
    assert force_metrics(test["force_n"], pred) == res["metrics"]
    assert model.meta["test_metrics"] == res["metrics"]  # the bundle carries the metrics it was scored with


def test_scalers_are_fitted_on_the_training_split_only(fitted, data):
    res = fitted("pca")
    model = ForceModel.load(res["model_path"])
    test_ids = set(model.meta["test_case_ids"])
    train_idx = [i for i, c in enumerate(data["case_id"]) if c not in test_ids]
    tr = subset(data, train_idx)
    R = local_rotations(tr["frame_normal"], tr["frame_t1"], tr["frame_t2"])
    y = force_to_local(tr["force_n"], R)
    np.testing.assert_allclose(model.pre.target_scaler.mean, y.mean(axis=0), rtol=1e-12)
    R_all = local_rotations(data["frame_normal"], data["frame_t1"], data["frame_t2"])
    assert not np.allclose(model.pre.target_scaler.mean, force_to_local(data["force_n"], R_all).mean(axis=0))


def test_prediction_is_invariant_to_rigid_motion(fitted):
    model = ForceModel.load(fitted("pca")["model_path"])
    cases = synthetic_arrays(10, seed=77, nodes=(350, 500), dent_width_mm=12.0, dtype=np.float64)
    Q = random_rotation(np.random.default_rng(5))
    moved = rigid_motion(cases, Q, np.array([-300.0, 20.0, 512.0]))
    f0 = model.predict_local(cases)
    np.testing.assert_allclose(model.predict_local(moved), f0, atol=1e-6)
    # source-frame predictions rotate with the liver
    np.testing.assert_allclose(model.predict(moved), model.predict(cases) @ Q.T, atol=1e-6)


def test_format_version_mismatch_is_refused(fitted, tmp_path):
    model = ForceModel.load(fitted("pca")["model_path"])
    path = model.save(tmp_path / "m")
    doc = json.loads((path / "model.json").read_text())
    doc["format_version"] = 999
    (path / "model.json").write_text(json.dumps(doc))
    with pytest.raises(ModelFormatError, match="format version 999"):
        ForceModel.load(path)
    with pytest.raises(ModelFormatError, match="no model.json"):
        ForceModel.load(tmp_path / "nothing")


@pytest.mark.parametrize("old_version", [3, 4])
def test_an_older_bundle_still_loads(fitted, tmp_path, old_version):
    """Version 4 only added the GP ensemble and 5 the indentation strain: a bundle written at version 3 (one GP
    or an MLP) or 4 (no indentation strain: the key is absent) loads and predicts as before."""
    from liverforce.learn.model import FORMAT_VERSION

    model = ForceModel.load(fitted("pca")["model_path"])
    path = model.save(tmp_path / "m")
    doc = json.loads((path / "model.json").read_text())
    assert doc["format_version"] == FORMAT_VERSION == 18
    assert doc["scalers"].pop("indentation_strain") is False
    doc["format_version"] = old_version
    (path / "model.json").write_text(json.dumps(doc))
    old = ForceModel.load(path)
    assert old.regressor_spec == model.regressor_spec and not old.pre.indentation_strain
    cases = synthetic_arrays(6, n_geometries=1, seed=9, nodes=(120, 200))
    np.testing.assert_array_equal(old.predict(cases), model.predict(cases))


def test_same_seed_gives_same_metrics(tmp_path):
    arrays = synthetic_arrays(60, n_geometries=3, seed=4, nodes=(120, 200))
    model = {**MODEL, "encoder": "dae", "grid_size": 6, "hidden": [16], "dropout": 0.1, "noise_mm": 0.05,
             "occlusion": {"radius_mm": 3.0, "mode": "noise"}}
    train = {**TRAIN, "epochs": 8}
    tune = {"enabled": True, "trials": 2, "folds": 2, "sobol_trials": 2, "epochs": 3}
    a = train_scenario(arrays, model, train, tune, "IV", "dae", out_dir=tmp_path / "a", seed=3)
    b = train_scenario(arrays, model, train, tune, "IV", "dae", out_dir=tmp_path / "b", seed=3)
    c = train_scenario(arrays, model, train, tune, "IV", "dae", out_dir=tmp_path / "c", seed=4)
    assert a["metrics"] == b["metrics"]
    assert a["best_params"] == b["best_params"]
    assert a["metrics"] != c["metrics"]
    assert a["split"]["by"] == "geometry" and a["split"]["cv_grouping"] == "geometry"
