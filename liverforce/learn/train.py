"""Train one (scenario, variant): split, representation, CV + Ax tuning, final fit, test metrics.

Steps (every fitted quantity sees the training split only):

1. held-out test split (by case; by geometry for scenario IV) — never seen by
   tuning (:mod:`.splits`);
2. representation fitted on the training cases (grid extent), features with
   the observation model (:mod:`.representation`). The grid extent (a median
   of ROI sizes, no labels) is shared by the CV folds; scalers and encoders
   are refitted per fold;
3. if ``tune.enabled`` or ``model.regressor: gp``: k-fold CV folds inside the
   training split; per fold the scalers + encoder are fitted on the fold's
   training part once. For the MLP, Ax proposes regressor hyper-parameters
   scored by CV MSE (:mod:`.tune`); the GP has none to search (its kernel's
   are its marginal likelihood's, :mod:`.gp`). Either way the folds give the
   CV MAE in newtons (``cv_mae_n``) that ``validate.variant: auto`` reads.
   Without tuning an MLP uses the configured hyper-parameters;
4. the best configuration is refitted on the whole training split
   (``train.epochs``) and evaluated on the test split in the source frame
   (:mod:`.metrics`), the stochastic observation model drawn with
   :func:`~liverforce.learn.model.eval_seed` (stored in the model). The
   per-epoch ``test_loss`` of this final fit is logged for monitoring only:
   no choice (epochs, parameters) is made from it;
5. uncertainty: with ``train.repeats = R > 1`` the same configuration is
   refitted on ``R - 1`` further seeded splits (``seed + r``; other test
   cases, for IV other test livers) and scored on each split's own test set.
   ``metrics_mean`` / ``metrics_sd`` summarise the ``R`` splits (the first is
   the main split's). The hyper-parameters tuned on the first split's training
   side are reused: the repeats measure the spread due to the split, not a
   fresh tuning. A camera-cloud model is also scored on each split's test set
   with an exact tool tip (the same model and clouds, no kinematics noise:
   ``exact_tip``), which separates what the tracker's error costs from what
   the cloud does;
6. with ``train.final_fit`` (the default config's setting) the saved model is not the main split's: the
   same configuration is refitted on every case of the scenario, test split included (:func:`fit_final`),
   and its interval calibrated on all of them. The splits measure the configuration; the served model
   then sees all the data (in IV all the livers; the validation's unseen livers are still never seen).
   Without it the main split's model is saved;
7. outputs: ``out_dir/model/`` (bundle), ``out_dir/figures/*.png``,
   ``out_dir/test_predictions.csv`` (atomic), ``out_dir/interval_calibration.npz``
   (the calibration predictions of the interval, atomic) and the result dict, which the
   caller writes to ``metrics.json`` (:mod:`liverforce.pipeline.train`, its only writer). What an
   earlier run wrote there is removed first (:func:`clear_outputs`): an interrupted run leaves no
   file of the old model beside the new one's;
   with a ``tracker`` everything is also logged (parent run per scenario +
   variant, one nested run per Ax trial). The tracker is duck-typed (see
   :class:`liverforce.tracking.Tracker`); this module never imports mlflow.
"""

from __future__ import annotations

import io
import logging
import re
import shutil
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from liverforce.atomic import remove_stale_temps, write_bytes_atomic, write_text_atomic
from liverforce.config import config_hash
from liverforce.learn.camera import exact_tip, tips_off_grid
from liverforce.learn.interval import coverage_per_component, fit_conformal
from liverforce.learn.metrics import force_metrics
from liverforce.learn.model import (
    PER_RUN_KEYS,
    ForceModel,
    encoder_code_size,
    eval_seed,
    fit_force_model,
    fit_preprocessor,
    member_columns,
    n_views_for,
    outside_training_range,
    prepare,
    regressor_data,
    state_options,
    subset,
    training_distances,
    view_groups,
    view_seeds,
)
from liverforce.learn.plots import evaluation_figures
from liverforce.learn.provenance import ARTIFACT as PROVENANCE_ARTIFACT
from liverforce.learn.provenance import provenance_params, provenance_tags
from liverforce.learn.regressor import fit_params, gp_code_members
from liverforce.learn.representation import representation_from_config
from liverforce.learn.splits import cv_folds, group_key, train_test_split
from liverforce.learn.torchutil import configure_torch
from liverforce.learn.tune import FoldData, cv_force_mae, cv_score, tune
from liverforce.pipeline.job import run_status
from liverforce.seeds import derive

log = logging.getLogger("liverforce")

#: what :func:`train_scenario` writes in ``out_dir``, by name (step 7; the caller writes ``metrics.json``): the
#: bundle folder, the figures folder and its files (:func:`~liverforce.learn.plots.evaluation_figures`' names),
#: the files beside the bundle (:func:`clear_outputs` removes an earlier run's)
MODEL_DIR = "model"
FIGURES_DIR = "figures"
FIGURE_FILES = ("pred_vs_true_x.png", "pred_vs_true_y.png", "pred_vs_true_z.png", "error_histogram.png")
OUTPUT_FILES = ("test_predictions.csv", "interval_calibration.npz")
_FOLD_CALIBRATION = re.compile(r"interval_calibration_folds[0-9]+\.npz")  # calibrate_folds' (an experiment's)
#: a killed write's temporary file of one of them (:func:`~liverforce.atomic.atomic_path`'s naming,
#: ``.<stem>.<8 random>.tmp<suffix>``): names the fold calibration it was written for, which may not exist
_FOLD_CALIBRATION_TEMP = re.compile(r"\.(interval_calibration_folds[0-9]+)\.[a-z0-9_]{8}\.tmp\.npz")
_SAVE_TEMP = re.compile(rf"\.{MODEL_DIR}\.[a-z0-9_]{{8}}")  # ForceModel.save's temporary folder (mkdtemp)


def _remove_file(f: Path, gone: list[Path]) -> None:
    """Remove ``f`` (a file, or a symlink itself: never its target) and the temporary files of its killed
    writes (:func:`~liverforce.atomic.remove_stale_temps`, by name, whether ``f`` exists or not)."""
    gone += remove_stale_temps(f)
    if f.is_symlink() or f.is_file():
        f.unlink()
        gone.append(f)


