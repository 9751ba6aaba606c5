"""MLflow tracking: nested Ax trial runs, model reload by run id, SQLite lock retries and concurrency."""

import multiprocessing as mp
import sqlite3

import numpy as np
import pytest
from mlflow.exceptions import MlflowException

from liverforce.learn.metrics import force_metrics
from liverforce.learn.model import ForceModel, subset
from liverforce.learn.synthetic import synthetic_arrays
from liverforce.learn.train import train_scenario
from liverforce.tracking import PARENT_TAG, Tracker, ensure_store, is_lock_error, load_pyfunc, predict_pyfunc, with_retry

MODEL = {
    "encoder": "pca", "code_size": 3, "state_vector": True, "grid_size": 6, "hidden": [16], "dropout": 0.0,
    "occlusion": {"radius_mm": 2.0, "mode": "remove"}, "noise_mm": 0.05,
}
TRAIN = {"test_fraction": 0.25, "epochs": 15, "batch_size": 16, "lr": 3e-3, "weight_decay": 0.0, "seed": 0}
TUNE = {"enabled": True, "trials": 3, "folds": 2, "sobol_trials": 3, "epochs": 4}


def test_ax_loop_writes_nested_runs_and_the_model_reloads(tmp_path):
    arrays = synthetic_arrays(48, n_geometries=4, seed=2, nodes=(100, 160))
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    tracker = Tracker(uri, "liverforce-test")
    tags = {"rule": "train", "data_version": "manifest-abc123", "config_hash": "cafe"}
    res = train_scenario(arrays, MODEL, TRAIN, TUNE, "IV", "pca_sv", tracker=tracker, out_dir=tmp_path / "out",
                         tags=tags)

    client = tracker.client
    parent = client.get_run(res["run_id"])
    assert parent.info.status == "FINISHED"
    assert parent.data.tags["rule"] == "train"
    assert parent.data.tags["data_version"] == "manifest-abc123"
    assert parent.data.tags["config_hash"] == "cafe"
    for key in ("mae_x", "mae_y", "mae_z", "mae_vec", "rmse_x", "rmse_y", "rmse_z", "rmse_vec", "accuracy_pct",
                "cv_mse"):
        assert parent.data.metrics[key] == pytest.approx(res["metrics"].get(key, res["cv_mse"]), rel=1e-12)
    assert parent.data.params["model.encoder"] == "pca"
    train_hist = client.get_metric_history(res["run_id"], "train_loss")
    assert len(train_hist) == TRAIN["epochs"]
    assert len(client.get_metric_history(res["run_id"], "test_loss")) == TRAIN["epochs"]

    trials = tracker.nested_runs(res["run_id"])
    assert len(trials) == 3
    for run in trials:
        assert run.data.tags[PARENT_TAG] == res["run_id"]
        assert {"lr", "dropout", "n_layers", "width", "batch_size"} <= set(run.data.params)
        assert np.isfinite(run.data.metrics["cv_mse"])
        assert len(client.get_metric_history(run.info.run_id, "val_loss")) == TUNE["epochs"]
    assert min(r.data.metrics["cv_mse"] for r in trials) == pytest.approx(res["cv_mse"])

    figures = {f.path for f in client.list_artifacts(res["run_id"], "figures")}
    assert {"figures/pred_vs_true_x.png", "figures/error_histogram.png"} <= figures
    assert "force_model/model.json" in {f.path for f in client.list_artifacts(res["run_id"], "force_model")}

    # reload: our loader from the run's artifact, and the MLflow pyfunc by run id
    local = client.download_artifacts(res["run_id"], "force_model", str(tmp_path / "dl"))
    model = ForceModel.load(local)
    test = subset(arrays, [list(arrays["case_id"]).index(c) for c in model.meta["test_case_ids"]])
    seed = res["eval_observation_seed"]
    pred = model.predict(test, observation_seed=seed)
    assert force_metrics(test["force_n"], pred) == res["metrics"]
    pyfunc = load_pyfunc(f"runs:/{res['run_id']}/model", uri)
    pred_pf = predict_pyfunc(pyfunc, test, observation_seed=seed)
    np.testing.assert_array_equal(pred_pf, pred)
    assert force_metrics(test["force_n"], pred_pf) == res["metrics"]
    assert res["model_uri"] == f"runs:/{res['run_id']}/model"


def test_retry_on_locked_database_only():
    calls = []

    def flaky():
        calls.append(1)
        if len(calls) < 3:
            raise sqlite3.OperationalError("database is locked")
        return "ok"

    assert with_retry(flaky, backoff_s=0.001) == "ok" and len(calls) == 3

    def broken():
        calls.append(1)
        raise MlflowException("RESOURCE_DOES_NOT_EXIST: no such run")

    calls.clear()
    with pytest.raises(MlflowException):
        with_retry(broken, backoff_s=0.001)
    assert len(calls) == 1  # not a lock error: no retry

    try:
        try:
            raise sqlite3.OperationalError("database is locked")
        except sqlite3.OperationalError as inner:
            raise MlflowException("(sqlite3.OperationalError) failed") from inner
    except MlflowException as wrapped:
        assert is_lock_error(wrapped)

    calls.clear()

    def always_locked():
        calls.append(1)
        raise sqlite3.OperationalError("database is locked")

    with pytest.raises(sqlite3.OperationalError):
        with_retry(always_locked, retries=2, backoff_s=0.001)
    assert len(calls) == 3


def _log_many(uri: str, name: str, barrier, n_runs: int, queue) -> None:
    try:
        import mlflow  # noqa: F401  (imported before the barrier: both then hit the fresh store at once)

        barrier.wait(timeout=120)
        ensure_store(uri)
        tracker = Tracker(uri, "concurrent")
        for i in range(n_runs):
            run_id = tracker.start_run(f"{name}-{i}", params={"worker": name, "i": i})
            tracker.log_history(run_id, {"loss": [1.0 / (k + 1) for k in range(20)]})
            tracker.log_metrics(run_id, {"final": float(i)})
            tracker.end_run(run_id)
        queue.put((name, "ok"))
    except Exception as exc:  # report to the parent process
        queue.put((name, f"{type(exc).__name__}: {exc}"))


@pytest.mark.slow  # one of the default set's slowest (CI's --durations): run with -m slow
def test_two_processes_log_to_a_fresh_sqlite_store_at_once(tmp_path):
    uri = f"sqlite:///{tmp_path / 'shared.db'}"
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    barrier = ctx.Barrier(2)  # released when both have imported mlflow
    procs = [ctx.Process(target=_log_many, args=(uri, name, barrier, 15, queue)) for name in ("a", "b")]
    for p in procs:
        p.start()
    for p in procs:
        p.join(timeout=180)
    results = dict(queue.get(timeout=5) for _ in procs)
    assert results == {"a": "ok", "b": "ok"}
    tracker = Tracker(uri, "concurrent")
    runs = tracker.client.search_runs([tracker.experiment_id], max_results=100)
    assert len(runs) == 30
    assert all(r.info.status == "FINISHED" for r in runs)
