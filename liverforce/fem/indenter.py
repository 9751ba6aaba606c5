"""Rigid spherical indenter in frictionless contact (penalty, optionally augmented Lagrangian).

The tool as a rigid sphere of radius ``R`` whose centre ``c`` is prescribed
(displacement control) and moved along a path in load steps. At the facet
quadrature points ``X_q`` of a candidate surface (7-point rule, as
:class:`~liverforce.fem.boundary.UnilateralPenalty`), with the current position
``x = X + u(X)``,

.. math::

    g(u) = R - |x - c| \\quad (> 0: \\text{penetration}), \\qquad
    n = \\frac{x - c}{|x - c|},

and the (augmented) penalty energy per unit *reference* area

.. math::

    \\Pi_c(u) = \\int_\\Gamma \\frac{1}{2k}\\big(\\langle \\lambda + k g\\rangle_+^2
    - \\lambda^2\\big)\\, dA ,\\qquad p = \\langle \\lambda + k g \\rangle_+ ,

which is the plain penalty ``0.5 k <g>_+^2`` for multipliers ``lambda = 0``.
``p`` is the contact pressure (N/mm² per reference area). Gradient (the
force the body exerts on the sphere, assembled) ``f_a = -int p N_a n dA`` and
the consistent (semismooth) tangent

.. math::

    K_{ai,bk} = \\int_\\Gamma N_a N_b \\Big( k\\, H(p)\\, n_i n_k
    - \\frac{p}{|x - c|} (\\delta_{ik} - n_i n_k) \\Big) dA

(the second term is the curvature of the sphere distance: ``p / (k R)`` relative to the
first, but it acts tangentially, where the soft body has little stiffness of its own; with
``geometric_tangent=False`` (a Gauss-Newton tangent) Newton converges only linearly, and with
it on from the first iteration the indefinite tangent cuts steps back; ``"auto"`` switches it on
once the active set has settled).

Augmented Lagrangian (Uzawa): after a converged penalty solve the
multipliers are updated ``lambda <- p`` and the step re-solved, until the
largest penetration is below ``gap_tol``; the penetration then no longer
scales with ``1/k``.

Force bookkeeping: the Newton residual is ``f_int + f_c - f_ext``, so the
contact force on the body is ``-sum f_c`` and the force on the sphere
(:meth:`SphereContact.force_on_sphere`) is ``+sum f_c`` per component (the
body pushes the sphere back out).

Entry points: :class:`SphereContact` (the contact term, pluggable into
:class:`~liverforce.fem.newton.DiscreteSystem` as its ``contact``),
:func:`indent` (displacement-controlled path on a system) and
:func:`indent_liver` (a :class:`~liverforce.fem.problem.LiverModel` with its
supports and reactions).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.sparse as sp

from .boundary import _facet_quadrature
from .elements import TetDiscretization
from .newton import _SAFETY_NET, DiscreteSystem, SolverOptions, _StepFailure
from .problem import CaseResult


class SphereContact:
    """Frictionless rigid sphere (radius ``radius`` mm, centre ``centre``) on a candidate facet set.

    Parameters
    ----------
    disc : discretisation (P1 or P2 facets).
    points : (n, 3) reference vertices (mm).
    facets : (k, 3) candidate contact facets (outward normals).
    radius : sphere radius (mm).
    kn : penalty stiffness (N/mm³: pressure per mm of penetration).
    centre : (3,) initial centre (mm); move it with :meth:`set_centre`.
    geometric_tangent : include the sphere-curvature term in the tangent: True (consistent),
        False (Gauss-Newton: linear convergence, contraction ~0.5 per iteration on a liver) or
        "auto" (default): only once the active set is the one of the previous tangent, so the
        first iterations of a step keep the robust positive Gauss-Newton tangent and the last ones
        converge quadratically (on the 15.6k-dof liver at 2 and 4 mm: 21 iterations, against 45
        for either fixed choice).

    Implements the ``contact`` protocol of :class:`~liverforce.fem.newton.DiscreteSystem`:
    ``energy_force(u)``, ``tangent_values(u)`` on the static ``rows`` / ``cols``.
    """

    def __init__(self, disc: TetDiscretization, points, facets, radius: float, kn: float,
                 centre=(0.0, 0.0, 0.0), geometric_tangent: bool | str = "auto"):
        points = np.asarray(points, float)
        facets = np.asarray(facets, np.int64).reshape(-1, 3)
        if not radius > 0 or not kn > 0:
            raise ValueError(f"sphere radius and penalty must be positive, got R={radius}, k={kn}")
        if len(facets) == 0:
            raise ValueError("SphereContact needs at least one candidate facet")
        self.radius, self.kn = float(radius), float(kn)
        if geometric_tangent not in (True, False, "auto"):
            raise ValueError(f"geometric_tangent must be True, False or 'auto', got {geometric_tangent!r}")
        self.geometric_tangent = geometric_tangent
        self._last_active = None
        self.n_dofs = disc.n_dofs
        fn, Xq, W, N, _, _ = _facet_quadrature(disc, points, facets)
        self.facets = facets
        self.fn, self.Xq, self.W, self.N = fn, Xq, W, N  # (k,nfn), (k,nq,3), (k,nq), (nq,nfn)
        self.dofs = (3 * fn[:, :, None] + np.arange(3)).reshape(len(fn), -1)  # (k, 3 nfn)
        nd = self.dofs.shape[1]
        self.rows = np.repeat(self.dofs, nd, axis=1).ravel()
        self.cols = np.tile(self.dofs, (1, nd)).ravel()
        self.multipliers = np.zeros_like(W)
        self.set_centre(centre)

    # ------------------------------------------------------------------
    def set_centre(self, centre) -> None:
        self.centre = np.asarray(centre, float).reshape(3).copy()

    def positions(self, u: np.ndarray) -> np.ndarray:
        """Current positions ``x = X + u`` (k, nq, 3) of the quadrature points."""
        uf = np.asarray(u, float).reshape(-1, 3)[self.fn]  # (k, nfn, 3)
        return self.Xq + np.einsum("qa,kai->kqi", self.N, uf)

    def _kinematics(self, u):
        r = self.positions(u) - self.centre
        rho = np.maximum(np.linalg.norm(r, axis=-1), 1e-300)
        n = r / rho[..., None]
        g = self.radius - rho
        p = np.maximum(self.multipliers + self.kn * g, 0.0)
        return g, p, n, rho

    def gap(self, u: np.ndarray) -> np.ndarray:
        """Penetration ``R - |x - c|`` (k, nq) in mm (> 0 inside the sphere)."""
        return self._kinematics(u)[0]

    def pressure(self, u: np.ndarray) -> np.ndarray:
        """Contact pressure ``<lambda + k g>_+`` (k, nq), N/mm² per reference area."""
        return self._kinematics(u)[1]

    def energy_force(self, u: np.ndarray) -> tuple[float, np.ndarray]:
        """Contact energy (N mm) and its gradient (n_dofs,)."""
        g, p, n, _ = self._kinematics(u)
        energy = float(np.sum(self.W * (p**2 - self.multipliers**2))) / (2.0 * self.kn)
        # f_a = -int p N_a n dA
        local = -np.einsum("kq,qa,kqi->kai", self.W * p, self.N, n).reshape(len(self.fn), -1)
        f = np.bincount(self.dofs.ravel(), weights=local.ravel(), minlength=self.n_dofs)
        return energy, f

    def tangent_values(self, u: np.ndarray) -> np.ndarray:
        """Values of the tangent on (``rows``, ``cols``) at ``u`` (see ``geometric_tangent``)."""
        act = self._kinematics(u)[1] > 0.0
        settled = self._last_active is not None and np.array_equal(act, self._last_active)
        self._last_active = act
        geometric = self.geometric_tangent is True or (self.geometric_tangent == "auto" and settled)
        return self._tangent_blocks(u, geometric).ravel()

    def _tangent_blocks(self, u: np.ndarray, geometric: bool) -> np.ndarray:
        """Element blocks (k, nfn, 3, nfn, 3) of the tangent; ``geometric``: with the curvature term."""
        g, p, n, rho = self._kinematics(u)
        act = p > 0.0
        nn = np.einsum("kqi,kqj->kqij", n, n)
        S = (self.kn * act)[..., None, None] * nn
        if geometric:
            S = S - (p / rho)[..., None, None] * (np.eye(3) - nn)
        return np.einsum("kq,qa,qb,kqij->kaibj", self.W, self.N, self.N, S)

    def centre_coupling(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Derivatives with respect to the centre, from the consistent tangent ``K_c`` at ``u``.

        The energy depends on ``x - c`` only and the shape functions sum to one, so moving the
        centre by ``dc`` is moving every node by ``-dc``: ``d f_c / d c = -K_c T`` with ``T``
        (n_dofs, 3) the rigid translations. Returns ``B = K_c T`` (n_dofs, 3) and
        ``T^T K_c T`` (3, 3) (the contact's stiffness against a rigid translation of the body).
        """
        blk = self._tangent_blocks(u, True).sum(axis=3)  # (k, nfn, 3, 3): sum over the column nodes
        B = np.zeros((self.n_dofs, 3))
        rows = self.dofs.reshape(len(self.fn), -1)  # (k, 3 nfn) interleaved like blk's (a, i)
        flat = blk.reshape(len(self.fn), -1, 3)
        for k in range(3):
            B[:, k] = np.bincount(rows.ravel(), weights=flat[:, :, k].ravel(), minlength=self.n_dofs)
        return B, B.reshape(-1, 3, 3).sum(axis=0)

    def tangent_matrix(self, u: np.ndarray) -> sp.csr_matrix:
        n = self.n_dofs
        return sp.coo_matrix((self.tangent_values(u), (self.rows, self.cols)), shape=(n, n)).tocsr()

    # ------------------------------------------------------------------
    def force_on_sphere(self, u: np.ndarray) -> np.ndarray:
        """Total contact force (3,) the body exerts on the sphere (N); minus the force on the body."""
        _, p, n, _ = self._kinematics(u)
        return -np.einsum("kq,kqi->i", self.W * p, n)

    def summary(self, u: np.ndarray) -> dict:
        """Force on the sphere, active points, contact area (reference, mm²), peak pressure, max penetration."""
        g, p, n, _ = self._kinematics(u)
        act = p > 0.0
        return {
            "force_on_sphere": -np.einsum("kq,kqi->i", self.W * p, n),
            "active_points": int(act.sum()),
            "contact_area_mm2": float(self.W[act].sum()),
            "peak_pressure_mpa": float(p.max()) if p.size else 0.0,
            "max_penetration_mm": float(max(g.max(), 0.0)) if g.size else 0.0,
            "active_on_rim": bool(np.any(act & self._rim_mask())),
        }

    def _rim_mask(self) -> np.ndarray:
        """(k, nq) quadrature points on candidate facets that touch the candidate set's border."""
        if not hasattr(self, "_rim"):
            edges = np.sort(np.concatenate([self.facets[:, [0, 1]], self.facets[:, [1, 2]],
                                            self.facets[:, [2, 0]]]), axis=1)
            _, inv, cnt = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
            border = cnt[inv.ravel()] == 1
            bnodes = np.unique(edges[border])
            rim = np.isin(self.facets, bnodes).any(axis=1)
            self._rim = np.broadcast_to(rim[:, None], self.W.shape)
        return self._rim


