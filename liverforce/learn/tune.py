"""Ax Bayesian optimisation of the regressor's hyper-parameters with k-fold CV.

Search space (default; ``tune.space`` may override any entry):

==========  ==========================================  =====
name        range                                        type
==========  ==========================================  =====
lr          [1e-4, 1e-2], log scale                      float
dropout     [0, 0.5]                                     float
n_layers    [1, 4]                                       int
width       {16, 32, 64, 128, 256} (ordered choice)      int
batch_size  {16, 32, 64, 128} (ordered choice)           int
==========  ==========================================  =====

The objective is the k-fold CV mean squared error of the standardised local
force (lower is better). The first ``sobol_trials`` trials are quasi-random
(Sobol, the first at the centre of the space), the rest come from Ax's GP
("fast" generation strategy). The best trial is the one with the lowest
*observed* CV MSE (ties: the earlier trial). Every finished trial is handed to
``on_trial`` (e.g. a tracker writing a nested MLflow run) — this module never
imports mlflow.

Uses the Ax 1.3 API: ``Client``, ``RangeParameterConfig``,
``ChoiceParameterConfig``, ``get_next_trials``, ``complete_trial``.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from liverforce.learn.regressor import FitParams, RegressorSpec, fit_regressor, predict_regressor
from liverforce.seeds import derive

DEFAULT_SPACE: dict[str, dict] = {
    "lr": {"bounds": [1e-4, 1e-2], "scaling": "log"},
    "dropout": {"bounds": [0.0, 0.5]},
    "n_layers": {"bounds": [1, 4], "type": "int"},
    "width": {"values": [16, 32, 64, 128, 256]},
    "batch_size": {"values": [16, 32, 64, 128]},
}

OBJECTIVE = "cv_mse"


@dataclass
class TrialReport:
    """One finished Ax trial (what a tracker logs as a nested run)."""

    index: int
    params: dict
    cv_mse: float
    fold_mse: list[float]
    history: dict[str, list[float]]  # per-epoch losses, mean over folds
    seconds: float
    status: str = "completed"  # or "failed"
    error: str = ""


@dataclass
class TuneResult:
    best_params: dict
    best_cv_mse: float
    best_trial: int
    trials: list[TrialReport] = field(default_factory=list)


@dataclass
class FoldData:
    """Scaled regressor inputs/targets of one CV fold (preprocessing fitted on the fold's train part)."""

    z_train: np.ndarray
    y_train: np.ndarray
    z_val: np.ndarray
    y_val: np.ndarray
    groups_train: np.ndarray | None = None  # case index of each training row (views of one case share it)
    columns: list | None = None  # GP ensemble: each member's input columns (liverforce.learn.model.member_columns)


def regressor_from_params(params: dict, n_inputs: int) -> RegressorSpec:
    """``n_layers`` hidden layers of ``width`` units, dropout ``dropout``; or the GP (``params["regressor"]: gp``)."""
    if params.get("regressor") == "gp":
        return RegressorSpec(n_inputs, (), 0.0, kind="gp")
    return RegressorSpec(n_inputs, tuple([int(params["width"])] * int(params["n_layers"])), float(params["dropout"]))


def _fit_of(params: dict, epochs: int, weight_decay: float) -> FitParams:
    """The fit settings of one parameterization: Ax's MLP values, or the GP's (``regressor: gp``)."""
    if params.get("regressor") == "gp":  # params: train.py's GP settings (liverforce.learn.regressor.fit_params)
        return FitParams(0.0, 1, 0, regressor="gp",
                         gp_max_points=int(params.get("max_points", FitParams.gp_max_points)),
                         gp_iterations=int(params.get("iterations", FitParams.gp_iterations)),
                         gp_kernel=str(params.get("kernel", FitParams.gp_kernel)),
                         gp_shape=None if params.get("shape") is None else float(params["shape"]),
                         gp_per_output=bool(params.get("per_output", FitParams.gp_per_output)),
                         gp_noise_floor=float(params.get("noise_floor", FitParams.gp_noise_floor)))
    return FitParams(lr=float(params["lr"]), batch_size=int(params["batch_size"]), epochs=int(epochs),
                     weight_decay=weight_decay)


def fold_seed(seed: int, k: int) -> int:
    """Seed of fold ``k``'s regressor fit in :func:`cv_score` and :func:`cv_force_mae` (:mod:`liverforce.seeds`)."""
    return derive(seed, "tune.fold", k)


def cv_score(
    folds: list[FoldData], params: dict, *, epochs: int, seed: int, weight_decay: float = 0.0
) -> tuple[float, list[float], dict[str, list[float]]]:
    """Train the regressor on each fold; returns ``(mean val MSE, per-fold MSE, mean history)``."""
    fold_mse, hists = [], []
    fit = _fit_of(params, epochs, weight_decay)
    for k, f in enumerate(folds):
        spec = regressor_from_params(params, f.z_train.shape[1])
        _, hist = fit_regressor(f.z_train, f.y_train, spec, fit, seed=fold_seed(seed, k), z_val=f.z_val,
                                y_val=f.y_val, groups=f.groups_train, columns=f.columns)
        fold_mse.append(hist["val_loss"][-1])
        hists.append(hist)
    history = {key: np.mean([h[key] for h in hists], axis=0).tolist() for key in ("train_loss", "val_loss")}
    return float(np.mean(fold_mse)), fold_mse, history


def cv_force_mae(
    folds: list[FoldData], to_newton: list[Callable[[np.ndarray], np.ndarray]], y_val_n: list[np.ndarray],
    params: dict, *, epochs: int, seed: int, weight_decay: float = 0.0, with_mse: bool = False,
) -> float | tuple[float, float]:
    """Mean over the folds of the validation MAE of the force vector in N, for one parameterization.

    The same fits as :func:`cv_score` (same seeds), scored in newtons: ``to_newton[k]``
    maps fold ``k``'s scaled regressor outputs back to local forces (N), ``y_val_n[k]``
    are its true local forces. Unlike the CV MSE of the scaled targets, this is
    comparable between variants (other scalings, with or without the state vector).
    ``with_mse``: also return the mean validation MSE of the scaled targets (what
    :func:`cv_score` returns first), from the same fits.
    """
    fit = _fit_of(params, epochs, weight_decay)
    maes, mses = [], []
    for k, f in enumerate(folds):
        spec = regressor_from_params(params, f.z_train.shape[1])
        net, _ = fit_regressor(f.z_train, f.y_train, spec, fit, seed=fold_seed(seed, k), groups=f.groups_train,
                               columns=f.columns)
        out = predict_regressor(net, f.z_val)
        maes.append(float(np.linalg.norm(to_newton[k](out) - y_val_n[k], axis=1).mean()))
        mses.append(float(np.mean((out - f.y_val) ** 2)))
    return (float(np.mean(maes)), float(np.mean(mses))) if with_mse else float(np.mean(maes))


def _parameter_configs(space: dict[str, dict]):
    from ax import ChoiceParameterConfig, RangeParameterConfig

    configs = []
    for name, spec in space.items():
        if "values" in spec:
            values = list(spec["values"])
            ptype = spec.get("type") or ("int" if all(isinstance(v, int) for v in values) else "float")
            configs.append(ChoiceParameterConfig(name=name, values=values, parameter_type=ptype, is_ordered=True))
        else:
            lo, hi = spec["bounds"]
            ptype = spec.get("type") or ("int" if isinstance(lo, int) and isinstance(hi, int) else "float")
            configs.append(RangeParameterConfig(name=name, bounds=(lo, hi), parameter_type=ptype,
                                                scaling=spec.get("scaling")))
    return configs


def quiet_ax() -> None:
    """Ax logs INFO lines for every trial; its logger ignores levels, use its own setter."""
    from ax.utils.common.logger import set_stderr_log_level

    set_stderr_log_level(logging.WARNING)


def tune(
    evaluate: Callable[[dict], tuple[float, list[float], dict[str, list[float]]]],
    *,
    trials: int,
    sobol_trials: int,
    seed: int,
    space: dict[str, dict] | None = None,
    on_trial: Callable[[TrialReport], None] | None = None,
) -> TuneResult:
    """Run ``trials`` Ax trials of ``evaluate(params) -> (cv_mse, fold_mse, history)``.

    Parameters
    ----------
    evaluate : callable
        Scores one parameterization (e.g. :func:`cv_score` bound to the folds).
    trials, sobol_trials : int
        Total trials and quasi-random initial trials (``tune.trials``,
        ``tune.sobol_trials``).
    seed : int
        Seeds Ax's Sobol sequence and model fitting.
    space : dict, optional
        Overrides of :data:`DEFAULT_SPACE` entries (same shape).
    on_trial : callable, optional
        Called with a :class:`TrialReport` after each trial (also failed ones).

    Raises
    ------
    RuntimeError
        If every trial failed.
    """
    from ax import Client

    quiet_ax()
    full_space = {**DEFAULT_SPACE, **(space or {})}
    ax_seed = derive(seed, "tune.ax")
    client = Client(random_seed=ax_seed)
    client.configure_experiment(parameters=_parameter_configs(full_space), name="liverforce_regressor")
    client.configure_optimization(objective=f"-{OBJECTIVE}")
    client.configure_generation_strategy(
        method="fast",
        initialization_budget=int(max(1, min(sobol_trials, trials))),
        initialization_random_seed=ax_seed,
    )
    reports: list[TrialReport] = []
    for _ in range(int(trials)):
        (index, params), = client.get_next_trials(max_trials=1).items()
        params = dict(params)
        t0 = time.perf_counter()
        try:
            cv_mse, fold_mse, history = evaluate(params)
            if not math.isfinite(cv_mse):
                raise FloatingPointError(f"CV MSE is {cv_mse}")
        except (FloatingPointError, RuntimeError, ValueError) as exc:
            client.mark_trial_failed(index, failed_reason=str(exc))
            report = TrialReport(index, params, float("nan"), [], {}, time.perf_counter() - t0, "failed", str(exc))
        else:
            client.complete_trial(index, raw_data={OBJECTIVE: float(cv_mse)})
            report = TrialReport(index, params, float(cv_mse), list(fold_mse), history, time.perf_counter() - t0)
        reports.append(report)
        if on_trial is not None:
            on_trial(report)
    done = [r for r in reports if r.status == "completed"]
    if not done:
        raise RuntimeError(f"all {len(reports)} tuning trials failed; first error: {reports[0].error}")
    best = min(done, key=lambda r: (r.cv_mse, r.index))
    return TuneResult(best.params, best.cv_mse, best.index, reports)
