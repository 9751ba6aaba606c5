"""Warm starts across cases: the load-space distance, the case chain and the pool of recent solutions."""
import numpy as np
import pytest

from liverforce.fem import BoundaryParams, LiverModel, SolverOptions, ToolLoad, make_material
from liverforce.fem.continuation import WarmStartPool, case_distance, chain_order
from liverforce.fem.testing import ellipsoid_liver
from liverforce.sweep.design import force_vectors

P0 = np.array([0.0, 0.0, 0.0])
P1 = np.array([30.0, 0.0, 0.0])
MAT = [1.61e-3, 12.5e-3, 5.31e-3]


def test_distance_same_point_other_point_and_material():
    fa, fb = np.array([0.0, 0.0, -3.0]), np.array([0.0, 1.0, -3.0])
    assert case_distance(P0, fa, MAT, P0, fb, MAT) == pytest.approx(1.0)
    assert case_distance(P0, fa, MAT, P1, fb, MAT) == pytest.approx(np.hypot(3.0, np.sqrt(10.0)))
    # symmetric, zero for the same case
    assert case_distance(P0, fa, MAT, P1, fb, MAT) == pytest.approx(case_distance(P1, fb, MAT, P0, fa, MAT))
    assert case_distance(P0, fa, MAT, P0, fa, MAT) == 0.0
    # every constant 20 % lower at the same 3 N load: the stiffness change unbalances ~0.2 x 3 N
    assert case_distance(P0, fa, MAT, P0, fa, [0.8 * c for c in MAT]) == pytest.approx(0.2 * 3.0)
    # a material change matters little at small loads
    small = np.array([0.0, 0.0, -0.1])
    assert case_distance(P0, small, MAT, P0, small, [0.8 * c for c in MAT]) == pytest.approx(0.02)
    assert case_distance(P0, fa, MAT, P0, fa, MAT[:2]) == np.inf  # another material model


def _cone_forces(n, seed):
    rng = np.random.default_rng(seed)
    return force_vectors(rng.random(n), rng.random(n), rng.random(n), np.tile(np.eye(3), (n, 1, 1)), 0.0, 5.0, 30.0)


def test_chain_starts_small_visits_all_and_each_step_is_the_nearest_left():
    f = _cone_forces(40, 0)
    p = np.tile(MAT, (40, 1)) * (1 + 0.3 * (2 * np.random.default_rng(1).random((40, 3)) - 1))
    order = chain_order(f, p)
    assert sorted(order) == list(range(40))
    assert order[0] == int(np.argmin(np.linalg.norm(f, axis=1)))
    for k in range(len(order) - 1):
        i, left = order[k], order[k + 1:]
        d = [case_distance(P0, f[i], p[i], P0, f[j], p[j]) for j in left]
        assert case_distance(P0, f[i], p[i], P0, f[order[k + 1]], p[order[k + 1]]) == pytest.approx(min(d))
    assert chain_order(np.zeros((0, 3)), np.zeros((0, 3))) == []


def test_chain_steps_are_shorter_than_sorting_by_magnitude():
    f = _cone_forces(25, 3)
    p = np.tile(MAT, (25, 1))

    def path(order):
        return sum(np.linalg.norm(f[a] - f[b]) for a, b in zip(order[:-1], order[1:]))

    chain, by_mag = chain_order(f, p), list(np.argsort(np.linalg.norm(f, axis=1)))
    assert path(chain) < 0.8 * path(by_mag), (path(chain), path(by_mag))


class _Res:
    def __init__(self, point, force, converged=True):
        self.load = ToolLoad(point, force, 5.0)
        self.converged = converged


def test_pool_picks_the_nearest_kept_solution_or_rest():
    pool = WarmStartPool(size=3)
    a, b = _Res(P0, [0, 0, -1.0]), _Res(P0, [0, 0, -3.0])
    pool.add(a, MAT)
    pool.add(b, MAT)
    pool.add(_Res(P0, [0, 0, -2.9], converged=False), MAT)  # failed cases are never offered
    assert len(pool) == 2
    assert pool.nearest(ToolLoad(P0, [0, 0.2, -2.8], 5.0), MAT) is b
    assert pool.nearest(ToolLoad(P0, [0, 0, -1.2], 5.0), MAT) is a
    assert pool.nearest(ToolLoad(P0, [0, 0, -0.3], 5.0), MAT) is None  # rest (0 N) is nearer than 1 N
    assert pool.nearest(ToolLoad(P1, [0, 0, -3.0], 5.0), MAT) is None  # another point: from rest
    for k in range(3):  # only the last `size` are kept
        pool.add(_Res(P1, [0, 0, -4.0 - k]), MAT)
    assert pool.nearest(ToolLoad(P0, [0, 0, -3.0], 5.0), MAT) is None
    with pytest.raises(ValueError):
        WarmStartPool(size=0)


def test_warm_start_from_the_pool_solves_the_same_case():
    L = ellipsoid_liver(2)
    x0 = L["points"][np.argmax(L["points"][:, 2] + 0.3 * L["points"][:, 1])]
    mat = make_material("yeoh", dict(zip(("C10", "C20", "C30"), MAT)), nu=0.49)
    model = LiverModel(L["points"], L["tets"], L["facets"], L["facet_region"], mat,
                       BoundaryParams.from_totals(L["points"], L["facets"], L["facet_region"]),
                       SolverOptions(modified_newton=True, tol=1e-9))
    pool = WarmStartPool()
    for f in ([0, 0, -1.0], [0, 0, -2.0]):
        pool.add(model.solve(ToolLoad(x0, f, 5.0), u0=pool.nearest(ToolLoad(x0, f, 5.0), MAT)), MAT)
    load = ToolLoad(x0, [0.2, 0.0, -2.3], 5.0)
    start = pool.nearest(load, MAT)
    assert start is not None and start.load.force_N[2] == -2.0
    warm, cold = model.solve(load, u0=start), model.solve(load)
    assert warm.converged and cold.converged and warm.load_steps < cold.load_steps
    assert np.abs(warm.u_nodes - cold.u_nodes).max() <= 1e-6 * np.abs(cold.u_nodes).max()
