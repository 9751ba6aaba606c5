"""Time per case: the force-controlled sphere tool against the Gaussian traction, on the default liver.

The default procedural liver (seed 0, config/mesh/default.yaml: ~800 vertices refined to 6 mm around
the exertion candidates, P2 mean dilatation, ~14.5k dofs), the default material and supports, the
sweep's cases (scenario I design: Sobol forces 0-5 N within 30 degrees of the inward normal) at the
first exertion point, run through the product loop
(``liverforce.pipeline.simulate.simulate_cases``) twice: ``simulate.tool_model=traction`` and
``=sphere`` (``tool_tip_radius_mm`` 2.5 mm, automatic penalty). Prints per tool model the median and
mean wall time per case, Newton iterations, converged count and the failure reasons, with one thread
(``--threads``). The time limit per case is raised (``--time-limit``) and the iteration budget lifted
(``simulate.max_total_iter``) so every case is measured to its end.

Run: ``.venv/bin/python benchmarks/bench_sphere_case.py [--cases 6] [--time-limit 3600]``

First run (commit after 9c31e2c, 1 thread, loaded 2-core machine, 5 cases 0.57-3.93 N, 14.5k dofs):
traction median 1.07 s per case (10-23 Newton iterations, 5/5 converged); sphere 0/5 converged:
4 hit the 120 s limit (217-421 Newton iterations; the semismooth contact Newton needs 10-15
iterations per centre update and often fails a full update, then steps it in 0.5 mm increments),
1 refused as "cannot hold" (3.46 N at 29.9 deg, slide > 2.5 mm). A 2.5 mm sphere on this mesh's
6 mm facets is under-resolved (7 quadrature points per facet; a single 2.5 mm push from first
touch tunnels to a spurious state with an outward force, hence 0.5 mm first increments), and the
frictionless sphere's tangential stiffness there is tiny or negative (Jacobian eigenvalues
-0.014 / 0.056 / 0.174 N/mm at 4 mm depth): even the few-degree difference between the sweep's
normal and the sphere's natural force direction needs a ~2 mm slide at 0.3 N.
"""

from __future__ import annotations

import argparse
import time
from collections import Counter

import numpy as np

from liverforce.pipeline.job import thread_env


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=6)
    ap.add_argument("--time-limit", type=float, default=3600.0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--max-slide", type=float, default=None, help="simulate.tool_max_slide_mm (default: config)")
    ap.add_argument("--controls", default="magnitude", help="sphere controls to run: magnitude,vector (simulate.tool_control)")
    args = ap.parse_args(argv)
    thread_env(args.threads)

    from liverforce.config import compose
    from liverforce.geometry import procedural
    from liverforce.mesh import build
    from liverforce.pipeline.simulate import simulate_cases
    from liverforce.pipeline.sweep import exertion_set, material_checks
    from liverforce.sweep.design import build_cases

    cfg = compose([])
    mc = cfg["mesh"]
    t0 = time.perf_counter()
    mesh = build.build_liver_mesh(
        procedural.procedural_liver(0), target_nodes=mc["target_nodes"], refine_radius_mm=mc["refine_radius_mm"],
        refine_edge_mm=mc["refine_edge_mm"], refine_growth=mc["refine_growth"],
        refine_ivc_edge_mm=mc["refine_ivc_edge_mm"],
        exertion_sampling={"n_points": cfg["sweep"]["exertion"]["n_points"],
                           "min_spacing_mm": cfg["sweep"]["exertion"]["min_spacing_mm"], "seed": 0})
    print(f"liver: {len(mesh.points)} vertices, {len(mesh.tets)} tets, meshed in {time.perf_counter() - t0:.1f} s")
    sim0 = dict(cfg["simulate"])
    ex = exertion_set(mesh, cfg["sweep"]["exertion"]["n_points"], cfg["sweep"]["exertion"]["min_spacing_mm"], 0,
                      sim0["tool_radius_mm"], candidates=mesh.meta["exertion_candidates_mm"])
    material = dict(cfg["material"], on_unstable="clip")
    stable, bulk = material_checks(material["stability_stretch"], material["nu"])
    spec = {"n_cases": 8 * args.cases, "exertion": "varies", "material": "fixed"}
    cases = build_cases("II", spec, ["g"], {"g": ex}, material, dict(cfg["sweep"]["force"]), "sobol", 0,
                        args.cases, stable, bulk).rows
    cases = [r for r in cases if r["exertion_id"] == cases[0]["exertion_id"]][: args.cases]
    print(f"{len(cases)} cases at exertion point {cases[0]['exertion_id']}, |F| "
          + ", ".join(f"{c['force_magnitude_n']:.2f}" for c in cases) + " N")
    runs = [("traction", "traction", None)] + [(f"sphere ({c})", "sphere", c) for c in args.controls.split(",")]
    for model, tool, control in runs:
        sim = dict(sim0, tool_model=tool, time_limit_s=args.time_limit, max_total_iter=100_000)
        if control:
            sim["tool_control"] = control
        if args.max_slide is not None:
            sim["tool_max_slide_mm"] = args.max_slide
        rows = simulate_cases(cases, {"g": mesh}, sim, cfg["boundary"], cfg["dataset"])
        t = np.array([r["wall_time_s"] for r in rows])
        its = np.array([r["newton_iterations"] for r in rows])
        ok = np.array([r["converged"] for r in rows])
        print(f"\n{model}: median {np.median(t):.2f} s, mean {t.mean():.2f} s per case (converged: median "
              f"{np.median(t[ok]) if ok.any() else float('nan'):.2f} s); Newton iterations median {np.median(its):.0f}; "
              f"converged {ok.sum()}/{len(rows)}")
        for r, c in zip(rows, cases):
            f, f0 = np.asarray(r["force_n"], float), np.asarray(c["force_n"], float)
            ang = np.degrees(np.arccos(np.clip(f @ f0 / max(np.linalg.norm(f) * np.linalg.norm(f0), 1e-300), -1, 1)))
            print(f"   {r['case_id']}: |F| {np.linalg.norm(f):.3f} N (case {np.linalg.norm(f0):.3f} N, "
                  f"{ang:.1f} deg apart), {r['wall_time_s']:.1f} s, "
                  f"{r['newton_iterations']} it, {'ok' if r['converged'] else 'FAILED: ' + r['reason'][:150]}")
        for why, k in Counter(r["reason"].split(":")[1][:60] if ":" in r["reason"] else r["reason"]
                              for r in rows if not r["converged"]).items():
            print(f"   failed x{k}: {why}")


if __name__ == "__main__":
    main()
