"""Surface → tagged tetrahedral liver mesh, in one call."""

from __future__ import annotations

import logging
from dataclasses import asdict

import numpy as np

from liverforce.geometry.surface import Surface
from liverforce.mesh.boundary import boundary_facets
from liverforce.mesh.quality import mesh_quality
from liverforce.mesh.regions import RegionParams, tag_regions, visible_facets
from liverforce.mesh.tetra import DEFAULT_TARGET_NODES, tetrahedralise_with_info
from liverforce.mesh.types import REGION_CODES, LiverMesh

log = logging.getLogger(__name__)


def build_liver_mesh(
    surface: Surface,
    target_nodes: int | None = DEFAULT_TARGET_NODES,
    region_params: RegionParams | None = None,
    *,
    edge_length_mm: float | None = None,
    refine_points=None,
    refine_radius_mm: float | None = None,
    refine_edge_mm: float | None = None,
    refine_visible_edge_mm: float | None = None,
    refine_visible_depth_mm: float = 10.0,
    refine_growth: float = 0.3,
    conforming_regions: bool = True,
    exertion_sampling: dict | None = None,
    refine_ivc_edge_mm: float | None = None,
    mesher: str = "gmsh",
    seed: int = 0,
    require_regions: bool = False,
    supports: tuple | None = None,
    support_frame=None,
    file_vertices=None,
    exertion_points=None,
    exertion_labels: list[str] | None = None,
    exertion_reading=None,
    file_groups=None,
    auto_regions: tuple | None = None,
    regions_check: str = "warn",
    require_held: str | None = None,
) -> LiverMesh:
    """Tetrahedralise ``surface``, extract and tag its boundary facets.

    Parameters
    ----------
    surface : Surface
        Closed, outward-oriented surface in mm.
    target_nodes : int or None
        Wanted node count (default 5000); ignored if ``edge_length_mm`` is given.
    region_params : RegionParams, optional
        Region parameters (defaults if ``None``).
    edge_length_mm : float, optional
        Uniform edge length (mm) instead of a node count.
    refine_points, refine_radius_mm, refine_edge_mm
        Local refinement (see :func:`~liverforce.mesh.tetra.tetrahedralise`);
        a zero or missing radius means no refinement.
    refine_visible_edge_mm : float, optional
        Edge length (mm) on the visible surface (where the tool may push) and
        within ``refine_visible_depth_mm`` under it, growing back to the bulk
        size at ``refine_growth`` mm per mm. The visible set is computed on the
        input surface with ``region_params`` (the same rule as on the mesh), so
        every later exertion point lies in the refined zone. None or 0: off.
        With ``target_nodes`` the bulk size grows to keep the node count.
    refine_visible_depth_mm : float
        Depth (mm) of the refined layer under the visible surface (default 10).
    refine_growth : float
        Size growth rate (mm per mm) away from refined zones (default 0.3).
    exertion_sampling : dict, optional
        ``{"n_points": k, "min_spacing_mm": s, "seed": i}``: sample the candidate
        exertion points (where the tool will push; see
        :func:`liverforce.sweep.design.sample_exertion_points`) on the visible
        part of the *input* surface before meshing, store them in
        ``meta["exertion_candidates_mm"]`` and, when ``refine_radius_mm > 0``
        and no ``refine_points`` are given, refine the mesh around them. The
        tool traction is a Gaussian of a few mm; a bulk mesh resolves it only
        when refined there (measured on a procedural liver at 3 N: the
        displacement under the tool changes by ~1 % between this mesh and
        one of twice the node density, against 5-15 % without refinement).
    refine_ivc_edge_mm : float, optional
        Edge length (mm) on and around the fixed IVC patch. Its border is where a
        clamped surface meets a free one (a stress singularity), so its reaction
        converges slowly on a coarse mesh: 6.7 % between the default mesh and one of
        twice the density without this, under 5 % with 6 mm. None or 0: off.
    conforming_regions : bool
        Tag the regions on the input surface and make the mesh conform to
        their borders (default): a region then covers the same surface at
        every mesh size, so support reactions converge under refinement
        (whole-facet regions move their borders by up to an element, which
        changed reactions by ~10 % at ~800 nodes). Falls back to tagging the
        mesh facets if the conforming mesh fails. False: tag mesh facets.
    mesher : {"gmsh", "tetgen"}
        Volume mesher (see :func:`~liverforce.mesh.tetra.tetrahedralise`).
    seed : int
        Mesher seed.
    supports : tuple, optional
        ``(mode, [Support])`` from :func:`liverforce.mesh.supports.parse_supports`:
        user supports applied to the input surface's facets (replacing or on top
        of the auto-tagged regions) before meshing; the mesh conforms to their
        borders. ``meta["supports"]`` lists each with its facet count and, for
        point files, the snapping distance.
    support_frame : PointFrame, optional
        How the geometry file's coordinates map to ``surface`` (identity if None).
    file_vertices : callable, optional
        Returns the geometry file's vertices as read (for selectors by vertex id).
    file_groups : callable, optional
        Returns the geometry file's tagged groups (:func:`liverforce.mesh.groups.read_file_groups`),
        for ``group`` selectors: the groups are transferred onto the input surface.
    exertion_points : array-like, optional
        ``(k, 3)`` given exertion points in the surface's frame (mm): snapped to the
        input surface (refused beyond 5 mm or on a fixed support), used instead of
        ``exertion_sampling`` as ``meta["exertion_candidates_mm"]``, refined around;
        ``meta["exertion_snap_mm"]`` holds the snapping distances.
    exertion_labels : list of str, optional
        Each given point as the user gave it (:func:`liverforce.mesh.supports.exertion_points_mesh`), for the
        refusals' messages.
    exertion_reading : ExertionReading, optional
        How they were read (:func:`~liverforce.mesh.supports.exertion_points_mesh`): a point too far from the
        surface is refused saying which other frame or units would fit.
    auto_regions : (region, visible), optional
        The auto-tagged regions of ``surface`` with ``region_params``
        (:func:`~liverforce.mesh.regions.tag_regions`), when the caller has them already (the mesh stage
        tags them to check them before meshing): used as they are instead of tagging the surface again, which
        on a large surface takes as long as the check. Their lengths must match ``surface.faces``.
    regions_check : {"warn", "strict", "off"}
        ``mesh.regions_check``: a given exertion point off the visible area (where built-in sampling places
        the tool) is logged as a warning and listed in ``meta["exertion_not_visible"]``, or, under ``strict``,
        refused (:func:`~liverforce.mesh.supports.check_exertion_facing`); a support's file of points that fits
        the surface better mirrored in x and y (read in the wrong of RAS and LPS), or a sphere whose centre lies
        on the surface only mirrored, likewise, recorded on its report in ``meta["supports"]`` (``frame_check``,
        :func:`liverforce.mesh.supports.check_support_frame`, :func:`~liverforce.mesh.supports.check_sphere_frame`).
    require_held : str, optional
        Refuse ``supports`` that leave the liver free to move as a rigid body, on the input surface before
        meshing (:func:`~liverforce.mesh.supports.check_held`; the string says where they were given, for the
        message). The mesh stage asks it of a lab's supports; ``None`` (default) does not check.
    require_regions : bool
        Raise ``ValueError`` if a region (1–4) or the visible set is empty;
        otherwise empty ones are only logged and listed in
        ``meta["empty_regions"]``.

    Returns
    -------
    LiverMesh
        ``meta`` holds ``surface`` (the surface provenance), ``meshing``,
        ``region_params``, ``quality`` and ``empty_regions``.
    """
    params = region_params or RegionParams()
    if edge_length_mm is not None:
        target_nodes = None
    if refine_radius_mm is not None and refine_radius_mm <= 0:
        refine_points = None
    zones = []
    surface_labels = None
    candidates = None
    support_report, snap, owner = None, None, None
    not_visible = [] if exertion_points is not None and regions_check != "off" else None
    user = supports is not None and len(supports[1]) > 0
    if (conforming_regions or refine_visible_edge_mm or exertion_sampling or refine_ivc_edge_mm or user
            or exertion_points is not None):
        if auto_regions is None:
            s_region, s_visible = tag_regions(surface.vertices, surface.faces, params)
        else:
            s_region, s_visible = (np.array(a, copy=True) for a in auto_regions)
            if s_region.shape != (len(surface.faces),) or s_visible.shape != (len(surface.faces),):
                raise ValueError(f"auto_regions: {s_region.shape[0]} region codes and {s_visible.shape[0]} visible "
                                 f"flags for the {len(surface.faces)} facets of {surface.meta.get('source', '?')}: "
                                 "pass tag_regions(surface.vertices, surface.faces, region_params) of this surface")
        if user:
            from liverforce.mesh.supports import PointFrame, assign_supports

            s_region, support_report, owner = assign_supports(
                surface.vertices, surface.faces, s_region, supports[0], supports[1],
                support_frame or PointFrame(), file_vertices, file_groups=file_groups, regions_check=regions_check)
            if require_held:
                from liverforce.mesh.supports import require_held_by

                require_held_by(surface.vertices, surface.faces, s_region, supports[1], require_held)
            s_visible = visible_facets(surface.vertices, surface.faces, s_region, params)
            for info in support_report:
                log.info("support %s (%s, %s): %d facets%s", info["name"], info["kind"], info["selector"],
                         info["n_facets"], f", snapped up to {info['snap_mm']['max']:.3g} mm"
                         if "snap_mm" in info else "")
        if conforming_regions or user:
            surface_labels = s_region
        if exertion_points is not None:
            from liverforce.mesh.supports import snap_exertion_points

            candidates, snap = snap_exertion_points(surface.vertices, surface.faces, s_region, exertion_points,
                                                     labels=exertion_labels, owner=owner,
                                                     supports=supports[1] if user else None, visible=s_visible,
                                                     regions_check=regions_check, params=params,
                                                     not_visible=not_visible, frame=support_frame,
                                                     reading=exertion_reading)
            log.info("%d given exertion points snapped to the surface (max %.3g mm)", len(candidates), snap.max())
            if refine_points is None and refine_radius_mm:
                refine_points = candidates
        elif exertion_sampling:
            from liverforce.sweep.design import sample_exertion_points

            if user and not s_visible.any():
                from liverforce.mesh.supports import no_tool_area

                raise no_tool_area(supports[1], support_report)
            candidates = sample_exertion_points(
                surface.vertices, surface.faces, s_visible, int(exertion_sampling["n_points"]),
                float(exertion_sampling["min_spacing_mm"]), int(exertion_sampling["seed"]))
            if refine_points is None and refine_radius_mm:
                refine_points = candidates
        ivc = s_region == REGION_CODES["ivc"]
        if refine_ivc_edge_mm and ivc.any():
            zones.append({"points": _surface_samples(surface, ivc, 0.5 * refine_ivc_edge_mm),
                          "radius_mm": float(refine_ivc_edge_mm), "edge_mm": float(refine_ivc_edge_mm),
                          "growth": float(refine_growth)})
        if refine_visible_edge_mm and s_visible.any():
            zones.append({"points": _surface_samples(surface, s_visible, 0.5 * refine_visible_edge_mm),
                          "radius_mm": float(refine_visible_depth_mm), "edge_mm": float(refine_visible_edge_mm),
                          "growth": float(refine_growth)})
    points, tets, info = tetrahedralise_with_info(
        surface,
        target_nodes=target_nodes,
        edge_length_mm=edge_length_mm,
        refine_points=refine_points,
        refine_radius_mm=refine_radius_mm,
        refine_edge_mm=refine_edge_mm,
        seed=seed,
        mesher=mesher,
        refine_growth=refine_growth,
        surface_labels=surface_labels,
        refine_zones=zones,
    )
    facets = boundary_facets(tets)
    if info.boundary_labels is not None:
        region = _facet_labels(points, facets, info.boundary_triangles, info.boundary_labels).astype(np.int8)
        visible = visible_facets(points, facets, region, params)
        region_source = "input surface (conforming mesh)"
    elif surface_labels is not None:  # conforming mesh refused: same regions, borders rounded to facets
        region = _transfer_labels(points, facets, surface, surface_labels).astype(np.int8)
        visible = visible_facets(points, facets, region, params)
        region_source = "input surface (transferred to facets)"
    else:
        region, visible = tag_regions(points, facets, params)
        region_source = "mesh facets"
    held = None if owner is None else _support_owner(points, facets, region, surface, s_region, owner)
    empty = [name for name, code in REGION_CODES.items() if code and not (region == code).any()]
    if not visible.any():
        empty.append("visible")
    if empty:
        msg = f"empty boundary regions {empty} on surface {surface.meta.get('source', '?')}"
        if require_regions:
            raise ValueError(msg + ": adjust RegionParams (e.g. anterior/superior for an imported liver)")
        if user and supports[0] == "replace" and "visible" not in empty:
            log.info(msg + " (the user's supports replace the auto-tagged regions)")
        else:
            log.warning(msg)
    meta = {
        "surface": dict(surface.meta),
        "meshing": info.as_dict(),
        "region_params": _plain(asdict(params)),
        "regions_tagged_on": region_source,
        "refine_visible": ({"edge_mm": float(refine_visible_edge_mm), "depth_mm": float(refine_visible_depth_mm),
                            "growth": float(refine_growth)} if refine_visible_edge_mm else None),
        "refine_ivc_edge_mm": float(refine_ivc_edge_mm) if refine_ivc_edge_mm else None,
        "quality": mesh_quality(points, tets),
        "exertion_candidates_mm": None if candidates is None else candidates.tolist(),
        "exertion_given": exertion_points is not None,
        "exertion_snap_mm": None if snap is None else snap.tolist(),
        "exertion_not_visible": not_visible,
        "supports": support_report,
        "refine_points": (None if refine_points is None or not refine_radius_mm else
                          {"n": int(len(np.atleast_2d(refine_points))), "radius_mm": float(refine_radius_mm),
                           "edge_mm": None if refine_edge_mm is None else float(refine_edge_mm)}),
        "empty_regions": empty,
        "units": "mm",
    }
    return LiverMesh(points, tets, facets, region, visible, meta, facet_support=held)


