"""The run report: one HTML page (tables + PNG figures) a surgeon-engineer can read.

Every number in the report is read from the stage outputs (``metrics.json`` of
each model, the shard manifests and shards, the validation metrics, the study
results ``studies/<study>.json``), and every number that comes from a model
names the MLflow run it was logged to, so the report can be checked against
the tracking store (``tests/test_smoke_workflow.py`` does).

Sections, in order: the headline (the study's Table 5.9 layout with our
numbers, mean ± sd over repeated seeded splits, beside the study's; encoders;
the unseen-liver MAE as mean ± sd over the unseen livers); the setup (the
liver population as a picture, the geometries, material, boundary, sweep);
simulations and solver statistics; every trained model; the unseen-liver
validation (per liver, mean ± sd, the worst liver, error against force
magnitude, every variant) with its figures; the comparison studies with their
plots (the learning curve over livers among them); where the MLflow runs are.
"""

from __future__ import annotations

import html
import json
import os
from pathlib import Path

import numpy as np

from liverforce.atomic import atomic_path, write_text_atomic
from liverforce.layout import gid_of, model_of_metrics, scenario_of_manifest, study_picture_of
from liverforce.report.heldout import ACCURACY_FLOOR_PCT, flag_accuracy, heldout_cell
from liverforce.report.heldout import pm as _pm  # mean ± sd, as in the held-out cell (one helper)
from liverforce.report.imported import geometry_record, given_points, imported_section, is_imported

#: the study's accuracies (Table 5.9), % — deformation only / with state vector
STUDY_ACCURACY = {
    "I": {"without": 92.1, "with": 95.8},
    "II": {"without": 78.1, "with": 91.2},
    "III": {"without": 69.1, "with": 88.5},
    "IV": {"without": 65.7, "with": 84.8},
}
STUDY_VALIDATION_MAE_N = 0.249
STUDY_OCCLUSION_COST_POINTS = 4.2
#: a force bin whose MAE is at least this fraction of its mean force is flagged (issue target: below 20 %)
REL_MAE_LIMIT = 0.20
#: the camera-cloud model should be within this many accuracy points of the correspondence model (issue 15)
CAMERA_GAP_LIMIT = 2.0
#: ... and its MAE on the unseen livers (mean over the livers) at most this, N (issue 15)
CAMERA_UNSEEN_MAE_LIMIT_N = 0.2
SCENARIO_TEXT = {
    "I": "fixed exertion point, one liver, one material",
    "II": "exertion point varies, one liver, one material",
    "III": "exertion point and material vary, one liver",
    "IV": "exertion point, material and liver vary (test livers unseen in training)",
}
STUDY_TEXT = {
    "roi_fraction": "How much of the liver surface around the tool the camera must see. The ROI is re-grown "
                    "from the stored full-surface displacements at each fraction (no new simulation). The study "
                    "judged 18 % enough.",
    "encoder": "How the ROI grid is compressed before the regressor: PCA, an autoencoder (AE) or a denoising "
               "autoencoder (DAE, trained to undo occlusion and noise).",
    "state_vector": "Deformation alone vs deformation plus the pre-operative state vector (liver centroid, ROI "
                    "centroids, inertia tensor, material constants, in the local frame).",
    "occlusion": "The tool hides the surface around it: nodes within the radius are removed before resampling "
                 "(remove) or replaced by noise (noise). The study reported a cost of 4.2 accuracy points.",
    "noise": "Gaussian noise on every observed point (a stereo endoscope reconstructs the surface with roughly "
             "0.5-2 mm error).",
    "train_size": "Learning curve: the same model trained on a fraction of the fitting part, scored on the same "
                  "validation split. A curve still rising at 1.0 means more simulated cases would raise the accuracy.",
    "train_livers": "Learning curve over the liver population (scenario IV): the same model trained on the cases of "
                    "2, 4, 8, … training livers, scored on the same held-out validation livers. A curve still rising at the "
                    "largest count means more livers (not more cases per liver) would raise the accuracy on a new "
                    "patient.",
}


def _fitted_widening(g) -> str:
    """How an interval with ``widen: fitted`` widens outside the calibration's stiffness range, from its exponents
    ``g`` (t1, t2, n; :func:`liverforce.learn.interval.stiffness_exponent_fit`)."""
    say = ("widened outside the calibration livers' stiffness range as far as the calibration residuals grow with "
           f"the stiffness (|r| ~ k^g, g = {' / '.join(f'{v:.2f}' for v in g)} for t1 / t2 / n: ")
    if all(v == 0 for v in g):
        return say + "they do not, so no liver is widened)"
    if all(v <= 0 for v in g):
        return say + ("they shrink as the stiffness grows, so a stiffer liver's widths are not widened and a softer "
                      "one's grow by (k_lo / k)^-g)")
    if all(v >= 0 for v in g):
        return say + ("they grow with it, so a stiffer liver's widths grow by (k / k_hi)^g and a softer one's are not "
                      "widened)")
    return say + ("a stiffer liver's widths grow by (k / k_hi)^g where g is positive, a softer one's by "
                  "(k_lo / k)^-g where g is negative)")


def _rel(path: str | Path, start: Path) -> str:
    return html.escape(os.path.relpath(Path(path).resolve(), start.resolve()))


def _table(header: list[str], rows: list[list], cls: str = "", row_cls: str = "") -> str:
    th = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    tr = f"<tr class='{row_cls}'>" if row_cls else "<tr>"
    body = "".join(tr + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows)
    c = f" class='{cls}'" if cls else ""
    return f"<table{c}><thead><tr>{th}</tr></thead><tbody>{body}</tbody></table>"


def _fmt(v, nd=3) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        return "–" if not np.isfinite(v) else f"{v:.{nd}f}"
    return html.escape(str(v))


def _flagged(text: str, missed: bool) -> str:
    """``text`` marked as missing its target (red, ⚠) when ``missed``."""
    return f"<b class='flag'>{text} ⚠</b>" if missed else text


def _worst_bin(bins) -> str:
    """The force bin with the largest relative MAE, as "x % (lo–hi N)", flagged at or above the target."""
    scored = [(r, b) for b in (bins or []) if (r := _rel_mae(b)) is not None]
    if not scored:
        return "–"
    r, b = max(scored, key=lambda t: t[0])
    text = f"{100 * r:.1f} % ({b['force_lo_n']:.2f}–{b['force_hi_n']:.2f} N)"
    return _flagged(text, r >= REL_MAE_LIMIT)


def _rel_mae(b: dict) -> float | None:
    """Relative MAE of a force bin: ``relative_mae``, else MAE / mean force (None when neither is known)."""
    r = b.get("relative_mae")
    if r is None and b.get("mean_force_n"):
        r = b["mae_vec_n"] / b["mean_force_n"]
    return None if r is None or not np.isfinite(r) else float(r)


def _run(run_id) -> str:
    return f"<code>{html.escape(str(run_id))}</code>"


def _small_run(run_id) -> str:
    return f"<br><small>run <code>{html.escape(str(run_id))}</code></small>" if run_id else ""


def _figure(src: str | Path, out_dir: Path, caption: str = "", width: int = 420) -> str:
    cap = f"<figcaption>{html.escape(caption)}</figcaption>" if caption else ""
    return f"<figure><img src='{_rel(src, out_dir)}' width='{width}'>{cap}</figure>"


# --------------------------------------------------------------------------
# collect
# --------------------------------------------------------------------------


def _scale_words(setup: dict) -> str:
    """Whether the unseen livers' constants (the material's x ``validate.material_scale``) lie outside the
    training range (each constant drawn within +-``material.vary_rel``), in words; then each held-out liver
    with its own material (``geometry.imported[].material``), which is not scaled."""
    scale = (setup.get("validate") or {}).get("material_scale")
    rel = (setup.get("material") or {}).get("vary_rel")
    if scale is None or rel is None:
        return "outside the training range"  # an older setup without them: the default's 1.4 against +-30 %
    mats = _own_materials(setup)
    run = (setup.get("material") or {}).get("params_mpa") or {}
    inside = (mats["inside"]({k: float(v) * float(scale) for k, v in run.items()}) if run and mats["centred"]
              else 1.0 - float(rel) <= float(scale) <= 1.0 + float(rel))
    own = mats["unseen"]
    words = [] if own and not _scaled_unseen(setup) else ["within the training range" if inside
                                                          else "outside the training range"]
    words += [f"<code>{html.escape(g)}</code>: its own, {html.escape(p)} MPa, {'within' if ok else 'outside'} the "
              "training range" for g, p, ok in own]
    return "; ".join(words)


def _scaled_unseen(setup: dict) -> bool:
    """Whether some unseen liver takes the run's constants x ``validate.material_scale`` (not its own)."""
    unseen = (setup.get("population") or {}).get("unseen")
    return unseen is None or any(g not in (setup.get("liver_materials") or {}) for g in unseen)


def _entered_words(entered: dict) -> str:
    """A liver's material as the lab entered it (``{"E_pa": 9000}``, ``{"params_mpa": {"C10": 0.0015}}``), in
    words: ``E_pa 9000``, ``params_mpa C10 0.0015``."""
    return ", ".join(f"{k} " + (", ".join(f"{n} {x:g}" if isinstance(x, (int, float)) else f"{n} {x}"
                                          for n, x in v.items()) if isinstance(v, dict) else f"{v}")
                     for k, v in entered.items())


def _own_materials(setup: dict) -> dict:
    """The imported livers with their own material (``setup["liver_materials"]``, :meth:`Plan.liver_materials`):
    ``{"unseen": [(gid, constants in words, inside the training range)], "training": [(gid, words, entered)],
    "inside": <constants -> bool>, "centred": <some training liver has its own>}``.

    The training range: around each training liver's centre (its own constants, else the run's), every constant
    within +-``material.vary_rel`` of that one centre where scenario IV varies the material, the centres alone
    where it does not. A set is inside when one training liver's range holds all its constants.
    """
    own = setup.get("liver_materials") or {}
    pop = setup.get("population") or {}
    mat = setup.get("material") or {}
    unseen, training = set(pop.get("unseen") or []), list(pop.get("training") or [])
    varies = str(((setup.get("sweep") or {}).get("scenarios") or {}).get("IV", {}).get("material")) == "varies"
    rel = float(mat.get("vary_rel") or 0.0) if varies else 0.0
    run = mat.get("params_mpa") or {}
    centres = [(own.get(g) or {}).get("params_mpa") or run for g in training] or [run]

    def words(p):
        return ", ".join(f"{k} {float(v):.4g}" for k, v in p.items())

    def inside(p):
        return any(all(c.get(k) is not None and (1 - rel) * c[k] * (1 - 1e-9) <= v <= (1 + rel) * c[k] * (1 + 1e-9)
                       for k, v in p.items()) for c in centres)

    out = {"unseen": [], "training": [], "inside": inside, "centred": any(g in own for g in training)}
    for gid, m in sorted(own.items()):
        p = m.get("params_mpa") or {}
        if gid in unseen:
            out["unseen"].append((gid, words(p), inside(p)))
        else:
            out["training"].append((gid, words(p), m.get("entered")))
    return out


