"""What the modelling choices cost the trained models (issue #18): the physics study.

The sweep simulates every case with one set of modelling choices: the supports
of ``config/boundary`` (foundation stiffness, k_t/k_n, a bilateral rib, no
gravity) and the tool as a Gaussian traction. A real liver is held by supports
nobody measured, and pushed by a rigid instrument. This stage takes the first
``validate.physics.n_cases`` cases of one unseen liver (never a training
liver: the same cases the validation scores) and simulates them again with one
choice changed at a time:

* foundation stiffness x ``foundation_scale`` (both foundations);
* k_t/k_n = ``tangential_ratio`` (the visceral face and ligaments slide);
* the rib as ``rib_contact`` (``unilateral``: it may separate; ``off``);
* gravity along each of ``gravity`` (RAS: ``[0, -1, 0]`` posterior = supine):
  the displacements are the tool's increment over the sagged state of the same
  supports and constants (the pre-operative image is of the sagged liver);
* the tool as a rigid sphere (``tool: sphere``, when the simulate stage offers
  it: ``simulate.tool_model``).

For every choice it reports what the physics does (the displacement under the
tool at the same force, relative to the baseline's: the force at a given
indentation moves by about the inverse; and how much the displacement field over
the ROI changes, in % of the baseline's) and what every trained scenario-IV
model makes of it: MAE and accuracy on the changed cases against the baseline
cases. The models assume the baseline (their stiffness probe is the baseline
supports'), as a model in surgery assumes the configured supports: the change
in error is what mis-modelling that choice costs the product.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np

from liverforce.atomic import write_json_atomic
from liverforce.dataset import io as dio
from liverforce.layout import gid_of, model_of_metrics, physics_variant_files

log = logging.getLogger("liverforce")

BASELINE = "baseline (config)"


def physics_variants(boundary: dict, sim: dict, spec: dict) -> list[dict]:
    """The changed choices, each ``{"name", "what", "boundary", "simulate"}`` (full config slices).

    ``spec`` is ``validate.physics``; the baseline (the configured supports and tool) comes first.
    """
    out = [{"name": BASELINE, "what": "the configured supports and tool", "boundary": boundary, "simulate": sim}]

    def add(name, what, b=None, s=None):
        out.append({"name": name, "what": what, "boundary": {**boundary, **(b or {})}, "simulate": {**sim, **(s or {})}})

    for f in spec.get("foundation_scale", []):
        add(f"foundation x{f:g}", f"both foundations' stiffness x{f:g}",
            {"ligament_total_n_per_mm": f * boundary["ligament_total_n_per_mm"],
             "visceral_total_n_per_mm": f * boundary["visceral_total_n_per_mm"]})
    for r in spec.get("tangential_ratio", []):
        add(f"kt/kn {r:g}", f"tangential foundation stiffness {r:g} x the normal one", {"tangential_ratio": float(r)})
    for rib in spec.get("rib_contact", []):
        if rib == "off":
            add("rib off", "no rib support", {"rib_normal_n_per_mm3": 0.0})
        else:
            add(f"rib {rib}", f"rib contact {rib}", {"rib_contact": rib})
    for d in spec.get("gravity", []):
        d = [float(x) for x in d]
        name = {(0.0, -1.0, 0.0): "gravity supine", (0.0, 0.0, -1.0): "gravity upright"}.get(tuple(d), f"gravity {d}")
        add(name, f"self-weight {boundary['gravity']['density_kg_per_m3']:g} kg/m³ along {d} (RAS); "
                  "displacements over the sagged state",
            {"gravity": {**boundary["gravity"], "enabled": True, "direction": d}})
    if spec.get("tool") == "sphere":
        add("tool: rigid sphere", f"a rigid frictionless sphere of radius {sim.get('tool_tip_radius_mm', 2.5)} mm "
                                  "in place of the Gaussian traction", s={"tool_model": "sphere"})
    return out


def tool_displacement_mm(rows) -> np.ndarray:
    """|u| (mm) at the ROI node nearest each case's exertion point, from column arrays (``load_training_arrays``)."""
    out = []
    for und, dfm, x0 in zip(rows["roi_undeformed_mm"], rows["roi_deformed_mm"], rows["exertion_point_mm"]):
        und = np.asarray(und, float).reshape(-1, 3)
        dfm = np.asarray(dfm, float).reshape(-1, 3)
        k = int(np.argmin(np.linalg.norm(und - np.asarray(x0, float), axis=1)))
        out.append(float(np.linalg.norm(dfm[k] - und[k])))
    return np.asarray(out)


