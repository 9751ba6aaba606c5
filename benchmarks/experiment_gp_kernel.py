"""Experiment: the GP regressor's kernel (``model.gp.kernel``, ``model.gp.shape``), chosen on training livers only.

For each kernel setting and variant, on a finished run's shards (``--results``):

- **training-side CV MAE**: the 4-fold CV by liver inside the training livers
  (``cv_mae_n``, what ``validate.variant: auto`` reads), on ``--cv-splits``
  seeded splits (the pipeline's split seeds: the main split, then those of
  ``train.repeats``), each split trained as its own run. This is what the
  default was chosen on: no test liver enters it.
- **test accuracy** over the pipeline's ``train.repeats`` seeded splits
  (:func:`liverforce.learn.train.train_scenario` with the pipeline's seed, so
  the default's row repeats the run's own figures), per split, and for IV
- **the unseen livers' MAE** (mean +- sd over livers; the main split's model).

::

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python benchmarks/experiment_gp_kernel.py --results results/default \\
        --variants pca_sv --kernels squared_exponential rational_quadratic:fit rational_quadratic:1 rational_quadratic:2

A kernel is ``squared_exponential`` or ``rational_quadratic:A`` (``A`` the fixed shape ``a``, or ``fit``: fitted
by the marginal likelihood).
"""

from __future__ import annotations

import argparse


def parse_kernel(text: str) -> dict:
    name, _, shape = text.partition(":")
    if name == "squared_exponential":
        return {"kernel": name, "shape": None}
    if name != "rational_quadratic":
        raise SystemExit(f"--kernels: unknown '{text}' (squared_exponential or rational_quadratic:A|fit)")
    return {"kernel": name, "shape": None if shape in ("", "fit") else float(shape)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results/default")
    ap.add_argument("--variants", nargs="*", default=["pca_sv"])
    ap.add_argument("--scenario", default="IV")
    ap.add_argument("--kernels", nargs="*", default=["squared_exponential", "rational_quadratic:2"])
    ap.add_argument("--cv-splits", type=int, default=5, help="seeded splits the training-side CV MAE is averaged over")
    ap.add_argument("--out", default="/tmp/liverforce-experiment-gp-kernel")
    args = ap.parse_args()

    from benchmarks.experiment import PipelineTraining

    run = PipelineTraining(args.results, "GP kernel experiment")
    for name in args.variants:
        v = dict(run.variants[name])
        if v.get("regressor") != "gp":
            raise SystemExit(f"variant {name} does not use the GP regressor")
        for text in args.kernels:
            model_cfg = {**v, "gp": {**v["gp"], **parse_kernel(text)}}
            out = f"{args.out}/{name}-{args.scenario}-{text.replace(':', '-')}"
            print(run.score(model_cfg, args.scenario, name, text, out, args.cv_splits), flush=True)


if __name__ == "__main__":
    main()