class ContactSum:
    """Several contact terms (e.g. the unilateral rib and the sphere) as one ``contact`` of a system."""

    def __init__(self, terms):
        self.terms = [t for t in terms if t is not None]
        self.rows = np.concatenate([t.rows for t in self.terms])
        self.cols = np.concatenate([t.cols for t in self.terms])

    def energy_force(self, u):
        e, f = 0.0, 0.0
        for t in self.terms:
            et, ft = t.energy_force(u)
            e, f = e + et, f + ft
        return e, f

    def tangent_values(self, u):
        return np.concatenate([t.tangent_values(u) for t in self.terms])


@dataclass
class IndentResult:
    """State at one prescribed sphere position (see :func:`indent`).

    Attributes
    ----------
    u : full dof vector (mm); ``u_nodes`` the vertex displacements (n_vertices, 3).
    centre : sphere centre (mm); ``depth`` the path parameter's depth (mm).
    force_on_sphere : total contact force on the sphere (N, 3-vector); the force on the body is its negative.
    active_points, contact_area_mm2 : quadrature points in contact and their reference area.
    peak_pressure_mpa, max_penetration_mm : largest contact pressure and penetration.
    active_on_rim : a point in contact lies on the candidate set's border (enlarge the candidate set).
    reactions : support reactions (N) on the body; with :func:`indent_liver` per region (as
        :meth:`LiverModel.reactions`) plus "indenter" (force of the sphere on the liver) and "imbalance".
    augmentations : Uzawa updates used at this position.
    """

    u: np.ndarray
    u_nodes: np.ndarray
    centre: np.ndarray
    depth: float
    force_on_sphere: np.ndarray
    active_points: int
    contact_area_mm2: float
    peak_pressure_mpa: float
    max_penetration_mm: float
    active_on_rim: bool
    reactions: dict = field(default_factory=dict)
    augmentations: int = 0
    newton_iterations: int = 0


