"""Mesh size: refinement zones and the node-count model that turns a node count into an edge length.

The model (:class:`NodeCountModel`) integrates the size field ``s`` gmsh is
given (``h`` in the bulk, finer in the refinement zones) over the volume and
the surface, plus a few nodes a mesh has whatever its size:

    n ≈ ∫ dV / (1.44 s³) + ∫ dA / (1.19 s²) + offset

(``V / (1.44 h³) + A / (1.19 h²)`` without refinement). The offset is
``OFFSET_NODES`` + ``OFFSET_PER_PATCH`` per label patch of a conforming mesh
+ ``OFFSET_REFINED`` with refinement zones: fitted on four procedural livers
(proc-0000..0003) meshed at fixed sizes along the two-patch and labelled
routes, with and without the exertion and IVC zones (48 meshes of 330-5900
nodes: max error 4 %; on 16 further meshes with one zone only, 3 exertion
points or finer zones: max 8 %, typically 2-3 %; the former
``k (V/(1.44 h³) + A/(1.19 h²))`` + zone terms undershot the labelled, refined
meshes by 10-30 %, so every pipeline liver took three attempts). The mesher
corrects the model from the counts it obtains
(:func:`liverforce.mesh.gmsh_mesher.mesh_route`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class RefinementZone:
    """Mesh at ``edge_mm`` within ``radius_mm`` of ``points`` (mm), growing back at ``growth`` mm per mm."""

    points: np.ndarray
    radius_mm: float
    edge_mm: float
    growth: float

    def as_dict(self) -> dict:
        return {
            "points_mm": self.points.tolist(),
            "radius_mm": self.radius_mm,
            "edge_mm": self.edge_mm,
            "growth": self.growth,
        }


def refinement_zone(points, radius, edge, growth) -> RefinementZone | None:
    """A validated :class:`RefinementZone`, or None when there are no points."""
    if points is None:
        return None
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return None
    if radius is None or edge is None or radius < 0 or edge <= 0:
        raise ValueError("refine_points need refine_radius_mm >= 0 and refine_edge_mm > 0")
    if not 0 < growth <= 2:
        raise ValueError(f"refine_growth must be in (0, 2], got {growth}")
    return RefinementZone(pts, float(radius), float(edge), float(growth))


def refine_provenance(zones: list[RefinementZone]) -> dict | None:
    """JSON provenance of the refinement zones (the first zone's keys at the top level, as before)."""
    if not zones:
        return None
    out = zones[0].as_dict()
    if len(zones) > 1:
        out["zones"] = [{k: v for k, v in z.as_dict().items() if k != "points_mm"} | {"n_points": len(z.points)}
                        for z in zones]
    return out


def size_at(h: float, dist: np.ndarray, zones: list[RefinementZone]) -> np.ndarray:
    """gmsh's background size at points ``dist[z]`` mm from zone ``z``'s nearest point (bulk size ``h``).

    As :func:`liverforce.mesh.gmsh_mesher._set_refinement_field` sets it: per
    zone ``edge_mm`` within ``radius_mm``, then linear growth at ``growth`` mm
    per mm up to ``h`` (a Threshold field on a Distance field), the minimum
    over the zones finer than ``h``.
    """
    size = np.full(dist.shape[1:], float(h))
    for z, d in zip(zones, dist):
        if z.edge_mm < h:
            np.minimum(size, np.clip(z.edge_mm + (d - z.radius_mm) * z.growth, z.edge_mm, h), out=size)
    return size


class SizeFieldQuadrature:
    """Quadrature of a surface and the volume it encloses, with each point's distance to each zone.

    Surface: the triangles (centroid, area); volume: the centres of a grid of
    cells of ``step_mm`` inside the surface (ray parity along z), weighted to
    sum to ``volume``. Built once per surface and zones; :meth:`integrals`
    is then cheap for any bulk size.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, zones: list[RefinementZone], volume: float,
                 step_mm: float | None = None):
        from scipy.spatial import cKDTree

        vertices = np.asarray(vertices, dtype=np.float64)
        faces = np.asarray(faces, dtype=np.int64)
        self.zones = list(zones)
        tri = vertices[faces]
        self.area_w = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        centroids = tri.mean(axis=1)
        if step_mm is None:
            # half the finest zone edge, coarsened so the bounding box holds at most ~4e5 cells
            finest = min((z.edge_mm for z in self.zones), default=10.0)
            box = float(np.prod(np.ptp(vertices, axis=0)))
            step_mm = max(0.5 * finest, (box / 4e5) ** (1 / 3))
        self.step_mm = float(step_mm)
        inside = inside_grid(vertices, faces, self.step_mm)
        self.volume_w = np.full(len(inside), volume / max(len(inside), 1))
        trees = [cKDTree(z.points) for z in self.zones]
        self.area_d = np.array([t.query(centroids)[0] for t in trees]).reshape(len(trees), len(centroids))
        self.volume_d = np.array([t.query(inside)[0] for t in trees]).reshape(len(trees), len(inside))

    def integrals(self, h: float) -> tuple[float, float]:
        """``(∫ dV / s³, ∫ dA / s²)`` for the size field ``s`` at bulk size ``h``."""
        sv = size_at(h, self.volume_d, self.zones)
        sa = size_at(h, self.area_d, self.zones)
        return float(np.sum(self.volume_w / sv**3)), float(np.sum(self.area_w / sa**2))


def inside_grid(vertices: np.ndarray, faces: np.ndarray, step_mm: float) -> np.ndarray:
    """Centres of the cells of a ``step_mm`` grid over the bounding box that lie inside the closed surface.

    Each grid column (x, y) is crossed by the surface at the z of the triangles
    over it; a cell centre is inside when an odd number of crossings lie below
    it. The grid is offset from the box corner by an irrational fraction of a
    step, so columns do not run through vertices or edges of regular surfaces.
    """
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    origin = lo + step_mm * np.array([0.5 / np.sqrt(2), 0.5 / np.sqrt(3), 0.5])
    n = np.maximum(np.ceil((hi - origin) / step_mm).astype(np.int64) + 1, 1)
    tri = vertices[faces]
    xy = tri[:, :, :2]
    # the grid columns under each triangle's xy bounding box
    c0 = np.ceil((xy.min(axis=1) - origin[:2]) / step_mm).astype(np.int64)
    c1 = np.floor((xy.max(axis=1) - origin[:2]) / step_mm).astype(np.int64)
    c0, c1 = np.clip(c0, 0, n[:2] - 1), np.clip(c1, -1, n[:2] - 1)
    span = np.maximum(c1 - c0 + 1, 0)
    count = span[:, 0] * span[:, 1]
    t = np.repeat(np.arange(len(faces)), count)
    local = np.arange(len(t)) - np.repeat(np.cumsum(count) - count, count)
    ix = c0[t, 0] + local // np.maximum(span[t, 1], 1)
    iy = c0[t, 1] + local % np.maximum(span[t, 1], 1)
    p = origin[:2] + step_mm * np.stack([ix, iy], axis=1)
    a, b, c = xy[t, 0], xy[t, 1], xy[t, 2]
    det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    ok = det != 0
    det = np.where(ok, det, 1.0)
    w1 = ((p[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (p[:, 1] - a[:, 1])) / det
    w2 = ((b[:, 0] - a[:, 0]) * (p[:, 1] - a[:, 1]) - (p[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])) / det
    hit = ok & (w1 >= 0) & (w2 >= 0) & (w1 + w2 <= 1)
    t, ix, iy, w1, w2 = t[hit], ix[hit], iy[hit], w1[hit], w2[hit]
    z = (1 - w1 - w2) * tri[t, 0, 2] + w1 * tri[t, 1, 2] + w2 * tri[t, 2, 2]
    # a crossing toggles inside/outside for every cell centre above it
    kz = np.clip(np.ceil((z - origin[2]) / step_mm).astype(np.int64), 0, n[2])
    toggles = np.zeros((n[0], n[1], n[2] + 1), dtype=np.int64)
    np.add.at(toggles, (ix, iy, kz), 1)
    inside = (np.cumsum(toggles, axis=2)[:, :, : n[2]] % 2) == 1
    idx = np.argwhere(inside)
    return origin + step_mm * idx


#: Node-count model coefficients: mm³ and mm² per node in units of the local size ``s``.
VOLUME_PER_NODE = 1.44
AREA_PER_NODE = 1.19
#: Nodes a mesh has beyond the size-field integral, whatever its size (see the module docstring).
OFFSET_NODES = 52.0
OFFSET_PER_PATCH = 6.3
OFFSET_REFINED = 58.0


class NodeCountModel:
    """Expected node count of a mesh of one surface as a function of the bulk edge length ``h``.

    ``n(h) = ∫ dV / (1.44 s³) + ∫ dA / (1.19 s²) + offset`` with ``s`` the size
    field at bulk size ``h`` (:func:`size_at`), integrated by a
    :class:`SizeFieldQuadrature` of the surface when there are refinement
    zones (exactly ``V / (1.44 h³) + A / (1.19 h²)`` without). ``n_patches``:
    the label patches of a conforming mesh (0 otherwise). The refinement
    offset ramps in from ``h`` = the finest zone edge (no refinement) to 1.5
    times it.
    """

    def __init__(self, volume: float, area: float, zones: list[RefinementZone] | None = None,
                 vertices: np.ndarray | None = None, faces: np.ndarray | None = None, n_patches: int = 0):
        self.volume, self.area = float(volume), float(area)
        self.zones = list(zones or [])
        self.n_patches = int(n_patches)
        self.quadrature = None
        if self.zones:
            if vertices is None or faces is None:
                raise ValueError("a node-count model with refinement zones needs the surface")
            self.quadrature = SizeFieldQuadrature(vertices, faces, self.zones, self.volume)

    def integral(self, h: float) -> float:
        """The size-field part ``∫ dV / (1.44 s³) + ∫ dA / (1.19 s²)``."""
        if self.quadrature is None or all(z.edge_mm >= h for z in self.zones):
            return self.volume / (VOLUME_PER_NODE * h**3) + self.area / (AREA_PER_NODE * h**2)
        iv, ia = self.quadrature.integrals(h)
        return iv / VOLUME_PER_NODE + ia / AREA_PER_NODE

    def offset(self, h: float) -> float:
        """The size-independent nodes: ``OFFSET_NODES`` + per patch + refinement (ramped in)."""
        off = OFFSET_NODES + OFFSET_PER_PATCH * self.n_patches
        finest = min((z.edge_mm for z in self.zones), default=np.inf)
        if h > finest:
            off += OFFSET_REFINED * min(1.0, 2.0 * (h / finest - 1.0))
        return off

    def expected(self, h: float, scale: float = 1.0, shift: float = 0.0) -> float:
        """``scale · integral(h) + offset(h) + shift`` (the mesher's corrections: ``scale``, ``shift``)."""
        return scale * self.integral(h) + self.offset(h) + shift

    def edge_for(self, target: float, scale: float = 1.0, shift: float = 0.0, h_max: float | None = None) -> float:
        """Solve ``expected(h) = target`` for ``h`` by bisection (log scale) in ``[1e-3, 2] V^(1/3)``
        (up to ``h_max``; ``h_max`` itself when even that gives more than ``target``)."""
        lo, hi = 1e-3 * self.volume ** (1 / 3), 2.0 * self.volume ** (1 / 3)
        if h_max is not None and h_max < hi:
            if self.expected(h_max, scale, shift) > target:
                return float(h_max)
            hi = h_max
        for _ in range(80):
            mid = np.sqrt(lo * hi)
            if self.expected(mid, scale, shift) > target:
                lo = mid
            else:
                hi = mid
        return float(np.sqrt(lo * hi))

    def uniform(self) -> NodeCountModel:
        """The same model without the refinement zones."""
        return NodeCountModel(self.volume, self.area, n_patches=self.n_patches)
