"""Tetrahedron quality figures: orientation, radius ratio, dihedral angles."""

from __future__ import annotations

import numpy as np

#: Radius-ratio bound below which an element is counted as poor (``n_below_bound``).
DEFAULT_QUALITY_BOUND = 0.2


def signed_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed tetrahedron volumes (mm³), positive for positive orientation.

    Notes
    -----
    ``V = det[b − a, c − a, d − a] / 6`` for a tet ``(a, b, c, d)``.
    """
    a, b, c, d = (points[tets[:, i]] for i in range(4))
    return np.einsum("ij,ij->i", b - a, np.cross(c - a, d - a)) / 6.0


def orient_positive(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Return a copy of ``tets`` with every element positively oriented.

    Negative elements get their last two nodes swapped.  Raises
    ``ValueError`` if an element is degenerate (|V| ≤ 1e-12 · mean |V|).
    """
    tets = np.array(tets, dtype=np.int64, copy=True)
    vol = signed_volumes(points, tets)
    scale = np.abs(vol).mean() if len(vol) else 1.0
    flat = np.abs(vol) <= 1e-12 * scale
    if flat.any():
        raise ValueError(
            f"{int(flat.sum())} degenerate (zero-volume) tetrahedra, e.g. element "
            f"{int(np.flatnonzero(flat)[0])}: the mesh cannot be oriented"
        )
    neg = vol < 0
    tets[neg] = tets[neg][:, [0, 1, 3, 2]]
    return tets


def radius_ratio(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Normalised radius ratio ``ρ = 3 r_in / R_circ`` per tet (1 = regular).

    Notes
    -----
    ``r_in = 3|V| / Σ A_faces``; ``R_circ = sqrt((aA+bB+cC)(aA+bB−cC)
    (aA−bB+cC)(−aA+bB+cC)) / (24|V|)`` with ``a, A`` etc. the lengths of
    opposite edge pairs.  ρ → 0 for slivers, needles and caps alike.
    """
    p = [points[tets[:, i]] for i in range(4)]
    vol = np.abs(signed_volumes(points, tets))
    faces = [(1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1)]
    area = sum(0.5 * np.linalg.norm(np.cross(p[j] - p[i], p[k] - p[i]), axis=1) for i, j, k in faces)
    r_in = 3.0 * vol / np.maximum(area, 1e-300)

    def length(i: int, j: int) -> np.ndarray:
        return np.linalg.norm(p[i] - p[j], axis=1)

    aA = length(0, 1) * length(2, 3)
    bB = length(0, 2) * length(1, 3)
    cC = length(0, 3) * length(1, 2)
    prod = (aA + bB + cC) * (aA + bB - cC) * (aA - bB + cC) * (-aA + bB + cC)
    r_circ = np.sqrt(np.maximum(prod, 0.0)) / np.maximum(24.0 * vol, 1e-300)
    return np.where(vol > 0, 3.0 * r_in / np.maximum(r_circ, 1e-300), 0.0)


def dihedral_angles(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """The six interior dihedral angles (degrees) of each tet, ``(m, 6)``.

    Notes
    -----
    With outward unit face normals ``n_i, n_j`` of the two faces meeting at
    an edge, the interior dihedral angle is ``π − arccos(n_i · n_j)``.
    """
    p = [points[tets[:, i]] for i in range(4)]
    sign = np.sign(signed_volumes(points, tets))[:, None]
    # face opposite node i, outward for positive orientation
    faces = [(1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1)]
    normals = []
    for i, j, k in faces:
        n = np.cross(p[j] - p[i], p[k] - p[i]) * sign
        normals.append(n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300))
    pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    cos = np.stack([np.einsum("ij,ij->i", normals[a], normals[b]) for a, b in pairs], axis=1)
    return np.degrees(np.pi - np.arccos(np.clip(cos, -1.0, 1.0)))


def mesh_quality(points: np.ndarray, tets: np.ndarray, bound: float = DEFAULT_QUALITY_BOUND) -> dict:
    """Quality figures of a tetrahedral mesh (JSON-serialisable).

    Parameters
    ----------
    points : numpy.ndarray
        ``(n, 3)`` node coordinates, mm.
    tets : numpy.ndarray
        ``(m, 4)`` node indices.
    bound : float
        Radius-ratio bound; elements below it are counted in
        ``n_below_bound``.

    Returns
    -------
    dict
        ``n_nodes``, ``n_tets``, ``volume_mm3``, ``n_inverted`` (det ≤ 0),
        ``radius_ratio_min``, ``radius_ratio_mean`` (normalised ``3 r_in /
        R_circ``, 1 = regular), ``quality_bound``, ``n_below_bound``,
        ``min_dihedral_deg``, ``max_dihedral_deg``, ``edge_mean_mm``,
        ``edge_min_mm``, ``edge_max_mm``.
    """
    points = np.asarray(points, dtype=np.float64)
    tets = np.asarray(tets, dtype=np.int64)
    vol = signed_volumes(points, tets)
    rho = radius_ratio(points, tets)
    dih = dihedral_angles(points, tets)
    edges = np.concatenate([tets[:, [i, j]] for i, j in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))])
    edges = np.unique(np.sort(edges, axis=1), axis=0)
    elen = np.linalg.norm(points[edges[:, 0]] - points[edges[:, 1]], axis=1)
    return {
        "n_nodes": int(len(np.unique(tets))),
        "n_tets": int(len(tets)),
        "volume_mm3": float(vol.sum()),
        "n_inverted": int((vol <= 0).sum()),
        "radius_ratio_min": float(rho.min()),
        "radius_ratio_mean": float(rho.mean()),
        "quality_bound": float(bound),
        "n_below_bound": int((rho < bound).sum()),
        "min_dihedral_deg": float(dih.min()),
        "max_dihedral_deg": float(dih.max()),
        "edge_mean_mm": float(elen.mean()),
        "edge_min_mm": float(elen.min()),
        "edge_max_mm": float(elen.max()),
    }
