"""Stage adapters: read a job's input files, call the package, write its outputs.

Each function takes plain values (the rule's ``params:`` slice and paths) and
is what a workflow script calls; the math lives in the stage packages. Every
output is written atomically (temporary name, then rename).
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np

from liverforce.dataset import io as dio

log = logging.getLogger("liverforce")


# ----------------------------------------------------------------- geometry


def make_geometry(spec: dict, surface_path: str | Path, meta_path: str | Path) -> dict:
    """Build one closed liver surface (procedural, cube or imported) and save it as PLY + JSON."""
    from liverforce.geometry.procedural import LiverShapeParams, cube_phantom, procedural_liver

    kind = spec["kind"]
    messages: list[str] = []
    if kind == "procedural":
        surface = procedural_liver(int(spec["seed"]), LiverShapeParams(**spec.get("shape", {})))
    elif kind == "cube":
        surface = cube_phantom(float(spec["edge_mm"]))
    elif kind == "imported":
        from liverforce.geometry.importers import load_surface

        units = spec.get("units", "mm")
        try:
            units = float(units)
        except (TypeError, ValueError):
            pass
        surface, messages = load_surface(spec["path"], units=units, label=spec.get("label"))
    else:
        raise ValueError(f"unknown geometry kind '{kind}'")
    for m in messages:
        log.info("repair: %s", m)
    save_surface(surface, surface_path)
    meta = {**surface.meta, "spec": spec, "repairs": messages,
            "volume_mm3": surface.volume_mm3, "area_mm2": surface.area_mm2,
            "extent_mm": surface.extent_mm.tolist()}
    dio.write_json_atomic(meta, meta_path)
    log.info("geometry %s: %d vertices, %.0f mL, extent %s mm", spec, len(surface.vertices),
             surface.volume_mm3 / 1000, np.round(surface.extent_mm, 1).tolist())
    return meta


def save_surface(surface, path: str | Path) -> None:
    import meshio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    meshio.write(tmp, meshio.Mesh(surface.vertices, [("triangle", surface.faces)]), binary=True)
    tmp.replace(path)


def load_surface_file(path: str | Path):
    import meshio

    from liverforce.geometry.surface import Surface

    m = meshio.read(path)
    return Surface(m.points.astype(np.float64), m.get_cells_type("triangle").astype(np.int64), {"source": str(path)})


# --------------------------------------------------------------------- mesh


def exertion_seed(seed: int, gid: str) -> int:
    """Seed of a geometry's candidate exertion points: the config seed and the geometry id."""
    import zlib

    return int(np.random.SeedSequence([int(seed), zlib.crc32(gid.encode())]).generate_state(1)[0])


def make_mesh(surface_path, mesh_cfg: dict, seed: int, mesh_path, features_path, picture_path,
              exertion: dict | None = None) -> dict:
    """Tetrahedralise a surface, tag regions, compute features, draw the regions.

    ``exertion`` (the ``sweep.exertion`` config: ``n_points``, ``min_spacing_mm``):
    the geometry's candidate exertion points are sampled on the visible input
    surface here, refined around (``mesh.refine_radius_mm`` / ``refine_edge_mm``),
    and written to the features JSON, from which every scenario's sweep takes them.
    """
    from liverforce.mesh.build import build_liver_mesh
    from liverforce.mesh.features import compute_features
    from liverforce.mesh.io import write_mesh
    from liverforce.mesh.plot import plot_regions
    from liverforce.mesh.regions import RegionParams

    surface = load_surface_file(surface_path)
    meta_file = Path(surface_path).with_suffix(".json")
    if meta_file.exists():
        surface.meta.update(json.loads(meta_file.read_text()))
    t0 = time.perf_counter()
    mesh = build_liver_mesh(
        surface,
        target_nodes=mesh_cfg["target_nodes"],
        region_params=RegionParams(**mesh_cfg.get("regions", {})),
        mesher=mesh_cfg["mesher"],
        seed=seed,
        refine_radius_mm=mesh_cfg.get("refine_radius_mm", 0.0),
        refine_edge_mm=mesh_cfg.get("refine_edge_mm"),
        refine_ivc_edge_mm=mesh_cfg.get("refine_ivc_edge_mm"),
        refine_growth=mesh_cfg.get("refine_growth", 0.3),
        exertion_sampling=None if exertion is None else {
            "n_points": exertion["n_points"], "min_spacing_mm": exertion["min_spacing_mm"],
            "seed": exertion_seed(seed, Path(mesh_path).stem)},
    )
    elapsed = time.perf_counter() - t0
    write_mesh(mesh_path, mesh)
    feats = compute_features(mesh)
    feats["meshing_time_s"] = elapsed
    feats["exertion_candidates_mm"] = mesh.meta.get("exertion_candidates_mm")
    feats["refine_points"] = mesh.meta.get("refine_points")
    feats["regions_tagged_on"] = mesh.meta.get("regions_tagged_on")
    dio.write_json_atomic(feats, features_path)
    plot_regions(mesh, picture_path)
    log.info("mesh: %d nodes, %d tets in %.1f s", len(mesh.points), len(mesh.tets), elapsed)
    return feats


