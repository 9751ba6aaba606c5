"""What the learning experiments share: the pipeline's training settings and a finished run's shards.

``benchmarks/experiment_*.py`` train through the pipeline's own
:func:`liverforce.learn.train.train_scenario` with the pipeline's seed, so a row
with the default config repeats the run's own figures.
"""

from __future__ import annotations

from pathlib import Path


class PipelineTraining:
    """The default config's training settings (no interval, no held-out points) and a run's arrays, loaded once."""

    def __init__(self, results: str | Path, label: str):
        from liverforce.config import compose
        from liverforce.learn.torchutil import configure_torch
        from liverforce.pipeline.plan import Plan

        configure_torch(1)
        self.cfg = compose([])
        plan = Plan(self.cfg)
        self.seed = plan.train_seed()
        self.train = {k: v for k, v in self.cfg["train"].items() if k != "variants"}
        self.train.update(interval=None, heldout_points=None)
        self.variants = plan.variants()
        self.results = Path(results)
        self.label = label
        self._loaded: dict = {}

    def arrays(self, scenario: str, camera: bool) -> dict:
        from liverforce.pipeline.shared import run_arrays

        if (scenario, camera) not in self._loaded:
            self._loaded[(scenario, camera)] = run_arrays(self.results, scenario, camera, self.label)
        return self._loaded[(scenario, camera)]

    def unseen(self, res: dict, camera: bool, observation: dict | None = None) -> dict:
        """Per-liver metrics of a training result's saved model on the run's unseen livers (scenario V):
        :func:`liverforce.learn.metrics.metrics_by_group` (``mean``, ``sd`` over livers). ``observation``: a
        camera model re-observed with these observation settings over its own, nothing refitted."""
        from liverforce.config import merge_mapping
        from liverforce.learn.metrics import metrics_by_group
        from liverforce.learn.model import ForceModel, eval_seed

        model = ForceModel.load(res["model_path"])
        if observation:
            cam = model.representation.camera
            model = model.observed_with({**cam, "observation": merge_mapping(cam.get("observation") or {},
                                                                             observation)})
        u = self.arrays("V", camera)
        pred = model.predict(u, observation_seed=eval_seed(int(res["seed"])))
        return metrics_by_group(u["force_n"], pred, u["geometry_id"])

    def score(self, model_cfg: dict, scenario: str, name: str, label: str, out: str, cv_splits: int,
              observe: list | None = None) -> str:
        """Train ``model_cfg`` as the pipeline does and return one line: the training-side CV MAE (4 folds by
        liver, ``cv_mae_n``) on ``cv_splits`` seeded splits (the main split, then the repeats' split seeds, each
        trained as its own run; what a default is chosen on; 0: not reported), the test accuracy per split over
        ``train.repeats``, the main split's test MAE per local component (:func:`local_test_mae`), and for IV the
        unseen livers' MAE (the saved model: with ``train.final_fit``, refitted on every case of the scenario), for
        a camera model also re-observed with each ``(label, observation settings)`` of ``observe``."""
        import time

        import numpy as np

        from liverforce.learn.train import train_scenario
        from liverforce.seeds import derive

        camera = model_cfg.get("roi_features") == "cloud"
        arrays = self.arrays(scenario, camera)
        t = time.perf_counter()
        res = train_scenario(arrays, model_cfg, self.train, self.cfg["tune"], scenario, name, seed=self.seed,
                             out_dir=out)
        line = f"{name:8s} {scenario:3s} {label:24s}"
        if cv_splits > 0:
            cv = [res["cv_mae_n"]]
            for r in range(1, cv_splits):
                got = train_scenario(arrays, model_cfg, {**self.train, "repeats": 1}, self.cfg["tune"], scenario,
                                     name, seed=derive(self.seed, "split.repeat", r), out_dir=f"{out}-cv{r}")
                cv.append(got["cv_mae_n"])
            line += f" CV MAE {np.mean(cv):.4f} N ({len(cv)} splits: {' '.join(f'{c:.4f}' for c in cv)}) |"
        m, s = res["metrics_mean"], res["metrics_sd"]
        per_split = [x["metrics"]["accuracy_pct"] for x in res["repeats"]]  # the main split first
        local = ' / '.join(f'{e:.4f}' for e in local_test_mae(f"{out}/test_predictions.csv", arrays))
        line += (f" test {m['accuracy_pct']:6.2f} +- {s['accuracy_pct']:.2f} % (splits "
                 f"{' '.join(f'{a:.1f}' for a in per_split)}), MAE {m['mae_vec']:.4f} +- {s['mae_vec']:.4f} N, "
                 f"main split t1 / t2 / n {local} N")
        if scenario == "IV":
            g = self.unseen(res, camera)
            line += f" | unseen MAE {g['mean']['mae_vec']:.4f} +- {g['sd']['mae_vec']:.4f} N"
            for text, obs in (observe or []) if camera else []:
                g = self.unseen(res, camera, obs)
                line += f" | unseen, {text}: {g['mean']['mae_vec']:.4f} +- {g['sd']['mae_vec']:.4f} N"
        return f"{line} | {time.perf_counter() - t:.0f} s"


def local_test_mae(predictions_csv, arrays: dict):
    """MAE per local force component ``(t1, t2, n)`` N of a training run's ``test_predictions.csv`` (source-frame
    forces, true and predicted, by ``case_id``), each case in its own local frame from ``arrays``: what the
    vector MAE hides, the normal component against the tangential ones, mean over the cases (``component_mae``
    of ``benchmarks/experiment_camera_loss.py``, which gives the same split for the shipped models)."""
    import numpy as np
    import pandas as pd

    from benchmarks.experiment_camera_loss import component_mae
    from liverforce.learn.frames import case_rotations, force_to_local

    d = pd.read_csv(predictions_csv)
    row = {str(c): i for i, c in enumerate(arrays["case_id"])}
    missing = [c for c in d["case_id"].astype(str) if c not in row]
    if missing:
        raise ValueError(f"{predictions_csv}: {len(missing)} case ids not in the arrays (e.g. {missing[0]})")
    R = case_rotations(arrays)[[row[c] for c in d["case_id"].astype(str)]]
    true = force_to_local(d[["fx_true_n", "fy_true_n", "fz_true_n"]].to_numpy(np.float64), R)
    pred = force_to_local(d[["fx_pred_n", "fy_pred_n", "fz_pred_n"]].to_numpy(np.float64), R)
    return component_mae(true, pred, np.zeros(len(d)))[:3]  # one group: the mean over the cases
