"""Geometric features of a liver mesh (the pre-operative "state" of a geometry)."""

from __future__ import annotations

import numpy as np

from liverforce.mesh.quality import mesh_quality, signed_volumes
from liverforce.mesh.types import REGION_CODES, LiverMesh


def volume_moments(points: np.ndarray, tets: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Volume (mm³), centroid (mm) and inertia tensor (mm⁵) of a tet mesh.

    Notes
    -----
    Unit density.  For a tet with vertices ``v_a`` (relative to the
    centroid) and volume ``V``, ``∫ x xᵀ dV = V/20 (Σ_a v_a v_aᵀ + s sᵀ)``
    with ``s = Σ_a v_a``; this is exact for the polyhedral body.  The
    inertia tensor is ``J = ∫ (r·r I − r ⊗ r) dV = tr(M) I − M`` with
    ``M = ∫ r rᵀ dV`` about the centroid.
    """
    vol = signed_volumes(points, tets)
    total = float(vol.sum())
    centroid = (vol[:, None] * points[tets].mean(axis=1)).sum(axis=0) / total
    v = points[tets] - centroid  # (m, 4, 3)
    s = v.sum(axis=1)
    m = np.einsum("t,tai,taj->ij", vol, v, v) + np.einsum("t,ti,tj->ij", vol, s, s)
    m /= 20.0
    inertia = np.trace(m) * np.eye(3) - m
    return total, centroid, inertia


def compute_features(mesh: LiverMesh) -> dict:
    """JSON-serialisable geometric features and provenance of a mesh.

    Returns
    -------
    dict
        ``volume_mm3``; ``surface_area_mm2``; ``centroid_mm`` (3);
        ``inertia_mm5`` (3×3, about the centroid, unit density,
        ``∫(r·r I − r⊗r) dV``); ``principal_inertia_mm5`` (ascending) and
        ``principal_axes`` (columns, unit); ``bbox_min_mm``, ``bbox_max_mm``,
        ``extent_mm``; ``n_nodes``, ``n_tets``, ``n_facets``,
        ``n_surface_nodes``; ``region_area_mm2`` (per region name) and
        ``region_facets``; ``visible_area_mm2``, ``visible_facets``;
        ``quality`` (see :func:`~liverforce.mesh.quality.mesh_quality`);
        ``provenance`` (the mesh ``meta``: source, sha256, units/scale,
        generator seed and parameters, meshing and region parameters).
    """
    points, tets, facets = mesh.points, mesh.tets, mesh.facets
    volume, centroid, inertia = volume_moments(points, tets)
    a, b, c = (points[facets[:, i]] for i in range(3))
    areas = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    evals, evecs = np.linalg.eigh(0.5 * (inertia + inertia.T))
    lo, hi = points.min(axis=0), points.max(axis=0)
    region_area = {name: float(areas[mesh.facet_region == code].sum()) for name, code in REGION_CODES.items()}
    region_count = {name: int((mesh.facet_region == code).sum()) for name, code in REGION_CODES.items()}
    return {
        "volume_mm3": float(volume),
        "surface_area_mm2": float(areas.sum()),
        "centroid_mm": centroid.tolist(),
        "inertia_mm5": inertia.tolist(),
        "principal_inertia_mm5": evals.tolist(),
        "principal_axes": evecs.tolist(),
        "bbox_min_mm": lo.tolist(),
        "bbox_max_mm": hi.tolist(),
        "extent_mm": (hi - lo).tolist(),
        "n_nodes": int(len(points)),
        "n_tets": int(len(tets)),
        "n_facets": int(len(facets)),
        "n_surface_nodes": int(len(np.unique(facets))),
        "region_area_mm2": region_area,
        "region_facets": region_count,
        "visible_area_mm2": float(areas[mesh.facet_visible].sum()),
        "visible_facets": int(mesh.facet_visible.sum()),
        "quality": mesh_quality(points, tets),
        "provenance": _jsonable(mesh.meta),
    }


def _jsonable(obj):
    """Deep copy of ``obj`` with numpy scalars/arrays turned into Python types."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return obj
