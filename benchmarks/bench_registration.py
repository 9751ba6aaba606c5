"""Benchmark of the registration refinement (``liverforce.learn.registration.refine_registration``), one core.

It runs once per exertion point, when the tool touches: the camera's unloaded cloud is fitted to the
pre-operative surface and the instrument's axis in it anchors the shift along the surface. For clouds of
``--points`` points (default 1,000, 5,000 and 20,000 of the liver, the instrument's visible points at the same
density, 0.5 mm noise) of synthetic livers (``liverforce.learn.synthetic.synthetic_surface_arrays``: ellipsoids,
``--cases`` exertion points), each moved off by a shift of ``--shift`` mm in a random direction and a turn of
``--turn`` degrees about the liver's centroid, prints the median and 90th percentile of the refinement's time
over the cases and ``--repeats`` runs (the pre-operative raster is built beforehand, as the context is), and how
well it undid the motion at the exertion point (the median error along the normal and along the surface). The
grid settings are the shipped camera variant's (``cloud_sv``).

Each is run twice in the same loop: with the liver's change of shape since the scan fitted (the default,
``SHAPE_DEGREE``) and rigid only (``shape_degree=0``), their ratio printed; and the time to apply each to a
cloud of the same size (``Refinement.points``: the rigid map, or the rigid map and the reshaping, which a
compiled path with such a refinement runs once per cloud).

Usage: ``PYTHONPATH=. OMP_NUM_THREADS=1 python benchmarks/bench_registration.py [--points 1000 5000 20000]
[--cases 40] [--repeats 5] [--shift 2] [--turn 2]``
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
from scipy.spatial.transform import Rotation


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, nargs="+", default=[1000, 5000, 20000])
    ap.add_argument("--cases", type=int, default=40)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--shift", type=float, default=2.0)
    ap.add_argument("--turn", type=float, default=2.0)
    args = ap.parse_args()

    from liverforce.config import compose
    from liverforce.learn.camera import grid_spec
    from liverforce.learn.cloud_features import ReferenceSurface
    from liverforce.learn.observation import ObservationConfig, observe
    from liverforce.learn.registration import SHAPE_DEGREE, refine_registration
    from liverforce.learn.synthetic import synthetic_surface_arrays
    from liverforce.pipeline.plan import Plan
    from liverforce.serve.preop import Preop

    model = Plan(compose([])).variants()["cloud_sv"]
    half = float(model.get("grid_half_width_mm") or 20.0)
    spec = grid_spec(int(model["grid_size"]), half, model["camera"])
    obs = model["camera"]["observation"]
    a = synthetic_surface_arrays(args.cases, n_geometries=4, seed=5)
    rng = np.random.default_rng(0)
    cases = []
    for i in range(args.cases):
        ctx = Preop.from_arrays(a, i)
        ref = ReferenceSurface.for_case(ctx.roi_undeformed_mm, ctx.roi_triangles, ctx.exertion_point_mm, ctx.rotation,
                                        spec)
        d, ax = rng.normal(size=3), rng.normal(size=3)
        Q = Rotation.from_rotvec(math.radians(args.turn) * ax / np.linalg.norm(ax)).as_matrix()
        c = np.asarray(a["liver_centroid_mm"][i], dtype=np.float64)
        cases.append((i, ctx, ref, Q, c - Q @ c + args.shift * d / np.linalg.norm(d)))
    print(f"grid {spec.grid_size} x {spec.grid_size}, +-{half:g} mm, instrument radius {spec.instrument_radius_mm:g} "
          f"mm; {args.cases} exertion points on 4 synthetic livers, moved {args.shift:g} mm and {args.turn:g} deg; "
          f"medians over cases x {args.repeats} runs, 1 thread")
    for k in args.points:
        cfg = ObservationConfig(n_points=(k, k), noise_sd_mm=0.5, instrument_in_cloud=True,
                                roi_radius_mm=math.sqrt(2.0) * half + 2.0 * spec.spacing_mm,
                                tool_radius_mm=float(obs.get("tool_radius_mm") or 2.5))
        degrees = (SHAPE_DEGREE, 0)
        times = {d: [] for d in degrees}
        apply = {d: [] for d in degrees}
        err_n, err_t, sizes = [], [], []
        for i, ctx, ref, Q, b in cases:
            V, T = a["surface_meshes"][a["geometry_id"][i]]
            cloud, _ = observe(V, T, ctx.exertion_point_mm, ctx.frame[2], cfg, seed=i)
            moved, tip = cloud @ Q.T + b, Q @ ctx.exertion_point_mm + b
            sizes.append(len(cloud))
            for _ in range(args.repeats):
                for d in degrees:  # interleaved: the host's drift falls on both
                    t0 = time.perf_counter()
                    fix = refine_registration(ref, spec, moved, tip, shape_degree=d)
                    times[d].append(time.perf_counter() - t0)
                    t0 = time.perf_counter()
                    fix.points(moved)
                    apply[d].append(time.perf_counter() - t0)
            fix = refine_registration(ref, spec, moved, tip)
            e = ctx.rotation @ (fix.points(tip) - ctx.exertion_point_mm)
            err_n.append(abs(e[2]))
            err_t.append(math.hypot(e[0], e[1]))
        t = {d: np.asarray(v) * 1e3 for d, v in times.items()}
        u = {d: np.median(v) * 1e6 for d, v in apply.items()}
        deg = SHAPE_DEGREE
        print(f"{k:6d} liver points ({int(np.median(sizes))} with the instrument's): median {np.median(t[deg]):.1f} "
              f"ms, p90 {np.quantile(t[deg], 0.9):.1f} ms (rigid only {np.median(t[0]):.1f} ms, "
              f"{np.median(t[deg]) / np.median(t[0]):.2f}x); applied to the cloud {u[deg]:.0f} us "
              f"(rigid {u[0]:.0f} us); left at the exertion point: {np.median(err_n):.3f} mm along the "
              f"normal, {np.median(err_t):.3f} mm along the surface (medians; moved {args.shift:g} mm / "
              f"{args.turn:g} deg)", flush=True)


if __name__ == "__main__":
    main()
