"""The force regressor: [code, state vector] -> the standardised local force ``(F.t1, F.t2, F.n)``.

``kind: mlp``: ``n_layers`` hidden blocks ``Linear(width) -> ReLU -> Dropout(p)``
and a linear output of 3, trained with Adam on the MSE
(:func:`liverforce.learn.torchutil.train_loop`).
``kind: gp``: an exact Gaussian process with a shared ARD kernel, fitted by its
marginal likelihood (:mod:`liverforce.learn.gp`); with ``columns`` (``model.gp.code_members``)
the mean of one such GP per column set (:class:`liverforce.learn.gp.GPEnsemble`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import nn

from liverforce.learn import names
from liverforce.learn.torchutil import EpochCallback, forward_numpy, train_loop


@dataclass(frozen=True)
class RegressorSpec:
    """Architecture of the MLP (JSON-serialisable)."""

    n_inputs: int
    hidden: tuple[int, ...]
    dropout: float
    n_outputs: int = 3
    kind: str = "mlp"  # mlp | gp

    def to_dict(self) -> dict:
        d = asdict(self)
        d["hidden"] = list(self.hidden)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "RegressorSpec":
        return cls(int(d["n_inputs"]), tuple(int(h) for h in d["hidden"]), float(d["dropout"]), int(d["n_outputs"]),
                   str(d.get("kind", "mlp")))


REGRESSORS = ("mlp", "gp")


def load_regressor(spec: RegressorSpec, state: dict) -> nn.Module:
    """The fitted regressor of a bundle from its spec and saved ``state_dict``."""
    if spec.kind == "gp":
        from liverforce.learn.gp import GPEnsemble, GPRegressor

        if GPEnsemble.is_state_dict(state):
            return GPEnsemble.from_state_dict(state).eval()
        return GPRegressor.from_state_dict(state).eval()
    net = build_mlp(spec)
    net.load_state_dict(state)
    return net.eval()


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
    regressor: str = "mlp"  # mlp | gp (model.regressor); gp reads only the gp_ fields below
    gp_max_points: int = 2000  # model.gp.max_points
    gp_iterations: int = 200  # model.gp.iterations
    gp_code_members: tuple[int, ...] = ()  # model.gp.code_members (PCA code sizes of a GP ensemble; () = one GP)
    gp_kernel: str = "rational_quadratic"  # model.gp.kernel (liverforce.learn.gp)
    gp_shape: float | None = 2.0  # model.gp.shape: the rational quadratic's a, None = fitted (unused by the SE)
    gp_per_output: bool = False  # model.gp.per_output: one kernel per force component
    gp_noise_floor: float = 0.0  # model.gp.noise_floor: the least noise variance (standardised targets)


def gp_code_members(model_cfg: dict) -> tuple[int, ...]:
    """The PCA code sizes of the GP ensemble a model config asks for (``model.gp.code_members``), sorted;
    ``()`` for one GP: no members listed, another regressor than the GP, or another encoder than PCA
    (only PCA codes are nested, so only they give the same model at several code sizes)."""
    if str(model_cfg.get("regressor", "mlp")) != "gp" or str(model_cfg.get("encoder", "pca")) != "pca":
        return ()
    try:
        return names.gp_code_members((model_cfg.get("gp") or {}).get("code_members"))
    except ValueError as exc:
        raise ValueError(f"model.gp.code_members: {exc}") from None


def fit_params(model_cfg: dict, *, lr: float, batch_size: int, epochs: int, weight_decay: float = 0.0) -> FitParams:
    """:class:`FitParams` with the regressor kind and GP settings of a model config slice."""
    kind = str(model_cfg.get("regressor", "mlp"))
    if kind not in REGRESSORS:
        raise ValueError(f"model.regressor: unknown '{kind}', choose one of {', '.join(REGRESSORS)}")
    gp = model_cfg.get("gp") or {}
    return FitParams(float(lr), int(batch_size), int(epochs), float(weight_decay), kind,
                     int(gp.get("max_points", FitParams.gp_max_points)),
                     int(gp.get("iterations", FitParams.gp_iterations)), gp_code_members(model_cfg),
                     *_kernel_settings(gp), bool(gp.get("per_output", FitParams.gp_per_output)),
                     float(gp.get("noise_floor", FitParams.gp_noise_floor)))


def _kernel_settings(gp: dict) -> tuple[str, float | None]:
    """``model.gp.kernel`` and ``model.gp.shape`` (None: fitted; None also for the squared exponential, which
    has no shape, so a model records none)."""
    kernel = str(gp.get("kernel", FitParams.gp_kernel))
    shape = gp.get("shape", FitParams.gp_shape)
    return kernel, None if shape is None or kernel == "squared_exponential" else float(shape)


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
    groups: np.ndarray | None = None,
    columns: list | None = None,
) -> tuple[nn.Sequential, dict[str, list[float]]]:
    """Train the regressor ``spec.kind``; returns ``(net, history)`` with ``train_loss``/``val_loss`` lists.

    MLP: one entry per epoch. GP: one entry (the MSE at the fitted hyper-parameters);
    ``history["gp"]`` holds :func:`liverforce.learn.gp.fit_gp`'s info. ``groups`` labels rows that are
    views of one case (GP: the hyper-parameters' likelihood uses one row per case; MLP: unused).
    ``columns`` (GP only): one index array of ``z``'s columns per member of a GP ensemble
    (:func:`liverforce.learn.gp.fit_gp_ensemble`); None: one GP on every column.
    """
    if spec.kind == "gp":
        from liverforce.learn.gp import fit_gp, fit_gp_ensemble

        settings = dict(seed=seed, max_points=fit.gp_max_points, iterations=fit.gp_iterations, groups=groups,
                        kernel=fit.gp_kernel, shape=fit.gp_shape, per_output=fit.gp_per_output,
                        noise_floor=fit.gp_noise_floor)
        gp, info = fit_gp_ensemble(z, y, columns, **settings) if columns else fit_gp(z, y, **settings)
        hist = {"train_loss": [float(np.mean((forward_numpy(gp, z) - y) ** 2))], "val_loss": [], "gp": info}
        if z_val is not None and y_val is not None:
            hist["val_loss"] = [float(np.mean((forward_numpy(gp, z_val) - y_val) ** 2))]
        if on_epoch is not None:
            on_epoch(0, hist["train_loss"][0], hist["val_loss"][0] if hist["val_loss"] else None)
        return gp, hist
    if spec.kind != "mlp":
        raise ValueError(f"unknown regressor kind '{spec.kind}': choose one of {', '.join(REGRESSORS)}")
    torch.manual_seed(int(seed))
    net = build_mlp(spec)
    hist = train_loop(
        net, z, y, epochs=fit.epochs, lr=fit.lr, batch_size=fit.batch_size, seed=seed,
        weight_decay=fit.weight_decay, x_val=z_val, y_val=y_val, on_epoch=on_epoch,
    )
    return net, hist


def predict_regressor(net: nn.Module, z: np.ndarray) -> np.ndarray:
    return forward_numpy(net, z)
