"""``train.final_fit``: the saved model is the chosen configuration refitted on every case of the scenario."""

import numpy as np
import pytest

from liverforce.learn.metrics import force_metrics
from liverforce.learn.model import ForceModel, subset
from liverforce.learn.state import recorded_ranges, state_range_values
from liverforce.learn.synthetic import synthetic_arrays
from liverforce.learn.train import train_scenario

MODEL = {
    "encoder": "pca", "code_size": 3, "state_vector": True, "grid_size": 6, "hidden": [32],
    "dropout": 0.0, "occlusion": {"radius_mm": 0.0, "mode": "remove"}, "noise_mm": 0.0,
}
TRAIN = {"test_fraction": 0.25, "epochs": 30, "batch_size": 32, "lr": 3e-3, "weight_decay": 0.0, "seed": 0,
         "repeats": 2, "interval": {"coverage": 0.9, "calibration_fraction": 0.3, "folds": 2, "scale": "none"}}
NO_TUNE = {"enabled": False, "trials": 1, "folds": 2, "sobol_trials": 1, "epochs": 1}


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    data = synthetic_arrays(160, seed=3, n_geometries=8, nodes=(150, 200), dent_width_mm=12.0)
    out = {}
    for final in (False, True):
        res = train_scenario(data, MODEL, {**TRAIN, "final_fit": final}, NO_TUNE, "IV", "v",
                             out_dir=tmp_path_factory.mktemp(f"final-{final}"))
        out[final] = (res, ForceModel.load(res["model_path"]))
    return data, out


def test_the_splits_measure_the_same_configuration_either_way(runs):
    _, out = runs
    (split, _), (final, _) = out[False], out[True]
    assert final["metrics"] == split["metrics"]
    assert [r["metrics"] for r in final["repeats"]] == [r["metrics"] for r in split["repeats"]]
    assert final["split"]["test_geometries"] == split["split"]["test_geometries"]
    assert split["final_fit"] is None
    assert final["interval"]["test_coverage"] == split["interval"]["test_coverage"]  # the main split's


def test_the_saved_model_is_fitted_on_every_case(runs):
    data, out = runs
    (split, split_model), (final, model) = out[False], out[True]
    ids = list(data["case_id"])
    assert final["final_fit"]["n_cases"] == len(ids) == split["n_train"] + split["n_test"]
    assert len(final["final_fit"]["geometries"]) == 8
    assert model.meta["final_fit"] is True and model.meta["test_case_ids"] == []
    assert model.meta["split_test_case_ids"] == split_model.meta["test_case_ids"]
    assert model.meta["test_metrics"] == split["metrics"]  # what the configuration scored on held-out livers
    # its scalers' recorded ranges are those of all the cases, the split model's those of its training cases
    every = state_range_values(data)
    for key, rng in recorded_ranges(model.meta["training_scale"]).items():
        assert rng == pytest.approx((every[key].min(), every[key].max()), rel=1e-9), key
    held = [ids.index(c) for c in split_model.meta["test_case_ids"]]
    train = subset(data, [i for i in range(len(ids)) if i not in set(held)])
    assert any(recorded_ranges(split_model.meta["training_scale"])[k]
               != pytest.approx((v.min(), v.max()), rel=1e-9) for k, v in every.items()), \
        "the split's test livers widen no range: the check above cannot tell the two models apart"
    for key, rng in recorded_ranges(split_model.meta["training_scale"]).items():
        v = state_range_values(train)[key]
        assert rng == pytest.approx((v.min(), v.max()), rel=1e-9), key
    # the split's test livers are training livers of the final model: it fits them closer than the split model
    test = subset(data, held)
    err_final = force_metrics(test["force_n"], model.predict(test))["mae_vec"]
    assert err_final < 0.8 * split["metrics"]["mae_vec"], (err_final, split["metrics"]["mae_vec"])


def test_the_final_interval_is_calibrated_on_every_case(runs):
    data, out = runs
    (split, _), (final, model) = out[False], out[True]
    n = len(data["case_id"])
    assert split["interval"]["n_calibration"] == split["n_train"]  # cross-conformal: each training case once
    assert final["interval"]["n_calibration"] == model.interval.n_calibration == n
    with np.load(f"{final['model_path']}/../interval_calibration.npz") as z:
        assert z["true_local"].shape == (n, 3)  # the file holds the saved model's calibration
    got = model.predict_interval(data)
    assert np.isfinite(got["half_width_local_n"]).all() and (got["half_width_local_n"] > 0).all()
