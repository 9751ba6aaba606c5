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
       other label.
    Repeated until nothing changes (at most ``passes`` times). Changes are at
    the scale of one triangle of ``faces``.
    """
    faces = np.asarray(faces, dtype=np.int64)
    lab = np.asarray(labels, dtype=np.int64).copy()
    _, ta, tb = _edge_pairs(faces)
    k = len(faces)
    nl = int(lab.max()) + 1 if lab.size else 1
    for _ in range(passes):
        changed = False
        # 1. majority of the edge neighbours
        nbr = np.full((k, 3), -1, dtype=np.int64)
        fill = np.zeros(k, dtype=np.int64)
        for x, y in ((ta, tb), (tb, ta)):
            for t, o in zip(x, y):
                nbr[t, fill[t]] = o
                fill[t] += 1
        nl_ = lab[nbr]
        agree = np.where(nl_[:, 0] == nl_[:, 1], nl_[:, 0], np.where(nl_[:, 1] == nl_[:, 2], nl_[:, 1],
                                                                     np.where(nl_[:, 0] == nl_[:, 2], nl_[:, 0], -1)))
        flip = (agree >= 0) & (agree != lab)
        if flip.any():
            lab[flip] = agree[flip]
            changed = True
        # 2. pinches: sectors(v, L) = #triangles(v, L) - #edges(v, L) between two L triangles
        v_of = faces.ravel()
        code_t = v_of * nl + np.repeat(lab, 3)
        n_t = np.bincount(code_t, minlength=len(v_of) and (faces.max() + 1) * nl)
        same = lab[ta] == lab[tb]
        keys, _, _ = _edge_pairs(faces)
        ev = keys[same].ravel()
        code_e = ev * nl + np.repeat(lab[ta][same], 2)
        n_e = np.bincount(code_e, minlength=n_t.size)
        pinch = np.flatnonzero(n_t - n_e >= 2)
        if pinch.size:
            for code in pinch:
                v, L = divmod(int(code), nl)
                fan = np.flatnonzero((faces == v).any(axis=1))
                mine = fan[lab[fan] == L]
                others = lab[fan][lab[fan] != L]
                if others.size:
                    lab[mine] = np.bincount(others).argmax()
            changed = True
        if not changed:
            break
    return lab


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

