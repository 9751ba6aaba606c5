"""Benchmark of the camera observation model and the cloud grid features (liverforce.learn.observation,
liverforce.learn.cloud_features).

Prints, on one core, the median over ``--repeats`` runs (each with a new seed, so a new camera pose) of:

1. ``observe`` of one procedural liver surface (seed 0) with a 6 mm Gaussian dent pushed in at an
   anterior-superior exertion point, at two surface resolutions (voxel 2.5 mm: ~39k triangles, the
   generator's default; voxel 4 mm: ~15k triangles), for fixed cloud sizes 200 / 2,000 / 20,000 points
   and for the default log-uniform size (200-20,000), with the default settings otherwise (camera
   60-120 mm in a 40 deg cone, tool 2.5 mm, 256^2 depth buffer, 0.5 mm noise); plus ``make_view``
   (camera, depth buffer and tool of one pose, 90 mm along the normal) alone;
2. ``cloud_grid`` (12 x 12 grid) of camera clouds of 200 / 5,000 / 20,000 points, and the one-off
   pre-operative reference per exertion point: ``ReferenceSurface.from_patch`` (the z-buffer of the ROI
   patch's triangles, the default) beside ``ReferenceSurface.build`` (the ROI points' interpolant).

Usage: ``python benchmarks/bench_observation.py [--quick] [--repeats N]``
(``--quick``: the 15k-triangle surface only, fewer repeats).
"""

from __future__ import annotations

import argparse
import itertools

from liverforce.pipeline.job import thread_env

_ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
_ap.add_argument("--quick", action="store_true", help="one surface resolution, fewer repeats")
_ap.add_argument("--repeats", type=int, default=None, help="timed runs per case (default 30; quick 10)")
ARGS = _ap.parse_args()
thread_env(1)

import numpy as np  # noqa: E402

from benchmarks.harness import Bench  # noqa: E402
from liverforce.dataset.roi import local_frame, roi_triangles, surface_graph  # noqa: E402
from liverforce.geometry.procedural import LiverShapeParams, procedural_liver  # noqa: E402
from liverforce.learn.cloud_features import CloudGridSpec, ReferenceSurface, cloud_grid  # noqa: E402
from liverforce.learn.observation import ObservationConfig, SurfaceTopology, make_view, observe  # noqa: E402

REPEATS = ARGS.repeats or (10 if ARGS.quick else 30)
VOXELS = (4.0,) if ARGS.quick else (2.5, 4.0)


def dented_liver(voxel_mm: float):
    """Procedural liver 0, an exertion point, its frame, and the surface pushed in by a 6 mm Gaussian dent."""
    s = procedural_liver(0, LiverShapeParams(voxel_mm=voxel_mm))
    V, T = s.vertices, s.faces
    i = int(np.argmax(V[:, 1] + 0.3 * V[:, 2]))
    frame = local_frame(surface_graph(V, T), V[i])
    n = frame[2]
    r2 = np.sum((V - V[i]) ** 2, axis=1)
    Vd = V - 6.0 * np.exp(-r2 / (2 * 12.0**2))[:, None] * n
    return V, Vd, T, V[i] - 6.0 * n, V[i], frame


def main() -> None:
    b = Bench("camera observation model (1 thread; median over new camera poses)", repeats=REPEATS, warmup=2)
    seeds = itertools.count()
    clouds = {}
    for vox in VOXELS:
        V, Vd, T, tip, p, frame = dented_liver(vox)
        topo = SurfaceTopology.of(T, V)
        m = len(T)
        tag = f"{m // 1000}k tris"
        for n_pts in (200, 2000, 20000):
            cfg = ObservationConfig(n_points=(n_pts, n_pts))
            b.time(f"observe, {tag}, {n_pts} points",
                   lambda cfg=cfg: observe(Vd, topo, tip, frame[2], cfg, next(seeds)))
        cfg = ObservationConfig()
        b.time(f"observe, {tag}, default 200-20000 points", lambda: observe(Vd, topo, tip, frame[2], cfg, next(seeds)))
        C = tip + 90.0 * frame[2]
        b.time(f"make_view (depth buffer 256^2), {tag}", lambda: make_view(Vd, topo, tip, C, cfg, normal=frame[2]))
        for n_pts in (200, 5000, 20000):
            clouds[n_pts] = observe(Vd, topo, tip, frame[2], ObservationConfig(n_points=(n_pts, n_pts)), 1)[0]
        inside = np.linalg.norm(V - p, axis=1) < 60.0
        roi = V[inside]
        roi_tri = roi_triangles(T, np.flatnonzero(inside))
    spec = CloudGridSpec(grid_size=12, half_width_mm=40.0)
    R = np.asarray(frame)  # rows t1, t2, n
    b.time(f"ReferenceSurface.from_patch ({len(roi)} pre-op points, {len(roi_tri)} triangles; the default)",
           lambda: ReferenceSurface.from_patch(roi, roi_tri, p, R, spec))
    b.time(f"ReferenceSurface.build ({len(roi)} pre-op points; reference: points)",
           lambda: ReferenceSurface.build(roi, p, frame[2], frame[0], frame[1], spec))
    ref = ReferenceSurface.from_patch(roi, roi_tri, p, R, spec)
    for n_pts, c in clouds.items():
        b.time(f"cloud_grid 12x12, {n_pts} points", lambda c=c: cloud_grid(c, ref, spec))
    b.print()


if __name__ == "__main__":
    main()
