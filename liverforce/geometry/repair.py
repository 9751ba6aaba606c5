"""Checks and conservative repairs of triangle surfaces.

:func:`repair_surface` turns a raw triangle soup into a closed, manifold,
consistently outward-oriented surface or refuses it with a
:class:`~liverforce.geometry.errors.GeometryError`.  Each repair it makes is
reported as one human-readable message:

=====================================  =====================================
defect                                 outcome
=====================================  =====================================
no triangles / non-finite coordinates  refused
duplicate vertices                     merged (reported, except the corners an
                                       STL stores apart for each triangle:
                                       ``corners_apart``, reading, no repair)
triangles with a repeated vertex       removed ("degenerate triangles removed")
duplicate triangles                    removed (reported)
edges shared by > 2 triangles          a few (≤ ``max_non_manifold_fraction``
(non-manifold)                         of the edges): dangling triangles on
                                       them (fins: a triangle with an open
                                       edge) removed; triangles around the
                                       edges still shared > 2 times cut out,
                                       their hole re-filled below, if they are
                                       ≤ ``max_cut_fraction`` of the area
                                       ("non-manifold edges repaired");
                                       more: refused
zero-area triangles (three distinct    removed by splitting the neighbour
but collinear vertices)                across the long edge at the middle
                                       vertex (the surface stays closed), or
                                       dropped when there is none
                                       ("zero-area triangles repaired");
                                       more than ``max(10, 1 %)``: refused
several disconnected components        smaller ones dropped if each is
                                       < ``component_ratio`` of the largest
                                       ("largest component kept"), else refused
holes (boundary loops)                 filled by a fan from the loop centroid
                                       ("holes filled") unless the holes are
                                       large (> ``max_hole_fraction``), else refused
inconsistent winding                   made consistent (reported)
all normals inward                     flipped ("normals flipped")
self-intersecting triangles            local ones: the triangles round them
                                       replaced by MeshFix, the rest of the
                                       surface kept exactly; a voxel remesh
                                       of the whole surface only if that
                                       fails (reported); many: refused
=====================================  =====================================
"""

from __future__ import annotations

import numpy as np

from liverforce.geometry.errors import refuse
from liverforce.geometry.surface import signed_volume, triangle_areas


