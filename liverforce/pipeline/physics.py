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


def tool_displacement_mm(arrays_or_rows) -> np.ndarray:
    """|u| (mm) at the ROI node nearest each case's exertion point, from shard rows or arrays."""
    rows = arrays_or_rows
    out = []
    for und, dfm, x0 in zip(rows["roi_undeformed_mm"], rows["roi_deformed_mm"], rows["exertion_point_mm"]):
        und = np.asarray(und, float).reshape(-1, 3)
        dfm = np.asarray(dfm, float).reshape(-1, 3)
        k = int(np.argmin(np.linalg.norm(und - np.asarray(x0, float), axis=1)))
        out.append(float(np.linalg.norm(dfm[k] - und[k])))
    return np.asarray(out)


def _over_sag(rows: list[dict], mesh, boundary: dict, sim: dict) -> float:
    """With gravity on: every row's displacements minus the gravity-only state of its constants (in place).

    Returns the largest sag (mm) over the constants. The pre-operative image shows the sagged liver, so
    the tool's increment over that state is what a camera sees.
    """
    from liverforce.dataset.roi import surface_graph
    from liverforce.fem.materials import make_material
    from liverforce.fem.problem import LiverModel, ToolLoad
    from liverforce.pipeline.simulate import boundary_params, solver_options

    surf = surface_graph(mesh.points, mesh.facets)
    sags: dict = {}
    fe = None
    for row in rows:
        key = (row["material_model"], tuple(row["material_params_mpa"]), row["bulk_modulus_mpa"])
        if key not in sags:
            mat = make_material(key[0], dict(zip(row["material_param_names"], key[1])), bulk_mpa=key[2])
            if fe is None:
                fe = LiverModel(mesh.points, mesh.tets, mesh.facets, mesh.facet_region, mat,
                                boundary_params(mesh, boundary), solver_options(sim))
            res = fe.solve(ToolLoad(np.asarray(row["exertion_point_mm"], float), np.zeros(3), sim["tool_radius_mm"]),
                           material=mat)
            if not res.converged:
                raise RuntimeError(f"the gravity-only state did not converge ({res.reason})")
            sags[key] = res.u_nodes
        u_g = sags[key]
        ids = np.asarray(row["roi_node_ids"], int)
        row["roi_deformed_mm"] = (np.asarray(row["roi_deformed_mm"], float) - u_g[ids]).astype(np.float32)
        row["roi_centroid_deformed_mm"] = np.asarray(row["roi_deformed_mm"], float).mean(axis=0)
        if len(row["surface_displacement_mm"]):
            row["surface_displacement_mm"] = (np.asarray(row["surface_displacement_mm"], float)
                                              - u_g[surf.node_ids]).astype(np.float32)
    return float(max(np.linalg.norm(u, axis=1).max() for u in sags.values()))