# -------------------------------------------------------------------- sweep


def material_checks(stretch_range):
    """(stability_check, bulk_modulus) callables for :func:`liverforce.sweep.design.build_cases`."""
    from liverforce.fem.materials import make_material
    from liverforce.fem.stability import check_stability

    def stable(model, params):
        try:
            mat = make_material(model, params, nu=0.45)
        except ValueError as exc:
            return False, str(exc)
        rep = check_stability(mat, stretch_range=tuple(stretch_range))
        return bool(rep.stable), rep.message

    def bulk(model, params, nu):
        return make_material(model, params, nu=nu).bulk

    return stable, bulk


def exertion_set(mesh, n_points: int, min_spacing_mm: float, seed: int, frame_radius_mm: float,
                 candidates=None):
    """Candidate exertion points of one mesh with their normals and local frames.

    ``candidates`` : points chosen at the mesh stage (on the input surface, where
    the mesh is refined), moved onto the nearest visible mesh facet; else
    ``n_points`` are sampled on the mesh's visible facets with ``seed``.
    """
    from liverforce.dataset.roi import local_frame, surface_graph
    from liverforce.sweep.design import ExertionSet, SweepError, sample_exertion_points

    if candidates is not None:
        cand = np.asarray(candidates, float).reshape(-1, 3)
        if len(cand) < n_points:
            raise SweepError(f"the mesh carries {len(cand)} exertion candidates, the sweep asks {n_points}: "
                             "re-run the mesh stage with this sweep.exertion config")
        pts = closest_surface_points(mesh.points, mesh.facets[mesh.facet_visible], cand[:n_points])
    else:
        pts = sample_exertion_points(mesh.points, mesh.facets, mesh.facet_visible, n_points, min_spacing_mm, seed)
    surf = surface_graph(mesh.points, mesh.facets)
    frames = np.stack([local_frame(surf, p, frame_radius_mm) for p in pts])
    return ExertionSet(points=pts, normals=frames[:, 2], frames=frames)


def closest_surface_points(points, facets, query, k: int = 16) -> np.ndarray:
    """The closest point on the triangles ``points[facets]`` to each query point (mm).

    Searched over the ``k`` triangles with the nearest centroids (query points
    lie on or near the surface).
    """
    from scipy.spatial import cKDTree
    from trimesh.triangles import closest_point

    tri = np.asarray(points, float)[np.asarray(facets)]
    query = np.atleast_2d(np.asarray(query, float))
    k = min(k, len(tri))
    _, near = cKDTree(tri.mean(axis=1)).query(query, k=k)
    near = near.reshape(len(query), k)
    cp = closest_point(tri[near.ravel()], np.repeat(query, k, axis=0)).reshape(len(query), k, 3)
    best = np.argmin(np.linalg.norm(cp - query[:, None], axis=2), axis=1)
    return cp[np.arange(len(query)), best]


