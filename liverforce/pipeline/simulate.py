"""Simulate stage adapter: FE solves of a shard's cases (in memory, then one atomic Parquet shard), the manifest."""

from __future__ import annotations

import json
import logging
import time
from dataclasses import replace

import numpy as np

from liverforce.atomic import write_json_atomic
from liverforce.dataset import io as dio
from liverforce.layout import features_of_mesh, gid_of, progress_of_shard

log = logging.getLogger("liverforce")


def boundary_params(mesh, cfg: dict):
    """Per-area spring stiffness (N/mm³) from the study's total stiffness (N/mm) per region.

    Interpretation (stated in config/boundary): the study's foundation
    stiffness is the region's total stiffness spread uniformly over its
    reference area, ``k = K_total / A``; tangential = ratio × normal.
    ``rib_contact`` (bilateral | unilateral) and ``gravity`` (body force
    ``rho g`` in N/mm³ = kg/m³ × m/s² × 1e-9) as in config/boundary/study.yaml.
    A slice recorded before those two keys existed (a model bundle's probe
    settings) has neither: it meant a bilateral rib and no gravity.
    """
    from liverforce.fem.boundary import gravity_body_force
    from liverforce.fem.problem import BoundaryParams

    legacy = "rib_contact" not in cfg and "gravity" not in cfg
    grav = None if legacy else cfg["gravity"]
    body = (gravity_body_force(grav["density_kg_per_m3"], grav["direction"]) if grav and grav["enabled"]
            else (0.0, 0.0, 0.0))
    return BoundaryParams.from_totals(
        mesh.points, mesh.facets, mesh.facet_region,
        ligament_total_n_per_mm=cfg["ligament_total_n_per_mm"],
        visceral_total_n_per_mm=cfg["visceral_total_n_per_mm"],
        tangential_ratio=cfg["tangential_ratio"], rib_kn=cfg["rib_normal_n_per_mm3"],
        rib_contact="bilateral" if legacy else cfg["rib_contact"], body_force_n_per_mm3=body,
    )


def solver_options(sim: dict):
    """The FE solver's options from the ``simulate`` config slice.

    A case's deterministic budget is ``max_total_iter`` Newton iterations; ``time_limit_s`` is a
    wall-time safety net far above it. Settings written before ``max_total_iter`` was a config key
    (older shards' and bundles' metadata) get the solver's default, which they ran with.
    """
    from liverforce.fem.problem import SolverOptions

    return SolverOptions(
        formulation=sim["formulation"], tol=sim["tol"], max_iter=sim["max_iter"],
        max_total_iter=sim.get("max_total_iter", SolverOptions.max_total_iter),
        initial_step=sim["initial_step"], min_step=sim["min_step"], max_steps=sim["max_steps"],
        time_limit_s=sim["time_limit_s"], modified_newton=sim["modified_newton"],
        linear_solver=sim["linear_solver"],
    )


def probe_reference(material_cfg: dict) -> dict:
    """The stiffness probe's reference material: the ``material`` config at its nominal constants.

    The probe (:mod:`liverforce.fem.probe`) measures what the liver's shape and
    supports do to the force-displacement map; one material for every case keeps
    it a property of the liver alone (the case's own constants enter the state
    vector separately). Returns ``{"model", "params_mpa" (name -> MPa), "bulk_mpa"}``.
    """
    from liverforce.fem.materials import make_material

    params = {str(k): float(v) for k, v in material_cfg["params_mpa"].items()}
    return {"model": str(material_cfg["model"]), "params_mpa": params,
            "bulk_mpa": float(make_material(material_cfg["model"], params, nu=material_cfg["nu"]).bulk)}


def probe_compliances(fe, surf, points: dict, reference: dict, tool_radius_mm: float) -> dict:
    """Compliance (3 x 3, mm/N, local frame at each point) of one liver model at ``points`` (key -> point).

    One factorisation of the rest tangent for ``reference`` (:func:`probe_reference`),
    three back-solves per point. A point that cannot be probed gets NaN and a
    logged reason (the training stage names such cases).
    """
    from liverforce.dataset.roi import local_frame
    from liverforce.fem.materials import make_material
    from liverforce.fem.probe import ComplianceProbe

    mat = make_material(reference["model"], reference["params_mpa"], bulk_mpa=reference["bulk_mpa"])
    out = {k: np.full((3, 3), np.nan) for k in points}
    try:
        probe = ComplianceProbe(fe, material=mat)
    except Exception as exc:  # recorded as NaN compliance; training refuses such rows by name
        log.error("stiffness probe failed for this liver (%s: %s); its cases get a NaN compliance",
                  type(exc).__name__, exc)
        return out
    for key, point in points.items():
        point = np.asarray(point, dtype=float)
        C = probe.compliance(point, local_frame(surf, point, tool_radius_mm), tool_radius_mm)
        out[key] = 0.5 * (C + C.T)  # symmetric by reciprocity; remove round-off asymmetry
    return out


