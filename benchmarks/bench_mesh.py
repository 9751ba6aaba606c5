"""Benchmark of the geometry and mesh stages (liverforce.geometry, liverforce.mesh).

Prints, per geometry, the median over ``--repeats`` runs of:

1. surface generation / import time;
2. ``tetrahedralise`` wall time at the default resolution (~5k nodes) and at
   the study's ~20k nodes, with the node/tet counts obtained and the quality
   (min and mean normalised radius ratio, min dihedral angle, elements below
   the radius-ratio bound 0.2);
3. region tagging and feature computation time at ~5k nodes.

Geometries: procedural livers (seeds 0, 1, 2), the 50 mm cube phantom and,
when ../shared/data/livers exists, the SOFA liver-smooth.obj (units=40).

Usage: ``python benchmarks/bench_mesh.py [--repeats N] [--quick] [--mesher gmsh|tetgen]``
(``--quick``: one procedural liver and the cube, 5k nodes only, 1 repeat).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

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
    args = ap.parse_args()
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
