"""The run logger: :class:`Tracker` writes training runs to an MLflow store.

Layout of one experiment (``<experiment_prefix>-<experiment>``, named by the caller):

- a **parent run** per scenario + variant (:meth:`Tracker.start_run`) with the
  flattened config slices as params, tags (rule name, config hash, data
  version), the final model's per-epoch ``train_loss``/``test_loss``, test
  metrics (``mae_x/y/z/vec``, ``rmse_x/y/z/vec`` in N, ``accuracy_pct``),
  ``cv_mse``, figures, the model bundle (artifact ``force_model/``) and an
  MLflow pyfunc model (:meth:`Tracker.log_force_model`, see
  :mod:`liverforce.tracking.model`);
- a **nested run** per Ax trial (:meth:`Tracker.log_trial`; tag
  ``mlflow.parentRunId``) with the trial's hyper-parameters, per-epoch
  fold-mean ``train_loss`` / ``val_loss``, per-fold MSE and ``cv_mse``.

Runs are addressed by id through ``MlflowClient`` (no global active run), so
one process may log several runs safely. Every store call goes through
:func:`~liverforce.tracking.store.with_retry`; opening an experiment closes the
runs that dead processes of this host left ``RUNNING``
(:func:`~liverforce.tracking.store.close_stale_runs`).

Training code reaches the tracker by duck typing (``tracker.start_run``,
``tracker.log_metrics`` ...): :mod:`liverforce.learn` never imports this module.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any, Callable

import mlflow
from mlflow.entities import Metric, Param
from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient

from liverforce.tracking.store import T, close_stale_runs, ensure_store, owner_tags, sqlite_path, with_retry

PARENT_TAG = "mlflow.parentRunId"
_MAX_BATCH = 900  # MLflow log_batch accepts up to 1000 metrics


def _param_value(v: Any) -> str:
    s = str(v)
    return s if len(s) <= 6000 else s[:5997] + "..."


def _finite(metrics: dict) -> dict[str, float]:
    return {k: float(v) for k, v in metrics.items() if v is not None and math.isfinite(float(v))}


class Tracker:
    """Log training runs to MLflow (parent run per scenario + variant, nested runs per trial).

    Parameters
    ----------
    uri : str
        Tracking URI, e.g. ``sqlite:///results/mlflow.db``.
    experiment_name : str
        Created if missing.
    artifact_root : path, optional
        Where artifacts of a *new* experiment go; default ``<db folder>/mlartifacts``
        for SQLite (MLflow's default would be ``./mlruns`` of the working directory).
    retries, backoff_s : int, float
        Lock-retry policy (:func:`~liverforce.tracking.store.with_retry`).
    """

    def __init__(self, uri: str, experiment_name: str, *, artifact_root: str | Path | None = None,
                 retries: int = 12, backoff_s: float = 0.1):
        self.uri = uri
        self.experiment_name = experiment_name
        self.retries, self.backoff_s = retries, backoff_s
        ensure_store(uri)
        self.client = MlflowClient(tracking_uri=uri)
        db = sqlite_path(uri)
        if artifact_root is None and db is not None:
            artifact_root = db.parent / "mlartifacts"
        exp = self._call(self.client.get_experiment_by_name, experiment_name)
        if exp is None:
            location = None
            if artifact_root is not None:
                safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in experiment_name)
                location = (Path(artifact_root).resolve() / safe).as_uri()
            try:
                self.experiment_id = self._call(self.client.create_experiment, experiment_name,
                                                artifact_location=location)
            except MlflowException:  # created meanwhile by a parallel job
                exp = self._call(self.client.get_experiment_by_name, experiment_name)
                if exp is None:
                    raise
                self.experiment_id = exp.experiment_id
        else:
            self.experiment_id = exp.experiment_id
        self.close_stale_runs()

    def _call(self, fn: Callable[..., T], *args, **kwargs) -> T:
        return with_retry(fn, *args, retries=self.retries, backoff_s=self.backoff_s, **kwargs)

    # ------------------------------------------------------------------
    def start_run(self, run_name: str, *, params: dict | None = None, tags: dict | None = None,
                  parent_run_id: str | None = None) -> str:
        """Create a run (nested under ``parent_run_id`` if given); returns its id."""
        all_tags = {k: str(v) for k, v in (tags or {}).items()}
        for k, v in owner_tags().items():
            all_tags.setdefault(k, v)
        if parent_run_id:
            all_tags[PARENT_TAG] = parent_run_id
        run = self._call(self.client.create_run, self.experiment_id, tags=all_tags, run_name=run_name)
        run_id = run.info.run_id
        if params:
            self.log_params(run_id, params)
        return run_id

    def close_stale_runs(self) -> list[str]:
        """Mark ``KILLED`` the runs left ``RUNNING`` by processes of this host that no longer exist.

        Returns the ids of the runs it closed. Runs without host/pid tags, of
        another host, or of a live process are left alone.
        """
        return close_stale_runs(self.client, self.experiment_id, call=self._call)

    def log_params(self, run_id: str, params: dict) -> None:
        items = [Param(str(k), _param_value(v)) for k, v in params.items()]
        for i in range(0, len(items), 100):
            self._call(self.client.log_batch, run_id, params=items[i:i + 100])

    def log_metrics(self, run_id: str, metrics: dict, step: int = 0) -> None:
        ts = int(time.time() * 1000)
        items = [Metric(k, v, ts, step) for k, v in _finite(metrics).items()]
        for i in range(0, len(items), _MAX_BATCH):
            self._call(self.client.log_batch, run_id, metrics=items[i:i + _MAX_BATCH])

    def log_history(self, run_id: str, history: dict[str, list[float]]) -> None:
        """Per-epoch series, ``step`` = epoch."""
        ts = int(time.time() * 1000)
        items = [Metric(k, float(v), ts, step) for k, vals in history.items()
                 for step, v in enumerate(vals) if v is not None and math.isfinite(float(v))]
        for i in range(0, len(items), _MAX_BATCH):
            self._call(self.client.log_batch, run_id, metrics=items[i:i + _MAX_BATCH])

    def log_trial(self, parent_run_id: str, trial) -> str:
        """One Ax trial (:class:`liverforce.learn.tune.TrialReport`) as a nested run; returns its id."""
        run_id = self.start_run(
            f"trial-{trial.index:03d}",
            params=dict(trial.params),
            tags={"trial_index": trial.index, "trial_status": trial.status},
            parent_run_id=parent_run_id,
        )
        self.log_history(run_id, trial.history)
        metrics = {"cv_mse": trial.cv_mse, "trial_seconds": trial.seconds}
        metrics.update({f"cv_mse_fold{k}": v for k, v in enumerate(trial.fold_mse)})
        self.log_metrics(run_id, metrics)
        if trial.error:
            self._call(self.client.set_tag, run_id, "error", trial.error[:5000])
        self.end_run(run_id, status="FINISHED" if trial.status == "completed" else "FAILED")
        return run_id

    def log_artifact(self, run_id: str, path: str | Path, artifact_path: str | None = None) -> None:
        self._call(self.client.log_artifact, run_id, str(path), artifact_path)

    def log_artifacts(self, run_id: str, local_dir: str | Path, artifact_path: str | None = None) -> None:
        self._call(self.client.log_artifacts, run_id, str(local_dir), artifact_path)

    def log_dict(self, run_id: str, obj: dict, artifact_file: str) -> None:
        """``obj`` as the JSON artifact ``artifact_file`` (e.g. ``training_provenance.json``) of run ``run_id``."""
        self._call(self.client.log_dict, run_id, obj, artifact_file)

    def log_force_model(self, run_id: str, model_dir: str | Path, example_arrays: dict) -> str:
        """Log the bundle as an MLflow pyfunc model of run ``run_id`` (signature + input example).

        Resumes the run and leaves it ``FINISHED``: call it last, :meth:`end_run`
        then sets the final status. Returns the model URI ``runs:/<run_id>/model``
        (:func:`liverforce.tracking.model.log_force_model`).
        """
        from liverforce.tracking.model import log_force_model  # torch + serving: only when a model is logged

        return log_force_model(self.uri, run_id, model_dir, example_arrays, call=self._call)

    def register_force_model(self, model_uri: str, name: str) -> str:
        """Register a logged model (e.g. ``runs:/<run_id>/model``) under ``name``; returns the new version."""
        def _register():
            mlflow.set_tracking_uri(self.uri)
            mlflow.set_registry_uri(self.uri)
            return mlflow.register_model(model_uri, name)

        return str(self._call(_register).version)

    def end_run(self, run_id: str, status: str = "FINISHED") -> None:
        self._call(self.client.set_terminated, run_id, status)

    def nested_runs(self, parent_run_id: str) -> list:
        """The runs nested under ``parent_run_id`` (e.g. the Ax trials)."""
        return self._call(
            self.client.search_runs, [self.experiment_id],
            filter_string=f"tags.`{PARENT_TAG}` = '{parent_run_id}'", max_results=10000,
        )
