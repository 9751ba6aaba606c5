"""Support sensitivity (issue #18): how the supports move the force-displacement map.

On one procedural liver (``procedural_liver(0)``) meshed as the mesh stage does
with the default config (``config/mesh``), the default material and solver
(``config/material``, ``config/simulate``), a tool force of ``--force`` N
(default 2) pressing along the inward surface normal at the first candidate
exertion point, each support model is solved from rest and the table gives:

* ``u_n``: the displacement under the tool along the push (mm), the tool
  traction's own weighted mean (as the stiffness probe pairs them);
* ``|u|max``: the largest displacement anywhere (mm);
* the share of the tool force each support carries (%, the reaction's
  component against the tool force over ``|F|``; they sum to 100).

Variants change one thing from the configured baseline (foundation totals
56.3 / 42.6 N/mm, k_t/k_n 1, bilateral rib penalty 0.1 N/mm³, no gravity):
foundation stiffness x0.25 / x4, k_t/k_n 0.1, rib unilateral / off, gravity
on (1060 kg/m³ along -z, inferior in RAS, and along -y, posterior = supine).
With gravity the columns are the tool's own increment: the case minus the
gravity-only state of the same supports (``sag`` gives that state's largest
displacement).

Usage: ``PYTHONPATH=. .venv/bin/python benchmarks/support_sensitivity.py [--force 2] [--threads 1]``
"""

from __future__ import annotations

import argparse
import time

from liverforce.pipeline.job import thread_env

_ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
_ap.add_argument("--force", type=float, default=2.0, help="tool force magnitude, N (along the inward normal)")
_ap.add_argument("--threads", type=int, default=1, help="BLAS/numba threads (default 1)")
ARGS = _ap.parse_args()
thread_env(ARGS.threads)

import numpy as np  # noqa: E402

from liverforce.config import compose  # noqa: E402
from liverforce.fem import LiverModel, ToolLoad, make_material  # noqa: E402
from liverforce.fem.boundary import vertex_normals  # noqa: E402
from liverforce.geometry.procedural import procedural_liver  # noqa: E402
from liverforce.mesh.build import build_liver_mesh  # noqa: E402
from liverforce.pipeline.simulate import boundary_params, solver_options  # noqa: E402
from liverforce.pipeline.sweep import closest_surface_points  # noqa: E402

SUPPORTS = ("ivc", "ligament", "visceral", "rib")
GRAVITY_Z = {"enabled": True, "density_kg_per_m3": 1060.0, "direction": [0.0, 0.0, -1.0]}
GRAVITY_Y = {"enabled": True, "density_kg_per_m3": 1060.0, "direction": [0.0, -1.0, 0.0]}


def variants(base: dict) -> list[tuple[str, dict]]:
    def v(**kw):
        return {**base, **kw}

    lig, vis = base["ligament_total_n_per_mm"], base["visceral_total_n_per_mm"]
    return [
        ("baseline (config)", v()),
        ("foundation x0.25", v(ligament_total_n_per_mm=0.25 * lig, visceral_total_n_per_mm=0.25 * vis)),
        ("foundation x4", v(ligament_total_n_per_mm=4 * lig, visceral_total_n_per_mm=4 * vis)),
        ("kt/kn 0.1", v(tangential_ratio=0.1)),
        ("rib unilateral", v(rib_contact="unilateral")),
        ("rib off", v(rib_normal_n_per_mm3=0.0)),
        ("gravity -z", v(gravity=GRAVITY_Z)),
        ("gravity -z, rib unilat.", v(gravity=GRAVITY_Z, rib_contact="unilateral")),
        ("gravity -y (supine)", v(gravity=GRAVITY_Y)),
        ("gravity -y, rib unilat.", v(gravity=GRAVITY_Y, rib_contact="unilateral")),
    ]


