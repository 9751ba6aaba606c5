"""Serving: predict the tool force from a trained model — Python, CLI, MLflow pyfunc, batches.

Public API
----------
- :class:`~liverforce.serve.predictor.Predictor` — load (a directory, or any
  reference through a ``fetch`` callable) and predict from (a) tracked ROI
  nodes, (b) an unordered point cloud, or input-contract arrays. Models logged
  to MLflow (run id, ``runs:/``/``models:/`` URI, registered name) load with
  :class:`liverforce.tracking.MlflowPredictor`: tracking builds on serving,
  serving never imports tracking.
- :class:`~liverforce.serve.preop.Preop` — the pre-operative context of one
  exertion point (from the undeformed surface or given directly).
- :class:`~liverforce.serve.compiled.CompiledROI` — the fixed-topology fast
  path (haptic rates).
- :func:`~liverforce.serve.batch.predict_shards` — whole shards/datasets to
  Parquet or CSV.
- :class:`~liverforce.serve.input_frame.InputFrame` — inputs in a lab's own frame and units (LPS, a 4x4,
  metres, or the liver's import record) to the model's RAS mm, and the force back.
- :class:`~liverforce.serve.errors.PredictionInputError` — every refused input.
- :func:`~liverforce.serve.cli.register` — the ``liverforce predict`` subcommand.
"""

from liverforce.serve.errors import PredictionInputError

__all__ = ["CompiledROI", "InputFrame", "Limits", "PredictionInputError", "Predictor", "Preop", "TrainingScale"]

_LAZY = {
    "CompiledROI": "liverforce.serve.compiled",
    "InputFrame": "liverforce.serve.input_frame",
    "Limits": "liverforce.serve.checks",
    "TrainingScale": "liverforce.serve.checks",
    "Predictor": "liverforce.serve.predictor",
    "Preop": "liverforce.serve.preop",
}


def __getattr__(name: str):  # lazy: `liverforce.serve.cli` is imported by the main CLI without torch
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(name)