def make_sweep(params: dict, mesh_paths: list[str], cases_path, report_path) -> dict:
    """Build and write the case table of one scenario (refusing unstable materials first)."""
    from liverforce.mesh.io import read_mesh
    from liverforce.sweep.design import build_cases

    gids = params["geometries"]
    by_gid = {Path(p).stem: p for p in mesh_paths}
    stable, bulk = material_checks(params["material"]["stability_stretch"])
    ex = {}
    for i, gid in enumerate(gids):
        mesh = read_mesh(by_gid[gid])
        feats = Path(by_gid[gid]).with_suffix(".features.json")
        cand = json.loads(feats.read_text()).get("exertion_candidates_mm") if feats.exists() else None
        ex[gid] = exertion_set(mesh, params["exertion"]["n_points"], params["exertion"]["min_spacing_mm"],
                               params["seed"] * 7919 + i, params["tool_radius_mm"], candidates=cand)
    result = build_cases(
        scenario=params["scenario"], spec=params["spec"], geometry_ids=gids, exertion=ex,
        material=params["material"], force=params["force"], design=params["design"], seed=params["seed"],
        cases_per_shard=params["cases_per_shard"], stability_check=stable, bulk_modulus=bulk,
    )
    dio.write_case_table(result.rows, cases_path, extra_meta={"sweep": params})
    report = {
        "scenario": params["scenario"],
        "cases": len(result.rows),
        "dropped_unstable": result.dropped_unstable,
        "exertion_points_mm": {g: e.points.tolist() for g, e in ex.items()},
    }
    dio.write_json_atomic(report, report_path)
    if result.dropped_unstable:
        log.warning("scenario %s: %d sampled material sets were not Drucker-stable and were dropped",
                    params["scenario"], len(result.dropped_unstable))
    log.info("scenario %s: %d cases on %s", params["scenario"], len(result.rows), gids)
    return report


# ----------------------------------------------------------------- simulate


def boundary_params(mesh, cfg: dict):
    """Per-area spring stiffness (N/mm³) from the study's total stiffness (N/mm) per region.

    Interpretation (stated in config/boundary): the study's foundation
    stiffness is the region's total stiffness spread uniformly over its
    reference area, ``k = K_total / A``; tangential = ratio × normal.
    """
    from liverforce.fem.problem import BoundaryParams

    return BoundaryParams.from_totals(
        mesh.points, mesh.facets, mesh.facet_region,
        ligament_total_n_per_mm=cfg["ligament_total_n_per_mm"],
        visceral_total_n_per_mm=cfg["visceral_total_n_per_mm"],
        tangential_ratio=cfg["tangential_ratio"], rib_kn=cfg["rib_normal_n_per_mm3"],
    )


def solver_options(sim: dict):
    from liverforce.fem.problem import SolverOptions

    return SolverOptions(
        formulation=sim["formulation"], tol=sim["tol"], max_iter=sim["max_iter"],
        initial_step=sim["initial_step"], min_step=sim["min_step"], max_steps=sim["max_steps"],
        time_limit_s=sim["time_limit_s"], modified_newton=sim["modified_newton"],
        linear_solver=sim["linear_solver"],
    )


def _progress_path(shard_path) -> Path:
    shard_path = Path(shard_path)
    # results/<exp>/shards/<scenario>/shard-NNNN.parquet -> results/<exp>/progress/<scenario>-NNNN.json
    return shard_path.parent.parent.parent / "progress" / f"{shard_path.parent.name}-{shard_path.stem.split('-')[-1]}.json"


