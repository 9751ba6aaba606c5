"""Experiment: coverage of the calibrated interval on the test livers and on the unseen livers.

Retrains the scenario-IV model of one variant on a finished run's shards with
``train.interval`` (split conformal, calibrated on a training-side split held
out by liver) and prints its half-widths, the coverage per local component
(t1, t2, n) on the IV test livers and on the unseen livers of scenario V,
overall and per liver. The pipeline's validate stage writes the same numbers
for the validated model (``validate/metrics.json`` ``interval``); this script
measures them on existing shards without re-running the pipeline.

    PYTHONPATH=. .venv/bin/python benchmarks/experiment_interval.py --results results/default
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results/default")
    ap.add_argument("--variant", default="pca_sv")
    ap.add_argument("--out-dir", default="/tmp/liverforce-interval-experiment")
    args = ap.parse_args()
    results = Path(args.results)

    from liverforce.config import compose, variant_model
    from liverforce.dataset import io as dio
    from liverforce.learn.train import train_scenario
    from liverforce.pipeline.validate import interval_on_unseen

    cfg = compose([])
    v = {x["name"]: x for x in cfg["train"]["variants"]}[args.variant]
    model = variant_model(cfg["model"], v)
    train = {k: val for k, val in cfg["train"].items() if k != "variants"}
    arrays = dio.load_training_arrays(dio.verify_manifest(results / "shards/IV/manifest.json"))
    unseen = dio.load_training_arrays(dio.verify_manifest(results / "shards/V/manifest.json"))
    t = time.perf_counter()
    res = train_scenario(arrays, model, train, cfg["tune"], "IV", args.variant, out_dir=args.out_dir)
    iv = interval_on_unseen(res["model_path"], unseen)
    print(json.dumps({"interval": res["interval"],
                      "unseen": {k: iv[k] for k in ("coverage", "half_width_mean_n", "n_calibration")},
                      "unseen_per_liver": iv["coverage_per_liver"],
                      "seconds": round(time.perf_counter() - t, 1)}, indent=1))


if __name__ == "__main__":
    main()