def clear_outputs(out_dir: str | Path) -> list[Path]:
    """Remove what an earlier :func:`train_scenario` left in ``out_dir``; returns the paths removed.

    Only this module's outputs, by name (:data:`MODEL_DIR`, :data:`FIGURE_FILES` in :data:`FIGURES_DIR`, which
    goes if then empty, :data:`OUTPUT_FILES`, the fold-count calibrations), and the temporary files and folders
    killed writes of them left, also when the final file was never written; nothing else in ``out_dir``. A run
    calls it before it writes anything, so an interrupted run never leaves the old model's figures, predictions
    or calibration beside the new model (or beside none, when Snakemake removed the declared outputs): every
    file there is the current run's, and each is written atomically.

    Never deletes through a symlink: a symlinked output is unlinked, its target kept. A symlinked
    :data:`FIGURES_DIR` is unlinked as a whole, its folder and files untouched (not even those named as the
    figures), and the run then writes its figures into a folder of its own: left in place, the link would have
    the run overwrite the target's files of those names, and an interrupted run leave the old figures there.
    """
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        return []
    gone: list[Path] = []
    for name in OUTPUT_FILES:
        _remove_file(out_dir / name, gone)
    names = [p.name for p in out_dir.iterdir()]
    folds = {n for n in names if _FOLD_CALIBRATION.fullmatch(n)}
    folds |= {m.group(1) + ".npz" for m in map(_FOLD_CALIBRATION_TEMP.fullmatch, names) if m}
    for name in sorted(folds):
        _remove_file(out_dir / name, gone)
    figures = out_dir / FIGURES_DIR
    if figures.is_symlink():
        figures.unlink()
        gone.append(figures)
    elif figures.is_dir():
        for name in FIGURE_FILES:
            _remove_file(figures / name, gone)
        if not any(figures.iterdir()):
            figures.rmdir()
            gone.append(figures)
    for d in [out_dir / MODEL_DIR, *sorted(p for p in out_dir.iterdir() if _SAVE_TEMP.fullmatch(p.name))]:
        if d.is_symlink() or d.is_file():
            d.unlink()
            gone.append(d)
        elif d.is_dir():
            shutil.rmtree(d)
            gone.append(d)
    return gone


REQUIRED_ARRAYS = (
    "case_id", "geometry_id", "force_n", "exertion_point_mm", "frame_normal", "frame_t1", "frame_t2",
    "liver_centroid_mm", "inertia_mm5", "tool_thickness_mm", "probe_compliance_mm_per_n", "material_params_mpa",
    "roi_undeformed_mm", "roi_deformed_mm",
    "roi_centroid_undeformed_mm", "roi_centroid_deformed_mm",
)


def check_arrays(arrays: dict) -> int:
    """Validate the input contract; returns the number of cases."""
    missing = [k for k in REQUIRED_ARRAYS if k not in arrays]
    if missing:
        raise KeyError(f"training arrays lack {missing}; the loader must provide every input-contract key")
    n = len(arrays["case_id"])
    bad = {k: len(arrays[k]) for k in REQUIRED_ARRAYS if len(arrays[k]) != n}
    if bad:
        raise ValueError(f"training arrays disagree on the number of cases ({n} case ids): {bad}")
    force = np.asarray(arrays["force_n"], dtype=np.float64)
    if force.shape != (n, 3) or not np.isfinite(force).all():
        raise ValueError("force_n must be a finite (n, 3) array in N")
    thick = np.asarray(arrays["tool_thickness_mm"], dtype=np.float64)
    if not np.all(np.isfinite(thick) & (thick > 0)):
        bad = [str(c) for c, t in zip(arrays["case_id"], thick) if not (np.isfinite(t) and t > 0)][:5]
        raise ValueError(f"tool_thickness_mm must be finite and > 0 mm; cases {bad} are not (an open surface "
                         "under the tool?)")
    C = np.asarray(arrays["probe_compliance_mm_per_n"], dtype=np.float64).reshape(n, 3, 3)
    finite = np.isfinite(C).all(axis=(1, 2))
    ok = finite.copy()
    ok[finite] = np.linalg.eigvalsh(0.5 * (C[finite] + np.transpose(C[finite], (0, 2, 1))))[:, 0] > 0
    if not ok.all():
        bad = [str(c) for c, good in zip(arrays["case_id"], ok) if not good][:5]
        raise ValueError(f"probe_compliance_mm_per_n must be a finite, positive-definite 3x3 (mm/N); cases {bad} "
                         "are not (the stiffness probe failed for their liver: see the simulate log; a liver "
                         "without supports has no finite compliance)")
    return n


def _flatten(prefix: str, d: dict) -> dict:
    out = {}
    for k, v in d.items():
        key = f"{prefix}.{k}" if prefix else str(k)
        if isinstance(v, dict):
            out.update(_flatten(key, v))
        else:
            out[key] = v
    return out


