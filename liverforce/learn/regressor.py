"""The force regressor: an MLP from [code, state vector] to the local force.

``n_layers`` hidden blocks ``Linear(width) -> ReLU -> Dropout(p)`` and a
linear output of 3 (the standardised local force ``(F.t1, F.t2, F.n)``),
trained with Adam on the MSE (:func:`liverforce.learn.torchutil.train_loop`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import nn

from liverforce.learn.torchutil import EpochCallback, forward_numpy, train_loop


@dataclass(frozen=True)
class RegressorSpec:
    """Architecture of the MLP (JSON-serialisable)."""

    n_inputs: int
    hidden: tuple[int, ...]
    dropout: float
    n_outputs: int = 3

    def to_dict(self) -> dict:
        d = asdict(self)
        d["hidden"] = list(self.hidden)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "RegressorSpec":
        return cls(int(d["n_inputs"]), tuple(int(h) for h in d["hidden"]), float(d["dropout"]), int(d["n_outputs"]))


def build_mlp(spec: RegressorSpec) -> nn.Sequential:
    layers: list[nn.Module] = []
    d = spec.n_inputs
    for width in spec.hidden:
        layers += [nn.Linear(d, width), nn.ReLU()]
        if spec.dropout > 0:
            layers.append(nn.Dropout(spec.dropout))
        d = width
    layers.append(nn.Linear(d, spec.n_outputs))
    return nn.Sequential(*layers)


@dataclass(frozen=True)
class FitParams:
    """Training hyper-parameters of the regressor (the Ax search space lives in :mod:`.tune`)."""

    lr: float
    batch_size: int
    epochs: int
    weight_decay: float = 0.0


def fit_regressor(
    z: np.ndarray,
    y: np.ndarray,
    spec: RegressorSpec,
    fit: FitParams,
    *,
    seed: int,
    z_val: np.ndarray | None = None,
    y_val: np.ndarray | None = None,
    on_epoch: EpochCallback | None = None,
) -> tuple[nn.Sequential, dict[str, list[float]]]:
    """Train the MLP; returns ``(net, history)`` with per-epoch ``train_loss``/``val_loss``."""
    torch.manual_seed(int(seed))
    net = build_mlp(spec)
    hist = train_loop(
        net, z, y, epochs=fit.epochs, lr=fit.lr, batch_size=fit.batch_size, seed=seed,
        weight_decay=fit.weight_decay, x_val=z_val, y_val=y_val, on_epoch=on_epoch,
    )
    return net, hist


def predict_regressor(net: nn.Module, z: np.ndarray) -> np.ndarray:
    return forward_numpy(net, z)
