"""Automatic repair of a crafted broken liver: non-manifold edges, a hole, duplicate and degenerate faces."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from liverforce.geometry import load_surface
from liverforce.geometry.procedural import procedural_liver


@pytest.fixture(scope="module")
def liver():
    return procedural_liver(0)


def face_at(surface, direction):
    """Index of the triangle furthest along ``direction`` (well apart for different directions)."""
    return int(np.argmax(surface.vertices[surface.faces].mean(axis=1) @ np.asarray(direction, float)))


def unit_normal(v, t):
    n = np.cross(v[t[1]] - v[t[0]], v[t[2]] - v[t[0]])
    return n / np.linalg.norm(n)


def broken_liver(liver):
    """The liver with, each in a different place:

    * a fin: a third triangle on an edge, pointing outward (dangling);
    * a near-copy of a triangle with its third vertex lifted 0.5 mm: its edge is shared three ways;
    * a small closed tetrahedron glued onto an edge (4 triangles on it, none dangling: cut out);
    * a hole: the six-or-so triangles around one vertex removed;
    * an exact duplicate triangle and a triangle with a repeated vertex.
    """
    v, f = liver.vertices.copy(), liver.faces.copy()
    new_v, new_f = [v], [f]
    n = len(v)

    a, b, c = f[face_at(liver, [1, 0, 0])]  # fin on the right tip
    p = 0.5 * (v[a] + v[b]) + 5.0 * unit_normal(v, (a, b, c))
    new_v.append(p[None]), new_f.append([[a, b, n]])
    n += 1

    a, b, c = f[face_at(liver, [-1, 0, 0])]  # lifted copy on the left tip
    new_v.append((v[c] + 0.5 * unit_normal(v, (a, b, c)))[None]), new_f.append([[a, b, n]])
    n += 1

    a, b, c = f[face_at(liver, [0, 0, 1])]  # a tetrahedron (a, b, p, q) glued on edge ab at the top
    nrm = unit_normal(v, (a, b, c))
    mid = 0.5 * (v[a] + v[b])
    side = np.cross(nrm, v[b] - v[a])
    side /= np.linalg.norm(side)
    p, q = mid + 3.0 * nrm + 1.0 * side, mid + 3.0 * nrm - 1.0 * side
    tet = np.array([[a, b, n], [b, a, n + 1], [a, n + 1, n], [b, n, n + 1]])
    pts = np.vstack([v[a], v[b], p, q])
    if trimesh.Trimesh(pts, [[0, 1, 2], [1, 0, 3], [0, 3, 2], [1, 2, 3]], process=False).volume < 0:
        tet = tet[:, ::-1]
    new_v.append(np.vstack([p, q])), new_f.append(tet)
    n += 2

    hole_vertex = f[face_at(liver, [0, -1, 0])][0]  # a hole on the posterior face
    ring = (f == hole_vertex).any(axis=1)
    new_f[0] = f[~ring]

    new_f.append(f[face_at(liver, [0, 1, 0])][None])  # exact duplicate on the anterior face
    new_f.append([[f[0][0], f[0][0], f[0][1]]])  # a repeated vertex
    return np.vstack(new_v), np.vstack(new_f), int(ring.sum())


def test_crafted_broken_liver_is_repaired_and_says_so(tmp_path, liver):
    v, f, hole_faces = broken_liver(liver)
    raw = trimesh.Trimesh(v, f, process=False)
    edges = np.unique(np.sort(raw.edges, axis=1), axis=0, return_counts=True)[1]
    assert (edges > 2).sum() == 7 and (edges == 1).any()  # really broken (4 of the 7 from the duplicates), open
    path = tmp_path / "broken_liver.ply"
    raw.export(path)

    s, msgs = load_surface(path, units="mm")

    m = s.to_trimesh()
    counts = np.unique(np.sort(m.edges, axis=1), axis=0, return_counts=True)[1]
    assert (counts == 2).all(), "every edge shared by exactly two triangles (closed, manifold)"
    assert m.is_watertight and m.is_winding_consistent and s.volume_mm3 > 0
    assert s.volume_mm3 == pytest.approx(liver.volume_mm3, rel=0.01)
    text = "\n".join(msgs)
    assert "non-manifold edges repaired (3 edges shared by more than two triangles: 2 dangling triangles removed" \
        in text, msgs
    assert "cut out" in text and "holes filled" in text, msgs
    assert "duplicate triangles removed (1)" in text and "degenerate triangles removed (1" in text, msgs
    assert s.meta["repairs"] == msgs


def test_a_clean_liver_is_left_alone(tmp_path, liver):
    path = tmp_path / "clean.ply"
    trimesh.Trimesh(liver.vertices, liver.faces, process=False).export(path)
    s, msgs = load_surface(path, units="mm")
    assert msgs == []
    assert np.array_equal(s.faces, liver.faces) and np.allclose(s.vertices, liver.vertices)
