"""Scalar functions of the deformation gradient and their derivatives.

Every hyperelastic energy in :mod:`liverforce.fem.materials` is written as a
function ``f(s_1, ..., s_n)`` of a few scalars ``s_k(F)`` (invariants,
Jacobian, traces of powers of ``C``). The first Piola–Kirchhoff stress and its
tangent then follow from the chain rule

.. math::

    P = \\sum_k f_{,k} \\frac{\\partial s_k}{\\partial F}, \\qquad
    \\mathbb{A} = \\sum_{k,l} f_{,kl} \\frac{\\partial s_k}{\\partial F}
    \\otimes \\frac{\\partial s_l}{\\partial F}
    + \\sum_k f_{,k} \\frac{\\partial^2 s_k}{\\partial F \\partial F}.

All functions are vectorised over leading axes: ``F`` has shape ``(..., 3, 3)``,
gradients ``(..., 3, 3)`` and Hessians ``(..., 3, 3, 3, 3)`` with index order
``[i, J, k, L]`` meaning ``d^2 s / dF_iJ dF_kL``.
"""

from __future__ import annotations

import numpy as np

_EYE = np.eye(3)
#: ``delta_ik delta_JL`` as a (3, 3, 3, 3) array.
IDENTITY4 = np.einsum("ik,JL->iJkL", _EYE, _EYE)
#: Permutation (Levi-Civita) symbol.
LEVI_CIVITA = np.zeros((3, 3, 3))
for _i, _j, _k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
    LEVI_CIVITA[_i, _j, _k], LEVI_CIVITA[_i, _k, _j] = 1.0, -1.0