def repair_surface(
    vertices: np.ndarray,
    faces: np.ndarray,
    path=None,
    *,
    component_ratio: float = 0.1,
    max_hole_fraction: float = 0.2,
    check_self_intersections: bool = True,
    remesh_self_intersections: bool = True,
    max_intersecting_fraction: float = 0.02,
    max_non_manifold_fraction: float = 0.01,
    max_cut_fraction: float = 0.02,
    unit: str = "mm",
    locate=None,
    corners_apart: bool = False,
) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Check and repair a triangle surface (units unchanged).

    Parameters
    ----------
    vertices, faces : numpy.ndarray
        ``(n, 3)`` coordinates and ``(k, 3)`` 0-based triangle indices.
    path : str or Path, optional
        Source file, named in every message.
    component_ratio : float
        Smaller components are dropped only if each has less than this
        fraction of the largest component's area; otherwise refused.
    max_hole_fraction : float
        Holes are filled only if the added area is at most this fraction
        of the surface area.
    check_self_intersections : bool
        Run the (vectorised, O(k log k)) triangle–triangle intersection test.
    remesh_self_intersections : bool
        Repair *local* self-intersections (at most ``max_intersecting_fraction``
        of the triangles, or 10 pairs): by :func:`local_self_intersection_repair`
        (only the triangles round them change), or where that fails by
        :func:`voxel_remesh` (the whole surface, details below ~2 voxels lost);
        otherwise refuse.
    max_intersecting_fraction : float
        See above.
    max_non_manifold_fraction : float
        Non-manifold edges are repaired only if at most this fraction of the
        edges (and at least 20 are always allowed); otherwise refused.
    max_cut_fraction : float
        Triangles cut out around non-manifold edges may be at most this
        fraction of the surface area; otherwise refused.
    unit : str
        Unit of the coordinates, for messages.
    locate : callable, optional
        ``point (3,) -> str``: where a point of ``vertices`` lies in the file as given (its own units and
        frame); the messages that name a place add it (``load_surface`` passes one whenever it converted).
    corners_apart : bool
        The file's format stores each triangle's three corners apart (STL): a vertex shared by six
        triangles is written six times, so merging them is how the surface is read, not the repair of a
        broken file, and is not reported. Every other repair still is.

    Returns
    -------
    vertices, faces, messages
        Closed, manifold, outward-oriented surface and the repairs made.

    Raises
    ------
    GeometryError
        When the surface cannot be repaired safely.
    """
    import trimesh

    msgs: list[str] = []
    vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) == 0:
        raise refuse(path, "the file contains no triangles (or no cells that form a surface)",
                     "Export a closed triangle surface of the liver")
    if not np.isfinite(vertices).all():
        raise refuse(path, f"{int((~np.isfinite(vertices)).any(axis=1).sum())} vertices have NaN/inf "
                           "coordinates", "Re-export the surface")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise refuse(path, "triangle indices out of range", "The file is corrupted; re-export it")

    used = np.unique(faces)
    if len(used) < len(vertices):  # e.g. interior nodes of a volume mesh: not a defect
        remap = np.full(len(vertices), -1, dtype=np.int64)
        remap[used] = np.arange(len(used))
        vertices, faces = vertices[used], remap[faces]
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    n_before = len(mesh.vertices)
    mesh.merge_vertices(merge_tex=True, merge_norm=True)
    if len(mesh.vertices) < n_before and not corners_apart:
        msgs.append(f"merged {n_before - len(mesh.vertices)} duplicate vertices")
    f = np.asarray(mesh.faces)
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    if repeated.any():
        mesh.update_faces(~repeated)
        msgs.append(f"degenerate triangles removed ({int(repeated.sum())} with a repeated vertex)")
    if len(mesh.faces) == 0:
        raise refuse(path, "all triangles are degenerate", "Export a valid closed triangle surface")
    key = np.sort(np.asarray(mesh.faces), axis=1)
    _, first = np.unique(key, axis=0, return_index=True)
    if len(first) < len(mesh.faces):
        keep = np.zeros(len(mesh.faces), dtype=bool)
        keep[first] = True
        msgs.append(f"duplicate triangles removed ({int((~keep).sum())})")
        mesh.update_faces(keep)
    mesh.remove_unreferenced_vertices()

    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = _repair_non_manifold(v, np.asarray(mesh.faces, dtype=np.int64), path, max_non_manifold_fraction,
                             max_cut_fraction, msgs)
    f = _repair_zero_area(v, f, path, unit, msgs, locate)
    if len(f) == 0:
        raise refuse(path, "no triangles left after removing the defective ones", "Re-export the surface")
    mesh = trimesh.Trimesh(v, f, process=False)
    mesh.remove_unreferenced_vertices()
    mesh = _keep_largest_component(mesh, path, component_ratio, msgs)

    if not mesh.is_winding_consistent:
        before = np.asarray(mesh.faces).copy()
        trimesh.repair.fix_winding(mesh)
        changed = int(np.any(np.asarray(mesh.faces) != before, axis=1).sum())
        if not mesh.is_winding_consistent:
            raise refuse(path, "triangle winding cannot be made consistent (non-orientable surface)",
                         "Repair the surface (e.g. MeshLab 'Re-Orient all faces coherently')")
        msgs.append(f"winding made consistent ({changed} triangles flipped)")

    if not mesh.is_watertight:
        mesh = _fill_holes(mesh, path, max_hole_fraction, msgs)

    v, fc = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
    vol = signed_volume(v, fc)
    if vol < 0:
        fc = fc[:, ::-1].copy()
        msgs.append("normals flipped (all triangles faced inward)")
    elif vol == 0:
        raise refuse(path, "the surface encloses zero volume", "Export a closed surface of a solid")

    if check_self_intersections:
        pairs = self_intersections(v, fc)
        if len(pairs):
            where = _at(v[fc[pairs[0, 0]]].mean(axis=0), unit, locate)
            local = len(pairs) <= max(10, int(max_intersecting_fraction * len(fc)))
            if not (remesh_self_intersections and local):
                raise refuse(
                    path,
                    f"the surface intersects itself ({len(pairs)} intersecting triangle pairs, e.g. near "
                    f"{where})" + ("" if local else "; too many to repair by remeshing"),
                    "Repair it (e.g. MeshLab 'Select Self Intersecting Faces' then remesh, or "
                    "re-segment) before meshing",
                )
            local_fix = local_self_intersection_repair(v, fc)
            if local_fix is not None:
                v, fc, n_removed, n_added = local_fix
                msgs.append(
                    f"self-intersections removed locally ({len(pairs)} intersecting triangle pairs near {where}: "
                    f"{n_removed} triangles round them replaced by {n_added} (MeshFix), every other "
                    f"triangle kept as given)"
                )
                return v, np.ascontiguousarray(fc), msgs
            vol_before = signed_volume(v, fc)
            v, fc, voxel = voxel_remesh(v, fc)
            if abs(signed_volume(v, fc) / vol_before - 1.0) > 0.05 or len(self_intersections(v, fc)):
                raise refuse(path, f"the surface intersects itself ({len(pairs)} triangle pairs near {where}) "
                                   f"and voxel remeshing could not repair it",
                             "Repair it in a mesh editor (e.g. MeshLab) or re-segment")
            msgs.append(
                f"self-intersections removed by voxel remeshing ({len(pairs)} intersecting triangle "
                f"pairs near {where}; a local repair failed, so the whole surface was rebuilt: voxel "
                f"{voxel:.3g} {unit}, even-odd inside rule, details below about 2 voxels lost)"
            )
    return v, np.ascontiguousarray(fc), msgs


def _at(p: np.ndarray, unit: str, locate=None) -> str:
    """A place on the surface for a message: its coordinates as repaired and, given ``locate`` (the caller's
    map back to the file as given), where that is in the file."""
    here = f"{np.round(p, 3).tolist()} {unit}"
    return f"{here} ({locate(p)})" if locate is not None else here


def _edge_counts(f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per face, the number of faces on each of its three edges ``(k, 3)``; and the edge ids ``(k, 3)``."""
    k = len(f)
    key = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    return counts[inv].reshape(3, k).T, inv.reshape(3, k).T