def _unseen_kinds(unseen) -> str:
    """The unseen livers in words: the procedural ones (``val-…``, held-out seeds) and a lab's own livers held
    out of training (``validate.imported``, named)."""
    ids = sorted(str(g) for g in unseen)
    proc = [g for g in ids if g.startswith("val-")]
    own = [g for g in ids if not g.startswith("val-")]
    words = [f"{len(proc)} procedural, <code>val-…</code>, held-out seeds"] if proc else []
    if own:
        words.append(f"{len(own)} imported and held out of training: "
                     + ", ".join(f"<code>{html.escape(g)}</code>" for g in own))
    return "; ".join(words) or "none"


def _spread(sd: dict | None, n) -> dict:
    """The sds of a summary over ``n`` splits or livers: none (``{}``, so no ± is printed) for fewer than two (the
    records give 0.0 for one: not a spread of zero but none measured); as recorded when the count is unknown."""
    return dict(sd or {}) if n is None or n >= 2 else {}


def _one_spread(summary: dict | None) -> dict | None:
    """A summary over splits (``n_splits``, ``metrics_sd``) with its sds dropped for one split (:func:`_spread`)."""
    if not summary:
        return summary
    return {**summary, "metrics_sd": _spread(summary.get("metrics_sd"), summary.get("n_splits"))}


def collect(model_metrics: list[str | Path], manifests: list[str | Path], validation: str | Path,
            features: list[str | Path], studies: list[str | Path] = ()) -> dict:
    """Read every number the report shows (also used by the report tests)."""
    models = []
    for p in model_metrics:
        m = json.loads(Path(p).read_text())
        models.append({
            "scenario": m.get("scenario") or model_of_metrics(p)[0],
            "variant": m.get("variant") or model_of_metrics(p)[1],
            "state_vector": m.get("state_vector"), "encoder": m.get("encoder"),
            "metrics": m.get("metrics", {}), "run_id": m.get("run_id"), "n_cases": m.get("n_cases"),
            "n_train": m.get("n_train"), "n_test": m.get("n_test"), "best_params": m.get("best_params"),
            "seconds": m.get("seconds"), "path": str(p),
            "metrics_mean": m.get("metrics_mean") or {},
            "metrics_sd": _spread(m.get("metrics_sd"), m.get("n_splits")),
            "n_splits": m.get("n_splits"), "repeats": m.get("repeats") or [],
            "model_cfg": m.get("model_cfg") or {}, "heldout_points": m.get("heldout_points"),
            "outside_training": m.get("outside_training"), "exact_tip": _one_spread(m.get("exact_tip")),
            "final_fit": m.get("final_fit"),
        })
    shards = []
    for p in manifests:
        m = json.loads(Path(p).read_text())
        shards.append({"scenario": scenario_of_manifest(p), "rows": m["rows"], "failed": m["failed"],
                       "shards": len(m["shards"]), "data_version": m["data_version"], "manifest": str(p)})
    val = json.loads(Path(validation).read_text())
    missing = [k for k in ("per_liver", "livers", "error_by_force_magnitude") if k not in val]
    if missing:
        raise ValueError(f"{validation}: no {', '.join(missing)} (a validation from before the set of unseen "
                         "livers); re-run the validate stage (snakemake --forcerun validate) and then the report")
    n_livers = val["livers"].get("n")  # every variant is validated on the same livers (its record has no count)
    val["livers"] = {**val["livers"], "sd": _spread(val["livers"].get("sd"), n_livers)}
    for d in (val.get("all_variants") or {}).values():
        if d.get("livers"):
            d["livers"] = {**d["livers"], "sd": _spread(d["livers"].get("sd"), d["livers"].get("n", n_livers))}
    geoms = []
    for p in features:
        f = json.loads(Path(p).read_text())
        rec = geometry_record(p)
        geoms.append({"id": gid_of(p), **f, **({"geometry_record": rec} if rec is not None else {})})
    study_docs = []
    for p in studies:
        d = json.loads(Path(p).read_text())
        d["path"] = str(p)
        study_docs.append(d)
    return {"models": models, "shards": shards, "validation": val, "geometries": geoms, "studies": study_docs}


# --------------------------------------------------------------------------
# the Table 5.9 layout
# --------------------------------------------------------------------------


#: the label of a headline cell's single split: the saved model's own, or the main split of a model refitted on
#: every case (``train.final_fit``)
SPLIT_LABEL = {False: "saved model's split", True: "main split"}


def table59(data: dict, main_variant: str | None = None) -> list[dict]:
    """Per scenario: our accuracy/MAE without and with the state vector, the study's, and the source run.

    Each cell: ``accuracy_mean`` ± ``accuracy_sd`` and ``mae_mean`` ±
    ``mae_sd`` over the model's ``n_splits`` repeated seeded train/test splits
    (``metrics_mean`` / ``metrics_sd`` of its ``metrics.json``; None when the
    cell comes from a study point, which has one split), and
    ``accuracy_pct`` / ``mae_vec`` of the main split (the one its MLflow run
    logs as ``accuracy_pct``; the saved model's own split unless it was refitted
    on every case, ``final_fit``).

    Preference for each cell: a fully trained (Ax-tuned) model variant — the
    main variant, else the same encoder, else any — then a point of the
    ``state_vector`` study (trained without Ax), marked as such.
    """
    out = []
    scenarios = sorted({m["scenario"] for m in data["models"]}, key=lambda s: ("I", "II", "III", "IV").index(s)
                       if s in ("I", "II", "III", "IV") else 9)
    sv_study = next((d for d in data.get("studies", []) if d["study"] == "state_vector"), None)
    for sc in scenarios:
        row = {"scenario": sc}
        ms = [m for m in data["models"] if m["scenario"] == sc]
        main = next((m for m in ms if m["variant"] == main_variant), ms[0] if ms else None)
        for key, want in (("without", False), ("with", True)):
            cands = [m for m in ms if bool(m.get("state_vector")) == want]
            cands.sort(key=lambda m: (m is not main, m.get("encoder") != (main or {}).get("encoder"), m["variant"]))
            cell = None
            if cands:
                m = cands[0]
                mean, sd = m.get("metrics_mean") or {}, m.get("metrics_sd") or {}
                cell = {"accuracy_pct": m["metrics"].get("accuracy_pct"), "mae_vec": m["metrics"].get("mae_vec"),
                        "accuracy_mean": mean.get("accuracy_pct"), "accuracy_sd": sd.get("accuracy_pct"),
                        "mae_mean": mean.get("mae_vec"), "mae_sd": sd.get("mae_vec"),
                        "n_splits": m.get("n_splits"), "run_id": m["run_id"], "source": f"model {m['variant']}",
                        "final_fit": bool(m.get("final_fit"))}
            elif sv_study:
                p = next((p for p in sv_study["points"] if p["scenario"] == sc and p["status"] == "ok"
                          and bool(p["state_vector"]) == want), None)
                if p:
                    cell = {"accuracy_pct": p["metrics"]["accuracy_pct"], "mae_vec": p["metrics"]["mae_vec"],
                            "accuracy_mean": None, "accuracy_sd": None, "mae_mean": None, "mae_sd": None,
                            "n_splits": 1, "run_id": p.get("run_id"), "final_fit": False,
                            "source": f"state-vector study ({p['encoder']}, no Ax, one split)"}
            row[key] = cell
            row[f"study_{key}"] = STUDY_ACCURACY.get(sc, {}).get(key)
        out.append(row)
    return out


def livers_curve_text(doc: dict) -> str:
    """One measured sentence on the ``train_livers`` study: does accuracy still rise with more livers?

    Compares the two points with the most training livers actually used
    (``n_train_geometries``; a requested count above the training livers
    available uses them all, so such points coincide).
    """
    pts = {}
    for p in doc["points"]:
        if p["status"] == "ok" and p.get("n_train_geometries"):
            pts.setdefault(int(p["n_train_geometries"]), p)  # same count twice: the same model
    if len(pts) < 2:
        return "<p>Fewer than two distinct numbers of training livers: no trend to read.</p>"
    ks = sorted(pts)
    a, b = pts[ks[-2]], pts[ks[-1]]
    d_acc = b["metrics"]["accuracy_pct"] - a["metrics"]["accuracy_pct"]
    d_mae = b["metrics"]["mae_vec"] - a["metrics"]["mae_vec"]
    capped = [p["label"] for p in doc["points"] if p.get("train_livers") and p.get("n_train_geometries")
              and int(p["train_livers"]) > int(p["n_train_geometries"])]
    note = (f" (requested {', '.join(html.escape(c) for c in capped)}: only {ks[-1]} training livers exist, so "
            "those points use them all)") if capped else ""
    return (f"<p class='livers-trend'>From {ks[-2]} to {ks[-1]} training livers the accuracy on the fixed validation "
            f"livers changed by <b>{d_acc:+.1f} points</b> and the MAE by {d_mae:+.3f} N{note}. One split per "
            f"point: read changes of a few points against the ± sd of Table 5.9.</p>")


# --------------------------------------------------------------------------
# figures made by the report
# --------------------------------------------------------------------------


