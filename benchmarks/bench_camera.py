"""Benchmark of camera-cloud serving: a raw 5,000-point cloud and the tool tip -> force and interval, one core.

Target (issue #15): p99 <= 2 ms per cloud, and >= 10,000 clouds/s in batches, on 1 core.

For each regressor (``--regressors``, default both: ``gp``, the default of ``config/model/default.yaml``, an exact
Gaussian process, and ``mlp``), prints, on one core (1 BLAS / torch / numba thread), each figure the median over
``--repeats`` runs:

1. one cloud per call, ``--calls`` calls per run: p50 / p99 latency of the compiled path
   (``Predictor.compile_cloud(ctx).predict(cloud, tip)``: one numba pass grids the cloud, the
   out-of-distribution checks, the affine map + regressor, the interval), of the reference grid alone
   (``cloud_grid``) and of the reference path (``Predictor.predict_cloud(..., return_info=True)``:
   context checks, features, torch, interval), with the ratio;
2. batch throughput (clouds/s): ``CompiledCloud.predict_batch`` on lists of ``--batches`` clouds
   (default 256 and 4096), on one thread and the largest batch again gridded in ``--threads`` threads
   (``predict_batch(threads=)``; default 2; its forces checked to be the same bits), against the per-cloud compiled
   loop and the reference
   ``ForceModel.predict`` on a list of clouds (on ``--ref-batch`` clouds), and the largest batch again in a
   lab's frame (LPS metres, ``compile_cloud(ctx, frame="LPS", units="m")``) against the same clouds in RAS mm;
3. whether the targets are met on this machine, and a summary table of both regressors;
4. with ``--profile``: where a batch's time goes, per cloud (the largest batch, medians of ``--repeats`` calls):
   the gridding pass (``CompiledCloud._grid``), again with the dent fit, the tilted instrument fit and both
   switched off in the kernel's parameters, and without the drop of gross depth errors (what each costs; the
   features then differ, only the time is read), the head (affine map, regressor: ``_head``; for a GP with the
   input-distance flag also without it, the same model compiled without the flag, and the ratio) and the checks
   (``_reasons``).

The models are trained here on synthetic cases with whole surfaces
(``liverforce.learn.synthetic.synthetic_surface_arrays``, ``--cases``; accuracy is irrelevant). The model config is
the shipped camera variant's, read from the config (``cloud_sv``: a 16 x 16 grid with a 1.5-cell kernel, ``--grid``
and ``--kernel-cells`` to change them; state vector, the dent fit round the tool; the GP is the mean of five GPs on
PCA codes of 8, 16, 32, 48 and 64 components, ``model.gp.code_members``, each on every training row, about 640 with
the default 480 cases; the default experiment's camera model has 1,920, as ``--cases 1440`` gives; the MLP 2 x 128,
3 epochs). Clouds are observed from a case's deformed surface with ``--points`` points (default 5,000) of the liver,
the instrument's visible points at the same density (a few hundred more; the shipped camera model fits the tool's
axis to them) and 0.5 mm noise: 20 observations, and ``--distinct`` (default 256) jittered copies of them for the
batches, so a batch reads clouds from memory, not from a few cached ones.

Usage: ``python benchmarks/bench_camera.py [--quick] [--regressors gp mlp] [--calls N] [--repeats N]
[--batches 256 4096] [--points K] [--grid G] [--kernel-cells C] [--cases N] [--no-instrument]``

Measured (2-core VM shared with other jobs, 1 thread; figures vary by tens of % with the load),
``python benchmarks/bench_camera.py``: see the commit that last changed this file.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import tempfile
import time

from liverforce.pipeline.job import thread_env

_ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
_ap.add_argument("--quick", action="store_true", help="fewer calls, cases and batches")
_ap.add_argument("--regressors", nargs="+", default=["gp", "mlp"], choices=["gp", "mlp"], help="models to measure")
_ap.add_argument("--calls", type=int, default=None, help="calls per path and run (default 2000; quick 300)")
_ap.add_argument("--repeats", type=int, default=None, help="runs of every measurement (default 5; quick 2)")
_ap.add_argument("--batches", type=int, nargs="+", default=None, help="batch sizes (default 256 4096; quick 256)")
_ap.add_argument("--ref-batch", type=int, default=None, help="clouds through the reference batch (default 1000; "
                 "quick 200)")
_ap.add_argument("--points", type=int, default=5000, help="points per cloud")
_ap.add_argument("--grid", type=int, default=None, help="the cloud's grid points per side (default: the shipped "
                 "camera variant's, config/train/default.yaml cloud_sv)")
_ap.add_argument("--kernel-cells", type=float, default=None, help="the grid's kernel radius in cells (default: the "
                 "shipped variant's)")
_ap.add_argument("--cases", type=int, default=None, help="synthetic training cases (default 480; quick 120)")
_ap.add_argument("--distinct", type=int, default=256, help="distinct clouds (jittered copies) cycled in a batch")
_ap.add_argument("--threads", type=int, default=2, help="also the largest batch gridded in this many threads "
                 "(predict_batch(threads=); default 2, this machine's cores; 1: not measured)")
_ap.add_argument("--profile", action="store_true", help="also time the compiled path's stages per cloud")
_ap.add_argument("--no-instrument", action="store_true", help="models trained on clouds without the instrument, "
                 "served such clouds (the camera model before it fitted the instrument's axis)")
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
from liverforce.serve.compiled_cloud import cores  # noqa: E402

torch.set_num_threads(1)


@functools.lru_cache(maxsize=1)
def _shipped_config() -> dict:
    """The default config (composed once)."""
    from liverforce.config import compose

    return compose([])


def shipped_camera_model(grid: int | None, kernel_cells: float | None, no_instrument: bool) -> dict:
    """The shipped camera variant's model config (``cloud_sv``: ``config/model/default.yaml`` with the variant's
    overrides in ``config/train/default.yaml``, as the pipeline merges them), with ``grid`` points per side and a
    ``kernel_cells`` kernel when given; ``no_instrument``: the instrument neither in the cloud nor fitted (no tool
    axis, no dent fit)."""
    from liverforce.config import merge_mapping
    from liverforce.pipeline.plan import Plan

    model = Plan(_shipped_config()).variants()["cloud_sv"]
    over: dict = {"camera": {"grid": {}}}
    if grid is not None:
        over["grid_size"] = int(grid)
    if kernel_cells is not None:
        over["camera"]["grid"]["kernel_radius_cells"] = float(kernel_cells)
    if no_instrument:
        over["camera"]["observation"] = {"instrument_in_cloud": False}
        over["camera"]["grid"].update(instrument_radius_mm=0.0, instrument_max_tilt_deg=0.0, dent_radius_mm=0.0)
    return merge_mapping(model, over)


CALLS = ARGS.calls or (300 if ARGS.quick else 2000)
REPEATS = ARGS.repeats or (2 if ARGS.quick else 5)
BATCHES = ARGS.batches or ([256] if ARGS.quick else [256, 4096])
REF_BATCH = ARGS.ref_batch or (200 if ARGS.quick else 1000)
CASES = ARGS.cases or (120 if ARGS.quick else 480)
MODEL = shipped_camera_model(ARGS.grid, ARGS.kernel_cells, ARGS.no_instrument)
TRAIN = {"test_fraction": 0.2, "epochs": 3, "batch_size": 64, "lr": 3e-3, "weight_decay": 0.0, "seed": 0,
         # the shipped interval (scale, bins, widening) calibrated on one held-out quarter instead of 4 folds
         "interval": {**_shipped_config()["train"]["interval"], "folds": 1, "calibration_fraction": 0.25}}
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


def pcts(fn, args) -> tuple[float, float]:
    """Median over REPEATS runs of (p50, p99) seconds per call."""
    runs = [timed(fn, args) for _ in range(REPEATS)]
    return float(np.median([np.percentile(t, 50) for t in runs])), float(np.median([np.percentile(t, 99) for t in runs]))


def ms(p: tuple[float, float]) -> str:
    return f"p50 {1e3 * p[0]:.3f} ms, p99 {1e3 * p[1]:.3f} ms"


def rate(fn, n: int, repeats: int) -> float:
    """Median over ``repeats`` runs of n / (seconds of one fn())."""
    fn()
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        out.append(n / (time.perf_counter() - t0))
    return float(np.median(out))


def describe(model) -> str:
    reg = model.regressor
    if model.regressor_spec.kind == "gp":
        members = getattr(reg, "members", None)
        if members is not None:
            return (f"mean of {len(members)} GPs on {reg.n_train} training rows of "
                    f"{', '.join(str(m.X.shape[1]) for m in members)} inputs")
        return f"GP on {reg.n_train} training rows of {reg.X.shape[1]} inputs"
    return f"MLP {model.regressor_spec.hidden}"


def profile(fast, batch: list, tips: np.ndarray, plain=None) -> None:
    """Per-cloud time of the compiled batch's stages (module docstring, 4.): gridding with the shipped kernel
    parameters and with the dent (``inst[10]``), the tilted fit (``inst[8]``) or both off, and without the drop of
    gross depth errors (``inst[14]``, when the model drops them), head, checks. ``plain``: the same model compiled
    without the input-distance flag (its head computes no distance), whose head is timed beside."""
    nb = len(batch)

    def per_cloud(fn) -> float:  # us per cloud, from the median of the runs' rates (as the batches')
        return 1e6 / rate(fn, nb, REPEATS)

    P = [fast._cloud(c) for c in batch]
    inst = fast._inst.copy()
    grid = {}
    rows = [("as shipped", ()), ("without the dent fit", (10,)), ("without the tilted fit", (8,)),
            ("without both", (8, 10))] + ([("without the gross-error drop", (14,))] if inst[14] > 0 else [])
    for name, off in rows:
        fast._inst[:] = inst
        fast._inst[list(off)] = 0.0
        grid[name] = per_cloud(lambda: fast._grid(P, None, None, tips))
    fast._inst[:] = inst
    X, n_used, n_bad, n_tool = fast._grid(P, None, None, tips)
    head = per_cloud(lambda: fast._head(X))
    bare = ""
    if plain is not None:  # the input-distance flag's share of the head (a max over the kernel matrix per member)
        head_plain = per_cloud(lambda: plain._head(X))
        bare = f" (without the input distance {head_plain:.1f}: x{head / head_plain:.2f})"
    counts = np.array([len(c) for c in P])
    checks = per_cloud(lambda: fast._reasons(lambda r: P[r], counts, tips, X, n_used, n_bad, n_tool))
    total = per_cloud(lambda: fast.predict_batch(batch, tips))
    print(f"profile, batch of {nb} clouds, us per cloud (medians of {REPEATS}): predict_batch {total:.1f}; "
          f"gridding {grid['as shipped']:.1f} (" + ", ".join(f"{k} {v:.1f}" for k, v in grid.items()
                                                         if k != "as shipped") +
          f"); head {head:.1f}{bare}; checks {checks:.1f}")


def measure(kind: str, model, arrays: dict, ctx, tip, clouds, batch_pool) -> dict:
    pred = Predictor(model)
    print(f"\n== {kind}: {describe(model)}; {len(clouds[0])} points per cloud, grid "
          f"{model.representation.grid_size}^2, PCA {model.pre.encoder.code_size}; {CALLS} calls per path and run, "
          f"medians of {REPEATS} runs ==")
    t0 = time.perf_counter()
    fast = pred.compile_cloud(ctx)
    print(f"compile (once per exertion point: context checks, pre-operative raster, state, kernels loaded): "
          f"{1e3 * (time.perf_counter() - t0):.1f} ms")
    args = [clouds[k % len(clouds)] for k in range(CALLS)]
    diff = max(float(np.abs(fast.predict(c, tip)[0] - pred.predict_cloud(c, ctx, tool_tip_mm=tip)).max())
               for c in clouds[:5])
    print(f"compiled vs reference force (5 clouds): max |diff| {diff:.2e} N")
    t_fast = pcts(lambda c: fast.predict(c, tip), args)
    t_grid = pcts(lambda c: cloud_grid(c, fast.ref, fast.spec, tip), args)
    t_ref = pcts(lambda c: pred.predict_cloud(c, ctx, tool_tip_mm=tip, return_info=True), args[:max(CALLS // 5, 100)])
    print(f"one cloud, compiled predict (force + interval): {ms(t_fast)}")
    print(f"one cloud, reference cloud_grid (features only): {ms(t_grid)}")
    print(f"one cloud, reference predict_cloud (peer):       {ms(t_ref)}; compiled is {t_ref[0] / t_fast[0]:.1f}x "
          f"(p50) / {t_ref[1] / t_fast[1]:.1f}x (p99) faster")
    loop_n = min(1000, max(BATCHES))
    loop = [batch_pool[k % len(batch_pool)] for k in range(loop_n)]

    def one_by_one():
        for c in loop:
            fast.predict(c, tip)

    r_loop = rate(one_by_one, loop_n, REPEATS)
    rates = {}
    for nb in BATCHES:
        batch = [batch_pool[k % len(batch_pool)] for k in range(nb)]
        tips = np.tile(tip, (nb, 1))
        rates[nb] = rate(lambda: fast.predict_batch(batch, tips), nb, REPEATS)
    # the largest batch again, gridded (and its head run) in ARGS.threads threads (the same bits: checked)
    r_thr = None
    nbig = max(BATCHES)
    if ARGS.threads > 1:
        batch = [batch_pool[k % len(batch_pool)] for k in range(nbig)]
        tips = np.tile(tip, (nbig, 1))
        one, many = fast.predict_batch(batch, tips), fast.predict_batch(batch, tips, threads=ARGS.threads)
        same = (np.array_equal(one.force, many.force, equal_nan=True) and one.refused == many.refused
                and np.array_equal(one.half_width, many.half_width, equal_nan=True) and one.warnings == many.warnings)
        r_thr = rate(lambda: fast.predict_batch(batch, tips, threads=ARGS.threads), nbig, REPEATS)
    # a lab's clouds in LPS metres: the compiled path folds the map into its rotation (no conversion per point)
    lab = pred.compile_cloud(ctx, frame="LPS", units="m")
    lps = np.array([-1.0, -1.0, 1.0])
    pool_lab = [c * lps / 1000.0 for c in batch_pool]  # made once, outside the timing
    nb = max(BATCHES)
    batch_lab = [pool_lab[k % len(pool_lab)] for k in range(nb)]
    r_lab = rate(lambda: lab.predict_batch(batch_lab, np.tile(tip * lps / 1000.0, (nb, 1))), nb, REPEATS)
    d_lab = max(float(np.abs(lab.predict(c * lps / 1000.0, tip * lps / 1000.0)[0] * lps
                             - fast.predict(c, tip)[0]).max()) for c in clouds[:5])
    arr = subset({k: v for k, v in arrays.items() if k not in ("surface_displacement_mm",)}, np.zeros(REF_BATCH, int))
    arr["camera_cloud_mm"] = [batch_pool[k % len(batch_pool)] for k in range(REF_BATCH)]
    arr["tool_tip_mm"] = np.tile(tip, (REF_BATCH, 1))
    r_ref = rate(lambda: model.predict(arr), REF_BATCH, max(1, REPEATS // 2))
    print(f"per-cloud compiled predict in a loop: {r_loop:,.0f} clouds/s")
    for nb, r in rates.items():
        print(f"predict_batch, {nb} clouds: {r:,.0f} clouds/s ({r / r_loop:.1f}x the loop, {r / r_ref:.0f}x the "
              f"reference)")
    if r_thr is not None:
        print(f"predict_batch, {nbig} clouds gridded in {ARGS.threads} threads: {r_thr:,.0f} clouds/s "
              f"({r_thr / rates[nbig]:.2f}x 1 thread); forces, widths, refusals and warnings "
              f"{'the same bits' if same else 'DIFFERENT'} as 1 thread")
    print(f"predict_batch, {nb} clouds in LPS metres (compile_cloud(ctx, frame='LPS', units='m')): {r_lab:,.0f} "
          f"clouds/s ({r_lab / rates[nb]:.2f}x the same clouds in RAS mm); max |dF| against RAS mm {d_lab:.1e} N")
    print(f"reference ForceModel.predict, list of {REF_BATCH} clouds (peer): {r_ref:,.0f} clouds/s")
    if ARGS.profile:
        plain = None
        if model.distance_flag is not None:  # nor far widths, which read the distance too
            meta = {k: v for k, v in model.meta.items() if k != "input_distance"}
            if model.interval is not None:
                meta["interval"] = dataclasses.replace(model.interval, far_threshold=None, far_factor=None,
                                                       near_factor=None).to_dict()
            plain = Predictor(ForceModel(model.representation, model.pre, model.regressor_spec, model.regressor,
                                         meta)).compile_cloud(ctx)
        profile(fast, [batch_pool[k % len(batch_pool)] for k in range(nb)], np.tile(tip, (nb, 1)), plain)
    best = max(rates.values())
    print(f"targets on this machine: p99 {1e3 * t_fast[1]:.3f} ms <= 2 ms: "
          f"{'met' if t_fast[1] <= 2e-3 else 'NOT met'}; batch {best:,.0f} clouds/s >= 10,000: "
          f"{'met' if best >= 1e4 else 'NOT met'} on 1 core" + ("" if r_thr is None else
          f"; {r_thr:,.0f} clouds/s in {ARGS.threads} threads (at most the {cores()} cores this process has)"))
    return {"rates": rates, "p": t_fast, "ref_p": t_ref, "ref_rate": r_ref, "diff": diff, "threads": r_thr}


def main() -> None:
    arrays = synthetic_surface_arrays(CASES, n_geometries=3, seed=0, material_varies=True)
    models = {}
    with tempfile.TemporaryDirectory() as tmp:
        for kind in ARGS.regressors:
            t0 = time.perf_counter()
            res = train_scenario(arrays, {**MODEL, "regressor": kind}, TRAIN, NO_TUNE, "IV", "cloud",
                                 out_dir=f"{tmp}/{kind}")
            models[kind] = ForceModel.load(res["model_path"])
            print(f"trained the {kind} model on {CASES} synthetic cases in {time.perf_counter() - t0:.0f} s")
    i = 0
    V, T = arrays["surface_meshes"][arrays["geometry_id"][i]]
    u = np.asarray(arrays["surface_displacement_mm"][i], dtype=np.float64)
    p = arrays["exertion_point_mm"][i]
    tip = p + u[int(np.argmin(np.linalg.norm(V - p, axis=1)))]
    cfg = ObservationConfig(n_points=(ARGS.points, ARGS.points), noise_sd_mm=0.5, roi_radius_mm=40.0,
                            instrument_in_cloud=not ARGS.no_instrument)  # as the shipped model sees them
    clouds = [observe(V + u, T, tip, arrays["frame_normal"][i], cfg, seed=s)[0] for s in range(20)]
    rng = np.random.default_rng(0)
    pool = [clouds[k % len(clouds)] + rng.normal(0.0, 0.01, clouds[k % len(clouds)].shape)
            for k in range(ARGS.distinct)]
    ctx = Preop.from_arrays({k: v for k, v in arrays.items() if k != "roi_deformed_mm"}, i)
    out = {kind: measure(kind, model, arrays, ctx, tip, clouds, pool) for kind, model in models.items()}
    inst = "" if ARGS.no_instrument else f" of the liver, {len(clouds[0]) - ARGS.points} of the instrument"
    print(f"\nsummary (1 thread, medians of {REPEATS} runs; {ARGS.points}-point clouds{inst}; reference = "
          f"ForceModel.predict on a list / predict_cloud per cloud):")
    thr = f" | batch {max(BATCHES)} in {ARGS.threads} threads" if ARGS.threads > 1 else ""
    head = "regressor | " + " | ".join(f"batch {nb} clouds/s (x ref)" for nb in BATCHES) + thr + \
        " | p50 / p99 ms (x ref p50) | max |dF| N"
    print(head)
    for kind, o in out.items():
        cols = [f"{o['rates'][nb]:,.0f} ({o['rates'][nb] / o['ref_rate']:.0f}x)" for nb in BATCHES]
        cols += [] if o["threads"] is None else [f"{o['threads']:,.0f}"]
        print(f"{kind} | " + " | ".join(cols) + f" | {1e3 * o['p'][0]:.3f} / {1e3 * o['p'][1]:.3f} "
              f"({o['ref_p'][0] / o['p'][0]:.0f}x) | {o['diff']:.1e}")


if __name__ == "__main__":
    main()