def _pinch_vertices(f: np.ndarray) -> np.ndarray:
    """Vertices where holes touch: on more than two boundary (open) edges, whatever the winding."""
    if len(f) == 0:
        return np.zeros(0, dtype=np.int64)
    per_face, _ = _edge_counts(f)
    half = np.stack([f, np.roll(f, -1, axis=1)], axis=2)  # (k, 3, 2): edge (f[i], f[i+1])
    v, n = np.unique(half[per_face == 1].ravel(), return_counts=True)
    return v[n > 2]


def _repair_non_manifold(v, f, path, max_fraction: float, max_cut: float, msgs: list[str]) -> np.ndarray:
    """Remove fins and cut out the triangles around edges shared by more than two triangles.

    The holes left are filled later by :func:`_fill_holes`; pieces cut loose
    are dropped by :func:`_keep_largest_component`.
    """
    per_face, edge_id = _edge_counts(f)
    n_bad = len(np.unique(edge_id[per_face > 2]))
    if n_bad == 0:
        return f
    n_edges = int(edge_id.max()) + 1
    what = f"non-manifold surface: {n_bad} edges are shared by more than two triangles"
    todo = "Repair it (e.g. MeshLab 'Repair non Manifold Edges') or re-segment; a liver surface must be " \
           "a single closed 2-manifold"
    if n_bad > max(20, max_fraction * n_edges):
        raise refuse(path, f"{what} ({100 * n_bad / n_edges:.2g} % of the edges): too many to repair "
                           "automatically", todo)
    area = triangle_areas(v, f)
    keep = np.ones(len(f), dtype=bool)
    dangling = 0
    for _ in range(20):  # fins: triangles on a non-manifold edge with an open edge of their own
        per_face, _ = _edge_counts(f[keep])
        fin = (per_face > 2).any(axis=1) & (per_face == 1).any(axis=1)
        if not fin.any():
            break
        idx = np.flatnonzero(keep)[fin]
        keep[idx] = False
        dangling += len(idx)
    per_face, edge_id = _edge_counts(f[keep])
    around = (per_face > 2).any(axis=1)
    n_cut_edges = len(np.unique(edge_id[per_face > 2]))
    cut = 0
    if around.any():
        idx = np.flatnonzero(keep)[around]
        keep[idx] = False
        cut += len(idx)
        for _ in range(20):  # widen the cut where two holes touch at a vertex
            pinch = _pinch_vertices(f[keep])
            if len(pinch) == 0:
                break
            hit = np.isin(f[keep], pinch).any(axis=1)
            idx = np.flatnonzero(keep)[hit]
            keep[idx] = False
            cut += len(idx)
        else:
            raise refuse(path, f"{what}; cutting them out leaves holes that touch each other", todo)
        frac = float(area[~keep].sum() / area.sum())
        if frac > max_cut:
            raise refuse(path, f"{what}; cutting them out would remove {100 * frac:.2g} % of the area (more "
                               f"than {100 * max_cut:g} %): too much to repair safely", todo)
    text = f"non-manifold edges repaired ({n_bad} edges shared by more than two triangles: " \
           f"{dangling} dangling triangles removed"
    if cut:
        text += f", {cut} triangles around {n_cut_edges} edges cut out (the hole is filled below)"
    msgs.append(text + ")")
    return f[keep]


