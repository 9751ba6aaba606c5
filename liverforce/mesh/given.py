"""A tagged liver mesh from a tet mesh imported as given (no remeshing, node numbering kept).

The counterpart of :func:`liverforce.mesh.build.build_liver_mesh` for
``geometry.imported[].mesh: as_given``: the nodes and tets are the file's
(:func:`liverforce.geometry.volume_mesh.load_volume_mesh`), the boundary facets
are the faces of exactly one tet, and the regions are tagged on those facets
(automatic tagging, then the user's supports, as on a remeshed liver). Exertion
points given by the user are snapped onto the mesh surface; otherwise candidates
are sampled on its visible facets. Nothing is refined: the mesh settings
(``mesh.target_nodes``, ``refine_*``, ``mesher``) do not apply.
"""

from __future__ import annotations

import logging

import numpy as np

from liverforce.mesh.boundary import boundary_facets
from liverforce.mesh.quality import mesh_quality, orient_positive
from liverforce.mesh.regions import RegionParams, tag_regions, visible_facets
from liverforce.mesh.types import REGION_CODES, LiverMesh

log = logging.getLogger(__name__)


def build_given_mesh(points, tets, meta: dict | None = None, region_params: RegionParams | None = None, *,
                     supports: tuple | None = None, support_frame=None, file_vertices=None, file_groups=None,
                     exertion_points=None, exertion_sampling: dict | None = None,
                     exertion_labels: list[str] | None = None, exertion_reading=None, regions_check: str = "warn",
                     coarse_edge_mm: float | None = None, require_held: str | None = None) -> LiverMesh:
    """Tag the boundary of a given tet mesh; node ``i`` stays node ``i``.

    Parameters
    ----------
    points, tets : (n, 3) mm and (m, 4) node ids (any orientation; reoriented if needed).
    meta : provenance of the volume mesh (``VolumeMesh.meta``), kept under ``meta["surface"]``.
    region_params : automatic region tagging parameters.
    supports, support_frame, file_vertices, file_groups :
        as :func:`liverforce.mesh.build.build_liver_mesh` (user supports applied to the
        mesh's own boundary facets).
    exertion_points : (k, 3) given exertion points (mesh frame, mm): snapped onto the mesh surface.
    exertion_labels : each given point as the user gave it, for the refusals' messages.
    exertion_reading : how they were read (:func:`~liverforce.mesh.supports.exertion_points_mesh`), for the hints of
        the refusal of a point too far from the surface.
    regions_check : ``mesh.regions_check``, as :func:`liverforce.mesh.build.build_liver_mesh`: a given exertion
        point off the visible area is warned and listed in ``meta["exertion_not_visible"]`` (refused under
        ``strict`` if it faces away from the camera or looks like a frame mix-up; ``off``: not checked); a
        support's file of points (or sphere) read in the wrong frame is warned (refused under ``strict``) and
        recorded on its report (``frame_check``).
    exertion_sampling : ``{"n_points", "min_spacing_mm", "seed"}``: candidates sampled on the visible facets.
    coarse_edge_mm : warn when the mean boundary edge is longer (mm): the tool's few-mm traction is then
        resolved by few facets (the mesh stage passes twice ``mesh.refine_edge_mm``).
    require_held : refuse supports that leave the mesh free to move as a rigid body, as
        :func:`liverforce.mesh.build.build_liver_mesh` (``None``: not checked).

    Returns
    -------
    LiverMesh
        ``meta["node_numbering"] == "file"``; ``meta["meshing"]["mesher"] == "as_given"``.
    """
    params = region_params or RegionParams()
    points = np.asarray(points, float)
    given = np.asarray(tets, np.int64)
    tets = orient_positive(points, given)
    n_reoriented = int((tets != given).any(axis=1).sum())  # 0 from load_volume_mesh, which orients and reports
    facets = boundary_facets(tets)
    region, visible = tag_regions(points, facets, params)
    support_report, owner = None, None
    user = supports is not None and len(supports[1]) > 0
    if user:
        from liverforce.mesh.supports import PointFrame, assign_supports

        region, support_report, owner = assign_supports(points, facets, region, supports[0], supports[1],
                                                        support_frame or PointFrame(), file_vertices,
                                                        file_groups=file_groups, regions_check=regions_check)
        if require_held:
            from liverforce.mesh.supports import require_held_by

            require_held_by(points, facets, region, supports[1], require_held)
        visible = visible_facets(points, facets, region, params)
        for info in support_report:
            log.info("support %s (%s, %s): %d facets of the given mesh", info["name"], info["kind"],
                     info["selector"], info["n_facets"])
    candidates, snap = None, None
    not_visible = [] if exertion_points is not None and regions_check != "off" else None
    if exertion_points is not None:
        from liverforce.mesh.supports import snap_exertion_points

        candidates, snap = snap_exertion_points(points, facets, region, exertion_points, labels=exertion_labels,
                                                owner=owner, supports=supports[1] if user else None,
                                                visible=visible, regions_check=regions_check, params=params,
                                                not_visible=not_visible, frame=support_frame, reading=exertion_reading)
        log.info("%d given exertion points snapped to the given mesh's surface (max %.3g mm)", len(candidates),
                 snap.max())
    elif exertion_sampling and user and not visible.any():
        from liverforce.mesh.supports import no_tool_area

        raise no_tool_area(supports[1], support_report)
    elif exertion_sampling and visible.any():
        from liverforce.sweep.design import sample_exertion_points

        candidates = sample_exertion_points(points, facets, visible, int(exertion_sampling["n_points"]),
                                            float(exertion_sampling["min_spacing_mm"]),
                                            int(exertion_sampling["seed"]))
    edge = float(np.linalg.norm(points[facets] - points[np.roll(facets, 1, axis=1)], axis=2).mean())
    if coarse_edge_mm and edge > coarse_edge_mm:
        log.warning("the given mesh is coarse for the tool: mean boundary edge %.3g mm (> %.3g mm); the "
                    "indentation will depend on the mesh (import it with mesh: remesh to refine around the "
                    "exertion points)", edge, coarse_edge_mm)
    quality = mesh_quality(points, tets)
    if quality["n_below_bound"]:
        log.warning("the given mesh has %d of %d tets with radius ratio below %.2g (min %.3g): the solution near "
                    "them is less accurate and Newton may need more steps (mesh: remesh gives a quality mesh)",
                    quality["n_below_bound"], len(tets), quality["quality_bound"], quality["radius_ratio_min"])
    empty = [name for name, code in REGION_CODES.items() if code and not (region == code).any()]
    if not visible.any():
        empty.append("visible")
    if empty:
        (log.info if user and supports[0] == "replace" and "visible" not in empty else log.warning)(
            "empty boundary regions %s on the given mesh %s", empty, (meta or {}).get("source", "?"))
    out_meta = {
        "surface": dict(meta or {}),
        "meshing": {"mesher": "as_given", "n_nodes": int(len(points)), "n_tets": int(len(tets)),
                    "mean_boundary_edge_mm": edge, "reoriented_here": n_reoriented},
        "node_numbering": "file",
        "region_params": _plain(params),
        "regions_tagged_on": "mesh facets (mesh as given)",
        "quality": quality,
        "exertion_candidates_mm": None if candidates is None else np.asarray(candidates).tolist(),
        "exertion_given": exertion_points is not None,
        "exertion_snap_mm": None if snap is None else snap.tolist(),
        "exertion_not_visible": not_visible,
        "supports": support_report,
        "refine_points": None,
        "empty_regions": empty,
        "units": "mm",
    }
    return LiverMesh(points, tets, facets, region, visible, out_meta, facet_support=owner)


def _plain(params) -> dict:
    from dataclasses import asdict

    def plain(o):
        if isinstance(o, dict):
            return {k: plain(v) for k, v in o.items()}
        if isinstance(o, (list, tuple)):
            return [plain(v) for v in o]
        return o.item() if isinstance(o, np.generic) else o

    return plain(asdict(params))