def train_scenario(
    arrays: dict,
    model_cfg: dict,
    train_cfg: dict,
    tune_cfg: dict,
    scenario: str,
    variant: str,
    tracker=None,
    threads: int = 1,
    seed: int | None = None,
    *,
    out_dir: str | Path,
    tags: dict | None = None,
    model_meta: dict | None = None,
    provenance: dict | None = None,
    calibrate_folds: tuple[int, ...] = (),
) -> dict:
    """Train and evaluate one scenario + variant; returns the result dict (the pipeline writes ``metrics.json``).

    Parameters
    ----------
    arrays : dict
        Converged cases of one scenario in the input contract (mm, N, MPa).
    model_cfg, train_cfg, tune_cfg : dict
        The ``model`` (with the variant's overrides merged in), ``train`` and
        ``tune`` config slices. Optional model keys: ``roi_features``
        (default ``displacement``), ``grid_half_width_mm`` (0 = fit),
        ``dae_input_noise`` (0.1); optional tune key ``space``.
    scenario, variant : str
        ``I``..``IV`` (IV splits by geometry) and the variant name.
    tracker : liverforce.tracking.Tracker, optional
        Receives the parent run, nested trial runs, metrics, figures, model.
    threads : int
        torch intra-op threads (the config's ``threads``).
    seed : int, optional
        Master seed of split, folds, weights and observation noise; default
        ``train_cfg["seed"]``.
    out_dir : path
        Output folder.
    tags : dict, optional
        Run tags, e.g. ``{"rule": "train", "config_hash": ..., "data_version": ...}``.
    model_meta : dict, optional
        Entries of the saved model's ``meta`` (e.g. ROI fraction, frame radius for serving); also run params
        (``model._meta.*``).
    provenance : dict, optional
        What the model was trained on: the livers and the material
        (:func:`liverforce.pipeline.provenance.training_provenance`). Saved as the model's
        ``meta["provenance"]``; the run gets its searchable tags and params
        (:func:`liverforce.learn.provenance.provenance_tags`, :func:`~liverforce.learn.provenance.provenance_params`)
        and the whole record as the artifact ``training_provenance.json``.
    calibrate_folds : tuple of int
        Without ``train.final_fit`` only (an experiment's): the split model's calibration predictions again with
        each of these cross-conformal fold counts, written to ``out_dir/interval_calibration_folds{k}.npz``
        (the same model, fitted once; ``benchmarks/experiment_interval.py --folds``).

    Returns
    -------
    dict
        ``metrics`` (test, N and %), ``best_params``, ``cv_mse``, ``run_id``,
        ``model_uri``, ``model_path``, split sizes and notes, ``trials``.
    """
    t_start = time.perf_counter()
    configure_torch(threads)
    seed = int(train_cfg.get("seed", 0) if seed is None else seed)
    out_dir = Path(out_dir)
    if calibrate_folds and (train_cfg.get("final_fit") or not (train_cfg.get("interval") or {}).get("coverage")):
        raise ValueError("calibrate_folds needs an interval (train.interval.coverage) and train.final_fit off: "
                         "the split model's calibration is recalibrated")
    n = check_arrays(arrays)
    for p in clear_outputs(out_dir):  # an earlier run's model never stays beside this one's (or its absence)
        log.info("removed %s, an earlier training run's output", p)
    geo = np.asarray(arrays["geometry_id"]).astype(str)

    tr, te = train_test_split(geo, scenario=scenario, test_fraction=float(train_cfg["test_fraction"]), seed=seed)
    if provenance and not train_cfg.get("final_fit"):
        # the saved model is the split model: its training livers are the train split's (IV splits by liver)
        fitted = set(geo[tr].tolist())
        provenance = {**provenance, "livers": [r for r in provenance["livers"] if r.get("geometry_id") in fitted],
                      "test_livers": sorted({r.get("geometry_id") for r in provenance["livers"]} - fitted)}
        own = (provenance.get("material") or {}).get("per_liver")
        if own:  # a liver's own material (geometry.imported[].material): the fitted livers' only
            mat = {**provenance["material"], "per_liver": {g: m for g, m in own.items() if g in fitted}}
            provenance["material"] = mat if mat["per_liver"] else {k: v for k, v in mat.items() if k != "per_liver"}
    if model_meta or provenance:
        # stored in the model bundle (e.g. ROI fraction, frame radius for serving; the training livers)
        meta = {**(model_meta or {}), **({"provenance": provenance} if provenance else {})}
        model_cfg = {**model_cfg, "_meta": meta}
    train_arrays, test_arrays = subset(arrays, tr), subset(arrays, te)
    rep = representation_from_config(model_cfg, train_arrays)
    off_grid = _warn_tips_off_grid(arrays, rep, scenario, variant)
    encoder = str(model_cfg["encoder"])
    use_state = bool(model_cfg["state_vector"])
    code_size = encoder_code_size(model_cfg["code_size"], gp_code_members(model_cfg))
    dae_noise = float(model_cfg.get("dae_input_noise", 0.1))
    weight_decay = float(train_cfg.get("weight_decay", 0.0))

    run_tags = {"scenario": scenario, "variant": variant, "config_hash": config_hash(
        {"model": {k: v for k, v in model_cfg.items() if k != "_meta"}, "train": train_cfg, "tune": tune_cfg})}
    run_tags.update({k: str(v) for k, v in (tags or {}).items()})
    run_tags.update(provenance_tags(provenance))
    run_id = None
    if tracker is not None:
        logged_cfg = dict(model_cfg)
        if "_meta" in logged_cfg:  # the provenance record goes to the run as its own params and artifact
            logged_cfg["_meta"] = {k: v for k, v in logged_cfg["_meta"].items() if k != "provenance"}
        params = {
            **_flatten("model", logged_cfg), **_flatten("train", train_cfg), **_flatten("tune", tune_cfg),
            "scenario": scenario, "variant": variant, "seed": seed, "threads": threads,
            "n_cases": n, "n_train": len(tr), "n_test": len(te), "split_by": group_key(scenario),
            "grid_half_width_mm": rep.half_width_mm, "roi_features": rep.features,
            "encoder_code_size": code_size,  # the PCA GP ensemble's largest member, else model.code_size
            **provenance_params(provenance),
        }
        run_id = tracker.start_run(f"{scenario}-{variant}", params=params, tags=run_tags)
    try:
        if tracker is not None and provenance:
            tracker.log_dict(run_id, provenance, PROVENANCE_ARTIFACT)
        with threadpool_limits(limits=int(threads)):  # BLAS (SVD, scipy) as well as torch
            result = _train(
            tracker, run_id, rep, train_arrays, test_arrays, tr, te, geo, model_cfg, train_cfg, tune_cfg,
                scenario, variant, seed, encoder, use_state, code_size, dae_noise, weight_decay, out_dir,
                calibrate_folds,
            )
        result.update(run_id=run_id, tags=run_tags, n_cases=n, seconds=time.perf_counter() - t_start)
        if off_grid is not None:
            result["tips_off_grid"] = off_grid
        if tracker is not None:
            result["model_uri"] = tracker.log_force_model(run_id, result["model_path"], subset(test_arrays, [0]))
            tracker.log_metrics(run_id, {"wall_time_s": result["seconds"]})
            tracker.end_run(run_id)
    except BaseException as exc:
        if tracker is not None and run_id is not None:
            tracker.end_run(run_id, status=run_status(exc))  # KILLED for Ctrl-C: no failure of the code
        raise
    return result


def _warn_tips_off_grid(arrays: dict, rep, scenario: str, variant: str) -> dict | None:
    """A camera model's cases whose tool tip lies off its grid along the surface (:func:`camera.tips_off_grid`):
    logged as a warning (they are trained and scored on, but serving refuses such a tip) and returned as a
    record for the metrics (None for other models)."""
    if rep.features != "cloud":
        return None
    off = tips_off_grid(arrays, rep.half_width_mm)
    if off is None:  # neither the tips nor the surfaces to place them on: not measured, not "none off"
        return {"n": None, "half_width_mm": rep.half_width_mm, "cases": [], "largest_mm": None}
    if off:
        worst = max(off, key=lambda t: t[1])
        log.warning("%s %s: %d of %d cases have the tool tip off the camera grid along the surface (beyond %.3g "
                    "mm; the largest %.3g mm, %s): the model is trained and scored on them, but serving refuses "
                    "such a tip. Usually a lobe swinging on loose supports, or a force too large for this liver",
                    scenario, variant, len(off), len(arrays["exertion_point_mm"]), rep.half_width_mm, worst[1],
                    worst[0])
    return {"n": len(off), "half_width_mm": rep.half_width_mm, "cases": [c for c, _ in off],
            "largest_mm": max((a for _, a in off), default=None)}