def outer(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dyadic product ``a_iJ b_kL`` of two second-order tensors."""
    return a[..., :, :, None, None] * b[..., None, None, :, :]


def det3(F: np.ndarray) -> np.ndarray:
    """Determinant of (..., 3, 3) arrays (explicit cofactor formula)."""
    return (
        F[..., 0, 0] * (F[..., 1, 1] * F[..., 2, 2] - F[..., 1, 2] * F[..., 2, 1])
        - F[..., 0, 1] * (F[..., 1, 0] * F[..., 2, 2] - F[..., 1, 2] * F[..., 2, 0])
        + F[..., 0, 2] * (F[..., 1, 0] * F[..., 2, 1] - F[..., 1, 1] * F[..., 2, 0])
    )


def cofactor(F: np.ndarray) -> np.ndarray:
    """Cofactor ``cof F = J F^{-T} = dJ/dF`` (valid for any F, also J <= 0)."""
    c = np.empty_like(F)
    c[..., 0, 0] = F[..., 1, 1] * F[..., 2, 2] - F[..., 1, 2] * F[..., 2, 1]
    c[..., 0, 1] = F[..., 1, 2] * F[..., 2, 0] - F[..., 1, 0] * F[..., 2, 2]
    c[..., 0, 2] = F[..., 1, 0] * F[..., 2, 1] - F[..., 1, 1] * F[..., 2, 0]
    c[..., 1, 0] = F[..., 0, 2] * F[..., 2, 1] - F[..., 0, 1] * F[..., 2, 2]
    c[..., 1, 1] = F[..., 0, 0] * F[..., 2, 2] - F[..., 0, 2] * F[..., 2, 0]
    c[..., 1, 2] = F[..., 0, 1] * F[..., 2, 0] - F[..., 0, 0] * F[..., 2, 1]
    c[..., 2, 0] = F[..., 0, 1] * F[..., 1, 2] - F[..., 0, 2] * F[..., 1, 1]
    c[..., 2, 1] = F[..., 0, 2] * F[..., 1, 0] - F[..., 0, 0] * F[..., 1, 2]
    c[..., 2, 2] = F[..., 0, 0] * F[..., 1, 1] - F[..., 0, 1] * F[..., 1, 0]
    return c


def jacobian(F: np.ndarray, hessian: bool = True):
    """``J = det F`` with ``dJ/dF = J F^{-T}`` and
    ``d2J/dF_iJ dF_kL = e_ikm e_JLN F_mN`` (``e`` the permutation symbol; equal to
    ``(cof_iJ cof_kL - cof_iL cof_kJ) / J`` but polynomial, so valid for J <= 0).

    Returns
    -------
    J, dJ, d2J (d2J is None unless ``hessian``).
    """
    J = det3(F)
    cof = cofactor(F)
    if not hessian:
        return J, cof, None
    d2J = np.einsum("ikm,JLN,...mN->...iJkL", LEVI_CIVITA, LEVI_CIVITA, F, optimize=True)
    return J, cof, d2J


def first_invariant(F: np.ndarray, hessian: bool = True):
    """``I1 = tr C = F:F``, ``dI1/dF = 2F``, ``d2I1 = 2 delta_ik delta_JL``."""
    I1 = np.einsum("...ij,...ij->...", F, F)
    d2 = np.broadcast_to(2.0 * IDENTITY4, F.shape[:-2] + (3, 3, 3, 3)) if hessian else None
    return I1, 2.0 * F, d2


def second_invariant(F: np.ndarray, hessian: bool = True):
    """``I2 = (I1^2 - C:C)/2`` and its derivatives.

    Notes
    -----
    ``dI2/dF = 2 (I1 F - F C)`` and
    ``d2I2/dF_iJ dF_kL = 4 F_iJ F_kL + 2 I1 d_ik d_JL
    - 2 (d_ik C_LJ + F_iL F_kJ + B_ik d_JL)`` with ``B = F F^T``.
    """
    C = np.einsum("...ki,...kj->...ij", F, F)
    I1 = np.trace(C, axis1=-2, axis2=-1)
    I2 = 0.5 * (I1**2 - np.einsum("...ij,...ij->...", C, C))
    dI2 = 2.0 * (I1[..., None, None] * F - F @ C)
    if not hessian:
        return I2, dI2, None
    B = F @ np.swapaxes(F, -1, -2)
    d2 = (
        4.0 * outer(F, F)
        + 2.0 * I1[..., None, None, None, None] * IDENTITY4
        - 2.0
        * (
            np.einsum("ik,...LJ->...iJkL", _EYE, C)
            + np.einsum("...iL,...kJ->...iJkL", F, F)
            + np.einsum("...ik,JL->...iJkL", B, _EYE)
        )
    )
    return I2, dI2, d2


def _power_divided_difference(ca: np.ndarray, cb: np.ndarray, beta: float) -> np.ndarray:
    """``(ca^beta - cb^beta) / (ca - cb)``, continuous at ``ca == cb`` (positive args)."""
    t = np.log(ca / cb)
    small = np.abs(t) < 1e-6
    ts = np.where(small, 1.0, t)
    ratio = np.where(small, beta * (1.0 + 0.5 * (beta - 1.0) * t), np.expm1(beta * ts) / np.expm1(ts))
    return cb ** (beta - 1.0) * ratio


def trace_power(F: np.ndarray, alpha: float, hessian: bool = True):
    """``g = tr C^{alpha/2} = sum_a lambda_a^alpha`` (principal stretches).

    Notes
    -----
    ``dg/dF = 2 F G`` with ``G = dg/dC = (alpha/2) C^{alpha/2 - 1}``. The
    Hessian uses the Daleckii–Krein formula in the eigenbasis ``C = Q c Q^T``:
    ``d2g/dF_iJ dF_kL = 2 d_ik G_LJ + 2 sum_ab (FQ)_ia Q_Jb h_ab
    [Q_La (FQ)_kb + (FQ)_ka Q_Lb]`` with the divided differences
    ``h_ab = (h(c_a) - h(c_b)) / (c_a - c_b)`` of ``h(c) = (alpha/2) c^{alpha/2-1}``
    (``h'(c_a)`` for equal eigenvalues), so repeated stretches need no special case.
    """
    C = np.einsum("...ki,...kj->...ij", F, F)
    c, Q = np.linalg.eigh(C)
    c = np.maximum(c, 1e-300)
    g = np.sum(c ** (0.5 * alpha), axis=-1)
    beta = 0.5 * alpha - 1.0
    hc = 0.5 * alpha * c**beta
    G = np.einsum("...ia,...a,...ja->...ij", Q, hc, Q)
    dg = 2.0 * F @ G
    if not hessian:
        return g, dg, None
    h1 = 0.5 * alpha * _power_divided_difference(c[..., :, None], c[..., None, :], beta)
    FQ = F @ Q
    t1 = np.einsum("...ia,...Jb,...ab,...La,...kb->...iJkL", FQ, Q, h1, Q, FQ, optimize=True)
    t2 = np.einsum("...ia,...Jb,...ab,...ka,...Lb->...iJkL", FQ, Q, h1, FQ, Q, optimize=True)
    d2 = 2.0 * np.einsum("ik,...LJ->...iJkL", _EYE, G) + 2.0 * (t1 + t2)
    return g, dg, d2


def principal_stretches(F: np.ndarray) -> np.ndarray:
    """Principal stretches ``lambda_a = sqrt(eig(C))``, ``C = F^T F``, ascending, shape ``(..., 3)``.

    The stretches of the total ``F`` (volume change included; ``J = prod lambda_a``),
    the quantity the Drucker check (:mod:`liverforce.fem.stability`) ranges over.
    """
    C = np.einsum("...ki,...kj->...ij", F, F)
    return np.sqrt(np.maximum(np.linalg.eigvalsh(C), 0.0))


def principal_stretch_range(disc, u: np.ndarray) -> tuple[float, float]:
    """(min, max) principal stretch over every quadrature point of ``disc`` at the dof vector ``u``.

    ``F = I + grad u`` is evaluated at the quadrature points of the element
    (4 per P2 tet, 1 per P1 tet: the points where the material is evaluated).
    Returns (NaN, NaN) if ``u`` is not finite or does not match ``disc``.

    Parameters
    ----------
    disc : :class:`~liverforce.fem.elements.TetDiscretization`
    u : (3 * n_nodes,) or (n_nodes, 3) displacement of all nodes of ``disc`` (mm).
    """
    from .kernels import deformation_gradient

    u = np.asarray(u, dtype=float)
    if u.size != disc.n_dofs or not np.all(np.isfinite(u)):
        return float("nan"), float("nan")
    lam = principal_stretches(deformation_gradient(np.ascontiguousarray(u.reshape(-1, 3)), disc.conn, disc.dN))
    return float(lam[..., 0].min()), float(lam[..., 2].max())
