"""Region of interest (ROI): the surface patch around the tool, and the local frame.

The ROI is grown from the exertion point along the surface (geodesic distance
along surface edges, Dijkstra), adding surface nodes in order of distance until
their share of the surface area reaches the requested fraction (the study used
18 %). Growing along the surface, not in space, keeps the patch on the touched
side of thin parts such as the left lobe.

Notes
-----
Node area = one third of the area of each adjacent surface triangle, so node
areas sum to the total surface area and the achieved fraction differs from the
target by at most one node's area.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra


@dataclass(frozen=True)
class SurfaceGraph:
    """Surface nodes of one geometry, with their areas and edge graph.

    Attributes
    ----------
    node_ids : (s,) int64   mesh point ids of surface nodes, sorted
    points : (s, 3)         their reference coordinates, mm
    areas : (s,)            node areas, mm^2
    normals : (s, 3)        area-weighted outward unit normals
    graph : (s, s) sparse   edge lengths, mm
    triangles : (m, 3) int64 the surface triangles as indices into ``node_ids``
    """

    node_ids: np.ndarray
    points: np.ndarray
    areas: np.ndarray
    normals: np.ndarray
    graph: sp.csr_matrix
    triangles: np.ndarray

    @property
    def total_area(self) -> float:
        return float(self.areas.sum())


def surface_graph(points: np.ndarray, facets: np.ndarray) -> SurfaceGraph:
    """Build the surface graph from mesh points and boundary triangles (outward)."""
    node_ids = np.unique(facets)
    local = np.full(points.shape[0], -1, dtype=np.int64)
    local[node_ids] = np.arange(node_ids.size)
    tri = local[facets]
    p = points[node_ids]
    a, b, c = p[tri[:, 0]], p[tri[:, 1]], p[tri[:, 2]]
    cross = np.cross(b - a, c - a)
    tri_area = 0.5 * np.linalg.norm(cross, axis=1)
    areas = np.zeros(node_ids.size)
    normals = np.zeros((node_ids.size, 3))
    for k in range(3):
        np.add.at(areas, tri[:, k], tri_area / 3.0)
        np.add.at(normals, tri[:, k], 0.5 * cross)
    nrm = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = normals / np.where(nrm > 0, nrm, 1.0)
    i = np.concatenate([tri[:, 0], tri[:, 1], tri[:, 2]])
    j = np.concatenate([tri[:, 1], tri[:, 2], tri[:, 0]])
    w = np.linalg.norm(p[i] - p[j], axis=1)
    g = sp.coo_matrix((w, (i, j)), shape=(node_ids.size,) * 2).tocsr()
    g = g.maximum(g.T).tocsr()
    return SurfaceGraph(node_ids=node_ids, points=p, areas=areas, normals=normals, graph=g, triangles=tri)


def nearest_surface_node(surf: SurfaceGraph, point: np.ndarray) -> int:
    """Local index of the surface node closest to ``point``."""
    d = np.linalg.norm(surf.points - np.asarray(point)[None, :], axis=1)
    return int(np.argmin(d))


def extract_roi(surf: SurfaceGraph, point: np.ndarray, fraction: float) -> tuple[np.ndarray, float]:
    """Surface nodes within the geodesic patch covering ``fraction`` of the area.

    Parameters
    ----------
    surf : SurfaceGraph
    point : (3,) exertion point, mm (on or near the surface)
    fraction : float in (0, 1]

    Returns
    -------
    local_ids : (r,) int64
        Local surface indices (into ``surf.node_ids``), ordered by distance.
    achieved : float
        Achieved area fraction.
    """
    if not 0.0 < fraction <= 1.0:
        raise ValueError(f"ROI fraction must be in (0, 1], got {fraction}")
    src = nearest_surface_node(surf, point)
    dist = dijkstra(surf.graph, directed=False, indices=src)
    order = np.lexsort((np.arange(dist.size), dist))
    order = order[np.isfinite(dist[order])]
    cum = np.cumsum(surf.areas[order])
    target = fraction * surf.total_area
    n = int(np.searchsorted(cum, target, side="left")) + 1
    n = min(max(n, 1), order.size)
    # take whichever of n-1 / n nodes is closer to the target area
    if n > 1 and abs(cum[n - 2] - target) < abs(cum[n - 1] - target):
        n -= 1
    ids = order[:n]
    return ids, float(cum[n - 1] / surf.total_area)


def roi_triangles(facets: np.ndarray, roi_point_ids: np.ndarray) -> np.ndarray:
    """The ROI patch's own triangles: the surface ``facets`` (mesh point ids) whose three nodes are all ROI
    nodes, as ``(m, 3)`` indices into ``roi_point_ids`` (the order of ``roi_undeformed_mm``).

    The models read the patch's top sheet through them: a camera model's pre-operative height
    (:meth:`liverforce.learn.cloud_features.ReferenceSurface.from_patch`) and a node model's grid
    (:func:`liverforce.learn.grid.interpolate_top_sheet`).
    """
    F = np.asarray(facets, dtype=np.int64).reshape(-1, 3)
    ids = np.asarray(roi_point_ids, dtype=np.int64).ravel()
    if ids.size == 0 or F.size == 0:
        return np.empty((0, 3), dtype=np.int64)
    pos = np.full(max(int(F.max()), int(ids.max())) + 1, -1, dtype=np.int64)
    pos[ids] = np.arange(ids.size)
    T = pos[F]
    return T[(T >= 0).all(axis=1)]


def local_frame(surf: SurfaceGraph, point: np.ndarray, radius_mm: float = 5.0) -> np.ndarray:
    """Right-handed local frame at the exertion point: rows (t1, t2, n).

    ``n`` is the outward normal, area-weighted over surface nodes within
    ``radius_mm`` (the nearest node if none); ``t1`` is the global axis least
    aligned with ``n`` projected onto the tangent plane (deterministic), and
    ``t2 = n x t1``.
    """
    d = np.linalg.norm(surf.points - np.asarray(point)[None, :], axis=1)
    near = d <= radius_mm
    if not near.any():
        near = d == d.min()
    n = (surf.normals[near] * surf.areas[near, None]).sum(axis=0)
    n /= np.linalg.norm(n)
    axis = np.eye(3)[int(np.argmin(np.abs(n)))]
    t1 = axis - axis.dot(n) * n
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(n, t1)
    return np.stack([t1, t2, n])


def thickness_along_normal(points: np.ndarray, facets: np.ndarray, point: np.ndarray, normal: np.ndarray,
                           min_mm: float = 0.5) -> float:
    """Tissue thickness under the tool: distance from ``point`` along ``-normal`` to the opposite surface (mm).

    A ray from the exertion point into the liver (``-normal``, the outward
    normal negated) is intersected with every surface triangle
    (Möller–Trumbore); the nearest hit farther than ``min_mm`` (which skips the
    triangles around the point itself) where the ray *leaves* the liver is the
    thickness. Triangles the ray enters through are skipped, so a point a
    little outside the surface (a point snapped onto the FE mesh, given with
    the surface it was segmented on) is not read as a liver a millimetre
    thick. Which side is out follows the surface's enclosed volume, so the
    triangles' winding may be inward or outward. ``nan`` when the ray leaves
    through no triangle (an open surface).

    Examples
    --------
    A cube of edge 50 mm, pushed at the centre of its top face: 50 mm.
    """
    tri = np.asarray(points, dtype=np.float64)[np.asarray(facets)]
    o = np.asarray(point, dtype=np.float64)
    d = -np.asarray(normal, dtype=np.float64)
    d = d / np.linalg.norm(d)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    h = np.cross(d, e2)
    a = np.einsum("ij,ij->i", e1, h)
    ok = np.abs(a) > 1e-12
    f = np.zeros_like(a)
    f[ok] = 1.0 / a[ok]
    s = o - tri[:, 0]
    u = f * np.einsum("ij,ij->i", s, h)
    q = np.cross(s, e1)
    v = f * (q @ d)
    t = f * np.einsum("ij,ij->i", e2, q)
    # a = -d . (e1 x e2): negative where the ray leaves through a triangle wound outward
    outward = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() >= 0.0
    leaves = (a < 0) if outward else (a > 0)
    hit = ok & leaves & (u >= -1e-9) & (v >= -1e-9) & (u + v <= 1 + 1e-9) & (t > min_mm)
    return float(t[hit].min()) if hit.any() else float("nan")