def _train(tracker, run_id, rep, train_arrays, test_arrays, tr, te, geo, model_cfg, train_cfg, tune_cfg,
           scenario, variant, seed, encoder, use_state, code_size, dae_noise, weight_decay, out_dir,
           calibrate_folds=()) -> dict:
    prep_train = prepare(train_arrays, rep, observation_seeds=view_seeds(seed, n_views_for(rep)))
    prep_test = prepare(test_arrays, rep, observation_seeds=[eval_seed(seed)])
    notes: list[str] = []
    trials: list[dict] = []
    cv_grouping = None
    best_cv = None
    cv_mae_n = None

    gp = str(model_cfg.get("regressor", "mlp")) == "gp"
    if tune_cfg.get("enabled", True) or gp:
        folds = cv_folds(np.arange(len(tr)), geo[tr], scenario=scenario, folds=int(tune_cfg["folds"]), seed=seed)
        notes += folds.notes
        cv_grouping = folds.grouping
        tune_epochs = int(tune_cfg["epochs"])
        fold_data, to_newton, y_val_n = [], [], []
        for k, (ftr, fva) in enumerate(folds.pairs):
            rows_tr, rows_va = prep_train.rows(ftr), prep_train.rows(fva)
            pre = fit_preprocessor(
                rows_tr, rep, encoder=encoder, code_size=code_size, use_state=use_state, seed=derive(seed, "encoder.fold", k),
                epochs=tune_epochs, lr=float(train_cfg["lr"]), batch_size=int(train_cfg["batch_size"]),
                dae_input_noise=dae_noise, **state_options(model_cfg),
            )
            z_tr, y_tr = regressor_data(pre, rows_tr)
            z_va, y_va = regressor_data(pre, rows_va, all_views=False)
            fold_data.append(FoldData(z_tr, y_tr, z_va, y_va, view_groups(rows_tr),
                                      member_columns(pre, gp_code_members(model_cfg))))
            stiff = pre.stiffness(rows_va.state, len(fva))
            to_newton.append(lambda out, ts=pre.target_scaler, k_=stiff: ts.inverse_transform(out) * k_)
            y_val_n.append(rows_va.y_local)

        if gp:  # no hyper-parameter search: the GP's are its marginal likelihood's (liverforce.learn.gp)
            fp = fit_params(model_cfg, lr=0.0, batch_size=1, epochs=0)
            best = {"regressor": "gp", "max_points": fp.gp_max_points, "iterations": fp.gp_iterations,
                    "kernel": fp.gp_kernel, "shape": fp.gp_shape, "code_members": list(fp.gp_code_members),
                    "per_output": fp.gp_per_output, "noise_floor": fp.gp_noise_floor}
            hidden, dropout = [], 0.0
            lr, batch_size = float(train_cfg["lr"]), int(train_cfg["batch_size"])
            # the CV error in newtons (validate.variant: auto) and of the scaled targets, from one fit per fold
            cv_mae_n, best_cv = cv_force_mae(fold_data, to_newton, y_val_n, best, epochs=tune_epochs, seed=seed,
                                             weight_decay=weight_decay, with_mse=True)
        else:
            def evaluate(params: dict):
                return cv_score(fold_data, params, epochs=tune_epochs, seed=seed, weight_decay=weight_decay)

            on_trial = None
            if tracker is not None:
                def on_trial(report):
                    tracker.log_trial(run_id, report)

            res = tune(evaluate, trials=int(tune_cfg["trials"]), sobol_trials=int(tune_cfg["sobol_trials"]),
                       seed=seed, space=tune_cfg.get("space"), on_trial=on_trial)
            best = dict(res.best_params)
            best_cv = res.best_cv_mse
            trials = [{"index": r.index, "params": r.params, "cv_mse": r.cv_mse, "status": r.status,
                       "seconds": round(r.seconds, 3)} for r in res.trials]
            hidden = [int(best["width"])] * int(best["n_layers"])
            dropout, lr, batch_size = float(best["dropout"]), float(best["lr"]), int(best["batch_size"])
            # the best configuration's CV error in newtons: comparable between variants (validate.variant: auto)
            cv_mae_n = cv_force_mae(fold_data, to_newton, y_val_n, best, epochs=tune_epochs, seed=seed,
                                    weight_decay=weight_decay)
    else:
        hidden = [int(h) for h in model_cfg["hidden"]]
        dropout, lr, batch_size = float(model_cfg["dropout"]), float(train_cfg["lr"]), int(train_cfg["batch_size"])
        best = {"hidden": hidden, "dropout": dropout, "lr": lr, "batch_size": batch_size}

    fit = fit_params(model_cfg, lr=lr, batch_size=batch_size, epochs=int(train_cfg["epochs"]),
                     weight_decay=weight_decay)
    meta = {
        "scenario": scenario, "variant": variant, "seed": seed, "eval_observation_seed": eval_seed(seed),
        "encoder": encoder, "state_vector": use_state, "hyper_parameters": best,
        "test_case_ids": [str(c) for c in test_arrays["case_id"]],
        **(model_cfg.get("_meta") or {}),
    }
    model, history = fit_force_model(
        prep_train, rep, encoder=encoder, code_size=code_size, use_state=use_state, hidden=hidden,
        dropout=dropout, fit=fit, seed=seed, dae_input_noise=dae_noise, monitor=(prep_test, "test"), meta=meta,
        **state_options(model_cfg),
    )
    pred = model.predict(test_arrays, observation_seed=eval_seed(seed))
    metrics = force_metrics(prep_test.force, pred)
    model.meta["test_metrics"] = metrics
    interval = None
    ci = None
    final = bool(train_cfg.get("final_fit"))
    if (train_cfg.get("interval") or {}).get("coverage"):
        try:
            cal = calibration_predictions(train_arrays, model_cfg, train_cfg["interval"], scenario, seed, encoder,
                                          use_state, code_size, dae_noise, hidden, dropout, fit)
            ci = interval_from_calibration(cal, train_cfg["interval"], scenario, notes)
            if not final:
                _write_calibration(out_dir / "interval_calibration.npz", cal)
        except ValueError as exc:  # e.g. one training liver in IV: nothing to hold out by liver
            notes.append(f"no calibrated interval: {exc}")
    for k in (calibrate_folds if ci is not None else ()):  # an experiment's other fold counts (errors propagate)
        cal_k = calibration_predictions(train_arrays, model_cfg, {**train_cfg["interval"], "folds": int(k)},
                                        scenario, seed, encoder, use_state, code_size, dae_noise, hidden, dropout,
                                        fit)
        _write_calibration(out_dir / f"interval_calibration_folds{int(k)}.npz", cal_k)
    if ci is not None:
        flag = set_input_distance(model, cal, train_cfg["interval"], train_arrays, prep_train, scenario, seed)
        ci = far_widths(ci, cal, flag, train_cfg["interval"], notes)
        model.meta["interval"] = ci.to_dict()
        got = model.predict_interval(test_arrays, observation_seed=eval_seed(seed))
        interval = {**ci.to_dict(), "test_coverage": coverage_per_component(
            prep_test.y_local, got["force_local_n"], got["half_width_local_n"])}
        model.meta["interval_test_coverage"] = interval["test_coverage"]
        if flag is not None:
            interval["input_distance"] = {**flag, **flagged_errors(got["input_distance"], flag, prep_test.force,
                                                                    pred)}
    repeats = [{"split_seed": seed, "test_geometries": _geometries(test_arrays), "metrics": metrics,
                "outside_training": outside_training_split(model, test_arrays, pred),
                **exact_tip_metrics(model, test_arrays, seed)}]
    final_info, rep_saved = None, rep
    if final:  # train.final_fit: the saved model is the same configuration fitted on every case (step 6)
        model, rep_saved, interval, final_info = fit_final(
            train_arrays, test_arrays, model_cfg, train_cfg, scenario, seed, encoder, use_state, code_size, dae_noise,
            hidden, dropout, fit, meta, metrics, interval, out_dir)
    saved_pred = model.predict(test_arrays, observation_seed=eval_seed(seed)) if final else pred
    model_path = model.save(out_dir / MODEL_DIR)
    # the saved bundle must reproduce its predictions exactly (guards the format)
    reloaded = ForceModel.load(model_path).predict(test_arrays, observation_seed=eval_seed(seed))
    if not np.array_equal(reloaded, saved_pred):
        raise RuntimeError(f"the saved model at {model_path} does not reproduce its predictions")
    figures = evaluation_figures(prep_test.force, pred, out_dir / FIGURES_DIR, title=f"{scenario} {variant}")
    _write_predictions(out_dir / "test_predictions.csv", test_arrays["case_id"], prep_test.force, pred)

    repeats += repeated_splits(train_arrays, test_arrays, rep, model_cfg, train_cfg, scenario, seed, encoder,
                               use_state, code_size, dae_noise, hidden, dropout, fit)
    summary = summarise_repeats([r["metrics"] for r in repeats])
    exact = None
    if all("exact_tip" in r for r in repeats):
        e = summarise_repeats([r["exact_tip"] for r in repeats])
        exact = {"metrics_mean": e["mean"], "metrics_sd": e["sd"], "n_splits": e["n"]}
    outside = summarise_outside([r["outside_training"] for r in repeats])
    points = None
    hp = train_cfg.get("heldout_points") or {}
    if scenario in (hp.get("scenarios") or []) and "exertion_id" in train_arrays:
        points = heldout_points(train_arrays, test_arrays, model_cfg, int(hp.get("folds", 4)), seed, encoder,
                                use_state, code_size, dae_noise, hidden, dropout, fit)

    if tracker is not None:
        tracker.log_history(run_id, history)
        tracker.log_metrics(run_id, {**metrics, **({"cv_mse": best_cv} if best_cv is not None else {}),
                                     **({"cv_mae_n": cv_mae_n} if cv_mae_n is not None else {}),
                                     **{f"{k}_mean": v for k, v in summary["mean"].items()},
                                     **{f"{k}_sd": v for k, v in summary["sd"].items()},
                                     "n_splits": summary["n"],
                                     **({"n_outside_training": outside["n_outside"],
                                         **{f"{side}_training_range_accuracy_pct_mean": outside[f"{side}_accuracy_pct"]["mean"]
                                            for side in ("inside", "outside")
                                            if outside[f"{side}_accuracy_pct"]["mean"] is not None}}
                                        if outside else {}),
                                     **({f"heldout_points_{k}_{m}": v for m in ("mean", "sd")
                                         for k, v in (points[f"metrics_{m}"] or {}).items()}
                                        if points else {}),  # none when not measured, no sd with one fold
                                     **({f"exact_tip_{k}_{m}": v for m in ("mean", "sd")
                                         for k, v in exact[f"metrics_{m}"].items()} if exact else {})})
        tracker.log_params(run_id, {f"best.{k}": v for k, v in best.items()})
        for path in figures:
            tracker.log_artifact(run_id, path, "figures")
        tracker.log_artifacts(run_id, model_path, "force_model")

    return {
        "scenario": scenario,
        "variant": variant,
        "seed": seed,
        "metrics": metrics,
        "metrics_mean": summary["mean"],
        "metrics_sd": summary["sd"],
        "n_splits": summary["n"],
        "repeats": repeats,
        "cv_mse": best_cv,
        "cv_mae_n": cv_mae_n,
        "interval": interval,
        "final_fit": final_info,
        "exact_tip": exact,
        "heldout_points": points,
        "outside_training": outside,
        "best_params": best,
        "trials": trials,
        "n_train": int(len(tr)),
        "n_test": int(len(te)),
        "split": {
            "by": group_key(scenario),
            "cv_grouping": cv_grouping,
            "test_geometries": sorted(set(np.asarray(test_arrays["geometry_id"]).astype(str).tolist())),
            "notes": notes,
        },
        "representation": rep_saved.to_dict(),  # the saved model's
        "eval_observation_seed": eval_seed(seed),
        "final_train_loss": history["train_loss"][-1],
        "model_path": str(model_path),
        "model_uri": None,
        "figures": [str(p) for p in figures],
    }


