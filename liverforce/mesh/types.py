"""The mesh artifact handed to the FE, dataset and learning stages."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: Facet region codes (``LiverMesh.facet_region``).
REGION_CODES = {"free": 0, "ivc": 1, "ligament": 2, "visceral": 3, "rib": 4}
#: Inverse of :data:`REGION_CODES`.
REGION_NAMES = {v: k for k, v in REGION_CODES.items()}


@dataclass
class LiverMesh:
    """Tetrahedral liver mesh with tagged boundary facets (mm).

    Parameters
    ----------
    points : numpy.ndarray
        ``(n, 3)`` float64 node coordinates, mm.
    tets : numpy.ndarray
        ``(m, 4)`` int64 node indices, positively oriented
        (``det[b−a, c−a, d−a] > 0``).
    facets : numpy.ndarray
        ``(k, 3)`` int64 boundary triangles (faces of exactly one tet),
        outward normals by the right-hand rule.
    facet_region : numpy.ndarray
        ``(k,)`` int8 region code per facet, see :data:`REGION_CODES`:
        0 free, 1 IVC patch (fixed), 2 ligaments (elastic foundation),
        3 lower visceral face (elastic foundation), 4 rib contact (no normal
        motion, free sliding).
    facet_visible : numpy.ndarray
        ``(k,)`` bool, facets where tool exertion points may lie (always
        ``facet_region == 0``).
    meta : dict
        JSON-serialisable provenance (surface source/seed, meshing
        parameters, region parameters, quality).
    facet_support : numpy.ndarray, optional
        ``(k,)`` int64, which of the user's supports (``meta["supports"]``,
        in order) holds each facet, -1 where none does (a free facet, or an
        auto-tagged region beneath them under ``mode: add``); None for a mesh
        without user supports. What the regions picture names each support's
        facets by; stored in the VTU as the cell-data array ``support``
        (:mod:`liverforce.mesh.io`; a file without it reads back as None).
    """

    points: np.ndarray
    tets: np.ndarray
    facets: np.ndarray
    facet_region: np.ndarray
    facet_visible: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)
    facet_support: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.points = np.ascontiguousarray(self.points, dtype=np.float64)
        self.tets = np.ascontiguousarray(self.tets, dtype=np.int64)
        self.facets = np.ascontiguousarray(self.facets, dtype=np.int64)
        self.facet_region = np.ascontiguousarray(self.facet_region, dtype=np.int8)
        self.facet_visible = np.ascontiguousarray(self.facet_visible, dtype=bool)
        if self.facet_support is not None:
            self.facet_support = np.ascontiguousarray(self.facet_support, dtype=np.int64)

    @property
    def n_nodes(self) -> int:
        return int(len(self.points))

    @property
    def n_tets(self) -> int:
        return int(len(self.tets))

    def validate(self) -> None:
        """Check the data contract; raise ``ValueError`` naming the first breach."""
        from liverforce.mesh.boundary import boundary_facets
        from liverforce.mesh.quality import signed_volumes

        n, k = len(self.points), len(self.facets)
        if self.points.ndim != 2 or self.points.shape[1] != 3:
            raise ValueError(f"points must be (n, 3), got {self.points.shape}")
        if self.tets.ndim != 2 or self.tets.shape[1] != 4 or len(self.tets) == 0:
            raise ValueError(f"tets must be (m, 4) with m > 0, got {self.tets.shape}")
        if self.tets.min() < 0 or self.tets.max() >= n:
            raise ValueError("tet indices out of range")
        if self.facet_region.shape != (k,) or self.facet_visible.shape != (k,):
            raise ValueError("facet_region and facet_visible must have one entry per facet")
        if not np.isin(self.facet_region, list(REGION_CODES.values())).all():
            raise ValueError(f"facet_region values must be in {sorted(REGION_CODES.values())}")
        if (signed_volumes(self.points, self.tets) <= 0).any():
            raise ValueError("tets must all be positively oriented")
        if not np.array_equal(_canonical(boundary_facets(self.tets)), _canonical(self.facets)):
            raise ValueError("facets are not the outward-oriented boundary faces of the tets")
        if (self.facet_visible & (self.facet_region != 0)).any():
            raise ValueError("visible facets must all be free (region 0)")
        if self.facet_support is not None:
            if self.facet_support.shape != (k,):
                raise ValueError("facet_support must have one entry per facet")
            if ((self.facet_support >= 0) & (self.facet_region == 0)).any():
                raise ValueError("facets held by a user support (facet_support >= 0) must not be free (region 0)")


def _canonical(tris: np.ndarray) -> np.ndarray:
    """Triangles rotated to start at their smallest index (winding kept), rows sorted."""
    tris = np.asarray(tris, dtype=np.int64)
    shift = np.argmin(tris, axis=1)
    idx = (shift[:, None] + np.arange(3)[None, :]) % 3
    rot = np.take_along_axis(tris, idx, axis=1)
    return rot[np.lexsort(rot.T[::-1])]
