"""A case's budget is counted in Newton iterations, not timed, so the dataset does not depend on machine load.

* a traction case over ``max_total_iter`` stops after exactly that many iterations, naming the config key;
* with the process clock running 200x faster than real time (every step seemingly 200x slower, as on an
  overloaded machine), a converged case and a budget-stopped one give the same state, reason and iteration count
  as at full speed: below the wall-time safety net, nothing timed decides a case;
* a magnitude-controlled sphere case's budget holds over all its pushes (each push used to get a whole budget of
  its own); a force-controlled one's over its first push and its direct centre moves (on this body it never
  falls back to a stepped move);
* the pipeline's ``simulate.max_total_iter`` reaches the solver; a budget below ``max_iter`` is refused.
"""

import time

import numpy as np
import pytest

from liverforce.config import ConfigError, compose
from liverforce.fem import BoundaryParams, LiverModel, ToolLoad, make_material
from liverforce.fem import indenter as indenter_mod
from liverforce.fem import newton as newton_mod
from liverforce.fem.indenter import LiverIndenter
from liverforce.fem.newton import SolverOptions
from liverforce.fem.testing import ellipsoid_liver
from liverforce.pipeline.simulate import solver_options

YEOH = {"C10": 1.61e-3, "C20": 12.5e-3, "C30": 5.31e-3}


@pytest.fixture(scope="module")
def liver():
    m = ellipsoid_liver(nrefs=2)
    mat = make_material("yeoh", YEOH, nu=0.49)
    bp = BoundaryParams.from_totals(m["points"], m["facets"], m["facet_region"])
    model = LiverModel(m["points"], m["tets"], m["facets"], m["facet_region"], mat, bp,
                       SolverOptions(formulation="p1"))
    P = m["points"][np.unique(m["facets"][m["facet_visible"]])]
    x0 = P[np.argmax(P[:, 1] + P[:, 2])]  # anterior-superior, away from the IVC patch
    return model, x0


class _SlowClock:
    """Stands in for the ``time`` module: ``perf_counter`` runs ``factor`` times faster than the real one,
    as if every step of the solve took ``factor`` times longer (an overloaded machine)."""

    def __init__(self, factor):
        self.factor, self.t0 = factor, time.perf_counter()

    def perf_counter(self):
        return self.t0 + self.factor * (time.perf_counter() - self.t0)


def _solve(model, x0, **opts):
    load = ToolLoad(x0, [0.0, -1.5, -1.5], 5.0)
    model.system.linear = type(model.system.linear)("auto")  # no factorisation kept from an earlier solve
    return model.solve(load, options=SolverOptions(formulation="p1", **opts))


def test_a_traction_case_stops_at_its_iteration_budget(liver):
    model, x0 = liver
    full = _solve(model, x0, max_total_iter=10_000)
    assert full.converged, full.reason
    n = full.newton_iterations
    assert n >= 6, n  # a problem that needs several iterations, so a budget can cut it
    cut = _solve(model, x0, max_total_iter=n - 3)
    assert not cut.converged
    assert cut.reason.startswith("max_total_iter") and "simulate.max_total_iter" in cut.reason, cut.reason
    assert cut.newton_iterations == n - 3
    exact = _solve(model, x0, max_total_iter=n)  # the budget is inclusive: n iterations are enough
    assert exact.converged and exact.newton_iterations == n


def test_the_outcome_does_not_depend_on_the_clock(liver, monkeypatch):
    model, x0 = liver
    _solve(model, x0)  # compiled kernels warm, so both runs below time the solve alone
    budgets = (10_000, 4)
    at_speed = [_solve(model, x0, max_total_iter=b, time_limit_s=1e6) for b in budgets]
    monkeypatch.setattr(newton_mod, "time", _SlowClock(200.0))
    slowed = []
    for b in budgets:
        t0 = time.perf_counter()
        slowed.append(_solve(model, x0, max_total_iter=b, time_limit_s=1e6))
        real = time.perf_counter() - t0
        assert slowed[-1].wall_time_s > 100.0 * real  # the solver's clock ran ~200x faster than real time
    for a, s in zip(at_speed, slowed):
        assert (a.converged, a.reason, a.newton_iterations) == (s.converged, s.reason, s.newton_iterations)
        np.testing.assert_array_equal(a.u_nodes, s.u_nodes)
    assert at_speed[0].converged and not at_speed[1].converged


def _indenter(model, x0):
    return LiverIndenter(model, x0, radius_mm=20.0, candidate_radius_mm=100.0)  # touches from the start here


def test_a_sphere_case_keeps_one_budget_over_its_pushes(liver):
    model, x0 = liver
    ind = _indenter(model, x0)
    ref = ind.push([6.0])
    assert ref.converged, ref.reason
    target = float(np.linalg.norm(ref.results[0].force_on_sphere)) * -ind.normal
    opts = SolverOptions(formulation="p1", max_total_iter=10_000)
    free = _indenter(model, x0).push_to_magnitude(target, options=opts, rtol=1e-4)
    assert free.converged, free.reason
    assert free.outer_iterations >= 2, free.outer_iterations  # several pushes: the budget spans them
    n = free.newton_iterations
    budget = n // 2
    cut = _indenter(model, x0).push_to_magnitude(target, rtol=1e-4,
                                                  options=SolverOptions(formulation="p1", max_total_iter=budget))
    assert not cut.converged and "max_total_iter" in cut.reason, cut.reason
    assert cut.newton_iterations == budget, (cut.newton_iterations, budget)


def test_a_force_controlled_sphere_case_keeps_one_budget(liver):
    model, x0 = liver
    ind = _indenter(model, x0)
    ref = ind.push([6.0])
    F = -ref.results[0].force_on_sphere  # the force on the liver
    free = _indenter(model, x0).push_to_force(F, options=SolverOptions(formulation="p1", max_total_iter=10_000),
                                             rtol=1e-4, max_slide_mm=30.0, first_depth_mm=4.0)
    assert free.converged, free.reason
    n = free.newton_iterations
    for budget in (n // 3, (2 * n) // 3):
        cut = _indenter(model, x0).push_to_force(F, options=SolverOptions(formulation="p1", max_total_iter=budget),
                                                rtol=1e-4, max_slide_mm=30.0, first_depth_mm=4.0)
        assert not cut.converged and "max_total_iter" in cut.reason, cut.reason
        assert cut.newton_iterations == budget, (cut.newton_iterations, budget)


def test_the_pipeline_budget_reaches_the_solver():
    sim = compose([])["simulate"]
    opts = solver_options(sim)
    assert opts.max_total_iter == sim["max_total_iter"]
    assert opts.time_limit_s == sim["time_limit_s"]
    assert solver_options(dict(sim, max_total_iter=37)).max_total_iter == 37
    legacy = {k: v for k, v in sim.items() if k != "max_total_iter"}  # settings written before the key
    assert solver_options(legacy).max_total_iter == SolverOptions.max_total_iter
    with pytest.raises(ConfigError, match="simulate.max_total_iter"):
        compose(["simulate.max_total_iter=3"])


def test_the_indenter_budget_helper_subtracts_what_is_spent():
    opt = SolverOptions(formulation="p1", max_total_iter=50, time_limit_s=100.0)
    left = indenter_mod._left_of(opt, {"iters": 20}, time.perf_counter() - 30.0)
    assert left.max_total_iter == 30
    assert 69.0 < left.time_limit_s <= 70.0
    assert indenter_mod._left_of(opt, {"iters": 80}, time.perf_counter()).max_total_iter == 0
