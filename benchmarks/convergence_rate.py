"""Observed order of mesh convergence of the production FE formulation (manufactured solution).

Problem: a 10 mm cube with the production's boundary terms -- the face x = 0 held (region ivc,
prescribed displacements), an elastic foundation with separate normal and tangential springs on
z = 0 (region visceral), the rib normal penalty on x = 10 (region rib), the tool face z = 10 and
the faces y = 0, 10 free (region 0) -- and the study's Yeoh material (nu = 0.49), total-Lagrangian
large deformation. A smooth displacement field ``u*`` (see :class:`Manufactured`: principal
stretches 0.89-1.10, nearly isochoric) is made the exact solution by the body force
``b = -Div P(I + grad u*)``, the tractions ``t = P N`` (plus ``S u*`` on the spring faces,
``S = k_n N N + k_t (I - N N)``) and ``u = u*`` at the nodes of x = 0; the loads are integrated as
consistent nodal loads with high-order rules (scikit-fem: degree 4 in the volume, 6 on the faces).
The production solver (:class:`liverforce.fem.LiverModel` with its springs; its
``DiscreteSystem.solve`` with these loads) runs on structured meshes of n x n x n cubes of 6 tets
(h = 10/n mm), and the results are compared with the exact values:

* ``tool``: the displacement under the tool, the Gaussian (width 3 mm) weighted mean of the
  surface displacement around the centre of the top face -- weights from the production tool
  load (``LiverModel.nodal_loads``); exact ``int g u* dA / int g dA``;
* ``ivc``: the reaction of the held face (consistent, from the residual); exact ``int P N dA``;
* ``visceral``, ``rib``: the foundation reactions ``-K u``; exact ``-int S u* dA``;
* ``u(x0)``: the displacement of the node under the tool centre (a point value).

Expected orders. All five are linear functionals of the discrete solution (or point values), so
by the duality argument their error is the product of the primal and the dual errors in the
energy-type norm ``|u - u_h|_1 + |p - p_h|_0 / sqrt(mu K)``-like:

* ``p2_mean_dilatation`` (production): P2 displacements with an element-constant (P0) pressure /
  dilatation (the condensed u-p-J mixed element). The P0 pressure is approximated to O(h), so
  the energy error is O(h) and the functionals converge as O(h^2); point values in 3D converge
  like the L2 error, also O(h^2).
* ``p2`` (pure displacement): energy error O(h^2), functionals O(h^4) asymptotically, with a
  constant that grows with K / mu (locking).
* ``p1``: energy error O(h), functionals O(h^2), with a constant that grows with K / mu.

Measured (nu = 0.49, relative errors at n = 8, observed order between n = 8 and 12 or 12 and 16):

=====================  ===========================  ====================================
formulation            tool / ivc error at n = 8    observed orders (tool ivc visc rib u)
=====================  ===========================  ====================================
p2_mean_dilatation     1.7e-3 / 6.4e-3              2.00 1.93 1.91 2.01 2.05 (n 8 -> 12)
p2                     2.5e-5 / 1.6e-5              3.63 3.54 3.50 3.28 3.38 (n 6 -> 8)
p1                     7.6e-3 / 1.1e-2              1.98 2.07 2.13 1.98 1.84 (n 12 -> 16)
=====================  ===========================  ====================================

Usage: ``python benchmarks/convergence_rate.py [--levels 2 4 6 8 12] [--formulation p2_mean_dilatation]
[--nu 0.49]`` (levels are cells per cube edge, even; about a minute for the default levels on one
core, most of it the n = 12 mesh). ``tests/fem/test_convergence_rate.py`` asserts the orders.
"""

from __future__ import annotations

import argparse
import time
from functools import lru_cache

import numpy as np

L = 10.0  # cube edge (mm)
TOOL_POINT = np.array([5.0, 5.0, L])
TOOL_RADIUS = 3.0  # mm: 4 r > the top face's half diagonal, so the production load cutoff keeps all of it
YEOH = {"C10": 1.61e-3, "C20": 12.5e-3, "C30": 5.31e-3}  # the study's Yeoh set (MPa)
NU = 0.49
SPRING = (0.01, 0.004)  # visceral k_n, k_t (N/mm^3)
RIB_KN = 0.05  # N/mm^3
AMPLITUDE = 0.15
QUANTITIES = ("tool", "ivc", "visceral", "rib", "u(x0)")
IVC, VISCERAL, RIB = 1, 3, 4


