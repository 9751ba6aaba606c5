"""Predict whole shards or datasets and write the forces (Parquet or CSV, atomically).

Inputs are shard files, folders of shards (``*.parquet``) or ``manifest.json``
files (whose shards are verified against their hashes first). Shards are read
by :mod:`liverforce.dataset.io` (schema version checked); failed simulation
cases are skipped (their ROI carries no deformation) and counted.

Output columns: ``case_id, geometry_id, scenario, fx_n, fy_n, fz_n`` (the
predicted force, liver frame, N), ``half_width_t1_n, half_width_t2_n, half_width_n_n`` (the model's calibrated
interval, :mod:`liverforce.learn.interval`: each local component of the force, ``R F`` with the rows of ``R`` the
case's ``t1, t2, n``, lies in ``+-`` its half-width at the model's nominal coverage; NaN for a refused row, and
every row's NaN for a model without an interval, as a sequence's rows), ``refused`` (why the serving checks
refused the row, in the words ``Predictor.predict_arrays`` and the MLflow pyfunc raise, ``"case <id>: ..."``;
empty when predicted), ``warnings`` (the case's geometric state
outside the training range, a predicted force beyond the training forces; ``"; "``-joined, empty when none) and,
when the shards carry labels,
``fx_true_n, fy_true_n, fz_true_n, error_n`` (``|F̂ − F|``) and, with an interval, ``covered_t1, covered_t2,
covered_n`` (whether the true local component lies within the interval; empty for a refused row); the returned
summary adds the metrics of :func:`liverforce.learn.metrics.force_metrics` over the predicted rows and
``interval_coverage``, the fraction covered per component over them (None without an interval): the
coverage reached on the user's own labelled cases, against the nominal one.

The half-widths are those of the forces shown: the interval reads each row's stiffness factor, the GP
ensemble members' spread (``train.interval.spread``) and, for a scale by the force, the shown force itself
(:meth:`liverforce.learn.interval.ConformalInterval.half_widths`), from one more forward pass of the predicted
rows (:meth:`liverforce.learn.model.ForceModel.forward`; timed apart, ``interval_seconds``); the reference path
(``fast=False``) gives exactly ``ForceModel.predict_interval``'s widths, the compiled path those of its forces
(within ~1e-6 N of the reference's).

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
from liverforce.learn.model import ModelFormatError, subset
from liverforce.serve.errors import PredictionInputError
from liverforce.serve.files import write_frame
from liverforce.serve.sequence import COMPONENTS


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
        rows; the forces alone), ``interval_seconds`` (the half-widths' forward pass), ``out`` and, with labels,
        ``metrics`` (of the predicted rows) and ``interval_coverage`` (``nominal``, ``rows`` and the fraction
        covered per component ``t1``, ``t2``, ``n`` over the predicted rows with a width; None without an
        interval or such a row); the DataFrame itself under ``frame``.
    """
    paths = shard_paths(inputs)
    arrays, skipped = load_shards(paths)
    t0 = time.perf_counter()
    force, warnings, refused = predictor.predict_arrays(arrays, observation_seed=observation_seed, fast=fast,
                                                        return_warnings=True, return_refused=True)
    seconds = time.perf_counter() - t0
    n = len(force)
    ok = np.array([not r for r in refused], dtype=bool)
    t0 = time.perf_counter()
    ci, fw, local, half = interval_of_rows(predictor.model, arrays, force, ok, observation_seed)
    interval_seconds = time.perf_counter() - t0
    cols = {
        "case_id": [str(c) for c in arrays["case_id"]],
        "geometry_id": [str(c) for c in arrays["geometry_id"]],
        "scenario": [str(c) for c in arrays.get("scenario", [""] * n)],
        "fx_n": force[:, 0], "fy_n": force[:, 1], "fz_n": force[:, 2],
        **{f"half_width_{c}_n": half[:, j] for j, c in enumerate(COMPONENTS)},
        "refused": list(refused),  # why the row was refused ("case <id>: ..."); "" when predicted
        # each row's warnings, as Predictor.predict_cloud gives one case's (the context outside the training
        # range, a camera cloud's, a force beyond training's), "; "-joined; "" when none
        "warnings": ["; ".join(w) for w in warnings],
    }
    n_ok = int(ok.sum())
    summary: dict = {"rows": n, "predicted": n_ok, "refused": n - n_ok, "skipped_failed": int(skipped),
                     "shards": [str(p) for p in paths], "seconds": seconds,
                     "predictions_per_s": n_ok / seconds if seconds > 0 else None,
                     "interval_seconds": interval_seconds}
    true = np.asarray(arrays.get("force_n", np.zeros((0, 3))), dtype=np.float64)
    if n and true.shape == (n, 3) and np.isfinite(true).all():
        cols.update({"fx_true_n": true[:, 0], "fy_true_n": true[:, 1], "fz_true_n": true[:, 2],
                     "error_n": np.linalg.norm(force - true, axis=1)})
        if n_ok:
            summary["metrics"] = force_metrics(true[ok], force[ok])
        summary["interval_coverage"] = None
        if ci is not None:
            given = np.zeros((n, 3), dtype=bool)  # a row predicted with a width (a row's spread may be NaN)
            inside = np.zeros((n, 3), dtype=bool)
            if fw is not None:
                given[ok] = np.isfinite(half[ok])
                inside[ok] = np.abs(np.einsum("nij,nj->ni", fw.R, true[ok]) - local) <= half[ok]
            for j, c in enumerate(COMPONENTS):  # missing (pd.NA) for a refused row or a row without a width
                col = pd.array([pd.NA] * n, dtype="boolean")
                col[given[:, j]] = inside[given[:, j], j]
                cols[f"covered_{c}"] = col
            every = given.all(axis=1)
            if every.any():
                summary["interval_coverage"] = {"nominal": float(ci.coverage), "rows": int(every.sum()),
                                                **{c: float(inside[every, j].mean()) for j, c in enumerate(COMPONENTS)}}
    df = pd.DataFrame(cols)
    summary["out"] = None if out_path is None else str(write_frame(df, out_path))
    summary["frame"] = df
    return summary


