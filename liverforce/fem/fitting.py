"""Least-squares fit of hyperelastic constants to stress–stretch data.

Data are nominal (engineering) stress in MPa versus stretch for the
incompressible test modes of :mod:`liverforce.fem.homogeneous`. The fit
minimises ``sum_i w_i (T_model(lam_i) - T_i)^2`` with
:func:`scipy.optimize.least_squares` and reports the normalised RMSE

.. math::

    \\mathrm{NRMSE} = \\frac{\\sqrt{\\frac{1}{n}\\sum_i (T_{model,i} - T_i)^2}}
    {\\max_i T_i - \\min_i T_i},

i.e. the root-mean-square error divided by the range of the data (over all
modes together, and per mode in ``nrmse_per_mode``).

Example
-------
>>> import numpy as np
>>> from liverforce.fem.materials import make_material
>>> from liverforce.fem.homogeneous import nominal_stress
>>> true = make_material("yeoh", {"C10": 1.6e-3, "C20": 12e-3, "C30": 5e-3}, nu=0.49)
>>> lam = np.linspace(0.7, 1.3, 25)
>>> fit = fit_material("yeoh", {"uniaxial": (lam, nominal_stress(true, "uniaxial", lam))})
>>> fit.nrmse < 1e-10
True
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
from scipy.optimize import least_squares

from .homogeneous import MODES, nominal_stress
from .materials import _MODELS, Material, _canonical, make_material

_DUMMY_BULK = 1.0  # the fit is incompressible; K does not enter nominal_stress


@dataclass
class FitResult:
    """Result of :func:`fit_material`.

    Attributes
    ----------
    model : canonical model name.
    params : fitted constants (MPa; Ogden alphas dimensionless).
    nrmse : RMSE / (max - min) of all data.
    nrmse_per_mode : the same per test mode.
    rmse_mpa : RMSE in MPa.
    success, message : from scipy's ``least_squares``.
    """

    model: str
    params: dict[str, float]
    nrmse: float
    nrmse_per_mode: dict[str, float]
    rmse_mpa: float
    success: bool
    message: str


def _param_names(model: str, n_ogden: int) -> list[str]:
    if model == "ogden":
        return [n for p in range(1, n_ogden + 1) for n in (f"mu{p}", f"alpha{p}")]
    return list(_MODELS[model].required)


def fit_material(
    model: str,
    data: Mapping[str, tuple[Sequence[float], Sequence[float]]],
    x0: Mapping[str, float] | None = None,
    n_ogden_terms: int = 2,
    weights: Mapping[str, float] | None = None,
) -> FitResult:
    """Fit a model's constants to nominal stress–stretch curves.

    Parameters
    ----------
    model : str
        A name accepted by :func:`~liverforce.fem.materials.make_material`.
    data : dict
        ``{mode: (stretch, nominal_stress_mpa)}`` with mode in
        ``uniaxial``, ``equibiaxial``, ``planar``.
    x0 : dict, optional
        Initial constants. Default: a linear least-squares solution for the
        invariant models (their nominal stress is linear in the constants);
        ``mu_p = mu/N``, ``alpha = 2, -2, 4, -4, ...`` for Ogden.
    n_ogden_terms : int
        Number of Ogden terms when ``x0`` is not given.
    weights : dict, optional
        Per-mode weights of the residuals (default 1).

    Returns
    -------
    FitResult
    """
    key = _canonical(model)
    items = []
    for mode, (lam, T) in data.items():
        if mode not in MODES:
            raise ValueError(f"unknown test mode {mode!r} in data; choose from {MODES}")
        lam, T = np.asarray(lam, float), np.asarray(T, float)
        if lam.shape != T.shape or lam.ndim != 1 or lam.size == 0:
            raise ValueError(f"data[{mode!r}]: stretch and stress must be equal-length 1-D arrays")
        if np.any(lam <= 0):
            raise ValueError(f"data[{mode!r}]: stretches must be positive")
        items.append((mode, (lam, T)))
    if not items:
        raise ValueError("data is empty: give at least one test mode")
    T_all = np.concatenate([T for _, (_, T) in items])
    w = np.concatenate(
        [np.full(lam.size, np.sqrt((weights or {}).get(mode, 1.0))) for mode, (lam, _) in items]
    )
    if x0 is not None:
        names = list(x0)
        x = np.array([x0[n] for n in names], float)
    else:
        n_og = n_ogden_terms
        names = _param_names(key, n_og)
        if key == "ogden":
            mu_est = _shear_estimate(items)
            alphas = [2.0 * (1 + p // 2) * (1 if p % 2 == 0 else -1) for p in range(n_og)]
            x = np.array(
                [v for a in alphas for v in (2.0 * mu_est / (n_og * a), a)], float
            )
        else:
            # nominal stress is linear in the constants: columns = unit constants
            cols = []
            for i in range(len(names)):
                e = np.zeros(len(names))
                e[i] = 1.0
                cols.append(_model_stress_unchecked(key, names, e, items))
            M = np.stack(cols, -1)
            x = np.linalg.lstsq(M * w[:, None], T_all * w, rcond=None)[0]

    def residual(x):
        try:
            r = _model_stress_unchecked(key, names, x, items) - T_all
        except (ValueError, FloatingPointError):
            return np.full(T_all.size, 1e3)
        return np.where(np.isfinite(r), r, 1e3) * w

    sol = least_squares(residual, x, method="lm" if T_all.size >= x.size else "trf",
                        xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=20000)
    params = dict(zip(names, map(float, sol.x)))
    pred = _model_stress_unchecked(key, names, sol.x, items)
    rng = float(T_all.max() - T_all.min()) or 1.0
    rmse = float(np.sqrt(np.mean((pred - T_all) ** 2)))
    per_mode, k = {}, 0
    for mode, (lam, T) in items:
        p = pred[k : k + lam.size]
        k += lam.size
        r = float(T.max() - T.min()) or 1.0
        per_mode[mode] = float(np.sqrt(np.mean((p - T) ** 2)) / r)
    return FitResult(key, params, rmse / rng, per_mode, rmse, bool(sol.success), str(sol.message))


def _model_stress_unchecked(model, names, x, items):
    """Nominal stress without the mu0 > 0 check (the optimiser may pass through it)."""
    params = dict(zip(names, map(float, x)))
    mat = Material(model=model, params=params, bulk=_DUMMY_BULK, mu0=1.0, _spec=_MODELS[model])
    return np.concatenate([nominal_stress(mat, mode, lam) for mode, (lam, _) in items])


def _shear_estimate(items) -> float:
    """Small-strain shear modulus from the data (neo-Hookean least squares)."""
    num = den = 0.0
    for mode, (lam, T) in items:
        mat = make_material("neo_hookean", {"C10": 0.5}, bulk_mpa=_DUMMY_BULK)  # mu = 1
        unit = nominal_stress(mat, mode, lam)
        num += float(unit @ T)
        den += float(unit @ unit)
    return max(num / den, 1e-12) if den > 0 else 1.0
