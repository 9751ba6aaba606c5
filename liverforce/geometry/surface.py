"""A closed triangle surface in millimetres: the output of the geometry stage.

A :class:`Surface` is the hand-over between the geometry stage (procedural
livers, importers) and the mesh stage (tetrahedralisation).  It carries the
vertices in mm, the triangles (outward oriented by the right-hand rule), and a
JSON-serialisable ``meta`` dict with provenance (source, hash, units/scale,
generator seed and parameters, repairs done).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class Surface:
    """Closed, outward-oriented triangle surface.

    Parameters
    ----------
    vertices : numpy.ndarray
        ``(n, 3)`` float64 vertex coordinates in mm.
    faces : numpy.ndarray
        ``(k, 3)`` int64 vertex indices per triangle, counter-clockwise when
        seen from outside (normals by the right-hand rule point outward).
    meta : dict
        JSON-serialisable provenance (e.g. ``source``, ``sha256``,
        ``scale_to_mm``, ``seed``, ``params``, ``repairs``).
    """

    vertices: np.ndarray
    faces: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int64)
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3:
            raise ValueError(f"vertices must be (n, 3), got {self.vertices.shape}")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise ValueError(f"faces must be (k, 3), got {self.faces.shape}")

    @property
    def bbox_mm(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box ``(min, max)`` in mm."""
        return self.vertices.min(axis=0), self.vertices.max(axis=0)

    @property
    def extent_mm(self) -> np.ndarray:
        """Bounding-box edge lengths ``(3,)`` in mm."""
        lo, hi = self.bbox_mm
        return hi - lo

    @property
    def volume_mm3(self) -> float:
        """Signed enclosed volume in mm³ (positive for outward orientation).

        Notes
        -----
        Divergence theorem: ``V = Σ_f (a·(b×c)) / 6`` over triangles
        ``(a, b, c)``; exact for a closed polyhedral surface.
        """
        return signed_volume(self.vertices, self.faces)

    @property
    def area_mm2(self) -> float:
        """Total surface area in mm²."""
        return float(triangle_areas(self.vertices, self.faces).sum())

    def to_trimesh(self):
        """Return a :class:`trimesh.Trimesh` view (no processing, no merging)."""
        import trimesh

        return trimesh.Trimesh(self.vertices.copy(), self.faces.copy(), process=False)


def triangle_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Areas (mm²) of the triangles ``faces`` over ``vertices``."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume (mm³) enclosed by a closed triangle surface.

    Notes
    -----
    ``V = (1/6) Σ a·(b×c)``; the result is translation invariant only for a
    closed surface, so the vertices are centred first for round-off.
    """
    v = vertices - vertices.mean(axis=0)
    a, b, c = (v[faces[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)
