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

A lab's liver held out with its own supports (``geometry.imported[].supports``,
:mod:`liverforce.mesh.supports`) keeps them: every choice, the baseline too, is
simulated with its foundations' stiffness (``support_boundary`` of its features
JSON, as the validation's simulation of it, ``simulate_shard``), changed as the
configured ones are: foundation x f scales the lab's foundations' stiffness with
the configured totals, k_t/k_n = r sets each lab foundation's ``kt = r kn``; fixed
and sliding supports are not springs and stay as they are. The rib choices act on
the rib region (a lab's sliding supports are rib region); a liver without one (a
lab's under ``mode: replace`` with no sliding support) skips them, as it skips the
foundation choices without a foundation region: the choice would change nothing.
The study's JSON lists each skipped choice with the reason under ``skipped``.

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
from liverforce.layout import features_of_mesh, gid_of, model_of_metrics, physics_variant_files
from liverforce.mesh.supports import FOUNDATION_SLOTS
from liverforce.mesh.types import REGION_CODES

log = logging.getLogger("liverforce")

BASELINE = "baseline (config)"
#: the baseline's name for a lab's liver simulated with its own supports
LAB_BASELINE = "baseline (the lab's supports)"


def physics_variants(boundary: dict, sim: dict, spec: dict, supports: dict | None = None,
                     lab: list[dict] | None = None, areas: dict | None = None) -> list[dict]:
    """The changed choices, each ``{"name", "what", "boundary", "simulate", "supports"}`` (full config slices).

    ``spec`` is ``validate.physics``; the baseline (the configured supports and tool, or the lab's) comes first.

    Parameters
    ----------
    supports : the liver's own foundation stiffness (``support_boundary`` of its features JSON, N/mm³:
        ``ligament_kn`` ...), passed to ``simulate_cases(supports=)`` in place of the config's; None or empty:
        none. Each choice carries its own (``"supports"``): foundation x f scales every foundation's ``*_kn``
        and ``*_kt``, k_t/k_n = r sets each foundation's ``kt = r kn``, the other choices keep them.
    lab : the lab's supports as the features JSON lists them (``supports``: ``name``, ``kind``, ``region_code``);
        given, the baseline is named :data:`LAB_BASELINE` and the choices' ``what`` say what becomes of them.
    areas : the liver's region areas (region code -> mm², :func:`liverforce.fem.boundary.region_areas`); given, a
        choice that would change nothing on this liver (the rib choices without a rib region, the foundation
        choices without a foundation region) gets ``"skip"``: why, and is not to be simulated. None: none skipped.
    """
    own = {k: float(v) for k, v in (supports or {}).items()}
    base = {"name": LAB_BASELINE if lab else BASELINE, "boundary": boundary, "simulate": sim, "supports": own,
            "what": (f"the lab's supports of this liver ({_lab_words(lab)}; under supports mode: add the "
                     "auto-tagged regions beneath them keep the configured stiffness, except in a foundation slot "
                     "(ligament, visceral) one of the lab's foundations takes: its stiffness holds the whole slot) "
                     "and the configured tool")
            if lab else "the configured supports and tool"}
    out = [base]
    n_stay = sum(s.get("kind") in ("fixed", "sliding") for s in lab or [])
    stay = (f"; the lab's {_lab_words(lab, ('fixed', 'sliding'))} "
            + ("is not a spring: it stays as it is" if n_stay == 1 else "are not springs: they stay as they are")
            if n_stay else "")
    no_rib = areas is not None and not areas.get(REGION_CODES["rib"], 0.0) > 0
    no_foundation = areas is not None and not sum(areas.get(REGION_CODES[s], 0.0) for s in FOUNDATION_SLOTS) > 0

    def add(name, what, b=None, s=None, own_changed=None, skip=None):
        out.append({"name": name, "what": what, "boundary": {**boundary, **(b or {})},
                    "simulate": {**sim, **(s or {})}, "supports": own if own_changed is None else own_changed,
                    **({"skip": skip} if skip else {})})

    lab_found = _lab_words(lab, ("foundation",))
    found_skip = ("the liver has no foundation region (ligament or visceral): its stiffness would change nothing"
                  if no_foundation else None)
    for f in spec.get("foundation_scale", []):
        add(f"foundation x{f:g}", (f"every foundation's stiffness x{f:g}: the lab's {lab_found} and the configured "
                                   "totals" if lab_found else f"both foundations' stiffness x{f:g}") + stay,
            {"ligament_total_n_per_mm": f * boundary["ligament_total_n_per_mm"],
             "visceral_total_n_per_mm": f * boundary["visceral_total_n_per_mm"]},
            own_changed={k: (f * v if _is_foundation_key(k) else v) for k, v in own.items()}, skip=found_skip)
    for r in spec.get("tangential_ratio", []):
        add(f"kt/kn {r:g}", f"tangential foundation stiffness {r:g} x the normal one" + (
            f", the lab's {lab_found} and the configured ones" if lab_found else "") + stay,
            {"tangential_ratio": float(r)},
            own_changed={**own, **{f"{s}_kt": float(r) * own[f"{s}_kn"] for s in FOUNDATION_SLOTS
                                   if f"{s}_kn" in own}}, skip=found_skip)
    sliding = _lab_words(lab, ("sliding",))
    on_rib = f" (the rib region: the lab's {sliding})" if sliding else ""
    rib_skip = ("the liver has no rib region" + (" (the lab's supports hold no sliding one)" if lab else "")
                + ": the rib's contact would change nothing") if no_rib else None
    for rib in spec.get("rib_contact", []):
        if rib == "off":
            add("rib off", "no rib support" + on_rib, {"rib_normal_n_per_mm3": 0.0}, skip=rib_skip)
        else:
            add(f"rib {rib}", f"rib contact {rib}" + on_rib, {"rib_contact": rib}, skip=rib_skip)
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


def _is_foundation_key(key: str) -> bool:
    """A foundation's stiffness in ``support_boundary``: ``<slot>_kn`` or ``<slot>_kt``, slot ligament or visceral."""
    slot, _, k = key.rpartition("_")
    return slot in FOUNDATION_SLOTS and k in ("kn", "kt")


def _lab_words(lab: list[dict] | None, kinds=("fixed", "foundation", "sliding")) -> str:
    """The lab's supports of ``kinds`` for a choice's ``what``: ``fixed 'cava', foundation (visceral) 'bed'``."""
    slots = {REGION_CODES[s]: s for s in FOUNDATION_SLOTS}
    return ", ".join(f"{s.get('kind')}" + (f" ({slots[s['region_code']]})" if s.get("region_code") in slots
                                           and s.get("kind") == "foundation" else "") + f" '{s.get('name')}'"
                     for s in lab or [] if s.get("kind") in kinds)


def tool_displacement_mm(rows) -> np.ndarray:
    """|u| (mm) at the ROI node nearest each case's exertion point, from column arrays (``load_training_arrays``)."""
    out = []
    for und, dfm, x0 in zip(rows["roi_undeformed_mm"], rows["roi_deformed_mm"], rows["exertion_point_mm"]):
        und = np.asarray(und, float).reshape(-1, 3)
        dfm = np.asarray(dfm, float).reshape(-1, 3)
        k = int(np.argmin(np.linalg.norm(und - np.asarray(x0, float), axis=1)))
        out.append(float(np.linalg.norm(dfm[k] - und[k])))
    return np.asarray(out)


def _sag_max(mesh, boundary: dict, sim: dict, case: dict, supports: dict | None = None) -> float:
    """The largest displacement (mm) of the liver under gravity alone, with ``case``'s constants.

    ``supports``: the liver's own foundation stiffness (``support_boundary``), as ``simulate_cases`` takes it."""
    from liverforce.fem.materials import make_material
    from liverforce.fem.problem import LiverModel, ToolLoad
    from liverforce.pipeline.simulate import _sag, boundary_params, solver_options

    mat = make_material(case["material_model"], dict(zip(case["material_param_names"], case["material_params_mpa"])),
                        bulk_mpa=case["bulk_modulus_mpa"])
    fe = LiverModel(mesh.points, mesh.tets, mesh.facets, mesh.facet_region, mat,
                    boundary_params(mesh, boundary).with_supports(supports), solver_options(sim))
    u = _sag(fe, ToolLoad(np.asarray(case["exertion_point_mm"], float), np.zeros(3), sim["tool_radius_mm"]), mat)
    return float(np.linalg.norm(u, axis=1).max())


def physics_study(cases_path, mesh_path, model_dirs, model_metrics, sim: dict, boundary: dict, dataset: dict,
                  material: dict, spec: dict, out_path, shard_dir) -> dict:
    """Simulate one unseen liver's first cases under each :func:`physics_variants` choice and score every model.

    ``model_dirs`` / ``model_metrics``: the scenario-IV models (all variants). Writes one shard per choice
    under ``shard_dir`` and the study as JSON to ``out_path``; returns it.

    The liver's features JSON is the one beside its mesh (``features_of_mesh``), as the simulate stage reads
    it. A lab's liver with its own supports (its
    ``supports`` and ``support_boundary``) keeps them in every choice (:func:`physics_variants`), so the
    baseline is the validation's simulation of these cases; the JSON records them under ``own_supports``
    (None for the configured supports) and the choices that would change nothing on this liver under
    ``skipped`` (``name``, ``what``, ``reason``).

    The sphere (``tool: sphere``) runs the liver's first ``tool_cases`` cases of at most ``tool_max_force_n`` (a
    contact case costs tens of traction cases, and a 5 mm tip sinks deeper than the default mesh resolves
    beyond about 1 N: Hertz gives ~7 mm at 1 N for R 2.5 mm in this tissue). On a held-out liver of its own
    material the cap is scaled by its stiffness (``spec["tool_force_scale"]``, :func:`_tool_cap`); the cap used
    is recorded as ``tool_max_force_n``, and no case under it skips the sphere (listed under ``skipped``).
    A frictionless tip exerts a force close to the surface normal whatever the push direction, so it is compared
    with the traction carrying the *same* force vectors (the sphere's own, simulated as an extra choice "traction
    at the sphere's forces"), not with the baseline's inclined ones.
    """
    from liverforce.fem.boundary import region_areas
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
    feats = _features(mesh_path)
    own, lab = feats.get("support_boundary") or {}, feats.get("supports") or []
    variants = physics_variants(boundary, sim, spec, own, lab,
                                region_areas(mesh.points, mesh.facets, mesh.facet_region))
    baseline = variants[0]["name"]
    probe = probe_reference(material)
    models = {model_of_metrics(mp)[1]: ForceModel.load(Path(d)) for d, mp in zip(model_dirs, model_metrics)}
    shard_dir = Path(shard_dir)
    out = {"liver": gid, "n_cases": len(cases), "case_ids": [c["case_id"] for c in cases],
           "forces_n": [float(np.linalg.norm(c["force_n"])) for c in cases],
           "own_supports": {"supports": lab, "support_boundary": own} if lab else None, "variants": [], "skipped": []}
    if lab:
        log.info("physics: %s keeps the lab's supports (%s) in every choice, as the validation simulated it",
                 gid, _lab_words(lab))
    done: dict = {}  # name -> (rows, measured fields) of the choices simulated so far

    def run(k, v, these, ref_name):
        t0 = time.perf_counter()
        rows = simulate_cases(these, {gid: mesh}, v["simulate"], v["boundary"], dataset, probe=probe,
                              supports={gid: v["supports"]})
        sag, sag_error = None, None
        if v["boundary"]["gravity"]["enabled"]:
            try:
                sag = _sag_max(mesh, v["boundary"], v["simulate"], these[0], v["supports"])
            except Exception as exc:  # noqa: BLE001 - not held against its weight: this choice fails, the rest go on
                sag_error = f"{type(exc).__name__}: {exc}"
                log.warning("physics %s: %s; its cases are recorded as failed", v["name"], sag_error)
        if done:  # a model in surgery assumes the baseline's supports: its stiffness probe is the baseline's
            base = {tuple(r["exertion_point_mm"]): r["probe_compliance_mm_per_n"] for r in done[baseline][0]}
            for r in rows:  # (a point the baseline did not probe was probed here with the baseline's supports)
                r["probe_compliance_mm_per_n"] = base.get(tuple(r["exertion_point_mm"]), r["probe_compliance_mm_per_n"])
        entry = {"name": v["name"], "what": v["what"], "n_cases": len(rows),
                 "converged": int(sum(r["converged"] for r in rows)), "sag_max_mm": sag,
                 **({"sag_error": sag_error} if sag_error else {}), "compared_with": ref_name,
                 **_score(k, v, rows, done.get(ref_name), models, mesh_path, dataset, probe, shard_dir)}
        entry["wall_time_s"] = time.perf_counter() - t0
        done[v["name"]] = (rows, entry.pop("_fields"))
        out["variants"].append(entry)
        against = _comparison(entry, ref_name) if ref_name else ""  # the baseline: none; the sphere: after its pair
        log.info("physics %s: %d/%d converged%s, %s (%.0f s)", v["name"], entry["converged"], len(rows), against,
                 ", ".join(f"{n} MAE {e['mae_vec']:.3f} N" for n, e in entry["models"].items()), entry["wall_time_s"])
        return rows

    k = 0
    for v in variants:  # the baseline first
        if v.get("skip"):
            log.warning("physics %s: not simulated, %s", v["name"], v["skip"])
            out["skipped"].append({"name": v["name"], "what": v["what"], "reason": v["skip"]})
            continue
        if v["simulate"].get("tool_model") == "sphere":
            cap, scaled = _tool_cap(spec)
            these = [c for c in liver_cases if c["force_magnitude_n"] <= cap][: int(spec.get("tool_cases", len(cases)))]
            out["tool_max_force_n"] = cap if np.isfinite(cap) else None
            if scaled:
                out["tool_force_scale"] = float(spec["tool_force_scale"])
                log.info("physics: the sphere's cases of at most %.3g N (validate.physics.tool_max_force_n %g x "
                         "%.3g, %s's own initial shear modulus over the procedural unseen livers')", cap,
                         spec["tool_max_force_n"], spec["tool_force_scale"], gid)
            if not these:
                why = (f"no case of {gid} of at most {cap:.3g} N for the sphere (validate.physics.tool_max_force_n"
                       + (f" {spec['tool_max_force_n']:g} x {spec['tool_force_scale']:.3g}, this liver's own "
                          "stiffness" if scaled else "") + "): give validate.n_cases more cases, or a larger cap "
                       "with a finer mesh at the exertion points (mesh.refine_edge_mm)")
                log.warning("physics %s: not simulated, %s", v["name"], why)
                out["skipped"].append({"name": v["name"], "what": v["what"], "reason": why})
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
        run(k, v, cases, None if k == 0 else baseline)
        k += 1
    write_json_atomic(out_path, out)
    return out


def _tool_cap(spec: dict) -> tuple[float, bool]:
    """The sphere's force cap (N) on this liver, and whether it was scaled: ``tool_max_force_n`` x
    ``tool_force_scale`` (:meth:`liverforce.pipeline.plan.Plan.physics_spec`: a held-out liver of its own
    material, its stiffness over the procedural unseen livers' for which the cap is set), else as configured."""
    cap = float(spec.get("tool_max_force_n", np.inf))
    if "tool_force_scale" not in spec:
        return cap, False
    return cap * float(spec["tool_force_scale"]), True


def _features(mesh_path) -> dict:
    """The liver's features JSON beside its mesh, as ``simulate_shard`` reads it; {} when there is none."""
    p = features_of_mesh(mesh_path)
    return json.loads(p.read_text()) if p.exists() else {}


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
                                "probe": probe, "physics_variant": v["name"], "support_boundary": v["supports"]})
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


