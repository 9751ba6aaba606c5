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

    def unseen(self, res: dict, camera: bool) -> dict:
        """Per-liver metrics of a training result's saved model on the run's unseen livers (scenario V):
        :func:`liverforce.learn.metrics.metrics_by_group` (``mean``, ``sd`` over livers)."""
        from liverforce.learn.metrics import metrics_by_group
        from liverforce.learn.model import ForceModel, eval_seed

        model = ForceModel.load(res["model_path"])
        u = self.arrays("V", camera)
        pred = model.predict(u, observation_seed=eval_seed(int(res["seed"])))
        return metrics_by_group(u["force_n"], pred, u["geometry_id"])
