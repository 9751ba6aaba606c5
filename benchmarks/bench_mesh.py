"""Benchmark of the geometry and mesh stages (liverforce.geometry, liverforce.mesh).

First, the PIPELINE meshing as the mesh rule runs it
(:func:`liverforce.pipeline.mesh.make_mesh` with the composed config's ``mesh``,
``seed`` and ``sweep.exertion``, on the geometry stage's PLY of each liver):
seconds per liver (the ``meshing_time_s`` the stage records, i.e. the
``build_liver_mesh`` call, and the whole ``make_mesh`` call with region check,
features, VTU and picture, in wall time and in this process's CPU time, which
other jobs on a shared machine disturb less), remesh attempts, node count against the target and
the minimum radius ratio, with the median over the livers. Default config on
proc-0000..0003 (``--livers``) and the smoke config (``experiment=smoke``) on
its own livers. Issue #14: <= 5 s per liver at the default resolution.

Then, per geometry, the median over ``--repeats`` runs of:

1. surface generation / import time;
2. ``tetrahedralise`` wall time at the default resolution (~5k nodes) and at
   the study's ~20k nodes, with the node/tet counts obtained and the quality
   (min and mean normalised radius ratio, min dihedral angle, elements below
   the radius-ratio bound 0.2);
3. region tagging and feature computation time at ~5k nodes.

Geometries: procedural livers (seeds 0, 1, 2), the 50 mm cube phantom and,
when ../shared/data/livers exists, the SOFA liver-smooth.obj (units=40).

Usage: ``python benchmarks/bench_mesh.py [--repeats N] [--quick] [--mesher gmsh|tetgen]
[--only pipeline|tetra] [--livers N]``
(``--quick``: pipeline on two livers, then one procedural liver and the cube, 5k nodes only, 1 repeat;
``--only pipeline``: the pipeline meshing figures alone).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

from liverforce.pipeline.job import thread_env

thread_env(1, override=False)

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from liverforce.geometry import cube_phantom, load_surface, procedural_liver  # noqa: E402
from liverforce.mesh.boundary import boundary_facets  # noqa: E402
from liverforce.mesh.build import build_liver_mesh  # noqa: E402
from liverforce.mesh.features import compute_features  # noqa: E402
from liverforce.mesh.quality import mesh_quality  # noqa: E402
from liverforce.mesh.regions import RegionParams, tag_regions  # noqa: E402
from liverforce.mesh.tetra import tetrahedralise_with_info  # noqa: E402

SOFA = ROOT.parent / "shared" / "data" / "livers" / "liver-smooth.obj"


def median_time(fn, repeats: int):
    """(median seconds, last result) of ``repeats`` calls."""
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def pipeline_meshing(experiment: str, livers: int | None) -> list[dict]:
    """Mesh the experiment's first training livers as the mesh rule does; one row per liver.

    The surfaces are made by the geometry stage (PLY + JSON in a temporary
    folder; not timed). Meshing is deterministic, so each liver is meshed once
    and the figure is the median over livers.
    """
    from liverforce.config import compose
    from liverforce.layout import Layout
    from liverforce.pipeline.geometry import make_geometry
    from liverforce.pipeline.mesh import make_mesh
    from liverforce.pipeline.plan import Plan

    # run=False: meshing runs no pipeline, so a count the pipeline refuses (1 liver with scenario IV) is taken
    cfg = compose([f"experiment={experiment}"], run=False)
    plan = Plan(cfg)
    gids = [g for g in plan.train_geometries if g.startswith("proc-")]
    if livers is not None:
        plan = Plan(compose([f"experiment={experiment}", f"geometry.procedural.count={livers}"], run=False))
        gids = [g for g in plan.train_geometries if g.startswith("proc-")]
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_mesh_") as tmp:
        for gid in gids:
            paths = Layout(tmp)
            surface = paths.surface(gid)
            make_geometry(plan.geometry_spec(gid), surface, paths.surface_meta(gid))
            t0, c0 = time.perf_counter(), time.process_time()
            feats = make_mesh(surface, cfg["mesh"], plan.seed("mesh", gid), paths.mesh(gid), paths.features(gid),
                              paths.regions_picture(gid), exertion=cfg["sweep"]["exertion"])
            total, cpu = time.perf_counter() - t0, time.process_time() - c0
            meshing = feats["provenance"]["meshing"]
            rows.append({"experiment": experiment, "gid": gid, "mesh_s": feats["meshing_time_s"], "stage_s": total,
                         "cpu_s": cpu,
                         "attempts": len(meshing["attempts"]), "nodes": feats["n_nodes"],
                         "target": cfg["mesh"]["target_nodes"], "route": meshing["route"],
                         "h": meshing["edge_length_mm"], "rr_min": feats["quality"]["radius_ratio_min"],
                         "tries": " ".join(f"{a['edge_length_mm']:.1f}:{a['n_nodes']}" for a in meshing["attempts"])})
            r = rows[-1]
            print(f"{experiment:8s} {gid:10s} {r['mesh_s']:7.2f} {r['stage_s']:8.2f} {r['cpu_s']:6.2f} "
                  f"{r['attempts']:5d} {r['nodes']:6d} {r['target']:6d} {r['route']:>9s} {r['rr_min']:6.3f}  "
                  f"{r['tries']}", flush=True)
    return rows


def run_pipeline(quick: bool, livers: int) -> None:
    print("\n== pipeline meshing (pipeline.mesh.make_mesh as the mesh rule runs it; one run per liver) ==")
    print(f"{'config':8s} {'liver':10s} {'mesh s':>7s} {'stage s':>8s} {'cpu s':>6s} {'tries':>5s} {'nodes':>6s} "
          f"{'target':>6s} {'route':>9s} {'rr min':>6s}  attempts (h mm:nodes)")
    summary = []
    for experiment, n in (("default", 2 if quick else livers), ("smoke", 2 if quick else None)):
        rows = pipeline_meshing(experiment, n)
        med = lambda key: statistics.median(r[key] for r in rows)  # noqa: E731
        summary.append(f"{experiment:8s} {len(rows)} livers: median {med('mesh_s'):.2f} s per liver "
                       f"(stage {med('stage_s'):.2f} s, stage CPU {med('cpu_s'):.2f} s), "
                       f"attempts {[r['attempts'] for r in rows]}, "
                       f"nodes {[r['nodes'] for r in rows]} (target {rows[0]['target']}), "
                       f"min rr {min(r['rr_min'] for r in rows):.3f}")
    print("\n".join(summary))


def geometries(quick: bool):
    items = [("procedural seed 0", lambda: procedural_liver(0))]
    if not quick:
        items += [("procedural seed 1", lambda: procedural_liver(1)), ("procedural seed 2", lambda: procedural_liver(2))]
    items.append(("cube 50 mm", lambda: cube_phantom(50.0)))
    if not quick:
        if SOFA.exists():
            items.append(("SOFA liver-smooth.obj x40", lambda: load_surface(SOFA, units=40)[0]))
        else:
            print(f"(skipping the SOFA liver: {SOFA} not found)")
    return items


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3, help="timed repeats per measurement (median reported)")
    ap.add_argument("--quick", action="store_true", help="one liver + cube, 5k nodes, 1 repeat")
    ap.add_argument("--mesher", default="gmsh", choices=("gmsh", "tetgen"))
    ap.add_argument("--only", choices=("pipeline", "tetra"), help="run one part only")
    ap.add_argument("--livers", type=int, default=4, help="default-config livers for the pipeline part (proc-0000..)")
    args = ap.parse_args()
    if args.only != "tetra":
        run_pipeline(args.quick, args.livers)
        if args.only == "pipeline":
            return 0
    repeats = 1 if args.quick else max(1, args.repeats)
    targets = (5000,) if args.quick else (5000, 20000)
    print(f"bench_mesh: mesher={args.mesher}, repeats={repeats} (medians), targets={targets}, 1 thread")
    header = (f"{'geometry':28s} {'target':>6s} {'nodes':>6s} {'tets':>7s} {'mesh s':>7s} "
              f"{'rr min':>6s} {'rr mean':>7s} {'dih min':>7s} {'<0.2':>5s} {'h mm':>5s} {'tries':>5s}")
    rows = []
    other = []
    for name, make in geometries(args.quick):
        t_geo, surface = median_time(make, repeats)
        other.append(f"{name:28s} surface {t_geo:6.2f} s  ({len(surface.faces)} triangles, "
                      f"{surface.volume_mm3 / 1e6:.3f} L)")
        for target in targets:
            t_mesh, (points, tets, info) = median_time(
                lambda s=surface, n=target: tetrahedralise_with_info(s, target_nodes=n, mesher=args.mesher), repeats
            )
            q = mesh_quality(points, tets)
            rows.append(
                f"{name:28s} {target:6d} {q['n_nodes']:6d} {q['n_tets']:7d} {t_mesh:7.2f} "
                f"{q['radius_ratio_min']:6.3f} {q['radius_ratio_mean']:7.3f} {q['min_dihedral_deg']:7.2f} "
                f"{q['n_below_bound']:5d} {info.edge_length_mm:5.2f} {len(info.attempts):5d}"
            )
            print(rows[-1], flush=True)
            if target == 5000:
                facets = boundary_facets(tets)
                t_tag, _ = median_time(lambda: tag_regions(points, facets, RegionParams()), repeats)
                mesh = build_liver_mesh(surface, target_nodes=target, mesher=args.mesher)
                t_feat, _ = median_time(lambda m=mesh: compute_features(m), repeats)
                other.append(f"{name:28s} tag_regions {t_tag:6.3f} s, compute_features {t_feat:6.3f} s at {len(points)} nodes")
    print("\n== tetrahedralise (median wall time; rr = normalised radius ratio 3 r_in / R_circ) ==")
    print(header)
    print("\n".join(rows))
    print("\n== surfaces, regions, features ==")
    print("\n".join(other))
    return 0


if __name__ == "__main__":
    sys.exit(main())