def interval_of_rows(model, arrays: dict, force: np.ndarray, ok: np.ndarray, observation_seed: int | None = None):
    """The model's calibrated interval of the forces ``force`` ``(n, 3)`` (liver frame) predicted for the rows
    ``ok`` of ``arrays``: ``(interval, forward, force_local, half)``, ``forward`` the
    :class:`~liverforce.learn.model.Forward` of the rows ``ok`` (their rotations, stiffness factors and members'
    spread), ``force_local`` ``(n_ok, 3)`` the shown forces in their local frames and ``half`` ``(n, 3)`` N the
    half-widths (NaN for the other rows; every row's for a model without an interval, then ``interval`` None).
    ``forward`` and ``force_local`` are None when no row was predicted. The widths are those of the shown forces
    (a scale by the force reads ``|F|``), not of ``forward``'s own. ``arrays``: as ``Predictor.predict_arrays``
    read them (node displacements; a shard carries no camera clouds, which a camera model's refinement moves).
    An interval that cannot be read (:attr:`~liverforce.learn.model.ForceModel.interval`'s
    :class:`~liverforce.learn.model.ModelFormatError`) is refused as a :class:`PredictionInputError`, as
    ``Predictor.from_dir`` refuses a bundle."""
    half = np.full((len(force), 3), np.nan)
    try:
        ci = model.interval
    except ModelFormatError as exc:  # an interval no path can give (a bundle edited by hand): as a model's load
        raise PredictionInputError(f"model: {exc}") from exc
    rows = np.flatnonzero(ok)
    if ci is None or not len(rows):
        return ci, None, None, half
    fw = model.forward(arrays if len(rows) == len(force) else subset(arrays, rows), observation_seed)
    local = np.einsum("nij,nj->ni", fw.R, force[rows])
    half[rows] = ci.half_widths(fw.stiffness, local, fw.spread_local, fw.input_distance)
    return ci, fw, local, half

