"""The run report: one HTML page (tables + PNG figures) a surgeon-engineer can read.

Every number in the report is read from the stage outputs (``metrics.json`` of
each model, the shard manifests, the validation metrics), and each model row
carries the MLflow run id it came from, so the report can be checked against
the tracking store.
"""

from __future__ import annotations

import html
import json
import os
from pathlib import Path

#: the study's accuracies (Table 5.9), % — deformation only / with state vector
STUDY_ACCURACY = {
    "I": {"without": 92.1, "with": 95.8},
    "II": {"without": 78.1, "with": 91.2},
    "III": {"without": 69.1, "with": 88.5},
    "IV": {"without": 65.7, "with": 84.8},
}
STUDY_VALIDATION_MAE_N = 0.249


def _rel(path: str | Path, start: Path) -> str:
    return html.escape(os.path.relpath(Path(path).resolve(), start.resolve()))


def _table(header: list[str], rows: list[list]) -> str:
    th = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><thead><tr>{th}</tr></thead><tbody>{body}</tbody></table>"


def _fmt(v, nd=3) -> str:
    return "–" if v is None else (f"{v:.{nd}f}" if isinstance(v, float) else html.escape(str(v)))


def collect(model_metrics: list[str | Path], manifests: list[str | Path], validation: str | Path,
            features: list[str | Path]) -> dict:
    """Read every number the report shows (also used by the report test)."""
    models = []
    for p in model_metrics:
        m = json.loads(Path(p).read_text())
        models.append({
            "scenario": m.get("scenario") or Path(p).parent.parent.name,
            "variant": m.get("variant") or Path(p).parent.name,
            "state_vector": m.get("state_vector"), "encoder": m.get("encoder"),
            "metrics": m.get("metrics", {}), "run_id": m.get("run_id"), "n_cases": m.get("n_cases"),
            "seconds": m.get("seconds"), "path": str(p),
        })
    shards = []
    for p in manifests:
        m = json.loads(Path(p).read_text())
        shards.append({"scenario": Path(p).parent.name, "rows": m["rows"], "failed": m["failed"],
                       "shards": len(m["shards"]), "data_version": m["data_version"]})
    val = json.loads(Path(validation).read_text())
    geoms = []
    for p in features:
        f = json.loads(Path(p).read_text())
        geoms.append({"id": Path(p).name.removesuffix(".features.json"), **f})
    return {"models": models, "shards": shards, "validation": val, "geometries": geoms}


def write_report(data: dict, pictures: list[str | Path], experiment: str, out_html: str | Path,
                 solver_stats: dict | None = None) -> Path:
    out_html = Path(out_html)
    out_dir = out_html.parent
    out_dir.mkdir(parents=True, exist_ok=True)
    parts = [f"<h1>liverforce report — experiment <code>{html.escape(experiment)}</code></h1>",
             "<p>Units: mm, N, MPa. Accuracy % = 100 × (1 − Σ‖F̂ − F‖ / Σ‖F‖) over the test cases. "
             "Every model row names the MLflow run it came from.</p>"]

    # setup: geometries
    parts.append("<h2>Geometries</h2>")
    rows = []
    for g in data["geometries"]:
        vol = g.get("volume_mm3")
        rows.append([html.escape(g["id"]), _fmt(vol / 1e6 if vol else None, 3), _fmt(g.get("n_nodes"), 0),
                     _fmt(g.get("n_tets"), 0), _fmt(g.get("meshing_time_s"), 1)])
    parts.append(_table(["geometry", "volume (L)", "nodes", "tets", "meshing (s)"], rows))
    parts.append("<div class='pics'>" + "".join(
        f"<figure><img src='{_rel(p, out_dir)}' width='420'><figcaption>{html.escape(Path(p).name)}</figcaption></figure>"
        for p in pictures) + "</div>")

    # simulations
    parts.append("<h2>Simulations</h2>")
    rows = [[s["scenario"], s["rows"], s["failed"], _fmt(100 * s["failed"] / s["rows"] if s["rows"] else 0.0, 1),
             s["shards"], s["data_version"]] for s in data["shards"]]
    parts.append(_table(["scenario", "cases", "failed", "failed %", "shards", "data version"], rows))
    if solver_stats:
        parts.append("<p>" + html.escape(", ".join(f"{k}: {v}" for k, v in solver_stats.items())) + "</p>")

    # the accuracy table, like the study's Table 5.9
    parts.append("<h2>Accuracy per scenario (cf. the study's Table 5.9)</h2>")
    rows = []
    for m in sorted(data["models"], key=lambda m: (m["scenario"], m["variant"])):
        sv = "with" if m.get("state_vector") else "without"
        study = STUDY_ACCURACY.get(m["scenario"], {}).get(sv)
        mt = m["metrics"]
        rows.append([m["scenario"], html.escape(m["variant"]), html.escape(str(m.get("encoder"))), sv,
                     _fmt(mt.get("accuracy_pct"), 1), _fmt(study, 1), _fmt(mt.get("mae_vec")), _fmt(mt.get("rmse_vec")),
                     _fmt(mt.get("mae_x")), _fmt(mt.get("mae_y")), _fmt(mt.get("mae_z")),
                     f"<code>{html.escape(str(m.get('run_id')))}</code>"])
    parts.append(_table(["scenario", "variant", "encoder", "state vector", "accuracy %", "study %", "MAE (N)",
                         "RMSE (N)", "MAE x", "MAE y", "MAE z", "MLflow run"], rows))

    # validation
    v = data["validation"]
    vm = v["metrics"]
    parts.append("<h2>Unseen liver (validation)</h2>")
    parts.append(_table(["cases", "MAE (N)", "RMSE (N)", "accuracy %", "study MAE (N)", "MLflow run", "model run"],
                        [[v["n_cases"], _fmt(vm["mae_vec"]), _fmt(vm["rmse_vec"]), _fmt(vm["accuracy_pct"], 1),
                          _fmt(STUDY_VALIDATION_MAE_N), f"<code>{html.escape(str(v.get('run_id')))}</code>",
                          f"<code>{html.escape(str(v.get('model_run_id')))}</code>"]]))
    parts.append(_table(["|F| from (N)", "to (N)", "cases", "MAE (N)"],
                        [[_fmt(b["force_lo_n"], 2), _fmt(b["force_hi_n"], 2), b["n"], _fmt(b["mae_vec_n"])]
                         for b in v.get("error_by_force_magnitude", [])]))
    val_dir = Path(data.get("validation_dir", out_dir))
    parts.append("<div class='pics'>" + "".join(
        f"<figure><img src='{_rel(val_dir / f, out_dir)}' width='420'></figure>" for f in v.get("figures", [])) + "</div>")

    style = ("<style>body{font-family:sans-serif;max-width:1200px;margin:auto}table{border-collapse:collapse;"
             "margin:8px 0}td,th{border:1px solid #bbb;padding:3px 8px;text-align:right}"
             ".pics{display:flex;flex-wrap:wrap;gap:8px}</style>")
    doc = f"<!doctype html><html><head><meta charset='utf-8'><title>liverforce {html.escape(experiment)}</title>{style}</head><body>{''.join(parts)}</body></html>"
    tmp = out_html.with_name(f".{out_html.name}.tmp")
    tmp.write_text(doc)
    tmp.replace(out_html)
    return out_html
