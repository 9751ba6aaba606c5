"""Homogeneous states: exact compressible solution, incompressible closed form, patch test."""
import numpy as np
import pytest
from scipy.optimize import brentq

from liverforce.fem.elements import build_discretization
from liverforce.fem.materials import make_material
from liverforce.fem.newton import DiscreteSystem, SolverOptions
from liverforce.fem.testing import box_mesh

FORMULATIONS = ["p1", "p2_mean_dilatation"]


def uniaxial_cube(formulation, material, stretch, shape=(2, 2, 2)):
    """Unit cube, symmetry planes x=0, y=0, z=0, prescribed u_x = (stretch-1) on x=1."""
    points, tets, _ = box_mesh(shape)
    order = 1 if formulation == "p1" else 2
    disc = build_discretization(points, tets, order)
    X = disc.nodes
    fixed = np.unique(np.concatenate([
        3 * np.flatnonzero(X[:, 0] < 1e-12), 3 * np.flatnonzero(X[:, 1] < 1e-12) + 1,
        3 * np.flatnonzero(X[:, 2] < 1e-12) + 2, 3 * np.flatnonzero(X[:, 0] > 1 - 1e-12)]))
    opt = SolverOptions(formulation=formulation, tol=1e-12, initial_step=0.25)
    system = DiscreteSystem(points, tets, fixed, options=opt, disc=disc)
    u_bar = np.where(fixed % 3 == 0, (stretch - 1.0) * X[fixed // 3, 0], 0.0)
    res = system.solve(material, u_bar=u_bar)
    right = 3 * np.flatnonzero(X[:, 0] > 1 - 1e-12)
    return res, X, (res.f_int[right].sum() if res.f_int is not None else np.nan)  # nominal stress (unit area)


@pytest.mark.parametrize("formulation", FORMULATIONS)
@pytest.mark.parametrize("stretch", [0.7, 1.3])
def test_uniaxial_matches_exact_compressible_solution(formulation, stretch):
    mat = make_material("yeoh", {"C10": 0.3, "C20": 0.2, "C30": 0.1}, nu=0.45)
    res, X, force = uniaxial_cube(formulation, mat, stretch)
    assert res.converged, res.reason
    # reference: the lateral stretch that makes the lateral stress vanish (same energy)
    lat = brentq(lambda s: mat.stress(np.diag([stretch, s, s]))[1, 1], 0.3, 3.0, xtol=1e-15)
    exact = np.column_stack([(stretch - 1) * X[:, 0], (lat - 1) * X[:, 1], (lat - 1) * X[:, 2]])
    u = res.u.reshape(-1, 3)
    assert np.abs(u - exact).max() <= 1e-8 * np.abs(exact).max()
    P11 = mat.stress(np.diag([stretch, lat, lat]))[0, 0]
    assert force == pytest.approx(P11, rel=1e-8)


@pytest.mark.parametrize("stretch", [0.7, 0.85, 1.15, 1.3])
def test_default_formulation_matches_incompressible_closed_form(stretch):
    C10 = 0.01
    mat = make_material("neo_hookean", {"C10": C10}, bulk_mpa=2e4 * C10)  # K/mu = 1e4
    res, X, force = uniaxial_cube("p2_mean_dilatation", mat, stretch, shape=(1, 1, 1))
    assert res.converged, res.reason
    T_incompressible = 2 * C10 * (stretch - stretch**-2)
    assert force == pytest.approx(T_incompressible, rel=0.01)
    lateral = 1 + res.u.reshape(-1, 3)[np.argmax(X[:, 1]), 1] / X[:, 1].max()
    assert lateral == pytest.approx(stretch**-0.5, rel=0.01)


@pytest.mark.parametrize("formulation", ["p1", "p2", "p2_mean_dilatation"])
def test_patch_test_on_distorted_mesh(formulation):
    points, tets, _ = box_mesh((3, 3, 3))
    interior = np.all((points > 1e-9) & (points < 1 - 1e-9), axis=1)
    rng = np.random.default_rng(7)
    points[interior] += 0.08 * rng.uniform(-1, 1, (interior.sum(), 3))
    order = 1 if formulation == "p1" else 2
    disc = build_discretization(points, tets, order)
    X = disc.nodes
    on_boundary = np.any((X < 1e-9) | (X > 1 - 1e-9), axis=1)
    F0 = np.array([[1.15, 0.1, 0.0], [0.05, 0.9, 0.08], [0.0, -0.04, 1.05]])
    exact = X @ (F0 - np.eye(3)).T
    fixed = (3 * np.flatnonzero(on_boundary)[:, None] + np.arange(3)).ravel()
    system = DiscreteSystem(points, tets, fixed, options=SolverOptions(formulation=formulation, tol=1e-12), disc=disc)
    mat = make_material("mooney_rivlin_2", {"C10": 0.2, "C01": 0.1}, nu=0.45)
    res = system.solve(mat, u_bar=exact.ravel()[fixed])
    assert res.converged, res.reason
    assert np.abs(res.u.reshape(-1, 3) - exact).max() < 1e-9 * np.abs(exact).max()
