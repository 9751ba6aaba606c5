"""Sweep stage adapter: exertion points per geometry and the case table of one scenario."""

from __future__ import annotations

import json
import logging

import numpy as np

from liverforce.atomic import write_json_atomic
from liverforce.dataset import io as dio
from liverforce.layout import features_of_mesh, gid_of
from liverforce.seeds import derive

log = logging.getLogger("liverforce")


def material_checks(stretch_range, nu: float):
    """(stability_check, bulk_modulus) callables for :func:`liverforce.sweep.design.build_cases`.

    ``stretch_range`` : ``material.stability_stretch``; ``nu`` : ``material.nu``, the
    Poisson ratio the cases are simulated with: the check builds that same material.
    (The Drucker check itself walks the incompressible test modes, so its verdict
    depends on the isochoric constants only; ``nu`` sets the bulk modulus.)
    """
    from liverforce.fem.materials import make_material
    from liverforce.fem.stability import check_stability

    def stable(model, params):
        try:
            mat = make_material(model, params, nu=nu)
        except ValueError as exc:
            return False, str(exc)
        rep = check_stability(mat, stretch_range=tuple(stretch_range))
        return bool(rep.stable), rep.message

    def bulk(model, params, nu):
        return make_material(model, params, nu=nu).bulk

    return stable, bulk


def exertion_set(mesh, n_points: int, min_spacing_mm: float, seed: int, frame_radius_mm: float,
                 candidates=None, given: bool = False):
    """Candidate exertion points of one mesh with their normals and local frames.

    ``candidates`` : points chosen at the mesh stage (on the input surface, where
    the mesh is refined), moved onto the nearest visible mesh facet; else
    ``n_points`` are sampled on the mesh's visible facets with ``seed``.
    ``given`` : the candidates are the user's exertion points
    (``geometry.imported[].exertion_points``): all of them are used, whatever
    ``n_points``, each moved onto the nearest mesh facet that is not fixed.
    """
    from liverforce.dataset.roi import local_frame, surface_graph
    from liverforce.sweep.design import ExertionSet, SweepError, sample_exertion_points

    if candidates is not None and given:
        pts = closest_surface_points(mesh.points, mesh.facets[mesh.facet_region != 1],
                                     np.asarray(candidates, float).reshape(-1, 3))
    elif candidates is not None:
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
    lie on or near the surface; :func:`liverforce.mesh.supports.closest_on_triangles`).
    """
    from liverforce.mesh.supports import closest_on_triangles

    tri = np.asarray(points, float)[np.asarray(facets)]
    return closest_on_triangles(tri, np.atleast_2d(np.asarray(query, float)), k)[0]


def make_sweep(params: dict, mesh_paths: list[str], cases_path, report_path) -> dict:
    """Build and write the case table of one scenario (refusing unstable materials first)."""
    from liverforce.mesh.io import read_mesh
    from liverforce.sweep.design import build_cases

    gids = params["geometries"]
    if params["material"].get("conversion"):  # constants derived from a Young's modulus (liverforce.config)
        log.info("material: %s", params["material"]["conversion"])
    for gid, own in sorted((params["material"].get("per_liver") or {}).items()):
        log.info("material of %s: its own (geometry.imported[].material %s): %s MPa (nu %g)", gid, own.get("entered"),
                 ", ".join(f"{k} {v:.4g}" for k, v in own["params_mpa"].items()), params["material"]["nu"])
    by_gid = {gid_of(p): p for p in mesh_paths}
    stable, bulk = material_checks(params["material"]["stability_stretch"], params["material"]["nu"])
    ex, given_by = {}, {}
    for gid in gids:
        mesh = read_mesh(by_gid[gid])
        feats = features_of_mesh(by_gid[gid])
        fj = json.loads(feats.read_text()) if feats.exists() else {}
        cand, given = fj.get("exertion_candidates_mm"), bool(fj.get("exertion_given"))
        ex[gid] = exertion_set(mesh, params["exertion"]["n_points"], params["exertion"]["min_spacing_mm"],
                               derive(params["seed"], "sweep.exertion", gid), params["tool_radius_mm"],
                               candidates=cand, given=given)
        if given:
            moved = np.linalg.norm(ex[gid].points - np.asarray(cand, float).reshape(-1, 3), axis=1)
            given_by[gid] = {"n_points": len(moved), "moved_to_mesh_mm": moved.tolist()}
            log.info("%s: %d exertion points given by the user (sweep.exertion.n_points ignored), moved up to "
                     "%.3g mm from the input surface onto the mesh", gid, len(moved), moved.max())
            if moved.max() > 1.0:
                log.warning("%s: a given exertion point moved %.3g mm onto the mesh surface: refine the mesh "
                            "there (mesh.refine_radius_mm, refine_edge_mm)", gid, moved.max())
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
        "exertion_given": given_by,
    }
    write_json_atomic(report_path, report)
    if result.dropped_unstable:
        log.warning("scenario %s: %d sampled material sets were not Drucker-stable and were dropped",
                    params["scenario"], len(result.dropped_unstable))
    log.info("scenario %s: %d cases on %s", params["scenario"], len(result.rows), gids)
    return report


