"""Hand-written numba kernels for the total-Lagrangian residual and tangent.

They implement, element by element and quadrature point by quadrature point,

.. math::

    F = I + \\sum_a u_a \\otimes \\nabla_X N_a, \\qquad
    r_{ai} = \\sum_q w_q P_{iJ} \\partial_J N_a, \\qquad
    K_{ai,bk} = \\sum_q w_q \\partial_J N_a \\mathbb{A}_{iJkL} \\partial_L N_b
    + \\kappa_e G_{ai} G_{bk},

the last term being the rank-one mean-dilatation coupling (``kappa_e = 0`` for
the pure-displacement formulation). The readable scikit-fem forms in
:mod:`liverforce.fem.forms_skfem` are the test oracle for these kernels.
All kernels are serial and deterministic.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def deformation_gradient(u, conn, dN):
    """``F[e, q] = I + sum_a u[conn[e, a]] (x) dN[e, q, a]``; u is (n_nodes, 3)."""
    ne, nq, nen, _ = dN.shape
    F = np.zeros((ne, nq, 3, 3))
    for e in range(ne):
        for q in range(nq):
            for i in range(3):
                F[e, q, i, i] = 1.0
            for a in range(nen):
                n = conn[e, a]
                for i in range(3):
                    ui = u[n, i]
                    for J in range(3):
                        F[e, q, i, J] += ui * dN[e, q, a, J]
    return F


@njit(cache=True)
def internal_force(P, dN, w, conn, n_nodes):
    """Global internal force vector (3 * n_nodes,), interleaved dofs."""
    ne, nq, nen, _ = dN.shape
    f = np.zeros(3 * n_nodes)
    for e in range(ne):
        for q in range(nq):
            wq = w[e, q]
            for a in range(nen):
                base = 3 * conn[e, a]
                for i in range(3):
                    s = 0.0
                    for J in range(3):
                        s += P[e, q, i, J] * dN[e, q, a, J]
                    f[base + i] += wq * s
    return f


@njit(cache=True)
def tangent_data(A, dN, w, G, kappa, pos, nnz):
    """Assemble element tangents straight into CSR ``data`` (length ``nnz``).

    ``pos[e, r * nd + c]`` is the position of local entry (r, c) in ``data``
    or -1 for entries that are dropped (constrained dofs). ``G`` (ne, nd) and
    ``kappa`` (ne,) add ``kappa G G^T`` per element.
    """
    ne, nq, nen, _ = dN.shape
    nd = 3 * nen
    data = np.zeros(nnz)
    Ke = np.empty((nd, nd))
    B = np.empty((nen, 3, 3, 3))
    for e in range(ne):
        Ke[:, :] = 0.0
        for q in range(nq):
            wq = w[e, q]
            for a in range(nen):
                for i in range(3):
                    for k in range(3):
                        for L in range(3):
                            s = 0.0
                            for J in range(3):
                                s += dN[e, q, a, J] * A[e, q, i, J, k, L]
                            B[a, i, k, L] = wq * s
            for a in range(nen):
                for b in range(a, nen):
                    for i in range(3):
                        for k in range(3):
                            s = 0.0
                            for L in range(3):
                                s += B[a, i, k, L] * dN[e, q, b, L]
                            Ke[3 * a + i, 3 * b + k] += s
        ke = kappa[e]
        for r in range(nd):
            for c in range(nd):
                if c // 3 < r // 3:  # lower block: mirror of the upper block
                    v = Ke[c, r]
                else:
                    v = Ke[r, c]
                if ke != 0.0:
                    v += ke * G[e, r] * G[e, c]
                p = pos[e, r * nd + c]
                if p >= 0:
                    data[p] += v
    return data


@njit(cache=True)
def kinematic_scalars(F):
    """Per point: ``J = det F``, ``cof F``, ``I1 = F:F`` and ``I2 = (I1^2 - C:C)/2``."""
    n = F.shape[0]
    J = np.empty(n)
    I1 = np.empty(n)
    I2 = np.empty(n)
    cof = np.empty((n, 3, 3))
    for p in range(n):
        f = F[p]
        c00 = f[1, 1] * f[2, 2] - f[1, 2] * f[2, 1]
        c01 = f[1, 2] * f[2, 0] - f[1, 0] * f[2, 2]
        c02 = f[1, 0] * f[2, 1] - f[1, 1] * f[2, 0]
        cof[p, 0, 0], cof[p, 0, 1], cof[p, 0, 2] = c00, c01, c02
        cof[p, 1, 0] = f[0, 2] * f[2, 1] - f[0, 1] * f[2, 2]
        cof[p, 1, 1] = f[0, 0] * f[2, 2] - f[0, 2] * f[2, 0]
        cof[p, 1, 2] = f[0, 1] * f[2, 0] - f[0, 0] * f[2, 1]
        cof[p, 2, 0] = f[0, 1] * f[1, 2] - f[0, 2] * f[1, 1]
        cof[p, 2, 1] = f[0, 2] * f[1, 0] - f[0, 0] * f[1, 2]
        cof[p, 2, 2] = f[0, 0] * f[1, 1] - f[0, 1] * f[1, 0]
        J[p] = f[0, 0] * c00 + f[0, 1] * c01 + f[0, 2] * c02
        s1 = 0.0
        cc = 0.0
        for i in range(3):
            for j in range(3):
                s1 += f[i, j] * f[i, j]
                cij = f[0, i] * f[0, j] + f[1, i] * f[1, j] + f[2, i] * f[2, j]
                cc += cij * cij
        I1[p] = s1
        I2[p] = 0.5 * (s1 * s1 - cc)
    return J, cof, I1, I2


@njit(cache=True)
def invariant_pk1(F, cof, I1, f1, f2, fJ):
    """``P = 2 f1 F + 2 f2 (I1 F - F C) + fJ cof F`` per point (f_a = dW/dI_a, fJ = dW/dJ)."""
    n = F.shape[0]
    P = np.empty((n, 3, 3))
    for p in range(n):
        f = F[p]
        for i in range(3):
            for J in range(3):
                v = 2.0 * f1[p] * f[i, J] + fJ[p] * cof[p, i, J]
                if f2[p] != 0.0:
                    fc = 0.0
                    for M in range(3):
                        cmj = f[0, M] * f[0, J] + f[1, M] * f[1, J] + f[2, M] * f[2, J]
                        fc += f[i, M] * cmj
                    v += 2.0 * f2[p] * (I1[p] * f[i, J] - fc)
                P[p, i, J] = v
    return P


@njit(cache=True)
def invariant_tangent(F, cof, J, I1, f1, f2, fJ, f11, f12, f22, f1J, f2J, fJJ):
    """Tangent ``A = dP/dF`` per point of ``W(I1, I2, J)`` from its scalar derivatives.

    ``A = sum_ab f_ab g_a (x) g_b + f1 d2I1 + f2 d2I2 + fJ d2J`` with
    ``g1 = 2F``, ``g2 = 2 (I1 F - F C)``, ``gJ = cof F``,
    ``d2I1 = 2 d_ik d_JL``,
    ``d2I2 = 4 F_iJ F_kL + 2 I1 d_ik d_JL - 2 (d_ik C_LJ + F_iL F_kJ + B_ik d_JL)``,
    ``d2J = (cof_iJ cof_kL - cof_iL cof_kJ) / J``.
    """
    n = F.shape[0]
    A = np.empty((n, 3, 3, 3, 3))
    g1 = np.empty((3, 3))
    g2 = np.empty((3, 3))
    C = np.empty((3, 3))
    B = np.empty((3, 3))
    for p in range(n):
        f = F[p]
        cf = cof[p]
        for a in range(3):
            for b in range(3):
                C[a, b] = f[0, a] * f[0, b] + f[1, a] * f[1, b] + f[2, a] * f[2, b]
                B[a, b] = f[a, 0] * f[b, 0] + f[a, 1] * f[b, 1] + f[a, 2] * f[b, 2]
        for i in range(3):
            for j in range(3):
                fc = f[i, 0] * C[0, j] + f[i, 1] * C[1, j] + f[i, 2] * C[2, j]
                g1[i, j] = 2.0 * f[i, j]
                g2[i, j] = 2.0 * (I1[p] * f[i, j] - fc)
        a11, a12, a22 = f11[p], f12[p], f22[p]
        a1J, a2J, aJJ = f1J[p], f2J[p], fJJ[p]
        b1, b2, bJ = f1[p], f2[p], fJ[p] / J[p]
        for i in range(3):
            for jj in range(3):
                for k in range(3):
                    for L in range(3):
                        v = (a11 * g1[i, jj] * g1[k, L]
                             + a12 * (g1[i, jj] * g2[k, L] + g2[i, jj] * g1[k, L])
                             + a22 * g2[i, jj] * g2[k, L]
                             + a1J * (g1[i, jj] * cf[k, L] + cf[i, jj] * g1[k, L])
                             + a2J * (g2[i, jj] * cf[k, L] + cf[i, jj] * g2[k, L])
                             + aJJ * cf[i, jj] * cf[k, L]
                             + bJ * (cf[i, jj] * cf[k, L] - cf[i, L] * cf[k, jj]))
                        if i == k and jj == L:
                            v += 2.0 * b1
                        if b2 != 0.0:
                            d2 = 4.0 * f[i, jj] * f[k, L] - 2.0 * f[i, L] * f[k, jj]
                            if i == k:
                                d2 -= 2.0 * C[L, jj]
                                if jj == L:
                                    d2 += 2.0 * I1[p]
                            if jj == L:
                                d2 -= 2.0 * B[i, k]
                            v += b2 * d2
                        A[p, i, jj, k, L] = v
    return A