def simulate_shard(cases_path, mesh_paths: list[str], shard: int, sim: dict, boundary: dict, dataset: dict,
                   shard_path) -> dict:
    """Simulate every case of one shard and write the shard atomically.

    A case that fails (no convergence, time limit, solver error) becomes a row
    with ``converged = False`` and its reason; it never stops the shard.
    """
    from liverforce.dataset.roi import extract_roi, surface_graph
    from liverforce.fem.continuation import WarmStartPool
    from liverforce.fem.materials import make_material
    from liverforce.fem.problem import LiverModel, ToolLoad
    from liverforce.mesh.features import compute_features
    from liverforce.mesh.io import read_mesh

    table = dio.read_table(cases_path)
    cases = [r for r in table.to_pylist() if r["shard_index"] == shard]
    by_gid = {Path(p).stem: p for p in mesh_paths}
    options = solver_options(sim)
    rows: list[dict] = []
    models: dict[str, tuple] = {}
    pools: dict[str, WarmStartPool] = {}  # recent converged solutions per geometry, for warm starts
    t_start = time.perf_counter()
    for n_done, case in enumerate(cases, start=1):
        gid = case["geometry_id"]
        if gid not in models:
            mesh = read_mesh(by_gid[gid])
            feats = compute_features(mesh)
            surf = surface_graph(mesh.points, mesh.facets)
            first_mat = make_material(case["material_model"], dict(zip(case["material_param_names"], case["material_params_mpa"])),
                                      bulk_mpa=case["bulk_modulus_mpa"])
            fe = LiverModel(mesh.points, mesh.tets, mesh.facets, mesh.facet_region, first_mat,
                            boundary_params(mesh, boundary), options)
            models[gid] = (mesh, feats, surf, fe)
            pools[gid] = WarmStartPool(size=8)
        mesh, feats, surf, fe = models[gid]
        material = make_material(case["material_model"], dict(zip(case["material_param_names"], case["material_params_mpa"])),
                                 bulk_mpa=case["bulk_modulus_mpa"])
        load = ToolLoad(point_mm=np.asarray(case["exertion_point_mm"]), force_N=np.asarray(case["force_n"]),
                        radius_mm=sim["tool_radius_mm"])
        start = pools[gid].nearest(load, case["material_params_mpa"]) if sim["warm_start"] else None
        t0 = time.perf_counter()
        try:
            res = fe.solve(load, material=material, u0=start)
            error = None
        except Exception as exc:  # a solver crash is recorded as a failed case, never fatal to the shard
            res, error = None, f"{type(exc).__name__}: {exc}"
            log.exception("case %s crashed", case["case_id"])
        wall = time.perf_counter() - t0
        rows.append(_case_row(case, res, error, wall, mesh, feats, surf, dataset, sim["tool_radius_mm"], extract_roi))
        if res is not None and res.converged:
            pools[gid].add(res, case["material_params_mpa"])
        rate = n_done / (time.perf_counter() - t_start) * 3600
        dio.write_json_atomic({"done": n_done, "total": len(cases), "failed": sum(not r["converged"] for r in rows),
                               "elapsed_s": time.perf_counter() - t_start, "updated": time.time()},
                              _progress_path(shard_path))
        log.info("case %s (%d/%d): %s, |F| %.2f N, max|u| %.2f mm, %d it, %.2f s — %.0f cases/h",
                 case["case_id"], n_done, len(cases), "ok" if rows[-1]["converged"] else f"FAILED ({rows[-1]['reason']})",
                 case["force_magnitude_n"], rows[-1]["max_displacement_mm"], rows[-1]["newton_iterations"], wall, rate)
    entry = dio.write_shard(rows, shard_path, compression=dataset["compression"],
                            extra_meta={"simulate": sim, "boundary": boundary, "dataset": dataset})
    if rows and entry["failed"] == len(rows):
        log.warning("shard %s: every case failed (see the 'reason' column)", shard_path)
    log.info("shard %s: %d rows, %d failed", shard_path, entry["rows"], entry["failed"])
    return entry


