"""Mesh size: refinement zones and the node-count model that turns a node count into an edge length.

The model is ``n ≈ k (V / (1.44 h³) + A / (1.19 h²))`` (fitted on livers)
plus what each refinement zone adds; the mesher corrects ``k`` from the
counts it obtains (:func:`liverforce.mesh.gmsh_mesher.mesh_route`).
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


def expected_nodes(h: float, volume: float, area: float, refine: list[RefinementZone]) -> float:
    """Node-count model ``V/(1.44 h³) + A/(1.19 h²)`` + refined zones.

    A zone of isolated points adds refined half balls; a zone whose points
    cover a surface patch densely (closer than their reach) adds a refined
    layer: its surface at ``edge_mm`` plus the volume under it.
    """
    n = volume / (1.44 * h**3) + area / (1.19 * h**2)
    for z in refine:
        if z.edge_mm >= h:
            continue
        hf = z.edge_mm
        t = (h - hf) / z.growth
        reach = z.radius_mm + t
        r = np.linspace(0.0, reach, 200)
        size = np.clip(hf + (r - z.radius_mm) / max(t, 1e-9) * (h - hf), hf, h)
        balls = _disjoint_balls(z.points, reach)
        if balls >= 0.5 * len(z.points):
            n += len(z.points) * np.trapezoid(2.0 * np.pi * r**2 * (1.0 / size**3 - 1.0 / h**3), r) / 1.44
        else:
            patch = _covered_area(z.points, hf)
            n += patch * ((1.0 / hf**2 - 1.0 / h**2) / 1.19 + np.trapezoid(1.0 / size**3 - 1.0 / h**3, r) / 1.44)
    return float(n)


def edge_for_nodes(target: int, k: float, volume: float, area: float, refine: list[RefinementZone]) -> float:
    """Solve ``k · expected_nodes(h) = target`` for ``h`` by bisection (log scale)."""
    lo, hi = 1e-3 * volume ** (1 / 3), 2.0 * volume ** (1 / 3)
    for _ in range(80):
        mid = np.sqrt(lo * hi)
        if k * expected_nodes(mid, volume, area, refine) > target:
            lo = mid
        else:
            hi = mid
    return float(np.sqrt(lo * hi))


def _disjoint_balls(points: np.ndarray, radius: float) -> float:
    """Effective number of balls of ``radius`` around ``points`` (area covered / one disc)."""
    if len(points) <= 1 or radius <= 0:
        return float(len(points))
    cell = max(radius, 1e-9)
    occupied = len(np.unique(np.floor(points / cell).astype(np.int64), axis=0))
    return float(min(len(points), occupied * cell**2 / (np.pi * radius**2)))


def _covered_area(points: np.ndarray, cell: float) -> float:
    """Area (mm²) of the surface patch sampled by ``points`` (occupied cells of a grid, ~1.5 per cell² of area)."""
    cell = max(cell, 1e-6)
    return len(np.unique(np.floor(points / cell).astype(np.int64), axis=0)) * cell**2 / 1.5