def _repair_zero_area(v, f, path, unit: str, msgs: list[str], locate=None) -> np.ndarray:
    """Remove zero-area triangles whose three distinct vertices are collinear, keeping the surface closed.

    Notes
    -----
    Such a triangle ``(p, m, q)`` has ``m`` on its long edge ``pq``.  The
    neighbour across ``pq``, ``(p, q, d)`` in its own order, is split at
    ``m`` into ``(p, m, d)`` and ``(m, q, d)``, which then share ``pm`` and
    ``mq`` with the triangles the zero-area one shared them with, so the
    zero-area triangle is dropped without opening the surface.  Without a
    neighbour across ``pq`` (an isolated sliver, or one on an open border)
    it is simply dropped.
    """
    area = triangle_areas(v, f)
    tiny = np.flatnonzero(area <= 1e-10 * max(area.mean(), 1e-300))
    if len(tiny) == 0:
        return f
    where = _at(v[f[tiny[0]]].mean(axis=0), unit, locate)
    if len(tiny) > max(10, 0.01 * len(f)):
        raise refuse(path, f"{len(tiny)} zero-area triangles with three distinct but collinear vertices (e.g. "
                           f"near {where}): too many to repair automatically",
                     "Remesh or clean the surface (e.g. MeshLab 'Remove Zero Area Faces' + 'Close holes')")
    faces = [list(t) for t in f.tolist()]
    alive = [True] * len(faces)
    on_edge: dict[tuple[int, int], set[int]] = {}

    def edges(t):
        return [(min(t[i], t[(i + 1) % 3]), max(t[i], t[(i + 1) % 3])) for i in range(3)]

    def add(i):
        for e in edges(faces[i]):
            on_edge.setdefault(e, set()).add(i)

    def remove(i):
        for e in edges(faces[i]):
            on_edge[e].discard(i)

    for i in range(len(faces)):
        add(i)
    queue, split, dropped = list(tiny.tolist()), 0, 0
    while queue:
        i = queue.pop()
        if not alive[i]:
            continue
        t = faces[i]
        lengths = [np.linalg.norm(v[t[(j + 1) % 3]] - v[t[j]]) for j in range(3)]
        j = int(np.argmax(lengths))
        p, q, m = t[j], t[(j + 1) % 3], t[(j + 2) % 3]
        across = on_edge[(min(p, q), max(p, q))] - {i}
        remove(i)
        alive[i] = False
        if not across:
            dropped += 1
            continue
        n = across.pop()
        if across or m in faces[n]:
            raise refuse(path, f"a zero-area triangle with collinear vertices near "
                               f"{_at(v[t].mean(axis=0), unit, locate)} sits on a non-manifold edge "
                               "and cannot be removed without opening the surface",
                         "Remesh or clean the surface (e.g. MeshLab 'Remove Zero Area Faces' + 'Close holes')")
        a, b, d = faces[n]
        while {a, b} != {p, q}:  # rotate the neighbour so that (a, b) is the shared edge in its own order
            a, b, d = b, d, a
        remove(n)
        faces[n] = [a, m, d]
        faces.append([m, b, d])
        alive.append(True)
        add(n)
        add(len(faces) - 1)
        split += 1
        for k in (n, len(faces) - 1):
            if triangle_areas(v, np.array([faces[k]]))[0] <= 1e-10 * max(area.mean(), 1e-300):
                queue.append(k)
        if split > 4 * len(tiny) + 10:
            raise refuse(path, f"zero-area triangles near {where} could not be removed (their "
                               "neighbours are degenerate too)",
                         "Remesh or clean the surface (e.g. MeshLab 'Remove Zero Area Faces' + 'Close holes')")
    msgs.append(f"zero-area triangles repaired ({len(tiny)} with three collinear vertices, e.g. near {where}: "
                f"{split} removed by splitting the neighbour across their long edge, {dropped} dropped "
                "with no neighbour there)")
    return np.asarray([t for t, ok in zip(faces, alive) if ok], dtype=np.int64).reshape(-1, 3)


