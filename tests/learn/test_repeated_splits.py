"""Uncertainty of the headline metrics: repeated seeded splits that really differ."""

import numpy as np
import pytest

from liverforce.learn.synthetic import synthetic_arrays
from liverforce.learn.train import summarise_repeats, train_scenario

MODEL = {
    "encoder": "pca", "code_size": 3, "state_vector": True, "grid_size": 6, "hidden": [32],
    "dropout": 0.0, "occlusion": {"radius_mm": 0.0, "mode": "remove"}, "noise_mm": 0.0,
}
TRAIN = {"test_fraction": 0.25, "epochs": 30, "batch_size": 32, "lr": 3e-3, "weight_decay": 0.0, "seed": 0,
         "repeats": 4}
NO_TUNE = {"enabled": False, "trials": 1, "folds": 2, "sobol_trials": 1, "epochs": 1}


def test_summary_is_mean_and_sample_sd():
    s = summarise_repeats([{"mae_vec": 1.0, "name": "x"}, {"mae_vec": 2.0, "name": "y"}, {"mae_vec": 4.0, "name": "z"}])
    assert s["n"] == 3 and set(s["mean"]) == {"mae_vec"}
    assert s["mean"]["mae_vec"] == pytest.approx(7 / 3)
    assert s["sd"]["mae_vec"] == pytest.approx(np.std([1.0, 2.0, 4.0], ddof=1))
    assert summarise_repeats([{"a": 3.0}])["sd"]["a"] == 0.0


@pytest.mark.parametrize("scenario, n_geo", [("II", 1), ("IV", 8)])
def test_repeated_splits_hold_out_different_cases_and_give_a_spread(tmp_path, scenario, n_geo):
    data = synthetic_arrays(160, seed=3, n_geometries=n_geo, nodes=(150, 200), dent_width_mm=12.0)
    res = train_scenario(data, MODEL, TRAIN, NO_TUNE, scenario, "v", out_dir=tmp_path)
    reps = res["repeats"]
    assert res["n_splits"] == len(reps) == 4
    from liverforce.seeds import derive

    assert [r["split_seed"] for r in reps] == [0] + [derive(0, "split.repeat", r) for r in (1, 2, 3)]
    assert reps[0]["metrics"] == res["metrics"]  # the first split is the saved model's
    if scenario == "IV":  # split by liver: the held-out livers differ between splits
        held = {tuple(r["test_geometries"]) for r in reps}
        assert len(held) >= 3, held
    maes = np.array([r["metrics"]["mae_vec"] for r in reps])
    assert len(set(maes.round(12))) == 4  # every split scored its own test set
    assert res["metrics_mean"]["mae_vec"] == pytest.approx(maes.mean())
    assert res["metrics_sd"]["mae_vec"] == pytest.approx(maes.std(ddof=1))
    assert res["metrics_sd"]["mae_vec"] > 0
