"""Per-triangle surface labels a mesher can follow: cleaning, patch majority, label borders.

A conforming mesh (route ``"labelled"`` of :func:`liverforce.mesh.tetra.tetrahedralise`)
turns the borders between labels into curves of the gmsh geometry; the labels
must first be free of one-triangle spikes and of pinches (a label touching
itself at a single vertex), which no patch parametrisation accepts.
"""

from __future__ import annotations

import numpy as np

__all__ = ["clean_labels", "label_boundary_edges", "patch_majority"]


def clean_labels(faces: np.ndarray, labels: np.ndarray, passes: int = 20) -> np.ndarray:
    """Labels a mesher can follow: no spikes, no patch touching itself at a single vertex.

    1. A triangle whose edge neighbours agree (two or three) on another label
       takes that label (removes one-triangle spikes and notches).
    2. At a vertex where a label occupies two or more separate sectors of the
       triangle fan (a "pinch", which no patch parametrisation accepts), the
       triangles of that label around the vertex take the fan's most common
       other label (ties: the smallest label), vertex by vertex in the order
       of ``vertex * n_labels + label``.
    Repeated until nothing changes (at most ``passes`` times). Changes are at
    the scale of one triangle of ``faces``.

    The edge adjacency, the neighbour table and the vertex fans depend on
    ``faces`` only: they are built once (vectorised), each pass only reads them.
    """
    faces = np.asarray(faces, dtype=np.int64)
    lab = np.asarray(labels, dtype=np.int64).copy()
    k = len(faces)
    if k == 0:
        return lab
    keys, ta, tb = _edge_pairs(faces)
    nbr = _neighbour_table(k, ta, tb)
    fan_start, fan_faces = _vertex_fans(faces)
    nl = int(lab.max()) + 1 if lab.size else 1
    v_of = faces.ravel()
    n_codes = (int(faces.max()) + 1) * nl
    ev = keys.ravel()  # both ends of every interior edge, edge by edge
    for _ in range(passes):
        changed = False
        # 1. majority of the edge neighbours
        nl_ = lab[nbr]
        agree = np.where(nl_[:, 0] == nl_[:, 1], nl_[:, 0], np.where(nl_[:, 1] == nl_[:, 2], nl_[:, 1],
                                                                     np.where(nl_[:, 0] == nl_[:, 2], nl_[:, 0], -1)))
        flip = (agree >= 0) & (agree != lab)
        if flip.any():
            lab[flip] = agree[flip]
            changed = True
        # 2. pinches: sectors(v, L) = #triangles(v, L) - #edges(v, L) between two L triangles
        n_t = np.bincount(v_of * nl + np.repeat(lab, 3), minlength=n_codes)
        la = lab[ta]
        same = np.repeat(la == lab[tb], 2)
        n_e = np.bincount((ev * nl + np.repeat(la, 2))[same], minlength=n_codes)
        pinch = np.flatnonzero(n_t - n_e >= 2)
        if pinch.size:
            for code in pinch:
                v, L = divmod(int(code), nl)
                fan = fan_faces[fan_start[v]:fan_start[v + 1]]
                fl = lab[fan]
                others = fl[fl != L]
                if others.size:
                    lab[fan[fl == L]] = np.bincount(others).argmax()
            changed = True
        if not changed:
            break
    return lab


def _neighbour_table(k: int, ta: np.ndarray, tb: np.ndarray) -> np.ndarray:
    """``(k, 3)`` edge neighbours of each triangle (-1 where an edge has none).

    Per triangle, its neighbours across the edges where it is ``ta`` (in edge
    order), then those where it is ``tb``.
    """
    t_all = np.concatenate([ta, tb])
    o_all = np.concatenate([tb, ta])
    order = np.argsort(t_all, kind="stable")
    t_s, o_s = t_all[order], o_all[order]
    start = np.searchsorted(t_s, np.arange(k))
    slot = np.arange(len(t_s)) - start[t_s]
    if slot.size and slot.max() >= 3:
        raise ValueError("surface is not manifold: a triangle has more than three edge neighbours")
    nbr = np.full((k, 3), -1, dtype=np.int64)
    nbr[t_s, slot] = o_s
    return nbr


def _vertex_fans(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """CSR fans: the triangles around vertex ``v`` are ``fan_faces[fan_start[v]:fan_start[v + 1]]`` (ascending)."""
    n_v = int(faces.max()) + 1
    v_of = faces.ravel()
    order = np.argsort(v_of, kind="stable")
    tri = order // 3
    # a degenerate triangle repeating a vertex appears once in that vertex's fan
    keep = np.ones(len(order), dtype=bool)
    sv = v_of[order]
    keep[1:] = (sv[1:] != sv[:-1]) | (tri[1:] != tri[:-1])
    counts = np.bincount(sv[keep], minlength=n_v)
    fan_start = np.concatenate([[0], np.cumsum(counts)])
    return fan_start, tri[keep]


def patch_majority(patches: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Per-face label = the most common label of the face's patch."""
    out = labels.copy()
    for p in np.unique(patches):
        sel = patches == p
        out[sel] = np.bincount(labels[sel]).argmax()
    return out


def label_boundary_edges(faces: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Edges ``(e, 2)`` shared by two triangles of different labels."""
    k, a, b = _edge_pairs(faces)
    return k[labels[a] != labels[b]]


def _edge_pairs(faces: np.ndarray):
    """Interior edges of a closed triangulation: (edge keys (e, 2), triangle a (e,), triangle b (e,))."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    owner = np.tile(np.arange(len(faces)), 3)
    key = np.sort(edges, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, owner = key[order], owner[order]
    same = np.all(key[1:] == key[:-1], axis=1)
    return key[:-1][same], owner[:-1][same], owner[1:][same]

