"""Predict whole shards or datasets and write the forces (Parquet or CSV, atomically).

Inputs are shard files, folders of shards (``*.parquet``) or ``manifest.json``
files (whose shards are verified against their hashes first). Shards are read
by :mod:`liverforce.dataset.io` (schema version checked); failed simulation
cases are skipped (their ROI carries no deformation) and counted.

Output columns: ``case_id, geometry_id, scenario, fx_n, fy_n, fz_n`` (the
predicted force, liver frame, N), ``refused`` (why the serving checks refused the row, in the words
``Predictor.predict_arrays`` and the MLflow pyfunc raise, ``"case <id>: ..."``; empty when predicted),
``warnings`` (the case's geometric state
outside the training range, a predicted force beyond the training forces; ``"; "``-joined, empty when none) and,
when the shards carry labels,
``fx_true_n, fy_true_n, fz_true_n, error_n`` (``|F̂ − F|``); the returned
summary adds the metrics of :func:`liverforce.learn.metrics.force_metrics` over the predicted rows.

A refused row does not stop the batch: its forces (and ``error_n``) are NaN, its reason is in ``refused``, and
the other rows are predicted (``Predictor.predict_arrays(return_refused=True)``; the compiled and the reference
path refuse the same rows in the same words), as a recorded sequence's refused clouds are
(:mod:`liverforce.serve.sequence`). The summary counts them.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd

from liverforce.layout import shards_in
from liverforce.learn.metrics import force_metrics
from liverforce.serve.errors import PredictionInputError
from liverforce.serve.files import write_frame


def shard_paths(inputs: Sequence[str | Path]) -> list[Path]:
    """Expand files, folders and manifests into shard paths (sorted within a folder)."""
    from liverforce.dataset import io as dio

    out: list[Path] = []
    for item in inputs:
        p = Path(item)
        if p.is_dir():
            found = shards_in(p) or sorted(p.glob("*.parquet"))
            if not found:
                raise PredictionInputError(f"{p}: no Parquet shards in this folder")
            out += found
        elif p.name.endswith(".json"):
            try:
                out += dio.verify_manifest(p)
            except (dio.ShardError, OSError, KeyError, ValueError) as exc:
                raise PredictionInputError(f"{p}: {exc}") from exc
        elif p.is_file():
            out.append(p)
        else:
            raise PredictionInputError(f"{p}: no such shard, folder or manifest")
    return out


def load_shards(paths: Sequence[Path]) -> tuple[dict, int]:
    """Input-contract arrays of the converged cases and the number of failed cases skipped."""
    from liverforce.dataset import io as dio

    try:
        arrays = dio.load_training_arrays(paths, converged_only=True)
        total = sum(dio.read_table(p, columns=["converged"]).num_rows for p in paths)
    except dio.ShardError as exc:
        raise PredictionInputError(str(exc)) from exc
    return arrays, total - len(arrays["case_id"])


def predict_shards(predictor, inputs: Sequence[str | Path], out_path: str | Path | None = None, *,
                   observation_seed: int | None = None, fast: bool = True) -> dict:
    """Predict every converged case of the given shards; write ``out_path`` (``.parquet``/``.csv``) if given.

    Parameters
    ----------
    predictor : liverforce.serve.Predictor
    inputs : sequence of paths
        Shards, folders of shards, or manifests.
    out_path : path, optional
        Result file, written atomically.
    observation_seed : int, optional
        Reproduce the evaluation's stochastic observation model (simulated data).
    fast : bool
        Rows sharing a context go through the compiled path (equal to the
        reference to ~1e-6 N).

    Returns
    -------
    dict
        ``rows``, ``predicted``, ``refused`` (rows refused by the serving checks: NaN forces, the reason in
        the ``refused`` column), ``skipped_failed``, ``shards``, ``seconds``, ``predictions_per_s`` (predicted
        rows), ``out`` and, with labels, ``metrics`` (of the predicted rows); the DataFrame itself under
        ``frame``.
    """
    paths = shard_paths(inputs)
    arrays, skipped = load_shards(paths)
    t0 = time.perf_counter()
    force, warnings, refused = predictor.predict_arrays(arrays, observation_seed=observation_seed, fast=fast,
                                                        return_warnings=True, return_refused=True)
    seconds = time.perf_counter() - t0
    n = len(force)
    ok = np.array([not r for r in refused], dtype=bool)
    cols = {
        "case_id": [str(c) for c in arrays["case_id"]],
        "geometry_id": [str(c) for c in arrays["geometry_id"]],
        "scenario": [str(c) for c in arrays.get("scenario", [""] * n)],
        "fx_n": force[:, 0], "fy_n": force[:, 1], "fz_n": force[:, 2],
        "refused": list(refused),  # why the row was refused ("case <id>: ..."); "" when predicted
        # each row's warnings, as Predictor.predict_cloud gives one case's (the context outside the training
        # range, a camera cloud's, a force beyond training's), "; "-joined; "" when none
        "warnings": ["; ".join(w) for w in warnings],
    }
    n_ok = int(ok.sum())
    summary: dict = {"rows": n, "predicted": n_ok, "refused": n - n_ok, "skipped_failed": int(skipped),
                     "shards": [str(p) for p in paths], "seconds": seconds,
                     "predictions_per_s": n_ok / seconds if seconds > 0 else None}
    true = np.asarray(arrays.get("force_n", np.zeros((0, 3))), dtype=np.float64)
    if n and true.shape == (n, 3) and np.isfinite(true).all():
        cols.update({"fx_true_n": true[:, 0], "fy_true_n": true[:, 1], "fz_true_n": true[:, 2],
                     "error_n": np.linalg.norm(force - true, axis=1)})
        if n_ok:
            summary["metrics"] = force_metrics(true[ok], force[ok])
    df = pd.DataFrame(cols)
    summary["out"] = None if out_path is None else str(write_frame(df, out_path))
    summary["frame"] = df
    return summary