def fit_final(train_arrays, test_arrays, model_cfg, train_cfg, scenario, seed, encoder, use_state, code_size,
              dae_noise, hidden, dropout, fit, meta, split_metrics, split_interval, out_dir):
    """``train.final_fit``: the chosen configuration refitted on every case of the scenario, the saved model.

    The splits measure the configuration; the model a user serves should then see all the data there is (for IV
    every liver: the unseen livers of the validation are still never seen). Same hyper-parameters, seeds and
    observation seeds as the main split; its interval is calibrated the same way on all the cases
    (cross-conformal by liver in IV) and its calibration predictions replace the split's
    ``interval_calibration.npz``. The bundle records ``final_fit: true``, no test cases, and as
    ``test_metrics`` / ``interval_test_coverage`` the main split's (the same settings on held-out cases: what
    this model is expected to do on new ones). Returns the model, its representation, the result's ``interval``
    (the final interval, with the main split's test coverage) and ``final_fit`` (what it was fitted on).
    """
    cases = _all_cases(train_arrays, test_arrays)
    rep = representation_from_config(model_cfg, cases)
    prep = prepare(cases, rep, observation_seeds=view_seeds(seed, n_views_for(rep)))
    meta = {**meta, "test_case_ids": [], "final_fit": True,
            "split_test_case_ids": [str(c) for c in test_arrays["case_id"]]}
    model, _ = fit_force_model(prep, rep, encoder=encoder, code_size=code_size, use_state=use_state, hidden=hidden,
                               dropout=dropout, fit=fit, seed=seed, dae_input_noise=dae_noise, meta=meta,
                               **state_options(model_cfg))
    model.meta["test_metrics"] = split_metrics
    interval = None
    if split_interval is not None:  # the split was calibrated, so the full set can be
        cal = calibration_predictions(cases, model_cfg, train_cfg["interval"], scenario, seed, encoder, use_state,
                                      code_size, dae_noise, hidden, dropout, fit)
        said: list = []
        ci = interval_from_calibration(cal, train_cfg["interval"], scenario, said)
        _write_calibration(out_dir / "interval_calibration.npz", cal)
        flag = set_input_distance(model, cal, train_cfg["interval"], cases, prep, scenario, seed)
        ci = far_widths(ci, cal, flag, train_cfg["interval"], said)
        model.meta["interval"] = ci.to_dict()
        if said:  # e.g. the interval without the members' spread: kept with the model
            model.meta["interval_notes"] = said
        model.meta["interval_test_coverage"] = split_interval["test_coverage"]
        interval = {**ci.to_dict(), "test_coverage": split_interval["test_coverage"]}
        if split_interval.get("input_distance") is not None:  # the split model's flag on its test livers
            interval["split_input_distance"] = split_interval["input_distance"]
    info = {"n_cases": len(cases["case_id"]), "geometries": _geometries(cases)}
    return model, rep, interval, info


def interval_from_calibration(cal: dict, interval_cfg, scenario, notes: list | None = None):
    """Conformal interval (:mod:`liverforce.learn.interval`) of ``interval_cfg`` (coverage, scale, bins) fitted on
    :func:`calibration_predictions`' output: the same calibration predictions give every scale, with no new fit.
    ``interval_cfg["scale"]``: ``none``, ``stiffness``, ``force`` or ``force_bins`` (the module docstring; the
    config sets it, ``force_bins`` by default, with ``interval_cfg["bins"]`` bins; a dict without the key gets
    ``stiffness``, what it meant before the key existed); ``interval_cfg["widen"]``: ``proportional`` (without
    the key) or ``fitted``, the widening outside the calibration's stiffness range; ``interval_cfg["spread"]``:
    the members' spread's beta (None: not scaled by it; a calibration without ``spread_local``, a model without a GP
    ensemble, is fitted without it). Members that agree on most calibration cases (median sd 0) leave nothing to
    scale by: the interval is fitted without the spread, and ``notes`` (a list, if given) says so."""
    from liverforce.learn.interval import SpreadUnusable

    beta = interval_cfg.get("spread")
    spread = cal.get("spread_local")

    def fit(use_spread: bool):
        return fit_conformal(cal["true_local"], cal["pred_local"], cal["stiffness"], float(interval_cfg["coverage"]),
                             group_key(scenario), scale=str(interval_cfg.get("scale", "stiffness")),
                             folds=int(cal["folds"]), bins=int(interval_cfg.get("bins", 5)),
                             widen=str(interval_cfg.get("widen", "proportional")),
                             spread=spread if use_spread else None, spread_beta=beta if use_spread else None)

    if beta is None or spread is None:
        return fit(False)
    try:
        return fit(True)
    except SpreadUnusable as exc:
        if notes is not None:
            notes.append(f"interval without the members' spread: {exc}")
        return fit(False)


