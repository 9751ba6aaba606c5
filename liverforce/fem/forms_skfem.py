"""Readable scikit-fem weak forms of the same discrete problem (test oracle).

These forms are slow (scikit-fem loops in Python over the local matrix
entries) but read like the equations; :mod:`liverforce.fem.kernels` must give
the same numbers. With ``grad u`` the displacement gradient,
``F = I + grad u``:

.. math::

    r(v) = \\int \\big(P_{iso}(F) + p\\, \\mathrm{cof} F\\big) : \\nabla v \\, dX,

    a(\\delta u, v) = \\int \\nabla v : \\big(\\mathbb{A}_{iso}(F)
    + p\\, \\partial^2_{FF} J\\big) : \\nabla \\delta u \\, dX
    \\; [+\\, U''(J)\\, (\\mathrm{cof}F : \\nabla v)(\\mathrm{cof}F : \\nabla\\delta u)]
    \\; [+\\, B\\, \\mathrm{diag}(U''(\\bar J_e)/V_e)\\, B^T],

with ``p = U'(J)`` at the quadrature point (pure displacement) or
``p = U'(\\bar J_e)`` per element (mean dilatation, P2/P0), where
``B`` is the mixed form ``b(q, v) = \\int q\\, \\mathrm{cof} F : \\nabla v`` with
piecewise-constant ``q``.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import skfem
from skfem import (Basis, BilinearForm, ElementTetP0, ElementTetP1, ElementTetP2, ElementVector,
                   LinearForm, asm)
from skfem.helpers import ddot, grad

from . import kinematics as kin


def _tensor_last(a):
    """skfem layout (3, 3, ne, nq) -> (ne, nq, 3, 3)."""
    return np.moveaxis(a, (0, 1), (-2, -1))


def _tensor_first(a):
    """(ne, nq, 3, 3) -> skfem layout (3, 3, ne, nq)."""
    return np.moveaxis(a, (0, 1), (-2, -1))


def make_basis(points, tets, order: int) -> Basis:
    """Vector P1/P2 basis with the quadrature of :mod:`liverforce.fem.elements`."""
    mesh = skfem.MeshTet(np.asarray(points, float).T, np.asarray(tets).T)
    elem = ElementTetP1() if order == 1 else ElementTetP2()
    return Basis(mesh, ElementVector(elem), intorder=0 if order == 1 else 2)


def _deformation(u_field):
    return _tensor_last(grad(u_field)) + np.eye(3)


def _mean_dilatation(basis: Basis, u, material):
    """Element mean dilatation ``J_e = int J / V_e`` and ``p_e``, ``kappa_e`` on (ne, nq)."""
    F = _deformation(basis.interpolate(u))
    J = kin.det3(F)
    dx = basis.dx
    V = dx.sum(axis=1)
    Jbar = (J * dx).sum(axis=1) / V
    _, dU, d2U = material.volumetric(Jbar)
    nq = dx.shape[1]
    return np.repeat(dU[:, None], nq, 1), d2U / V


def internal_force(basis: Basis, u: np.ndarray, material, mean_dilatation: bool) -> np.ndarray:
    """``r(v)`` assembled by scikit-fem (its dof numbering)."""
    p_elem = _mean_dilatation(basis, u, material)[0] if mean_dilatation else None

    @LinearForm
    def residual(v, w):
        F = _deformation(w["u"])
        _, P, _ = material.isochoric(F, tangent=False)
        J, cof, _ = kin.jacobian(F, hessian=False)
        p = p_elem if mean_dilatation else material.volumetric(J)[1]
        return ddot(_tensor_first(P + p[..., None, None] * cof), grad(v))

    return asm(residual, basis, u=basis.interpolate(u))


def tangent(basis: Basis, u: np.ndarray, material, mean_dilatation: bool):
    """``a(du, v)`` assembled by scikit-fem (sparse, its dof numbering)."""
    p_elem, kappa = _mean_dilatation(basis, u, material) if mean_dilatation else (None, None)

    @BilinearForm
    def stiffness(du, v, w):
        F = _deformation(w["u"])
        _, _, A = material.isochoric(F)
        J, cof, d2J = kin.jacobian(F)
        if mean_dilatation:
            A = A + p_elem[..., None, None, None, None] * d2J
        else:
            _, dU, d2U = material.volumetric(J)
            A = A + d2U[..., None, None, None, None] * kin.outer(cof, cof) + dU[..., None, None, None, None] * d2J
        A = np.moveaxis(A, (0, 1), (-2, -1))  # (3, 3, 3, 3, ne, nq)
        gv, gdu = grad(v), grad(du)
        return np.einsum("ij...,ijkl...,kl...->...", gv, A, gdu)

    K = asm(stiffness, basis, u=basis.interpolate(u))
    if mean_dilatation:
        pbasis = basis.with_element(ElementTetP0())

        @BilinearForm
        def coupling(q, v, w):
            _, cof, _ = kin.jacobian(_deformation(w["u"]), hessian=False)
            return q * ddot(_tensor_first(cof), grad(v))

        B = asm(coupling, pbasis, basis, u=basis.interpolate(u))  # (n_u, n_elements)
        K = K + B @ sp.diags(kappa) @ B.T
    return K


def node_map(basis: Basis, nodes: np.ndarray) -> np.ndarray:
    """Index of each of our nodes in scikit-fem's nodal numbering (by position)."""
    from scipy.spatial import cKDTree

    locs = basis.doflocs[:, ::3].T  # one location per node (interleaved dofs)
    dist, idx = cKDTree(locs).query(nodes)
    if dist.max() > 1e-9 * max(1.0, np.abs(nodes).max()):
        raise ValueError("node positions do not match scikit-fem's dof locations")
    return idx


def dof_map(basis: Basis, nodes: np.ndarray) -> np.ndarray:
    """scikit-fem dof index of each of our interleaved dofs."""
    nm = node_map(basis, nodes)
    return (3 * nm[:, None] + np.arange(3)).ravel()
