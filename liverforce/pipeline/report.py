"""Report stage adapter: the run's HTML report from the stage outputs."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from liverforce.dataset import io as dio
from liverforce.layout import gid_of, scenario_of_manifest

log = logging.getLogger("liverforce")


def solver_statistics(manifests: list[str], stretch_range=None) -> dict:
    """Cases, failures (with reasons) and solve times per scenario, read from the verified shards.

    Also the principal stretches the cases reached (:func:`stretch_statistics`):
    ``per_scenario[sc]["stretch"]``, and ``stretch_range`` (the Drucker-checked
    ``material.stability_stretch``) as ``"stretch_range_checked"``.
    """
    per, reasons = {}, {}
    all_walls = []
    for m in manifests:
        walls, iters, steps, umax = [], [], [], []
        ids, lam_min, lam_max = [], [], []
        for shard in dio.verify_manifest(m):
            t = dio.read_table(shard, columns=["wall_time_s", "newton_iterations", "load_steps", "converged",
                                               "reason", "max_displacement_mm", "case_id", "min_principal_stretch",
                                               "max_principal_stretch"])
            ids += t.column("case_id").to_pylist()
            lam_min += t.column("min_principal_stretch").to_pylist()
            lam_max += t.column("max_principal_stretch").to_pylist()
            walls += t.column("wall_time_s").to_pylist()
            iters += t.column("newton_iterations").to_pylist()
            steps += t.column("load_steps").to_pylist()
            conv = t.column("converged").to_pylist()
            umax += [u for u, c in zip(t.column("max_displacement_mm").to_pylist(), conv) if c]
            for r, c in zip(t.column("reason").to_pylist(), conv):
                if not c:
                    key = (r or "unknown").split(":")[0][:80]
                    reasons[key] = reasons.get(key, 0) + 1
        all_walls += walls
        if walls:
            per[scenario_of_manifest(m)] = {
                "solve_time_total_s": float(np.sum(walls)), "solve_time_median_s": float(np.median(walls)),
                "solve_time_max_s": float(np.max(walls)), "newton_iterations_median": float(np.median(iters)),
                "load_steps_median": float(np.median(steps)),
                "max_displacement_median_mm": float(np.median(umax)) if umax else None,
                "stretch": stretch_statistics(ids, lam_min, lam_max, stretch_range),
            }
    overall = {}
    if all_walls:
        overall = {"cases simulated": len(all_walls),
                   "solver wall time total (s)": round(float(np.sum(all_walls)), 1),
                   "median per case (s)": round(float(np.median(all_walls)), 3)}
    return {"overall": overall, "per_scenario": per, "reasons": dict(sorted(reasons.items(), key=lambda kv: -kv[1])),
            "stretch_range_checked": list(stretch_range) if stretch_range is not None else None}


def stretch_statistics(case_ids, min_stretch, max_stretch, stretch_range=None, n_named: int = 5) -> dict:
    """The principal-stretch range a scenario's cases reached, and the cases outside the checked range.

    Parameters
    ----------
    case_ids, min_stretch, max_stretch : per case (the shard columns ``case_id``,
        ``min_principal_stretch``, ``max_principal_stretch``); NaN (a crashed solve) is skipped.
    stretch_range : ``(lo, hi)``, the Drucker-checked range; None: nothing is counted as outside.
    n_named : how many ids of outside cases to keep (the most extreme first).

    Returns
    -------
    dict
        ``n`` (cases with stretches), ``min`` / ``max`` (None if ``n == 0``),
        ``n_outside`` (None without a range) and ``outside_ids`` (up to ``n_named``).
    """
    lo_c = np.asarray(min_stretch, dtype=float).reshape(-1)
    hi_c = np.asarray(max_stretch, dtype=float).reshape(-1)
    ok = np.isfinite(lo_c) & np.isfinite(hi_c)
    out = {"n": int(ok.sum()), "min": float(lo_c[ok].min()) if ok.any() else None,
           "max": float(hi_c[ok].max()) if ok.any() else None, "n_outside": None, "outside_ids": []}
    if stretch_range is not None:
        lo, hi = map(float, stretch_range)
        # how far each case goes beyond the range, in log-stretch (0 inside)
        excess = np.maximum(np.log(lo) - np.log(np.where(ok, lo_c, lo)), np.log(np.where(ok, hi_c, hi)) - np.log(hi))
        outside = np.flatnonzero(ok & (excess > 0))
        outside = outside[np.argsort(-excess[outside], kind="stable")]
        out["n_outside"] = int(outside.size)
        out["outside_ids"] = [str(case_ids[i]) for i in outside[:n_named]]
    return out


def make_report(model_metrics: list[str], manifests: list[str], validation: str, features: list[str],
                pictures: list[str], experiment: str, out_html, studies: list[str] = (),
                setup: dict | None = None, surfaces: list[str] = (), physics: str | None = None) -> Path:
    """Write ``report/index.html`` (+ ``report/figures/``) from the stage outputs.

    ``studies``: the ``studies/<study>.json`` files (their PNGs beside them);
    ``setup``: the config slices the setup section shows (``population``:
    ``{"training": [ids], "unseen": [ids], "volume_range_l": [lo, hi]}``);
    ``surfaces``: the ``geometry/<id>.ply`` of every liver, drawn as the
    population picture ``report/figures/population.png`` (volumes from the
    mesh features). ``physics``: ``validate/physics.json`` (:mod:`liverforce.pipeline.physics`), if run.
    """
    from liverforce.report.html import collect, write_report

    setup = setup or {}
    data = collect(model_metrics, manifests, validation, features, studies)
    data["validation_dir"] = str(Path(validation).parent)
    if physics:
        data["physics"] = json.loads(Path(physics).read_text())
    stats = solver_statistics(manifests, (setup.get("material") or {}).get("stability_stretch"))
    population_png = None
    if surfaces:
        from liverforce.report.population import load_population, population_figure

        pop = setup.get("population") or {}
        livers = load_population({gid_of(p): p for p in surfaces},
                                 {g["id"]: g.get("volume_mm3") for g in data["geometries"]},
                                 training=pop.get("training", ()), unseen=pop.get("unseen", ()))
        population_png = population_figure(livers, Path(out_html).parent / "figures" / "population.png",
                                           volume_range_l=pop.get("volume_range_l"))
    path = write_report(data, pictures, experiment, out_html, solver_stats=stats, setup=setup,
                        population_png=population_png)
    log.info("report: %s", path)
    return path
