"""MLflow tracking — the only package that imports ``mlflow``; one job per module.

- :mod:`~liverforce.tracking.store` — the store: SQLite lock retries
  (:func:`with_retry`), one-time creation (:func:`ensure_store`), runs left
  ``RUNNING`` by dead processes (:func:`~liverforce.tracking.store.close_stale_runs`);
- :mod:`~liverforce.tracking.runs` — the run logger :class:`Tracker` (parent
  run per scenario + variant, nested run per Ax trial);
- :mod:`~liverforce.tracking.model` — force models in MLflow: the pyfunc
  wrapper, logging, download (:func:`download_force_model`) and
  :class:`MlflowPredictor` (a serving predictor that loads run ids, ``runs:/``
  / ``models:/`` URIs and registered names).

Import layers: ``tracking.model`` builds on :mod:`liverforce.serve` and
:mod:`liverforce.learn`; neither imports tracking (training takes a tracker by
duck typing, serving takes a ``fetch`` callable). The names of
:mod:`~liverforce.tracking.model` load on first use, so ``from liverforce.tracking
import ensure_store`` (the Snakefile) or ``Tracker`` imports neither torch nor
the serving layer.
"""

import os

# artifact downloads (model loading) print progress bars by default: keep job logs readable
os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")

from liverforce.tracking.runs import PARENT_TAG, Tracker  # noqa: E402
from liverforce.tracking.store import HOST_TAG, PID_TAG, ensure_store, is_lock_error, sqlite_path, with_retry  # noqa: E402

__all__ = [
    "ForceModelPyfunc", "HOST_TAG", "MODEL_NAME", "MlflowPredictor", "OUTPUT_COLUMNS", "PARENT_TAG", "PID_TAG",
    "PyfuncInputError", "Tracker", "arrays_to_frame", "download_force_model", "ensure_store", "fetch_force_model",
    "frame_to_arrays", "is_lock_error", "load_pyfunc", "predict_pyfunc", "resolve_model_uri", "sqlite_path",
    "with_retry",
]

_MODEL_NAMES = {
    "ForceModelPyfunc", "MODEL_NAME", "MlflowPredictor", "OUTPUT_COLUMNS", "PyfuncInputError", "arrays_to_frame",
    "download_force_model", "fetch_force_model", "frame_to_arrays", "load_pyfunc", "predict_pyfunc",
    "resolve_model_uri",
}


def __getattr__(name: str):  # lazy: liverforce.tracking.model imports torch and the serving layer
    if name in _MODEL_NAMES:
        from liverforce.tracking import model

        return getattr(model, name)
    raise AttributeError(f"module 'liverforce.tracking' has no attribute {name!r}")