def simulate_cases(cases: list[dict], meshes: dict, sim: dict, boundary: dict, dataset: dict,
                   progress=None, supports: dict | None = None, probe: dict | None = None,
                   stretch_range=None) -> list[dict]:
    """Simulate cases in memory: one shard row per case, in the order given.

    Parameters
    ----------
    cases : the case-table rows (``liverforce.sweep.design.build_cases``), already in chain order.
    meshes : geometry id -> :class:`liverforce.mesh.types.LiverMesh` (every ``geometry_id`` of ``cases``).
    sim, boundary, dataset : the ``simulate``, ``boundary`` and ``dataset`` config slices.
    supports : optional geometry id -> a liver's own foundation stiffness (``support_boundary`` of its
        features JSON: user-given supports, :mod:`liverforce.mesh.supports`), in place of the config's.
    progress : optional callable ``progress(n_done, total, rows, result)`` after every case
        (``result``: the case's :class:`liverforce.fem.problem.CaseResult`, or None when the solve raised).
    probe : the stiffness probe's reference material (:func:`probe_reference`); None: each
        liver's first case's material (for tests and benchmarks; the pipeline passes the config's).
    stretch_range : the Drucker-checked stretch range ``(lo, hi)`` (``material.stability_stretch``);
        a case whose principal stretches leave it is logged as a warning. None: no check.

    Returns
    -------
    list of dict
        Shard rows (:mod:`liverforce.dataset.schema`); each row's ``wall_time_s`` is the solve time.

    Notes
    -----
    One FE model per geometry is built on first use and kept. Each case starts
    from the nearest of the last 8 converged solutions of its geometry
    (``sim["warm_start"]``; rest when rest is nearer). When a geometry's model
    is built, the pre-operative stiffness probe runs at each of its exertion
    points in ``cases`` (:func:`probe_compliances`). ``sim["tool_model"]``: "traction" (the
    Gaussian traction of width ``tool_radius_mm``, :meth:`LiverModel.solve`) or "sphere" (a rigid
    frictionless sphere of radius ``tool_tip_radius_mm`` pushed to the case's force magnitude or,
    with ``tool_control: vector``, positioned to exert its force vector, :func:`_solve_sphere`; the
    row's ``force_n`` is then the force the sphere actually exerts on the liver). With
    ``boundary["gravity"]["enabled"]`` the row's displacements are the tool's increment over the
    gravity-only state of the same constants (:func:`_sag`). A case that fails (no
    convergence, its budget of Newton iterations, the wall-time safety net, solver error)
    becomes a row with ``converged = False`` and its reason; it never stops the loop. This is the loop the
    simulate rule runs and ``benchmarks/bench_fem.py`` measures.
    """
    from liverforce.dataset.roi import surface_graph
    from liverforce.fem.continuation import WarmStartPool
    from liverforce.fem.materials import make_material
    from liverforce.fem.problem import LiverModel, ToolLoad
    from liverforce.mesh.features import compute_features

    options = solver_options(sim)
    tool_model = sim.get("tool_model", "traction")  # a slice from before the key existed meant the traction
    if tool_model not in TOOL_MODELS:
        raise ValueError(f"simulate.tool_model: unknown '{tool_model}', choose one of {', '.join(TOOL_MODELS)}")
    if tool_model == "sphere" and (boundary.get("gravity") or {}).get("enabled"):
        raise ValueError("simulate.tool_model=sphere does not support boundary.gravity.enabled=true yet")
    indenters: dict[tuple, object] = {}  # (geometry id, exertion point) -> LiverIndenter
    rows: list[dict] = []
    models: dict[str, tuple] = {}
    pools: dict[str, WarmStartPool] = {}  # recent converged solutions per geometry, for warm starts
    gravity = bool((boundary.get("gravity") or {}).get("enabled"))
    sags: dict = {}  # (geometry, constants) -> the gravity-only displacement (n_vertices, 3)
    t_start = time.perf_counter()
    for n_done, case in enumerate(cases, start=1):
        gid = case["geometry_id"]
        material = make_material(case["material_model"], dict(zip(case["material_param_names"], case["material_params_mpa"])),
                                 bulk_mpa=case["bulk_modulus_mpa"])
        if gid not in models:
            mesh = meshes[gid]
            bp = boundary_params(mesh, boundary).with_supports((supports or {}).get(gid))
            fe = LiverModel(mesh.points, mesh.tets, mesh.facets, mesh.facet_region, material, bp, options)
            surf = surface_graph(mesh.points, mesh.facets)
            points = {tuple(c["exertion_point_mm"]): c["exertion_point_mm"] for c in cases if c["geometry_id"] == gid}
            ref = probe or {"model": case["material_model"], "bulk_mpa": case["bulk_modulus_mpa"],
                            "params_mpa": dict(zip(case["material_param_names"], case["material_params_mpa"]))}
            comp = probe_compliances(fe, surf, points, ref, sim["tool_radius_mm"])
            models[gid] = (mesh, compute_features(mesh), surf, fe, comp)
            pools[gid] = WarmStartPool(size=8)
        mesh, feats, surf, fe, comp = models[gid]
        load = ToolLoad(point_mm=np.asarray(case["exertion_point_mm"]), force_N=np.asarray(case["force_n"]),
                        radius_mm=sim["tool_radius_mm"])
        start = pools[gid].nearest(load, case["material_params_mpa"]) if sim["warm_start"] else None
        t0 = time.perf_counter()
        try:
            if tool_model == "sphere":
                res = _solve_sphere(indenters, gid, fe, case, material, start, sim)
            else:
                res = fe.solve(load, material=material, u0=start)
            error = None
            if gravity and res.u_nodes is not None:
                # the pre-operative image shows the sagged liver: the row holds the tool's increment over the
                # gravity-only state of the same constants (stretches and reactions stay the total state's)
                key = (gid, tuple(case["material_params_mpa"]), case["bulk_modulus_mpa"])
                if key not in sags:
                    sags[key] = _sag(fe, load, material)
                res = replace(res, u_nodes=res.u_nodes - sags[key])
        except Exception as exc:  # a solver crash is recorded as a failed case, never fatal to the shard
            res, error = None, f"{type(exc).__name__}: {exc}"
            log.exception("case %s crashed", case["case_id"])
        wall = time.perf_counter() - t0
        rows.append(_case_row(case, res, error, wall, mesh, feats, surf, dataset, sim["tool_radius_mm"],
                              comp[tuple(case["exertion_point_mm"])]))
        if tool_model == "sphere" and res is not None and res.force_on_liver is not None:
            # the label is the force the sphere exerts on the liver (the target within tolerance if converged)
            rows[-1]["force_n"] = np.asarray(res.force_on_liver, dtype=float)
            rows[-1]["force_magnitude_n"] = float(np.linalg.norm(res.force_on_liver))
        if res is not None and res.converged:
            pools[gid].add(res, case["material_params_mpa"])
        lam_lo, lam_hi = rows[-1]["min_principal_stretch"], rows[-1]["max_principal_stretch"]
        if stretch_range is not None and (lam_lo < stretch_range[0] or lam_hi > stretch_range[1]):
            log.warning("case %s: principal stretches %.3f-%.3f leave the Drucker-checked range %g-%g "
                        "(material.stability_stretch): the material's stability is unchecked there",
                        case["case_id"], lam_lo, lam_hi, stretch_range[0], stretch_range[1])
        rate = n_done / (time.perf_counter() - t_start) * 3600
        if progress is not None:
            progress(n_done, len(cases), rows, res)
        log.info("case %s (%d/%d): %s, |F| %.2f N, max|u| %.2f mm, %d it, %.2f s — %.0f cases/h",
                 case["case_id"], n_done, len(cases), "ok" if rows[-1]["converged"] else f"FAILED ({rows[-1]['reason']})",
                 case["force_magnitude_n"], rows[-1]["max_displacement_mm"], rows[-1]["newton_iterations"], wall, rate)
    return rows