@dataclass
class IndentPath:
    """Outcome of :func:`indent`: the results at the requested depths (in order) and solver facts."""

    results: list
    converged: bool
    reason: str
    load_steps: int
    newton_iterations: int
    wall_time_s: float
    history: list = field(default_factory=list)


def _left_of(opt: SolverOptions, stats: dict, t0: float) -> SolverOptions:
    """``opt`` with what is left of a case's budget: Newton iterations (``stats["iters"]`` spent) and wall time
    (since ``t0``). For a sub-path that counts from zero (:func:`indent`), so the case's budget holds over all its
    sub-paths; a direct ``_newton`` call on the case's own ``stats`` and ``t0`` takes ``opt`` as it is."""
    return replace(opt, max_total_iter=max(opt.max_total_iter - stats["iters"], 0),
                   time_limit_s=max(opt.time_limit_s - (time.perf_counter() - t0), 1e-3))


def indent(system: DiscreteSystem, contact: SphereContact, material, start, direction, depths,
           u0=None, f_ext=None, options: SolverOptions | None = None, max_increment: float | None = None,
           augmented: int = 0, gap_tol: float = 0.0, reactions=None) -> IndentPath:
    """Push the sphere from ``start`` along ``direction`` through the ``depths`` (mm), in load steps.

    ``system.contact`` must include ``contact`` (alone or in a :class:`ContactSum`).
    The centre is ``start + depth * direction/|direction|``; depths may go down as well as up
    (retraction). Each depth is reached by increments of at most ``max_increment`` mm
    (default: the largest gap between requested depths), cut back on failure (Newton as
    :meth:`DiscreteSystem.solve`, with a secant predictor), and refined by up to ``augmented``
    Uzawa updates of the multipliers while the max penetration exceeds ``gap_tol``.
    ``f_ext`` : optional dead loads (held constant). ``reactions(u, f_int) -> dict`` : optional
    support bookkeeping from the state and the internal forces.
    Never raises on non-convergence: ``converged=False`` with a reason and the results reached.
    """
    floor = system.ref_force_floor
    try:
        return _indent(system, contact, material, start, direction, depths, u0, f_ext, options,
                       max_increment, augmented, gap_tol, reactions)
    finally:
        system.ref_force_floor = floor