def _case_row(case, res, error, wall, mesh, feats, surf, dataset, tool_radius_mm, extract_roi) -> dict:
    from liverforce.dataset.roi import local_frame

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
        roi_fraction=float(dataset["roi_fraction"]), roi_area_fraction=achieved,
        roi_node_ids=node_ids.astype(np.int32), roi_undeformed_mm=und.astype(np.float32),
        roi_deformed_mm=de.astype(np.float32),
        roi_centroid_undeformed_mm=und.mean(axis=0), roi_centroid_deformed_mm=de.mean(axis=0),
        surface_displacement_mm=surf_u.astype(np.float32),
        max_displacement_mm=float(np.linalg.norm(u, axis=1).max()),
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


# -------------------------------------------------------------------- train


def train_model(manifest_path, scenario: str, variant: str, model_cfg: dict, train_cfg: dict, tune_cfg: dict,
                tracking_uri: str, experiment_prefix: str, experiment: str, seed: int, threads: int,
                metrics_path, model_dir, mesh_paths: list[str] | None = None) -> dict:
    """Train one scenario/variant from verified shards; track it in MLflow.

    Every shard is checked against the manifest's hash before it is read: a
    truncated or modified shard stops training with its name (delete it and
    re-run to rebuild it). With ``model_cfg["roi_fraction"]`` set, the ROI is
    re-grown at that area fraction from the stored full-surface displacements
    (``mesh_paths``: the scenario's meshes) and the model is trained and saved
    for that fraction.
    """
    from liverforce.config import config_hash
    from liverforce.learn.train import train_scenario
    from liverforce.tracking import Tracker

    shards = dio.verify_manifest(manifest_path)
    manifest = json.loads(Path(manifest_path).read_text())
    shard_meta = dio.read_metadata(shards[0])
    roi_fraction = float(shard_meta["dataset"]["roi_fraction"])
    wanted = model_cfg.get("roi_fraction")
    if wanted is not None and abs(float(wanted) - roi_fraction) > 1e-12:
        from liverforce.learn.representation import with_roi_fraction

        if not mesh_paths:
            raise ValueError(f"variant {variant}: model.roi_fraction={wanted} needs the scenario's meshes")
        arrays = with_roi_fraction(load_study_arrays(manifest_path, full_surface=True), float(wanted),
                                   surface_graphs(mesh_paths))
        arrays.pop("surface_displacement_mm", None)
        log.info("scenario %s / %s: ROI re-grown at %.3f of the surface (shards: %.3f; achieved mean %.3f)",
                 scenario, variant, float(wanted), roi_fraction, float(np.mean(arrays["roi_area_fraction"])))
        roi_fraction = float(wanted)
    else:
        arrays = dio.load_training_arrays(shards)
    n = len(arrays["case_id"])
    log.info("scenario %s / %s: %d converged cases from %d shards (data version %s)", scenario, variant, n,
             len(shards), manifest["data_version"])
    if n < 10:
        raise RuntimeError(
            f"scenario {scenario}: only {n} converged cases in {manifest_path}; too few to train "
            f"({manifest['failed']} failed — see the 'reason' column); raise sweep.scenarios.{scenario}.n_cases"
        )
    out_dir = Path(metrics_path).parent
    tracker = Tracker(tracking_uri, f"{experiment_prefix}-{experiment}-{scenario}")
    tags = {
        "rule": "train", "scenario": scenario, "variant": variant, "experiment": experiment,
        "config_hash": config_hash({"model": model_cfg, "train": train_cfg, "tune": tune_cfg}),
        "data_version": manifest["data_version"],
    }
    model_meta = {
        "roi_fraction": roi_fraction,
        "frame_radius_mm": float(shard_meta["simulate"]["tool_radius_mm"]),
        "data_version": manifest["data_version"],
    }
    result = train_scenario(arrays, model_cfg, train_cfg, tune_cfg, scenario, variant, tracker=tracker,
                            threads=threads, seed=seed + train_cfg["seed"], out_dir=out_dir, tags=tags,
                            model_meta=model_meta)
    result.update(encoder=model_cfg["encoder"], state_vector=bool(model_cfg["state_vector"]), model_cfg=model_cfg)
    dio.write_json_atomic(result, metrics_path)
    log.info("scenario %s / %s: test %s", scenario, variant,
             {k: round(v, 4) for k, v in result.get("metrics", {}).items() if isinstance(v, float)})
    return result