def _keep_largest_component(mesh, path, ratio: float, msgs: list[str]):
    parts = mesh.split(only_watertight=False)
    if len(parts) <= 1:
        return mesh
    areas = np.array([p.area for p in parts])
    order = np.argsort(-areas, kind="stable")
    largest = parts[order[0]]
    second = areas[order[1]]
    if second >= ratio * areas[order[0]]:
        raise refuse(
            path,
            f"{len(parts)} disconnected components, the second one is {100 * second / areas[order[0]]:.0f} % "
            "of the largest by area: the file seems to hold more than one object",
            "Keep only the liver in the file (or choose its label in a label volume)",
        )
    dropped = 100.0 * areas[order[1:]].sum() / areas.sum()
    msgs.append(f"largest component kept ({len(parts) - 1} smaller components dropped, {dropped:.2g} % of the area)")
    return largest


def _fill_holes(mesh, path, max_fraction: float, msgs: list[str]):
    """Fill each boundary loop with a fan of triangles around its centroid."""
    import trimesh

    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces, dtype=np.int64)
    half = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    key = np.sort(half, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    boundary = half[counts[inv.ravel()] == 1]  # directed as in their triangle
    starts, n_out = np.unique(boundary[:, 0], return_counts=True)
    if (n_out > 1).any():
        raise refuse(
            path,
            f"open surface with {len(boundary)} boundary edges whose holes touch each other at "
            f"{int((n_out > 1).sum())} vertices (non-simple holes)",
            "Close the holes in a mesh editor (e.g. MeshLab 'Close Holes') or re-segment",
        )
    nxt = dict(zip(boundary[:, 0].tolist(), boundary[:, 1].tolist()))
    loops, seen = [], set()
    for start in boundary[:, 0].tolist():
        if start in seen:
            continue
        loop, cur = [], start
        while cur not in seen:
            seen.add(cur)
            loop.append(cur)
            cur = nxt.get(cur)
            if cur is None:
                raise refuse(path, "open surface with a broken boundary loop",
                             "Close the holes in a mesh editor (e.g. MeshLab 'Close Holes')")
        loops.append(loop)
    new_v, new_f = [v], [f]
    n = len(v)
    for loop in loops:
        ring = np.array(loop)
        # each boundary half-edge (a -> b) gets the triangle (b, a, centroid)
        tri = np.stack([np.roll(ring, -1), ring, np.full(len(ring), n)], axis=1)
        new_v.append(v[ring].mean(axis=0)[None])
        new_f.append(tri)
        n += 1
    all_v = np.concatenate(new_v)
    added_area = float(triangle_areas(all_v, np.concatenate(new_f[1:])).sum())
    total = float(mesh.area)
    if added_area > max_fraction * total:
        raise refuse(
            path,
            f"open surface: {len(loops)} holes would add {added_area:.4g} (file units²), "
            f"{100 * added_area / total:.0f} % of the surface area; too large to fill safely",
            "Close the surface in a mesh editor or re-segment the liver",
        )
    filled = trimesh.Trimesh(all_v, np.concatenate(new_f), process=False)
    if not filled.is_watertight:
        raise refuse(path, "open surface: filling its holes did not close it",
                     "Close the holes in a mesh editor (e.g. MeshLab 'Close Holes')")
    sizes = sorted((len(lp) for lp in loops), reverse=True)
    msgs.append(
        f"holes filled ({len(loops)} holes, largest with {sizes[0]} boundary edges, "
        f"{100 * added_area / total:.2g} % of the area added)"
    )
    return filled


def self_intersections(vertices: np.ndarray, faces: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Pairs of triangles that intersect each other, ``(p, 2)`` int.

    Notes
    -----
    Candidate pairs come from KD-trees on the triangle centroids (bounding
    spheres that overlap), the triangles grouped by size (radius within a
    factor 4) so that a few long triangles (a spike, a fan across a filled
    hole) search only their own neighbourhood, not make every triangle search
    theirs (which on a dense surface asked for billions of pairs); pairs
    sharing a vertex are skipped (neighbours).
    Two triangles intersect if an edge of one crosses the other
    (Möller–Trumbore, strictly inside within ``tol`` relative).  Coplanar
    overlaps are not detected.
    """
    tri = vertices[faces]
    centre = tri.mean(axis=1)
    radius = np.linalg.norm(tri - centre[:, None, :], axis=2).max(axis=1)
    a, b = _bounding_sphere_pairs(centre, radius)
    if len(a) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    fa, fb = faces[a], faces[b]
    share = (fa[:, :, None] == fb[:, None, :]).any(axis=(1, 2))
    a, b = a[~share], b[~share]
    overlap = np.all(
        (tri[a].min(axis=1) <= tri[b].max(axis=1)) & (tri[b].min(axis=1) <= tri[a].max(axis=1)), axis=1
    )
    a, b = a[overlap], b[overlap]
    if len(a) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    hit = np.zeros(len(a), dtype=bool)
    for s, t in ((a, b), (b, a)):
        for i, j in ((0, 1), (1, 2), (2, 0)):
            hit |= _segment_hits_triangle(tri[s][:, i], tri[s][:, j], tri[t], tol)
    return np.stack([a[hit], b[hit]], axis=1)


def _bounding_sphere_pairs(centre: np.ndarray, radius: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pairs ``(a, b)``, ``a != b``, each once, whose bounding spheres overlap; searched per pair of size groups
    (radius within a factor 4 of each other) with that pair's largest radii only."""
    from scipy.spatial import cKDTree

    if len(radius) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    base = max(float(np.median(radius)), 1e-12 * float(radius.max()), 1e-300)
    level = np.floor(np.log(np.maximum(radius, base) / base) / np.log(4.0)).astype(np.int64)
    groups = [np.flatnonzero(level == k) for k in np.unique(level)]
    trees = [cKDTree(centre[g]) for g in groups]
    out_a, out_b = [], []
    for i, gi in enumerate(groups):
        for j in range(i, len(groups)):
            gj = groups[j]
            r = float(radius[gi].max() + radius[gj].max())
            if i == j:
                p = trees[i].query_pairs(r=r, output_type="ndarray")
                a, b = gi[p[:, 0]], gi[p[:, 1]]
            else:
                hits = trees[i].query_ball_tree(trees[j], r=r)
                a = np.repeat(gi, [len(h) for h in hits])
                b = gj[np.fromiter((k for h in hits for k in h), np.int64, count=len(a))]
            close = np.linalg.norm(centre[a] - centre[b], axis=1) <= radius[a] + radius[b]
            out_a.append(a[close])
            out_b.append(b[close])
    return np.concatenate(out_a).astype(np.int64), np.concatenate(out_b).astype(np.int64)


def _segment_hits_triangle(p0: np.ndarray, p1: np.ndarray, tri: np.ndarray, tol: float) -> np.ndarray:
    """Vectorised Möller–Trumbore: does segment p0→p1 cross triangle ``tri`` (strictly)?"""
    d = p1 - p0
    e1 = tri[:, 1] - tri[:, 0]
    e2 = tri[:, 2] - tri[:, 0]
    h = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, h)
    scale = np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1) * np.linalg.norm(d, axis=1)
    ok = np.abs(det) > 1e-12 * np.maximum(scale, 1e-300)
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = p0 - tri[:, 0]
    u = inv * np.einsum("ij,ij->i", s, h)
    q = np.cross(s, e1)
    v = inv * np.einsum("ij,ij->i", d, q)
    t = inv * np.einsum("ij,ij->i", e2, q)
    eps = tol
    return ok & (u > eps) & (v > eps) & (u + v < 1 - eps) & (t > eps) & (t < 1 - eps)