def _surface_samples(surface: Surface, mask: np.ndarray, spacing_mm: float) -> np.ndarray:
    """Centroids of the masked surface triangles, thinned to about one per ``spacing_mm`` cube."""
    cent = surface.vertices[surface.faces[mask]].mean(axis=1)
    _, first = np.unique(np.floor(cent / max(spacing_mm, 1e-6)).astype(np.int64), axis=0, return_index=True)
    return cent[np.sort(first)]


def _facet_labels(points, facets, tri, labels) -> np.ndarray:
    """Label of each boundary facet from the mesher's labelled triangles (same nodes, any order);
    facets the mesher did not label (exposed by peeling a sliver) take the nearest labelled facet's."""
    from scipy.spatial import cKDTree

    n = len(points)
    key = lambda t: np.sort(t, axis=1) @ np.array([n * n, n, 1], dtype=np.int64)  # noqa: E731
    k_tri, k_fac = key(tri), key(facets)
    order = np.argsort(k_tri)
    pos = np.clip(np.searchsorted(k_tri[order], k_fac), 0, len(order) - 1)
    hit = k_tri[order][pos] == k_fac
    out = np.empty(len(facets), dtype=np.int64)
    out[hit] = labels[order[pos[hit]]]
    if (~hit).any():
        cent = points[facets].mean(axis=1)
        _, j = cKDTree(cent[hit]).query(cent[~hit])
        out[~hit] = out[hit][j]
    return out