# ----------------------------------------------------------------- validate


def choose_variant(metrics_paths: list, how: str = "auto") -> tuple[int, str]:
    """Index of the scenario-IV model to validate, and why.

    ``main``: the first listed (the main variant). ``auto``: the lowest Ax
    cross-validation MSE (folds by liver, training split only: neither the IV
    test liver nor the unseen liver informs the choice); the first listed when
    no variant was tuned. Else the variant of that name.
    """
    docs = [json.loads(Path(p).read_text()) for p in metrics_paths]
    names = [d.get("variant") or Path(p).parent.name for d, p in zip(docs, metrics_paths)]
    if how == "main":
        return 0, "validate.variant=main (the first of train.variants)"
    if how != "auto":
        if how not in names:
            raise ValueError(f"validate.variant '{how}' is not among the trained scenario-IV variants {names}")
        return names.index(how), f"validate.variant={how}"
    cv = [d.get("cv_mse") for d in docs]
    if any(c is None for c in cv):
        return 0, "first listed variant (not every variant was tuned, no CV score to compare)"
    best = int(np.argmin(cv))
    return best, ("lowest cross-validation MSE on the training livers: "
                  + ", ".join(f"{n} {c:.4f}" for n, c in zip(names, cv)))


def validate_model(model_dir, model_metrics_path, manifest_path, train_manifest_path, tracking_uri, out_path,
                   experiment_name: str = "liverforce-validation", variant: str = "auto") -> dict:
    """Predict the unseen liver's cases with the chosen scenario-IV model.

    ``model_dir`` / ``model_metrics_path`` may be lists (every scenario-IV
    variant): :func:`choose_variant` picks one by ``variant``.

    Reports MAE / RMSE (N), accuracy %, and the error against force magnitude
    and against the distance of the exertion point from the nearest training
    exertion point (in the local frame sense: both livers are centred on their
    centroids, since they are different shapes).
    """
    from liverforce.learn.metrics import force_metrics
    from liverforce.learn.model import ForceModel
    from liverforce.tracking import Tracker

    def predict(d):
        m = ForceModel.load(Path(d))
        return m.predict(arrays, observation_seed=int(m.meta.get("eval_observation_seed", 0)))

    choice = "the only model given"
    others = {}
    arrays = dio.load_training_arrays(dio.verify_manifest(manifest_path))
    n = len(arrays["case_id"])
    if n == 0:
        raise RuntimeError(f"{manifest_path}: no converged validation case to evaluate")
    if isinstance(model_metrics_path, (list, tuple)):
        k, choice = choose_variant(list(model_metrics_path), variant)
        preds = [predict(d) for d in model_dir]  # every candidate on the unseen liver, for the report
        for p, mp in zip(preds, model_metrics_path):
            others[Path(mp).parent.name] = {"metrics": force_metrics(arrays["force_n"], p),
                                            "model_run_id": json.loads(Path(mp).read_text()).get("run_id")}
        model_dir, model_metrics_path, pred = list(model_dir)[k], list(model_metrics_path)[k], preds[k]
    else:
        pred = predict(model_dir)
    log.info("validated %s (%s)", model_dir, choice)
    train = dio.load_training_arrays(dio.verify_manifest(train_manifest_path))
    true = arrays["force_n"]
    metrics = force_metrics(true, pred)
    err = np.linalg.norm(pred - true, axis=1)
    mag = np.linalg.norm(true, axis=1)
    rel_v = arrays["exertion_point_mm"] - arrays["liver_centroid_mm"]
    rel_t = train["exertion_point_mm"] - train["liver_centroid_mm"]
    dist = np.min(np.linalg.norm(rel_v[:, None, :] - rel_t[None, :, :], axis=2), axis=1)
    bins = np.linspace(0.0, max(mag.max(), 1e-9), 6)
    by_mag = []
    for lo, hi in zip(bins[:-1], bins[1:]):
        sel = (mag >= lo) & (mag <= hi)
        if sel.any():
            by_mag.append({"force_lo_n": float(lo), "force_hi_n": float(hi), "n": int(sel.sum()),
                           "mae_vec_n": float(err[sel].mean())})
    model_metrics = json.loads(Path(model_metrics_path).read_text())
    result = {
        "n_cases": n,
        "metrics": metrics,
        "error_by_force_magnitude": by_mag,
        "error_vs_distance": {"distance_mm": dist.tolist(), "error_n": err.tolist()},
        "corr_error_distance": float(np.corrcoef(dist, err)[0, 1]) if n > 2 and dist.std() > 0 else float("nan"),
        "model_run_id": model_metrics.get("run_id"),
        "model_variant": model_metrics.get("variant") or Path(model_metrics_path).parent.name,
        "variant_choice": choice,
        "all_variants": others,
        "predictions": {"case_id": [str(c) for c in arrays["case_id"]], "true_n": true.tolist(), "pred_n": pred.tolist()},
    }
    out_dir = Path(out_path).parent
    out_dir.mkdir(parents=True, exist_ok=True)
    from liverforce.learn.plots import evaluation_figures

    figures = evaluation_figures(true, pred, out_dir / "figures", title="unseen liver")
    result["figures"] = [str(Path(f).relative_to(out_dir)) for f in figures]
    tracker = Tracker(tracking_uri, experiment_name)
    run_id = tracker.start_run("validation", params={"model_run_id": str(result["model_run_id"]), "n_cases": n,
                                                     "model_variant": result["model_variant"]},
                               tags={"rule": "validate", "model_run_id": str(result["model_run_id"])})
    tracker.log_metrics(run_id, metrics)
    for f in figures:
        tracker.log_artifact(run_id, f)
    tracker.end_run(run_id)
    result["run_id"] = run_id
    dio.write_json_atomic(result, out_path)
    log.info("validation on the unseen liver: MAE %.3f N, RMSE %.3f N, accuracy %.1f %% (%d cases)",
             metrics["mae_vec"], metrics["rmse_vec"], metrics["accuracy_pct"], n)
    return result


