"""Surface → tagged tetrahedral liver mesh, in one call."""

from __future__ import annotations

import logging
from dataclasses import asdict

import numpy as np

from liverforce.geometry.surface import Surface
from liverforce.mesh.boundary import boundary_facets
from liverforce.mesh.quality import mesh_quality
from liverforce.mesh.regions import RegionParams, tag_regions
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
    mesher: str = "gmsh",
    seed: int = 0,
    require_regions: bool = False,
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
    mesher : {"gmsh", "tetgen"}
        Volume mesher (see :func:`~liverforce.mesh.tetra.tetrahedralise`).
    seed : int
        Mesher seed.
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
    points, tets, info = tetrahedralise_with_info(
        surface,
        target_nodes=target_nodes,
        edge_length_mm=edge_length_mm,
        refine_points=refine_points,
        refine_radius_mm=refine_radius_mm,
        refine_edge_mm=refine_edge_mm,
        seed=seed,
        mesher=mesher,
    )
    facets = boundary_facets(tets)
    region, visible = tag_regions(points, facets, params)
    empty = [name for name, code in REGION_CODES.items() if code and not (region == code).any()]
    if not visible.any():
        empty.append("visible")
    if empty:
        msg = f"empty boundary regions {empty} on surface {surface.meta.get('source', '?')}"
        if require_regions:
            raise ValueError(msg + ": adjust RegionParams (e.g. anterior/superior for an imported liver)")
        log.warning(msg)
    meta = {
        "surface": dict(surface.meta),
        "meshing": info.as_dict(),
        "region_params": _plain(asdict(params)),
        "quality": mesh_quality(points, tets),
        "empty_regions": empty,
        "units": "mm",
    }
    return LiverMesh(points, tets, facets, region, visible, meta)


def _plain(obj):
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj
