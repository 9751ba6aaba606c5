"""Benchmark: one marginal-likelihood evaluation (value and gradient) of the GP regressor, and a whole fit.

``liverforce.learn.gp.neg_log_likelihood`` computes the gradient in closed form
(one Cholesky factor and one inverse). The peer is torch autograd through the
same Cholesky-based value (what ``fit_gp`` did before): the same numbers to
round-off, measured side by side on the same rows, for each kernel: the
squared exponential and the rational quadratic (whose shape ``a`` is one more
raw parameter when it is fitted). Sizes are those of the default run's camera
model in scenario IV (about 960 rows of 43 inputs, three outputs). Prints
medians over ``--repeats`` runs, one thread.

    PYTHONPATH=. .venv/bin/python benchmarks/bench_gp_fit.py [--rows 960] [--inputs 43] [--repeats 7]
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch

from liverforce.learn.gp import JITTER, MIN_LENGTH, _shape_kernel, _sq_dist, fit_gp, neg_log_likelihood


def autograd_value_and_grad(X, Y, raw):
    """The peer: the same objective, its gradient by autograd through the Cholesky factor."""
    p = [r.clone().requires_grad_(True) for r in raw]
    n, m = Y.shape
    a = X / (MIN_LENGTH + torch.exp(p[0]))
    shape = torch.exp(p[4]) if len(p) > 4 else math.inf  # the rational quadratic's a, or the squared exponential
    K = torch.exp(2 * p[1]) * _shape_kernel(_sq_dist(a, a), shape) + torch.exp(2 * p[2]) * (X @ X.T)
    K = K + (torch.exp(2 * p[3]) + JITTER) * torch.eye(n, dtype=torch.float64)
    L = torch.linalg.cholesky(K)
    a = torch.cholesky_solve(Y, L)
    v = (0.5 * (Y * a).sum() + m * torch.log(torch.diagonal(L)).sum()) / (n * m) + 0.5 * math.log(2 * math.pi)
    v.backward()
    return float(v.detach()), [q.grad for q in p]


def median_s(fn, repeats: int) -> float:
    fn()
    out = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return float(np.median(out))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=960)
    ap.add_argument("--inputs", type=int, default=43)
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    z = rng.normal(size=(args.rows, args.inputs))
    y = np.stack([np.sin(z[:, 0]) + 0.3 * z[:, 1], z[:, 2] * z[:, 3], np.cos(z[:, 4])], 1)
    y += 0.05 * rng.normal(size=y.shape)
    X, Y = torch.from_numpy(z), torch.from_numpy(y)
    raw = [torch.full((args.inputs,), 1.0, dtype=torch.float64), torch.tensor(0.0, dtype=torch.float64),
           torch.tensor(-2.3, dtype=torch.float64), torch.tensor(-2.3, dtype=torch.float64)]
    print(f"{args.rows} rows x {args.inputs} inputs, 3 outputs, 1 thread, medians of {args.repeats} runs")
    for kernel, extra in (("squared_exponential", []), ("rational_quadratic", [torch.tensor(0.5, dtype=torch.float64)])):
        r = raw + extra
        v_ours, g_ours, _ = neg_log_likelihood(X, Y, *r)
        v_peer, g_peer = autograd_value_and_grad(X, Y, r)
        err = max(float((a - b).abs().max() / b.abs().max().clamp_min(1e-300)) for a, b in zip(g_ours, g_peer))
        print(f"{kernel}: value |diff| {abs(v_ours - v_peer):.1e}; gradient max relative diff {err:.1e}")
        t_ours = median_s(lambda: neg_log_likelihood(X, Y, *r), args.repeats)
        t_peer = median_s(lambda: autograd_value_and_grad(X, Y, r), args.repeats)
        print(f"  one evaluation: closed form {1e3 * t_ours:.1f} ms, autograd (peer) {1e3 * t_peer:.1f} ms: "
              f"{t_peer / t_ours:.2f}x")
    for kernel, shape in (("squared_exponential", None), ("rational_quadratic", 2.0), ("rational_quadratic", None)):
        t_fit = median_s(lambda: fit_gp(z, y, seed=0, kernel=kernel, shape=shape), max(1, args.repeats // 3))
        _, info = fit_gp(z, y, seed=0, kernel=kernel, shape=shape)
        label = kernel if kernel == "squared_exponential" else f"{kernel}, shape {'fitted' if shape is None else shape}"
        print(f"whole fit_gp ({label}): {t_fit:.2f} s ({info['evaluations']} evaluations, "
              f"{t_fit / info['evaluations'] * 1e3:.1f} ms each)")

if __name__ == "__main__":
    main()