# -------------------------------------------------------------------- study


def surface_graphs(mesh_paths) -> dict:
    """Geometry id (mesh file stem) -> surface graph of its mesh, as the simulation built it (ROI re-growing)."""
    from liverforce.dataset.roi import surface_graph
    from liverforce.mesh.io import read_mesh

    out = {}
    for p in mesh_paths:
        mesh = read_mesh(p)
        out[Path(p).stem] = surface_graph(mesh.points, mesh.facets)
    return out


def load_study_arrays(manifest_path, full_surface: bool = False) -> dict:
    """Converged cases of one scenario (verified shards); with ``surface_displacement_mm`` if ``full_surface``."""
    arrays = dio.load_training_arrays(dio.verify_manifest(manifest_path), full_surface=full_surface)
    if full_surface and any(len(x) == 0 for x in arrays["surface_displacement_mm"]):
        raise RuntimeError(
            f"{manifest_path}: the shards hold no full-surface displacements (dataset.store_full_surface "
            "was false when they were simulated); the ROI-fraction study needs them — set it to true and "
            "re-run the sweep"
        )
    return arrays


def run_study_stage(study: str, study_cfg: dict, manifests: dict, main_metrics: dict, mesh_paths: list[str],
                    model_cfg: dict, train_cfg: dict, tracking_uri: str, experiment_prefix: str, experiment: str,
                    seed: int, threads: int, out_json, out_png) -> dict:
    """Run one comparison study on the existing shards; write ``studies/<study>.json`` + PNG, log MLflow runs.

    ``manifests`` / ``main_metrics``: scenario -> path. The points reuse the
    main model's split seed (``seed + train.seed``) and tuned hyper-parameters.
    """
    from liverforce.learn.study import plot_study, run_study
    from liverforce.tracking import Tracker

    surfaces = surface_graphs(mesh_paths) if study == "roi_fraction" else None
    data, versions = {}, {}
    for sc, mp in manifests.items():
        data[sc] = load_study_arrays(mp, full_surface=study == "roi_fraction")
        versions[sc] = json.loads(Path(mp).read_text())["data_version"]
        log.info("study %s: scenario %s, %d converged cases (data version %s)", study, sc,
                 len(data[sc]["case_id"]), versions[sc])
    mains = {sc: json.loads(Path(p).read_text()) for sc, p in main_metrics.items()}
    tracker = Tracker(tracking_uri, f"{experiment_prefix}-{experiment}-studies")
    doc = run_study(study, study_cfg, data, model_cfg, mains, train_cfg, seed=seed + int(train_cfg["seed"]),
                    threads=threads, surfaces=surfaces, tracker=tracker,
                    tags={"experiment": experiment,
                          "data_version": ",".join(f"{k}:{v}" for k, v in sorted(versions.items()))})
    doc["data_version"] = versions
    doc["main_model_runs"] = {sc: m.get("run_id") for sc, m in mains.items()}
    plot_study(doc, out_png)
    doc["figure"] = Path(out_png).name
    dio.write_json_atomic(doc, out_json)
    ok = sum(p["status"] == "ok" for p in doc["points"])
    log.info("study %s: %d/%d points in %.1f s (%.1f s CPU)", study, ok, len(doc["points"]), doc["seconds"],
             doc["cpu_seconds"])
    return doc