def _indent(system, contact, material, start, direction, depths, u0, f_ext, options, max_increment,
            augmented, gap_tol, reactions) -> IndentPath:
    opt = options or system.options
    t0 = time.perf_counter()
    n = system.disc.n_dofs
    f_load = np.zeros(n) if f_ext is None else np.asarray(f_ext, float)
    start = np.asarray(start, float).reshape(3)
    d = np.asarray(direction, float).reshape(3)
    d = d / np.linalg.norm(d)
    depths = [float(x) for x in np.atleast_1d(depths)]
    stats = {"iters": 0, "steps": 0, "factorizations": 0, "history": [], "last_res": np.nan}
    u = np.zeros(n) if u0 is None else np.asarray(u0, float).copy()
    ub = u[system.fixed].copy()
    cur = 0.0 if u0 is None else None
    if cur is None:  # a warm start belongs to the contact's current centre
        cur = float((contact.centre - start) @ d)
    contact.set_centre(start + cur * d)
    gaps = np.abs(np.diff([cur] + depths))
    inc_max = float(max_increment) if max_increment else float(max(gaps.max(), 1e-12))
    u_prev, s_prev = None, None
    results = []

    def fail(reason):
        return IndentPath(results, False, reason, stats["steps"], stats["iters"], time.perf_counter() - t0,
                          stats["history"])

    for target in depths:
        step = min(inc_max, abs(target - cur)) if target != cur else 0.0
        its_here = 0
        while True:
            if time.perf_counter() - t0 > opt.time_limit_s:
                return fail(f"time limit reached at depth {cur:.4g} mm{_SAFETY_NET}")
            if stats["steps"] >= opt.max_steps:
                return fail(f"max_steps={opt.max_steps} reached at depth {cur:.4g} mm")
            nxt = target if abs(target - cur) <= step * (1 + 1e-9) else cur + np.sign(target - cur) * step
            contact.set_centre(start + nxt * d)
            u_try = u.copy()
            if u_prev is not None and s_prev is not None and cur != s_prev and np.sign(nxt - cur) == np.sign(cur - s_prev):
                u_sec = u + (nxt - cur) / (cur - s_prev) * (u - u_prev)
                u_sec[system.fixed] = ub
                u_try = system._better_start(u_try, u_sec, material, f_load)
            stats["steps"] += 1
            try:
                u_new, its, _ = system._newton(material, f_load, u_try, u, ub, opt, stats, t0, 1.0)
            except _StepFailure as exc:
                stats["history"].append((nxt, False, str(exc)))
                if str(exc).startswith(("time limit", "max_total_iter")):
                    contact.set_centre(start + cur * d)
                    return fail(str(exc))
                step *= opt.cutback
                if step < opt.min_step * inc_max:
                    contact.set_centre(start + cur * d)
                    return fail(f"depth increment below min_step at depth {cur:.4g} mm: {exc}")
                continue
            stats["history"].append((nxt, True, its))
            # the path's force scale: relative tolerances stay meaningful once the contact lets go
            system.ref_force_floor = max(system.ref_force_floor,
                                         float(np.linalg.norm(contact.energy_force(u_new)[1])))
            its_here += its
            u_prev, s_prev = u, cur
            u, cur = u_new, nxt
            if abs(cur - target) <= 1e-12 * max(1.0, abs(target)):
                cur = target
                break
            if its <= opt.easy_iter:
                step = min(step * opt.growth, inc_max)
        # augmented Lagrangian (Uzawa) at this depth
        n_aug = 0
        while n_aug < augmented and contact.summary(u)["max_penetration_mm"] > gap_tol:
            contact.multipliers = contact.pressure(u)
            try:
                u, its, _ = system._newton(material, f_load, u, u, ub, opt, stats, t0, 1.0)
            except _StepFailure as exc:
                return fail(f"augmented Lagrangian update failed at depth {cur:.4g} mm: {exc}")
            its_here += its
            n_aug += 1
        if n_aug:
            u_prev = None  # the multipliers changed the problem: no secant across
        s = contact.summary(u)
        reac = {}
        if reactions is not None:
            reac = reactions(u, system.assembler.evaluate(u, material, tangent=False).f_int)
        results.append(IndentResult(u.copy(), u.reshape(-1, 3)[: system.disc.n_vertices].copy(),
                                    contact.centre.copy(), cur, s["force_on_sphere"], s["active_points"],
                                    s["contact_area_mm2"], s["peak_pressure_mpa"], s["max_penetration_mm"],
                                    s["active_on_rim"], reac, n_aug, its_here))
    return IndentPath(results, True, "converged", stats["steps"], stats["iters"], time.perf_counter() - t0,
                      stats["history"])


def support_reactions(system: DiscreteSystem, contact: SphereContact):
    """Reaction bookkeeping for a bare :class:`DiscreteSystem` without dead loads: the force (N) on the
    body from the constrained dofs ("supports": the residual force ``f_int + f_boundary`` there, as
    :meth:`LiverModel.reactions`), the springs, the sphere ("indenter"), and their sum ("imbalance")."""

    def reac(u, f_int):
        fx = system.fixed
        R = f_int + system.boundary_force(u)
        out = {"supports": np.bincount(fx % 3, weights=R[fx], minlength=3) if fx.size else np.zeros(3)}
        out["springs"] = -(system.spring @ u).reshape(-1, 3).sum(axis=0)
        out["indenter"] = -contact.force_on_sphere(u)
        out["imbalance"] = out["supports"] + out["springs"] + out["indenter"]
        return out

    return reac


def candidate_facets(points, facets, point, radius: float, facet_mask=None) -> np.ndarray:
    """Indices of facets with a vertex within ``radius`` mm of ``point`` (reference configuration)."""
    points = np.asarray(points, float)
    facets = np.asarray(facets, np.int64)
    near = np.linalg.norm(points[facets] - np.asarray(point, float).reshape(3), axis=-1).min(axis=1) <= radius
    if facet_mask is not None:
        near &= np.asarray(facet_mask, bool)
    return np.flatnonzero(near)


def surface_normal(points, facets, point, radius: float = 2.0, facet_mask=None) -> np.ndarray:
    """Unit outward normal of the surface at ``point``: area- and Gaussian-weighted facet normals nearby."""
    from .elements import facet_geometry

    points = np.asarray(points, float)
    facets = np.asarray(facets, np.int64)
    area, nrm = facet_geometry(points, facets)
    dist = np.linalg.norm(points[facets].mean(axis=1) - np.asarray(point, float), axis=1)
    if facet_mask is not None:
        dist = np.where(np.asarray(facet_mask, bool), dist, np.inf)
    w = area * np.exp(-0.5 * (dist / radius) ** 2)
    if not w.sum() > 0:
        w = (dist == dist.min()).astype(float)
    v = (w[:, None] * nrm).sum(axis=0)
    return v / np.linalg.norm(v)