def main():
    cfg = compose([])
    mc = cfg["mesh"]
    ex = cfg["sweep"]["exertion"]
    t0 = time.perf_counter()
    mesh = build_liver_mesh(procedural_liver(0), target_nodes=mc["target_nodes"], mesher=mc["mesher"],
                            refine_radius_mm=mc["refine_radius_mm"], refine_edge_mm=mc["refine_edge_mm"],
                            refine_growth=mc["refine_growth"], refine_ivc_edge_mm=mc["refine_ivc_edge_mm"],
                            exertion_sampling={"n_points": ex["n_points"], "min_spacing_mm": ex["min_spacing_mm"],
                                               "seed": 0})
    t_mesh = time.perf_counter() - t0
    x0 = closest_surface_points(mesh.points, mesh.facets[mesh.facet_visible], mesh.meta["exertion_candidates_mm"][0])[0]
    vis = np.unique(mesh.facets[mesh.facet_visible])
    vn = vertex_normals(mesh.points, mesh.facets)
    n0 = vn[vis[np.argmin(np.linalg.norm(mesh.points[vis] - x0, axis=1))]]
    force = -ARGS.force * n0  # press along the inward normal
    mat_cfg = cfg["material"]
    mat = make_material(mat_cfg["model"], mat_cfg["params_mpa"], nu=mat_cfg["nu"])
    opts = solver_options(cfg["simulate"])
    radius = cfg["simulate"]["tool_radius_mm"]
    load = ToolLoad(x0, force, radius)
    print(f"procedural liver 0: {len(mesh.points)} vertices, {len(mesh.tets)} tets (meshed in {t_mesh:.1f} s); "
          f"material {mat_cfg['model']} nu {mat_cfg['nu']}; formulation {opts.formulation}")
    print(f"tool: {ARGS.force:g} N along the inward normal at {np.round(x0, 1)} mm (n = {np.round(n0, 3)}), "
          f"Gaussian width {radius} mm")
    head = (f"{'variant':<26}{'u_n mm':>8}{'|u|max':>8}{'sag mm':>8}" + "".join(f"{k + ' %':>11}" for k in SUPPORTS)
            + f"{'rib sep.':>9}{'its':>5}{'s':>6}")
    print(head)
    print("-" * len(head))
    F_hat = force / np.linalg.norm(force)
    for name, bcfg in variants(cfg["boundary"]):
        bp = boundary_params(mesh, bcfg)
        model = LiverModel.from_mesh(mesh, mat, bp, opts)
        w = model.nodal_loads(ToolLoad(x0, F_hat, radius))  # traction weights (sum to F_hat)
        t1 = time.perf_counter()
        res = model.solve(load)
        if not res.converged:
            print(f"{name:<26} failed: {res.reason}")
            continue
        its = res.newton_iterations
        u, reac, sag = res.state, res.reactions, float("nan")
        if bp.body_force_n_per_mm3 != (0.0, 0.0, 0.0):  # the tool's own increment over the sagged state
            g = model.solve(ToolLoad(x0, np.zeros(3), radius))
            assert g.converged, g.reason
            its += g.newton_iterations
            u = res.state - g.state
            reac = {k: res.reactions[k] - g.reactions[k] for k in SUPPORTS}
            sag = float(np.linalg.norm(g.u_nodes, axis=1).max())
        dt = time.perf_counter() - t1
        u_n = float(w @ u)
        umax = float(np.linalg.norm(u.reshape(-1, 3), axis=1).max())
        shares = [-100.0 * float(reac[k] @ F_hat) / ARGS.force for k in SUPPORTS]
        sep = "-"
        if model.rib_contact is not None:
            sep = f"{100.0 * (1.0 - model.rib_contact.active(res.state).mean()):.0f} %"
        print(f"{name:<26}{u_n:8.3f}{umax:8.3f}{sag:8.2f}" + "".join(f"{s:11.1f}" for s in shares)
              + f"{sep:>9}{its:5d}{dt:6.1f}")
    print("u_n, |u|max and shares: the tool's increment (with gravity: minus the gravity-only state); "
          "rib sep.: share of rib quadrature points out of contact at the loaded state (unilateral only).")


if __name__ == "__main__":
    main()
