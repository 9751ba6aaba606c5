"""Sparsity pattern and energy / residual / tangent evaluation for one formulation.

Formulations
------------
``p1``
    Linear tetrahedra, pure displacement, one quadrature point. Fast; locks
    in bending-dominated nearly incompressible response (the peer-check
    formulation against FElupe).
``p2``
    Quadratic tetrahedra, pure displacement (4-point rule). Also locks at
    high ``K/mu``; kept for the locking comparison.
``p2_mean_dilatation`` (default)
    Quadratic tetrahedra with the volumetric energy on the element's mean
    dilatation (P2/P0, pressure condensed per element; Simo–Taylor–Pister):

    .. math::

        \\Pi_{int}(u) = \\sum_e \\Big[ \\int_{\\Omega_e} \\bar W(F)\\, dV
        + V_e\\, U(\\bar J_e) \\Big], \\qquad
        \\bar J_e = \\frac{v_e}{V_e} = \\frac{1}{V_e}\\int_{\\Omega_e} J\\, dV.

    It is a pure-displacement functional, so the tangent is symmetric:
    ``K = K_iso + sum_q w p_e d2J + kappa_e G_e G_e^T`` with
    ``p_e = U'(J_e)``, ``kappa_e = U''(J_e) / V_e`` and
    ``G_e = dv_e/du = sum_q w cof(F) grad N``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from . import kinematics as kin
from .elements import TetDiscretization
from .kernels import (deformation_gradient, internal_force, invariant_pk1, invariant_tangent,
                      kinematic_scalars, tangent_data)

FORMULATIONS = {
    "p1": (1, False),
    "p2": (2, False),
    "p2_mean_dilatation": (2, True),
}


def formulation_spec(name: str) -> tuple[int, bool]:
    """(element order, mean dilatation) of a formulation name."""
    if name not in FORMULATIONS:
        raise ValueError(f"unknown formulation {name!r}; choose one of {sorted(FORMULATIONS)}")
    return FORMULATIONS[name]


class SparsityPattern:
    """CSR pattern of the tangent restricted to free dofs, with element scatter maps.

    Parameters
    ----------
    element_dofs : (ne, nd) global dofs per element.
    free : (ndof,) bool mask of unconstrained dofs.
    """

    def __init__(self, element_dofs: np.ndarray, free: np.ndarray):
        self.n_full = free.size
        self.free_dofs = np.flatnonzero(free)
        self.n = self.free_dofs.size
        self.free_index = np.full(self.n_full, -1, dtype=np.int64)
        self.free_index[self.free_dofs] = np.arange(self.n)
        ne, nd = element_dofs.shape
        red = self.free_index[element_dofs]  # (ne, nd)
        rows = np.repeat(red, nd, axis=1)
        cols = np.tile(red, (1, nd))
        keep = (rows >= 0) & (cols >= 0)
        keys = rows[keep] * self.n + cols[keep]
        ukeys, inv = np.unique(keys, return_inverse=True)
        self.keys = ukeys
        self.indices = (ukeys % self.n).astype(np.int32)
        counts = np.bincount(ukeys // self.n, minlength=self.n)
        self.indptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)
        self.nnz = ukeys.size
        pos = np.full((ne, nd * nd), -1, dtype=np.int64)
        pos[keep] = inv
        self.pos = pos

    def positions(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Positions in ``data`` of full-dof entries (rows, cols); -1 where a dof is constrained."""
        r, c = self.free_index[rows], self.free_index[cols]
        ok = (r >= 0) & (c >= 0)
        key = r * self.n + c
        p = np.searchsorted(self.keys, key)
        p = np.where(ok, p, -1)
        bad = ok & ((p >= self.nnz) | (self.keys[np.minimum(p, self.nnz - 1)] != key))
        if np.any(bad):
            raise ValueError("entry outside the element sparsity pattern")
        return p

    def matrix(self, data: np.ndarray) -> sp.csr_matrix:
        """CSR matrix (free × free) with this pattern."""
        return sp.csr_matrix((data, self.indices, self.indptr), shape=(self.n, self.n))


@dataclass
class Evaluation:
    """Result of :meth:`Assembler.evaluate` (``valid`` False if an element inverted)."""

    valid: bool
    min_J: float
    energy: float = np.nan
    f_int: np.ndarray | None = None
    data: np.ndarray | None = None


