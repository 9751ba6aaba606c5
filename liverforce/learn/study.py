"""Comparison studies on already-simulated shards (no new FE): one model per study point.

Studies (config group ``study``; each lists its ``scenarios`` and values)
----------------------------------------------------------------------
``roi_fraction``  ROI area fraction (e.g. 0.05-0.50); the ROI is grown again
                  from the stored full-surface displacements
                  (:func:`liverforce.learn.representation.with_roi_fraction`).
``encoder``       PCA vs autoencoder vs denoising autoencoder.
``state_vector``  deformation only vs deformation + state vector.
``occlusion``     tool occlusion radius (mm) per encoder and mode
                  (``remove`` | ``noise``).
``noise``         Gaussian point-cloud noise (mm, stereo endoscope).
``train_size``    fraction of the training split used (learning curve).
``train_livers``  number of training livers used (scenario IV learning curve
                  over the population: 2, 4, 8, ... livers, nested subsets of
                  the fitting livers; the validation livers are fixed).

Every study point starts from the scenario's *main model* (the first
``train.variants`` entry: its model settings, and its Ax-tuned
hyper-parameters read from its ``metrics.json`` when
``study.hyper_parameters: main``), changes one thing, and is trained **without
Ax** for ``study.epochs`` epochs on the main model's training split minus a
validation part (by liver in IV), then evaluated on that validation part with
the metrics of :mod:`liverforce.learn.metrics` (MAE/RMSE in N, accuracy %).
The main model's test split is never read by a study, so choosing a setting
from a study does not select on the test set. Points of one
study therefore differ in the studied setting only. A point that cannot be
trained (e.g. an occlusion radius that hides the whole ROI) is recorded with
``status: failed`` and its reason; it does not stop the study.

This module never imports mlflow: the tracker is duck-typed
(:class:`liverforce.tracking.Tracker`).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from liverforce.atomic import atomic_path
from liverforce.config import merge_mapping
from liverforce.learn.metrics import force_metrics
from liverforce.learn.model import (
    eval_seed,
    fit_force_model,
    n_views_for,
    prepare,
    state_options,
    subset,
    view_seeds,
)
from liverforce.learn.regressor import fit_params
from liverforce.learn.representation import representation_from_config, with_roi_fraction
from liverforce.learn.splits import train_test_split
from liverforce.learn.torchutil import configure_torch
from liverforce.seeds import derive

log = logging.getLogger("liverforce")

STUDIES = ("roi_fraction", "encoder", "state_vector", "occlusion", "noise", "train_size", "train_livers")

#: what each study varies, for titles and axis labels
STUDY_TITLES = {
    "roi_fraction": ("Accuracy vs ROI fraction", "ROI fraction of the liver surface"),
    "encoder": ("PCA vs autoencoder vs denoising autoencoder", "encoder"),
    "state_vector": ("With vs without the state vector", "state vector"),
    "occlusion": ("Tool occlusion", "occlusion radius (mm)"),
    "noise": ("Point-cloud noise", "Gaussian noise σ (mm)"),
    "train_size": ("Learning curve: accuracy vs training-set size", "fraction of the training split used"),
    "train_livers": ("Learning curve over livers: accuracy on held-out validation livers vs training livers",
                     "number of training livers"),
}


@dataclass(frozen=True)
class StudyPoint:
    """One model of a study: the scenario, the value studied and the settings it changes."""

    study: str
    scenario: str
    value: Any
    label: str
    model_overrides: dict = field(default_factory=dict)
    roi_fraction: float | None = None
    train_fraction: float | None = None  # learning curve: use this fraction of the training split
    train_livers: int | None = None  # learning curve over livers: use this many training livers
    series: str = ""  # curve the point belongs to in the plot (e.g. "dae / noise")


# --------------------------------------------------------------------------
# bookkeeping (pure; used by the Snakemake rules)
# --------------------------------------------------------------------------


def enabled_studies(study_cfg: dict) -> list[str]:
    """Names of the studies that run (``study.enabled`` and the study's own ``enabled``, with points)."""
    if not study_cfg.get("enabled", True):
        return []
    return [s for s in STUDIES if study_cfg[s].get("enabled", True) and study_points(s, study_cfg)]


def study_scenarios(study: str, study_cfg: dict) -> list[str]:
    return list(study_cfg[study]["scenarios"])


def study_slice(study: str, study_cfg: dict) -> dict:
    """The part of the ``study`` config one study uses (its rule's params: only its own change re-runs it)."""
    common = {k: v for k, v in study_cfg.items() if k not in STUDIES}
    return {**common, study: study_cfg[study]}


def study_geometries(study: str, study_cfg: dict, plan) -> list[str]:
    """Geometry ids whose meshes a study needs (the ROI-fraction study re-grows ROIs on them)."""
    if study != "roi_fraction":
        return []
    return sorted({g for s in study_scenarios(study, study_cfg) for g in plan.scenario_geometries(s)})


def study_points(study: str, study_cfg: dict) -> list[StudyPoint]:
    """Expand one study's config into its points (scenario-major)."""
    s = study_cfg[study]
    pts: list[StudyPoint] = []
    for sc in s["scenarios"]:
        if study == "roi_fraction":
            # the grid spans each point's own ROI (half-width fitted on it), so the ROI size is what changes
            pts += [StudyPoint(study, sc, float(v), f"{float(v):.2f}", {"grid_half_width_mm": 0.0},
                               roi_fraction=float(v), series=sc)
                    for v in s["values"]]
        elif study == "encoder":
            pts += [StudyPoint(study, sc, str(v), str(v), {"encoder": str(v)}, series=sc) for v in s["values"]]
        elif study == "state_vector":
            pts += [StudyPoint(study, sc, bool(v), "with" if v else "without",
                               {"state_vector": bool(v), "encoder": s["encoder"]}, series=sc) for v in s["values"]]
        elif study == "occlusion":
            for enc in s["encoders"]:
                for mode in s["modes"]:
                    for r in s["radii_mm"]:
                        pts.append(StudyPoint(
                            study, sc, float(r), f"{enc}/{mode}/{float(r):g}mm",
                            {"encoder": str(enc), "occlusion": {"radius_mm": float(r), "mode": str(mode)}},
                            series=f"{sc} {enc} {mode}"))
        elif study == "noise":
            pts += [StudyPoint(study, sc, float(v), f"{float(v):g}mm", {"noise_mm": float(v)}, series=sc)
                    for v in s["values"]]
        elif study == "train_size":
            pts += [StudyPoint(study, sc, float(v), f"{float(v):g}", train_fraction=float(v), series=sc)
                    for v in s["values"]]
        elif study == "train_livers":
            pts += [StudyPoint(study, sc, int(v), f"{int(v)} liver{'s' if int(v) != 1 else ''}", train_livers=int(v),
                               series=sc)
                    for v in s["values"]]
        else:
            raise ValueError(f"unknown study '{study}': use one of {STUDIES}")
    return pts


def hyper_parameters(main_metrics: dict | None, model_cfg: dict, train_cfg: dict, source: str = "main") -> dict:
    """Regressor hyper-parameters of the study points: ``hidden``, ``dropout``, ``lr``, ``batch_size``.

    ``source="main"``: the main model's tuned values (``best_params`` of its
    ``metrics.json``: Ax's ``n_layers`` x ``width``, or the fixed ``hidden``
    when it was not tuned); ``"config"``: ``model.hidden``, ``model.dropout``,
    ``train.lr``, ``train.batch_size``.
    """
    hp = {"hidden": [int(h) for h in model_cfg["hidden"]], "dropout": float(model_cfg["dropout"]),
          "lr": float(train_cfg["lr"]), "batch_size": int(train_cfg["batch_size"]), "source": "config"}
    if source == "main" and main_metrics and main_metrics.get("best_params"):
        b = main_metrics["best_params"]
        if "n_layers" in b and "width" in b:
            hp["hidden"] = [int(b["width"])] * int(b["n_layers"])
        elif "hidden" in b:
            hp["hidden"] = [int(h) for h in b["hidden"]]
        for k, cast in (("dropout", float), ("lr", float), ("batch_size", int)):
            if k in b:
                hp[k] = cast(b[k])
        hp["source"] = f"main model run {main_metrics.get('run_id')}"
    return hp


# --------------------------------------------------------------------------
# one study point
# --------------------------------------------------------------------------


def run_point(
    arrays: dict,
    model_cfg: dict,
    hp: dict,
    *,
    scenario: str,
    seed: int,
    test_fraction: float,
    epochs: int,
    threads: int = 1,
    roi_fraction: float | None = None,
    surfaces: dict | None = None,
    train_fraction: float | None = None,
    train_livers: int | None = None,
) -> dict:
    """Train one model on part of the main model's training split (no tuning); score it on the rest.

    The main model's test split is never read: the point trains on the training
    split minus a validation part (:func:`validation_split`, by liver in IV) and is
    scored on that validation part.

    Parameters
    ----------
    arrays : dict
        Converged cases of one scenario (input contract; with
        ``surface_displacement_mm`` when ``roi_fraction`` is given).
    model_cfg : dict
        The ``model`` slice with the point's overrides merged in.
    hp : dict
        :func:`hyper_parameters`.
    scenario : str
        ``I``..``IV`` (IV splits by geometry).
    seed : int
        Split, weights and observation-noise seed (the main model's, so its test
        split is the one left out; the validation split derives from it).
    test_fraction, epochs, threads
        As in ``train``; ``epochs`` is ``study.epochs``.
    roi_fraction, surfaces
        Re-select the ROI at this area fraction (``surfaces``: geometry id ->
        SurfaceGraph) before anything else.
    train_fraction
        Train on a seeded random subset of this fraction of the fitting part
        (every geometry keeps its share); the validation split is unchanged.
    train_livers
        Train on the cases of this many training geometries only (a seeded
        order of the training geometries, so 2 livers are a subset of 4, ...;
        all of them when there are fewer); the validation split is unchanged.

    Returns
    -------
    dict
        ``metrics`` (validation split, N and %), ``n_train``, ``n_val``, ``roi_nodes_mean``
        (ROI nodes per case), ``seconds``, ``representation``.
    """
    t0, c0 = time.perf_counter(), time.process_time()
    configure_torch(threads)
    with threadpool_limits(limits=int(threads)):
        if roi_fraction is not None:
            if surfaces is None:
                raise ValueError("an ROI fraction needs the surface graphs of the geometries")
            arrays = with_roi_fraction(arrays, roi_fraction, surfaces)
        # the main model's split: its test part is dropped here, before anything reads it
        main_tr, _ = train_test_split(np.asarray(arrays["geometry_id"]).astype(str), scenario=scenario,
                                      test_fraction=float(test_fraction), seed=int(seed))
        arrays = subset(arrays, main_tr)
        geo = np.asarray(arrays["geometry_id"]).astype(str)
        tr, te = validation_split(geo, scenario, float(test_fraction), int(seed))
        if train_fraction is not None and train_fraction < 1.0:
            tr = subsample_per_geometry(tr, geo, float(train_fraction), seed=int(seed))
        if train_livers is not None:
            tr = first_geometries(tr, geo, int(train_livers), seed=int(seed))
        train_arrays, test_arrays = subset(arrays, tr), subset(arrays, te)
        rep = representation_from_config(model_cfg, train_arrays)
        prep_train = prepare(train_arrays, rep, observation_seeds=view_seeds(seed, n_views_for(rep)))
        fit = fit_params(model_cfg, lr=float(hp["lr"]), batch_size=int(hp["batch_size"]), epochs=int(epochs),
                         weight_decay=float(hp.get("weight_decay", 0.0)))
        model, history = fit_force_model(
            prep_train, rep, encoder=str(model_cfg["encoder"]), code_size=int(model_cfg["code_size"]),
            use_state=bool(model_cfg["state_vector"]), hidden=list(hp["hidden"]), dropout=float(hp["dropout"]),
            fit=fit, seed=int(seed), dae_input_noise=float(model_cfg.get("dae_input_noise", 0.1)),
            **state_options(model_cfg),
        )
        pred = model.predict(test_arrays, observation_seed=eval_seed(seed))
    metrics = force_metrics(np.asarray(test_arrays["force_n"], dtype=np.float64), pred)
    return {
        "metrics": metrics,
        "evaluated_on": "validation",
        "n_train": int(len(tr)),
        "n_val": int(len(te)),
        "n_train_geometries": int(len(set(geo[tr].tolist()))),
        "val_geometries": sorted(set(geo[te].tolist())),
        "roi_nodes_mean": float(np.mean([len(x) for x in arrays["roi_undeformed_mm"]])),
        "roi_area_fraction_mean": (float(np.mean(arrays["roi_area_fraction"])) if "roi_area_fraction" in arrays
                                   else None),
        "final_train_loss": float(history["train_loss"][-1]),
        "representation": rep.to_dict(),
        "seconds": time.perf_counter() - t0,
        "cpu_seconds": time.process_time() - c0,
    }


def validation_split(geometry_ids, scenario: str, fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``(fit, validation)`` indices of the main model's *training* cases for a study point.

    Split like the test split (by liver in IV) with stage ``split.study``, so a study
    point is scored on training-side cases only: choosing a setting from a study
    never selects on the test split, which stays for the main models' single score.
    """
    return train_test_split(np.asarray(geometry_ids).astype(str), scenario=scenario, test_fraction=fraction,
                            seed=derive(seed, "split.study"))


def subsample_per_geometry(idx, geometry_ids, fraction: float, seed: int) -> np.ndarray:
    """A seeded subset of ``fraction`` of the indices ``idx``, taken per geometry (each keeps >= 1 case)."""
    if not 0 < fraction <= 1:
        raise ValueError(f"train fraction must be in (0, 1], got {fraction}")
    idx = np.asarray(idx)
    geo = np.asarray(geometry_ids)[idx]
    rng = np.random.default_rng(derive(seed, "study.train_size"))
    keep = []
    for g in np.unique(geo):
        members = idx[geo == g]
        n = max(1, int(round(fraction * len(members))))
        keep.append(rng.choice(members, size=n, replace=False))
    return np.sort(np.concatenate(keep))


def first_geometries(idx, geometry_ids, k: int, seed: int) -> np.ndarray:
    """The indices ``idx`` of the first ``k`` geometries in a seeded order of those ``idx`` covers.

    The order depends on the seed and the set of geometries only, so the
    subsets are nested (the first 2 are among the first 4). ``k`` larger than
    the number of geometries keeps them all.
    """
    if k < 1:
        raise ValueError(f"the number of training livers must be >= 1, got {k}")
    idx = np.asarray(idx)
    geo = np.asarray(geometry_ids).astype(str)[idx]
    order = np.random.default_rng(derive(seed, "study.train_livers")).permutation(np.unique(geo))
    return np.sort(idx[np.isin(geo, order[:k])])


# --------------------------------------------------------------------------
# a whole study
# --------------------------------------------------------------------------


def run_study(
    study: str,
    study_cfg: dict,
    data: dict[str, dict],
    model_cfg: dict,
    main_metrics: dict[str, dict | None],
    train_cfg: dict,
    *,
    seed: int,
    threads: int = 1,
    surfaces: dict | None = None,
    tracker=None,
    tags: dict | None = None,
) -> dict:
    """Run every point of one study; returns the study document (``studies/<study>.json``).

    Parameters
    ----------
    data : dict
        scenario -> converged-case arrays.
    model_cfg : dict
        The main variant's model config (points override it).
    main_metrics : dict
        scenario -> the main model's ``metrics.json`` (or None).
    tracker : optional
        Each point becomes one MLflow run tagged ``study``, ``value``,
        ``scenario``, ``label``; its id is in the document.
    """
    t0, c0 = time.perf_counter(), time.process_time()
    epochs = int(study_cfg["epochs"])
    points_out = []
    done: dict[str, dict] = {}  # identical settings (e.g. radius 0 in both occlusion modes) are trained once
    for pt in study_points(study, study_cfg):
        mcfg = merge_mapping(model_cfg, pt.model_overrides)
        hp = hyper_parameters(main_metrics.get(pt.scenario), model_cfg, train_cfg,
                              str(study_cfg.get("hyper_parameters", "main")))
        if mcfg["occlusion"]["radius_mm"] == 0:
            mcfg = merge_mapping(mcfg, {"occlusion": {"mode": "remove"}})  # no occlusion: the mode does not matter
        key = json.dumps([pt.scenario, mcfg, pt.roi_fraction, pt.train_fraction, pt.train_livers, hp],
                         sort_keys=True, default=str)
        doc: dict[str, Any] = {"study": study, "scenario": pt.scenario, "value": pt.value, "label": pt.label,
                               "series": pt.series, "overrides": pt.model_overrides, "roi_fraction": pt.roi_fraction,
                               "train_fraction": pt.train_fraction, "train_livers": pt.train_livers,
                               "encoder": mcfg["encoder"], "state_vector": bool(mcfg["state_vector"]),
                               "hyper_parameters": hp, "epochs": epochs}
        try:
            if key in done:
                doc.update(done[key], status="ok", same_as=done[key]["label"])
            else:
                res = run_point(data[pt.scenario], mcfg, hp, scenario=pt.scenario, seed=seed,
                                test_fraction=float(train_cfg["test_fraction"]), epochs=epochs, threads=threads,
                                roi_fraction=pt.roi_fraction, surfaces=surfaces, train_fraction=pt.train_fraction,
                                train_livers=pt.train_livers)
                done[key] = {**res, "label": pt.label}
                doc.update(res, status="ok")
            doc["label"] = pt.label
        except (ValueError, RuntimeError) as exc:  # a point that cannot be trained is recorded, not fatal
            log.warning("study %s, %s %s: failed: %s", study, pt.scenario, pt.label, exc)
            doc.update(status="failed", reason=f"{type(exc).__name__}: {exc}", metrics={})
        if tracker is not None:
            params = {"study": study, "scenario": pt.scenario, "value": pt.value, "label": pt.label,
                      "encoder": mcfg["encoder"], "state_vector": bool(mcfg["state_vector"]),
                      "occlusion.radius_mm": mcfg["occlusion"]["radius_mm"], "occlusion.mode": mcfg["occlusion"]["mode"],
                      "noise_mm": mcfg["noise_mm"], "roi_fraction": pt.roi_fraction, "epochs": epochs,
                      "train_fraction": pt.train_fraction, "train_livers": pt.train_livers,
                      "seed": seed, "hidden": hp["hidden"], "dropout": hp["dropout"], "lr": hp["lr"],
                      "batch_size": hp["batch_size"], "hyper_parameters_from": hp["source"]}
            run_tags = {"rule": "study", "study": study, "value": str(pt.value), "scenario": pt.scenario,
                        "label": pt.label, **{k: str(v) for k, v in (tags or {}).items()}}
            run_id = tracker.start_run(f"{study}-{pt.scenario}-{pt.label}", params=params, tags=run_tags)
            if doc["status"] == "ok":
                tracker.log_metrics(run_id, {**doc["metrics"], "roi_nodes_mean": doc["roi_nodes_mean"],
                                             "wall_time_s": doc["seconds"]})
            tracker.end_run(run_id, status="FINISHED" if doc["status"] == "ok" else "FAILED")
            doc["run_id"] = run_id
        if doc["status"] == "ok":
            log.info("study %s, %s %s: accuracy %.1f %%, MAE %.3f N (%.1f s)", study, pt.scenario, pt.label,
                     doc["metrics"]["accuracy_pct"], doc["metrics"]["mae_vec"], doc["seconds"])
        points_out.append(doc)
    return {
        "study": study,
        "title": STUDY_TITLES[study][0],
        "x_label": STUDY_TITLES[study][1],
        "epochs": epochs,
        "seed": seed,
        "points": points_out,
        "seconds": time.perf_counter() - t0,
        "cpu_seconds": time.process_time() - c0,
        "experiment_name": getattr(tracker, "experiment_name", None),
    }


def plot_study(doc: dict, path: str | Path) -> Path:
    """Accuracy % (left) and MAE in N (right) against the studied value, one curve per series."""
    from liverforce.learn.plots import _plt

    plt = _plt()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6), dpi=100)
    pts = [p for p in doc["points"] if p["status"] == "ok"]
    series = list(dict.fromkeys(p["series"] for p in doc["points"]))
    categorical = doc["study"] in ("encoder", "state_vector")
    cats = list(dict.fromkeys(p["label"] for p in doc["points"])) if categorical else []
    for k, s in enumerate(series):
        sp = [p for p in pts if p["series"] == s]
        if not sp:
            continue
        if categorical:
            width = 0.8 / max(1, len(series))
            x = np.array([cats.index(p["label"]) for p in sp]) + (k - (len(series) - 1) / 2) * width
            axes[0].bar(x, [p["metrics"]["accuracy_pct"] for p in sp], width, label=s)
            axes[1].bar(x, [p["metrics"]["mae_vec"] for p in sp], width, label=s)
        else:
            # the livers curve is over the livers actually used (a requested count above the population is "all")
            x = [float(p.get("n_train_geometries") or p["value"]) if doc["study"] == "train_livers" else float(p["value"])
                 for p in sp]
            axes[0].plot(x, [p["metrics"]["accuracy_pct"] for p in sp], "o-", label=s)
            axes[1].plot(x, [p["metrics"]["mae_vec"] for p in sp], "o-", label=s)
    for ax, name in zip(axes, ("accuracy % (validation split)", "MAE of the force vector (N)")):
        ax.set_ylabel(name)
        ax.set_xlabel(doc["x_label"])
        if categorical:
            ax.set_xticks(range(len(cats)), cats)
        elif doc["study"] == "train_livers":
            ax.set_xscale("log", base=2)
            ticks = sorted({int(p.get("n_train_geometries") or p["value"]) for p in pts})
            ax.set_xticks(ticks, [str(t) for t in ticks])
            ax.minorticks_off()
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, title="scenario", title_fontsize=7, loc="lower left" if categorical else "best")
    fig.suptitle(doc["title"], fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp)
    plt.close(fig)
    return Path(path)
