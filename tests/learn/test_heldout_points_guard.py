"""Held-out exertion points: a fold that trains on too few points of a liver is not scored (it could only
extrapolate how the force depends on the point), and says why; folds with enough points score as before."""

import numpy as np
import pytest

from liverforce.learn import train as train_mod
from liverforce.learn.model import subset
from liverforce.learn.regressor import fit_params
from liverforce.learn.synthetic import synthetic_arrays

MODEL = {"encoder": "pca", "code_size": 3, "state_vector": True, "grid_size": 6, "hidden": [8], "dropout": 0.0,
         "occlusion": {"radius_mm": 0.0, "mode": "remove"}, "noise_mm": 0.0}


def _points(n_cases: int, n_points: int, folds: int) -> dict:
    data = synthetic_arrays(n_cases, n_geometries=1, seed=4, nodes=(150, 200))
    data["exertion_id"] = np.arange(n_cases) % n_points
    cut = int(0.8 * n_cases)
    return train_mod.heldout_points(
        subset(data, np.arange(cut)), subset(data, np.arange(cut, n_cases)), MODEL, folds, 0, "pca", True, 3, 0.1,
        [8], 0.0, fit_params(MODEL, lr=3e-3, batch_size=16, epochs=3))


def test_three_points_in_two_folds_are_not_measured(monkeypatch):
    """smoke's shape: 3 exertion points, 2 folds -> one fold trains on 1 point, the other on 2: neither is
    fitted nor scored, the result says why with the counts, and no number is given."""
    def no_fit(*a, **k):
        raise AssertionError("a fold with too few training points was fitted")

    monkeypatch.setattr(train_mod, "fit_force_model", no_fit)
    hp = _points(24, 3, 2)
    assert hp["folds"] == 2 and hp["n_points"] == 3 and hp["n_scored"] == 0
    assert hp["metrics_mean"] is None and hp["metrics_sd"] is None
    assert sum(f["n_test"] for f in hp["per_fold"]) == 24  # every case still assigned to a fold
    assert all("metrics" not in f for f in hp["per_fold"])
    assert sorted(f["train_points"]["syn-0000"] for f in hp["per_fold"]) == [1, 2]
    one = next(f for f in hp["per_fold"] if f["train_points"]["syn-0000"] == 1)
    assert "trains on 1 exertion point of syn-0000" in one["skipped"]
    why = hp["not_measured"]
    assert why.startswith("3 exertion points (3 on syn-0000) in 2 folds leave at most 2 points")
    assert "give >= 6 exertion points per liver at 2 folds" in why  # 6 - 3 held out = 3 to train on


def test_fold_counts_and_advice():
    assert train_mod.fold_training_points(["a#0", "a#1", "a#2", "b#0"], ["a#0", "b#0"]) == {"a": 2, "b": 0}
    assert train_mod._points_needed(2) == 6 and train_mod._points_needed(4) == 4
    assert train_mod._folds_needed(3) is None and train_mod._folds_needed(4) == 4 and train_mod._folds_needed(6) == 2


def test_enough_points_score_as_without_the_guard(monkeypatch):
    """6 points in 3 folds (every fold trains on 4): the guard does not trigger, and the numbers are exactly
    those of the unguarded path (the minimum set to 0)."""
    guarded = _points(60, 6, 3)
    monkeypatch.setattr(train_mod, "MIN_TRAIN_POINTS", 0)
    plain = _points(60, 6, 3)
    assert guarded["n_scored"] == 3 and "not_measured" not in guarded
    assert all("skipped" not in f for f in guarded["per_fold"])
    assert guarded["metrics_mean"] == plain["metrics_mean"] and guarded["metrics_sd"] == plain["metrics_sd"]
    assert [f["metrics"] for f in guarded["per_fold"]] == [f["metrics"] for f in plain["per_fold"]]


def test_partly_scored_is_the_mean_of_the_scored_folds_only(monkeypatch):
    """4 points in 3 folds: one fold holds out 2 (trains on 2, skipped), two hold out 1 (train on 3, scored
    exactly as unguarded)."""
    guarded = _points(48, 4, 3)
    monkeypatch.setattr(train_mod, "MIN_TRAIN_POINTS", 0)
    plain = _points(48, 4, 3)
    assert guarded["n_scored"] == 2
    skipped = [i for i, f in enumerate(guarded["per_fold"]) if "skipped" in f]
    assert len(skipped) == 1 and len(guarded["per_fold"][skipped[0]]["points"]) == 2
    kept = [f["metrics"] for i, f in enumerate(plain["per_fold"]) if i not in skipped]
    assert [f["metrics"] for f in guarded["per_fold"] if "metrics" in f] == kept
    assert guarded["metrics_mean"]["accuracy_pct"] == pytest.approx(np.mean([m["accuracy_pct"] for m in kept]))


def test_one_scored_fold_has_no_spread():
    """5 points in 2 folds: one fold trains on 2 points (skipped), the other on 3 (scored). One fold gives a
    mean but no sd: ``metrics_sd`` is None, not 0."""
    hp = _points(50, 5, 2)
    assert hp["n_scored"] == 1 and "not_measured" not in hp
    assert sorted(f["train_points"]["syn-0000"] for f in hp["per_fold"] if "skipped" in f) == [2]
    scored = [f["metrics"] for f in hp["per_fold"] if "metrics" in f]
    assert hp["metrics_mean"] == scored[0]
    assert hp["metrics_sd"] is None


class _Tracker:
    """Records what train_scenario logs (a duck-typed tracker)."""

    def __init__(self):
        self.metrics: dict = {}

    def start_run(self, *a, **k):
        return "run"

    def log_metrics(self, run_id, metrics):
        assert all(v is not None for v in metrics.values()), [k for k, v in metrics.items() if v is None]
        self.metrics.update(metrics)

    def log_force_model(self, *a, **k):
        return "uri"

    def __getattr__(self, name):
        return lambda *a, **k: None


def test_one_scored_fold_logs_its_mean_and_no_sd(tmp_path):
    """The tracker gets the held-out mean of the one scored fold and no ``_sd`` metric (never None)."""
    data = synthetic_arrays(50, n_geometries=1, seed=4, nodes=(150, 200))
    data["exertion_id"] = np.arange(50) % 5
    train = {"test_fraction": 0.2, "epochs": 3, "batch_size": 16, "lr": 3e-3, "weight_decay": 0.0, "seed": 0,
             "repeats": 1, "heldout_points": {"scenarios": ["II"], "folds": 2}}
    no_tune = {"enabled": False, "trials": 1, "folds": 2, "sobol_trials": 1, "epochs": 1}
    tracker = _Tracker()
    res = train_mod.train_scenario(data, MODEL, train, no_tune, "II", "v", tracker=tracker, out_dir=tmp_path)
    hp = res["heldout_points"]
    assert hp["n_scored"] == 1 and hp["metrics_sd"] is None
    assert tracker.metrics["heldout_points_accuracy_pct_mean"] == hp["metrics_mean"]["accuracy_pct"]
    assert not [k for k in tracker.metrics if k.startswith("heldout_points_") and k.endswith("_sd")]