def set_input_distance(model, cal: dict, interval_cfg, arrays: dict, prep, scenario: str, seed: int) -> dict | None:
    """Fit the input-distance flag (:func:`liverforce.learn.interval.fit_input_distance`) at
    ``interval_cfg["distance_quantile"]`` on the training side's distances (:func:`training_distances`: each of
    ``arrays``' cases, in its evaluation view, to the GP's rows of other livers in IV, of other cases elsewhere;
    ``prep``: the rows the model was fitted on, with ``seed``) and record it in ``model.meta["input_distance"]``,
    with the calibration's distances (``cal["input_distance"]``, each to the fold model that did not see the
    case) as ``fold_quantiles`` for comparison. Returns it, or None: the key null or missing, or an MLP (no
    training rows to measure against; nothing is said, as an MLP has no members' spread either)."""
    from liverforce.learn.interval import DISTANCE_QUANTILES, fit_input_distance

    q = interval_cfg.get("distance_quantile")
    if q is None or not model.is_gp:
        return None
    by_liver = group_key(scenario) == "geometry" and len(set(np.asarray(arrays["geometry_id"]).tolist())) > 1
    labels = np.asarray(arrays["geometry_id" if by_liver else "case_id"]).astype(str)  # one liver: its other cases
    prep_eval = prepare(arrays, model.representation, observation_seeds=[eval_seed(seed)])
    dist = training_distances(model, prep, prep_eval, labels, seed)
    if not np.isfinite(dist).any():  # one case: nothing to measure it against
        return None
    rec = fit_input_distance(dist, q)
    rec["left_out"] = "liver" if by_liver else "case"
    fold = cal.get("input_distance")
    if fold is not None:
        rec["fold_quantiles"] = {f"{p:g}": float(np.nanquantile(fold, p)) for p in DISTANCE_QUANTILES}
    model.meta["input_distance"] = rec
    return rec


def far_widths(ci, cal: dict, flag: dict | None, interval_cfg, notes: list | None = None):
    """``ci`` with far widths (:func:`liverforce.learn.interval.with_far_widths`) when ``interval_cfg["far_widths"]``
    and the input-distance flag ``flag`` exists, fitted on the calibration ``cal`` at the flag's quantile; ``ci``
    itself otherwise, and when a group of the calibration is too small (``notes`` says so)."""
    from liverforce.learn.interval import with_far_widths

    if not interval_cfg.get("far_widths") or flag is None:
        return ci
    try:
        return with_far_widths(ci, cal, flag["threshold"], flag["quantile"])
    except ValueError as exc:
        if notes is not None:
            notes.append(f"no far widths: {exc}")
        return ci


def flagged_errors(distance, record: dict, true_force: np.ndarray, pred: np.ndarray) -> dict:
    """How the input-distance flag ``record`` splits the cases ``(n,)`` distances: ``n``, ``n_flagged``, and the
    mean error ``|F - F^|`` (N) of the flagged cases and of the others (None where there are none)."""
    from liverforce.learn.interval import distance_flags

    f = distance_flags(distance, record)
    err = np.linalg.norm(np.asarray(pred, float) - np.asarray(true_force, float), axis=1)
    return {"n": int(f.size), "n_flagged": int(f.sum()),
            "mae_flagged_n": float(err[f].mean()) if f.any() else None,
            "mae_others_n": float(err[~f].mean()) if (~f).any() else None}


def _write_calibration(path: Path, cal: dict) -> None:
    """The calibration predictions an interval was fitted on, next to the model (atomic): another scale or
    coverage can be fitted on them later without retraining (``benchmarks/experiment_interval.py``)."""
    buf = io.BytesIO()
    np.savez(buf, **{k: np.asarray(v) for k, v in cal.items()})
    write_bytes_atomic(path, buf.getvalue())


def calibration_predictions(train_arrays, model_cfg, interval_cfg, scenario, seed, encoder, use_state, code_size,
                            dae_noise, hidden, dropout, fit) -> dict:
    """The calibration cases' true and predicted local forces and stiffness factors, from the training split alone,
    and (``spread_local``) a GP ensemble's members' sd of each prediction (the interval's ``spread``) and
    (``input_distance``) a GP's inputs' distance to the fold model's training rows (the input-distance flag).

    ``interval_cfg["folds"]`` > 1: cross-conformal, the training cases cut into
    that many folds (by liver in IV, as the test split), each predicted by a model
    with the chosen settings fitted on the other folds; 1: one split, with
    ``calibration_fraction`` of the training cases (by liver in IV) held out. Every
    fold uses the main split's observation seeds (``seed``): each case is observed as it is in the main
    model's training or test (the observed data are fixed, only the split differs), so a camera model's
    features of a case are computed once per run and reused from the cache.
    """
    geo = np.asarray(train_arrays["geometry_id"]).astype(str)
    n_folds = int(interval_cfg.get("folds", 1))
    cal_seed = derive(seed, "interval.fit")
    if n_folds > 1:
        pairs = cv_folds(np.arange(len(geo)), geo, scenario=scenario, folds=n_folds,
                         seed=derive(seed, "split.calibration")).pairs
    else:
        fit_idx, cal_idx = train_test_split(geo, scenario=scenario,
                                            test_fraction=float(interval_cfg["calibration_fraction"]),
                                            seed=derive(seed, "split.calibration"))
        pairs = [(fit_idx, cal_idx)]
    true, pred, stiff, spread, dist = [], [], [], [], []
    for fit_idx, cal_idx in pairs:
        a_fit, a_cal = subset(train_arrays, fit_idx), subset(train_arrays, cal_idx)
        rep_c = representation_from_config(model_cfg, a_fit)
        prep_fit = prepare(a_fit, rep_c, observation_seeds=view_seeds(seed, n_views_for(rep_c)))
        model, _ = fit_force_model(prep_fit, rep_c, encoder=encoder, code_size=code_size, use_state=use_state,
                                   hidden=hidden, dropout=dropout, fit=fit, seed=cal_seed, dae_input_noise=dae_noise,
                                   **state_options(model_cfg))
        prep_cal = prepare(a_cal, rep_c, observation_seeds=[eval_seed(seed)])
        fw = model.forward(a_cal, observation_seed=eval_seed(seed))
        true.append(prep_cal.y_local)
        pred.append(fw.force_local)
        stiff.append(model.pre.material_factor(prep_cal.state if use_state else None, len(fw.force_local)))
        spread.append(fw.spread_local)
        dist.append(fw.input_distance)
    out = {"true_local": np.vstack(true), "pred_local": np.vstack(pred), "stiffness": np.vstack(stiff),
           "folds": len(pairs)}
    if all(d is not None for d in spread):  # a GP ensemble's members' sd (the interval's spread)
        out["spread_local"] = np.vstack(spread)
    if all(d is not None for d in dist):  # a GP's inputs' distance to the fold model's training rows
        out["input_distance"] = np.concatenate(dist)
    return out