def validation_figures(val: dict, out_dir: Path) -> dict[str, Path]:
    """Error per unseen liver, vs force magnitude and vs distance from the training exertion points (PNG).

    Returns ``{"per_liver" | "force" | "distance": path}`` for the figures the data allow.
    """
    from liverforce.learn.plots import _plt

    plt = _plt()
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {}

    def save(fig, key, name):
        path = out_dir / name
        fig.tight_layout()
        with atomic_path(path) as tmp:
            fig.savefig(tmp, format="png")
        plt.close(fig)
        paths[key] = path

    per = val.get("per_liver") or {}
    if per:
        ids = list(per)
        mae = np.array([per[g]["mae_vec"] for g in ids])
        lv = val["livers"]
        fig, ax = plt.subplots(figsize=(max(4.6, 0.45 * len(ids) + 1.5), 3.6), dpi=100)
        colours = ["C3" if g == lv["worst"] else "C1" for g in ids]
        ax.bar(range(len(ids)), mae, color=colours)
        m, sd = lv["mean"]["mae_vec"], (lv.get("sd") or {}).get("mae_vec")
        if sd is not None:
            ax.axhspan(m - sd, m + sd, color="0.85", zorder=0, label=f"mean ± sd {m:.3f} ± {sd:.3f} N")
        ax.axhline(m, color="0.3", lw=1, **({} if sd is not None else {"label": f"mean {m:.3f} N (one liver)"}))
        ax.set_xticks(range(len(ids)))
        ax.set_xticklabels(ids, rotation=45, ha="right", fontsize=7)
        ax.set_ylabel("MAE (N)")
        ax.set_title(f"MAE per unseen liver (worst: {lv['worst']})", fontsize=9)
        ax.set_ylim(0, float(mae.max()) * 1.3)  # head room for the legend
        ax.legend(fontsize=7, loc="upper left")
        ax.grid(alpha=0.3, axis="y")
        save(fig, "per_liver", "validation_mae_per_liver.png")
    pred = val.get("predictions") or {}
    if pred.get("true_n"):
        t = np.asarray(pred["true_n"], dtype=float)
        p = np.asarray(pred["pred_n"], dtype=float)
        err = np.linalg.norm(p - t, axis=1)
        mag = np.linalg.norm(t, axis=1)
        fig, ax = plt.subplots(figsize=(4.6, 3.9), dpi=100)
        ax.scatter(mag, err, s=10, alpha=0.6, label="case")
        line = np.array([0.0, float(mag.max())])
        ax.plot(line, REL_MAE_LIMIT * line, "--", color="0.4", lw=1, label=f"{100 * REL_MAE_LIMIT:.0f} % of |F|")
        bins = val.get("error_by_force_magnitude", [])
        if bins:
            ax.plot([b.get("mean_force_n", (b["force_lo_n"] + b["force_hi_n"]) / 2) for b in bins],
                    [b["mae_vec_n"] for b in bins], "o-", color="C3", label="MAE per bin")
        ax.set_xlabel("true |F| (N)")
        ax.set_ylabel("|F_pred − F_true| (N)")
        ax.set_title("unseen livers: error vs force magnitude", fontsize=9)
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=3, frameon=False)  # off the data
        ax.grid(alpha=0.3)
        save(fig, "force", "validation_error_vs_force.png")
    ed = val.get("error_vs_distance") or {}
    if ed.get("distance_mm"):
        fig, ax = plt.subplots(figsize=(4.6, 3.6), dpi=100)
        ax.scatter(ed["distance_mm"], ed["error_n"], s=10, alpha=0.7)
        ax.set_xlabel("distance to nearest training exertion point (mm)")
        ax.set_ylabel("|F_pred − F_true| (N)")
        r = val.get("corr_error_distance")
        ax.set_title(f"unseen livers: error vs distance (r = {_fmt(r, 2)})", fontsize=9)
        ax.grid(alpha=0.3)
        save(fig, "distance", "validation_error_vs_distance.png")
    return paths


# --------------------------------------------------------------------------
# write
# --------------------------------------------------------------------------


#: what each input of ``validate/metrics.json`` ``outside_training.by_input`` is, in the report's words
_STATE_INPUT_WORDS = {"tool_thickness_mm": "tissue thickness under the tool",
                      "probe_compliance_mm_per_n": "probe compliance",
                      "liver_size_mm": "liver size",
                      "centroid_distance_mm": "distance from the liver centroid"}


def _outside_iv_paragraph(data: dict, main_variant: str | None) -> str:
    """Scenario IV's test accuracy inside and outside the training livers' range of the geometric state."""
    ms = [m for m in data["models"] if m["scenario"] == "IV" and m.get("outside_training")]
    m = next((m for m in ms if m["variant"] == main_variant), ms[0] if ms else None)
    if m is None:
        return ""
    o = m["outside_training"]
    head = (f"<p id='iv-outside'><b>Scenario IV, where the accuracy goes</b> (<code>{html.escape(m['variant'])}"
            f"</code>, every split): {o['n_outside']} of {o['n_cases']} test cases over {o['n_splits']} splits lie "
            f"outside the training livers' range of the geometric state (tissue thickness under the tool, probe "
            f"compliance, liver size, distance from the centroid: what serving warns about).")
    if not o["n_outside"]:
        return head + " Every test case lies inside it.</p>"

    def side(name: str) -> str:
        a, e = o[f"{name}_accuracy_pct"], o[f"{name}_mae_vec"]
        spread = f"mean ± sd over {a['n_splits']} splits" if a["sd"] is not None else f"{a['n_splits']} split"
        return (f"<b>{_pm(a['mean'], a['sd'], 1)} %</b> (MAE {_pm(e['mean'], e['sd'])} N; {spread}; all its "
                f"cases pooled {_fmt(o.get(f'{name}_accuracy_pooled_pct'), 1)} %)")

    return (head + f" Accuracy on those {side('outside')}, on the others {side('inside')}. A test liver at the "
            "edge of the population is extrapolation for a model trained on the others.</p>")


def _extrapolation_paragraph(ext: dict | None) -> str:
    """The unseen cases served with an extrapolation warning, and their error against the others'."""
    if not ext:
        return ""
    n, k = ext["n_cases"], ext["n_outside"]
    by = ", ".join(f"{_STATE_INPUT_WORDS.get(name, name)}: {c} case{'s' * (c != 1)}"
                   for name, c in ext["by_input"].items() if c)
    if not k:
        return ("<h3>Outside the training range</h3><p>No unseen case lies outside the training cases' range of the "
                "geometric state (thickness under the tool, probe compliance, liver size, distance from the "
                "centroid); serving would have warned about none.</p>")
    err = (f"Their MAE is <b>{_fmt(ext['mae_outside_n'])} N</b>, against {_fmt(ext['mae_inside_n'])} N for the "
           f"other {n - k}." if k < n else f"Their MAE is <b>{_fmt(ext['mae_outside_n'])} N</b>.")
    return (f"<h3>Outside the training range</h3><p>{k} of {n} unseen cases lie outside the training cases' range "
            f"of the geometric state ({html.escape(by)}); serving predicts them with a warning naming the input "
            f"(<code>warnings</code> of <code>liverforce predict</code>, the pyfunc model and "
            f"<code>Predictor.context_warnings</code>). {err}</p>")


def _distance_paragraph(interval: dict | None) -> str:
    """The unseen cases the input-distance flag warns about (``validation.interval.input_distance``), and their
    error and interval coverage against the others'."""
    far = (interval or {}).get("input_distance")
    if not far:
        return ""
    n, k, q = far["n_cases"], far["n_flagged"], 100 * far["quantile"]
    other = "the other livers'" if far.get("left_out", "liver") == "liver" else "the other cases'"
    head = (f"<h3>Far from every training case</h3><p>Serving warns when a case's inputs lie farther from the "
            f"model's nearest training case (in the GP's length scales) than {q:.0f} % of its training cases lie "
            f"from {other} (threshold {_fmt(far['threshold'])}, from {far['n_calibration']:,} training cases). ")
    at = far.get("flagged_at") or {}
    beyond = "; ".join(f"{100 * c / n:.1f} % beyond the training side's {100 * float(p):.0f} % quantile"
                       for p, c in at.items() if float(p) >= 0.9)
    rate = f" A liver like the training livers puts {100 - q:.0f} % of its cases beyond it; the unseen livers: " \
           f"{beyond}." if beyond else ""
    if not k:
        return head + f"No unseen case lies beyond it (median distance {_fmt(far['median_distance'])}).{rate}</p>"
    cov = ""
    if far.get("coverage_flagged") and far.get("coverage_others"):
        cov = (" The interval covers the flagged cases' components in "
               + " / ".join(f"{100 * c:.0f}" for c in far["coverage_flagged"]) + " % (t1 / t2 / n), the others' in "
               + " / ".join(f"{100 * c:.0f}" for c in far["coverage_others"]) + " %.")
    others = (f", against {_fmt(far['mae_others_n'])} N for the other {n - k}" if far["mae_others_n"] is not None
              else "")
    return (head + f"It flags <b>{k} of {n}</b> unseen cases ({100 * k / n:.1f} %). Their MAE is "
            f"<b>{_fmt(far['mae_flagged_n'])} N</b>{others}; they hold {far['n_large_flagged']} of the "
            f"{far['n_large']} errors above {far['large_error_n']:g} N.{cov}{rate}</p>")


def _gap_cell(gap: float | None) -> str:
    """The camera's accuracy gap to the reference (points), flagged above :data:`CAMERA_GAP_LIMIT`."""
    if gap is None:
        return "–"
    return _flagged(f"{gap:.1f}", gap > CAMERA_GAP_LIMIT)


