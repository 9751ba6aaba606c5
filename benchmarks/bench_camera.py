"""Benchmark of camera-cloud serving: a raw 5,000-point cloud and the tool tip -> force and interval, one core.

Prints, on one core (1 BLAS / torch thread), over ``--calls`` calls each:

1. the compiled path (``Predictor.compile_cloud(ctx).predict(cloud, tip)``: grid the cloud, the
   out-of-distribution checks, PCA + MLP in NumPy, the interval): p50 / p99 latency per cloud, and
   its split (``cloud_grid`` alone vs the rest);
2. the reference path (``Predictor.predict_cloud(..., return_info=True)``: context checks, features,
   torch, interval) as its peer: p50 / p99 and the ratio;
3. batch throughput: ``--batch`` clouds through the compiled path in a loop (clouds/s) and through
   ``ForceModel.predict`` with a list of clouds (the reference batch).

The model is trained here for a few epochs on synthetic cases with whole surfaces
(``liverforce.learn.synthetic.synthetic_surface_arrays``): accuracy is irrelevant, the sizes are the
shipped config's (12 x 12 grid, PCA 16, state vector, MLP 2 x 128). Clouds are observed from a case's
deformed surface with ``--points`` points (default 5,000) and 0.5 mm noise.

Usage: ``python benchmarks/bench_camera.py [--quick] [--calls N] [--batch N] [--points K]``
"""

from __future__ import annotations

import argparse
import tempfile
import time

from liverforce.pipeline.job import thread_env

_ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
_ap.add_argument("--quick", action="store_true", help="fewer calls and a smaller batch")
_ap.add_argument("--calls", type=int, default=None, help="calls per path (default 3000; quick 300)")
_ap.add_argument("--batch", type=int, default=None, help="clouds per batch (default 2000; quick 200)")
_ap.add_argument("--points", type=int, default=5000, help="points per cloud")
ARGS = _ap.parse_args()
thread_env(1)

import numpy as np  # noqa: E402
import torch  # noqa: E402

from liverforce.learn.cloud_features import cloud_grid  # noqa: E402
from liverforce.learn.model import ForceModel, subset  # noqa: E402
from liverforce.learn.observation import ObservationConfig, observe  # noqa: E402
from liverforce.learn.synthetic import synthetic_surface_arrays  # noqa: E402
from liverforce.learn.train import train_scenario  # noqa: E402
from liverforce.serve import Predictor, Preop  # noqa: E402

torch.set_num_threads(1)
CALLS = ARGS.calls or (300 if ARGS.quick else 3000)
BATCH = ARGS.batch or (200 if ARGS.quick else 2000)
MODEL = {"encoder": "pca", "code_size": 16, "state_vector": True, "grid_size": 12, "hidden": [128, 128],
         "dropout": 0.1, "occlusion": {"radius_mm": 0.0, "mode": "remove"}, "noise_mm": 0.0, "roi_features": "cloud",
         "force_scaling": "stiffness", "probe_force_radius_mm": 5.0,
         "camera": {"observation": {"n_points": [200, 20000]}, "grid": {}, "tip_noise_mm": 0.5}}
TRAIN = {"test_fraction": 0.2, "epochs": 3, "batch_size": 64, "lr": 3e-3, "weight_decay": 0.0, "seed": 0,
         "interval": {"coverage": 0.9, "calibration_fraction": 0.25}}
NO_TUNE = {"enabled": False, "trials": 1, "folds": 2, "sobol_trials": 1, "epochs": 1}


def timed(fn, args, warmup=50) -> np.ndarray:
    for a in args[:warmup]:
        fn(a)
    out = np.empty(len(args))
    for i, a in enumerate(args):
        t = time.perf_counter()
        fn(a)
        out[i] = time.perf_counter() - t
    return out


def ms(t: np.ndarray) -> str:
    return f"p50 {1e3 * np.percentile(t, 50):.3f} ms, p99 {1e3 * np.percentile(t, 99):.3f} ms"


def main() -> None:
    arrays = synthetic_surface_arrays(120, n_geometries=3, seed=0, material_varies=True)
    with tempfile.TemporaryDirectory() as tmp:
        res = train_scenario(arrays, MODEL, TRAIN, NO_TUNE, "IV", "cloud", out_dir=tmp)
        model = ForceModel.load(res["model_path"])
        pred = Predictor(model)
    i = 0
    V, T = arrays["surface_meshes"][arrays["geometry_id"][i]]
    u = np.asarray(arrays["surface_displacement_mm"][i], dtype=np.float64)
    p = arrays["exertion_point_mm"][i]
    tip = p + u[int(np.argmin(np.linalg.norm(V - p, axis=1)))]
    cfg = ObservationConfig(n_points=(ARGS.points, ARGS.points), noise_sd_mm=0.5, roi_radius_mm=40.0)
    clouds = [observe(V + u, T, tip, arrays["frame_normal"][i], cfg, seed=s)[0] for s in range(20)]
    ctx = Preop.from_arrays({k: v for k, v in arrays.items() if k != "roi_deformed_mm"}, i)
    print(f"camera cloud serving, 1 core: {len(clouds[0])} points per cloud, grid {model.representation.grid_size}^2, "
          f"PCA {model.pre.encoder.code_size}, MLP {model.regressor_spec.hidden}; {CALLS} calls per path")
    t0 = time.perf_counter()
    fast = pred.compile_cloud(ctx)
    print(f"compile (once per exertion point: context checks, pre-operative raster, state): "
          f"{1e3 * (time.perf_counter() - t0):.1f} ms")
    args = [clouds[k % len(clouds)] for k in range(CALLS)]
    t_fast = timed(lambda c: fast.predict(c, tip), args)
    t_grid = timed(lambda c: cloud_grid(c, fast.ref, fast.spec), args)
    t_ref = timed(lambda c: pred.predict_cloud(c, ctx, tool_tip_mm=tip, return_info=True), args[:max(CALLS // 5, 60)])
    print(f"compiled cloud -> force + interval: {ms(t_fast)}")
    print(f"  of which cloud_grid (features):   {ms(t_grid)}")
    print(f"reference predict_cloud (peer):     {ms(t_ref)}; compiled is "
          f"{np.median(t_ref) / np.median(t_fast):.1f}x faster (median)")
    batch = [clouds[k % len(clouds)] for k in range(BATCH)]
    t0 = time.perf_counter()
    for c in batch:
        fast.predict(c, tip)
    rate = BATCH / (time.perf_counter() - t0)
    arr = subset({k: v for k, v in arrays.items() if k not in ("surface_displacement_mm",)}, np.zeros(BATCH, int))
    arr["camera_cloud_mm"] = batch
    arr["tool_tip_mm"] = np.tile(tip, (BATCH, 1))
    t0 = time.perf_counter()
    model.predict(arr)
    rate_ref = BATCH / (time.perf_counter() - t0)
    print(f"batch of {BATCH} clouds: compiled loop {rate:,.0f} clouds/s; reference ForceModel.predict "
          f"{rate_ref:,.0f} clouds/s (peer; ratio {rate / rate_ref:.1f}x)")


if __name__ == "__main__":
    main()
