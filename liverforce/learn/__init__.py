"""Learning stage: ROI representation, state vector, encoders, MLP regressor, CV + Ax tuning.

No mlflow import anywhere in this package: tracking reaches it through
callbacks and a duck-typed tracker (:mod:`liverforce.tracking`).

Public entry points
-------------------
- :func:`liverforce.learn.train.train_scenario` — the workflow's driver.
- :class:`liverforce.learn.model.ForceModel` — a fitted model; ``predict``,
  ``save``, ``load``.
- :func:`liverforce.learn.metrics.force_metrics`.
"""

__all__ = ["ForceModel", "ModelFormatError", "force_metrics", "train_scenario"]

_LAZY = {
    "ForceModel": "liverforce.learn.model",
    "ModelFormatError": "liverforce.learn.model",
    "force_metrics": "liverforce.learn.metrics",
    "train_scenario": "liverforce.learn.train",
}


def __getattr__(name: str):
    """Lazy exports: importing ``liverforce.learn.<light module>`` (e.g. ``names``, from the config
    check) must not load torch or Ax; the heavy modules load on first use of their names."""
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(name)
