"""Experiment: the MLP against the Gaussian process as the force regressor, on the same seeded splits.

Reads a finished run's scenario-IV and unseen-liver shards (``--results``) and
trains each variant's scenario-IV model once per regressor through the
pipeline's own training (:func:`liverforce.learn.train.train_scenario`: the
MLP tuned by Ax, the GP by its marginal likelihood; ``train.repeats`` seeded
splits by liver, the cross-conformal interval), then scores each on the unseen
livers (scenario V). Prints, per variant and regressor: IV test accuracy and
MAE (mean +- sd over the splits), the training-side cross-validation MAE the
variant choice reads (``cv_mae_n``), the unseen livers' MAE (mean +- sd over
livers, the worst), the relative MAE per force bin, the 90 % interval's
coverage per component on the unseen livers, and the training time.

``--peer`` also fits BoTorch's ``SingleTaskGP`` (GPyTorch, Matern-5/2 ARD,
its default priors) on the first split's regressor inputs of ``pca_sv`` and
prints its IV-test and unseen MAE and fit time beside ours on the same inputs.

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python benchmarks/experiment_regressor.py --results results/default
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

BINS = (0.0, 1.0, 2.0, 3.0, 4.0, np.inf)


def unseen_scores(model, unseen: dict, seed: int) -> dict:
    from liverforce.learn.frames import force_to_local
    from liverforce.learn.interval import coverage_per_component
    from liverforce.learn.model import eval_seed

    got = model.predict_interval(unseen, observation_seed=eval_seed(seed))
    true = np.asarray(unseen["force_n"], float)
    err = np.linalg.norm(got["force_n"] - true, axis=1)
    g = np.asarray(unseen["geometry_id"]).astype(str)
    per = {x: float(err[g == x].mean()) for x in sorted(set(g))}
    mag = np.linalg.norm(true, axis=1)
    rel = []
    for lo, hi in zip(BINS[:-1], BINS[1:]):
        b = (mag >= lo) & (mag < hi)
        if b.any():
            rel.append(float(err[b].mean() / mag[b].mean()))
    cover = coverage_per_component(force_to_local(true, got["frame"]), got["force_local_n"], got["half_width_local_n"])
    return {"per_liver": per, "rel_bins": rel, "coverage": cover}


def peer(results: Path, arrays: dict, unseen: dict, cfg: dict) -> None:
    """BoTorch's SingleTaskGP against liverforce.learn.gp on the first split's regressor inputs of pca_sv."""
    import torch
    from botorch.fit import fit_gpytorch_mll
    from botorch.models import SingleTaskGP
    from botorch.models.transforms import Normalize, Standardize
    from gpytorch.mlls import ExactMarginalLogLikelihood

    from liverforce.learn.gp import fit_gp
    from liverforce.learn.model import ForceModel, eval_seed, prepare, subset

    model = ForceModel.load(results)
    pre, rep, seed = model.pre, model.representation, int(model.meta["seed"])
    test_ids = set(model.meta["test_case_ids"])
    te = np.array([str(c) in test_ids for c in arrays["case_id"]])

    def zy(a, seeds):
        p = prepare(a, rep, observation_seeds=seeds)
        z = pre.inputs(p.x_obs[0], p.state)
        return z, p.y_local, pre.stiffness(p.state, len(z))

    z_tr, y_tr, k_tr = zy(subset(arrays, np.flatnonzero(~te)), [seed])
    z_te, y_te, k_te = zy(subset(arrays, np.flatnonzero(te)), [eval_seed(seed)])
    z_v, y_v, k_v = zy(unseen, [eval_seed(seed)])
    ts = pre.target_scaler
    target = ts.transform(y_tr / k_tr)

    def mae(p, y, k):
        return float(np.linalg.norm(ts.inverse_transform(p) * k - y, axis=1).mean())

    t = time.perf_counter()
    hp = model.meta.get("hyper_parameters") or {}  # the model's own GP settings (its kernel and shape)
    gp, _ = fit_gp(z_tr, target, seed=seed, kernel=hp.get("kernel", "rational_quadratic"), shape=hp.get("shape", 2.0),
                   per_output=bool(hp.get("per_output", False)), noise_floor=float(hp.get("noise_floor", 0.0)))
    ours = time.perf_counter() - t
    head = gp.numpy_head()
    print(f"  liverforce.learn.gp  fit {ours:6.1f} s   IV test MAE {mae(head(z_te), y_te, k_te):.3f} N   "
          f"unseen {mae(head(z_v), y_v, k_v):.3f} N", flush=True)
    torch.manual_seed(seed)
    X = torch.tensor(z_tr, dtype=torch.float64)
    t = time.perf_counter()
    st = SingleTaskGP(X, torch.tensor(target, dtype=torch.float64), input_transform=Normalize(X.shape[1]),
                      outcome_transform=Standardize(3))
    fit_gpytorch_mll(ExactMarginalLogLikelihood(st.likelihood, st))
    theirs = time.perf_counter() - t
    st.eval()
    with torch.no_grad():
        pt = st.posterior(torch.tensor(z_te)).mean.numpy()
        pv = st.posterior(torch.tensor(z_v)).mean.numpy()
    print(f"  botorch SingleTaskGP fit {theirs:6.1f} s   IV test MAE {mae(pt, y_te, k_te):.3f} N   "
          f"unseen {mae(pv, y_v, k_v):.3f} N   ({theirs / ours:.1f}x our fit time)", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results/default")
    ap.add_argument("--variants", nargs="*", default=["pca_sv", "cloud_sv"])
    ap.add_argument("--regressors", nargs="*", default=["mlp", "gp"])
    ap.add_argument("--overrides", nargs="*", default=[], help="config overrides (as for snakemake --config)")
    ap.add_argument("--out", default="/tmp/liverforce-experiment-regressor")
    ap.add_argument("--peer", action="store_true", help="also fit BoTorch's SingleTaskGP on the same inputs")
    args = ap.parse_args()
    results = Path(args.results)

    from liverforce.config import compose, variant_model
    from liverforce.pipeline.shared import run_arrays
    from liverforce.learn.model import ForceModel
    from liverforce.learn.torchutil import configure_torch
    from liverforce.learn.train import train_scenario

    configure_torch(1)
    cfg = compose(list(args.overrides))
    train = {k: v for k, v in cfg["train"].items() if k != "variants"}
    if args.peer:  # the peer is scored on the main split's held-out livers: save that split's model, not a final fit
        train["final_fit"] = False
    variants = {x["name"]: x for x in cfg["train"]["variants"]}
    loaded: dict = {}

    def load(scenario: str, camera: bool) -> dict:
        key = (scenario, camera)
        if key not in loaded:
            loaded[key] = run_arrays(results, scenario, camera, "regressor experiment")
        return loaded[key]

    for name in args.variants:
        v = variants[name]
        camera = str(v.get("roi_features", cfg["model"].get("roi_features"))) == "cloud"
        arrays, unseen = load("IV", camera), load("V", camera)
        for reg in args.regressors:
            model_cfg = {**variant_model(cfg["model"], v), "regressor": reg}
            t = time.perf_counter()
            res = train_scenario(arrays, model_cfg, train, cfg["tune"], "IV", name,
                                 out_dir=f"{args.out}/{name}-{reg}")
            seconds = time.perf_counter() - t
            model = ForceModel.load(res["model_path"])
            u = unseen_scores(model, unseen, int(res["seed"]))
            per = list(u["per_liver"].values())
            worst = max(u["per_liver"], key=u["per_liver"].get)
            m, s = res["metrics_mean"], res["metrics_sd"]
            cover = " / ".join(f"{100 * c:.1f}" for c in u["coverage"])
            print(f"{name:9s} {reg:4s} IV test {m['accuracy_pct']:.1f} +- {s['accuracy_pct']:.1f} %, MAE "
                  f"{m['mae_vec']:.3f} +- {s['mae_vec']:.3f} N ({res['n_splits']} splits), cv_mae_n "
                  f"{res.get('cv_mae_n') or float('nan'):.3f} N | unseen MAE {np.mean(per):.3f} +- "
                  f"{np.std(per, ddof=1):.3f} N over {len(per)} livers (worst {worst} {u['per_liver'][worst]:.3f}), "
                  f"rel MAE per bin {' / '.join(f'{100 * r:.1f}' for r in u['rel_bins'])} %, "
                  f"interval coverage {cover} % | {seconds:.0f} s", flush=True)
            if args.peer and name == "pca_sv" and reg == "gp":
                peer(Path(res["model_path"]), arrays, unseen, cfg)


if __name__ == "__main__":
    main()