def physics_study(cases_path, mesh_path, model_dirs, model_metrics, sim: dict, boundary: dict, dataset: dict,
                  material: dict, spec: dict, out_path, shard_dir) -> dict:
    """Simulate one unseen liver's first cases under each :func:`physics_variants` choice and score every model.

    ``model_dirs`` / ``model_metrics``: the scenario-IV models (all variants). Writes one shard per choice
    under ``shard_dir`` and the study as JSON to ``out_path``; returns it.
    """
    from liverforce.learn.metrics import force_metrics
    from liverforce.learn.model import ForceModel
    from liverforce.mesh.io import read_mesh
    from liverforce.pipeline.shared import camera_arrays
    from liverforce.pipeline.simulate import make_manifest, probe_reference, simulate_cases

    gid = gid_of(mesh_path)
    table = dio.read_table(cases_path).to_pylist()
    cases = sorted((c for c in table if c["geometry_id"] == gid), key=lambda c: c["case_id"])[: int(spec["n_cases"])]
    if not cases:
        raise ValueError(f"{cases_path}: no case on the liver {gid}")
    mesh = read_mesh(mesh_path)
    probe = probe_reference(material)
    models = {}
    for d, mp in zip(model_dirs, model_metrics):
        models[model_of_metrics(mp)[1]] = ForceModel.load(Path(d))
    shard_dir = Path(shard_dir)
    shard_dir.mkdir(parents=True, exist_ok=True)
    out = {"liver": gid, "n_cases": len(cases), "case_ids": [c["case_id"] for c in cases],
           "forces_n": [float(np.linalg.norm(c["force_n"])) for c in cases], "variants": []}
    base_rows = base_u = base_field = None
    for k, v in enumerate(physics_variants(boundary, sim, spec)):  # the baseline first
        t0 = time.perf_counter()
        rows = simulate_cases(cases, {gid: mesh}, v["simulate"], v["boundary"], dataset, probe=probe)
        sag = None
        if v["boundary"].get("gravity", {}).get("enabled"):
            sag = _over_sag(rows, mesh, v["boundary"], v["simulate"])
        if base_rows is None:
            base_rows = rows
        else:  # a model in surgery assumes the configured supports: its stiffness probe is the baseline's
            for r, b in zip(rows, base_rows):
                r["probe_compliance_mm_per_n"] = b["probe_compliance_mm_per_n"]
        shard, manifest = physics_variant_files(shard_dir, k)
        shard.parent.mkdir(parents=True, exist_ok=True)
        dio.write_shard(rows, shard, compression=dataset["compression"],
                        extra_meta={"simulate": v["simulate"], "boundary": v["boundary"], "dataset": dataset,
                                    "probe": probe, "physics_variant": v["name"]})
        make_manifest([str(shard)], manifest)
        ok = [r for r in rows if r["converged"]]
        entry = {"name": v["name"], "what": v["what"], "converged": len(ok), "wall_time_s": 0.0,
                 "sag_max_mm": sag, "models": {}}
        if ok:
            arrays = camera_arrays(manifest, [str(mesh_path)], "physics study")
            u = tool_displacement_mm(arrays)
            ids = [str(c) for c in arrays["case_id"]]
            field = {c: np.asarray(d, float).reshape(-1, 3) - np.asarray(e, float).reshape(-1, 3)
                     for c, d, e in zip(ids, arrays["roi_deformed_mm"], arrays["roi_undeformed_mm"])}
            if base_u is None:
                base_u, base_field = dict(zip(ids, u)), field
            both = [c for c in ids if c in base_u and base_u[c] > 1e-6]
            entry["u_tool_mm_median"] = float(np.median(u))
            if both:
                ratio = np.array([u[ids.index(c)] / base_u[c] for c in both])
                change = np.array([np.linalg.norm(field[c] - base_field[c]) / np.linalg.norm(base_field[c])
                                   for c in both])
                entry["u_tool_ratio_median"] = float(np.median(ratio))
                entry["u_tool_ratio_range"] = [float(ratio.min()), float(ratio.max())]
                entry["roi_change_pct_mean"] = float(100.0 * change.mean())
                entry["roi_change_pct_max"] = float(100.0 * change.max())
            for name, m in models.items():
                pred = m.predict(arrays, observation_seed=int(m.meta.get("eval_observation_seed", 0)))
                fm = force_metrics(arrays["force_n"], pred)
                entry["models"][name] = {"mae_vec": fm["mae_vec"], "accuracy_pct": fm["accuracy_pct"]}
        entry["wall_time_s"] = time.perf_counter() - t0
        out["variants"].append(entry)
        log.info("physics %s: %d/%d converged, u under the tool x%.2f of the baseline, ROI field changed %.0f %% (mean), "
                 "%s (%.0f s)", v["name"], len(ok), len(rows), entry.get("u_tool_ratio_median", float("nan")),
                 entry.get("roi_change_pct_mean", float("nan")),
                 ", ".join(f"{n} MAE {e['mae_vec']:.3f} N" for n, e in entry["models"].items()), entry["wall_time_s"])
    write_json_atomic(out_path, out)
    return out


def load(path) -> dict | None:
    """The physics study's JSON, or None when the file is absent (the stage is off)."""
    p = Path(path)
    return json.loads(p.read_text()) if p.exists() else None