def _sag(fe, load, material) -> np.ndarray:
    """The liver's displacement under gravity alone (its supports, these constants): the sagged state."""
    from liverforce.fem.problem import ToolLoad

    res = fe.solve(ToolLoad(point_mm=load.point_mm, force_N=np.zeros(3), radius_mm=load.radius_mm), material=material)
    if not res.converged:
        raise RuntimeError(f"the gravity-only state did not converge ({res.reason}): check boundary.gravity and "
                           "the supports (a liver must be held against its weight)")
    return res.u_nodes


#: ``simulate.tool_model``: how the tool acts on the liver
TOOL_MODELS = ("traction", "sphere")


def sphere_settings(sim: dict) -> dict:
    """The force-controlled sphere's settings from the ``simulate`` slice (``tool_model: sphere``)."""
    kn = float(sim["tool_penalty_n_per_mm3"])
    return {"radius_mm": float(sim["tool_tip_radius_mm"]), "kn": kn if kn > 0 else None,
            "rtol": float(sim["tool_force_rtol"]), "atol": float(sim["tool_force_atol_n"]),
            "max_slide_mm": float(sim["tool_max_slide_mm"]), "control": str(sim.get("tool_control", "magnitude"))}


def _solve_sphere(indenters: dict, gid, fe, case, material, start, sim):
    """One sphere case: :meth:`~liverforce.fem.indenter.LiverIndenter.push_to_magnitude` (``tool_control:
    magnitude``, from first touch) or :meth:`~liverforce.fem.indenter.LiverIndenter.push_to_force` (``vector``).

    One indenter per (geometry, exertion point), built on first use (candidate facets, contact
    system). Warm start (vector control): the pool's nearest converged case, used only when it is a sphere
    case at this exertion point (its state and sphere centre); otherwise the sphere starts from first touch.
    """
    from liverforce.fem.indenter import LiverIndenter, SphereCaseResult

    st = sphere_settings(sim)
    point = np.asarray(case["exertion_point_mm"], dtype=float)
    key = (gid, tuple(point))
    if key not in indenters:
        # candidate facets: the indenter's default reach (4 R + 10 mm) plus the slide allowed
        indenters[key] = LiverIndenter(fe, point, radius_mm=st["radius_mm"], kn=st["kn"],
                                       candidate_radius_mm=4.0 * st["radius_mm"] + 10.0 + st["max_slide_mm"])
    ind = indenters[key]
    if st["control"] == "magnitude":
        return ind.push_to_magnitude(np.asarray(case["force_n"], dtype=float), material=material, options=fe.options,
                                     rtol=st["rtol"], atol=st["atol"])
    warm = start if (isinstance(start, SphereCaseResult) and np.allclose(start.load.point_mm, point)) else None
    return ind.push_to_force(np.asarray(case["force_n"], dtype=float), material=material, u0=warm,
                             options=fe.options, rtol=st["rtol"], atol=st["atol"], max_slide_mm=st["max_slide_mm"])