def _sag_max(mesh, boundary: dict, sim: dict, case: dict) -> float:
    """The largest displacement (mm) of the liver under gravity alone, with ``case``'s constants."""
    from liverforce.fem.materials import make_material
    from liverforce.fem.problem import LiverModel, ToolLoad
    from liverforce.pipeline.simulate import _sag, boundary_params, solver_options

    mat = make_material(case["material_model"], dict(zip(case["material_param_names"], case["material_params_mpa"])),
                        bulk_mpa=case["bulk_modulus_mpa"])
    fe = LiverModel(mesh.points, mesh.tets, mesh.facets, mesh.facet_region, mat, boundary_params(mesh, boundary),
                    solver_options(sim))
    u = _sag(fe, ToolLoad(np.asarray(case["exertion_point_mm"], float), np.zeros(3), sim["tool_radius_mm"]), mat)
    return float(np.linalg.norm(u, axis=1).max())


def physics_study(cases_path, mesh_path, model_dirs, model_metrics, sim: dict, boundary: dict, dataset: dict,
                  material: dict, spec: dict, out_path, shard_dir) -> dict:
    """Simulate one unseen liver's first cases under each :func:`physics_variants` choice and score every model.

    ``model_dirs`` / ``model_metrics``: the scenario-IV models (all variants). Writes one shard per choice
    under ``shard_dir`` and the study as JSON to ``out_path``; returns it.

    The sphere (``tool: sphere``) runs the liver's first ``tool_cases`` cases of at most ``tool_max_force_n`` (a
    contact case costs tens of traction cases, and a 5 mm tip sinks deeper than the default mesh resolves
    beyond about 1 N: Hertz gives ~7 mm at 1 N for R 2.5 mm in this tissue). A frictionless tip exerts a force close to the surface normal whatever the push
    direction, so it is compared with the traction carrying the *same* force vectors (the sphere's own,
    simulated as an extra choice "traction at the sphere's forces"), not with the baseline's inclined ones.
    """
    from liverforce.learn.model import ForceModel
    from liverforce.mesh.io import read_mesh
    from liverforce.pipeline.simulate import probe_reference, simulate_cases

    gid = gid_of(mesh_path)
    table = dio.read_table(cases_path).to_pylist()
    liver_cases = sorted((c for c in table if c["geometry_id"] == gid), key=lambda c: c["case_id"])
    cases = liver_cases[: int(spec["n_cases"])]
    if not cases:
        raise ValueError(f"{cases_path}: no case on the liver {gid}")
    mesh = read_mesh(mesh_path)
    probe = probe_reference(material)
    models = {model_of_metrics(mp)[1]: ForceModel.load(Path(d)) for d, mp in zip(model_dirs, model_metrics)}
    shard_dir = Path(shard_dir)
    out = {"liver": gid, "n_cases": len(cases), "case_ids": [c["case_id"] for c in cases],
           "forces_n": [float(np.linalg.norm(c["force_n"])) for c in cases], "variants": []}
    done: dict = {}  # name -> (rows, measured fields) of the choices simulated so far

    def run(k, v, these, ref_name):
        t0 = time.perf_counter()
        rows = simulate_cases(these, {gid: mesh}, v["simulate"], v["boundary"], dataset, probe=probe)
        sag = _sag_max(mesh, v["boundary"], v["simulate"], these[0]) if v["boundary"]["gravity"]["enabled"] else None
        if done:  # a model in surgery assumes the configured supports: its stiffness probe is the baseline's
            base = {tuple(r["exertion_point_mm"]): r["probe_compliance_mm_per_n"] for r in done[BASELINE][0]}
            for r in rows:  # (a point the baseline did not probe was probed here with the baseline's supports)
                r["probe_compliance_mm_per_n"] = base.get(tuple(r["exertion_point_mm"]), r["probe_compliance_mm_per_n"])
        entry = {"name": v["name"], "what": v["what"], "n_cases": len(rows),
                 "converged": int(sum(r["converged"] for r in rows)), "sag_max_mm": sag, "compared_with": ref_name,
                 **_score(k, v, rows, done.get(ref_name), models, mesh_path, dataset, probe, shard_dir)}
        entry["wall_time_s"] = time.perf_counter() - t0
        done[v["name"]] = (rows, entry.pop("_fields"))
        out["variants"].append(entry)
        against = _comparison(entry, ref_name) if ref_name else ""  # the baseline: none; the sphere: after its pair
        log.info("physics %s: %d/%d converged%s, %s (%.0f s)", v["name"], entry["converged"], len(rows), against,
                 ", ".join(f"{n} MAE {e['mae_vec']:.3f} N" for n, e in entry["models"].items()), entry["wall_time_s"])
        return rows

    k = 0
    for v in physics_variants(boundary, sim, spec):  # the baseline first
        if v["simulate"].get("tool_model") == "sphere":
            cap = float(spec.get("tool_max_force_n", np.inf))
            these = [c for c in liver_cases if c["force_magnitude_n"] <= cap][: int(spec.get("tool_cases", len(cases)))]
            if not these:
                log.warning("physics: no case of at most %g N for the sphere (validate.physics.tool_max_force_n)", cap)
                continue
            sphere = run(k, v, these, None)
            k += 1
            same = [{**c, "force_n": list(map(float, r["force_n"])),
                     "force_magnitude_n": float(np.linalg.norm(r["force_n"]))} for c, r in zip(these, sphere)
                    if r["converged"]]
            trac = {**v, "name": "traction at the sphere's forces", "simulate": sim,
                    "what": "the Gaussian traction carrying the force vectors the sphere exerted"}
            if same:
                run(k, trac, same, None)
                k += 1
                # the sphere against the traction of the same forces: rescore with that reference
                sph = next(e for e in out["variants"] if e["name"] == v["name"])
                sph.update(_compare(done[v["name"]][1], done[trac["name"]][1]), compared_with=trac["name"])
                log.info("physics %s%s", v["name"], _comparison(sph, f"the {trac['name']}")
                         or f": no comparison with the {trac['name']} (no case converged in both)")
            continue
        run(k, v, cases, None if k == 0 else BASELINE)
        k += 1
    write_json_atomic(out_path, out)
    return out


