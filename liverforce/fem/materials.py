"""Nearly incompressible isotropic hyperelastic materials (units: MPa = N/mm²).

Each model is a pure function of the isochoric invariants (or, for Ogden, of
the isochoric principal stretches) with its equation in the docstring. The
strain energy density is split additively

.. math::

    W(F) = \\bar W(\\bar I_1, \\bar I_2) + U(J), \\qquad
    \\bar I_1 = J^{-2/3} I_1, \\quad \\bar I_2 = J^{-4/3} I_2, \\quad
    U(J) = \\frac{K}{2} (J - 1)^2,

i.e. ANSYS' ``(1/d)(J-1)^2`` with ``d = 2/K``. ``K`` is given directly or
from an initial Poisson ratio, ``K = 2 mu0 (1 + nu) / (3 (1 - 2 nu))`` with
``mu0`` the model's initial shear modulus. Stress and tangent come from the
chain rule over :mod:`liverforce.fem.kinematics`.

Example
-------
>>> import numpy as np
>>> mat = make_material("yeoh", {"C10": 1.61e-3, "C20": 12.5e-3, "C30": 5.31e-3}, nu=0.49)
>>> round(mat.mu0, 5), round(mat.bulk, 4)
(0.00322, 0.1599)
>>> bool(np.abs(mat.stress(np.eye(3))).max() < 1e-15)
True
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Callable, Mapping

import numpy as np

from . import kinematics as kin

# --------------------------------------------------------------------------
# Isochoric energies: pure functions returning W, (W_1, W_2), (W_11, W_12, W_22)
# with W_a = dW/dI_a-bar.
# --------------------------------------------------------------------------


def mooney_rivlin(I1b, I2b, C10=0.0, C01=0.0, C20=0.0, C11=0.0, C02=0.0):
    """Mooney–Rivlin (2, 3 or 5 parameters).

    .. math::

        \\bar W = C_{10}(\\bar I_1-3) + C_{01}(\\bar I_2-3) + C_{20}(\\bar I_1-3)^2
        + C_{11}(\\bar I_1-3)(\\bar I_2-3) + C_{02}(\\bar I_2-3)^2

    Initial shear modulus ``mu0 = 2 (C10 + C01)``.
    """
    a, b = I1b - 3.0, I2b - 3.0
    W = C10 * a + C01 * b + C20 * a * a + C11 * a * b + C02 * b * b
    W1 = C10 + 2.0 * C20 * a + C11 * b
    W2 = C01 + C11 * a + 2.0 * C02 * b
    return W, (W1, W2), (2.0 * C20 + 0 * a, C11 + 0 * a, 2.0 * C02 + 0 * a)


def neo_hookean(I1b, I2b, C10):
    """Neo-Hookean, ``W = C10 (I1b - 3)``; ``mu0 = 2 C10``."""
    return mooney_rivlin(I1b, I2b, C10=C10)


def yeoh(I1b, I2b, C10, C20=0.0, C30=0.0):
    """Yeoh (3 terms), ``W = C10 (I1b-3) + C20 (I1b-3)^2 + C30 (I1b-3)^3``; ``mu0 = 2 C10``."""
    a = I1b - 3.0
    W = C10 * a + C20 * a**2 + C30 * a**3
    W1 = C10 + 2.0 * C20 * a + 3.0 * C30 * a**2
    zero = 0.0 * a
    return W, (W1, zero), (2.0 * C20 + 6.0 * C30 * a, zero, zero)


def ogden_principal(stretches_bar, mus, alphas):
    """Ogden, N terms (ANSYS convention), on isochoric principal stretches.

    .. math::

        \\bar W = \\sum_{p=1}^N \\frac{\\mu_p}{\\alpha_p}
        (\\bar\\lambda_1^{\\alpha_p} + \\bar\\lambda_2^{\\alpha_p} + \\bar\\lambda_3^{\\alpha_p} - 3)

    Initial shear modulus ``mu0 = sum_p mu_p alpha_p / 2``. Returns ``W`` and
    ``dW/d lambda_a`` (same shape as ``stretches_bar``).
    """
    lam = np.asarray(stretches_bar, dtype=float)
    W = 0.0
    dW = 0.0
    for mu, al in zip(mus, alphas):
        W = W + mu / al * (np.sum(lam**al, axis=-1) - 3.0)
        dW = dW + mu * lam ** (al - 1.0)
    return W, dW


# --------------------------------------------------------------------------
# Registry
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class _ModelSpec:
    kind: str  # "invariant" or "ogden"
    func: Callable | None
    required: tuple[str, ...]
    uses_I2: bool
    mu0: Callable[[Mapping[str, float]], float]


_MODELS: dict[str, _ModelSpec] = {
    "neo_hookean": _ModelSpec("invariant", neo_hookean, ("C10",), False, lambda p: 2 * p["C10"]),
    "mooney_rivlin_2": _ModelSpec(
        "invariant", mooney_rivlin, ("C10", "C01"), True, lambda p: 2 * (p["C10"] + p["C01"])
    ),
    "mooney_rivlin_3": _ModelSpec(
        "invariant", mooney_rivlin, ("C10", "C01", "C11"), True, lambda p: 2 * (p["C10"] + p["C01"])
    ),
    "mooney_rivlin_5": _ModelSpec(
        "invariant",
        mooney_rivlin,
        ("C10", "C01", "C20", "C11", "C02"),
        True,
        lambda p: 2 * (p["C10"] + p["C01"]),
    ),
    "yeoh": _ModelSpec("invariant", yeoh, ("C10", "C20", "C30"), False, lambda p: 2 * p["C10"]),
    "ogden": _ModelSpec("ogden", None, (), False, lambda p: 0.0),  # parameters parsed below
}
_ALIASES = {
    "neohookean": "neo_hookean",
    "neo_hooke": "neo_hookean",
    "mooney_rivlin": "mooney_rivlin_2",
    "mr2": "mooney_rivlin_2",
    "mr3": "mooney_rivlin_3",
    "mr5": "mooney_rivlin_5",
}


def available_models() -> list[str]:
    """Names accepted by :func:`make_material`."""
    return sorted(_MODELS)


def _canonical(model: str) -> str:
    key = str(model).strip().lower().replace("-", "_").replace(" ", "_")
    key = _ALIASES.get(key, key)
    if key not in _MODELS:
        raise ValueError(
            f"unknown material model {model!r}; choose one of {available_models()} "
            f"(aliases: {sorted(_ALIASES)})"
        )
    return key


def _ogden_terms(params: Mapping[str, float]) -> tuple[tuple[float, ...], tuple[float, ...]]:
    idx = set()
    for k in params:
        m = re.fullmatch(r"(mu|alpha)(\d+)", k)
        if not m:
            raise ValueError(
                f"unknown Ogden parameter {k!r}; expected mu1, alpha1, mu2, alpha2, ... (MPa, -)"
            )
        idx.add(int(m.group(2)))
    n = len(idx)
    if n == 0 or idx != set(range(1, n + 1)):
        raise ValueError(
            f"Ogden parameters must be mu1..muN and alpha1..alphaN without gaps, got {sorted(params)}"
        )
    mus, alphas = [], []
    for p in range(1, n + 1):
        if f"mu{p}" not in params or f"alpha{p}" not in params:
            raise ValueError(f"Ogden term {p} needs both mu{p} and alpha{p}, got {sorted(params)}")
        if params[f"alpha{p}"] == 0.0:
            raise ValueError(f"Ogden alpha{p} must be non-zero")
        mus.append(float(params[f"mu{p}"]))
        alphas.append(float(params[f"alpha{p}"]))
    return tuple(mus), tuple(alphas)


def bulk_from_poisson(mu0: float, nu: float) -> float:
    """Bulk modulus ``K = 2 mu0 (1 + nu) / (3 (1 - 2 nu))`` (small-strain relation)."""
    if not (-1.0 < nu < 0.5):
        raise ValueError(f"Poisson ratio nu={nu} must lie in (-1, 0.5)")
    return 2.0 * mu0 * (1.0 + nu) / (3.0 * (1.0 - 2.0 * nu))


#: Pa per unit of a Young's modulus stated in a paper.
_TO_PA = {"Pa": 1.0, "kPa": 1e3, "MPa": 1e6}


def neo_hookean_from_young(E: float, nu: float, unit: str = "Pa") -> tuple[dict[str, float], str]:
    """Neo-Hookean constants (MPa) from a Young's modulus and Poisson ratio, as papers state them.

    ``mu = E / (2 (1 + nu))``, ``C10 = mu / 2`` (``W = C10 (I1b - 3)``, so ``mu0 = 2 C10``),
    and the bulk modulus this module derives from ``nu`` (:func:`bulk_from_poisson`),
    ``K = 2 mu (1 + nu) / (3 (1 - 2 nu)) = E / (3 (1 - 2 nu))``, i.e. ANSYS' ``D1 = 2 / K``.

    Parameters
    ----------
    E : Young's modulus in ``unit``.
    nu : Poisson ratio in (0, 0.5).
    unit : ``"Pa"``, ``"kPa"`` or ``"MPa"``.

    Returns
    -------
    params : ``{"C10": ...}`` in MPa, for :func:`make_material` with the same ``nu``.
    note : one line saying what was converted, e.g.
        ``"E 14.9 kPa, nu 0.49 -> mu 0.005 MPa, C10 0.0025 MPa, K 0.248 MPa (D1 = 2/K = 8.05 1/MPa)"``.

    Example
    -------
    >>> neo_hookean_from_young(14900.0, 0.49)[0]["C10"]
    0.0025
    """
    if unit not in _TO_PA:
        raise ValueError(f"unit '{unit}' must be one of {list(_TO_PA)}")
    E_pa = float(E) * _TO_PA[unit]
    if not (np.isfinite(E_pa) and E_pa > 0):
        raise ValueError(f"Young's modulus must be > 0 (got {E} {unit})")
    if not 0.0 < nu < 0.5:
        raise ValueError(f"Poisson ratio must be in (0, 0.5) (got {nu})")
    E_mpa = E_pa * 1e-6
    mu = E_mpa / (2.0 * (1.0 + nu))
    c10 = round(mu / 2.0, 15)  # round off the Pa -> MPa float noise only
    K = bulk_from_poisson(2.0 * c10, nu)
    shown = f"{E_pa / 1e3:.4g} kPa" if E_pa < 1e6 else f"{E_mpa:.4g} MPa"
    note = (f"E {shown}, nu {nu:g} -> mu {mu:.4g} MPa, C10 {c10:.4g} MPa, K {K:.4g} MPa "
            f"(D1 = 2/K = {2.0 / K:.4g} 1/MPa); neo_hookean, mm/N/MPa")
    return {"C10": c10}, note


@dataclass(frozen=True)
class Material:
    """A nearly incompressible hyperelastic material (build with :func:`make_material`).

    Attributes
    ----------
    model : str
        Canonical model name.
    params : dict
        Model constants in MPa (Ogden ``alpha`` dimensionless).
    bulk : float
        Bulk modulus ``K`` (MPa) of ``U(J) = K/2 (J-1)^2``.
    mu0 : float
        Initial shear modulus (MPa).
    """

    model: str
    params: Mapping[str, float]
    bulk: float
    mu0: float
    _spec: _ModelSpec = field(repr=False, compare=False, default=None)

    @property
    def poisson_ratio(self) -> float:
        """Initial Poisson ratio implied by ``K`` and ``mu0``."""
        r = self.bulk / self.mu0
        return (3.0 * r - 2.0) / (2.0 * (3.0 * r + 1.0))

    # -- volumetric part ----------------------------------------------------
    def volumetric(self, J):
        """``U = K/2 (J-1)^2`` and its first two derivatives in ``J``."""
        J = np.asarray(J, dtype=float)
        K = self.bulk
        return 0.5 * K * (J - 1.0) ** 2, K * (J - 1.0), np.full_like(J, K)

    # -- isochoric part -----------------------------------------------------
    def isochoric(self, F: np.ndarray, tangent: bool = True):
        """Isochoric energy density, 1st PK stress and tangent ``dP/dF``.

        Parameters
        ----------
        F : (..., 3, 3) deformation gradients with ``det F > 0``.
        tangent : also return the fourth-order tangent ``A[..., i, J, k, L]``.

        Returns
        -------
        W (...), P (..., 3, 3), A (..., 3, 3, 3, 3) or None.
        """
        F = np.asarray(F, dtype=float)
        if self._spec.kind == "ogden":
            return self._ogden_iso(F, tangent)
        J, dJ, d2J = kin.jacobian(F, tangent)
        I1, dI1, d2I1 = kin.first_invariant(F, tangent)
        uses_I2 = self._spec.uses_I2
        if uses_I2:
            I2, dI2, d2I2 = kin.second_invariant(F, tangent)
        else:
            I2 = np.full_like(I1, 3.0)
        out = self.isochoric_scalars(J, I1, I2, second=tangent)
        W, (f1, f2, fJ) = out[0], out[1]
        e2 = (Ellipsis, None, None)
        P = f1[e2] * dI1 + fJ[e2] * dJ
        if uses_I2:
            P = P + f2[e2] * dI2
        if not tangent:
            return W, P, None
        f11, f12, f22, f1J, f2J, fJJ = out[2]
        e4 = (Ellipsis, None, None, None, None)
        A = (
            f11[e4] * kin.outer(dI1, dI1)
            + f1J[e4] * (kin.outer(dI1, dJ) + kin.outer(dJ, dI1))
            + fJJ[e4] * kin.outer(dJ, dJ)
            + f1[e4] * d2I1
            + fJ[e4] * d2J
        )
        if uses_I2:
            A = A + (
                f12[e4] * (kin.outer(dI1, dI2) + kin.outer(dI2, dI1))
                + f22[e4] * kin.outer(dI2, dI2)
                + f2J[e4] * (kin.outer(dI2, dJ) + kin.outer(dJ, dI2))
                + f2[e4] * d2I2
            )
        return W, P, A

    @property
    def invariant_based(self) -> bool:
        """True if the isochoric energy is a function of (I1b, I2b) (not Ogden)."""
        return self._spec.kind == "invariant"

    def isochoric_scalars(self, J, I1, I2, second: bool = False):
        """Isochoric energy and its derivatives in ``(I1, I2, J)`` (invariant models).

        Returns ``W, (f1, f2, fJ)`` and, if ``second``, also
        ``(f11, f12, f22, f1J, f2J, fJJ)``, where ``f1 = dW/dI1`` etc. With them
        ``P = 2 f1 F + 2 f2 (I1 F - F C) + fJ cof F``.

        Notes
        -----
        With ``I1b = J^-2/3 I1``, ``I2b = J^-4/3 I2`` and ``a1 = dI1b/dJ = -2/3 I1b/J``,
        ``a2 = dI2b/dJ = -4/3 I2b/J``: ``f1 = W_1 J^-2/3``, ``f2 = W_2 J^-4/3``,
        ``fJ = W_1 a1 + W_2 a2`` and, differentiating once more,
        ``f11 = W_11 J^-4/3``, ``f12 = W_12 J^-2``, ``f22 = W_22 J^-8/3``,
        ``f1J = J^-2/3 (W_11 a1 + W_12 a2) - 2/3 W_1 J^-5/3``,
        ``f2J = J^-4/3 (W_12 a1 + W_22 a2) - 4/3 W_2 J^-7/3``,
        ``fJJ = W_11 a1^2 + 2 W_12 a1 a2 + W_22 a2^2 + 10/9 W_1 I1b/J^2 + 28/9 W_2 I2b/J^2``.
        """
        uses_I2 = self._spec.uses_I2
        Jm23 = J ** (-2.0 / 3.0)
        Jm43 = Jm23 * Jm23
        I1b = Jm23 * I1
        I2b = Jm43 * I2 if uses_I2 else np.full_like(J, 3.0)
        W, (p1, p2), (p11, p12, p22) = self._spec.func(I1b, I2b, **self.params)
        a1 = -2.0 / 3.0 * I1b / J
        a2 = -4.0 / 3.0 * I2b / J if uses_I2 else np.zeros_like(J)
        zero = np.zeros_like(J)
        f1 = p1 * Jm23
        f2 = p2 * Jm43 if uses_I2 else zero
        fJ = p1 * a1 + (p2 * a2 if uses_I2 else zero)
        if not second:
            return W, (f1, f2, fJ)
        f11 = p11 * Jm43
        f1J = Jm23 * (p11 * a1 + p12 * a2) - 2.0 / 3.0 * p1 * Jm23 / J
        fJJ = p11 * a1**2 + 2 * p12 * a1 * a2 + p22 * a2**2 + p1 * (10.0 / 9.0) * I1b / J**2
        if uses_I2:
            f12 = p12 * Jm23 * Jm43
            f22 = p22 * Jm43 * Jm43
            f2J = Jm43 * (p12 * a1 + p22 * a2) - 4.0 / 3.0 * p2 * Jm43 / J
            fJJ = fJJ + p2 * (28.0 / 9.0) * I2b / J**2
        else:
            f12 = f22 = f2J = zero
        bc = lambda x: np.broadcast_to(x, J.shape).astype(float)  # noqa: E731
        return W, (f1, f2, fJ), tuple(bc(x) for x in (f11, f12, f22, f1J, f2J, fJJ))

    def _ogden_iso(self, F, tangent):
        mus, alphas = _ogden_terms(self.params)
        J, dJ, d2J = kin.jacobian(F, tangent)
        e2 = (Ellipsis, None, None)
        e4 = (Ellipsis, None, None, None, None)
        W = 0.0 * J
        P = np.zeros_like(F)
        A = np.zeros(F.shape + (3, 3)) if tangent else None
        fJ = 0.0 * J
        fJJ = 0.0 * J
        for mu, al in zip(mus, alphas):
            g, dg, d2g = kin.trace_power(F, al, tangent)
            c, e = mu / al, -al / 3.0
            Je = J**e
            W = W + c * (Je * g - 3.0)
            fg = c * Je
            fJ = fJ + c * e * Je / J * g
            P = P + fg[e2] * dg
            if tangent:
                fgJ = c * e * Je / J
                fJJ = fJJ + c * e * (e - 1.0) * Je / J**2 * g
                A += fg[e4] * d2g + fgJ[e4] * (kin.outer(dg, dJ) + kin.outer(dJ, dg))
        P = P + fJ[e2] * dJ
        if tangent:
            A += fJJ[e4] * kin.outer(dJ, dJ) + fJ[e4] * d2J
        return W, P, A

    # -- full energy --------------------------------------------------------
    def energy(self, F: np.ndarray) -> np.ndarray:
        """Strain energy density ``W(F)`` (MPa = mJ/mm³)."""
        W, _, _ = self.isochoric(F, tangent=False)
        return W + self.volumetric(kin.det3(np.asarray(F, dtype=float)))[0]

    def stress(self, F: np.ndarray) -> np.ndarray:
        """First Piola–Kirchhoff stress ``P = dW/dF`` (MPa)."""
        F = np.asarray(F, dtype=float)
        _, P, _ = self.isochoric(F, tangent=False)
        J, cof, _ = kin.jacobian(F, hessian=False)
        return P + self.volumetric(J)[1][..., None, None] * cof

    def tangent(self, F: np.ndarray) -> np.ndarray:
        """Tangent ``A = dP/dF`` (MPa), index order ``[..., i, J, k, L]``."""
        F = np.asarray(F, dtype=float)
        _, _, A = self.isochoric(F, tangent=True)
        J, cof, d2J = kin.jacobian(F)
        _, dU, d2U = self.volumetric(J)
        e4 = (Ellipsis, None, None, None, None)
        return A + d2U[e4] * kin.outer(cof, cof) + dU[e4] * d2J

    # -- incompressible principal-stretch form (stability, fitting) ---------
    def incompressible_dW(self, stretches: np.ndarray):
        """Isochoric ``W`` and ``dW/d lambda_a`` at principal stretches with J = 1.

        ``stretches`` has shape ``(..., 3)``; the caller guarantees
        ``lambda_1 lambda_2 lambda_3 = 1``.
        """
        lam = np.asarray(stretches, dtype=float)
        if self._spec.kind == "ogden":
            return ogden_principal(lam, *_ogden_terms(self.params))
        sq = lam**2
        I1 = sq.sum(axis=-1)
        I2 = sq[..., 0] * sq[..., 1] + sq[..., 1] * sq[..., 2] + sq[..., 2] * sq[..., 0]
        W, (W1, W2), _ = self._spec.func(I1, I2, **self.params)
        dI2 = 2.0 * lam * (I1[..., None] - sq)
        return W, W1[..., None] * 2.0 * lam + np.asarray(W2)[..., None] * dI2


def make_material(
    model: str,
    params: Mapping[str, float],
    nu: float | None = None,
    bulk_mpa: float | None = None,
) -> Material:
    """Build a :class:`Material` from a model name and constants in MPa.

    Parameters
    ----------
    model : str
        ``neo_hookean`` (C10), ``mooney_rivlin_2`` (C10, C01), ``mooney_rivlin_3``
        (C10, C01, C11), ``mooney_rivlin_5`` (C10, C01, C20, C11, C02), ``yeoh``
        (C10, C20, C30), ``ogden`` (mu1, alpha1, ..., muN, alphaN).
    params : dict
        Constants in MPa (N/mm²); Ogden exponents are dimensionless.
    nu : float, optional
        Initial Poisson ratio; gives ``K = 2 mu0 (1+nu) / (3 (1-2 nu))``.
    bulk_mpa : float, optional
        Bulk modulus ``K`` in MPa. Give exactly one of ``nu`` and ``bulk_mpa``.

    Raises
    ------
    ValueError
        Unknown model, missing or unknown constants, non-positive ``mu0`` or ``K``.
    """
    key = _canonical(model)
    spec = _MODELS[key]
    params = {str(k): float(v) for k, v in dict(params).items()}
    if spec.kind == "ogden":
        mus, alphas = _ogden_terms(params)
        mu0 = 0.5 * sum(m * a for m, a in zip(mus, alphas))
    else:
        missing = [k for k in spec.required if k not in params]
        unknown = [k for k in params if k not in spec.required]
        if missing or unknown:
            raise ValueError(
                f"material {key!r} takes constants {list(spec.required)} (MPa); "
                f"missing {missing}, unknown {unknown}"
            )
        mu0 = float(spec.mu0(params))
    if not np.all(np.isfinite(list(params.values()))):
        raise ValueError(f"material {key!r}: constants must be finite, got {params}")
    if not mu0 > 0.0:
        raise ValueError(
            f"material {key!r} with {params} has initial shear modulus mu0={mu0:g} MPa <= 0; "
            "such constants are unstable at zero strain"
        )
    if (nu is None) == (bulk_mpa is None):
        raise ValueError("give exactly one of nu (initial Poisson ratio) and bulk_mpa (MPa)")
    K = bulk_from_poisson(mu0, float(nu)) if nu is not None else float(bulk_mpa)
    if not K > 0.0:
        raise ValueError(f"bulk modulus must be positive, got K={K:g} MPa")
    return Material(model=key, params=params, bulk=K, mu0=mu0, _spec=spec)