class LiverIndenter:
    """A :class:`~liverforce.fem.problem.LiverModel` pushed by a rigid sphere at ``point_mm``.

    The sphere (radius ``radius_mm``) starts touching the reference surface at ``point_mm``
    (centre ``point + R n`` with ``n`` the outward normal there, or ``-direction`` if given)
    and moves along ``direction`` (default the inward normal ``-n``). Candidate facets: those
    of the load-carrying regions (not the IVC) within ``candidate_radius_mm`` (default
    ``4 R + 10`` mm) of the point. The liver's supports (IVC, foundations, rib, unilateral
    rib contact) are the model's.
    """

    def __init__(self, model, point_mm, radius_mm: float = 2.5, kn: float | None = None, direction=None,
                 candidate_radius_mm: float | None = None, geometric_tangent: bool | str = "auto"):
        from .problem import IVC

        self.model = model
        self.point = np.asarray(point_mm, float).reshape(3)
        self.radius = float(radius_mm)
        mask = model.facet_region != IVC
        self.normal = surface_normal(model.points, model.facets, self.point, max(self.radius, 2.0), mask)
        self.direction = -self.normal if direction is None else np.asarray(direction, float) / np.linalg.norm(direction)
        self._magnitude_curve: list = []  # (depth, |F|) reached by push_to_magnitude: the next case's first guess
        self.start = self.point - self.radius * self.direction
        rc = candidate_radius_mm if candidate_radius_mm is not None else 4.0 * self.radius + 10.0
        cand = candidate_facets(model.points, model.facets, self.point, rc, mask)
        if kn is None:  # ~ 100 x the material's stiffness per local element size
            kn = 100.0 * 3.0 * model.material.mu0 / max(self._local_size(cand), 1e-3)
        self.contact = SphereContact(model.disc, model.points, model.facets[cand], self.radius, kn,
                                     self.start, geometric_tangent)
        terms = ContactSum([model.rib_contact, self.contact])
        spring = sum(model.region_springs.values()) if model.region_springs else None
        self.system = DiscreteSystem(model.points, None, model.system.fixed, spring, model.options,
                                     disc=model.disc, contact=terms)

    def _local_size(self, cand) -> float:
        from .elements import facet_geometry

        area, _ = facet_geometry(self.model.points, self.model.facets[cand])
        d = np.linalg.norm(self.model.points[self.model.facets[cand]].mean(axis=1) - self.point, axis=1)
        return float(np.sqrt(2.0 * area[np.argsort(d)[:10]].mean()))

    def reactions(self, u, f_int):
        """Forces (N) on the liver per support region (as :meth:`LiverModel.reactions`), the sphere's
        ("indenter" = minus the force on the sphere) and their sum ("imbalance", ~0 at equilibrium)."""
        out = self.model.reactions(u, f_int, np.zeros(self.model.n_dofs))
        # the IVC reaction from the full residual, the sphere's force on shared nodes included
        fx = self.model.system.fixed
        R = f_int + self.system.boundary_force(u)
        out["ivc"] = np.bincount(fx % 3, weights=R[fx], minlength=3) if fx.size else np.zeros(3)
        out.pop("tool", None)
        out["indenter"] = -self.contact.force_on_sphere(u)
        out["imbalance"] = sum(out[k] for k in ("ivc", "ligament", "visceral", "rib", "gravity", "indenter"))
        return out

    def push(self, depths, material=None, u0=None, options=None, **kw) -> IndentPath:
        """Push to each depth (mm along ``direction`` from first touch) in turn; see :func:`indent`."""
        mat = material or self.model.material
        return indent(self.system, self.contact, mat, self.start, self.direction, depths, u0=u0,
                      options=options or self.model.options, reactions=self.reactions, **kw)

    def centre_jacobian(self, u, material=None):
        """``J = dF/dc`` (3 x 3, N/mm): how the force the sphere exerts on the liver changes with the centre,
        at an equilibrium ``u``, and ``Z = du/dc`` (n_dofs, 3), the linearised response.

        From the consistent tangent ``K`` (body, supports and contact with its curvature term) and the
        centre coupling ``B = K_c T`` (:meth:`SphereContact.centre_coupling`):
        ``Z_f = K_ff^-1 B_f`` and ``J = T^T K_c T - B_f^T Z_f``, the Schur complement of the system
        with the centre as 3 extra unknowns (symmetric, positive semi-definite at a stable state). One
        factorisation (kept by the system's linear solver for the next Newton) and three back-solves.
        """
        return _centre_jacobian(self, np.asarray(u, float), material or self.model.material)

    def push_to_magnitude(self, force_n, material=None, options=None, rtol: float = 0.01, atol: float = 1e-3,
                          max_pushes: int = 12, max_increment: float | None = None) -> "SphereCaseResult":
        """Magnitude control: push the sphere along ``force_n``'s direction until the force it exerts on the
        liver has the magnitude ``|force_n|`` (within ``max(rtol |force_n|, atol)``).

        What a frictionless rigid tip can do: it transmits only pressure normal to its surface, so the
        force it exerts lies close to the contact normal whatever the push direction (on the default
        liver a push 30° off the normal gave a force about 3° off it), and the prescribed *vector*
        of a traction case is generally out of its reach (:meth:`push_to_force` then needs the
        sphere to slide far). The robot pushes along ``force_n``; the label is the force the sphere
        exerts (``force_on_liver``), whose direction the contact decides.

        From first touch at the exertion point (centre ``point + R n``), each push continues from the
        deepest state below the target to the next depth: a power law ``F ~ d^m`` through the two
        states nearest the target (earlier cases at this point included), then a secant inside the
        bracket; increments of at most ``max_increment`` mm (default ``R / 5``: a coarse surface mesh
        lets a longer step slip between contact points). Never raises: ``converged=False`` with the
        reason and the last state below the target.
        """
        return _push_to_magnitude(self, force_n, material, options, rtol, atol, max_pushes, max_increment)

    def push_to_force(self, force_n, material=None, u0=None, options=None, rtol: float = 0.01,
                      atol: float = 1e-3, max_outer: int = 30, max_move_mm: float | None = None,
                      max_slide_mm: float | None = None, first_depth_mm: float | None = None) -> "SphereCaseResult":
        """Force control: the sphere centre at which the force the sphere exerts on the liver is ``force_n``.

        ``force_n`` (N, 3-vector, on the liver). Converged when ``|F - force_n| <= max(rtol |force_n|, atol)``
        at an equilibrium (inner Newton to ``options.tol``). Never raises on failure: ``converged=False``
        with the reason and the last equilibrium reached.

        Method: an outer Newton on the centre ``c`` around displacement-controlled equilibria. At an
        equilibrium ``u(c)`` the exact Jacobian ``dF/dc`` is the Schur complement of the monolithic
        system (the centre as 3 extra unknowns of the potential ``Pi_body(u) + Pi_c(u, c) - F . c``;
        :meth:`centre_jacobian`), and ``u + Z dc`` predicts the next state, so each centre update costs
        one factorisation plus the few Newton iterations that correct the prediction; a failed
        correction falls back to the stepped path of :func:`indent` (cut-backs). Compared with
        solving the bordered (u, c) system directly this keeps the displacement-controlled solver's
        line search, cut-backs and active-set handling unchanged, and the centre never moves into a
        state the body cannot equilibrate. Far from the target magnitude (ratio outside 0.5-2) the
        centre moves along ``force_n`` by a power law ``F ~ d^m`` (``m`` from the local slope), which
        does not overshoot the stiffening force-depth curve as a Newton step would.

        Start: rest (when ``|force_n| <= atol``: the sphere touching, no force), a converged
        :class:`SphereCaseResult` ``u0`` at this point (its state and centre, re-equilibrated in this
        material), else a push of ``first_depth_mm`` (default the radius, at most 2 mm) along ``force_n`` from
        first touch.

        A frictionless sphere transmits only pressure normal to its surface: a force inclined to the
        surface normal is held only where the dent's wall (or the liver's curvature) leans the
        contact that way. If holding it needs the centre more than ``max_slide_mm`` (default the
        radius) off the normal line through the exertion point, the case fails with that reason
        rather than move the load elsewhere. ``max_move_mm`` caps a centre update (default R).
        """
        return _push_to_force(self, force_n, material, u0, options, rtol, atol, max_outer, max_move_mm,
                              max_slide_mm, first_depth_mm)


