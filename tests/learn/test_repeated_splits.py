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
    # every split counts its test cases outside its model's training range and scores both sides
    from liverforce.learn.model import ForceModel
    from liverforce.learn.state import outside_ranges, recorded_ranges, state_range_values

    from liverforce.learn.metrics import force_metrics
    from liverforce.learn.model import subset

    per = [r["outside_training"] for r in reps]
    model = ForceModel.load(res["model_path"])  # the main split, recomputed from the saved model
    ids = list(data["case_id"])
    test = subset(data, [ids.index(c) for c in model.meta["test_case_ids"]])
    masks, _ = outside_ranges(test, recorded_ranges(model.meta["training_scale"]))
    out = np.any(np.stack(list(masks.values())), axis=0)
    assert per[0]["n_cases"] == res["n_test"] == len(out) and per[0]["n_outside"] == int(out.sum())
    if (~out).any():
        pred = model.predict(test)
        assert per[0]["inside"]["mae_vec"] == pytest.approx(force_metrics(test["force_n"][~out], pred[~out])["mae_vec"])
    # the recorded ranges are the training rows' own (min, max), computed here from the raw arrays
    train = subset(data, [i for i, c in enumerate(ids) if c not in set(model.meta["test_case_ids"])])
    for key, rng in recorded_ranges(model.meta["training_scale"]).items():
        v = state_range_values(train)[key]
        assert rng == pytest.approx((v.min(), v.max()), rel=1e-9), key
    ot = res["outside_training"]
    if scenario == "IV":  # 2 of 8 livers held out: some test cases lie outside the other livers' range
        assert ot["n_outside"] > 0
        outs = [p["outside"]["accuracy_pct"] for p in per if p["outside"] is not None]
        assert ot["outside_accuracy_pct"]["mean"] == pytest.approx(np.mean(outs))
        err = sum(p["error_sum_n"]["outside"] for p in per)
        assert ot["outside_accuracy_pooled_pct"] == pytest.approx(100 * (1 - err / sum(p["force_sum_n"]["outside"]
                                                                                     for p in per)))
    assert ot["n_splits"] == 4 and ot["n_cases"] == sum(p["n_cases"] for p in per)
    assert ot["n_outside"] == sum(p["n_outside"] for p in per)
    for p in per:
        assert (p["inside"] is None) == (p["n_outside"] == p["n_cases"])
        assert (p["outside"] is None) == (p["n_outside"] == 0)
    got = [p["inside"]["accuracy_pct"] for p in per if p["inside"] is not None]
    assert ot["inside_accuracy_pct"]["mean"] == pytest.approx(np.mean(got))
    assert ot["inside_accuracy_pct"]["n_splits"] == len(got)


def test_heldout_exertion_points_never_train_on_a_test_point(tmp_path):
    """II/III split by case; train.heldout_points scores folds of whole exertion points, each by a model
    fitted on the other points only."""
    from liverforce.learn.synthetic import synthetic_arrays
    from liverforce.learn.train import train_scenario

    data = synthetic_arrays(120, n_geometries=1, seed=4, nodes=(150, 200))
    data["exertion_id"] = np.arange(120) % 6
    model = {"encoder": "pca", "code_size": 4, "state_vector": True, "grid_size": 6, "hidden": [16], "dropout": 0.0,
             "occlusion": {"radius_mm": 0.0, "mode": "remove"}, "noise_mm": 0.0}
    train = {"test_fraction": 0.2, "epochs": 5, "batch_size": 32, "lr": 3e-3, "weight_decay": 0.0, "seed": 0,
             "repeats": 1, "heldout_points": {"scenarios": ["II"], "folds": 3}}
    no_tune = {"enabled": False, "trials": 1, "folds": 2, "sobol_trials": 1, "epochs": 1}
    res = train_scenario(data, model, train, no_tune, "II", "v", out_dir=tmp_path)
    hp = res["heldout_points"]
    assert hp["folds"] == 3 and hp["n_points"] == 6 and sum(f["n_test"] for f in hp["per_fold"]) == 120
    held = [set(f["points"]) for f in hp["per_fold"]]
    assert all(len(h) == 2 for h in held) and set.union(*held) == {f"syn-0000#{i}" for i in range(6)}
    assert all(not (a & b) for i, a in enumerate(held) for b in held[i + 1:])  # every point held out once
    assert np.isfinite(hp["metrics_mean"]["mae_vec"]) and hp["metrics_sd"]["mae_vec"] >= 0
    # scenario I is not listed: no held-out-points evaluation
    assert train_scenario(data, model, train, no_tune, "I", "v", out_dir=tmp_path / "i")["heldout_points"] is None
