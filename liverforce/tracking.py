"""MLflow tracking for training runs — the only module that imports mlflow.

Layout of one experiment (``<experiment_prefix>-<experiment>``, named by the caller):

- a **parent run** per scenario + variant (``start_run``) with the flattened
  config slices as params, tags (rule name, config hash, data version), the
  final model's per-epoch ``train_loss``/``test_loss``, test metrics
  (``mae_x/y/z/vec``, ``rmse_x/y/z/vec`` in N, ``accuracy_pct``), ``cv_mse``,
  figures, the model bundle (artifact ``force_model/``) and an MLflow pyfunc
  model (reloadable by run id: ``mlflow.pyfunc.load_model(f"runs:/{run_id}/model")``),
  logged as "models from code" (no cloudpickle) with a signature and an input
  example, so ``mlflow models serve -m runs:/<id>/model --host 127.0.0.1 --env-manager local``
  serves it; its ``predict`` runs the serving checks of :mod:`liverforce.serve`
  (a refused row becomes HTTP 400 with the reason);
- a **nested run** per Ax trial (``log_trial``; tag ``mlflow.parentRunId``)
  with the trial's hyper-parameters, per-epoch fold-mean ``train_loss`` /
  ``val_loss``, per-fold MSE and ``cv_mse``.

SQLite stores take one writer at a time: every MLflow call goes through
:func:`with_retry`, which retries with exponential back-off (plus jitter)
while the error says the database is locked. Create a fresh store once with
:func:`ensure_store` before parallel jobs start (two processes creating the
schema at once fail); it is idempotent and serialised by a lock file.

Runs are addressed by id through ``MlflowClient`` (no global active run), so
one process may log several runs safely.

Every run carries the host and process id that created it (tags
``liverforce.host``, ``liverforce.pid``). A run left ``RUNNING`` by a process
that no longer exists on this host (a SIGKILLed job) is marked ``KILLED`` when
the next :class:`Tracker` opens the experiment (:meth:`Tracker.close_stale_runs`),
so a resumed workflow leaves no phantom running runs; runs of live processes
and of other hosts are never touched.

For serving, :func:`download_force_model` fetches the bundle of a logged model
(run id, ``runs:/``/``models:/`` URI or registered name) for
:meth:`liverforce.learn.model.ForceModel.load` (nothing unpickled), and
:meth:`Tracker.register_force_model` registers a logged model under a name.
"""

from __future__ import annotations

import fcntl
import math
import os
import random
import re
import socket
import tempfile
import time
from pathlib import Path
from typing import Any, Callable, TypeVar

import mlflow
import mlflow.artifacts
import mlflow.pyfunc
import numpy as np
import pandas as pd
from mlflow.entities import Metric, Param
from mlflow.exceptions import MlflowException
from mlflow.protos.databricks_pb2 import INVALID_PARAMETER_VALUE
from mlflow.models import infer_signature
from mlflow.types import ColSpec, Schema
from mlflow.tracking import MlflowClient

from liverforce.serve.errors import PredictionInputError

T = TypeVar("T")

# artifact downloads (model loading) print progress bars by default: keep job logs readable
os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")

PARENT_TAG = "mlflow.parentRunId"
HOST_TAG, PID_TAG = "liverforce.host", "liverforce.pid"
MODEL_NAME = "model"
#: columns of the pyfunc output frame (source-frame force, N)
OUTPUT_COLUMNS = ("fx_n", "fy_n", "fz_n")
_ROI_KEYS = ("roi_undeformed_mm", "roi_deformed_mm")
_MAX_BATCH = 900  # MLflow log_batch accepts up to 1000 metrics


# --------------------------------------------------------------------------
# retries and store creation
# --------------------------------------------------------------------------