# ----------------------------------------------------------------------
# force control: the sphere position that exerts a prescribed force
# ----------------------------------------------------------------------


@dataclass
class SphereCaseResult(CaseResult):
    """A :class:`~liverforce.fem.problem.CaseResult` of a force-controlled sphere
    (:meth:`LiverIndenter.push_to_force`); the common fields mean what they mean for the traction.

    ``newton_iterations`` / ``load_steps`` / ``factorizations`` count every inner solve (and the
    Jacobian factorisations); ``final_residual`` is the last inner Newton residual (relative);
    ``load_fraction`` is the share of the target force reached along its direction.
    ``reactions`` : per support region as :meth:`LiverIndenter.reactions`, plus "tool" (= "indenter").

    Extra attributes
    ----------------
    centre : sphere centre (mm) at the returned state.
    force_on_liver : force (N) the sphere exerts on the liver there (the label of a converged case).
    target_force : the prescribed force (N).
    force_error_n : ``|force_on_liver - target_force|`` (N).
    outer_iterations : centre updates (Jacobian evaluations).
    slide_mm : distance of the centre from the normal line through the exertion point (mm).
    contact : :meth:`SphereContact.summary` at the returned state (without the force).
    """

    centre: np.ndarray | None = None
    force_on_liver: np.ndarray | None = None
    target_force: np.ndarray | None = None
    force_error_n: float = float("nan")
    outer_iterations: int = 0
    slide_mm: float = float("nan")
    contact: dict = field(default_factory=dict)


def _slide(ind, centre) -> float:
    """Distance (mm) of a sphere centre from the normal line through the exertion point."""
    r = np.asarray(centre, float) - ind.point
    return float(np.linalg.norm(r - (r @ ind.normal) * ind.normal))


def _sphere_result(ind, u, mat, opt, stats, t0, F_t, ok, reason, outer) -> "SphereCaseResult":
    """A :class:`SphereCaseResult` at the state ``u`` (the contact at its current centre)."""
    from .kinematics import principal_stretch_range
    from .problem import ToolLoad

    system, contact = ind.system, ind.contact
    n = system.disc.n_dofs
    u = np.asarray(u, float)
    F = -contact.force_on_sphere(u)
    F_mag = float(np.linalg.norm(F_t))
    ev = system.assembler.evaluate(u, mat, tangent=False)
    f_int = ev.f_int if ev.valid else np.full(n, np.nan)
    reac = ind.reactions(u, f_int)
    reac["tool"] = reac["indenter"]
    lam_min, lam_max = principal_stretch_range(system.disc, u)
    summ = contact.summary(u)
    summ.pop("force_on_sphere")
    frac = float(np.clip(F @ F_t / F_mag**2, 0.0, 1.0)) if F_mag > 0 else 1.0
    return SphereCaseResult(
        u_nodes=u.reshape(-1, 3)[: ind.model.n_vertices].copy(), converged=ok, reason=reason,
        load_fraction=1.0 if ok else frac, load_steps=stats["steps"], newton_iterations=stats["iters"],
        final_residual=float(stats["last_res"]) if np.isfinite(stats["last_res"]) else 0.0,
        wall_time_s=time.perf_counter() - t0, linear_solver=system.linear.backend or "none", reactions=reac,
        state=u.copy(), load=ToolLoad(ind.point, F_t, ind.radius), formulation=opt.formulation, n_dofs=n,
        factorizations=stats["factorizations"], history=stats["history"], min_principal_stretch=lam_min,
        max_principal_stretch=lam_max, centre=contact.centre.copy(), force_on_liver=F, target_force=F_t.copy(),
        force_error_n=float(np.linalg.norm(F - F_t)), outer_iterations=outer, slide_mm=_slide(ind, contact.centre), contact=summ)


