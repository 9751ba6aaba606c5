"""Benchmark of serving (liverforce.serve): latency from a raw deformed point cloud to a force.

Prints, on one core (1 BLAS / torch thread):

1. single-sample latency of the fixed-topology fast path (``CompiledROI.predict``,
   the haptic loop: tracked ROI nodes -> force) over ``--calls`` calls: p50 and
   p99, with the split preprocessing (affine first stage incl. checks) vs
   network (MLP in NumPy); PCA and DAE encoders;
2. the same for the reference path (``Predictor.predict``: checks + top-sheet
   resampling of the ROI patch + scalers + torch) and its split (``Representation.features_of``
   vs the rest), and the one-off compile cost per exertion point;
3. batch throughput of the fast path (``predict_batch``, ``--batch`` rows per
   call) with the split, and of the reference path on a shard-like batch;
4. an unordered camera cloud (``Predictor.predict_cloud``, deformed-height model).

Usage: ``python benchmarks/bench_predict.py [--quick] [--calls N] [--batch N] [--nodes K]``

The models are trained here on synthetic cases (liverforce.learn.synthetic) for
a few epochs: accuracy is irrelevant, sizes are realistic (``--nodes`` ROI
nodes; the shipped model config: 12 x 12 grid, PCA 16 (or DAE), state vector, MLP 2 x 128, the grid on the
ROI patch's top sheet).
"""

from __future__ import annotations

import argparse
import tempfile
import time

from liverforce.pipeline.job import thread_env

_ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
_ap.add_argument("--quick", action="store_true", help="fewer calls and a smaller batch")
_ap.add_argument("--calls", type=int, default=None, help="single-sample calls per path (default 20000; quick 2000)")
_ap.add_argument("--batch", type=int, default=None, help="rows per batch call (default 20000; quick 5000)")
_ap.add_argument("--nodes", type=int, default=450, help="ROI nodes per case (the study's ROI order)")
ARGS = _ap.parse_args()
thread_env(1)

import numpy as np  # noqa: E402
import torch  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

from benchmarks.harness import Bench  # noqa: E402
from liverforce.learn.model import subset  # noqa: E402
from liverforce.learn.state import state_vector  # noqa: E402
from liverforce.learn.synthetic import synthetic_arrays  # noqa: E402
from liverforce.learn.train import train_scenario  # noqa: E402
from liverforce.serve import Predictor, Preop  # noqa: E402

torch.set_num_threads(1)
CALLS = ARGS.calls or (2000 if ARGS.quick else 20000)
BATCH = ARGS.batch or (5000 if ARGS.quick else 20000)
MODEL = {"encoder": "pca", "code_size": 16, "state_vector": True, "grid_size": 12, "hidden": [128, 128],
         "dropout": 0.1, "occlusion": {"radius_mm": 3.0, "mode": "remove"}, "noise_mm": 0.0,
         "interpolation": "surface"}
TRAIN = {"test_fraction": 0.2, "epochs": 5, "batch_size": 64, "lr": 3e-3, "weight_decay": 0.0, "seed": 0}
NO_TUNE = {"enabled": False, "trials": 1, "folds": 2, "sobol_trials": 1, "epochs": 1}


def per_call(fn, args_list, warmup=200) -> np.ndarray:
    """Seconds per call of ``fn(a)`` for each ``a`` (cycled), after ``warmup`` untimed calls."""
    for i in range(warmup):
        fn(args_list[i % len(args_list)])
    out = np.empty(len(args_list))
    clock = time.perf_counter
    for i, a in enumerate(args_list):
        t0 = clock()
        fn(a)
        out[i] = clock() - t0
    return out


def pct(t: np.ndarray) -> dict:
    return {f"p{q}_us": round(float(np.percentile(t, q)) * 1e6, 1) for q in (50, 99)}


def stream(U: np.ndarray, D: np.ndarray, n: int, seed: int = 0) -> list[np.ndarray]:
    """``n`` deformed states of one ROI (the dent at random depths plus 0.05 mm noise)."""
    rng = np.random.default_rng(seed)
    base = [U + (D - U) * s for s in rng.uniform(0.2, 1.2, size=64)]
    return [base[i % 64] + rng.normal(scale=0.05, size=U.shape) for i in range(n)]