def _transfer_labels(points, facets, surface: Surface, labels: np.ndarray) -> np.ndarray:
    """Label of each mesh facet: majority over its centroid and three inner points of the label of
    the nearest input-surface triangle (centroid distance); ties go to the centroid's label."""
    from scipy.spatial import cKDTree

    bary = np.array([[1 / 3, 1 / 3, 1 / 3], [2 / 3, 1 / 6, 1 / 6], [1 / 6, 2 / 3, 1 / 6], [1 / 6, 1 / 6, 2 / 3]])
    q = np.einsum("qm,kmi->kqi", bary, points[facets]).reshape(-1, 3)
    tree = cKDTree(surface.vertices[surface.faces].mean(axis=1))
    _, idx = tree.query(q)
    lab = np.asarray(labels, dtype=np.int64)[idx].reshape(-1, 4)
    n = int(lab.max()) + 1
    votes = np.stack([(lab == c).sum(axis=1) for c in range(n)], axis=1) * 2
    votes[np.arange(len(lab)), lab[:, 0]] += 1
    return votes.argmax(axis=1)


def _support_owner(points, facets, region, surface: Surface, s_region, owner) -> np.ndarray:
    """Which user support holds each mesh facet (:attr:`LiverMesh.facet_support`): the owner of the nearest
    input-surface facet of the same region code (centroid distance), -1 on free facets and where that facet
    is held by none (an auto-tagged region under ``mode: add``)."""
    from scipy.spatial import cKDTree

    out = np.full(len(facets), -1, dtype=np.int64)
    cent = points[facets].mean(axis=1)
    s_cent = surface.vertices[surface.faces].mean(axis=1)
    for code in np.unique(region[region != 0]):
        src, dst = np.flatnonzero(s_region == code), np.flatnonzero(region == code)
        if src.size == 0:
            continue
        if (owner[src] == owner[src[0]]).all():  # one holder of this code: no search
            out[dst] = owner[src[0]]
            continue
        _, j = cKDTree(s_cent[src]).query(cent[dst])
        out[dst] = owner[src[j]]
    return out


def _plain(obj):
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj
