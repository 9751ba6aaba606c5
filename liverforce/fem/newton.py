"""Static Newton–Raphson with adaptive load stepping (total Lagrangian).

The discrete problem is stationarity of the potential

.. math::

    \Pi(u) = \Pi_{int}(u) + \tfrac12 u^T K_s u - f^T u,
    \qquad u_c = \bar u_c \ \text{on constrained dofs},

plus, optionally, a piecewise-smooth contact penalty ``Pi_c(u)`` (the
unilateral rib, :class:`~liverforce.fem.boundary.UnilateralPenalty`; Newton
then uses its generalised tangent on the current active set: semismooth
Newton), with dead loads ``f`` and prescribed values ``u_bar`` moved along a load
path ``f(lambda)``, ``lambda`` in (0, 1]: ``lambda f_ext`` from rest (cold
start) or ``f0 + lambda (f_ext - f0)`` from a neighbouring solution ``u0`` in
equilibrium with ``f0`` (warm start; tried first at ``lambda = 1``).

Per load step, Newton iterations on the free dofs with a backtracking line
search on ``Pi`` (Armijo with quadratic interpolation; trials that invert an
element are halved; near round-off a residual decrease is accepted). A step
that diverges, inverts elements, meets NaN, stalls or exceeds ``max_iter`` is
cut back (``cutback``); easy steps grow the next one (``growth``). Prescribed
displacement increments get a linearised predictor, later steps a secant
predictor.

Modified Newton (``modified_newton``): the factorised tangent is kept across
iterations, load steps and cases and improved by L-BFGS secant updates; it is
refactorised when the observed contraction predicts more iterations than a
factorisation is worth (``refactor_cost``).

Convergence of a step: ``||R_free||_2 <= tol * ref`` with ``ref`` the largest
of the applied-load, reaction and foundation-force norms, and the last
correction ``||du||_inf <= tol_disp * max(||u||_inf, 1e-3 mm)`` (or a residual
1000× below tolerance). If corrections reach round-off
(``||du|| <= 1e-13 ||u||``) with ``||R|| <= 1e-5 ref``, the step is accepted
as converged to round-off (very high ``K/mu``). The solver never raises on
non-convergence: it returns ``converged=False`` with a reason.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from .assembly import Assembler, SparsityPattern, formulation_spec
from .elements import TetDiscretization, build_discretization
from .linsolve import LinearSolver


# appended to a wall-time stop: unlike the iteration budget, its outcome depends on the machine's speed and load
_SAFETY_NET = (": the wall-time safety net (simulate.time_limit_s). The machine was slow or overloaded, or the case "
               "needs longer than the limit, so this outcome depends on the machine; the deterministic budget is "
               "simulate.max_total_iter")


@dataclass
class SolverOptions:
    """Options of the nonlinear solver.

    Attributes
    ----------
    formulation : "p2_mean_dilatation" (default, locking-free), "p1" or "p2".
    tol : relative force-residual tolerance.
    tol_disp : relative tolerance on the last Newton correction (safeguard).
    max_iter : Newton iterations per load step before a cut-back. With
        ``modified_newton``, iterations on a kept factorisation cost about
        ``1 / refactor_cost`` of a factorised one and the cap is
        ``max_iter + ceil(refactor_cost)``.
    max_total_iter : Newton iterations per case: the deterministic budget (the pipeline's
        ``simulate.max_total_iter``).
    initial_step : first load fraction of a cold start.
    min_step : smallest load-fraction increment before giving up.
    max_step : largest load-fraction increment.
    max_steps : load steps per case (accepted + rejected).
    growth : step growth factor after an easy step (<= ``easy_iter`` iterations).
    easy_iter : see ``growth``.
    cutback : step reduction factor after a failed step.
    time_limit_s : wall-time limit per case (s): a safety net; a case stopped by it depends
        on the machine's load, one stopped by ``max_total_iter`` does not.
    modified_newton : keep the factorisation (also across cases) while the
        residual contracts fast enough; see ``refactor_cost``.
    refactor_cost : cost of a factorisation in cheap iterations (residual +
        solve); ``None`` estimates it from the problem size as
        ``15 (n_free / 15000)^(2/3)`` (factorisation work grows faster than
        solve work; measured ~10 at 15k and ~35 at 64k P2 dofs), clipped to
        [6, 60]. With a kept factorisation, a new one is computed when the
        current contraction rate ``rho`` predicts more than ``refactor_cost + 4``
        further iterations to reach ``tol`` (a fresh tangent needs ~4), when
        that rate would exceed the step's iteration cap, or when ``rho > modified_ratio_max``.
    modified_ratio_max : contraction factor that always triggers a refactorisation.
    quasi_newton : with ``modified_newton``, improve the kept factorisation by
        L-BFGS updates (secant pairs of the residual) between refactorisations.
    quasi_newton_memory : number of L-BFGS pairs kept.
    line_search : backtracking line search.
    max_line_search : backtracking trials per Newton iteration.
    linear_solver : "auto", "cholmod" or "superlu".
    """

    formulation: str = "p2_mean_dilatation"
    tol: float = 1e-7
    tol_disp: float = 1e-4
    max_iter: int = 20
    max_total_iter: int = 300
    initial_step: float = 0.5
    min_step: float = 1e-3
    max_step: float = 1.0
    max_steps: int = 60
    growth: float = 2.0
    easy_iter: int = 6
    cutback: float = 0.5
    time_limit_s: float = 300.0
    modified_newton: bool = False
    refactor_cost: float | None = None
    modified_ratio_max: float = 0.9
    quasi_newton: bool = True
    quasi_newton_memory: int = 20
    line_search: bool = True
    max_line_search: int = 6
    linear_solver: str = "auto"

    def __post_init__(self):
        formulation_spec(self.formulation)
        if not (0 < self.min_step <= self.initial_step <= 1.0):
            raise ValueError("SolverOptions: need 0 < min_step <= initial_step <= 1")
        if not (0 < self.cutback < 1) or self.growth < 1:
            raise ValueError("SolverOptions: need 0 < cutback < 1 and growth >= 1")
        if self.tol <= 0 or self.max_iter < 1:
            raise ValueError("SolverOptions: tol must be > 0 and max_iter >= 1")


@dataclass
class NewtonResult:
    """Outcome of :meth:`DiscreteSystem.solve` (all dofs, full load unless failed)."""

    u: np.ndarray
    converged: bool
    reason: str
    load_fraction: float
    load_steps: int
    newton_iterations: int
    final_residual: float
    wall_time_s: float
    linear_solver: str
    factorizations: int
    f_int: np.ndarray | None = None
    f_load: np.ndarray | None = None
    history: list = field(default_factory=list)
    timings: dict = field(default_factory=dict)


class _StepFailure(Exception):
    pass


class DiscreteSystem:
    """A meshed body with constrained dofs and a constant foundation stiffness.

    Parameters
    ----------
    points, tets : vertices (mm) and tetrahedra.
    fixed_dofs : constrained dofs (interleaved numbering of the formulation's nodes).
    spring : (n_dofs, n_dofs) constant foundation stiffness or None.
    options : :class:`SolverOptions`.
    disc : optional prebuilt discretisation (must match the formulation order).
    contact : optional nonlinear boundary term (e.g.
        :class:`~liverforce.fem.boundary.UnilateralPenalty`) with ``energy_force(u)``,
        ``tangent_values(u)`` on its static ``rows`` / ``cols``: its energy joins the
        potential, its force the residual and its generalised tangent the Newton
        matrix (semismooth Newton on a piecewise-smooth penalty).
    """

    def __init__(self, points, tets, fixed_dofs, spring=None, options: SolverOptions | None = None,
                 disc: TetDiscretization | None = None, contact=None):
        self.options = options or SolverOptions()
        order, mean_dil = formulation_spec(self.options.formulation)
        self.disc = disc if disc is not None else build_discretization(points, tets, order)
        if self.disc.order != order:
            raise ValueError("discretisation order does not match the formulation")
        n = self.disc.n_dofs
        self.fixed = np.unique(np.asarray(fixed_dofs, dtype=np.int64))
        free = np.ones(n, bool)
        free[self.fixed] = False
        self.free = free
        self.pattern = SparsityPattern(self.disc.element_dofs, free)
        self.assembler = Assembler(self.disc, mean_dil, self.pattern)
        self.spring = sp.csr_matrix((n, n)) if spring is None else sp.csr_matrix(spring)
        coo = self.spring.tocoo()
        pos = self.pattern.positions(coo.row, coo.col)
        self._spring_pos = pos[pos >= 0]
        self._spring_val = coo.data[pos >= 0]
        self.contact = contact
        if contact is not None:
            cpos = self.pattern.positions(contact.rows, contact.cols)
            self._contact_keep = cpos >= 0
            self._contact_pos = cpos[self._contact_keep]
        self.linear = LinearSolver(self.options.linear_solver)
        #: lower bound (N) of the residual's reference force; 0 = none. A displacement-controlled
        #: path (:func:`~liverforce.fem.indenter.indent`) sets it to the force scale of the path, so
        #: that a state with no load at all (a retracted indenter) can still meet the tolerance.
        self.ref_force_floor = 0.0

    # ------------------------------------------------------------------
    def tangent_matrix(self, data: np.ndarray, u: np.ndarray | None = None) -> sp.csr_matrix:
        """Reduced tangent (free × free) from element data plus the foundation springs.

        With a ``contact`` term, its generalised tangent at ``u`` (default the rest
        state, where a unilateral contact counts as touching) is added too.
        """
        d = data.copy()
        np.add.at(d, self._spring_pos, self._spring_val)
        if self.contact is not None:
            uc = np.zeros(self.disc.n_dofs) if u is None else u
            vals = self.contact.tangent_values(uc)[self._contact_keep]
            d += np.bincount(self._contact_pos, weights=vals, minlength=d.size)
        return self.pattern.matrix(d)

    def boundary_force(self, u: np.ndarray) -> np.ndarray:
        """Force of the foundation springs and the contact term at ``u`` (full dofs)."""
        fs = self.spring @ u
        if self.contact is not None:
            fs = fs + self.contact.energy_force(u)[1]
        return fs

    def _evaluate(self, u, material, f_load, tangent):
        ev = self.assembler.evaluate(u, material, tangent)
        if not ev.valid:
            return ev, None, None
        fs = self.spring @ u
        energy = ev.energy + 0.5 * float(u @ fs) - float(f_load @ u)
        if self.contact is not None:
            e_c, f_c = self.contact.energy_force(u)
            energy += e_c
            fs = fs + f_c
        R = ev.f_int + fs - f_load
        ev.energy = energy
        ref = max(
            float(np.linalg.norm(f_load)),
            float(np.linalg.norm(R[self.fixed])) if self.fixed.size else 0.0,
            float(np.linalg.norm(fs)),
            self.ref_force_floor,
            1e-12,
        )
        return ev, R, ref

    # ------------------------------------------------------------------
    def solve(self, material, f_ext=None, u_bar=None, u0=None, f0=None,
              options: SolverOptions | None = None) -> NewtonResult:
        """Solve for the full load; never raises on non-convergence.

        Parameters
        ----------
        material : :class:`~liverforce.fem.materials.Material`.
        f_ext : (n_dofs,) dead nodal loads at full load (N).
        u_bar : (n_fixed,) prescribed values on ``fixed_dofs`` at full load (mm; default 0).
        u0 : (n_dofs,) warm start (e.g. the solution of a neighbouring case).
        f0 : (n_dofs,) the load at which ``u0`` is in equilibrium. If given, a
            warm start that fails at full load continues from ``(u0, f0)`` along
            ``f0 + lambda (f_ext - f0)`` with cut-backs instead of restarting cold.
        options : overrides the system's options for this solve (same formulation).

        Notes
        -----
        Load path of a cold start: ``lambda f_ext`` and ``lambda u_bar`` from
        ``lambda = initial_step`` to 1. Warm start: first the full load from
        ``u0``; on failure the continuation above (if ``f0``), else a cold start.
        """
        opt = options or self.options
        t_start = time.perf_counter()
        n = self.disc.n_dofs
        f_ext = np.zeros(n) if f_ext is None else np.asarray(f_ext, float)
        u_bar = np.zeros(self.fixed.size) if u_bar is None else np.asarray(u_bar, float)
        stats = {"iters": 0, "steps": 0, "factorizations": 0, "history": [], "last_res": np.nan}
        timings0 = dict(self.assembler.timings)
        lin0 = (self.linear.time_factorize, self.linear.time_solve)

        current = {"f": np.zeros(n)}

        def finish(u, ok, reason, lam, f_int=None):
            tm = {k: self.assembler.timings[k] - timings0[k] for k in timings0}
            tm["factorize"] = self.linear.time_factorize - lin0[0]
            tm["solve"] = self.linear.time_solve - lin0[1]
            return NewtonResult(u, ok, reason, lam, stats["steps"], stats["iters"], stats["last_res"],
                                time.perf_counter() - t_start, self.linear.backend or "none",
                                stats["factorizations"], f_int, current["f"], stats["history"], tm)

        # attempts: (kind, start state, start load, start prescribed values, first step)
        attempts = []
        if u0 is not None:
            u0 = np.asarray(u0, float).copy()
            if f0 is not None:
                attempts.append(("warm", u0, np.asarray(f0, float), u0[self.fixed].copy(), 1.0))
            else:
                attempts.append(("warm-guess", u0, None, None, 1.0))
        attempts.append(("cold", np.zeros(n), np.zeros(n), np.zeros(self.fixed.size),
                         min(opt.initial_step, opt.max_step)))
        reason = ""
        for kind, u, fa, ua, step in attempts:
            lam = 0.0
            u_prev, lam_prev = None, 0.0
            current["f"] = f_ext if kind == "warm-guess" else fa
            f_int = None
            while True:
                if time.perf_counter() - t_start > opt.time_limit_s:
                    return finish(u, False, f"time limit {opt.time_limit_s:g} s reached{_SAFETY_NET}", lam)
                if stats["steps"] >= opt.max_steps:
                    return finish(u, False, f"max_steps={opt.max_steps} load steps reached", lam)
                target = min(1.0, lam + step)
                if kind == "warm-guess":
                    f_t, ub_t = f_ext, u_bar
                else:
                    f_t, ub_t = fa + target * (f_ext - fa), ua + target * (u_bar - ua)
                u_try = u.copy()
                u_try[self.fixed] = ub_t
                if u_prev is not None and lam - lam_prev > 0:  # secant predictor
                    u_sec = u + (target - lam) / (lam - lam_prev) * (u - u_prev)
                    u_sec[self.fixed] = ub_t
                    u_try = self._better_start(u_try, u_sec, material, f_t)
                elif np.any(ub_t != u[self.fixed]):  # prescribed displacements move
                    u_lin = self._dirichlet_predictor(u, ub_t, f_t, material, stats)
                    if u_lin is not None:
                        u_try = self._better_start(u_try, u_lin, material, f_t)
                stats["steps"] += 1
                try:
                    u_new, its, f_int = self._newton(material, f_t, u_try, u, ub_t, opt, stats, t_start, target)
                except _StepFailure as exc:
                    reason = str(exc)
                    stats["history"].append((kind, target, False, reason))
                    if reason.startswith("time limit") or reason.startswith("max_total_iter"):
                        return finish(u, False, reason, lam if kind == "cold" else 0.0)
                    if kind == "warm-guess":
                        break  # no load path known from the guess: restart cold
                    step *= opt.cutback
                    if step < opt.min_step:
                        if kind == "warm":
                            break
                        return finish(u, False, f"load step below min_step at load fraction {lam:.4g}: {reason}", lam)
                    continue
                stats["history"].append((kind, target, True, its))
                u_prev, lam_prev = u, lam
                u, lam = u_new, target
                current["f"] = f_t
                if lam >= 1.0:
                    return finish(u, True, "converged", 1.0, f_int)
                if its <= opt.easy_iter:
                    step = min(step * opt.growth, opt.max_step)
        return finish(np.zeros(n), False, reason or "no attempt", 0.0)  # pragma: no cover

    def _dirichlet_predictor(self, u, ub_t, f_load, material, stats):
        """Linearised response to a prescribed-displacement increment.

        Solves ``K_ff(u) d_f = -(R_f(u) + K_fc du_c)`` with ``du_c`` the
        increment of the prescribed values; ``K_fc du_c`` is a directional
        finite difference of the residual. Returns None if not computable.
        """
        du = np.zeros_like(u)
        du[self.fixed] = ub_t - u[self.fixed]
        ev0, R0, _ = self._evaluate(u, material, f_load, tangent=True)
        if not ev0.valid:
            return None
        eps = 1e-7 * max(1.0, float(np.abs(u).max())) / max(float(np.abs(du).max()), 1e-300)
        ev1, R1, _ = self._evaluate(u + eps * du, material, f_load, tangent=False)
        if not ev1.valid:
            return None
        try:
            self.linear.factorize(self.tangent_matrix(ev0.data, u), shift=True)
        except (RuntimeError, ValueError):
            return None
        stats["factorizations"] += 1
        rhs = R0 + (R1 - R0) / eps
        du[self.free] = -self.linear.solve(rhs[self.free])
        return u + du if np.all(np.isfinite(du)) else None

    def _better_start(self, u_a, u_b, material, f_load):
        """The start (last state or a prediction) with the lower potential."""
        ev_b, _, _ = self._evaluate(u_b, material, f_load, tangent=False)
        if not ev_b.valid:
            return u_a
        ev_a, _, _ = self._evaluate(u_a, material, f_load, tangent=False)
        if not ev_a.valid or ev_b.energy < ev_a.energy:
            return u_b
        return u_a

    # ------------------------------------------------------------------
    def _newton(self, material, f_load, u, u_last, ub_t, opt, stats, t_start, lam):
        """Newton iterations at one load level; returns (u, iterations, f_int) or raises _StepFailure."""
        free = self.free
        full = not opt.modified_newton
        ev, R, ref = self._evaluate(u, material, f_load, tangent=full)
        if not ev.valid:  # predictor inverted an element: restart from last converged state
            u = u_last.copy()
            u[self.fixed] = ub_t
            ev, R, ref = self._evaluate(u, material, f_load, tangent=full)
            if not ev.valid:
                raise _StepFailure(f"inverted element at load fraction {lam:.4g} (min J {ev.min_J:.3g})")
        norm = float(np.linalg.norm(R[free]))
        norm0 = norm
        du_inf = np.inf
        best, stall = norm, 0
        refactor = full or not self.linear.has_factor
        memory: list = []  # BFGS pairs (s, y, 1/(y.s)) on top of a kept factorisation
        # cheap iterations on a kept factorisation may run past max_iter, up to one factorisation's worth
        limit = opt.max_iter if full else opt.max_iter + int(np.ceil(self._refactor_cost(opt)))
        for it in range(limit + 1):
            stats["last_res"] = norm / ref
            if not np.isfinite(norm):
                raise _StepFailure(f"NaN residual at load fraction {lam:.4g}")
            u_inf = max(float(np.abs(u).max()), 1e-3)
            if norm <= opt.tol * ref and (du_inf <= opt.tol_disp * u_inf or norm <= 1e-3 * opt.tol * ref):
                return u, it, ev.f_int
            if du_inf <= 1e-13 * u_inf and norm <= 1e-5 * ref:  # limited by round-off
                return u, it, ev.f_int
            if it == limit:
                break
            if stats["iters"] >= opt.max_total_iter:
                raise _StepFailure("max_total_iter: the case's budget of Newton iterations (simulate.max_total_iter) "
                                   "is spent")
            if time.perf_counter() - t_start > opt.time_limit_s:  # no number: opt may hold only what is left
                raise _StepFailure(f"time limit reached at load fraction {lam:.4g}{_SAFETY_NET}")
            if norm > 1e8 * max(norm0, 1e-12 * ref):
                raise _StepFailure(f"diverged at load fraction {lam:.4g} (residual grew {norm / norm0:.2g}x)")
            if refactor:
                if ev.data is None:
                    ev_t, _, _ = self._evaluate(u, material, f_load, tangent=True)
                    ev.data = ev_t.data
                try:
                    self.linear.factorize(self.tangent_matrix(ev.data, u), shift=True)
                except (RuntimeError, ValueError) as exc:
                    raise _StepFailure(f"linear solver failed at load fraction {lam:.4g}: {exc}") from exc
                stats["factorizations"] += 1
                memory = []
            stats["iters"] += 1
            Rf = R[free]
            du = np.zeros_like(u)
            du[free] = -self._apply_inverse(Rf, memory)
            if not np.all(np.isfinite(du)):
                raise _StepFailure(f"singular tangent at load fraction {lam:.4g}")
            slope = float(du[free] @ Rf)
            accepted = self._line_search(u, du, ev, norm, slope, material, f_load, full, opt)
            if accepted is None:
                raise _StepFailure(f"every line-search trial inverted elements at load fraction {lam:.4g}")
            alpha, ev_new, R_new, n_new, ref = accepted
            if opt.modified_newton and opt.quasi_newton:
                step_f = alpha * du[free]
                y = R_new[free] - Rf
                ys = float(y @ step_f)
                if ys > 1e-12 * np.linalg.norm(y) * np.linalg.norm(step_f):
                    memory.append((step_f, y, 1.0 / ys))
                    if len(memory) > opt.quasi_newton_memory:
                        memory.pop(0)
            R = R_new
            u = u + alpha * du
            du_inf = alpha * float(np.abs(du).max())
            ratio = n_new / norm if norm > 0 else 0.0
            progress = ev_new.energy < ev.energy - 1e-11 * abs(ev.energy) or n_new < 0.999 * best
            ev, norm = ev_new, n_new
            if full:
                refactor = True
            elif ratio >= opt.modified_ratio_max or not n_new > 0:
                refactor = True
            else:  # predicted iterations to tol at the current rate vs the cost of a fresh tangent
                remaining = np.log(max(opt.tol * ref / n_new, 1e-300)) / np.log(max(ratio, 1e-300))
                refactor = remaining > self._refactor_cost(opt) + 4.0 or it + 1 + remaining > limit
            best = min(best, norm)
            stall = 0 if progress else stall + 1
            if stall >= 4:
                raise _StepFailure(f"no progress in 4 Newton iterations at load fraction {lam:.4g}")
        raise _StepFailure(f"{limit} Newton iterations (max_iter={opt.max_iter}"
                           f"{'' if full else ' + refactor_cost'}) reached at load fraction {lam:.4g}"
                           f" (residual {norm / ref:.2e})")

    def _refactor_cost(self, opt) -> float:
        if opt.refactor_cost is not None:
            return float(opt.refactor_cost)
        return float(np.clip(15.0 * (self.pattern.n / 15000.0) ** (2.0 / 3.0), 6.0, 60.0))

    def _apply_inverse(self, r, memory):
        """``H r`` with ``H`` the L-BFGS inverse built on the factorised tangent ``K0^-1``."""
        if not memory:
            return self.linear.solve(r)
        q = r.copy()
        coeffs = []
        for s_k, y_k, rho in reversed(memory):
            a = rho * float(s_k @ q)
            q -= a * y_k
            coeffs.append(a)
        z = self.linear.solve(q)
        for (s_k, y_k, rho), a in zip(memory, reversed(coeffs)):
            b = rho * float(y_k @ z)
            z += (a - b) * s_k
        return z

    # ------------------------------------------------------------------
    def _line_search(self, u, du, ev, norm, slope, material, f_load, full, opt):
        """Backtracking on the potential (Armijo, quadratic interpolation).

        Trials that invert an element are halved. When the energy change or
        the decrease the slope predicts is below the energy's round-off (close
        to convergence, tiny loads) or ``du`` is not a descent direction
        (indefinite tangent), a decrease of the residual norm is accepted
        instead. Returns (alpha, evaluation, R, |R_free|, ref) or None.
        """
        free = self.free
        e0 = ev.energy
        noise = 1e-10 * (abs(e0) + abs(float(f_load @ u)) + 1e-30)
        alpha, best = 1.0, None
        tries = opt.max_line_search + 1 if opt.line_search else 1
        for _ in range(tries):
            ev_t, R_t, ref_t = self._evaluate(u + alpha * du, material, f_load, tangent=full)
            if not ev_t.valid:
                alpha *= 0.5
                continue
            n_t = float(np.linalg.norm(R_t[free]))
            if not np.isfinite(n_t) or not np.isfinite(ev_t.energy):
                alpha *= 0.5
                continue
            cand = (alpha, ev_t, R_t, n_t, ref_t)
            de = ev_t.energy - e0
            if not opt.line_search:
                return cand
            if slope < 0:
                # the expected decrease below the energy's round-off: only the residual can judge the step
                blind = -alpha * slope <= 10.0 * noise
                if de <= 1e-4 * alpha * slope or ((abs(de) <= noise or blind) and n_t < norm):
                    return cand
                if best is None or ev_t.energy < best[1].energy:
                    best = cand
                # minimiser of the quadratic through e0, slope and e(alpha)
                a_new = -slope * alpha**2 / (2.0 * (de - slope * alpha))
                alpha = float(np.clip(a_new, 0.1 * alpha, 0.5 * alpha))
            else:
                if n_t < norm:
                    return cand
                if best is None or n_t < best[3]:
                    best = cand
                alpha *= 0.5
        return best
