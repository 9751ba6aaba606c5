"""Tet-mesh clean-up: drop unused nodes, peel flat boundary slivers."""

from __future__ import annotations

import numpy as np

from liverforce.mesh.boundary import _OUTWARD_FACES
from liverforce.mesh.quality import radius_ratio


def compact(points: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop nodes no tet uses; renumber (order kept)."""
    used = np.zeros(len(points), dtype=bool)
    used[tets.ravel()] = True
    renum = np.cumsum(used) - 1
    return points[used], renum[tets]


def peel_boundary_slivers(points: np.ndarray, tets: np.ndarray, bound: float = 0.15, passes: int = 5) -> np.ndarray:
    """Remove flat tets lying on the boundary (radius ratio < ``bound``).

    A tet is peeled if it has at least two faces on the boundary: such tets
    are flat wedges across a surface crease that no interior optimisation can
    fix.  Removing one exposes its other faces and loses only its (≈ 0)
    volume.  One pass peels slivers that share no node; a pass that would
    leave a boundary edge with more than two faces is not applied.  Up to
    ``passes`` passes.
    """
    for _ in range(passes):
        rho = radius_ratio(points, tets)
        cand = np.flatnonzero(rho < bound)
        if len(cand) == 0:
            break
        faces = np.sort(tets[:, _OUTWARD_FACES].reshape(-1, 3), axis=1)
        _, inv, counts = np.unique(faces, axis=0, return_inverse=True, return_counts=True)
        on_boundary = (counts[inv.ravel()] == 1).reshape(-1, 4).sum(axis=1)
        peel = cand[on_boundary[cand] >= 2]
        if len(peel) == 0:
            break
        # peel non-adjacent slivers only in one pass (keeps the boundary manifold)
        keep = np.ones(len(tets), dtype=bool)
        taken: set[int] = set()
        for t in peel:
            nodes = set(tets[t].tolist())
            if nodes & taken:
                continue
            keep[t] = False
            taken |= nodes
        if not _manifold_boundary(tets[keep]):
            break  # this pass would pinch the surface: keep the slivers instead
        tets = tets[keep]
    return tets


def _manifold_boundary(tets: np.ndarray) -> bool:
    """True if every boundary edge has exactly two boundary faces."""
    faces = tets[:, _OUTWARD_FACES].reshape(-1, 3)
    _, inv, counts = np.unique(np.sort(faces, axis=1), axis=0, return_inverse=True, return_counts=True)
    bnd = faces[counts[inv.ravel()] == 1]
    edges = np.sort(np.concatenate([bnd[:, [0, 1]], bnd[:, [1, 2]], bnd[:, [2, 0]]]), axis=1)
    _, ecount = np.unique(edges, axis=0, return_counts=True)
    return bool((ecount == 2).all())
