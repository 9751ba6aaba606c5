"""Benchmark: the GP's NumPy serving head (``GPRegressor.numpy_head``) per kernel and shape path.

The compiled serving paths evaluate, per cloud and GP member, one kernel row against every training row.
The squared exponential costs one ``exp`` per kernel value; the rational quadratic ``exp(-a log1p(t))``, one
``log1p`` more; for a whole shape up to ``POW_SHAPE_MAX_HEAD`` (the default a = 2) the head computes
``1 / (1 + t)^a`` by products and a reciprocal instead. This times them on the same rows, side by side in
the same run (the rational quadratic through exp and log1p is the peer: the path the whole shape took
before), and checks that the rational-quadratic paths give the same outputs. Since session 42 the products
are fused with the product by the weights in one compiled pass (``gp._rq_power_mean``); the NumPy passes it
replaced (scale, shift, square, reciprocal, product: ``_numpy_passes`` here) are timed beside it. Sizes are
the shipped camera model's: 2,000 training rows, blocks of 128 feature rows (``compiled_cloud._HEAD_ROWS``).
Prints medians over ``--repeats`` runs, in microseconds per feature row (one cloud), one thread.

Measured (session 42, 1 thread, nothing else running, medians of 9): exp and log1p 21.72 us per row, squared
exponential 12.16, five NumPy passes 10.44, fused 7.37 (2.95x the peer, 1.42x the passes).

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_gp_head.py [--inputs 62] [--repeats 9]
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch

from liverforce.learn import gp as gp_module
from liverforce.learn.gp import GPRegressor


def _head(X, alpha, inv_l, shape: float, products: bool):
    gp = GPRegressor(X, alpha, inv_l, torch.tensor(1.0), torch.tensor(0.01), torch.tensor(1e-4), shape)
    keep = gp_module.POW_SHAPE_MAX_HEAD
    gp_module.POW_SHAPE_MAX_HEAD = keep if products else 0  # 0: the whole shape through exp and log1p
    try:
        return gp.numpy_head()
    finally:
        gp_module.POW_SHAPE_MAX_HEAD = keep


def _numpy_passes(X, alpha, inv_l, a: int):
    """The products path as five NumPy passes over the kernel matrix (the head of sessions 36-41), on the same
    scaled inputs and weights: the peer of the fused pass."""
    Xs = (X * inv_l).numpy()
    XaT = np.vstack([Xs.T, np.ones(len(Xs)), -0.5 * np.einsum("ij,ij->i", Xs, Xs)])
    inv = inv_l.numpy()
    alpha_np = alpha.numpy()
    beta = 0.01 * (X.numpy().T @ alpha_np)  # linear_var of _head

    def head(Z):
        Za = np.empty((len(Z), Z.shape[1] + 2))
        np.multiply(Z, inv, out=Za[:, :-2])
        Za[:, -2] = -0.5 * np.einsum("ij,ij->i", Za[:, :-2], Za[:, :-2])
        Za[:, -1] = 1.0
        E = Za @ XaT
        E *= -1.0 / a
        E += 1.0
        for _ in range(a // 2):
            np.square(E, out=E)
        np.reciprocal(E, out=E)
        return E @ alpha_np + Z @ beta

    return head


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=2000, help="training rows")
    ap.add_argument("--inputs", type=int, default=62, help="inputs of the member (the shipped 62 for code 32)")
    ap.add_argument("--block", type=int, default=128, help="feature rows per head call")
    ap.add_argument("--calls", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=9)
    args = ap.parse_args()
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    X = torch.from_numpy(rng.normal(size=(args.rows, args.inputs)))
    alpha = torch.from_numpy(rng.normal(size=(args.rows, 3)))
    inv_l = torch.from_numpy(rng.uniform(0.05, 0.3, args.inputs))
    Z = rng.normal(size=(args.block, args.inputs))
    heads = {"squared exponential (exp)": _head(X, alpha, inv_l, math.inf, True),
             "rational quadratic a = 2, exp and log1p (peer)": _head(X, alpha, inv_l, 2.0, False),
             "rational quadratic a = 2, products, 5 NumPy passes": _numpy_passes(X, alpha, inv_l, 2),
             "rational quadratic a = 2, products, fused": _head(X, alpha, inv_l, 2.0, True)}
    a = heads["rational quadratic a = 2, exp and log1p (peer)"](Z)
    b = heads["rational quadratic a = 2, products, fused"](Z)
    c = heads["rational quadratic a = 2, products, 5 NumPy passes"](Z)
    print(f"head: {args.rows} training rows x {args.inputs} inputs, blocks of {args.block} rows, 1 thread, "
          f"medians of {args.repeats} runs of {args.calls} calls; rational quadratic paths agree to "
          f"{max(np.abs(a - b).max(), np.abs(c - b).max()) / np.abs(a).max():.1e} (relative)")
    times = {k: [] for k in heads}
    for _ in range(args.repeats):
        for name, h in heads.items():  # interleaved, so a noisy neighbour hits every path alike
            t = time.perf_counter()
            for _ in range(args.calls):
                h(Z)
            times[name].append((time.perf_counter() - t) / (args.calls * args.block) * 1e6)
    peer = float(np.median(times["rational quadratic a = 2, exp and log1p (peer)"]))
    for name, ts in times.items():
        m = float(np.median(ts))
        print(f"  {name:52s} {m:6.2f} us per row ({peer / m:.2f}x the peer)")


if __name__ == "__main__":
    main()
