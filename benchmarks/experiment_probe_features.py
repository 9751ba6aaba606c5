"""Experiment: what does the pre-operative stiffness probe give scenario IV and the unseen livers?

Reads a finished run (shards with the ``probe_compliance_mm_per_n`` column) and
trains the scenario-IV model of one variant three ways on the same seeded
splits: without the probe (its 6 state-vector columns held at their mean, so
they carry nothing), with the compliance only (``probe_force_radius_mm: 0``),
and with the compliance and the linear force estimate ``C^-1 u_w`` (the
default), and the default once more with the global shape features (liver
centroid offset, inertia) held at their mean, so only local features vary.
Prints test accuracy/MAE (mean +- sd over ``train.repeats`` splits)
and the MAE on the unseen livers (scenario V) of the first split's model.

    PYTHONPATH=. .venv/bin/python benchmarks/experiment_probe_features.py --results results/default
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results/default")
    ap.add_argument("--variant", default="pca_sv")
    ap.add_argument("--overrides", nargs="*", default=[], help="config overrides (as for snakemake --config)")
    ap.add_argument("--only", nargs="*", help="run only these rows (by name)")
    args = ap.parse_args()
    results = Path(args.results)

    import liverforce.learn.model as M
    from liverforce.config import compose, variant_model
    from liverforce.dataset import io as dio
    from liverforce.learn.train import train_scenario

    cfg = compose(list(args.overrides))
    v = {x["name"]: x for x in cfg["train"]["variants"]}[args.variant]
    model = variant_model(cfg["model"], v)
    train = {k: val for k, val in cfg["train"].items() if k != "variants"}
    arrays = dio.load_training_arrays(dio.verify_manifest(results / "shards/IV/manifest.json"))
    unseen = dio.load_training_arrays(dio.verify_manifest(results / "shards/V/manifest.json"))
    mean_c = np.asarray(arrays["probe_compliance_mm_per_n"]).mean(axis=0)

    def without_probe(a):
        out = dict(a)
        out["probe_compliance_mm_per_n"] = np.tile(mean_c, (len(a["case_id"]), 1))
        return out

    trace = np.mean([np.trace(np.reshape(i, (3, 3))) for i in arrays["inertia_mm5"]])

    def local_only(a):
        """The global shape features held constant: centroid offset 0 (centroid := exertion point) and an
        isotropic inertia of the mean trace (the same in every local frame); only local features vary."""
        out = dict(a)
        n = len(a["case_id"])
        out["liver_centroid_mm"] = np.asarray(a["exertion_point_mm"], float).copy()
        out["inertia_mm5"] = np.tile((trace / 3.0) * np.eye(3).ravel(), (n, 1))
        return out

    runs = (("no probe", without_probe, {"probe_force_radius_mm": 0.0}),
            ("+ compliance", lambda a: a, {"probe_force_radius_mm": 0.0}),
            ("+ C and C^-1 u_w", lambda a: a, {}),
            ("  without global", local_only, {}))
    if args.only:
        runs = tuple(r for r in runs if r[0].strip() in args.only)
    for name, data, over in runs:
        t = time.perf_counter()
        res = train_scenario(data(arrays), {**model, **over}, train, cfg["tune"], "IV", args.variant,
                             out_dir=f"/tmp/probe-exp-{name.replace(' ', '_')}")
        fm = M.ForceModel.load(res["model_path"])
        pred = fm.predict(data(unseen), observation_seed=M.eval_seed(res["seed"]))
        true = np.asarray(unseen["force_n"], float)
        g = np.asarray(unseen["geometry_id"]).astype(str)
        per = [float(np.linalg.norm(pred[g == x] - true[g == x], axis=1).mean()) for x in sorted(set(g))]
        m, s = res["metrics_mean"], res["metrics_sd"]
        print(f"{name:17s} IV test accuracy {m['accuracy_pct']:.1f} +- {s['accuracy_pct']:.1f} %, "
              f"MAE {m['mae_vec']:.3f} +- {s['mae_vec']:.3f} N ({res['n_splits']} splits); "
              f"unseen livers MAE {np.mean(per):.3f} +- {np.std(per, ddof=1):.3f} N over {len(per)} "
              f"(worst {max(per):.3f}); {time.perf_counter() - t:.0f} s", flush=True)


if __name__ == "__main__":
    main()