def simulate_shard(cases_path, mesh_paths: list[str], shard: int, sim: dict, boundary: dict, dataset: dict,
                   shard_path, material: dict | None = None) -> dict:
    """Simulate every case of one shard (:func:`simulate_cases`) and write the shard atomically.

    ``material`` is the ``material`` config slice: the stiffness probe's
    reference (:func:`probe_reference`), recorded in the shard metadata
    (``liverforce.probe``).

    Progress (cases done, failed, elapsed) is written to
    ``results/<exp>/progress/<scenario>-NNNN.json`` after every case.
    """
    from liverforce.mesh.io import read_mesh

    table = dio.read_table(cases_path)
    cases = [r for r in table.to_pylist() if r["shard_index"] == shard]
    by_gid = {gid_of(p): p for p in mesh_paths}
    meshes = {gid: read_mesh(by_gid[gid]) for gid in dict.fromkeys(c["geometry_id"] for c in cases)}
    supports = {}
    for gid in meshes:  # user-given foundation stiffness, written by the mesh stage
        feats = features_of_mesh(by_gid[gid])
        if feats.exists():
            supports[gid] = json.loads(feats.read_text()).get("support_boundary") or {}
    t_start = time.perf_counter()

    def progress(n_done, total, rows, _result):
        write_json_atomic(progress_of_shard(shard_path), {
            "done": n_done, "total": total, "failed": sum(not r["converged"] for r in rows),
            "elapsed_s": time.perf_counter() - t_start, "updated": time.time()})

    probe = probe_reference(material) if material is not None else None
    rows = simulate_cases(cases, meshes, sim, boundary, dataset, progress=progress, supports=supports, probe=probe,
                          stretch_range=material["stability_stretch"] if material is not None else None)
    entry = dio.write_shard(rows, shard_path, compression=dataset["compression"],
                            extra_meta={"simulate": sim, "boundary": boundary, "dataset": dataset, "probe": probe,
                                        "tool_model": sim.get("tool_model", "traction")})
    if rows and entry["failed"] == len(rows):
        log.warning("shard %s: every case failed (see the 'reason' column)", shard_path)
    log.info("shard %s: %d rows, %d failed", shard_path, entry["rows"], entry["failed"])
    return entry


