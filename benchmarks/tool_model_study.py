"""What the traction simplification costs: a rigid 5 mm instrument tip against the Gaussian traction.

On a procedural liver (seed 0, mesh refined around two sampled exertion points),
a rigid sphere of radius 2.5 mm (a 5 mm instrument) is pushed along the inward
surface normal in frictionless contact (liverforce.fem.indenter, penalty +
augmented Lagrangian) to the depths that give about 1, 3 and 5 N. The same
total force vector is then applied as the production tool load: the Gaussian
traction of width ``tool_radius_mm`` (config/simulate/default.yaml) around the
same point. Per point and force it prints

* the displacement magnitude at the exertion point (surface vertex nearest to it),
* the largest displacement over the mesh,
* the displacement difference over the ROI surface nodes (geodesic patch of
  ``roi_fraction`` of the surface, config/dataset/default.yaml) and over the
  ROI nodes within 15 mm of the tool: RMS and max (mm),
* the peak contact pressure (nominal, per reference area) against the traction's peak,

then the medians over points and forces.

Run: ``.venv/bin/python -m benchmarks.tool_model_study [--edge 2.0] [--points 2] [--kn 1.0]``
(an experiment, not a timed test). Slow: the semismooth Newton of the contact
needs 20-40 iterations per 1.5 mm depth increment on the 29k-dof P2 liver
(~2 s per iteration on a loaded 2-core machine); the first run (--kn 1, Nov
2026) reached only point 0 at 1 N within 25 min:

    pt  F(N)  depth    |u|@x0 s/t    max|u| s/t   ROI rms/max  near rms/max   p_peak s/t (kPa)   area    pen
     0  0.98   6.50   6.32/  3.99   6.32/  4.29   0.42/  2.34   0.55/  2.34    130.4/    6.26   22.5  0.130
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]


def _cfg(path):
    return yaml.safe_load((ROOT / path).read_text())


def traction_peak(model, load) -> float:
    """Peak of the Gaussian traction (N/mm²): |F| / integral of g over the loaded facets
    (the facets near x0 facing the way the surface does there, as tool_nodal_forces selects them)."""
    from liverforce.fem.boundary import _facet_quadrature
    from liverforce.fem.indenter import surface_normal

    x0, r = load.point_mm, load.radius_mm
    cent = model.points[model.facets].mean(axis=1)
    near = np.linalg.norm(cent - x0, axis=1) <= 4.0 * r + 10.0
    _, Xq, W, _, nrm, _ = _facet_quadrature(model.disc, model.points, model.facets[near])
    n0 = surface_normal(model.points, model.facets, x0, r)
    keep = nrm @ n0 > 0.0
    g = np.exp(-0.5 * np.sum((Xq[keep] - x0) ** 2, axis=-1) / r**2) * W[keep]
    return float(np.linalg.norm(load.force_N) / g.sum())


def force_to_depth(ind, targets, tol=0.07, max_depth=40.0, max_increment=1.5, augmented=0, verbose=True):
    """One continuation path that lands near each target |F| (N): the next depth is predicted from a
    local power law F ~ d^m fitted to the last two states; an overshoot beyond ``tol`` is redone
    from the previous state (secant). Returns the state nearest each target (within ``tol`` unless
    the path failed) as it is reached: yields (target, result). The traction comparison then uses
    that state's exact force vector."""
    states = []  # (depth, |F|, result)

    def push(d, base):
        ind.contact.multipliers[:] = 0.0
        if base is not None:
            ind.contact.set_centre(base.centre)
        path = ind.push([d], u0=base.u if base is not None else None, augmented=augmented,
                        max_increment=max_increment)
        if not path.converged:
            raise RuntimeError(f"indentation failed at {d:.2f} mm: {path.reason}")
        r = path.results[0]
        F = float(np.linalg.norm(r.force_on_sphere))
        if verbose:
            print(f"     depth {d:6.2f} mm: |F| {F:6.3f} N, {r.active_points} active, pen {r.max_penetration_mm:.3f} mm,"
                  f" {path.load_steps} steps / {path.newton_iterations} its, {path.wall_time_s:.1f} s", flush=True)
        return r, F

    for target in sorted(targets):
        lo = states[-1] if states else (0.0, 0.0, None)
        hi = None
        for _ in range(6):
            d0, F0, _ = lo
            if hi is not None:  # secant inside the bracket
                d = d0 + (target - F0) * (hi[0] - d0) / (hi[1] - F0)
            elif len(states) >= 2 and states[-2][1] > 0:
                (d1, F1, _), (d2, F2, _) = states[-2], states[-1]
                m = float(np.clip(np.log(F2 / F1) / np.log(d2 / d1), 1.0, 3.0))
                d = d2 * (target / F2) ** (1.0 / m)
            elif states:
                d = states[-1][0] * (target / states[-1][1]) ** (1.0 / 1.5)
            else:
                d = 2.0
            d = float(min(d, d0 + 3.0 * max_increment, max_depth))
            r, F = push(d, lo[2])
            if abs(F - target) <= tol * target:
                states.append((d, F, r))
                break
            if F < target:
                lo = (d, F, r)
                states.append(lo)
            else:
                hi = (d, F, r)
        else:
            raise RuntimeError(f"no depth within {tol:.0%} of {target} N")
        yield target, states[-1][2]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--edge", type=float, default=2.0, help="mesh edge (mm) within --refine mm of the points")
    ap.add_argument("--refine", type=float, default=10.0)
    ap.add_argument("--points", type=int, default=2)
    ap.add_argument("--tip-radius", type=float, default=2.5)
    ap.add_argument("--kn", type=float, default=5.0, help="penalty (N/mm³)")
    ap.add_argument("--forces", default="1,3,5")
    ap.add_argument("--tol", type=float, default=1e-6, help="relative residual tolerance (config: 1e-7)")
    args = ap.parse_args(argv)

    from liverforce.dataset.roi import extract_roi, surface_graph
    from liverforce.fem import BoundaryParams, LiverModel, SolverOptions, ToolLoad, make_material
    from liverforce.fem.indenter import LiverIndenter
    from liverforce.geometry import procedural
    from liverforce.mesh import build

    sim = _cfg("config/simulate/default.yaml")
    matc = _cfg("config/material/yeoh.yaml")
    bnd = _cfg("config/boundary/study.yaml")
    meshc = _cfg("config/mesh/default.yaml")
    roi_fraction = float(_cfg("config/dataset/default.yaml")["roi_fraction"])
    targets = [float(x) for x in args.forces.split(",")]

    t0 = time.perf_counter()
    mesh = build.build_liver_mesh(
        procedural.procedural_liver(0), target_nodes=meshc["target_nodes"], refine_radius_mm=args.refine,
        refine_edge_mm=args.edge, refine_growth=meshc["refine_growth"], refine_ivc_edge_mm=meshc["refine_ivc_edge_mm"],
        exertion_sampling={"n_points": args.points, "min_spacing_mm": 40.0, "seed": 3})
    points = np.asarray(mesh.meta["exertion_candidates_mm"], float)
    mat = make_material(matc["model"], matc["params_mpa"], nu=matc["nu"])
    bp = BoundaryParams.from_totals(mesh.points, mesh.facets, mesh.facet_region, bnd["ligament_total_n_per_mm"],
                                    bnd["visceral_total_n_per_mm"], bnd["tangential_ratio"],
                                    bnd["rib_normal_n_per_mm3"], bnd["rib_contact"])
    opt = SolverOptions(formulation=sim["formulation"], tol=args.tol, max_iter=sim["max_iter"],
                        initial_step=sim["initial_step"], min_step=sim["min_step"], max_steps=sim["max_steps"],
                        time_limit_s=1500.0, max_total_iter=3000, modified_newton=False)
    model = LiverModel.from_mesh(mesh, mat, bp, opt)
    print(f"liver: {len(mesh.points)} vertices, {len(mesh.tets)} tets, {model.n_dofs} dofs (P2), "
          f"edge {args.edge} mm within {args.refine} mm of {len(points)} points; meshed+built in "
          f"{time.perf_counter() - t0:.1f} s")
    print(f"tip: rigid sphere R = {args.tip_radius} mm, k = {args.kn} N/mm³ (penalty); "
          f"traction: Gaussian r = {sim['tool_radius_mm']} mm")
    surf = surface_graph(mesh.points, mesh.facets)

    rows = []
    hdr = (f"{'pt':>2} {'F(N)':>5} {'depth':>6} {'|u|@x0 s/t':>13} {'max|u| s/t':>13} "
           f"{'ROI rms/max':>13} {'near rms/max':>13} {'p_peak s/t (kPa)':>18} {'area':>6} {'pen':>6}")
    print(hdr)
    for ip, x0 in enumerate(points):
        t1 = time.perf_counter()
        ind = LiverIndenter(model, x0, radius_mm=args.tip_radius, kn=args.kn)
        vid = int(np.argmin(np.linalg.norm(mesh.points - x0, axis=1)))
        roi_local, _ = extract_roi(surf, x0, roi_fraction)
        roi = surf.node_ids[roi_local]
        near = roi[np.linalg.norm(mesh.points[roi] - x0, axis=1) <= 15.0]
        for target, r in force_to_depth(ind, targets):
            F_liver = -r.force_on_sphere
            load = ToolLoad(x0, F_liver, sim["tool_radius_mm"])
            tr = model.solve(load)
            if not tr.converged:
                print(f"  traction solve failed: {tr.reason}")
                continue
            us, ut = r.u_nodes, tr.u_nodes
            du = np.linalg.norm(us - ut, axis=1)
            row = dict(point=ip, force=float(np.linalg.norm(F_liver)), depth=r.depth,
                       u_x0_s=float(np.linalg.norm(us[vid])), u_x0_t=float(np.linalg.norm(ut[vid])),
                       umax_s=float(np.linalg.norm(us, axis=1).max()), umax_t=float(np.linalg.norm(ut, axis=1).max()),
                       roi_rms=float(np.sqrt(np.mean(du[roi] ** 2))), roi_max=float(du[roi].max()),
                       near_rms=float(np.sqrt(np.mean(du[near] ** 2))), near_max=float(du[near].max()),
                       p_s=r.peak_pressure_mpa, p_t=traction_peak(model, load), area=r.contact_area_mm2,
                       pen=r.max_penetration_mm, rim=r.active_on_rim,
                       imbalance=float(np.linalg.norm(r.reactions["imbalance"])))
            rows.append(row)
            print(f"{ip:>2} {row['force']:5.2f} {row['depth']:6.2f} {row['u_x0_s']:6.2f}/{row['u_x0_t']:6.2f} "
                  f"{row['umax_s']:6.2f}/{row['umax_t']:6.2f} {row['roi_rms']:6.2f}/{row['roi_max']:6.2f} "
                  f"{row['near_rms']:6.2f}/{row['near_max']:6.2f} {1e3 * row['p_s']:8.1f}/{1e3 * row['p_t']:8.2f} "
                  f"{row['area']:6.1f} {row['pen']:6.3f}{'  RIM' if row['rim'] else ''}")
        print(f"   point {ip} done in {time.perf_counter() - t1:.0f} s; sphere imbalance "
              f"max {max(r_['imbalance'] for r_ in rows if r_['point'] == ip):.2e} N")
    if not rows:
        return
    print("\nmedians over points and forces:")
    for target in targets:
        sel = [r for r in rows if abs(r["force"] - target) < 0.05 * target]
        if not sel:
            continue
        med = {k: float(np.median([r[k] for r in sel])) for k in sel[0] if k not in ("point", "rim")}
        print(f"  F ~ {target:g} N: |u|@x0 sphere {med['u_x0_s']:.2f} vs traction {med['u_x0_t']:.2f} mm "
              f"({100 * (med['u_x0_s'] / med['u_x0_t'] - 1):+.0f} %), max|u| {med['umax_s']:.2f} vs "
              f"{med['umax_t']:.2f} mm, ROI diff rms {med['roi_rms']:.2f} / max {med['roi_max']:.2f} mm, "
              f"near-tool rms {med['near_rms']:.2f} / max {med['near_max']:.2f} mm, peak pressure "
              f"{1e3 * med['p_s']:.0f} vs {1e3 * med['p_t']:.1f} kPa ({med['p_s'] / med['p_t']:.0f}x)")


if __name__ == "__main__":
    main()