def _geometries(arrays: dict) -> list[str]:
    return sorted(set(np.asarray(arrays["geometry_id"]).astype(str).tolist()))


def repeated_splits(train_arrays, test_arrays, rep, model_cfg, train_cfg, scenario, seed, encoder, use_state,
                    code_size, dae_noise, hidden, dropout, fit) -> list[dict]:
    """Refit the chosen configuration on ``train.repeats - 1`` further seeded splits; their test metrics.

    The cases are the union of the main split's training and test cases; split
    ``r`` uses seed ``seed + r`` (:func:`~liverforce.learn.splits.train_test_split`,
    by geometry for IV). Every split observes each case as the main split does
    (observation seeds from ``seed``): the observed data are fixed and only the
    split differs, so a camera model's features are computed once per case.
    """
    n_rep = int(train_cfg.get("repeats", 1))
    if n_rep <= 1:
        return []
    all_arrays = _all_cases(train_arrays, test_arrays)
    geo = np.asarray(all_arrays["geometry_id"]).astype(str)
    out = []
    for r in range(1, n_rep):
        split_seed = derive(seed, "split.repeat", r)
        tr, te = train_test_split(geo, scenario=scenario, test_fraction=float(train_cfg["test_fraction"]),
                                  seed=split_seed)
        a_tr, a_te = subset(all_arrays, tr), subset(all_arrays, te)
        rep_r = representation_from_config(model_cfg, a_tr)
        prep_tr = prepare(a_tr, rep_r, observation_seeds=view_seeds(seed, n_views_for(rep_r)))
        model, _ = fit_force_model(prep_tr, rep_r, encoder=encoder, code_size=code_size, use_state=use_state,
                                   hidden=hidden, dropout=dropout, fit=fit, seed=split_seed,
                                   dae_input_noise=dae_noise, **state_options(model_cfg))
        pred = model.predict(a_te, observation_seed=eval_seed(seed))
        out.append({"split_seed": split_seed, "test_geometries": _geometries(a_te),
                    "metrics": force_metrics(np.asarray(a_te["force_n"], float), pred),
                    "outside_training": outside_training_split(model, a_te, pred),
                    **exact_tip_metrics(model, a_te, seed)})
    return out


def exact_tip_metrics(model, test_arrays: dict, seed: int) -> dict:
    """``{"exact_tip": metrics}`` of a camera-cloud model on ``test_arrays`` with an exact tool tip: the same
    fitted model and the same clouds (evaluation observation seed of ``seed``), no kinematics noise on the
    tip; ``{}`` for any other model. A model that fits the instrument's axis still fits it, with the weights it
    was trained with (the kinematic tip, now exact, is the fit's prior): what the shipped model gives with a
    perfect tracker, not what an exact tip would."""
    if not model.representation.is_camera:
        return {}
    probe = model.observed_with(exact_tip(model.representation.camera))
    pred = probe.predict(test_arrays, observation_seed=eval_seed(seed))
    return {"exact_tip": force_metrics(np.asarray(test_arrays["force_n"], float), pred)}


def outside_training_split(model, test_arrays: dict, pred: np.ndarray) -> dict | None:
    """The test cases whose geometric state lies outside the model's training range, and the metrics of
    those and of the others (:func:`liverforce.learn.state.outside_ranges`, what serving warns about).

    None for a model without the state vector: it does not read the state, and serving does not warn
    about it (``Predictor.context_warnings``). ``error_sum_n`` / ``force_sum_n`` per side let the
    splits be pooled (:func:`summarise_outside`).
    """
    got = outside_training_range(model, test_arrays)
    if got is None:
        return None
    out, masks = got
    true = np.asarray(test_arrays["force_n"], dtype=np.float64)
    err = np.linalg.norm(pred - true, axis=1)
    mag = np.linalg.norm(true, axis=1)
    return {"n_cases": int(len(pred)), "n_outside": int(out.sum()),
            "by_input": {k: int(v.sum()) for k, v in masks.items()},
            "inside": force_metrics(true[~out], pred[~out]) if (~out).any() else None,
            "outside": force_metrics(true[out], pred[out]) if out.any() else None,
            "error_sum_n": {"inside": float(err[~out].sum()), "outside": float(err[out].sum())},
            "force_sum_n": {"inside": float(mag[~out].sum()), "outside": float(mag[out].sum())}}


def summarise_outside(per_split: list) -> dict | None:
    """Over the splits: the test cases outside the training range (counts summed); per side (inside,
    outside) the mean and sample sd over the splits that have such cases of the accuracy and MAE (sd None
    with fewer than 2 such splits), and the accuracy of all the side's cases pooled
    (``100 (1 - sum |e| / sum |F|)``, each case weighing the same)."""
    if not per_split or any(p is None for p in per_split):
        return None
    out = {"n_splits": len(per_split), "n_cases": sum(p["n_cases"] for p in per_split),
           "n_outside": sum(p["n_outside"] for p in per_split)}
    for side in ("inside", "outside"):
        got = [p[side] for p in per_split if p[side] is not None]
        for k in ("accuracy_pct", "mae_vec"):
            v = np.array([g[k] for g in got], dtype=np.float64)
            out[f"{side}_{k}"] = {"mean": float(v.mean()) if v.size else None,
                                  "sd": float(v.std(ddof=1)) if v.size > 1 else None,
                                  "n_splits": int(v.size)}
        e = sum(p["error_sum_n"][side] for p in per_split)
        f = sum(p["force_sum_n"][side] for p in per_split)
        out[f"{side}_accuracy_pooled_pct"] = float(100.0 * (1.0 - e / f)) if f > 0 else None
    return out


def _all_cases(train_arrays: dict, test_arrays: dict) -> dict:
    """The main split's training and test cases together, ordered by case id (independent of that split)."""
    both = {k: (train_arrays[k] if k in PER_RUN_KEYS
                else list(train_arrays[k]) + list(test_arrays[k]) if isinstance(train_arrays[k], list)
                else np.concatenate([np.asarray(train_arrays[k]), np.asarray(test_arrays[k])]))
            for k in train_arrays}
    return subset(both, np.argsort(np.asarray(both["case_id"]).astype(str), kind="stable"))


#: Fewest distinct exertion points on a liver a held-out-points fold must train on before its test points on that
#: liver are scored. The exertion point is a position on the liver's 2-D surface, and the state vector's
#: point-dependent entries (liver and ROI centroid offsets, inertia in the local frame, thickness, probe
#: compliance) are functions of it: an affine dependence on a 2-D position has 3 unknowns, so fewer than 3
#: points (1: those entries are constant in training; 2: they vary along one line only) leave the model
#: extrapolating in a direction it never saw, whatever it predicts.
MIN_TRAIN_POINTS = 3