def is_lock_error(exc: BaseException) -> bool:
    """True if ``exc`` (or an exception it wraps) says the SQLite database is locked/busy."""
    seen = 0
    e: BaseException | None = exc
    while e is not None and seen < 10:
        msg = str(e).lower()
        if "database is locked" in msg or "database table is locked" in msg or "database is busy" in msg:
            return True
        if type(e).__name__ == "OperationalError" and "locked" in msg:
            return True
        e = e.__cause__ or e.__context__
        seen += 1
    return False


def with_retry(fn: Callable[..., T], *args, retries: int = 12, backoff_s: float = 0.1, **kwargs) -> T:
    """Call ``fn(*args, **kwargs)``, retrying lock errors with back-off ``backoff_s * 2^i`` (max 5 s).

    Other exceptions propagate at once; after ``retries`` lock errors the
    last one propagates.
    """
    delay = backoff_s
    for attempt in range(retries + 1):
        try:
            return fn(*args, **kwargs)
        except Exception as exc:  # noqa: BLE001 - filtered by is_lock_error, others re-raised
            if attempt == retries or not is_lock_error(exc):
                raise
            time.sleep(delay * (1.0 + random.random()))
            delay = min(2.0 * delay, 5.0)
    raise AssertionError("unreachable")


def sqlite_path(uri: str) -> Path | None:
    """The database file of a ``sqlite:///`` URI (``None`` for other stores)."""
    if not uri.startswith("sqlite:///"):
        return None
    return Path(uri[len("sqlite:///"):])


