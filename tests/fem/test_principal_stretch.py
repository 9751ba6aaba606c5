"""The principal stretches the solver reports (issue 18: the Drucker range against the stretches reached).

- exact on fields the element interpolates exactly: a homogeneous F (any rotation,
  P1 and P2) and a quadratic displacement (P2), quadrature point by quadrature point;
- a solved homogeneous uniaxial stretch of a block (prescribed end displacement,
  the production formulation and the configured material) gives the prescribed
  stretch and the lateral stretch of the exact compressible solution;
- ``LiverModel.solve`` puts the range into the :class:`CaseResult`.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import brentq
from scipy.spatial.transform import Rotation

from liverforce.fem.elements import TET_Q4, build_discretization
from liverforce.fem.kinematics import principal_stretch_range, principal_stretches
from liverforce.fem.materials import make_material
from liverforce.fem.newton import DiscreteSystem, SolverOptions
from liverforce.fem.testing import box_mesh

YEOH = {"C10": 0.00161, "C20": 0.0125, "C30": 0.00531}  # config/material/yeoh.yaml, MPa


def distorted_box(shape=(3, 3, 3), seed=3):
    points, tets, _ = box_mesh(shape, size=(40.0, 30.0, 20.0))
    interior = np.all((points > 1e-9) & (points < np.array([40.0, 30.0, 20.0]) - 1e-9), axis=1)
    points[interior] += np.random.default_rng(seed).uniform(-2.0, 2.0, (interior.sum(), 3))
    return points, tets


def test_principal_stretches_are_the_singular_values_of_f():
    rng = np.random.default_rng(0)
    F = np.eye(3) + 0.3 * rng.normal(size=(50, 3, 3))
    F[np.linalg.det(F) < 0] *= -1.0
    np.testing.assert_allclose(principal_stretches(F), np.linalg.svd(F, compute_uv=False)[:, ::-1], rtol=1e-12)
    R = Rotation.from_rotvec([0.3, -0.7, 0.2]).as_matrix()
    np.testing.assert_allclose(principal_stretches(R @ np.diag([1.3, 0.8, 1.1])), [0.8, 1.1, 1.3], rtol=1e-13)


@pytest.mark.parametrize("order", [1, 2])
def test_a_homogeneous_deformation_gives_its_stretches_at_every_quadrature_point(order):
    points, tets = distorted_box()
    disc = build_discretization(points, tets, order)
    R = Rotation.from_rotvec([0.4, 0.1, -0.5]).as_matrix()
    F0 = R @ np.diag([1.35, 0.72, 1.02])  # rotation times stretch: the range is 0.72-1.35 whatever R is
    u = disc.nodes @ (F0 - np.eye(3)).T
    lo, hi = principal_stretch_range(disc, u.ravel())
    assert lo == pytest.approx(0.72, abs=1e-12) and hi == pytest.approx(1.35, abs=1e-12)


def test_a_quadratic_displacement_is_exact_in_p2_at_the_quadrature_points():
    """u = (a x^2, b x y, c z^2): F varies over the block; P2 interpolates u exactly, so F at each
    quadrature point (and the range over them) equals the analytic F there."""
    from liverforce.fem.kernels import deformation_gradient

    points, tets = distorted_box()
    disc = build_discretization(points, tets, 2)
    a, b, c = 0.006, -0.004, 0.009
    X = disc.nodes
    u = np.column_stack([a * X[:, 0] ** 2, b * X[:, 0] * X[:, 1], c * X[:, 2] ** 2])
    bary = TET_Q4[0]  # (nq, 4) barycentric coordinates of the quadrature points (straight-edged tets)
    Xq = np.einsum("qa,eaj->eqj", bary, points[disc.tets])
    x, y, z = Xq[..., 0], Xq[..., 1], Xq[..., 2]
    F = np.zeros(Xq.shape[:2] + (3, 3))
    F[..., 0, 0] = 1 + 2 * a * x
    F[..., 1, 0], F[..., 1, 1] = b * y, 1 + b * x
    F[..., 2, 2] = 1 + 2 * c * z
    np.testing.assert_allclose(deformation_gradient(np.ascontiguousarray(u), disc.conn, disc.dN), F, atol=1e-12)
    lam = principal_stretches(F)
    lo, hi = principal_stretch_range(disc, u)
    assert lo == pytest.approx(lam[..., 0].min(), abs=1e-12) and hi == pytest.approx(lam[..., 2].max(), abs=1e-12)
    assert hi > 1.3 and lo < 0.9  # a real range (1 + 2 c z up to 1.36, 1 + b x down to 0.84)


@pytest.mark.parametrize("stretch", [0.7, 1.3])
def test_solved_uniaxial_stretch_of_a_block_reaches_the_prescribed_stretch(stretch):
    """Production formulation (P2 mean dilatation), configured Yeoh at nu 0.49: symmetry planes x=0,
    y=0, z=0 and u_x prescribed on x=L. The solution is homogeneous: the axial principal stretch is
    the prescribed one at every quadrature point, the lateral one makes the lateral stress vanish."""
    L = 10.0
    points, tets, _ = box_mesh((2, 2, 2), size=(L, L, L))
    disc = build_discretization(points, tets, 2)
    X = disc.nodes
    fixed = np.unique(np.concatenate([
        3 * np.flatnonzero(X[:, 0] < 1e-9), 3 * np.flatnonzero(X[:, 1] < 1e-9) + 1,
        3 * np.flatnonzero(X[:, 2] < 1e-9) + 2, 3 * np.flatnonzero(X[:, 0] > L - 1e-9)]))
    system = DiscreteSystem(points, tets, fixed, options=SolverOptions(formulation="p2_mean_dilatation", tol=1e-12,
                                                                       initial_step=0.25), disc=disc)
    mat = make_material("yeoh", YEOH, nu=0.49)
    res = system.solve(mat, u_bar=np.where(fixed % 3 == 0, (stretch - 1.0) * X[fixed // 3, 0], 0.0))
    assert res.converged, res.reason
    lateral = brentq(lambda s: mat.stress(np.diag([stretch, s, s]))[1, 1], 0.3, 3.0, xtol=1e-15)
    lo, hi = principal_stretch_range(disc, res.u)
    expected = sorted([stretch, lateral])
    assert lo == pytest.approx(expected[0], abs=1e-9) and hi == pytest.approx(expected[1], abs=1e-9)


def test_solve_reports_the_range_in_the_case_result():
    from liverforce.fem.problem import BoundaryParams, LiverModel, ToolLoad

    points, tets, facets = box_mesh((3, 3, 2), size=(30.0, 30.0, 15.0))
    region = np.where(points[facets][:, :, 2].max(axis=1) < 1e-9, 1, 0)  # bottom clamped
    mat = make_material("yeoh", YEOH, nu=0.49)
    model = LiverModel(points, tets, facets, region, mat, BoundaryParams(),
                       SolverOptions(formulation="p2_mean_dilatation", tol=1e-10))
    res = model.solve(ToolLoad([15.0, 15.0, 15.0], [0.0, 0.0, -0.5], 4.0))
    assert res.converged, res.reason
    lo, hi = principal_stretch_range(model.disc, res.state)
    assert (res.min_principal_stretch, res.max_principal_stretch) == (lo, hi)
    assert lo < 0.99 and hi > 1.01  # compressed under the tool, stretched around it
    assert np.isnan(principal_stretch_range(model.disc, np.full(model.n_dofs, np.nan))).all()
    assert principal_stretch_range(model.disc, np.zeros(model.n_dofs)) == (1.0, 1.0)