class Assembler:
    """Evaluate internal energy, internal force and reduced tangent data.

    Parameters
    ----------
    disc : discretisation of matching order.
    mean_dilatation : volumetric energy on the element mean dilatation.
    pattern : sparsity pattern (free dofs) for the tangent.
    """

    def __init__(self, disc: TetDiscretization, mean_dilatation: bool, pattern: SparsityPattern):
        self.disc = disc
        self.mean_dilatation = mean_dilatation
        self.pattern = pattern
        self.timings = {"material": 0.0, "kernel": 0.0}

    def evaluate(self, u: np.ndarray, material, tangent: bool = True) -> Evaluation:
        """Energy, internal force (full dofs) and, if ``tangent``, reduced tangent data."""
        import time

        d = self.disc
        t0 = time.perf_counter()
        F = deformation_gradient(np.ascontiguousarray(u.reshape(-1, 3)), d.conn, d.dN)
        if getattr(material, "invariant_based", False):
            return self._evaluate_invariant(F, material, tangent, t0)
        ne, nq = F.shape[:2]
        J = kin.det3(F)
        min_J = float(J.min()) if np.all(np.isfinite(J)) else -np.inf
        if not min_J > 0.0:
            return Evaluation(False, min_J)
        Fq = F.reshape(-1, 3, 3)
        W, P, A = material.isochoric(Fq, tangent)
        W = W.reshape(ne, nq)
        P = P.reshape(ne, nq, 3, 3)
        cof = kin.cofactor(F)
        e2 = (Ellipsis, None, None)
        e4 = (Ellipsis, None, None, None, None)
        G = np.zeros((1, 1))
        kappa = np.zeros(ne)
        if self.mean_dilatation:
            Jbar = np.einsum("eq,eq->e", d.w, J) / d.volume
            if not Jbar.min() > 0.0:
                return Evaluation(False, float(Jbar.min()))
            Uv, dU, d2U = material.volumetric(Jbar)
            energy = float(np.sum(d.w * W) + np.sum(d.volume * Uv))
            P = P + dU[:, None, None, None] * cof
            if tangent:
                d2J = kin.jacobian(Fq)[2].reshape(ne, nq, 3, 3, 3, 3)
                A = A.reshape(ne, nq, 3, 3, 3, 3) + dU[:, None, None, None, None, None] * d2J
                G = np.einsum("eq,eqiJ,eqaJ->eai", d.w, cof, d.dN).reshape(ne, -1)
                kappa = d2U / d.volume
        else:
            Uv, dU, d2U = material.volumetric(J)
            energy = float(np.sum(d.w * (W + Uv)))
            P = P + dU[e2] * cof
            if tangent:
                d2J = kin.jacobian(Fq)[2].reshape(ne, nq, 3, 3, 3, 3)
                A = (A.reshape(ne, nq, 3, 3, 3, 3) + d2U[e4] * kin.outer(cof, cof) + dU[e4] * d2J)
        t1 = time.perf_counter()
        f_int = internal_force(np.ascontiguousarray(P), d.dN, d.w, d.conn, d.n_nodes)
        data = None
        if tangent:
            data = tangent_data(np.ascontiguousarray(A), d.dN, d.w, np.ascontiguousarray(G), kappa,
                                self.pattern.pos, self.pattern.nnz)
        t2 = time.perf_counter()
        self.timings["material"] += t1 - t0
        self.timings["kernel"] += t2 - t1
        return Evaluation(True, min_J, energy, f_int, data)

    def _evaluate_invariant(self, F, material, tangent, t0):
        """Fused numba path for invariant-based models (same math as the generic path)."""
        import time

        d = self.disc
        ne, nq = F.shape[:2]
        Fq = F.reshape(-1, 3, 3)
        J, cof, I1, I2 = kinematic_scalars(Fq)
        min_J = float(J.min()) if np.all(np.isfinite(J)) else -np.inf
        if not min_J > 0.0:
            return Evaluation(False, min_J)
        out = material.isochoric_scalars(J, I1, I2, second=tangent)
        W, (f1, f2, fJ) = out[0], out[1]
        w = d.w.ravel()
        G = np.zeros((1, 1))
        kappa = np.zeros(ne)
        fJJ_vol = 0.0
        if self.mean_dilatation:
            Jbar = np.einsum("eq,eq->e", d.w, J.reshape(ne, nq)) / d.volume
            if not Jbar.min() > 0.0:
                return Evaluation(False, float(Jbar.min()))
            Uv, dU, d2U = material.volumetric(Jbar)
            energy = float(w @ W + d.volume @ Uv)
            fJ = fJ + np.repeat(dU, nq)
            if tangent:
                G = np.einsum("eq,eqiJ,eqaJ->eai", d.w, cof.reshape(ne, nq, 3, 3), d.dN).reshape(ne, -1)
                kappa = d2U / d.volume
        else:
            Uv, dU, d2U = material.volumetric(J)
            energy = float(w @ (W + Uv))
            fJ = fJ + dU
            fJJ_vol = d2U
        t1 = time.perf_counter()
        P = invariant_pk1(Fq, cof, I1, f1, f2, fJ).reshape(ne, nq, 3, 3)
        f_int = internal_force(P, d.dN, d.w, d.conn, d.n_nodes)
        data = None
        if tangent:
            f11, f12, f22, f1J, f2J, fJJ = out[2]
            A = invariant_tangent(Fq, cof, J, I1, f1, f2, fJ, f11, f12, f22, f1J, f2J, fJJ + fJJ_vol)
            data = tangent_data(A.reshape(ne, nq, 3, 3, 3, 3), d.dN, d.w, np.ascontiguousarray(G), kappa,
                                self.pattern.pos, self.pattern.nnz)
        self.timings["material"] += t1 - t0
        self.timings["kernel"] += time.perf_counter() - t1
        return Evaluation(True, min_J, energy, f_int, data)