def ensure_store(uri: str) -> None:
    """Create the tracking store behind ``uri`` once (idempotent, safe across processes).

    For SQLite the schema is created under an exclusive lock file
    (``<db>.lock``), so parallel jobs never race to create tables.
    """
    db = sqlite_path(uri)
    if db is None:
        with_retry(MlflowClient(tracking_uri=uri).search_experiments, max_results=1)
        return
    db.parent.mkdir(parents=True, exist_ok=True)
    with open(db.with_name(db.name + ".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            with_retry(MlflowClient(tracking_uri=uri).search_experiments, max_results=1)
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def _param_value(v: Any) -> str:
    s = str(v)
    return s if len(s) <= 6000 else s[:5997] + "..."


def _finite(metrics: dict) -> dict[str, float]:
    return {k: float(v) for k, v in metrics.items() if v is not None and math.isfinite(float(v))}


# --------------------------------------------------------------------------
# pyfunc wrapper: DataFrame <-> input-contract arrays
# --------------------------------------------------------------------------


def arrays_to_frame(arrays: dict, keys: tuple[str, ...] | list[str]) -> pd.DataFrame:
    """One row per case: vectors as lists of floats, ROI clouds flattened to ``3 k`` floats, ids as str."""
    cols = {}
    for k in keys:
        v = arrays[k]
        if k in _ROI_KEYS:
            cols[k] = [np.asarray(a, dtype=np.float64).ravel().tolist() for a in v]
        elif k in ("case_id", "geometry_id"):
            cols[k] = [str(x) for x in v]
        else:
            a = np.asarray(v, dtype=np.float64)
            cols[k] = [row.tolist() for row in a.reshape(len(a), -1)]
    return pd.DataFrame(cols)


def frame_to_arrays(df: pd.DataFrame) -> dict:
    """Inverse of :func:`arrays_to_frame`."""
    out: dict = {}
    for k in df.columns:
        col = list(df[k])
        if k in _ROI_KEYS:
            out[k] = [np.asarray(x, dtype=np.float64).reshape(-1, 3) for x in col]
        elif k in ("case_id", "geometry_id"):
            out[k] = np.array([str(x) for x in col], dtype=object)
        else:
            out[k] = np.stack([np.asarray(x, dtype=np.float64).ravel() for x in col])
    return out


class ForceModelPyfunc(mlflow.pyfunc.PythonModel):
    """MLflow pyfunc around a :class:`liverforce.learn.model.ForceModel` bundle (artifact ``force_model``).

    Input: a DataFrame, one row per case, columns as :func:`arrays_to_frame`
    writes them. Output: a DataFrame ``fx_n, fy_n, fz_n`` (source frame, N).
    Param ``observation_seed`` (int, -1 = none) draws the stochastic
    observation model as in evaluation.
    """

    def load_context(self, context) -> None:
        from liverforce.learn.model import ForceModel

        self.model = ForceModel.load(context.artifacts["force_model"])

    def predict(self, context, model_input: pd.DataFrame, params: dict | None = None) -> pd.DataFrame:
        from liverforce.serve.predictor import Predictor

        seed = int((params or {}).get("observation_seed", -1))
        arrays = frame_to_arrays(pd.DataFrame(model_input))
        # the serving checks (shape, NaN/inf, units against the training scale, exertion point on the
        # surface) refuse bad rows with a PredictionInputError naming the row; then the reference path
        try:
            force = Predictor(self.model).predict_arrays(arrays, observation_seed=None if seed < 0 else seed)
        except PredictionInputError as exc:
            raise PyfuncInputError(str(exc)) from exc
        return pd.DataFrame(force, columns=list(OUTPUT_COLUMNS))


class PyfuncInputError(PredictionInputError, MlflowException):
    """A refused input inside the pyfunc: a :class:`PredictionInputError` that MLflow's scoring
    server answers with HTTP 400 and this message (other exceptions become a generic error)."""

    def __init__(self, message: str):
        MlflowException.__init__(self, message, error_code=INVALID_PARAMETER_VALUE)


#: MLflow "models from code" entry: logged instead of a cloudpickled object, so that loading or
#: serving the pyfunc model runs this file (an import of liverforce) and unpickles nothing
_PYFUNC_CODE = '''"""MLflow pyfunc entry of a liverforce force model (models from code; no pickle)."""
import mlflow

from liverforce.tracking import ForceModelPyfunc

mlflow.models.set_model(ForceModelPyfunc())
'''


# --------------------------------------------------------------------------
# the tracker
# --------------------------------------------------------------------------


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
        Lock-retry policy (:func:`with_retry`).
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
        all_tags.setdefault(HOST_TAG, socket.gethostname())
        all_tags.setdefault(PID_TAG, str(os.getpid()))
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
        host = socket.gethostname()
        try:
            running = self._call(self.client.search_runs, [self.experiment_id],
                                 filter_string="attributes.status = 'RUNNING'", max_results=10000)
        except MlflowException:
            return []
        closed = []
        for run in running:
            tags = run.data.tags
            if tags.get(HOST_TAG) != host or not str(tags.get(PID_TAG, "")).isdigit():
                continue
            if _pid_alive(int(tags[PID_TAG])):
                continue
            self._call(self.client.set_tag, run.info.run_id, "liverforce.stale",
                       f"process {tags[PID_TAG]} on {host} ended without closing the run")
            self._call(self.client.set_terminated, run.info.run_id, "KILLED")
            closed.append(run.info.run_id)
        return closed

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

    def log_force_model(self, run_id: str, model_dir: str | Path, example_arrays: dict) -> str:
        """Log the bundle as an MLflow pyfunc model of run ``run_id`` (signature + input example).

        Returns the model URI ``runs:/<run_id>/model``.
        """
        from liverforce.learn.model import ForceModel

        model = ForceModel.load(model_dir)
        keys = list(model.required_inputs())
        if "case_id" in example_arrays:
            keys.insert(0, "case_id")
        example = arrays_to_frame(example_arrays, keys)
        output = pd.DataFrame(model.predict(frame_to_arrays(example)), columns=list(OUTPUT_COLUMNS))
        signature = infer_signature(example, output, params={"observation_seed": -1})
        # case_id only seeds the per-case observation noise: optional
        signature.inputs = Schema([
            ColSpec(c.type, c.name, required=c.name != "case_id") for c in signature.inputs.inputs
        ])

        def _log():
            mlflow.set_tracking_uri(self.uri)
            with tempfile.TemporaryDirectory(prefix="liverforce-pyfunc-") as tmp:
                code = Path(tmp) / "liverforce_force_model.py"
                code.write_text(_PYFUNC_CODE)
                # resumes the run; leaving the block marks it FINISHED (FAILED on error) —
                # call this last, end_run then sets the final status
                with mlflow.start_run(run_id=run_id):
                    mlflow.pyfunc.log_model(
                        name=MODEL_NAME,
                        python_model=str(code),
                        artifacts={"force_model": str(model_dir)},
                        signature=signature,
                        input_example=example,
                        pip_requirements=_requirements(),
                    )

        self._call(_log)
        return f"runs:/{run_id}/{MODEL_NAME}"

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


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def _requirements() -> list[str]:
    from importlib.metadata import PackageNotFoundError, version

    reqs = []
    for pkg in ("torch", "numpy", "scipy", "pandas", "liverforce"):
        try:
            reqs.append(f"{pkg}=={version(pkg).split('+')[0]}")
        except PackageNotFoundError:
            continue
    return reqs


def load_pyfunc(model_uri: str, tracking_uri: str | None = None):
    """``mlflow.pyfunc.load_model`` (e.g. ``runs:/<run_id>/model``)."""
    if tracking_uri:
        mlflow.set_tracking_uri(tracking_uri)
    return mlflow.pyfunc.load_model(model_uri)


def resolve_model_uri(ref: str) -> str:
    """Run id (32 hex) -> ``runs:/<id>/model``; a name without scheme -> ``models:/<name>/latest``; URIs as given."""
    if re.fullmatch(r"[0-9a-f]{32}", ref):
        return f"runs:/{ref}/{MODEL_NAME}"
    if ":/" in ref:
        return ref
    return f"models:/{ref}/latest"


def download_force_model(model_ref: str, dst_dir: str | Path | None = None, tracking_uri: str | None = None) -> Path:
    """Download a logged force model and return its liverforce bundle directory.

    Parameters
    ----------
    model_ref : str
        ``runs:/<run_id>/model``, a bare run id, ``models:/<name>/<version>``,
        ``models:/<name>@<alias>`` or a registered model name (latest version).
    dst_dir : path, optional
        Where to download (default: a new temporary folder).
    tracking_uri : str, optional
        Tracking (and registry) store; default: MLflow's current one.

    Returns
    -------
    Path
        The bundle (``model.json`` + weights) inside the downloaded pyfunc
        model; load it with :meth:`liverforce.learn.model.ForceModel.load`,
        which never unpickles (the pyfunc's own code is not executed).
    """
    uri = resolve_model_uri(model_ref)
    if tracking_uri:
        mlflow.set_tracking_uri(tracking_uri)
        mlflow.set_registry_uri(tracking_uri)
    dst = Path(dst_dir) if dst_dir is not None else Path(tempfile.mkdtemp(prefix="liverforce-model-"))
    dst.mkdir(parents=True, exist_ok=True)
    local = Path(with_retry(mlflow.artifacts.download_artifacts, artifact_uri=uri, dst_path=str(dst)))
    hits = sorted(local.glob("artifacts/*/model.json")) or sorted(local.glob("**/model.json"))
    if not hits:
        raise FileNotFoundError(f"{uri}: the logged model holds no liverforce bundle (artifacts/*/model.json)")
    return hits[0].parent


def predict_pyfunc(pyfunc_model, arrays: dict, observation_seed: int | None = None) -> np.ndarray:
    """Run a loaded pyfunc model on input-contract ``arrays``; returns ``(n, 3)`` N."""
    keys = [k for k in arrays if k in _pyfunc_inputs(pyfunc_model)]
    df = arrays_to_frame(arrays, keys)
    out = pyfunc_model.predict(df, params={"observation_seed": -1 if observation_seed is None else observation_seed})
    return np.asarray(pd.DataFrame(out)[list(OUTPUT_COLUMNS)], dtype=np.float64)


def _pyfunc_inputs(pyfunc_model) -> set[str]:
    schema = pyfunc_model.metadata.get_input_schema()
    return set(schema.input_names()) if schema is not None else set()