def main() -> None:
    k = ARGS.nodes
    data = synthetic_arrays(300, n_geometries=3, seed=1, nodes=(k - 20, k + 20), dent_width_mm=12.0,
                            material_varies=True, dtype=np.float64)
    tmp = tempfile.mkdtemp(prefix="bench-predict-")
    t0 = time.perf_counter()
    preds = {}
    for name, over in (("pca", {}), ("dae", {"encoder": "dae"}),
                       ("deformed", {"roi_features": "deformed", "state_vector": False,
                                     "occlusion": {"radius_mm": 0.0, "mode": "remove"}})):
        res = train_scenario(data, {**MODEL, **over}, TRAIN, NO_TUNE, "IV", name, out_dir=f"{tmp}/{name}")
        preds[name] = Predictor.load(res["model_path"])
    print(f"trained 3 small models in {time.perf_counter() - t0:.1f} s (ROI ~{k} nodes, grid 12x12)")

    i = 0
    ctx = Preop.from_arrays(data, i)
    U, D = ctx.roi_undeformed_mm, np.asarray(data["roi_deformed_mm"][i])
    frames = stream(U, D, CALLS)
    bench = Bench("serve: raw deformed ROI (k x 3, mm) -> force (N), 1 core", repeats=1, warmup=0)
    summary = {}

    # ---- 1. fast path, single sample
    for name in ("pca", "dae"):
        pred = preds[name]
        t_comp = per_call(lambda _: pred.compile(ctx), [None] * 20, warmup=2)
        bench.record(f"{name}: compile once per exertion point", list(t_comp))
        comp = pred.compile(ctx)
        t = per_call(comp.predict, frames)
        t_pre = per_call(comp.first_stage, frames)
        staged = [(*comp.first_stage(f), f) for f in frames]
        t_net = per_call(lambda a: comp.finish(*a), staged)
        bench.record(f"{name}: fast single (CompiledROI.predict)", list(t), **pct(t))
        bench.record(f"{name}:   preprocessing (affine first stage)", list(t_pre), **pct(t_pre))
        net = "NumPy MLP" + (" + AE encoder" if name == "dae" else "")
        bench.record(f"{name}:   network ({net})", list(t_net), **pct(t_net))
        summary[name] = pct(t)

    # ---- 2. reference path, single sample
    pred = preds["pca"]
    n_ref = max(200, CALLS // 50)
    t_ref = per_call(lambda f: pred.predict(f, ctx), frames[:n_ref], warmup=10)
    arrs = [ctx.to_arrays(f) for f in frames[:n_ref]]
    rep, model = pred.model.representation, pred.model
    t_feat = per_call(rep.features_of, arrs, warmup=10)
    xs = [rep.features_of(a) for a in arrs[:50]]

    def rest(j):
        a = arrs[j % len(arrs)]
        z = model.pre.inputs(xs[j % len(xs)], state_vector(a))
        return model.pre.target_scaler.inverse_transform(model.regressor(torch.as_tensor(z, dtype=torch.float32))
                                                          .detach().double().numpy())
    with torch.no_grad():
        t_rest = per_call(rest, list(range(n_ref)), warmup=10)
    bench.record("pca: reference single (Predictor.predict)", list(t_ref), peer=None, **pct(t_ref))
    bench.record("pca:   preprocessing (features_of: top-sheet grid)", list(t_feat), **pct(t_feat))
    bench.record("pca:   network (scalers + PCA + torch MLP)", list(t_rest), **pct(t_rest))
    bench.results["pca: fast single (CompiledROI.predict)"].peer = "pca: reference single (Predictor.predict)"

    # ---- 3. batch throughput
    Db = np.stack(stream(U, D, BATCH, seed=1))
    for name in ("pca", "dae"):
        comp = preds[name].compile(ctx)
        comp.predict_batch(Db[:100])
        tb = per_call(lambda _: comp.predict_batch(Db), [None] * 5, warmup=1)
        def first(_):
            X = Db.reshape(BATCH, -1) - comp._U_flat
            z = np.empty((BATCH, len(comp.bU)))
            z[:] = comp.bU
            z[:, comp._dyn] += X @ comp._A_dyn.T
            return np.maximum(X.max(axis=1), -X.min(axis=1)), z

        tpre = per_call(first, [None] * 5, warmup=1)
        Z = first(None)[1]
        tnet = per_call(comp._network, [Z] * 5, warmup=1)
        rate = BATCH / np.median(tb)
        bench.record(f"{name}: fast batch of {BATCH}", list(tb), per_s=f"{rate:,.0f}/s")
        bench.record(f"{name}:   preprocessing (displacement, check, first stage)", list(tpre),
                     share=f"{np.median(tpre) / np.median(tb):.0%}")
        bench.record(f"{name}:   network", list(tnet), share=f"{np.median(tnet) / np.median(tb):.0%}")
        summary[f"{name}_batch_per_s"] = rate
    shard = subset(data, np.arange(min(100, len(data["case_id"]))))
    tsh = per_call(lambda _: pred.model.predict(shard), [None] * 3, warmup=0)
    bench.record("pca: reference batch (100 cases, 100 ROIs)", list(tsh),
                 per_s=f"{100 / np.median(tsh):,.0f}/s")

    # ---- 4. unordered cloud, deformed-height model (reference path, per-call Delaunay)
    pdef = preds["deformed"]
    rng = np.random.default_rng(2)
    clouds = [f[rng.permutation(len(f))] for f in frames[:n_ref]]
    t_cloud = per_call(lambda c: pdef.predict_cloud(c, ctx), clouds, warmup=10)
    bench.record("deformed: unordered cloud (predict_cloud)", list(t_cloud), **pct(t_cloud))

    bench.print()
    print()
    for name in ("pca", "dae"):
        s = summary[name]
        ok = "met" if s["p99_us"] <= 1000 else "NOT met"
        print(f"{name}: single p50 {s['p50_us']} us, p99 {s['p99_us']} us over {CALLS} calls -> goal p99 <= 1 ms {ok}; "
              f"batch {summary[name + '_batch_per_s']:,.0f} predictions/s -> goal >= 100,000/s "
              f"{'met' if summary[name + '_batch_per_s'] >= 1e5 else 'NOT met'}")


if __name__ == "__main__":
    with threadpool_limits(limits=1):
        main()