def camera_section(data: dict, v: dict, main_variant: str | None) -> str:
    """Camera cloud against node correspondence per scenario and on the unseen livers, and the camera model's
    error as one camera setting changes (``validation["camera_sensitivity"]``). Empty without a camera model."""
    models = data.get("models", [])
    cams = [m for m in models if (m.get("model_cfg") or {}).get("roi_features") == "cloud"]
    if not cams:
        return ""
    cam_name = cams[0]["variant"]
    ref_name = main_variant if main_variant and main_variant != cam_name else next(
        (m["variant"] for m in models if (m.get("model_cfg") or {}).get("roi_features") != "cloud"), None)
    rows = []
    for sc in sorted({m["scenario"] for m in models}):
        c = next((m for m in cams if m["scenario"] == sc and m["variant"] == cam_name), None)
        r = next((m for m in models if m["scenario"] == sc and m["variant"] == ref_name), None)
        if c is None or r is None:
            continue
        ca, ra = c["metrics_mean"].get("accuracy_pct"), r["metrics_mean"].get("accuracy_pct")
        gap = None if ca is None or ra is None else ra - ca
        ex = c.get("exact_tip") or {}
        rows.append([sc, _pm(ra, r["metrics_sd"].get("accuracy_pct"), 1),
                     _pm(ca, c["metrics_sd"].get("accuracy_pct"), 1), _gap_cell(gap),
                     _pm((ex.get("metrics_mean") or {}).get("accuracy_pct"),
                         (ex.get("metrics_sd") or {}).get("accuracy_pct"), 1),
                     _pm(r["metrics_mean"].get("mae_vec"), r["metrics_sd"].get("mae_vec")),
                     _pm(c["metrics_mean"].get("mae_vec"), c["metrics_sd"].get("mae_vec")),
                     _pm((ex.get("metrics_mean") or {}).get("mae_vec"), (ex.get("metrics_sd") or {}).get("mae_vec"))])
    allv = v.get("all_variants") or {}
    sens = v.get("camera_sensitivity")
    if cam_name in allv and ref_name in allv:
        u = [allv[n].get("livers") or {} for n in (ref_name, cam_name)]
        # the validated camera model with an exact tip: its sensitivity row at tip noise 0, when it has one
        ut = next((r for r in (sens or {}).get("tip_noise_mm") or [] if float(r["value"]) == 0.0), None)
        exact_ok = ut is not None and v.get("model_variant") == cam_name
        rows.append(["unseen livers", _pm(u[0]["mean"]["accuracy_pct"], u[0]["sd"].get("accuracy_pct"), 1),
                     _pm(u[1]["mean"]["accuracy_pct"], u[1]["sd"].get("accuracy_pct"), 1),
                     _gap_cell(u[0]["mean"]["accuracy_pct"] - u[1]["mean"]["accuracy_pct"]),
                     _pm(ut["accuracy_pct"], ut["accuracy_sd"], 1) if exact_ok else "–",
                     _pm(u[0]["mean"]["mae_vec"], u[0]["sd"].get("mae_vec")),
                     _flagged(_pm(u[1]["mean"]["mae_vec"], u[1]["sd"].get("mae_vec")),
                              u[1]["mean"]["mae_vec"] > CAMERA_UNSEEN_MAE_LIMIT_N),
                     _pm(ut["mae_vec"], ut["mae_sd"]) if exact_ok else "–"])
    cam_cfg = (cams[0].get("model_cfg") or {}).get("camera") or {}
    fits = float((cam_cfg.get("grid") or {}).get("instrument_radius_mm") or 0.0) > 0
    tilts = float((cam_cfg.get("grid") or {}).get("instrument_max_tilt_deg") or 0.0) > 0
    instrument = ("The cloud shows the instrument too, and the model fits its shaft's axis to its points for the "
                  "tip's position along the surface (the robot's tip is the fit's prior, and the tip along the "
                  "normal" + ("; the shaft's tilt from the normal is fitted too when its points show one" if tilts
                              else "") + "). " if fits else "")
    out = ["<h3 id='camera'>What the camera costs: camera cloud against node correspondence</h3>",
           f"<p><code>{html.escape(cam_name)}</code> reads what surgery has: an unordered, partial, noisy camera "
           "cloud of the deformed surface (observed from the stored full surface: camera pose in a cone above the "
           "tool, back-facing and self-occluded points and the tool's shadow dropped, random density, noise) and "
           "the tool tip's position from the robot, with noise; no FE node ids. " + instrument +
           f"<code>{html.escape(str(ref_name))}</code> reads the FE nodes' displacements (a reference no camera "
           f"gives). Accuracy % and MAE are mean ± sd over the repeated splits (scenarios) or over the unseen livers. "
           f"Targets: the camera within {CAMERA_GAP_LIMIT:.0f} points of the reference in every row, and its "
           f"MAE on the unseen livers at most {CAMERA_UNSEEN_MAE_LIMIT_N:.1f} N (⚠ where missed). "
           "<i>Exact tip</i>: the same camera model and the same clouds, the tool tip given exactly, without the "
           "kinematics noise the model was trained with: what this model gives with a perfect tool tracker. A "
           "model retrained for a more precise tracker (<code>model.camera.tip_noise_mm</code>) gains more than "
           "this column shows, as it learns to lean on the tip (docs/experiments.md, \"What a camera sees\"). "
           "The reference, by contrast, reads node displacements without noise (default settings).</p>",
           _table(["scenario", f"correspondence {html.escape(str(ref_name))} %", f"camera {html.escape(cam_name)} %",
                   "gap (points)", "camera, exact tip %", "correspondence MAE (N)", "camera MAE (N)",
                   "camera, exact tip MAE (N)"], rows, cls="camera", row_cls="cam")]
    if sens:
        what = {"n_points": ("cloud points (fixed)", ""), "noise_sd_mm": ("point noise", " mm"),
                "cone_half_angle_deg": ("view cone half-angle", "°"), "tip_noise_mm": ("tool tip noise", " mm"),
                "instrument_in_cloud": ("instrument's points in the cloud", ""),
                "tool_tilt_deg": ("tool axis tilted from the normal", "°"),
                "outlier_fraction": ("points at a gross depth error", "")}
        srows = []
        for key, (label, unit) in what.items():
            for r in sens.get(key) or []:
                val = (("yes" if r["value"] else "no") if isinstance(r["value"], bool)
                       else f"{100 * r['value']:g} %" if key == "outlier_fraction" else f"{r['value']:g}{unit}")
                srows.append([label, val, _pm(r["mae_vec"], r["mae_sd"]),
                              _pm(r["accuracy_pct"], r["accuracy_sd"], 1)])
        ms = sens.get("model_settings") or {}
        obs = ms.get("observation") or {}
        drop = float((ms.get("grid") or {}).get("outlier_mm") or 0.0)
        out.append("<p>The validated camera model on the unseen livers with one camera setting changed at a time "
                   f"(trained with {obs.get('n_points')} points, noise {_range_text(obs.get('noise_sd_mm'), ' mm')}, "
                   f"view cone {obs.get('cone_half_angle_deg')}°, tip noise {ms.get('tip_noise_mm')} mm, the "
                   f"instrument's points {'in the cloud' if obs.get('instrument_in_cloud') else 'masked out'}, the "
                   f"tool's axis {_range_text(obs.get('tool_tilt_deg'))} from the normal"
                   + (f", {100 * float(obs.get('outlier_fraction') or 0):g} % of its points at a gross depth error, "
                      f"up to {float(obs.get('outlier_range_mm') or 10.0):g} mm along their line of sight; it drops "
                      + (f"points farther than {drop:g} mm from their cell's plane" if drop > 0 else "no point as one")
                      if "outlier_fraction" in sens else "")
                   + "); mean ± sd over the livers.</p>")
        out.append(_table(["setting", "value", "unseen MAE (N)", "unseen accuracy %"], srows, cls="camera-sens",
                          row_cls="sens"))
    out.append(registration_table(v.get("registration")))
    out.append(shape_table(v.get("shape")))
    return "".join(out)


def registration_table(reg: dict | None) -> str:
    """The validated camera model with its camera's registration off, as registered and refined from the unloaded
    view (``validation["registration"]``, :func:`liverforce.pipeline.validate.registration_sensitivity`)."""
    if not reg or not reg.get("rows"):
        return ""
    rows = []
    for r in reg["rows"]:
        a, f = r["as_registered"], r.get("refined") or {}
        refused = int(f.get("n_refused") or 0)
        rows.append([f"{r['shift_mm']:g} mm, {r['turn_deg']:g}°", _pm(a["mae_vec"], a["mae_sd"]),
                     _pm(a["accuracy_pct"], a["accuracy_sd"], 1),
                     _pm(f["mae_vec"], f["mae_sd"]) if "mae_vec" in f else "–",
                     _pm(f["accuracy_pct"], f["accuracy_sd"], 1) if "accuracy_pct" in f else "–",
                     _flagged(str(refused), refused > 0),
                     ", ".join(f"{k} ({n})" for k, n in sorted((f.get("anchors") or {}).items())) or "–"])
    return ("<h4 id='registration'>When the camera's registration is off</h4>"
            "<p>The model reads the cloud's height over the pre-operative surface and the tool tip's displacement "
            "from the exertion point, both through the registration that places the camera on the pre-operative "
            "surface. Here each unseen case's cloud and tool tip are moved together by a rigid motion: a shift in a "
            "random direction and a turn about a random axis through the liver's centroid. <i>As registered</i>: "
            "predicted as they come. <i>Refined</i>: the registration first refined from the camera's view of the "
            "same region before the tool pushed (<code>liverforce predict --unloaded --contact-tip</code>: the "
            "undeformed surface observed with the model's camera settings, the robot's tip at contact with its "
            "kinematics noise; the surface fit gives the offset along the normal and the tilt, the instrument's axis "
            "in that view, or else the tip at contact, the shift along the surface; "
            "<code>liverforce.learn.registration</code>; the liver's change of shape since the scan, next table, is "
            "fitted too); a refinement beyond 10 mm or 15° at the exertion point, or a change of shape beyond 5 mm, "
            "is refused and counted. Mean ± sd over the livers.</p>"
            + _table(["registration off by", "as registered MAE (N)", "as registered %", "refined MAE (N)",
                      "refined %", "refused", "shift along the surface from (cases)"], rows, cls="registration",
                     row_cls="reg"))


def shape_table(shape: dict | None) -> str:
    """The validated camera model on unseen livers whose shape changed since the scan, as seen, refined rigidly
    and refined with the change of shape (``validation["shape"]``,
    :func:`liverforce.pipeline.validate.shape_sensitivity`)."""
    if not shape or not shape.get("rows"):
        return ""

    def cells(f: dict) -> list:
        refused = int(f.get("n_refused") or 0)
        return [_pm(f["mae_vec"], f["mae_sd"]) if "mae_vec" in f else "–",
                _pm(f["accuracy_pct"], f["accuracy_sd"], 1) if "accuracy_pct" in f else "–",
                _flagged(str(refused), refused > 0)]

    rows = []
    for r in shape["rows"]:
        a = r["as_registered"]
        rows.append([f"{r['amplitude_mm']:g} mm, {r['wavelength_mm']:g} mm", _pm(a["mae_vec"], a["mae_sd"]),
                     *cells(r.get("rigid") or {}), *cells(r.get("refined") or {})])
    return ("<h4 id='shape'>When the liver has changed shape since the scan</h4>"
            "<p>Between the scan and the operation the liver changes shape (pneumoperitoneum, breathing, "
            "mobilisation), and the model reads the cloud against the scanned surface. Here each unseen liver's "
            "surface is moved by a smooth field of the amplitude and wavelength given (three sinusoidal modes of "
            "random direction and phase, each of the amplitude / √3: the field's rms displacement is the amplitude "
            "/ √2, as one sinusoid's), and the tool pushes the changed "
            "surface as it pushed the scanned one in the local frame the field carries (the force label unchanged); "
            "the unloaded view is that surface observed before the push. <i>As seen</i>: predicted as the camera sees "
            "it. <i>Rigid</i>: the registration refined from the unloaded view by a rigid motion only "
            "(<code>--shape-degree 0</code>). <i>Refined</i>: refined with the change of shape as well, the default "
            "(a cubic in the tangent coordinates fitted to what the unloaded view still lies off the surface, its "
            "tangent plane at the exertion point taken by the rigid motion, the rest taken off every point's "
            "height). Refused and counted: a change of more than 5 mm over the model's grid, or the unloaded view "
            "still more than 2 mm (rms) off the surface. Mean ± sd over the livers.</p>"
            + _table(["shape changed by (amplitude, wavelength)", "as seen MAE (N)", "rigid MAE (N)", "rigid %",
                      "rigid refused", "refined MAE (N)", "refined %", "refined refused"], rows, cls="shape",
                     row_cls="shape"))


def _range_text(tilt, unit: str = "°") -> str:
    """A setting of a model's observation that may be a range: the tool's tilt ``12°``, or ``0-30°`` for a range
    (0 when absent); the point noise likewise with ``unit=" mm"``."""
    lo, hi = (tilt, tilt) if tilt is None or isinstance(tilt, (int, float)) else tuple(tilt)
    lo, hi = float(lo or 0.0), float(hi or 0.0)
    return f"{lo:g}{unit}" if lo == hi else f"{lo:g}-{hi:g}{unit}"