def material(nu: float = NU):
    from liverforce.fem import make_material

    return make_material("yeoh", YEOH, nu=nu)


class Manufactured:
    """The exact solution for Poisson ratio ``nu`` and the loads that make it one.

    ``u* = phi(X) - X + (mu0 / K) v(X)``: ``phi`` composes three shears ``x += a(y, z)``,
    ``y += b(x, z)``, ``z += c(x, y)`` (each with unit Jacobian, so ``phi`` is exactly isochoric)
    and ``v`` is a smooth dilatational field, so ``J* - 1 = O(mu0 / K)`` and the pressure
    ``K (J* - 1)`` stays of the order of the shear stresses however large ``K`` is, as in a nearly
    incompressible body. (A field whose ``J* - 1`` does not shrink with ``1/K`` makes the pressure,
    and with it every discretisation error, grow in proportion to ``K``.)
    """

    def __init__(self, nu: float = NU):
        import sympy as s

        self.nu = nu
        self.material = material(nu)
        x, y, z = X = s.symbols("x y z")
        c = AMPLITUDE * L
        x1 = x + c * (0.3 * (z / L) ** 2 + 0.2 * s.sin(s.pi * y / L))
        y2 = y + c * (0.3 * (x1 / L) * s.cos(s.pi * z / (2 * L)) - 0.1 * (z / L) ** 2)
        z3 = z + c * (-0.4 * (x1 / L) ** 2 + 0.2 * (x1 / L) * (y2 / L) + 0.1 * s.sin(s.pi * y2 / L))
        v = c * s.Matrix([(x / L) * (y / L), (y / L) * (z / L), (z / L) * (x / L)])
        u = s.Matrix([x1 - x, y2 - y, z3 - z]) + (self.material.mu0 / self.material.bulk) * v
        grad = u.jacobian(X)
        hess = [[[s.diff(u[i], X[j], X[k]) for k in range(3)] for j in range(3)] for i in range(3)]

        def compile_(expr):
            if isinstance(expr, (list, tuple)):
                fs = [compile_(e) for e in expr]
                return lambda P: np.stack([f(P) for f in fs])
            f = s.lambdify(X, expr, "numpy")
            return lambda P: np.broadcast_to(np.asarray(f(P[0], P[1], P[2]), float), np.shape(P[0]))

        self._u = compile_(list(u))
        self._grad = compile_([list(grad.row(i)) for i in range(3)])
        self._hess = compile_(hess)

    def u(self, X):
        """u*(X) for points X (3, ...) -> (3, ...)."""
        return self._u(np.asarray(X, float))

    def deformation(self, X):
        """F = I + grad u* at points X (3, ...) -> (..., 3, 3)."""
        G = self._grad(np.asarray(X, float))
        return np.moveaxis(G, (0, 1), (-2, -1)) + np.eye(3)

    def body_force(self, X, chunk=20000):
        """``b = -Div P = -A_iJkL d2u_k / dX_L dX_J`` at points X (3, ...) -> (3, ...)."""
        shape = np.shape(X)[1:]
        Xf = np.asarray(X, float).reshape(3, -1)
        out = np.empty_like(Xf)
        for s in range(0, Xf.shape[1], chunk):
            Xc = Xf[:, s:s + chunk]
            A = self.material.tangent(self.deformation(Xc))  # (n, i, J, k, L)
            H = np.moveaxis(self._hess(Xc), -1, 0)  # (n, k, L, J)
            out[:, s:s + chunk] = -np.einsum("niJkL,nkLJ->in", A, H)
        return out.reshape((3,) + shape)

    def traction(self, X, N, springs=(0.0, 0.0)):
        """``t = P N + (k_n N N + k_t (I - N N)) u*`` at points X (3, ...), unit normals N (3, ...)."""
        P = self.material.stress(self.deformation(X))  # (..., 3, 3)
        Nm = np.moveaxis(np.broadcast_to(np.asarray(N, float), np.shape(X)), 0, -1)
        t = np.einsum("...iJ,...J->...i", P, Nm)
        kn, kt = springs
        if kn or kt:
            u = np.moveaxis(self.u(X), 0, -1)
            un = np.einsum("...i,...i->...", u, Nm)[..., None]
            t = t + kn * un * Nm + kt * (u - un * Nm)
        return np.moveaxis(t, -1, 0)

    def consistent_loads(self, model, points, tets, facets, region):
        """Nodal loads (production dof order) of the body force and of the face tractions."""
        import skfem
        from skfem import ElementTetP1, ElementTetP2, ElementVector, LinearForm, asm

        from liverforce.fem.forms_skfem import dof_map

        mesh = skfem.MeshTet(points.T.copy(), tets.T.copy())
        elem = ElementVector(ElementTetP2() if model.disc.order == 2 else ElementTetP1())  # the model's elements
        basis = skfem.Basis(mesh, elem, intorder=4)

        @LinearForm
        def load(v, w):  # the load values at the quadrature points are computed once, outside
            return np.einsum("i...,i...->...", w["t"], v.value)

        f = asm(load, basis, t=self.body_force(basis.global_coordinates().value))
        n = len(points)
        keys = np.sort(mesh.facets.T, axis=1) @ np.array([n * n, n, 1])
        order = np.argsort(keys)
        for rid, springs in {0: (0.0, 0.0), VISCERAL: SPRING, RIB: (RIB_KN, 0.0)}.items():
            sel = np.sort(facets[region == rid], axis=1) @ np.array([n * n, n, 1])
            fb = skfem.FacetBasis(mesh, elem, facets=order[np.searchsorted(keys[order], sel)], intorder=6)
            f = f + asm(load, fb, t=self.traction(fb.global_coordinates().value, fb.normals, springs))
        return f[dof_map(basis, model.disc.nodes)]

    @lru_cache(maxsize=None)
    def exact_values(self) -> dict:
        """Exact quantities (dict of 3-vectors), by composite Gauss-Legendre rules on the faces."""
        X, W = _gauss_face(2, L)
        g = np.exp(-0.5 * np.sum((X - TOOL_POINT[:, None]) ** 2, axis=0) / TOOL_RADIUS**2) * W
        out = {"tool": self.u(X) @ g / g.sum(), "u(x0)": self.u(TOOL_POINT[:, None])[:, 0]}
        X, W = _gauss_face(0, 0.0)
        out["ivc"] = self.traction(X, [[-1.0], [0.0], [0.0]]) @ W
        for name, axis, value, N, springs in (("visceral", 2, 0.0, [[0.0], [0.0], [-1.0]], SPRING),
                                              ("rib", 0, L, [[1.0], [0.0], [0.0]], (RIB_KN, 0.0))):
            X, W = _gauss_face(axis, value)
            out[name] = -(self.traction(X, N, springs) - self.traction(X, N)) @ W
        return out