def local_self_intersection_repair(
    vertices: np.ndarray, faces: np.ndarray, max_volume_change: float = 0.05, max_replaced: float = 0.05
) -> tuple[np.ndarray, np.ndarray, int, int] | None:
    """Remove self-intersections by replacing only the triangles round them (MeshFix).

    Parameters
    ----------
    vertices, faces : numpy.ndarray
        Closed, consistently wound triangle surface that intersects itself
        in a few places.
    max_volume_change : float
        Largest relative change of the enclosed (signed) volume accepted, as
        for :func:`voxel_remesh` (a fold through the body lowers the input's
        signed volume, so a good repair can change it by a percent or so).
    max_replaced : float
        Largest fraction of the input triangles that may be removed: beyond
        it the repair is not local.

    Returns
    -------
    (vertices, faces, n_removed, n_added) or None
        The repaired surface, how many input triangles were removed and how
        many new ones fill their place; ``None`` when MeshFix could not clean
        the surface, left it open or self-intersecting (by
        :func:`self_intersections`), changed its volume by more than
        ``max_volume_change`` or removed more than ``max_replaced`` of the
        triangles: the caller then falls back to
        :func:`voxel_remesh`.

    Notes
    -----
    MeshFix (M. Attene, "A lightweight approach to repairing digitized
    polygon meshes", The Visual Computer 26, 2010; the ``pymeshfix``
    binding) deletes the intersecting triangles and a small neighbourhood,
    then fills the holes. It hands its points back rounded to float32, an
    error that grows with a coordinate's distance from the origin, so the
    surface is handed to it centred on its bounding box (a liver in scanner
    coordinates, a metre from the origin, keeps its local repair); the
    vertices it kept are put back at the input coordinates exactly, so away
    from the defects the surface is the one given, vertex for vertex and
    triangle for triangle.
    """
    import pymeshfix
    from scipy.spatial import cKDTree

    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
    fix = pymeshfix.MeshFix(v - centre, f.astype(np.int32))
    if not fix.clean() or fix.n_boundaries:
        return None
    v2 = np.array(fix.points, dtype=np.float64) + centre
    f2 = np.array(fix.faces, dtype=np.int64).reshape(-1, 3)
    if len(f2) == 0:
        return None
    tol = 1e-6 * float(np.ptp(v, axis=0).max())  # float32 rounding of centred points: 6e-8 of the extent at most
    dist, src = cKDTree(v).query(v2)
    kept = dist <= tol
    v2[kept] = v[src[kept]]
    if len(self_intersections(v2, f2)):
        return None
    vol = signed_volume(v, f)
    vol2 = signed_volume(v2, f2)
    if vol2 < 0:  # MeshFix keeps the winding; a flip here would be a failure of the repair
        return None
    if abs(vol2 / vol - 1.0) > max_volume_change:
        return None
    ids = np.where(kept, src, -1)
    given = {tuple(t) for t in np.sort(f, axis=1).tolist()}
    same = sum(1 for t in np.sort(ids[f2], axis=1).tolist() if t[0] >= 0 and tuple(t) in given)
    if len(f) - same > max_replaced * len(f):
        return None
    return v2, np.ascontiguousarray(f2), len(f) - same, len(f2) - same


