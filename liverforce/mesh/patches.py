"""Split a closed surface into two disc-like patches for gmsh's reparametrisation.

gmsh remeshes a discrete surface by parametrising patches that must be
topological discs.  Cutting a genus-0 surface along one smooth loop gives
two discs; the loop is the median level set of the Fiedler vector (second
eigenvector of the vertex-graph Laplacian), i.e. a cut across the longest
direction of an elongated body.
"""

from __future__ import annotations

import numpy as np


class PatchError(RuntimeError):
    """The surface could not be split into two discs (the caller falls back)."""


def two_patch_labels(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Split a closed genus-0 surface in two disc-like, connected patches.

    Notes
    -----
    The cut is the median level set of the Fiedler vector (second
    eigenvector of the vertex-graph Laplacian), which for elongated shapes is
    a smooth loop across the longest direction.  Raises :class:`PatchError`
    if a patch is not a single disc (then the caller falls back to gmsh's
    own classification).
    """
    import scipy.sparse as sp
    import scipy.sparse.linalg as sla
    from scipy.sparse.csgraph import connected_components

    n = len(vertices)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    adj = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
    adj = ((adj + adj.T) > 0).astype(np.float64)
    lap = sp.diags(np.asarray(adj.sum(axis=1)).ravel()) - adj
    v0 = vertices[:, np.argmax(np.ptp(vertices, axis=0))] - vertices.mean(axis=0)[np.argmax(np.ptp(vertices, axis=0))]
    try:
        w, vec = sla.eigsh(lap.tocsc(), k=2, sigma=-1e-3, which="LM", v0=v0)
    except Exception as exc:  # ARPACK failure
        raise PatchError(f"Fiedler vector failed ({exc})") from exc
    fiedler = vec[:, np.argsort(w)[1]]
    value = fiedler[faces].mean(axis=1)
    labels = (value > np.median(value)).astype(np.int64)
    # keep each label connected: small stray islands join the other label
    fa = _face_adjacency(faces)
    for _ in range(4):
        changed = False
        for lab in (0, 1):
            idx = np.flatnonzero(labels == lab)
            sub = fa[idx][:, idx]
            ncomp, comp = connected_components(sub, directed=False)
            if ncomp > 1:
                keep = np.argmax(np.bincount(comp))
                labels[idx[comp != keep]] = 1 - lab
                changed = True
        if not changed:
            break
    for lab in (0, 1):
        loops = _boundary_loop_count(faces[labels == lab])
        if loops != 1:
            raise PatchError(f"two-patch split gave a patch with {loops} boundary loops (not a disc)")
    return labels


def cut_loop(patch_faces: np.ndarray) -> np.ndarray:
    """Boundary loop of a disc patch as an ordered vertex array, starting at its smallest index."""
    half = np.concatenate([patch_faces[:, [0, 1]], patch_faces[:, [1, 2]], patch_faces[:, [2, 0]]])
    _, inv, counts = np.unique(np.sort(half, axis=1), axis=0, return_inverse=True, return_counts=True)
    bnd = half[counts[inv.ravel()] == 1]
    nxt = dict(zip(bnd[:, 0].tolist(), bnd[:, 1].tolist()))
    if len(nxt) != len(bnd):
        raise PatchError("two-patch cut loop touches itself")
    start = int(bnd[:, 0].min())
    loop, cur = [start], nxt[start]
    while cur != start and len(loop) <= len(bnd):
        loop.append(cur)
        cur = nxt[cur]
    if len(loop) != len(bnd):
        raise PatchError("two-patch cut is not a single simple loop")
    return np.asarray(loop, dtype=np.int64)


def _face_adjacency(faces: np.ndarray):
    """Sparse face-face adjacency through shared edges."""
    import scipy.sparse as sp

    m = len(faces)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    key = np.sort(edges, axis=1)
    owner = np.tile(np.arange(m), 3)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, owner = key[order], owner[order]
    same = np.all(key[1:] == key[:-1], axis=1)
    a, b = owner[:-1][same], owner[1:][same]
    adj = sp.coo_matrix((np.ones(len(a)), (a, b)), shape=(m, m)).tocsr()
    return adj + adj.T


def _boundary_loop_count(faces: np.ndarray) -> int:
    """Number of boundary loops of an open triangle patch (0 if closed)."""
    from scipy.sparse.csgraph import connected_components
    import scipy.sparse as sp

    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    bnd = uniq[counts == 1]
    if len(bnd) == 0:
        return 0
    verts, inv = np.unique(bnd.ravel(), return_inverse=True)
    inv = inv.reshape(-1, 2)
    g = sp.coo_matrix((np.ones(len(inv)), (inv[:, 0], inv[:, 1])), shape=(len(verts), len(verts)))
    ncomp, _ = connected_components(g, directed=False)
    return int(ncomp)


def disc_patches(vertices: np.ndarray, faces: np.ndarray, labels: np.ndarray, max_depth: int = 8) -> np.ndarray:
    """Split a labelled closed surface into disc-like patches of one label each.

    Each connected piece of a label that is not a topological disc (one
    boundary loop, Euler characteristic 1) is cut in two along the median
    level set of its own Fiedler vector, recursively (up to ``max_depth``
    levels). Returns a patch id per face (0, 1, ...); a piece that cannot be
    cut is left as it is (the mesher may still split it).
    """
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    faces = np.asarray(faces, dtype=np.int64)
    labels = np.asarray(labels, dtype=np.int64)
    fa = _face_adjacency(faces).tocsr()
    rows, cols = fa.nonzero()
    same = labels[rows] == labels[cols]
    g = sp.coo_matrix((np.ones(same.sum()), (rows[same], cols[same])), shape=fa.shape)
    _, comp = connected_components(g, directed=False)
    todo = [np.flatnonzero(comp == c) for c in np.unique(comp)]
    done: list[np.ndarray] = []
    depth = {0: todo}
    for level in range(max_depth + 1):
        nxt = []
        for idx in depth.get(level, []):
            if _is_disc(faces[idx]) or level == max_depth:
                done.append(idx)
                continue
            parts = _fiedler_split(vertices, faces, idx, fa)
            if parts is None:
                done.append(idx)
            else:
                nxt.extend(parts)
        if not nxt:
            break
        depth[level + 1] = nxt
    out = np.empty(len(faces), dtype=np.int64)
    for k, idx in enumerate(sorted(done, key=lambda a: int(a.min()))):
        out[idx] = k
    return out


def _is_disc(patch_faces: np.ndarray) -> bool:
    """One boundary loop, Euler characteristic 1 and no vertex where the boundary touches itself."""
    edges = np.sort(np.concatenate([patch_faces[:, [0, 1]], patch_faces[:, [1, 2]], patch_faces[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    nv = len(np.unique(patch_faces))
    if nv - len(uniq) + len(patch_faces) != 1 or _boundary_loop_count(patch_faces) != 1:
        return False
    bnd = uniq[counts == 1]
    return bool((np.bincount(bnd.ravel()) <= 2).all())


def _fiedler_split(vertices, faces, idx, fa):
    """Two connected halves of the face set ``idx`` (median Fiedler level set), or None."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as sla
    from scipy.sparse.csgraph import connected_components

    if len(idx) < 8:
        return None
    sub = faces[idx]
    verts, inv = np.unique(sub.ravel(), return_inverse=True)
    tri = inv.reshape(-1, 3)
    n = len(verts)
    e = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    adj = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
    adj = ((adj + adj.T) > 0).astype(np.float64)
    lap = (sp.diags(np.asarray(adj.sum(axis=1)).ravel()) - adj).tocsc()
    p = vertices[verts]
    axis = int(np.argmax(np.ptp(p, axis=0)))
    try:
        w, vec = sla.eigsh(lap, k=2, sigma=-1e-3, which="LM", v0=p[:, axis] - p[:, axis].mean())
    except Exception:  # ARPACK failure: leave the piece whole
        return None
    value = vec[:, np.argsort(w)[1]][tri].mean(axis=1)
    half = value > np.median(value)
    sfa = fa[idx][:, idx]
    parts = []
    for side in (half, ~half):
        loc = np.flatnonzero(side)
        if loc.size == 0:
            return None
        ncomp, comp = connected_components(sfa[loc][:, loc], directed=False)
        parts.append((loc, ncomp, comp))
    # strays (small components) join the other half
    assign = half.copy()
    for flag, (loc, ncomp, comp) in zip((True, False), parts):
        if ncomp > 1:
            keep = np.argmax(np.bincount(comp))
            assign[loc[comp != keep]] = not flag
    a, b = idx[assign], idx[~assign]
    if len(a) == 0 or len(b) == 0:
        return None
    return [a, b]