def _push_to_magnitude(ind: "LiverIndenter", force_n, material, options, rtol, atol, max_pushes,
                       max_increment) -> "SphereCaseResult":
    """See :meth:`LiverIndenter.push_to_magnitude`."""
    mat = material or ind.model.material
    opt = options or ind.model.options
    system, contact = ind.system, ind.contact
    t0 = time.perf_counter()
    R = ind.radius
    F_t = np.asarray(force_n, float).reshape(3)
    target = float(np.linalg.norm(F_t))
    tol_f = max(rtol * target, atol)
    stats = {"iters": 0, "steps": 0, "factorizations": 0, "history": [], "last_res": np.nan}
    zero = np.zeros(system.disc.n_dofs)
    contact.multipliers = np.zeros_like(contact.W)
    start = ind.point + R * ind.normal  # touching the surface at the exertion point
    d_hat = F_t / target if target > 0 else -ind.normal
    inc = float(max_increment) if max_increment else 0.2 * R
    contact.set_centre(start)
    if target <= atol:
        return _sphere_result(ind, zero, mat, opt, stats, t0, F_t, True, "converged", 0)
    lo, hi = (0.0, 0.0, zero), None  # (depth, |F|, state): the deepest state below the target, the shallowest above
    curve = list(ind._magnitude_curve)  # (depth, |F|) of earlier cases at this point: the first guess
    for push in range(1, max_pushes + 1):
        if hi is not None:  # inside the bracket: secant on |F|(depth)
            d = lo[0] + (target - lo[1]) * (hi[0] - lo[0]) / (hi[1] - lo[1])
            d = float(np.clip(d, lo[0] + 0.05 * (hi[0] - lo[0]), hi[0] - 0.05 * (hi[0] - lo[0])))
        else:
            pts = [(a, b) for a, b in curve if a > 0 and b > 0]
            if lo[1] > 0:
                pts.append((lo[0], lo[1]))
            if len(pts) >= 2:  # a power law F = a d^m through the two points nearest the target
                (d1, f1), (d2, f2) = sorted(pts, key=lambda q: abs(np.log(q[1] / target)))[:2]
                m = float(np.clip(np.log(f2 / f1) / np.log(d2 / d1), 1.0, 3.0)) if d1 != d2 and f1 != f2 else 1.5
                d = d2 * (target / f2) ** (1.0 / m)
            elif pts:
                d = pts[0][0] * (target / pts[0][1]) ** (1.0 / 1.5)
            else:
                d = R
            d = float(min(max(d, lo[0] + 0.1), lo[0] + 3.0))
        contact.set_centre(start + lo[0] * d_hat)
        path = indent(system, contact, mat, start, d_hat, [d], u0=lo[2], options=_left_of(opt, stats, t0),
                      max_increment=inc)
        stats["iters"] += path.newton_iterations
        stats["steps"] += path.load_steps
        stats["history"].append(("depth", d, path.converged, path.newton_iterations))
        if not path.converged:
            contact.set_centre(start + lo[0] * d_hat)
            return _sphere_result(ind, lo[2], mat, opt, stats, t0, F_t, False,
                                  f"sphere: push to {d:.3g} mm failed: {path.reason}", push)
        r = path.results[0]
        F = float(np.linalg.norm(r.force_on_sphere))
        if F < lo[1] or r.active_points == 0:  # deeper but less force: the sphere slipped between contact points
            contact.set_centre(start + lo[0] * d_hat)
            return _sphere_result(ind, lo[2], mat, opt, stats, t0, F_t, False, (
                f"sphere: at {d:.3g} mm the force fell to {F:.3g} N (from {lo[1]:.3g} N at {lo[0]:.3g} mm): the "
                f"sphere slipped through the surface mesh, whose facets are too coarse for a {R:g} mm tip at this "
                "depth; refine the mesh at the exertion points (mesh.refine_edge_mm) or take a larger "
                "simulate.tool_tip_radius_mm"), push)
        ind._magnitude_curve.append((d, F))
        state = (d, F, r.u)
        if abs(F - target) <= tol_f:
            ind._magnitude_curve = ind._magnitude_curve[-8:]
            return _sphere_result(ind, r.u, mat, opt, stats, t0, F_t, True, "converged", push)
        if F < target:
            lo = state
        else:
            hi = state if hi is None or d < hi[0] else hi
    contact.set_centre(start + lo[0] * d_hat)
    return _sphere_result(ind, lo[2], mat, opt, stats, t0, F_t, False,
                          f"sphere: |F| = {target:.3g} N not reached within {max_pushes} pushes", max_pushes)


