"""Experiment: would a flag on how far a case's inputs lie from every training case catch the worst unseen cases?

On a finished run's results (the validated camera model ``models/IV/<variant>/model``, the IV and validation
shards, the meshes), with the evaluation's observation seed:

1. the inputs the GP ensemble reads (``ForceModel.pre.inputs`` of the features and the state vector) of every IV
   training case and every unseen case;
2. per GP member, its columns scaled by its inverse length scales (the space its kernel measures distance in),
   and the distance of each case to the nearest IV training case, the mean over the members. On the training
   side a case's own liver is left out (a new liver there is what an unseen liver is in validation); an unseen
   case is measured against every training case;
3. a flag above the training side's 90 / 95 / 99 % quantile of that distance: how many unseen cases it flags,
   their error against the others', and how many of the errors above ``--big`` N it catches;
4. how well the distance, the GP's own posterior sd and the members' spread (which the interval reads) rank the
   unseen errors (Spearman), and where the worst cases stand by each.

Nothing is refitted; the model is the shipped one. Usage::

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python benchmarks/experiment_input_distance.py --results results/default

Measured on the fresh clone f70 of 03997ed (session 61, AMD EPYC with AVX-512): training side median 0.285,
90 / 95 / 99 % quantiles 0.481 / 0.600 / 1.194; unseen median 0.300. Flag above the 90 %: 21 of 240 unseen cases
(8.8 %), MAE 0.514 N flagged against 0.132 N, 10 of the 15 errors above 0.4 N; above the 95 %: 11 (4.6 %), 0.692
against 0.140 N, 7 of 15; above the 99 %: none. Spearman with the error: the distance 0.63, the GP's posterior
sd 0.60, the members' spread 0.58.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from scipy.stats import spearmanr

from liverforce.learn.frames import case_rotations
from liverforce.learn.gp import GPEnsemble, _kernel, nearest_scaled
from liverforce.learn.model import ForceModel
from liverforce.learn.state import state_vector
from liverforce.pipeline.shared import camera_arrays


def gp_inputs(m: ForceModel, arrays: dict, seed: int) -> np.ndarray:
    """The GP ensemble's inputs of ``arrays``' cases (the path of :meth:`ForceModel.forward`)."""
    rot = case_rotations(arrays)
    x = m.representation.features_of(arrays, observation_seed=seed, R=rot)
    s = state_vector(m.representation.state_arrays(arrays), R=rot) if m.uses_state else None
    return m.pre.inputs(x, s)


def posterior_sd(g, z: np.ndarray) -> np.ndarray:
    """The GP member ``g``'s posterior sd (its kernel with the linear term, noise on the training rows) at ``z``."""
    X = g.X
    K = _kernel(X, X, g.inv_length, g.signal_var, g.linear_var, float(g.shape))
    L = torch.linalg.cholesky(K + float(g.noise_var) * torch.eye(len(X), dtype=torch.float64))
    zt = torch.as_tensor(z, dtype=torch.float64)
    Ks = _kernel(zt, X, g.inv_length, g.signal_var, g.linear_var, float(g.shape))
    kss = torch.diagonal(_kernel(zt, zt, g.inv_length, g.signal_var, g.linear_var, float(g.shape)))
    var = kss - (Ks * torch.cholesky_solve(Ks.T, L).T).sum(1)
    return np.sqrt(np.maximum(var.numpy(), 0.0))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results/default")
    ap.add_argument("--variant", default="cloud_sv")
    ap.add_argument("--big", type=float, default=0.4, help="an error above this (N) is one the flag should catch")
    args = ap.parse_args()
    root = Path(args.results)
    m = ForceModel.load(root / "models" / "IV" / args.variant / "model")
    if not isinstance(m.regressor, GPEnsemble):
        raise SystemExit(f"{args.variant}: the experiment reads a GP ensemble's members; this model's regressor is "
                         f"{type(m.regressor).__name__}")
    seed = int(m.meta.get("eval_observation_seed", 0))
    meshes = sorted(str(p) for p in (root / "mesh").glob("*.vtu"))
    train = camera_arrays(root / "shards" / "IV" / "manifest.json", meshes, "the training side")
    unseen = camera_arrays(root / "shards" / "V" / "manifest.json", meshes, "the unseen livers")
    zt, zv = gp_inputs(m, train, seed), gp_inputs(m, unseen, seed)
    liver = np.asarray(train["geometry_id"]).astype(str)
    fw = m.forward(unseen, seed)
    err = np.linalg.norm(fw.force_source - np.asarray(unseen["force_n"], float), axis=1)
    dt, dv, sd = [], [], []
    for i, g in enumerate(m.regressor.members):
        cols = m.regressor.columns(i).numpy()
        il = g.inv_length.numpy()
        dt.append(nearest_scaled(zt[:, cols] * il, zt[:, cols] * il, groups_a=liver, groups_b=liver))
        dv.append(nearest_scaled(zv[:, cols] * il, zt[:, cols] * il))
        sd.append(posterior_sd(g, zv[:, cols]))
    dt, dv, sd = np.mean(dt, 0), np.mean(dv, 0), np.mean(sd, 0)
    print(f"distance to the nearest training case (scaled GP inputs, mean over {len(m.regressor.members)} members): "
          f"training side (its own liver left out) median {np.median(dt):.3f}, 90 / 95 / 99 % "
          + " / ".join(f"{np.quantile(dt, q):.3f}" for q in (0.9, 0.95, 0.99)) + f"; unseen median {np.median(dv):.3f}")
    big = err > args.big
    for q in (0.9, 0.95, 0.99):
        thr = np.quantile(dt, q)
        f = dv > thr
        flagged = f"{err[f].mean():.3f}" if f.any() else "-"
        print(f"flag above the training side's {q:.0%} ({thr:.3f}): {int(f.sum())} of {len(dv)} unseen cases "
              f"({f.mean():.1%}); MAE flagged {flagged} N, the others {err[~f].mean():.3f} N; errors above "
              f"{args.big:g} N flagged: {int((f & big).sum())} of {int(big.sum())}")
    spread = (np.linalg.norm(fw.spread_local, axis=1) if fw.spread_local is not None
              else np.full(len(err), np.nan))
    measures = {"distance": dv, "GP posterior sd": sd, "members' spread": spread}
    for name, v in measures.items():
        if np.isfinite(v).all():
            top = np.argsort(-v)[:max(1, len(v) // 10)]
            print(f"{name}: Spearman with the error {spearmanr(v, err)[0]:.3f}; errors above {args.big:g} N in its "
                  f"top 10 %: {int(big[top].sum())} of {int(big.sum())}")
    ids = np.asarray(unseen["case_id"]).astype(str)
    geo = np.asarray(unseen["geometry_id"]).astype(str)
    rank = {k: np.argsort(np.argsort(-v)) for k, v in measures.items() if np.isfinite(v).all()}
    print("the worst unseen cases (rank 0: the largest of the measure):")
    for i in np.argsort(-err)[:8]:
        print(f"  {ids[i]} ({geo[i]}): {err[i]:.3f} N off; " + ", ".join(f"{k} rank {r[i]}" for k, r in rank.items()))


if __name__ == "__main__":
    main()