def _gauss_face(fixed_axis, value, m=80, panels=8):
    """Composite Gauss-Legendre points (3, m*m) and weights on the face {X[fixed_axis] = value}."""
    g, w = np.polynomial.legendre.leggauss(m // panels)
    edges = np.linspace(0.0, L, panels + 1)
    t = np.concatenate([0.5 * (a + b) + 0.5 * (b - a) * g for a, b in zip(edges[:-1], edges[1:])])
    wt = np.concatenate([0.5 * (b - a) * w for a, b in zip(edges[:-1], edges[1:])])
    A, B = np.meshgrid(t, t, indexing="ij")
    free = [a for a in range(3) if a != fixed_axis]
    X = np.zeros((3, A.size))
    X[free[0]], X[free[1]], X[fixed_axis] = A.ravel(), B.ravel(), value
    return X, np.outer(wt, wt).ravel()


@lru_cache(maxsize=None)
def manufactured(nu: float = NU) -> Manufactured:
    return Manufactured(nu)


def cube_regions(points, facets):
    """Facet regions of the cube: x = 0 ivc (held), z = 0 visceral, x = L rib, the rest free."""
    c = points[facets].mean(axis=1)
    region = np.zeros(len(facets), np.int64)
    region[c[:, 0] < 1e-9] = IVC
    region[c[:, 2] < 1e-9] = VISCERAL
    region[c[:, 0] > L - 1e-9] = RIB
    return region


def solve_level(n: int, formulation: str = "p2_mean_dilatation", nu: float = NU, tol: float = 1e-10) -> dict:
    """Solve on the n x n x n cube mesh; returns h, the quantities, their relative errors, solver facts."""
    from liverforce.fem import BoundaryParams, LiverModel, SolverOptions, ToolLoad
    from liverforce.fem.testing import box_mesh

    if n % 2:
        raise ValueError("n must be even (a node under the tool centre)")
    t0 = time.perf_counter()
    mms = manufactured(nu)
    points, tets, facets = box_mesh((n, n, n), size=(L, L, L))
    region = cube_regions(points, facets)
    bp = BoundaryParams(0.0, 0.0, SPRING[0], SPRING[1], RIB_KN, 0.0)
    model = LiverModel(points, tets, facets, region, mms.material, bp,
                       SolverOptions(formulation=formulation, tol=tol))
    f = mms.consistent_loads(model, points, tets, facets, region)
    fixed = model.system.fixed
    u_bar = mms.u(model.disc.nodes[fixed // 3].T)[fixed % 3, np.arange(fixed.size)]
    res = model.system.solve(mms.material, f_ext=f, u_bar=u_bar)
    if not res.converged:
        raise RuntimeError(f"n={n}: {res.reason}")
    reac = model.reactions(res.u, res.f_int, f)
    weights = np.stack([model.nodal_loads(ToolLoad(TOOL_POINT, e, TOOL_RADIUS)) for e in np.eye(3)])
    centre = int(np.argmin(np.linalg.norm(model.disc.nodes - TOOL_POINT, axis=1)))
    values = {"tool": weights @ res.u, "ivc": reac["ivc"], "visceral": reac["visceral"], "rib": reac["rib"],
              "u(x0)": res.u.reshape(-1, 3)[centre]}
    exact = mms.exact_values()
    errors = {k: float(np.linalg.norm(values[k] - exact[k]) / np.linalg.norm(exact[k])) for k in values}
    return {"n": n, "h": L / n, "dofs": model.n_dofs, "values": values, "errors": errors,
            "newton": res.newton_iterations, "seconds": time.perf_counter() - t0}


def observed_orders(levels: list[dict], key: str) -> list[float]:
    """``log(e_i / e_{i+1}) / log(h_i / h_{i+1})`` between consecutive levels."""
    e = np.array([lv["errors"][key] for lv in levels])
    h = np.array([lv["h"] for lv in levels])
    return list(np.log(e[:-1] / e[1:]) / np.log(h[:-1] / h[1:]))


def table(levels: list[dict]) -> str:
    """Rows: h, n, dofs, then (relative error, observed order) per quantity."""
    head = f"{'h (mm)':>7} {'n':>3} {'dofs':>6}  " + "  ".join(f"{q:>17}" for q in QUANTITIES)
    sub = f"{'':>7} {'':>3} {'':>6}  " + "  ".join(f"{'error':>9} {'order':>7}" for _ in QUANTITIES)
    orders = {q: [np.nan] + observed_orders(levels, q) for q in QUANTITIES}
    rows = [head, sub]
    for i, lv in enumerate(levels):
        cells = "  ".join(f"{lv['errors'][q]:>9.2e} {orders[q][i]:>7.2f}" for q in QUANTITIES)
        rows.append(f"{lv['h']:>7.3f} {lv['n']:>3d} {lv['dofs']:>6d}  {cells}")
    return "\n".join(rows)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--levels", type=int, nargs="+", default=[2, 4, 6, 8, 12],
                    help="cells per cube edge, even (a node sits under the tool centre)")
    ap.add_argument("--formulation", default="p2_mean_dilatation", choices=["p2_mean_dilatation", "p2", "p1"])
    ap.add_argument("--nu", type=float, default=NU, help="initial Poisson ratio (sets the bulk modulus)")
    ap.add_argument("--threads", type=int, default=1, help="BLAS/numba threads (default 1)")
    args = ap.parse_args(argv)
    from liverforce.pipeline.job import thread_env

    thread_env(args.threads)
    exact = manufactured(args.nu).exact_values()
    print(f"manufactured solution on a {L:g} mm cube, Yeoh, nu = {args.nu}, formulation {args.formulation}")
    print("exact: " + "; ".join(f"{k} {np.array2string(v, precision=4)}" for k, v in exact.items()))
    levels = []
    for n in args.levels:
        levels.append(solve_level(n, args.formulation, args.nu))
        lv = levels[-1]
        print(f"  n = {n}: {lv['dofs']} dofs, {lv['newton']} Newton iterations, {lv['seconds']:.1f} s", flush=True)
    print("relative error |q_h - q| / |q| and observed order log(e_i / e_i+1) / log(h_i / h_i+1):")
    print(table(levels))
    print("expected order: 2 for p2_mean_dilatation (P0 pressure) and p1, 4 for p2 (asymptotically)")


if __name__ == "__main__":
    main()