def _push_to_force(ind: "LiverIndenter", force_n, material, u0, options, rtol, atol, max_outer, max_move_mm,
                   max_slide_mm, first_depth_mm) -> SphereCaseResult:
    mat = material or ind.model.material
    opt = options or ind.model.options
    system, contact = ind.system, ind.contact
    t0 = time.perf_counter()
    n = system.disc.n_dofs
    R = ind.radius
    F_t = np.asarray(force_n, float).reshape(3)
    F_mag = float(np.linalg.norm(F_t))
    tol_f = max(rtol * F_mag, atol)
    max_move = float(max_move_mm) if max_move_mm else R
    max_slide = float(max_slide_mm) if max_slide_mm is not None else R
    nrm = ind.normal
    stats = {"iters": 0, "steps": 0, "factorizations": 0, "history": [], "last_res": np.nan}
    zero = np.zeros(n)
    ub = np.zeros(system.fixed.size)
    contact.multipliers = np.zeros_like(contact.W)
    outer = 0

    def remaining():
        return _left_of(opt, stats, t0)

    def finish(u, ok, reason):
        return _sphere_result(ind, u, mat, opt, stats, t0, F_t, ok, reason, outer)

    def move(u, c_from, c_to, u_pred):
        """Equilibrium with the centre at ``c_to`` from the equilibrium ``u`` at ``c_from``: Newton from the
        linear prediction ``u_pred``, else a stepped path (cut-backs) from ``u``. Returns (u, None) or (None, why)."""
        contact.set_centre(c_to)
        stats["steps"] += 1
        try:
            u_new, its, _ = system._newton(mat, zero, u_pred, u, ub, opt, stats, t0, 1.0)  # the case's own stats
            stats["history"].append(("centre", c_to.tolist(), True, its))
            return u_new, None
        except _StepFailure as exc:
            stats["history"].append(("centre", c_to.tolist(), False, str(exc)))
            if str(exc).startswith(("time limit", "max_total_iter")):
                contact.set_centre(c_from)
                return None, str(exc)
            why = str(exc)
        d = np.asarray(c_to, float) - c_from
        L = float(np.linalg.norm(d))
        contact.set_centre(c_from)
        if L == 0.0:
            return None, why
        path = indent(system, contact, mat, c_from, d, [L], u0=u, options=remaining(), max_increment=min(L, 0.2 * R))
        stats["iters"] += path.newton_iterations
        stats["steps"] += path.load_steps
        if not path.converged:
            contact.set_centre(c_from)
            return None, path.reason
        return path.results[0].u, None

    # ---- the start: rest (|F| within tolerance), a warm start, or a first push along F
    contact.set_centre(ind.start)
    if F_mag <= atol:
        return finish(zero, True, "converged")
    u, c = None, None
    if isinstance(u0, SphereCaseResult) and u0.converged and u0.centre is not None and u0.state is not None:
        u_w, c_w = np.asarray(u0.state, float), np.asarray(u0.centre, float)
        u, why = move(u_w, c_w, c_w, u_w)  # the neighbour's state at its centre, in this material
        c = c_w if u is not None else None
    if u is None:
        d0 = float(first_depth_mm) if first_depth_mm else min(R, 2.0)
        path = indent(system, contact, mat, ind.start, F_t, [d0], options=remaining(), max_increment=0.2 * R)
        stats["iters"] += path.newton_iterations
        stats["steps"] += path.load_steps
        if not path.converged:
            contact.set_centre(ind.start)
            return finish(zero, False, f"sphere: first push of {d0:g} mm failed: {path.reason}")
        u, c = path.results[0].u, path.results[0].centre.copy()
    contact.set_centre(c)

    clipped = 0
    while True:
        F = -contact.force_on_sphere(u)
        err = F_t - F
        if np.linalg.norm(err) <= tol_f:
            return finish(u, True, "converged")
        if outer >= max_outer:
            return finish(u, False, f"sphere: force not reached in {max_outer} centre updates "
                                    f"(|F - F_target| = {np.linalg.norm(err):.3g} N > {tol_f:.3g} N)")
        s = contact.summary(u)
        if s["active_on_rim"]:
            return finish(u, False, "sphere: the contact reached the border of the candidate surface around the "
                                    "exertion point (the sphere slid or sank too far)")
        outer += 1
        if s["active_points"] == 0:  # out of contact: push along the force again
            dc, Z = min(0.25 * R, 1.0) * F_t / F_mag, np.zeros((n, 3))
        else:
            try:
                J, Z = ind.centre_jacobian(u, mat)
            except (RuntimeError, ValueError) as exc:
                return finish(u, False, f"sphere: centre Jacobian failed: {exc}")
            stats["factorizations"] += 1
            F_r = float(F @ F_t) / F_mag
            depth = float((c - ind.start) @ F_t) / F_mag
            k_r = float(F_t @ J @ F_t) / F_mag**2
            if F_r > 0 and depth > 0 and k_r > 0 and not 0.5 < F_mag / F_r < 2.0:
                # far from the target magnitude: a power law F ~ d^m along F (m from the local slope)
                # does not overshoot the stiffening force-depth curve as a Newton step does
                m = float(np.clip(k_r * depth / F_r, 1.0, 3.0))
                dc = (depth * (F_mag / F_r) ** (1.0 / m) - depth) * F_t / F_mag
            else:
                try:
                    dc = np.linalg.solve(J, err)
                except np.linalg.LinAlgError:
                    dc = np.linalg.lstsq(J, err, rcond=1e-8)[0]
        L = float(np.linalg.norm(dc))
        if L > max_move:
            dc *= max_move / L
        c_new = c + dc
        r = c_new - ind.point
        tang = r - (r @ nrm) * nrm
        if np.linalg.norm(tang) > max_slide:  # keep the sphere within max_slide of the exertion point
            c_new = c_new - tang * (1.0 - max_slide / np.linalg.norm(tang))
            clipped += 1
            if clipped >= 3:
                ang = np.degrees(np.arccos(np.clip(-F_t @ nrm / F_mag, -1.0, 1.0)))
                ang_r = np.degrees(np.arccos(np.clip(-F @ nrm / max(np.linalg.norm(F), 1e-300), -1.0, 1.0)))
                return finish(u, False, (
                    f"sphere: the frictionless sphere cannot hold this force: {F_mag:.3g} N at {ang:.1f} deg from "
                    f"the inward normal needs the sphere to slide more than {max_slide:g} mm (tool_max_slide_mm) "
                    f"from the exertion point; reached {np.linalg.norm(F):.3g} N at {ang_r:.1f} deg "
                    f"(|F - F_target| = {np.linalg.norm(err):.3g} N)"))
        else:
            clipped = 0
        dc = c_new - c
        u_pred = u + Z @ dc
        u_new, why = move(u, c, c_new, u_pred)
        if u_new is None:
            return finish(u, False, f"sphere: equilibrium at the next centre failed: {why}")
        u, c = u_new, c_new


def _centre_jacobian(ind: "LiverIndenter", u, material):
    system, contact = ind.system, ind.contact
    ev = system.assembler.evaluate(u, material, tangent=True)
    if not ev.valid:
        raise ValueError("inverted element at the state")
    saved = (contact.geometric_tangent, contact._last_active)
    contact.geometric_tangent = True
    try:
        K = system.tangent_matrix(ev.data, u)
    finally:
        contact.geometric_tangent, contact._last_active = saved
    system.linear.factorize(K, shift=False)
    B, Kt = contact.centre_coupling(u)
    free = system.free
    Z = np.zeros((system.disc.n_dofs, 3))
    for k in range(3):
        Z[free, k] = system.linear.solve(B[free, k])
    J = Kt - B[free].T @ Z[free]
    return 0.5 * (J + J.T), Z