def voxel_remesh(
    vertices: np.ndarray, faces: np.ndarray, voxel: float | None = None, smoothing_iterations: int = 10
) -> tuple[np.ndarray, np.ndarray, float]:
    """Rebuild a closed surface from the inside of a (possibly bad) one.

    Parameters
    ----------
    vertices, faces : numpy.ndarray
        Triangle surface; may self-intersect or be inconsistently wound.
    voxel : float, optional
        Grid spacing; default ``largest extent / 90``.
    smoothing_iterations : int
        Taubin smoothing iterations after marching cubes.

    Returns
    -------
    vertices, faces, voxel

    Notes
    -----
    Inside = even-odd rule along vertical (z) rays through each grid column
    (a ray–triangle crossing toggles the state), computed for all columns at
    once; then Gaussian smoothing (σ = 0.7 voxel), marching cubes at 0.5,
    the largest component and Taubin smoothing.  Details below ~2 voxels are
    lost.
    """
    import trimesh
    from scipy.ndimage import gaussian_filter
    from skimage.measure import marching_cubes

    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    if voxel is None:
        voxel = float((hi - lo).max()) / 90.0
    # grid of cell centres with a 3-voxel margin and a tiny irrational offset
    # so rays never pass exactly through mesh vertices or edges
    offset = voxel * np.array([0.01234567, 0.02345679, 0.0])
    origin = lo - 3 * voxel + offset
    shape = np.ceil((hi - lo) / voxel).astype(int) + 7
    tri = vertices[faces]
    # columns (ix, iy) covered by each triangle's xy bounding box
    tmin = np.floor((tri[:, :, :2].min(axis=1) - origin[:2]) / voxel).astype(int)
    tmax = np.ceil((tri[:, :, :2].max(axis=1) - origin[:2]) / voxel).astype(int)
    nx, ny = tmax[:, 0] - tmin[:, 0] + 1, tmax[:, 1] - tmin[:, 1] + 1
    counts = nx * ny
    t_id = np.repeat(np.arange(len(faces)), counts)
    local = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    ix = tmin[t_id, 0] + local % nx[t_id]
    iy = tmin[t_id, 1] + local // nx[t_id]
    px = origin[0] + ix * voxel
    py = origin[1] + iy * voxel
    a, b, c = tri[t_id, 0], tri[t_id, 1], tri[t_id, 2]
    det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    ok = np.abs(det) > 1e-300
    det = np.where(ok, det, 1.0)
    u = ((px - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (py - a[:, 1])) / det
    w = ((b[:, 0] - a[:, 0]) * (py - a[:, 1]) - (px - a[:, 0]) * (b[:, 1] - a[:, 1])) / det
    hit = ok & (u >= 0) & (w >= 0) & (u + w <= 1)
    hit &= (ix >= 0) & (ix < shape[0]) & (iy >= 0) & (iy < shape[1])
    z = a[hit, 2] + u[hit] * (b[hit, 2] - a[hit, 2]) + w[hit] * (c[hit, 2] - a[hit, 2])
    k = np.clip(np.ceil((z - origin[2]) / voxel).astype(int), 0, shape[2])
    toggles = np.zeros((shape[0], shape[1], shape[2] + 1), dtype=np.int32)
    np.add.at(toggles, (ix[hit], iy[hit], k), 1)
    inside = (np.cumsum(toggles, axis=2)[:, :, :-1] % 2).astype(np.float32)
    inside = gaussian_filter(inside, 0.7)
    verts, new_faces, _, _ = marching_cubes(inside, level=0.5, allow_degenerate=False)
    mesh = trimesh.Trimesh(verts * voxel + origin, new_faces.astype(np.int64), process=True)
    parts = mesh.split(only_watertight=False)
    if len(parts) > 1:
        mesh = max(parts, key=lambda m: m.area)
    if smoothing_iterations:
        trimesh.smoothing.filter_taubin(mesh, lamb=0.5, nu=0.53, iterations=smoothing_iterations)
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces, dtype=np.int64)
    if signed_volume(v, f) < 0:
        f = f[:, ::-1].copy()
    return v, np.ascontiguousarray(f), float(voxel)