def _comparison(entry: dict, ref: str) -> str:
    """", u under the tool xR of <ref>, ROI field changed C % (mean)" for the log; its parts that are measured."""
    ratio, change = entry.get("u_tool_ratio_median", np.nan), entry.get("roi_change_pct_mean", np.nan)
    parts = ([f"u under the tool x{ratio:.2f} of {ref}"] if np.isfinite(ratio) else []) + (
        [f"ROI field changed {change:.0f} % (mean)"] if np.isfinite(change) else [])
    return "".join(", " + p for p in parts)


def _fields(arrays) -> dict:
    """case id -> (|u| under the tool, ROI displacement field) of converged cases."""
    u = tool_displacement_mm(arrays)
    return {str(c): (u_i, np.asarray(d, float).reshape(-1, 3) - np.asarray(e, float).reshape(-1, 3))
            for c, u_i, d, e in zip(arrays["case_id"], u, arrays["roi_deformed_mm"], arrays["roi_undeformed_mm"])}


def _compare(fields: dict, ref: dict | None) -> dict:
    """The displacement under the tool and the ROI field against a reference choice's, on their common cases."""
    if ref is None:
        return {}
    both = [c for c in fields if c in ref and ref[c][0] > 1e-6]
    if not both:
        return {}
    ratio = np.array([fields[c][0] / ref[c][0] for c in both])
    change = np.array([np.linalg.norm(fields[c][1] - ref[c][1]) / np.linalg.norm(ref[c][1]) for c in both])
    return {"u_tool_ratio_median": float(np.median(ratio)), "u_tool_ratio_range": [float(ratio.min()), float(ratio.max())],
            "roi_change_pct_mean": float(100.0 * change.mean()), "roi_change_pct_max": float(100.0 * change.max())}


def _score(k, v, rows, ref, models, mesh_path, dataset, probe, shard_dir) -> dict:
    """Write the choice's shard, then measure it against ``ref`` (rows, fields) and score every model on it."""
    from liverforce.learn.metrics import force_metrics
    from liverforce.pipeline.shared import camera_arrays
    from liverforce.pipeline.simulate import make_manifest

    shard, manifest = physics_variant_files(shard_dir, k)
    shard.parent.mkdir(parents=True, exist_ok=True)
    dio.write_shard(rows, shard, compression=dataset["compression"],
                    extra_meta={"simulate": v["simulate"], "boundary": v["boundary"], "dataset": dataset,
                                "probe": probe, "physics_variant": v["name"]})
    make_manifest([str(shard)], manifest)
    out = {"models": {}, "_fields": {}}
    if not any(r["converged"] for r in rows):
        return out
    arrays = camera_arrays(manifest, [str(mesh_path)], "physics study")
    out["_fields"] = fields = _fields(arrays)
    out["u_tool_mm_median"] = float(np.median([f[0] for f in fields.values()]))
    out.update(_compare(fields, ref[1] if ref is not None else (fields if k == 0 else None)))
    for name, m in models.items():
        pred = m.predict(arrays, observation_seed=int(m.meta.get("eval_observation_seed", 0)))
        fm = force_metrics(arrays["force_n"], pred)
        out["models"][name] = {"mae_vec": fm["mae_vec"], "accuracy_pct": fm["accuracy_pct"]}
    return out


def load(path) -> dict | None:
    """The physics study's JSON, or None when the file is absent (the stage is off)."""
    p = Path(path)
    return json.loads(p.read_text()) if p.exists() else None