def _case_row(case, res, error, wall, mesh, feats, surf, dataset, tool_radius_mm, compliance) -> dict:
    from liverforce.dataset.roi import extract_roi, local_frame, roi_triangles, thickness_along_normal

    point = np.asarray(case["exertion_point_mm"])
    frame = local_frame(surf, point, tool_radius_mm)
    ids_local, achieved = extract_roi(surf, point, dataset["roi_fraction"])
    node_ids = surf.node_ids[ids_local]
    und = mesh.points[node_ids]
    converged = bool(res is not None and res.converged)
    if res is not None and res.u_nodes is not None and np.all(np.isfinite(res.u_nodes)):
        u = res.u_nodes
    else:
        u = np.zeros_like(mesh.points)
    de = und + u[node_ids]
    surf_u = u[surf.node_ids] if dataset["store_full_surface"] else np.zeros((0, 3))
    row = {k: case[k] for k in (
        "case_id", "scenario", "geometry_id", "shard_index", "seed", "material_model", "material_param_names",
        "material_params_mpa", "bulk_modulus_mpa", "exertion_id", "exertion_point_mm", "force_n", "force_magnitude_n")}
    row.update(
        frame_t1=frame[0], frame_t2=frame[1], frame_normal=frame[2],
        liver_centroid_mm=np.asarray(feats["centroid_mm"], dtype=float),
        inertia_mm5=np.asarray(feats["inertia_mm5"], dtype=float).reshape(9),
        tool_thickness_mm=thickness_along_normal(mesh.points, mesh.facets, point, frame[2]),
        probe_compliance_mm_per_n=np.asarray(compliance, dtype=float).reshape(9),
        roi_fraction=float(dataset["roi_fraction"]), roi_area_fraction=achieved,
        roi_node_ids=node_ids.astype(np.int32), roi_triangles=roi_triangles(mesh.facets, node_ids).astype(np.int32),
        roi_undeformed_mm=und.astype(np.float32),
        roi_deformed_mm=de.astype(np.float32),
        roi_centroid_undeformed_mm=und.mean(axis=0), roi_centroid_deformed_mm=de.mean(axis=0),
        surface_displacement_mm=surf_u.astype(np.float32),
        max_displacement_mm=float(np.linalg.norm(u, axis=1).max()),
        max_principal_stretch=float(res.max_principal_stretch) if res is not None else float("nan"),
        min_principal_stretch=float(res.min_principal_stretch) if res is not None else float("nan"),
        converged=converged,
        reason="" if converged else (error or (res.reason if res is not None else "unknown")),
        load_fraction=float(res.load_fraction) if res is not None else 0.0,
        load_steps=int(res.load_steps) if res is not None else 0,
        newton_iterations=int(res.newton_iterations) if res is not None else 0,
        final_residual=float(res.final_residual) if res is not None else float("nan"),
        linear_solver=str(res.linear_solver) if res is not None else "",
        wall_time_s=float(wall),
    )
    return row


def make_manifest(shard_paths: list[str], manifest_path) -> dict:
    """Manifest of a scenario's shards; prints the failure rate."""
    m = dio.write_manifest(shard_paths, manifest_path)
    log.info("%s: %d shards, %d rows, %d failed (failure rate %.1f %%)", manifest_path, len(m["shards"]), m["rows"],
             m["failed"], 100 * m["failure_rate"])
    return m


