"""Tet-mesh clean-up: drop unused nodes, peel flat boundary slivers, relax interior slivers."""

from __future__ import annotations

import numpy as np

from liverforce.mesh.boundary import _OUTWARD_FACES, boundary_facets
from liverforce.mesh.quality import radius_ratio, signed_volumes

#: Tets below this radius ratio are slivers: peeled off the boundary (two or more boundary faces)
#: or relaxed (interior nodes moved) by the meshers.
PEEL_BOUND = 0.15


def compact(points: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop nodes no tet uses; renumber (order kept)."""
    used = np.zeros(len(points), dtype=bool)
    used[tets.ravel()] = True
    renum = np.cumsum(used) - 1
    return points[used], renum[tets]


def compact_with_ids(points, tets, ids):
    """:func:`compact`, carrying the original index of every kept node."""
    both, tets = compact(np.column_stack([points, ids]), tets)
    return np.ascontiguousarray(both[:, :3]), tets, both[:, 3].astype(np.int64)


def peel_boundary_slivers(points: np.ndarray, tets: np.ndarray, bound: float = PEEL_BOUND,
                          passes: int = 5) -> np.ndarray:
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


def relax_slivers(points: np.ndarray, tets: np.ndarray, bound: float = PEEL_BOUND, passes: int = 4) -> np.ndarray:
    """Move interior nodes of tets below radius ratio ``bound`` toward their neighbours' mean.

    A node moves (by 1, 1/2 or 1/4 of the way to the mean of the nodes of
    its star) only if the worst radius ratio of its star improves and no tet
    inverts; boundary nodes never move (the surface is kept). Slivers with a
    face on the boundary and an interior apex near that face's plane occur
    next to region borders of a conforming mesh, where gmsh's optimisers
    leave them. Returns new points (same topology).
    """
    points = np.array(points, dtype=np.float64, copy=True)
    fixed = np.zeros(len(points), dtype=bool)
    fixed[boundary_facets(tets).ravel()] = True
    order = np.argsort(tets.ravel(), kind="stable")
    owner = np.repeat(np.arange(len(tets)), 4)[order]
    start = np.searchsorted(tets.ravel()[order], np.arange(len(points) + 1))
    for _ in range(passes):
        rr = radius_ratio(points, tets)
        bad = np.flatnonzero(rr < bound)
        nodes = np.unique(tets[bad].ravel())
        nodes = nodes[~fixed[nodes]]
        if nodes.size == 0:
            break
        moved = False
        for v in nodes:
            star = owner[start[v]:start[v + 1]]
            q0 = radius_ratio(points, tets[star]).min()
            nbrs = np.unique(tets[star].ravel())
            target = points[nbrs[nbrs != v]].mean(axis=0)
            old = points[v].copy()
            for w in (1.0, 0.5, 0.25):
                points[v] = old + w * (target - old)
                if (signed_volumes(points, tets[star]) > 0).all() and radius_ratio(points, tets[star]).min() > q0:
                    moved = True
                    break
                points[v] = old
        if not moved:
            break
    return points
