"""Boundary facets of a tetrahedral mesh, outward oriented."""

from __future__ import annotations

import numpy as np

#: Faces of a positively oriented tet ``(a, b, c, d)`` with outward normals
#: (right-hand rule): the face opposite node i is ``_OUTWARD_FACES[i]``.
_OUTWARD_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


def boundary_facets(tets: np.ndarray) -> np.ndarray:
    """Triangles that belong to exactly one tet, with outward normals.

    Parameters
    ----------
    tets : numpy.ndarray
        ``(m, 4)`` int, **positively oriented** tetrahedra.

    Returns
    -------
    numpy.ndarray
        ``(k, 3)`` int64 boundary triangles, ordered by the owning tet then
        the local face, counter-clockwise seen from outside.

    Raises
    ------
    ValueError
        If a face is shared by more than two tets (non-conforming mesh).
    """
    tets = np.asarray(tets, dtype=np.int64)
    faces = tets[:, _OUTWARD_FACES].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    if (counts > 2).any():
        raise ValueError(f"{int((counts > 2).sum())} faces shared by more than two tetrahedra")
    return faces[counts[inverse] == 1]


def facet_normals(points: np.ndarray, facets: np.ndarray, unit: bool = True) -> np.ndarray:
    """Right-hand-rule normals of triangles ``(k, 3)``; unit length if ``unit``.

    Non-unit normals have length twice the triangle area (mm²).
    """
    a, b, c = (points[facets[:, i]] for i in range(3))
    n = np.cross(b - a, c - a)
    if unit:
        n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    return n