def _point_liver(point: str) -> str:
    """The liver (``geometry_id``) of a held-out-points key ``"<geometry_id>#<exertion_id>"``."""
    return str(point).rsplit("#", 1)[0]


def fold_training_points(groups, part) -> dict[str, int]:
    """Per liver the fold ``part`` tests (points of ``groups`` keyed ``"<geometry_id>#<exertion_id>"``): how many
    distinct exertion points of that liver its training part (every other point) holds."""
    held = {str(p) for p in part}
    livers = sorted({_point_liver(p) for p in held})
    return {g: sum(1 for p in groups if str(p) not in held and _point_liver(p) == g) for g in livers}


def heldout_points(train_arrays, test_arrays, model_cfg, folds, seed, encoder, use_state, code_size, dae_noise,
                   hidden, dropout, fit) -> dict | None:
    """Accuracy on exertion points no training case used (scenarios split by case: II, III).

    The cases of both splits are cut into ``folds`` groups of whole exertion points
    (``geometry_id``, ``exertion_id``); each group is predicted by a model with the
    chosen settings fitted on the others (the cases observed as in the main split).
    Returns the metrics per fold and their mean and sd, or None with fewer than 2
    exertion points.

    A fold whose training part holds fewer than :data:`MIN_TRAIN_POINTS` distinct exertion points on a liver
    it tests is not fitted nor scored: its record keeps its points and test cases, ``train_points`` (per
    tested liver) and ``skipped`` (why); the mean and sd are over the scored folds (``n_scored``), and
    ``metrics_sd`` is None with one scored fold (no spread to give). With no fold scored, ``metrics_mean`` and
    ``metrics_sd`` are None and ``not_measured`` says why, with the counts.
    """
    all_arrays = _all_cases(train_arrays, test_arrays)
    point = np.char.add(np.asarray(all_arrays["geometry_id"]).astype(str),
                        np.char.add("#", np.asarray(all_arrays["exertion_id"]).astype(str)))
    groups = np.unique(point)
    if len(groups) < 2:
        return None
    k = min(int(folds), len(groups))
    rng = np.random.default_rng(derive(seed, "split.points"))
    parts = np.array_split(rng.permutation(groups), k)
    fold_seed = derive(seed, "points.fit")
    out = []
    for i, part in enumerate(parts, start=1):
        te = np.flatnonzero(np.isin(point, part))
        tr = np.flatnonzero(~np.isin(point, part))
        record = {"points": sorted(str(p) for p in part), "n_test": int(len(te))}
        n_train = fold_training_points(groups, part)
        few = {g: n for g, n in n_train.items() if n < MIN_TRAIN_POINTS}
        if few:
            record["train_points"] = n_train
            record["skipped"] = (f"fold {i} trains on " + ", ".join(
                f"{n} exertion point{'' if n == 1 else 's'} of {g}" for g, n in few.items())
                + f" (fewer than {MIN_TRAIN_POINTS}: how the force depends on the point is not learnt, only "
                "extrapolated)")
            out.append(record)
            continue
        a_tr, a_te = subset(all_arrays, tr), subset(all_arrays, te)
        rep_p = representation_from_config(model_cfg, a_tr)
        prep_tr = prepare(a_tr, rep_p, observation_seeds=view_seeds(seed, n_views_for(rep_p)))
        model, _ = fit_force_model(prep_tr, rep_p, encoder=encoder, code_size=code_size, use_state=use_state,
                                   hidden=hidden, dropout=dropout, fit=fit, seed=fold_seed,
                                   dae_input_noise=dae_noise, **state_options(model_cfg))
        pred = model.predict(a_te, observation_seed=eval_seed(seed))
        record["metrics"] = force_metrics(np.asarray(a_te["force_n"], float), pred)
        out.append(record)
    scored = [o["metrics"] for o in out if "metrics" in o]
    res = {"folds": k, "n_points": int(len(groups)), "min_train_points": MIN_TRAIN_POINTS, "n_scored": len(scored)}
    if scored:
        summary = summarise_repeats(scored)
        # one scored fold has no spread: no sd (not 0), and the report prints the mean alone
        res.update(metrics_mean=summary["mean"], metrics_sd=summary["sd"] if len(scored) >= 2 else None)
    else:
        per_liver = {}
        for p in groups:
            per_liver[_point_liver(p)] = per_liver.get(_point_liver(p), 0) + 1
        fewest = min(per_liver.values())
        most = max(min(o["train_points"].values()) for o in out)
        more_folds = _folds_needed(fewest)
        res.update(metrics_mean=None, metrics_sd=None,
                   not_measured=(f"{len(groups)} exertion point{'' if len(groups) == 1 else 's'} "
                                 f"({', '.join(f'{n} on {g}' for g, n in per_liver.items())}) in {k} folds leave "
                                 f"at most {most} point{'' if most == 1 else 's'} of a tested liver to train a fold on"
                                 f", fewer than the {MIN_TRAIN_POINTS} needed; give >= {_points_needed(k)} exertion "
                                 f"points per liver at {k} folds"
                                 + (f" or set train.heldout_points.folds >= {more_folds}" if more_folds else
                                    f" (>= {MIN_TRAIN_POINTS + 1} with as many folds as points)")))
    res["per_fold"] = out
    return res


def _folds_needed(n_points: int) -> int | None:
    """Fewest folds with which a liver of ``n_points`` exertion points leaves every fold
    :data:`MIN_TRAIN_POINTS` of them to train on (None: no number of folds does)."""
    for k in range(2, n_points + 1):
        if n_points - -(-n_points // k) >= MIN_TRAIN_POINTS:
            return k
    return None


def _points_needed(folds: int) -> int:
    """Fewest exertion points per liver with which every one of ``folds`` folds trains on
    :data:`MIN_TRAIN_POINTS` of them (a fold tests at most ``ceil(n / folds)`` points)."""
    n = MIN_TRAIN_POINTS + 1
    while n - -(-n // folds) < MIN_TRAIN_POINTS:
        n += 1
    return n


def summarise_repeats(metrics: list[dict]) -> dict:
    """Mean and sample standard deviation (ddof 1; 0 for one split, which the report prints as the mean alone)
    of every metric over the splits."""
    keys = [k for k in metrics[0] if all(isinstance(m.get(k), (int, float)) for m in metrics)]
    vals = {k: np.array([float(m[k]) for m in metrics]) for k in keys}
    return {"n": len(metrics),
            "mean": {k: float(v.mean()) for k, v in vals.items()},
            "sd": {k: float(v.std(ddof=1)) if len(v) > 1 else 0.0 for k, v in vals.items()}}


def _write_predictions(path: Path, case_ids, true: np.ndarray, pred: np.ndarray) -> None:
    lines = ["case_id,fx_true_n,fy_true_n,fz_true_n,fx_pred_n,fy_pred_n,fz_pred_n"]
    for cid, t, p in zip(case_ids, true, pred):
        lines.append(",".join([str(cid), *(repr(float(v)) for v in (*t, *p))]))
    write_text_atomic(path, "\n".join(lines) + "\n")