def physics_section(phys: dict | None, validated: str | None) -> str:
    """What the modelling choices cost (``validate/physics.json``, :mod:`liverforce.pipeline.physics`); "" if absent.

    Each choice is measured against its reference (``compared_with``: the baseline for the supports, the
    traction carrying the same forces for the sphere), its MAE change too."""
    if not phys or not phys.get("variants"):
        return ""
    by = {e["name"]: e for e in phys["variants"]}
    names = list(phys["variants"][0].get("models") or {})
    names.sort(key=lambda n: n != validated)  # the validated model first
    rows = []
    for e in phys["variants"]:
        ref = by.get(e.get("compared_with") or "")
        ratio, rng = e.get("u_tool_ratio_median"), e.get("u_tool_ratio_range")
        cells = [html.escape(e["name"]), html.escape(e["what"]), f"{e['converged']}/{e.get('n_cases', phys['n_cases'])}",
                 "–" if ref is None else html.escape(ref["name"]),
                 "–" if ratio is None or ref is None else f"{ratio:.2f}" + (f" ({rng[0]:.2f}–{rng[1]:.2f})" if rng else ""),
                 "–" if e.get("roi_change_pct_mean") is None or ref is None else
                 f"{e['roi_change_pct_mean']:.0f} / {e['roi_change_pct_max']:.0f}",
                 ("failed: " + html.escape(e["sag_error"])) if e.get("sag_error") else
                 "–" if e.get("sag_max_mm") is None else _fmt(e["sag_max_mm"], 1)]
        for n in names:
            m, b = (e.get("models") or {}).get(n), ((ref or {}).get("models") or {}).get(n)
            cells.append("–" if m is None else f"{_fmt(m['mae_vec'])}" + (
                "" if b is None else f" <small>({m['mae_vec'] - b['mae_vec']:+.3f})</small>"))
        rows.append(cells)
    head = ["choice", "what changed", "converged", "compared with", "|u| under the tool ÷ reference: median (range)",
            "ROI displacement change %: mean / max", "sag (mm)"]
    head += [f"MAE (N) {n}" + (" (validated)" if n == validated else "") for n in names]
    fmin, fmax = min(phys["forces_n"]), max(phys["forces_n"])
    lab = [s.get("name") for s in (phys.get("own_supports") or {}).get("supports") or []]
    assumes = (f"the lab's supports of this liver (<code>geometry.imported[].supports</code>: "
               f"{html.escape(', '.join(map(str, lab)))}; its validation was simulated with them) and the configured "
               "tool" if lab else "the configured supports and tool")
    skipped = "".join(f" Not simulated: {html.escape(e['name'])} ({html.escape(e['reason'])})."
                      for e in phys.get("skipped") or [])
    return ("<h3 id='physics'>What the modelling choices cost</h3>"
            f"<p>The first {phys['n_cases']} cases of the unseen liver <code>{html.escape(phys['liver'])}</code> "
            f"(|F| {fmin:.2f}–{fmax:.2f} N, the validation's constants) simulated again with one modelling choice "
            "changed at a time, and every scenario-IV model scored on them. "
            + ("The models were trained on the configured supports (their training livers'); here they assume this "
               "liver's baseline (their stiffness probe is the baseline supports'), as a model in "
               if lab else "The models were trained on the baseline and keep assuming it (their stiffness probe is "
               "the baseline supports'), as a model in ")
            + f"surgery assumes {assumes}: the change in MAE against the reference (in "
            "brackets) is what getting that choice wrong costs. The displacement under the tool at the same force "
            "shows what the physics does (the force at a given indentation moves by about its inverse); the ROI "
            "change is |u − u_reference| / |u_reference| over the ROI nodes, per case. With gravity, displacements "
            "are over the sagged state (the pre-operative image shows the sagged liver). A frictionless sphere "
            "exerts a force close to the surface normal whatever way it is pushed, so it runs the light cases "
            f"only{_tool_cap_words(phys)} and is compared with the traction carrying the very forces it exerted."
            f"{skipped}</p>"
            + _table(head, rows, cls="physics", row_cls="physics"))


def _tool_cap_words(phys: dict) -> str:
    """" (at most C N ...)" for the physics text: the sphere's force cap as used, scaled on a lab liver of its own
    material; "" for a study written before the cap was recorded."""
    cap = phys.get("tool_max_force_n")
    if cap is None:
        return ""
    if phys.get("tool_force_scale") is None:
        return f" (at most {cap:.2f} N)"
    return (f" (at most {cap:.2f} N: <code>validate.physics.tool_max_force_n</code> x "
            f"{phys['tool_force_scale']:.3g}, this liver's own initial shear modulus over the procedural unseen "
            "livers', for which the cap is set: a softer liver sinks deeper at the same force)")


def stretch_section(shards: list[dict], solver_stats: dict) -> str:
    """The principal stretches the cases reached against the Drucker-checked range (HTML; "" if unknown).

    ``solver_stats["per_scenario"][sc]["stretch"]``: ``{"n", "min", "max",
    "n_outside", "outside_ids"}`` (:func:`liverforce.pipeline.report.stretch_statistics`);
    ``solver_stats["stretch_range_checked"]``: ``[lo, hi]`` (``material.stability_stretch``).
    """
    per = solver_stats.get("per_scenario") or {}
    stats = {s["scenario"]: per.get(s["scenario"], {}).get("stretch") for s in shards}
    stats = {sc: st for sc, st in stats.items() if st}
    if not stats:
        return ""
    rng = solver_stats.get("stretch_range_checked")
    checked = f"{_fmt(float(rng[0]), 2)}–{_fmt(float(rng[1]), 2)}" if rng else "–"
    rows = [[sc, st["n"], _fmt(st["min"]), _fmt(st["max"]), _fmt(st["n_outside"]),
             html.escape(", ".join(st["outside_ids"])) or "–"] for sc, st in stats.items()]
    n = sum(st["n"] for st in stats.values())
    n_out = sum(st["n_outside"] or 0 for st in stats.values())
    text = (f"<h3>Stretches reached and the Drucker check</h3><p>The smallest and largest principal stretch "
            f"anywhere in the liver (every quadrature point of the FE solution; a failed case at its last accepted "
            f"state), against the stretch range the material's Drucker stability check covers ({checked}, "
            f"<code>material.stability_stretch</code>). Outside it the constants' stability was never checked.")
    if rng and n_out:
        ids = [i for st in stats.values() for i in st["outside_ids"]][:5]
        text += f" <b>{n_out} of {n} cases leave the checked range</b> (e.g. {html.escape(', '.join(ids))})."
    elif rng:
        text += f" All {n} cases stay inside it."
    return text + "</p>" + _table(["scenario", "cases", "min stretch", "max stretch", f"cases outside {checked}",
                                   "most extreme outside"], rows, cls="stretch", row_cls="stretch")


def _points_text(n_points, geometries: list[dict]) -> str:
    """The sweep's candidate exertion points: ``sweep.exertion.n_points`` per liver, except for the livers that
    give their own (counted apiece)."""
    given = given_points(geometries)
    if not given:
        return f"{n_points} candidate exertion points per liver"
    each = ", ".join(f"<code>{html.escape(g)}</code>: {n} given by the lab" for g, n in given.items())
    if len(given) == len(geometries):
        return f"candidate exertion points given per liver ({each})"
    return (f"{n_points} candidate exertion points per sampled liver (<code>sweep.exertion.n_points</code>); "
            f"livers with their own: {each}")


