"""The liver problem: regions -> boundary terms -> Newton solve -> case result.

Facet regions (``facet_region`` of :class:`liverforce.mesh.types.LiverMesh`):

== ============ ==========================================================
0  free         traction free (the tool load may act here)
1  ivc          fixed (homogeneous Dirichlet on all nodes of the region)
2  ligament     elastic foundation ``(k_n, k_t)`` per unit area
3  visceral     elastic foundation ``(k_n, k_t)`` per unit area
4  rib          free sliding, normal penalty ``rib_kn``: bilateral (no normal
                motion) or unilateral (pushes only, the liver may separate)
== ============ ==========================================================

An optional uniform body force (gravity, ``body_force_n_per_mm3``) acts on the
reference volume as a dead load, ramped together with the tool load.

Example
-------
>>> import numpy as np, skfem
>>> from liverforce.fem import make_material, BoundaryParams, ToolLoad, SolverOptions, solve_case
>>> m = skfem.MeshTet.init_tensor(*[np.linspace(0, 10, 3)] * 3)
>>> facets = m.facets[:, m.boundary_facets()].T
>>> region = np.where(m.p[2, facets].mean(axis=1) < 1e-9, 1, 0)  # bottom fixed
>>> mat = make_material("neo_hookean", {"C10": 1e-3}, nu=0.45)
>>> res = solve_case(m.p.T, m.t.T, facets, region, mat, BoundaryParams(),
...                  ToolLoad([5, 5, 10], [0, 0, -0.01], 3.0), SolverOptions(formulation="p1"))
>>> res.converged, bool(res.u_nodes[:, 2].min() < 0)
(True, True)
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .boundary import (UnilateralPenalty, body_force_loads, per_area_stiffness, region_areas, spring_matrix,
                       tool_nodal_forces, vertex_normals)
from .elements import build_discretization
from .kinematics import principal_stretch_range
from .materials import Material
from .newton import DiscreteSystem, SolverOptions
from .assembly import formulation_spec

FREE, IVC, LIGAMENT, VISCERAL, RIB = 0, 1, 2, 3, 4
REGION_NAMES = {FREE: "free", IVC: "ivc", LIGAMENT: "ligament", VISCERAL: "visceral", RIB: "rib"}
RIB_CONTACTS = ("bilateral", "unilateral")


@dataclass
class BoundaryParams:
    """Foundation stiffnesses per unit reference area (N/mm³).

    The defaults are the study's totals (56.3 N/mm ligaments, 42.6 N/mm
    visceral face) spread over the regions of a 1.26 L prototype liver with
    equal normal and tangential springs, and a rib normal penalty of
    0.1 N/mm³; use :meth:`from_totals` for a given mesh.

    Normal and tangential foundation stiffnesses are independent fields.
    ``rib_contact``: "bilateral" (default: the rib penalty holds the liver in
    both directions) or "unilateral" (frictionless, pushes only:
    :class:`~liverforce.fem.boundary.UnilateralPenalty`; needs ``rib_kt == 0``).
    ``body_force_n_per_mm3``: uniform dead body force (N/mm³), e.g.
    :func:`~liverforce.fem.boundary.gravity_body_force`; default none.
    """

    ligament_kn: float = 0.0041
    ligament_kt: float = 0.0041
    visceral_kn: float = 0.0016
    visceral_kt: float = 0.0016
    rib_kn: float = 0.1
    rib_kt: float = 0.0
    normals: str = "vertex"
    rib_contact: str = "bilateral"
    body_force_n_per_mm3: tuple = (0.0, 0.0, 0.0)

    def __post_init__(self):
        if self.normals not in ("vertex", "facet"):
            raise ValueError(f"BoundaryParams.normals must be 'vertex' or 'facet', got {self.normals!r}")
        if self.rib_contact not in RIB_CONTACTS:
            raise ValueError(f"BoundaryParams.rib_contact must be one of {RIB_CONTACTS}, got {self.rib_contact!r}")
        if self.rib_contact == "unilateral" and self.rib_kt != 0.0:
            raise ValueError("unilateral rib contact is frictionless: rib_kt must be 0")
        b = tuple(float(x) for x in np.asarray(self.body_force_n_per_mm3, float).reshape(-1))
        if len(b) != 3 or not all(np.isfinite(b)):
            raise ValueError(f"BoundaryParams.body_force_n_per_mm3 must be a finite 3-vector, got {b}")
        self.body_force_n_per_mm3 = b

    @classmethod
    def from_totals(cls, points, facets, facet_region, ligament_total_n_per_mm: float = 56.3,
                    visceral_total_n_per_mm: float = 42.6, tangential_ratio: float = 1.0,
                    rib_kn: float = 0.1, rib_contact: str = "bilateral",
                    body_force_n_per_mm3=(0.0, 0.0, 0.0)) -> "BoundaryParams":
        """Per-area stiffness = region total (N/mm) / region reference area (mm²).

        ``tangential_ratio`` sets ``k_t = ratio * k_n`` for both foundations
        (tangential stiffness independent of the normal one; 1 = isotropic springs).
        A region missing from the mesh gets zero stiffness.
        """
        areas = region_areas(points, facets, facet_region)
        lig = per_area_stiffness(ligament_total_n_per_mm, areas[LIGAMENT]) if areas.get(LIGAMENT, 0) > 0 else 0.0
        vis = per_area_stiffness(visceral_total_n_per_mm, areas[VISCERAL]) if areas.get(VISCERAL, 0) > 0 else 0.0
        return cls(lig, tangential_ratio * lig, vis, tangential_ratio * vis, rib_kn, 0.0,
                   rib_contact=rib_contact, body_force_n_per_mm3=body_force_n_per_mm3)

    def with_supports(self, support_boundary: dict | None) -> "BoundaryParams":
        """These parameters with a user's foundation stiffnesses (N/mm³) in place.

        ``support_boundary`` : ``{"ligament_kn": ..., "visceral_kt": ...}`` as
        :func:`liverforce.mesh.supports.support_stiffness` returns (the mesh
        stage writes it to the features JSON); None or empty: unchanged.
        """
        from dataclasses import fields, replace

        allowed = {f.name for f in fields(self)} - {"normals", "rib_contact", "body_force_n_per_mm3"}
        bad = set(support_boundary or {}) - allowed
        if bad:
            raise ValueError(f"support_boundary: unknown BoundaryParams fields {sorted(bad)} "
                             f"(allowed {sorted(allowed)})")
        return replace(self, **{k: float(v) for k, v in (support_boundary or {}).items()})

    def region_stiffness(self) -> dict[int, tuple[float, float]]:
        return {
            LIGAMENT: (self.ligament_kn, self.ligament_kt),
            VISCERAL: (self.visceral_kn, self.visceral_kt),
            RIB: (self.rib_kn, self.rib_kt),
        }


@dataclass
class ToolLoad:
    """Tool force: total ``force_N`` (N, dead load) as a Gaussian traction of width ``radius_mm``
    (standard deviation, mm) around ``point_mm`` (mm) on the reference surface."""

    point_mm: np.ndarray
    force_N: np.ndarray
    radius_mm: float = 5.0

    def __post_init__(self):
        self.point_mm = np.asarray(self.point_mm, float).reshape(3)
        self.force_N = np.asarray(self.force_N, float).reshape(3)


@dataclass
class CaseResult:
    """Outcome of one case (never raised; check ``converged`` and ``reason``).

    Attributes
    ----------
    u_nodes : (n_vertices, 3) displacement at the original mesh vertices (mm).
    converged, reason : convergence flag and a human-readable reason.
    load_fraction : load fraction reached (1.0 when converged).
    load_steps, newton_iterations : counts over the case (incl. rejected steps).
    final_residual : last relative force residual.
    wall_time_s : solve time.
    linear_solver : backend of the last factorisation.
    reactions : total force (N, 3-vector) exerted on the liver by each support
        region ("ivc", "ligament", "visceral", "rib"), the applied "tool" load,
        the body force "gravity" (zero unless enabled) and "imbalance" = sum of
        all of them (≈ 0 at equilibrium).
    state : full dof vector (all nodes of the formulation) for warm starts.
    formulation, n_dofs, factorizations : solver facts of this case.
    timings : seconds in material/kernel assembly, factorisation and solves.
    history : load steps as ``(attempt, load fraction, accepted, iterations or reason)``.
    load : the :class:`ToolLoad` of this case (a converged result passed as
        ``u0`` lets the next case continue along the load path from it).
    min_principal_stretch, max_principal_stretch : smallest and largest principal
        stretch of ``F`` over every quadrature point of the formulation's elements at
        the returned state (the converged one, or the last accepted state of a failed
        case); NaN if that state is not finite. Compare with the Drucker-checked
        range (``material.stability_stretch``).
    """

    u_nodes: np.ndarray
    converged: bool
    reason: str
    load_fraction: float
    load_steps: int
    newton_iterations: int
    final_residual: float
    wall_time_s: float
    linear_solver: str
    reactions: dict = field(default_factory=dict)
    state: object | None = None
    load: ToolLoad | None = None
    formulation: str = ""
    n_dofs: int = 0
    factorizations: int = 0
    timings: dict = field(default_factory=dict)
    history: list = field(default_factory=list)
    min_principal_stretch: float = float("nan")
    max_principal_stretch: float = float("nan")


class LiverModel:
    """A meshed liver with boundary terms, reusable across cases.

    Precomputes shape-function gradients, the sparsity pattern, the foundation
    stiffness and (lazily) the symbolic factorisation; :meth:`solve` takes a
    tool load and optionally a different material and a warm start.

    Parameters
    ----------
    points : (n, 3) vertices (mm).
    tets : (m, 4) tetrahedra (re-oriented if needed).
    facets : (k, 3) boundary triangles, outward normals.
    facet_region : (k,) region ids (see module docstring).
    material : default :class:`~liverforce.fem.materials.Material`.
    boundary : :class:`BoundaryParams`.
    options : :class:`~liverforce.fem.newton.SolverOptions`.
    """

    def __init__(self, points, tets, facets, facet_region, material: Material,
                 boundary: BoundaryParams | None = None, options: SolverOptions | None = None):
        self.options = options or SolverOptions()
        self.material = material
        self.boundary = boundary or BoundaryParams()
        points = np.ascontiguousarray(points, float)
        facets = np.asarray(facets, np.int64)
        region = np.asarray(facet_region).astype(np.int64)
        if facets.ndim != 2 or facets.shape[1] != 3:
            raise ValueError(f"facets must have shape (k, 3), got {facets.shape}")
        if region.shape != (facets.shape[0],):
            raise ValueError(f"facet_region must have shape ({facets.shape[0]},), got {region.shape}")
        if region.size and (region.min() < 0 or region.max() > 4):
            raise ValueError("facet_region ids must be in 0..4 (free, ivc, ligament, visceral, rib)")
        self.points, self.facets, self.facet_region = points, facets, region
        order, _ = formulation_spec(self.options.formulation)
        self.disc = build_discretization(points, tets, order)
        fnodes = self.disc.facet_nodes(facets)
        fixed_nodes = np.unique(fnodes[region == IVC])
        fixed_dofs = (3 * fixed_nodes[:, None] + np.arange(3)).ravel()
        stiff = self.boundary.region_stiffness()
        unilateral = self.boundary.rib_contact == "unilateral"
        self.region_springs = {}
        self.rib_contact = None
        for r, kk in stiff.items():
            # a region's own facets define its normal field: a support is a surface of its own,
            # and averaging across a sharp edge into a neighbouring region would tilt it
            normals = vertex_normals(points, facets[region == r]) if self.boundary.normals == "vertex" else None
            if r == RIB and unilateral:
                if kk[0] > 0 and np.any(region == RIB):
                    self.rib_contact = UnilateralPenalty(self.disc, points, facets[region == RIB], kk[0], normals)
                continue
            self.region_springs[REGION_NAMES[r]] = spring_matrix(self.disc, points, facets, region, {r: kk}, normals)
        spring = sum(self.region_springs.values())
        self.system = DiscreteSystem(points, tets, fixed_dofs, spring, self.options, disc=self.disc,
                                     contact=self.rib_contact)
        b = np.asarray(self.boundary.body_force_n_per_mm3, float)
        self.f_body = body_force_loads(self.disc, b) if np.any(b != 0.0) else None
        self._load_mask = region != IVC
        if not np.any(self._load_mask):
            self._load_mask = np.ones(len(facets), bool)
        self.n_vertices = len(points)

    @classmethod
    def from_mesh(cls, mesh, material: Material, boundary: BoundaryParams | None = None,
                  options: SolverOptions | None = None) -> "LiverModel":
        """Build from a :class:`liverforce.mesh.types.LiverMesh` (or any object with
        ``points``, ``tets``, ``facets`` and ``facet_region``)."""
        return cls(mesh.points, mesh.tets, mesh.facets, mesh.facet_region, material, boundary, options)

    @property
    def n_dofs(self) -> int:
        return self.disc.n_dofs

    def nodal_loads(self, load: ToolLoad) -> np.ndarray:
        """Consistent nodal loads (n_dofs,) of the tool traction (sum = ``load.force_N``)."""
        return tool_nodal_forces(self.disc, self.points, self.facets, load.point_mm, load.force_N,
                                 load.radius_mm, facet_mask=self._load_mask)

    def expand_state(self, u0) -> np.ndarray:
        """Full dof vector from a state vector or (n_vertices, 3) vertex displacements."""
        u0 = np.asarray(u0, float)
        if u0.size == self.n_dofs:
            return u0.reshape(-1).copy()
        if u0.shape == (self.n_vertices, 3):
            U = np.zeros((self.disc.n_nodes, 3))
            U[: self.n_vertices] = u0
            if self.disc.order == 2:
                e = self.disc.edges
                U[self.n_vertices:] = 0.5 * (u0[e[:, 0]] + u0[e[:, 1]])
            return U.ravel()
        raise ValueError(f"u0 must be a state vector of size {self.n_dofs} or ({self.n_vertices}, 3) vertex displacements")

    def gravity_loads(self) -> np.ndarray:
        """Nodal loads (n_dofs,) of the body force (zeros without one); they sum to the weight."""
        return self.f_body.copy() if self.f_body is not None else np.zeros(self.n_dofs)

    def reactions(self, u: np.ndarray, f_int: np.ndarray, f_ext: np.ndarray,
                  f_gravity: np.ndarray | None = None) -> dict:
        """Force (N) exerted on the liver by each support region, the tool load, the body force and their sum.

        ``f_ext`` : all applied nodal loads; ``f_gravity`` : the body-force part of them (default none).
        """
        R = f_int + self.system.boundary_force(u) - f_ext
        out = {}
        fx = self.system.fixed
        out["ivc"] = np.bincount(fx % 3, weights=R[fx], minlength=3) if fx.size else np.zeros(3)
        for name, K in self.region_springs.items():
            out[name] = -(K @ u).reshape(-1, 3).sum(axis=0)
        if self.boundary.rib_contact == "unilateral":
            out["rib"] = (-self.rib_contact.energy_force(u)[1].reshape(-1, 3).sum(axis=0)
                          if self.rib_contact is not None else np.zeros(3))
        grav = np.zeros(3) if f_gravity is None else f_gravity.reshape(-1, 3).sum(axis=0)
        out["tool"] = f_ext.reshape(-1, 3).sum(axis=0) - grav
        out["gravity"] = grav
        out["imbalance"] = sum(out[k] for k in ("ivc", "ligament", "visceral", "rib", "tool", "gravity"))
        return out

    def solve(self, load: ToolLoad, u0=None, material: Material | None = None,
              options: SolverOptions | None = None) -> CaseResult:
        """Solve one case.

        ``u0`` is a warm start: a previous :class:`CaseResult` (best: the solver
        then knows its load and can continue along the load path from it), its
        ``state`` vector, or (n_vertices, 3) vertex displacements.

        ``material`` replaces the model's default for this case (same geometry);
        ``options`` may change tolerances and stepping but not the formulation.
        """
        mat = material or self.material
        opt = options or self.options
        if opt.formulation != self.options.formulation:
            raise ValueError("options.formulation must match the LiverModel's formulation")
        f_tool = self.nodal_loads(load)
        f_ext, f0, f_tool0 = f_tool, None, None
        if self.f_body is not None:  # gravity: a dead load on the same load path as the tool
            f_ext = f_tool + self.f_body
        if isinstance(u0, CaseResult):
            if u0.converged and u0.load is not None and u0.state is not None:
                f0 = f_tool0 = self.nodal_loads(u0.load)
                if self.f_body is not None:
                    f0 = f_tool0 + self.f_body
            u0 = u0.state if u0.state is not None else u0.u_nodes
        start = self.expand_state(u0) if u0 is not None else None
        res = self.system.solve(mat, f_ext=f_ext, u0=start, f0=f0, options=opt)
        f_int = res.f_int
        if f_int is None:
            ev = self.system.assembler.evaluate(res.u, mat, tangent=False)
            f_int = ev.f_int if ev.valid else np.full(self.n_dofs, np.nan)
        f_now = res.f_load if res.f_load is not None else res.load_fraction * f_ext
        f_grav = None
        if self.f_body is not None:
            # the load path is affine between loads that all hold the whole body force or none of
            # it: read its share from the dofs no tool load touches (interior nodes)
            m = (f_tool == 0.0) & (self.f_body != 0.0)
            if f_tool0 is not None:
                m &= f_tool0 == 0.0
            fb = self.f_body[m]
            f_grav = self.f_body * (float(f_now[m] @ fb) / float(fb @ fb) if fb.size else res.load_fraction)
        reac = self.reactions(res.u, f_int, f_now, f_grav)
        lam_min, lam_max = principal_stretch_range(self.disc, res.u)
        return CaseResult(
            u_nodes=res.u.reshape(-1, 3)[: self.n_vertices].copy(),
            converged=res.converged,
            reason=res.reason,
            load_fraction=res.load_fraction,
            load_steps=res.load_steps,
            newton_iterations=res.newton_iterations,
            final_residual=res.final_residual,
            wall_time_s=res.wall_time_s,
            linear_solver=res.linear_solver,
            reactions=reac,
            state=res.u,
            load=load,
            formulation=opt.formulation,
            n_dofs=self.n_dofs,
            factorizations=res.factorizations,
            timings=res.timings,
            history=res.history,
            min_principal_stretch=lam_min,
            max_principal_stretch=lam_max,
        )


def solve_case(points, tets, facets, facet_region, material: Material, boundary: BoundaryParams,
               load: ToolLoad, options: SolverOptions | None = None, u0=None) -> CaseResult:
    """Build a :class:`LiverModel` and solve one case (convenience; use the model for sweeps)."""
    return LiverModel(points, tets, facets, facet_region, material, boundary, options).solve(load, u0=u0)
