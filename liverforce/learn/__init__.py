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

from liverforce.learn.metrics import force_metrics
from liverforce.learn.model import ForceModel, ModelFormatError

__all__ = ["ForceModel", "ModelFormatError", "force_metrics", "train_scenario"]


def __getattr__(name: str):  # lazy: importing the driver pulls in Ax only when needed
    if name == "train_scenario":
        from liverforce.learn.train import train_scenario

        return train_scenario
    raise AttributeError(name)