def write_report(data: dict, pictures: list[str | Path], experiment: str, out_html: str | Path,
                 solver_stats: dict | None = None, setup: dict | None = None,
                 population_png: str | Path | None = None) -> Path:
    """Write the HTML page (atomically) and its figures under ``report/figures``.

    ``population_png``: the population picture
    (:func:`liverforce.report.population.population_figure`), shown in the
    setup section; ``setup["population"]``: ``{"training": [ids], "unseen":
    [ids], "volume_range_l": [lo, hi]}`` names each liver's role.

    ``solver_stats``: ``{"overall": {...}, "per_scenario": {scenario: {...}}, "reasons": {...}}``
    or a flat dict (shown as one line). ``setup``: config slices shown in the
    setup section (``material``, ``boundary``, ``sweep``, ``mesh``,
    ``dataset``, ``validate``, ``train``, ``tune``, ``study``, ``tracking``);
    ``setup["mlflow_experiments"]``: ``{"models", "validation", "studies"}``,
    the run's MLflow experiment names (``Plan.experiment_name``).
    """
    out_html = Path(out_html)
    out_dir = out_html.parent
    out_dir.mkdir(parents=True, exist_ok=True)
    setup = setup or {}
    main_variant = setup.get("main_variant")
    v = data["validation"]
    vm = v["metrics"]
    parts = [f"<h1>liverforce report — experiment <code>{html.escape(experiment)}</code></h1>",
             "<p>liverforce estimates the tool force (Fx, Fy, Fz, in newtons) from how the liver surface around "
             "the tool deforms. The training labels come from finite-element simulations of a tool pushing on "
             "livers. Units: mm, N, MPa. <b>Accuracy %</b> = 100 × (1 − Σ‖F̂ − F‖ / Σ‖F‖) over the held-out "
             "test cases (the study did not define its own; 100 % is perfect, 0 % is as large an error as the "
             "force itself). <b>MAE</b> is the mean length of the force-error vector, in N. Every number that "
             "comes from a model names its MLflow run (<code>run …</code>); see the last section to open "
             "them.</p>"]

    # ------------------------------------------------------------ headline
    parts.append("<h2 id='headline'>Headline: the study's Table 5.9, ours beside it</h2>")
    rows = []
    t59 = table59(data, main_variant)
    ours = [r[k] for r in t59 for k in ("without", "with") if r[k]]
    splits = sorted({c["n_splits"] for c in ours if c["n_splits"] and c["accuracy_mean"] is not None})
    for r in t59:
        cells = [r["scenario"], html.escape(SCENARIO_TEXT.get(r["scenario"], ""))]
        for key in ("without", "with"):
            c = r[key]
            if c and c["accuracy_mean"] is not None:
                cells.append(f"<span class='pm'>{_pm(c['accuracy_mean'], c['accuracy_sd'], 1)} %</span><br>"
                             f"<small>MAE {_pm(c['mae_mean'], c['mae_sd'])} N; {c['n_splits']} splits<br>"
                             f"{SPLIT_LABEL[bool(c.get('final_fit'))]}: "
                             f"<span class='split'>{_fmt(c['accuracy_pct'], 1)} %</span>, "
                             f"MAE {_fmt(c['mae_vec'])} N; {html.escape(c['source'])}</small>"
                             f"{_small_run(c['run_id'])}")
            elif c:
                cells.append(f"<span class='split'>{_fmt(c['accuracy_pct'], 1)} %</span><br><small>MAE "
                             f"{_fmt(c['mae_vec'])} N; {html.escape(c['source'])}</small>{_small_run(c['run_id'])}")
            else:
                cells.append("– <small>(not trained)</small>")
            cells.append(f"{_fmt(r[f'study_{key}'], 1)} %")
        rows.append(cells)
    n_txt = (f"{splits[0]}" if len(splits) == 1 else "/".join(map(str, splits))) if splits else "–"
    parts.append(f"<p>Accuracy on the held-out test split of each scenario (scenario IV: test livers never seen "
                 f"in training), deformation only and with the state vector, beside the study's published values "
                 f"(ANSYS data, 24 CT livers). <b>Our cells are mean ± sd over {n_txt} repeated seeded "
                 f"train/test splits</b> (<code>train.repeats</code>: the chosen configuration refitted on each "
                 f"split; sample sd); below it, the single main split (logged as <code>accuracy_pct</code> in "
                 f"the model's MLflow run; the run also holds <code>accuracy_pct_mean</code>/<code>_sd</code>). "
                 + ("The model that is saved, served and validated is the same configuration refitted on every "
                    "case of its scenario, test split included (<code>train.final_fit</code>): these figures are "
                    "its configuration's, measured on cases it was not fitted on. "
                    if any(c.get("final_fit") for c in ours) else
                    "That split's model is the one saved, served and validated. ")
                 + "The study reported one split, without spread.</p>")
    parts.append(_table(["scenario", "what varies", "ours: deformation only", "study: deformation only",
                         "ours: with state vector", "study: with state vector"], rows, cls="t59"))
    parts.append(_outside_iv_paragraph(data, main_variant))

    enc = next((d for d in data.get("studies", []) if d["study"] == "encoder"), None)
    if enc:
        encs = list(dict.fromkeys(p["label"] for p in enc["points"]))
        rows = []
        for sc in dict.fromkeys(p["scenario"] for p in enc["points"]):
            row = [sc]
            for e in encs:
                p = next((p for p in enc["points"] if p["scenario"] == sc and p["label"] == e), None)
                if p and p["status"] == "ok":
                    row.append(f"{_fmt(p['metrics']['accuracy_pct'], 1)} %<br><small>MAE "
                               f"{_fmt(p['metrics']['mae_vec'])} N</small>{_small_run(p.get('run_id'))}")
                else:
                    row.append("– <small>failed</small>" if p else "–")
            rows.append(row)
        parts.append(f"<h3>PCA vs autoencoder vs denoising autoencoder</h3><p>Same data, split and regressor "
                     f"settings, only the encoder changes (trained without Ax, {enc['epochs']} epochs, scored on the "
                     f"training-side validation split; details in the studies section). With the GP and "
                     f"<code>model.gp.code_members</code>, a PCA code is read by the mean of one GP per code size; "
                     f"AE and DAE codes are not nested, so they are read by one GP.</p>")
        parts.append(_table(["scenario", *[e.upper() for e in encs]], rows))
    lv = v["livers"]
    worst = lv["worst"]
    scale = (setup.get("validate") or {}).get("material_scale")
    cam_validated = any(m["scenario"] == "IV" and m["variant"] == v.get("model_variant")
                        and (m.get("model_cfg") or {}).get("roi_features") == "cloud" for m in data["models"])
    parts.append(
        f"<p id='unseen-headline'><b>Unseen-liver validation</b> of <code>{html.escape(str(v.get('model_variant')))}"
        f"</code>{' (camera cloud and tool tip, no FE node ids: what surgery has)' if cam_validated else ''} "
        f"({lv['n']} liver shapes never seen in training"
        + (f", material constants × {_fmt(scale, 2)}" if scale is not None and _scaled_unseen(setup) else "")
        + "".join(f"; <code>{html.escape(g)}</code> its own material" for g, _, _ in _own_materials(setup)["unseen"])
        + "): MAE "
        f"<b>{_pm(lv['mean']['mae_vec'], lv['sd'].get('mae_vec'))} N</b>, accuracy "
        f"<b>{_pm(lv['mean']['accuracy_pct'], lv['sd'].get('accuracy_pct'), 1)} %</b> ("
        + (f"mean ± sd over the {lv['n']} livers" if lv['n'] != 1 else "one liver")
        + f"); worst liver <code>{html.escape(str(worst))}</code> (MAE "
        f"{_fmt(v['per_liver'][worst]['mae_vec'])} N). All {v['n_cases']} cases pooled: MAE "
        f"{_fmt(vm['mae_vec'])} N, accuracy {_fmt(vm['accuracy_pct'], 1)} %. The study: MAE "
        f"{_fmt(STUDY_VALIDATION_MAE_N)} N on one liver. {_small_run(v.get('run_id'))}</p>")

    # ------------------------------------------------------------ setup
    parts.append("<h2 id='setup'>Setup</h2>")
    pop = setup.get("population") or {}
    unseen = set(pop.get("unseen") or [g["id"] for g in data["geometries"] if g["id"].startswith("val-")])
    # the liver of scenarios I-III: the plan's (a lab's own liver when it brings one); an older setup without it
    # had the first training liver
    first = pop.get("single") or (pop.get("training") or [g["id"] for g in data["geometries"]
                                                         if g["id"] not in unseen] or [None])[0]
    n_train = sum(g["id"] not in unseen for g in data["geometries"])
    parts.append(f"<h3>Livers</h3><p>Procedural livers (seeded) or imported segmentations, meshed with "
                 f"tetrahedra: {n_train} training livers (scenario IV; scenarios I–III use one of them, "
                 f"<code>{html.escape(str(first))}</code>) and {len(unseen)} unseen livers ({_unseen_kinds(unseen)}, "
                 "validation only).</p>")
    if population_png:
        vr = pop.get("volume_range_l")
        parts.append("<figure class='population'>" + f"<img src='{_rel(population_png, out_dir)}' "
                     "style='max-width:100%'><figcaption>The liver population: the top view (x–y, seen from "
                     "superior; x patient right, y anterior) of every liver surface at the same scale, labelled "
                     "by id and volume, training livers in blue, unseen validation livers in orange; below, "
                     "the histogram of their volumes"
                     + (f" (procedural volumes are drawn in {vr[0]:g}–{vr[1]:g} L, shaded)" if vr else "")
                     + ".</figcaption></figure>")
    rows = []
    for g in data["geometries"]:
        vol = g.get("volume_mm3")
        ext = g.get("extent_mm")
        role = "unseen" if g["id"] in unseen else ("training, I–IV" if g["id"] == first else "training")
        rows.append([html.escape(g["id"]), role, _fmt(vol / 1e6 if vol else None, 3),
                     " × ".join(f"{e:.0f}" for e in ext) if ext else "–", _fmt(g.get("n_nodes"), 0),
                     _fmt(g.get("n_tets"), 0), _fmt(g.get("meshing_time_s"), 1)])
    parts.append(_table(["geometry", "role", "volume (L)", "extent (mm)", "nodes", "tets", "meshing (s)"], rows,
                        cls="geometries"))
    pics = "<div class='pics'>" + "".join(
        _figure(p, out_dir, gid_of(p), 300) for p in pictures) + "</div>"
    what = ("the boundary regions (fixed vena cava patch, ligament and visceral springs, rib contact, the "
            "visible surface where the tool may push)")
    if len(pictures) > 6:
        parts.append(f"<details><summary>Pictures of {what}, per liver ({len(pictures)})</summary>{pics}</details>")
    elif pictures:
        parts.append(f"<p>Pictures: {what}.</p>{pics}")
    sw = setup.get("sweep") or {}
    parts.append(imported_section(data["geometries"], sw.get("exertion", {}).get("n_points")))
    mat = setup.get("material")
    if mat:
        consts = ", ".join(f"{k} = {val:g}" for k, val in (mat.get("params_mpa") or {}).items())
        parts.append(f"<h3>Material</h3><p>{html.escape(str(mat.get('model')))} hyperelastic, constants (MPa): "
                     f"{html.escape(consts)}; Poisson ratio {_fmt(mat.get('nu'), 3)} (nearly incompressible). "
                     f"Where the material varies, each constant is drawn within ±{100 * mat.get('vary_rel', 0):.0f} %"
                     f" (unstable sets refused before solving). Unseen validation livers: "
                     + (f"constants × {_fmt((setup.get('validate') or {}).get('material_scale'), 2)} "
                        if _scaled_unseen(setup) else "") + f"({_scale_words(setup)})."
                     + "".join(f" <code>{html.escape(g)}</code> has its own constants ({html.escape(p)} MPa"
                               + (f", entered as {html.escape(_entered_words(e))}" if isinstance(e, dict) else "")
                               + "): its cases take them where the material is fixed and are drawn around them "
                               "where it varies."
                               for g, p, e in _own_materials(setup)["training"])
                     + "</p>")
    bnd = setup.get("boundary")
    if bnd:
        num = lambda v: isinstance(v, (int, float)) and not isinstance(v, bool)  # noqa: E731
        own = [g["id"] for g in data["geometries"] if is_imported(g) and g.get("supports")]
        parts.append("<p>Boundary" + (" (the built-in regions)" if own else "") + ": "
                     + html.escape(", ".join(f"{k} = {val:g}" if num(val) else f"{k} = {val}"
                                             for k, val in bnd.items()))
                     + (f"; {html.escape(', '.join(own))} held by {'its' if len(own) == 1 else 'their'} own supports "
                        "(see Imported livers)" if own else "") + "</p>")
    sw = setup.get("sweep")
    if sw:
        rows = [[sc, s["n_cases"], html.escape(str(s["geometries"])), s["exertion"], s["material"]]
                for sc, s in sw.get("scenarios", {}).items()]
        val_cfg = setup.get("validate") or {}
        # the unseen livers: the procedural ones and a lab's own held out of training (validate.imported)
        n_unseen = val_cfg.get("livers", 1) + len(val_cfg.get("imported") or [])
        n_val = (val_cfg["n_cases"] * n_unseen) if "n_cases" in val_cfg else "–"
        rows.append(["V (validation)", n_val, f"{n_unseen} unseen", "varies", "unseen"])
        f = sw.get("force", {})
        parts.append(f"<h3>Simulation sweep</h3><p>Force magnitude {_fmt(f.get('min_n'), 1)}–"
                     f"{_fmt(f.get('max_n'), 1)} N within {_fmt(f.get('cone_deg'), 0)}° of the inward normal; "
                     + _points_text(sw.get("exertion", {}).get("n_points", "–"), data["geometries"]) + "; "
                     f"{html.escape(str(sw.get('design')))} design. ROI: "
                     f"{_fmt(100 * (setup.get('dataset') or {}).get('roi_fraction', float('nan')), 0)} % of the "
                     f"surface; mesh target {(setup.get('mesh') or {}).get('target_nodes', '–')} vertices.</p>")
        parts.append(_table(["scenario", "cases", "livers", "exertion point", "material"], rows))
    tr, tu = setup.get("train"), setup.get("tune")
    if tr and tu:
        regs = setup.get("regressors") or {}
        gp = sorted(k for k, v in regs.items() if v == "gp")
        mlp = sorted(k for k, v in regs.items() if v != "gp")
        which = "".join([
            f"Gaussian-process regressor (ARD kernel, hyper-parameters by marginal likelihood, no Ax search): "
            f"{html.escape(', '.join(gp))}. " if gp else "",
            f"MLP regressor ({tr.get('epochs')} epochs; Ax tuning {'on' if tu.get('enabled') else 'off'}, "
            f"{tu.get('trials')} trials): {html.escape(', '.join(mlp)) or 'every variant'}. " if mlp or not gp
            else ""])
        parts.append(f"<p>{which}Cross-validation: {tu.get('folds')} folds of the training split; test fraction "
                     f"{_fmt(tr.get('test_fraction'), 2)} (scenario IV: split by liver).</p>")

    # ------------------------------------------------------------ simulations
    parts.append("<h2 id='simulations'>Simulations and solver statistics</h2>")
    per = (solver_stats or {}).get("per_scenario", {}) if isinstance(solver_stats, dict) else {}
    rows = []
    for s in data["shards"]:
        st = per.get(s["scenario"], {})
        rows.append([s["scenario"], s["rows"], s["failed"],
                     _fmt(100 * s["failed"] / s["rows"] if s["rows"] else 0.0, 1), s["shards"],
                     _fmt(st.get("solve_time_total_s"), 1), _fmt(st.get("solve_time_median_s"), 2),
                     _fmt(st.get("solve_time_max_s"), 1), _fmt(st.get("newton_iterations_median"), 0),
                     _fmt(st.get("load_steps_median"), 0), _fmt(st.get("max_displacement_median_mm"), 1),
                     f"<code>{html.escape(s['data_version'])}</code>"])
    parts.append(_table(["scenario", "cases", "failed", "failed %", "shards", "solve time total (s)",
                         "median per case (s)", "max per case (s)", "median Newton iterations", "median load steps",
                         "median max |u| (mm)", "data version"], rows))
    if solver_stats:
        overall = solver_stats.get("overall", solver_stats if "per_scenario" not in solver_stats else {})
        if overall:
            parts.append("<p>" + html.escape(", ".join(f"{k}: {val}" for k, val in overall.items())) + "</p>")
        reasons = solver_stats.get("reasons") or {}
        if reasons:
            parts.append("<p>Why cases failed (recorded in the shards' <code>reason</code> column):</p>")
            parts.append(_table(["reason", "cases"], [[html.escape(k), n] for k, n in reasons.items()]))
        parts.append(stretch_section(data["shards"], solver_stats))

    # ------------------------------------------------------------ every model
    parts.append("<h2 id='models'>Accuracy per scenario and variant (every trained model)</h2>")
    parts.append("<p>Mean ± sd over the repeated seeded splits (<code>train.repeats</code>), then the saved "
                 "model's own split (the numbers of its MLflow run's <code>accuracy_pct</code>, <code>mae_vec</code>"
                 ", …). Scenarios II and III split by case, so every test exertion point was also a training "
                 "point; their models are also scored on whole exertion points no training case used "
                 "(<code>train.heldout_points</code>: folds of points, each predicted by a model fitted on the "
                 "others; mean ± sd over the folds). A fold whose training part holds fewer than 3 exertion points "
                 "of a liver it tests is not scored (the force's dependence on the point, a position on a 2-D "
                 "surface, needs 3 to be learnt rather than extrapolated); an accuracy below "
                 f"{ACCURACY_FLOOR_PCT:.0f} % (errors larger than the forces) is flagged as extrapolation.</p>")
    rows = []
    for m in sorted(data["models"], key=lambda m: (m["scenario"], m["variant"])):
        sv = "with" if m.get("state_vector") else "without"
        study = STUDY_ACCURACY.get(m["scenario"], {}).get(sv)
        mt, mean, sd = m["metrics"], m["metrics_mean"], m["metrics_sd"]
        hp = m.get("heldout_points") or {}
        rows.append([m["scenario"], html.escape(m["variant"]), html.escape(str(m.get("encoder"))), sv,
                     flag_accuracy(_pm(mean.get("accuracy_pct"), sd.get("accuracy_pct"), 1),
                                   [mean.get("accuracy_pct")] + [r.get("metrics", {}).get("accuracy_pct")
                                                                 for r in m.get("repeats") or []]),
                     _pm(mean.get("mae_vec"), sd.get("mae_vec")),
                     _fmt(m.get("n_splits"), 0),
                     flag_accuracy(_fmt(mt.get("accuracy_pct"), 1), [mt.get("accuracy_pct")]),
                     _fmt(study, 1),
                     _fmt(mt.get("mae_vec")), _fmt(mt.get("rmse_vec")),
                     " / ".join(_fmt(mt.get(f"mae_{a}")) for a in "xyz"),
                     _run(m.get("run_id")), f"{_fmt(m.get('n_train'), 0)} / {_fmt(m.get('n_test'), 0)}",
                     _fmt(m.get("seconds"), 0),
                     heldout_cell(hp)])
    parts.append(_table(["scenario", "variant", "encoder", "state vector", "accuracy % mean ± sd", "MAE (N) mean ± sd",
                         "splits", "accuracy % (saved split)", "study %", "MAE (N) (saved split)", "RMSE (N)",
                         "MAE x / y / z (N)", "MLflow run", "train / test cases", "train time (s)",
                         "held-out exertion points: accuracy % mean ± sd"], rows,
                        cls="models", row_cls="model"))

    # ------------------------------------------------------------ validation
    parts.append("<h2 id='validation'>Unseen livers (validation)</h2>")
    chosen = v.get("model_variant")
    why = v.get("variant_choice")
    n_liv = lv["n"]
    parts.append(f"<p>A scenario-IV model predicts every case simulated on {n_liv} liver shapes it never saw in "
                 f"training ({_unseen_kinds(v['per_liver'])}; no seed, geometry or case shared with training), "
                 f"with material constants {_scale_words(setup)}"
                 + (f": variant <code>{html.escape(str(chosen))}</code>, chosen by {html.escape(str(why))}"
                    if chosen else "") + ". Each liver weighs the same in the mean ± sd (sample sd over the "
                 "livers), whatever its number of converged cases.</p>")
    vols = {g["id"]: g.get("volume_mm3") for g in data["geometries"]}
    rows = []
    for gid, m in v["per_liver"].items():
        name = f"<b>{html.escape(gid)}</b> <small>(worst)</small>" if gid == worst else html.escape(gid)
        vol = vols.get(gid)
        rows.append([name, _fmt(vol / 1e6 if vol else None, 2), m["n"], _fmt(m["mae_vec"]), _fmt(m["rmse_vec"]),
                     _fmt(m["accuracy_pct"], 1)])
    per = _table(["liver", "volume (L)", "cases", "MAE (N)", "RMSE (N)", "accuracy %"], rows, cls="per-liver",
                 row_cls="liver")
    mean_row = f"mean ± sd ({n_liv} livers)" if n_liv != 1 else "the one liver"
    foot = (f"<tr class='livers-mean'><th>{mean_row}</th><td></td><td>{v['n_cases']}</td>"
            f"<td>{_pm(lv['mean']['mae_vec'], lv['sd'].get('mae_vec'))}</td>"
            f"<td>{_pm(lv['mean']['rmse_vec'], lv['sd'].get('rmse_vec'))}</td>"
            f"<td>{_pm(lv['mean']['accuracy_pct'], lv['sd'].get('accuracy_pct'), 1)}</td></tr>"
            f"<tr class='livers-pooled'><th>all cases pooled</th><td></td><td>{v['n_cases']}</td>"
            f"<td>{_fmt(vm['mae_vec'])}</td><td>{_fmt(vm['rmse_vec'])}</td><td>{_fmt(vm['accuracy_pct'], 1)}</td></tr>")
    vfigs = validation_figures(v, out_dir / "figures")
    table = per.replace("</tbody>", "</tbody><tfoot>" + foot + "</tfoot>")
    fig = (_figure(vfigs["per_liver"], out_dir, "MAE per unseen liver; " + ("the band is the mean ± sd over the "
                   "livers, " if n_liv != 1 else "the line is its MAE, ") +
                   "the worst liver in red.", 460) if "per_liver" in vfigs else "")
    parts.append(f"<h3>Per unseen liver</h3><div class='side'>{table}{fig}</div>")
    parts.append(f"<p>Worst liver: <code>{html.escape(str(worst))}</code> (largest MAE). The study's single "
                 f"unseen liver: MAE {_fmt(STUDY_VALIDATION_MAE_N)} N. MLflow: validation run "
                 f"{_run(v.get('run_id'))} (per-liver mean/sd as <code>mae_vec_livers_mean</code>, "
                 f"<code>…_sd</code>), model run {_run(v.get('model_run_id'))}.</p>")
    iv = v.get("interval")
    if iv:
        cov = iv["coverage"]
        out = [k for k, c in zip(("t1", "t2", "n"), cov) if not 88.0 <= round(100 * c, 1) <= 92.0]  # as printed
        band = ("each within" if not out else "<b class='flag'>" + (", ".join(out[:-1]) + " and " if out[1:] else "")
                + out[-1] + " outside</b>")
        test = iv.get("test_coverage")
        lb = iv.get("coverage_band_by_liver")  # how well the livers measure it (runs before this field: absent)
        scale = iv.get("scale")
        g = iv.get("stiffness_exponent")
        widened = ("widened where a liver's stiffness lies outside the calibration livers' range, by how far "
                   "outside" + ("" if iv.get("widen", "proportional") != "fitted" else
                                " (the calibration spans too few stiffnesses to fit how its residuals grow)")
                   if iv.get("widen", "proportional") != "fitted" or g is None else _fitted_widening(g))
        how = {"force": "scaled per case by the predicted force's magnitude, a + b |F| fitted on the calibration "
                        "residuals, and " + widened,
               "force_bins": "a width per bin of the predicted force's magnitude, each bin calibrated on its own "
                             "calibration cases, and " + widened,
               "stiffness": "scaled by each case's stiffness factor C10 / C10_ref"}.get(
            scale, "fixed per component, " + widened)
        if iv.get("spread_beta") is not None:  # normalised conformal on the GP ensemble members' disagreement
            how = (f"{how}; each width also scaled by how far the model's GP members disagree on the case (their sd "
                   f"plus {iv['spread_beta']:g} x its median over the calibration), so a case the members disagree "
                   "on gets a wider interval")
        if iv.get("far_factor"):  # far widths: a width of its own beyond the input-distance threshold
            how = (f"{how}; a case beyond the input-distance threshold (below) gets its own width, x "
                   + " / ".join(f"{v:.2f}" for v in iv["far_factor"]) + ", the others x "
                   + " / ".join(f"{v:.2f}" for v in iv["near_factor"])
                   + " (t1 / t2 / n; each group's conformal quantile on the calibration)")
        parts.append(
            "<h3>Calibrated interval</h3><p>Every prediction comes with an interval per local force component "
            f"(conformal, calibrated on the training livers' predictions by models that did not see them: "
            f"{iv['n_calibration']} cases, nominal "
            f"{100 * iv['nominal']:.0f} %). On the unseen livers it covers the true tangential (t1, t2) and normal "
            f"(n) force in {', '.join(f'{100 * c:.1f}' for c in cov)} % of the cases ({band} the 88–92 % band"
            + (f"; from {len(iv.get('coverage_per_liver') or {})} livers, the population's coverage lies in "
               f"{', '.join(f'{100 * lo:.1f}–{100 * hi:.1f}' for lo, hi in lb)} % (95 %, by liver)" if lb else "")
            + "); "
            + (f"on the IV test livers in {', '.join(f'{100 * c:.1f}' for c in test)} %; " if test else "")
            + "mean half-widths "
            + ", ".join("unbounded" if h is None else f"{h:.3f}" for h in iv["half_width_mean_n"])
            + f" N ({how}). Coverage below nominal on the unseen livers means they differ from the training "
              "population by more than that.</p>")
        bins = iv.get("coverage_by_force") or []
        if bins:
            rows = [[f"{b['lo_n']:.2f}–{b['hi_n']:.2f}", str(b["n"])]
                    + [_fmt(100 * c, 1) for c in b["coverage"]]
                    + [", ".join("unbounded" if h is None else f"{h:.3f}" for h in b["half_width_mean_n"])]
                    for b in bins]
            why = {"force": "the half-widths grow with the predicted force, so that the large forces are bounded as "
                            "the small ones are",
                   "force_bins": "each bin of the predicted force has its own width, calibrated on the training "
                                 "livers' cases of that bin"}.get(
                scale, "with widths that do not follow the force, the small forces tend to be over-covered and the "
                       "large ones under-covered")
            worst = min(((c, j, b) for b in bins for j, c in enumerate(b["coverage"])), key=lambda t: t[0])
            c, j, b = worst
            axis = ("t1", "t2", "n")[j]
            flag = (f" The lowest is {_fmt(100 * c, 1)} % ({axis}, {b['lo_n']:.2f}–{b['hi_n']:.2f} N): below 88 %, "
                    "the unseen livers' errors at those forces are larger than the training livers'."
                    if c < 0.88 else "")
            parts.append(f"<p>Coverage per quintile of the true force magnitude on the unseen livers: {why}.{flag}</p>"
                         + _table(["|F| (N)", "cases", "t1 %", "t2 %", "n %", "mean half-widths t1, t2, n (N)"],
                                  rows, cls="interval-bins"))
    parts.append(_extrapolation_paragraph(v.get("outside_training")))
    parts.append(_distance_paragraph(v.get("interval")))
    allv = v.get("all_variants") or {}
    if len(allv) > 1:
        parts.append("<h3>Every scenario-IV variant on the same unseen livers</h3>")
        rows = []
        for name, d in allv.items():
            dl = d.get("livers") or {}
            mean, sd = dl.get("mean") or {}, dl.get("sd") or {}
            label = html.escape(name) + (" <small>(validated)</small>" if name == chosen else "")
            rows.append([label, _pm(mean.get("mae_vec"), sd.get("mae_vec")),
                         _pm(mean.get("accuracy_pct"), sd.get("accuracy_pct"), 1),
                         f"<code>{html.escape(str(dl.get('worst', '–')))}</code>", _fmt(d["metrics"]["mae_vec"]),
                         _fmt(d["metrics"]["rmse_vec"]), _fmt(d["metrics"]["accuracy_pct"], 1),
                         _worst_bin(d.get("error_by_force_magnitude")), _run(d.get("model_run_id"))])
        parts.append(_table(["variant", "MAE (N), mean ± sd over livers", "accuracy %, mean ± sd over livers",
                             "worst liver", "MAE pooled (N)", "RMSE pooled (N)", "accuracy pooled %",
                             f"largest relative MAE of a force bin (target below {100 * REL_MAE_LIMIT:.0f} %)",
                             "model run"], rows, cls="variants", row_cls="variant"))
    parts.append(camera_section(data, v, main_variant))
    parts.append(physics_section(data.get("physics"), chosen))
    parts.append("<h3>Error against force magnitude</h3>")
    bins = v["error_by_force_magnitude"]
    flagged = [b for b in bins if _rel_mae(b) is not None and _rel_mae(b) >= REL_MAE_LIMIT]
    parts.append(f"<p>All unseen cases in equal-width bins of the true force magnitude. Relative MAE = MAE / the "
                 f"bin's mean |F|; the target is below {100 * REL_MAE_LIMIT:.0f} % in every bin (a model biased "
                 f"towards a constant force fails it in the lowest bin). "
                 + (f"<b class='flag'>{len(flagged)} of {len(bins)} bins at or above "
                    f"{100 * REL_MAE_LIMIT:.0f} %</b> (marked ⚠)." if flagged else
                    f"Every bin is below {100 * REL_MAE_LIMIT:.0f} %.") + "</p>")
    rows = []
    for b in bins:
        r = _rel_mae(b)
        bad = r is not None and r >= REL_MAE_LIMIT
        rel = "–" if r is None else f"{100 * r:.1f} %"
        rows.append([_fmt(b["force_lo_n"], 2), _fmt(b["force_hi_n"], 2), b["n"], _fmt(b.get("mean_force_n"), 2),
                     _fmt(b["mae_vec_n"]), _flagged(rel, bad)])
    table = _table(["|F| from (N)", "to (N)", "cases", "mean |F| (N)", "MAE (N)", "relative MAE"], rows,
                   cls="force-bins", row_cls="force-bin")
    fig = (_figure(vfigs["force"], out_dir, f"Error of every unseen case against its true force magnitude; red: "
                   f"the MAE per bin at the bin's mean |F|; dashed: {100 * REL_MAE_LIMIT:.0f} % of |F| (the "
                   f"target is below it).", 420) if "force" in vfigs else "")
    parts.append(f"<div class='side'>{table}{fig}</div>")
    ed = v.get("error_vs_distance") or {}
    if ed.get("distance_mm"):
        d = np.asarray(ed["distance_mm"], dtype=float)
        parts.append(f"<p>Distance of each validation exertion point from the nearest training exertion point "
                     f"(both livers centred on their centroids): median {_fmt(float(np.median(d)), 1)} mm, max "
                     f"{_fmt(float(d.max()), 1)} mm; correlation of error with distance r = "
                     f"{_fmt(v.get('corr_error_distance'), 2)}.</p>")
    val_dir = Path(data.get("validation_dir", out_dir))
    figs = [val_dir / f for f in v.get("figures", [])]
    if "distance" in vfigs:
        figs.append(vfigs["distance"])
    parts.append("<h3>Predicted against true force, all unseen cases</h3>")
    parts.append("<div class='pics'>" + "".join(_figure(f, out_dir, width=380) for f in figs) + "</div>")

    # ------------------------------------------------------------ studies
    parts.append("<h2 id='studies'>Comparison studies</h2>")
    if data.get("studies"):
        parts.append("<p>Each study reuses the simulated shards (no new FE). Every point starts from the "
                     "scenario's main model (its settings, and an MLP's Ax-tuned hyper-parameters), changes one setting, "
                     "is trained without Ax on the main model's training split minus a validation part (by liver "
                     "in IV) and scored on that validation part: no study reads the test split, so a setting "
                     "chosen from a study is not chosen on the test set. Study numbers are therefore not the "
                     "test-split numbers of the tables above.</p>")
    else:
        parts.append("<p>No comparison study in this run (<code>study.enabled</code>).</p>")
    for d in data.get("studies", []):
        name = d["study"]
        parts.append(f"<h3 id='study-{html.escape(name)}'>{html.escape(d.get('title', name))}</h3>")
        parts.append(f"<p>{html.escape(STUDY_TEXT.get(name, ''))} {d.get('epochs')} epochs per point; "
                     f"MLflow experiment <code>{html.escape(str(d.get('experiment_name')))}</code>.</p>")
        png = study_picture_of(d["path"])
        if png.exists():
            parts.append(_figure(png, out_dir, width=760))
        if name == "train_livers":
            parts.append(livers_curve_text(d))
        rows = []
        for p in d["points"]:
            mt = p.get("metrics") or {}
            status = "ok" if p["status"] == "ok" else f"failed: {p.get('reason', '')}"
            rows.append([html.escape(name), p["scenario"], html.escape(p["label"]), _fmt(mt.get("accuracy_pct"), 1),
                         _fmt(mt.get("mae_vec")), _fmt(mt.get("rmse_vec")), _fmt(p.get("n_train_geometries"), 0),
                         _fmt(p.get("n_train"), 0), _fmt(p.get("roi_nodes_mean"), 0),
                         _fmt(p.get("seconds"), 1), html.escape(status), _run(p.get("run_id"))])
        parts.append(_table(["study", "scenario", "setting", "accuracy %", "MAE (N)", "RMSE (N)", "training livers",
                             "training cases", "ROI nodes", "time (s)", "status", "MLflow run"], rows,
                            row_cls="study-point"))

    # ------------------------------------------------------------ MLflow
    # the run's MLflow experiment names, as the jobs logged them (Plan.experiment_name, via the report rule)
    mlflow_names = {k: f"<code>{html.escape(str(v))}</code>"
                    for k, v in (setup.get("mlflow_experiments") or {}).items()}
    parts.append("<h2 id='mlflow'>Where the numbers come from (MLflow)</h2>")
    parts.append(f"<p>Runs are in the tracking store <code>{html.escape(str(setup.get('tracking_uri', 'results/mlflow.db')))}"
                 f"</code>, experiments {mlflow_names.get('models', 'per scenario')} "
                 f"(trained models, Ax trials nested), {mlflow_names.get('validation', 'of the validation')}"
                 f" and {mlflow_names.get('studies', 'of the studies')} (one run per study "
                 "point, tags <code>study</code>, <code>value</code>, <code>scenario</code>). Open them with "
                 "<code>.venv/bin/liverforce ui</code> (or <code>mlflow ui --backend-store-uri "
                 "sqlite:///results/mlflow.db --host 127.0.0.1</code>) and paste a run id into the search "
                 "(<code>attributes.run_id = '…'</code>).</p>")

    style = ("<style>body{font-family:sans-serif;max-width:1250px;margin:auto;line-height:1.35}"
             "table{border-collapse:collapse;margin:8px 0}td,th{border:1px solid #bbb;padding:3px 8px;"
             "text-align:right;vertical-align:top}th{background:#f0f0f0}small{color:#555}"
             ".t59 td:nth-child(4),.t59 td:nth-child(6){color:#666}"
             ".t59 .pm{font-weight:bold}.t59 td:nth-child(2){text-align:left}"
             ".models td{white-space:nowrap}.models{font-size:13px}.models code{font-size:11px}"
             ".side{display:flex;flex-wrap:wrap;gap:24px;align-items:flex-start}"
             ".side figure,.pics figure{display:table}.side figcaption,.pics figcaption{display:table-caption;"
             "caption-side:bottom}.flag{color:#b00}tfoot th,tfoot td{background:#f7f7f7;font-weight:bold}"
             "tfoot th{text-align:left}.population img{border:1px solid #ddd}summary{cursor:pointer;margin:6px 0}"
             ".models .why{white-space:normal;display:block;width:260px;text-align:left}"
             ".imported{border-left:3px solid #4a7ab5;padding-left:10px;margin:10px 0}"
             ".imported td,.imported th{text-align:left}.imported h4{margin:6px 0}.frame-flag td{background:#fdf0f0}"
             ".pics{display:flex;flex-wrap:wrap;gap:8px}figure{margin:4px}figcaption{font-size:small}</style>")
    doc = (f"<!doctype html><html><head><meta charset='utf-8'><title>liverforce {html.escape(experiment)}</title>"
           f"{style}</head><body>{''.join(parts)}</body></html>")
    write_text_atomic(out_html, doc)
    return out_html