# ------------------------------------------------------------------- report


def solver_statistics(manifests: list[str]) -> dict:
    """Cases, failures (with reasons) and solve times per scenario, read from the verified shards."""
    per, reasons = {}, {}
    all_walls = []
    for m in manifests:
        walls, iters, steps, umax = [], [], [], []
        for shard in dio.verify_manifest(m):
            t = dio.read_table(shard, columns=["wall_time_s", "newton_iterations", "load_steps", "converged",
                                               "reason", "max_displacement_mm"])
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
            per[Path(m).parent.name] = {
                "solve_time_total_s": float(np.sum(walls)), "solve_time_median_s": float(np.median(walls)),
                "solve_time_max_s": float(np.max(walls)), "newton_iterations_median": float(np.median(iters)),
                "load_steps_median": float(np.median(steps)),
                "max_displacement_median_mm": float(np.median(umax)) if umax else None,
            }
    overall = {}
    if all_walls:
        overall = {"cases simulated": len(all_walls),
                   "solver wall time total (s)": round(float(np.sum(all_walls)), 1),
                   "median per case (s)": round(float(np.median(all_walls)), 3)}
    return {"overall": overall, "per_scenario": per, "reasons": dict(sorted(reasons.items(), key=lambda kv: -kv[1]))}


def make_report(model_metrics: list[str], manifests: list[str], validation: str, features: list[str],
                pictures: list[str], experiment: str, out_html, studies: list[str] = (),
                setup: dict | None = None) -> Path:
    """Write ``report/index.html`` (+ ``report/figures/``) from the stage outputs.

    ``studies``: the ``studies/<study>.json`` files (their PNGs beside them);
    ``setup``: the config slices the setup section shows.
    """
    from liverforce.report.html import collect, write_report

    data = collect(model_metrics, manifests, validation, features, studies)
    data["validation_dir"] = str(Path(validation).parent)
    stats = solver_statistics(manifests)
    path = write_report(data, pictures, experiment, out_html, solver_stats=stats, setup=setup)
    log.info("report: %s", path)
    return path
