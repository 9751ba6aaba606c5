"""Benchmark of the liver FE solver (liverforce.fem).

Prints medians over repeats:

1. cold 3 N case and warm-started sweep (one exertion point, Sobol forces
   1-5 N within a 30 degree cone, chained nearest-neighbour) with the default
   formulation (P2 mean dilatation) at the default (~5k P2 nodes) and, unless
   ``--quick``, the ~20k-node resolution: time per case, cases per core-hour,
   share of time in assembly / factorisation / solves; and a shard as the
   pipeline runs it (the design's cases at one exertion point, 0-5 N, the
   first one cold, warm starts from the pool of recent solutions), with
   fixed (scenario II) and varied (III) material constants;
2. FElupe vs ours on the same P1 mesh and case (same answer checked);
3. mesh convergence: surface displacement near the tool and support reactions
   at 3 N on the default mesh and on one with twice the node density, with and
   without the default refinement at the exertion points.

Usage: ``python benchmarks/bench_fem.py [--quick] [--repeats N] [--cases N] [--threads N]``

Meshes: ``liverforce.mesh`` (procedural liver + gmsh) when importable, else a
liver-sized ellipsoid (scikit-fem). Facet regions use simple normal/position
rules here (ivc patch posterior-superior, ligaments superior-posterior,
visceral inferior, rib right-lateral) unless the mesh package provides them.
"""

from __future__ import annotations

import argparse
import sys
import time

from liverforce.pipeline.job import thread_env

_ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
_ap.add_argument("--quick", action="store_true", help="default mesh only, fewer cases")
_ap.add_argument("--repeats", type=int, default=3, help="repeats of the cold case")
_ap.add_argument("--cases", type=int, default=24, help="cases in the warm-started sweep")
_ap.add_argument("--threads", type=int, default=1, help="BLAS/numba threads (default 1)")
ARGS = _ap.parse_args()
thread_env(ARGS.threads)

import numpy as np  # noqa: E402
from scipy.stats import qmc  # noqa: E402

from liverforce.fem import BoundaryParams, LiverModel, SolverOptions, ToolLoad, make_material  # noqa: E402
from liverforce.fem.elements import facet_geometry  # noqa: E402
from liverforce.fem.testing import boundary_facets, ellipsoid_liver  # noqa: E402

YEOH = {"C10": 1.61e-3, "C20": 12.5e-3, "C30": 5.31e-3}  # the study's Yeoh set, MPa


# ----------------------------------------------------------------------------
# meshes
# ----------------------------------------------------------------------------
def tag_regions(points, tets):
    """Facets and liver-like regions by normal/position rules (RAS frame)."""
    facets = boundary_facets(points, tets)
    _, n = facet_geometry(points, facets)
    c = points[facets].mean(axis=1)
    region = np.zeros(len(facets), np.int8)
    region[n[:, 2] < -0.5] = 3
    region[(n[:, 2] > 0.4) & (n[:, 1] < -0.3)] = 2
    region[(n[:, 0] > 0.7) & (n[:, 2] > -0.5)] = 4
    surf = np.unique(facets)
    mid = np.abs(points[surf, 0] - np.median(points[surf, 0])) < 0.15 * np.ptp(points[:, 0])
    cand = surf[mid]
    p_ivc = points[cand[np.argmax(-points[cand, 1] + 0.5 * points[cand, 2])]]
    region[np.linalg.norm(c - p_ivc, axis=1) < 20.0] = 1
    visible = (region == 0) & ((n[:, 1] > 0.0) | (n[:, 2] > 0.3))
    return facets, region, visible


MESHES: dict = {}  # LiverMesh objects built by liver_mesh, by target size


def liver_mesh(target_vertices: int, refine_edge_mm: float | None = 6.0):
    """(points, tets, facets, region, visible, source, x0) with a bulk of about ``target_vertices`` vertices.

    As the mesh stage builds it by default: conforming regions, refined to
    ``refine_edge_mm`` within 10 mm of 8 candidate exertion points and on the
    IVC patch (None: no refinement); ``x0`` is the first candidate.
    """
    try:  # the project's own mesh stage, when present
        from liverforce.geometry.procedural import procedural_liver
        from liverforce.mesh.build import build_liver_mesh  # type: ignore
        from liverforce.pipeline.sweep import closest_surface_points

        m = build_liver_mesh(procedural_liver(0), target_nodes=target_vertices,
                             refine_radius_mm=10.0 if refine_edge_mm else 0.0,
                             refine_edge_mm=refine_edge_mm, refine_ivc_edge_mm=refine_edge_mm, refine_growth=0.6,
                             exertion_sampling={"n_points": 8, "min_spacing_mm": 15.0, "seed": 0})
        if refine_edge_mm is None:
            m.meta["refine_points"] = None
        MESHES[target_vertices] = m
        x0 = closest_surface_points(m.points, m.facets[m.facet_visible], m.meta["exertion_candidates_mm"][0])[0]
        src = "liverforce.mesh.build" + (f", refined to {refine_edge_mm:.2f} mm at 8 exertion points"
                                         if refine_edge_mm else ", no refinement")
        return (m.points, m.tets, m.facets, m.facet_region, m.facet_visible, src, x0)
    except ImportError:  # noqa: BLE001 - fall through to the next source
        pass
    nrefs = 3 if target_vertices < 3000 else 4
    L = ellipsoid_liver(nrefs)
    x0 = exertion_point(L["points"], L["facets"], L["facet_visible"])
    return L["points"], L["tets"], L["facets"], L["facet_region"], L["facet_visible"], f"ellipsoid nrefs={nrefs}", x0


def exertion_point(points, facets, visible):
    cand = np.unique(facets[visible])
    return points[cand[np.argmax(points[cand, 2] + 0.3 * points[cand, 1])]]


def sweep_forces(n, seed=0):
    s = qmc.Sobol(3, seed=seed).random_base2(int(np.ceil(np.log2(max(n, 2)))))[:n]
    mag = 1.0 + 4.0 * s[:, 0]
    th, ph = np.deg2rad(30.0) * np.sqrt(s[:, 1]), 2 * np.pi * s[:, 2]
    F = mag[:, None] * np.column_stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), -np.cos(th)])
    order = [int(np.argmin(mag))]
    left = set(range(n)) - set(order)
    while left:  # nearest-neighbour chain for warm starts
        j = min(left, key=lambda k: np.linalg.norm(F[k] - F[order[-1]]))
        order.append(j)
        left.remove(j)
    return F[order]


# ----------------------------------------------------------------------------
def bench_resolution(label, target_vertices, n_cases, repeats):
    points, tets, facets, region, visible, source, x0 = liver_mesh(target_vertices)
    mat = make_material("yeoh", YEOH, nu=0.49)
    bp = BoundaryParams.from_totals(points, facets, region)
    t0 = time.perf_counter()
    model = LiverModel(points, tets, facets, region, mat, bp, SolverOptions(modified_newton=True))
    t_build = time.perf_counter() - t0
    print(f"\n== {label}: {source}")
    print(f"   {len(points)} vertices, {len(tets)} tets -> P2 {model.disc.n_nodes} nodes, {model.n_dofs} dofs;"
          f" model build {t_build:.2f} s")
    cold = []
    for _ in range(repeats):
        model.system.linear = type(model.system.linear)(model.options.linear_solver)  # no cached factor
        r = model.solve(ToolLoad(x0, [0.0, 0.0, -3.0], 5.0))
        cold.append(r)
    rc = cold[len(cold) // 2]
    print(f"   cold 3 N: median {np.median([c.wall_time_s for c in cold]):.2f} s  (converged={rc.converged},"
          f" steps {rc.load_steps}, iterations {rc.newton_iterations}, factorisations {rc.factorizations},"
          f" max|u| {np.abs(rc.u_nodes).max():.2f} mm, solver {rc.linear_solver})")
    F = sweep_forces(n_cases)
    prev = model.solve(ToolLoad(x0, F[0], 5.0))
    times, its, facs, tm = [], [], [], {"material": 0.0, "kernel": 0.0, "factorize": 0.0, "solve": 0.0}
    failed = 0
    for f in F[1:]:
        r = model.solve(ToolLoad(x0, f, 5.0), u0=prev)
        times.append(r.wall_time_s)
        its.append(r.newton_iterations)
        facs.append(r.factorizations)
        for k in tm:
            tm[k] += r.timings.get(k, 0.0)
        failed += not r.converged
        prev = r if r.converged else prev
    total = sum(times)
    print(f"   warm sweep ({len(times)} cases, 1-5 N): median {np.median(times):.3f} s, mean {np.mean(times):.3f} s"
          f" per case -> {3600 / np.mean(times):.0f} cases per core-hour; iterations {np.mean(its):.1f},"
          f" factorisations {np.mean(facs):.2f} per case; failed {failed}")
    print("   time shares (sweep): " + ", ".join(
        f"{k} {100 * v / total:.0f}%" for k, v in [("assembly", tm["material"] + tm["kernel"]),
                                                   ("factorisation", tm["factorize"]), ("solves", tm["solve"])])
          + f", other {100 * (1 - sum(tm.values()) / total):.0f}%")
    return points, tets, facets, region, visible, x0


def bench_shard(label, target_vertices, scenario, n_cases=25):
    """A shard as the pipeline runs it, through the product's own loop
    (:func:`liverforce.pipeline.simulate.simulate_cases`) with the default config's ``simulate``,
    ``boundary`` and ``dataset`` slices: the sweep design's cases at the first exertion point
    (chained for warm starts), the first one cold, each next one from the nearest recent solution."""
    from liverforce.config import compose
    from liverforce.pipeline.simulate import simulate_cases
    from liverforce.pipeline.sweep import exertion_set, material_checks
    from liverforce.sweep.design import build_cases

    m = MESHES.get(target_vertices)
    if m is None:
        print(f"\n== shard ({label}): needs liverforce.mesh; skipped")
        return
    cfg = compose([])
    sim = dict(cfg["simulate"], time_limit_s=600.0, max_total_iter=100_000)  # every case to its end
    ex = exertion_set(m, 8, 15.0, 0, sim["tool_radius_mm"], candidates=m.meta["exertion_candidates_mm"])
    spec = {"n_cases": 8 * n_cases, "exertion": "varies", "material": "varies" if scenario == "III" else "fixed"}
    material = dict(cfg["material"], on_unstable="clip")
    stable, bulk = material_checks(material["stability_stretch"], material["nu"])
    cases = build_cases(scenario, spec, ["g"], {"g": ex}, material, dict(cfg["sweep"]["force"]), "sobol", 0,
                        n_cases, stable, bulk).rows
    cases = [r for r in cases if r["exertion_id"] == cases[0]["exertion_id"]][:n_cases]
    facs = []
    rows = simulate_cases(cases, {"g": m}, sim, cfg["boundary"], cfg["dataset"],
                          progress=lambda n, total, rows, res: facs.append(0 if res is None else res.factorizations))
    times = [r["wall_time_s"] for r in rows]
    failed = sum(not r["converged"] for r in rows)
    print(f"\n== shard ({label}, scenario {scenario}: {len(rows)} cases at one exertion point, "
          f"{cfg['sweep']['force']['min_n']:g}-{cfg['sweep']['force']['max_n']:g} N in a "
          f"{cfg['sweep']['force']['cone_deg']:g} degree cone"
          f"{', constants +-%g %%' % (100 * material['vary_rel']) if scenario == 'III' else ''}; the first case cold;"
          f" liverforce.pipeline.simulate.simulate_cases): mean {np.mean(times):.2f} s per case -> "
          f"{3600 / np.mean(times):.0f} cases per core-hour; median {np.median(times):.2f} s;"
          f" cold first case {times[0]:.2f} s; factorisations {np.mean(facs):.2f} per case; failed {failed}")


def bench_felupe(points, tets, facets, region, x0):
    try:
        import felupe as fem
    except ImportError:
        print("\n== FElupe not installed: peer timing skipped")
        return
    mat = make_material("neo_hookean", {"C10": 1.61e-3}, nu=0.49)
    fixed_regions = np.isin(region, (1, 2, 3))  # FElupe has no tet boundary region: fix instead of springs
    reg = np.where(fixed_regions, 1, 0)
    load = ToolLoad(x0, [0.0, 0.0, -2.0], 5.0)
    ours, runs = {}, {}
    # "modified": the pipeline's solver settings (config simulate.modified_newton: true, i.e. a kept
    # factorisation with L-BFGS updates); "full": a fresh tangent every iteration, as FElupe does
    for label, modified in (("modified", True), ("full", False)):
        opts = SolverOptions(formulation="p1", tol=1e-9, modified_newton=modified)
        model = LiverModel(points, tets, facets, reg, mat, BoundaryParams(0, 0, 0, 0, 0, 0), opts)
        times = []
        for _ in range(3):
            model.system.linear = type(model.system.linear)("auto")
            r = model.solve(load)
            times.append(r.wall_time_s)
        ours[label], runs[label] = float(np.median(times)), r
    r = runs["full"]
    f_nodes = model.nodal_loads(load).reshape(-1, 3)
    fixed_nodes = np.unique(facets[fixed_regions])
    loaded = np.flatnonzero(np.abs(f_nodes).sum(axis=1) > 0)
    theirs = []
    for _ in range(3):
        t0 = time.perf_counter()
        mesh = fem.Mesh(points, tets, cell_type="tetra")
        field = fem.FieldContainer([fem.Field(fem.RegionTetra(mesh), dim=3)])
        mask = np.zeros(len(points), bool)
        mask[fixed_nodes] = True
        solid = fem.SolidBody(fem.NeoHooke(mu=mat.mu0, bulk=mat.bulk), field)
        pl = fem.PointLoad(field, loaded, f_nodes[loaded])
        ramp = fem.math.linsteps([0, 1], num=max(1, r.load_steps))[1:, None, None] * f_nodes[loaded]
        step = fem.Step(items=[solid, pl], ramp={pl: ramp}, boundaries={"fixed": fem.dof.Boundary(field[0], mask=mask)})
        fem.Job(steps=[step]).evaluate(tol=1e-9, verbose=0)
        theirs.append(time.perf_counter() - t0)
    u_f = field[0].values
    t_f = float(np.median(theirs))
    print(f"\n== FElupe 11.3 vs ours, P1 mesh {len(points)} nodes, neo-Hooke, 2 N, fixed ivc/ligament/visceral,"
          f" tol 1e-9; FElupe {t_f:.3f} s (Newton, {r.load_steps} load steps)")
    for label in ("modified", "full"):
        rr = runs[label]
        diff = np.abs(rr.u_nodes - u_f).max() / np.abs(u_f).max()
        print(f"   ours, {label} Newton: {ours[label]:.3f} s (iterations {rr.newton_iterations}, factorisations"
              f" {rr.factorizations}) -> FElupe/ours = {t_f / ours[label]:.2f}; max |u| difference {diff:.1e} (relative)")


def bench_mesh_convergence(target_vertices, refine_edge_mm):
    """Displacement near the tool and support reactions at 3 N: a mesh vs one with twice the node density.

    Near-tool displacement = Gaussian(width)-weighted surface mean of the FE field,
    integrated exactly by the consistent nodal weights of a unit Gaussian traction.
    """
    runs = []
    for scale in (1, 2):
        edge = None if refine_edge_mm is None else refine_edge_mm / scale ** (1 / 3)
        points, tets, facets, region, visible, src, x0 = liver_mesh(scale * target_vertices, edge)
        x0 = x0 if not runs else runs[0]["x0"]
        mat = make_material("yeoh", YEOH, nu=0.49)
        model = LiverModel(points, tets, facets, region, mat, BoundaryParams.from_totals(points, facets, region))
        r = model.solve(ToolLoad(x0, [0.0, 0.0, -3.0], 5.0))
        ubar = {w: np.stack([model.nodal_loads(ToolLoad(x0, e, w)) for e in np.eye(3)]) @ r.state for w in (5.0, 10.0)}
        runs.append({"x0": x0, "n": model.disc.n_nodes, "ok": r.converged, "ubar": ubar, "src": src,
                     "reac": {k: np.asarray(r.reactions[k]) for k in ("ivc", "ligament", "visceral", "rib")}})
    c, f = runs
    print(f"\n== mesh convergence at 3 N (P2 mean dilatation, tool width 5 mm): {c['n']} vs {f['n']} P2 nodes"
          f" (converged {c['ok']}, {f['ok']}); {c['src']}")
    for w in (5.0, 10.0):
        rel = np.linalg.norm(c["ubar"][w] - f["ubar"][w]) / np.linalg.norm(f["ubar"][w])
        print(f"   surface displacement within a {w:g} mm Gaussian of the tool: |u| {np.linalg.norm(c['ubar'][w]):.3f}"
              f" vs {np.linalg.norm(f['ubar'][w]):.3f} mm, change {100 * rel:.1f} %")
    print("   support reactions (N) and change: " + ", ".join(
        f"{k} {np.linalg.norm(f['reac'][k]):.3f} "
        f"({100 * np.linalg.norm(c['reac'][k] - f['reac'][k]) / np.linalg.norm(f['reac'][k]):.1f} %)" for k in c["reac"]))


def main():
    print(f"liverforce.fem benchmark (threads={ARGS.threads}, python {sys.version.split()[0]})")
    n_cases = min(ARGS.cases, 12) if ARGS.quick else ARGS.cases
    default_vertices = 800  # with the default refinement ~5.5k P2 nodes
    pts, tets, facets, region, visible, x0 = bench_resolution("default resolution", default_vertices, n_cases, ARGS.repeats)
    bench_felupe(pts, tets, facets, region, x0)
    for scenario in ("II", "III"):
        bench_shard("default resolution", default_vertices, scenario)
    if not ARGS.quick:
        big = bench_resolution("~20k P2 nodes", 3000, max(10, n_cases // 2), max(1, ARGS.repeats - 2))
        for scenario in ("II", "III"):
            bench_shard("~20k P2 nodes", 3000, scenario)
        bench_felupe(big[0], big[1], big[2], big[3], big[5])
    for edge in (6.0, None):  # the default (refined at the exertion points and the IVC) and no refinement
        bench_mesh_convergence(default_vertices, edge)


if __name__ == "__main__":
    main()
