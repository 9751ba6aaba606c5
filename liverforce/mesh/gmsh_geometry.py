"""Load a closed triangle surface into gmsh as reparametrised discrete patches enclosing a volume.

Routes (see :func:`liverforce.mesh.tetra.tetrahedralise`):

- ``"two_patch"``: smooth shapes are split in two disc-like patches along a
  level set of the Fiedler vector (:mod:`liverforce.mesh.patches`), given to
  gmsh with an explicit topology (gmsh's own ``createTopology`` made runs differ);
- ``"features"``: gmsh's ``classifySurfaces`` splits at the feature angle so
  sharp edges survive;
- ``"classify"``: ``classifySurfaces`` with parametrisable patches only;
- ``"labelled"``: the borders of per-triangle labels become curves of the
  geometry, so the mesh conforms to them.

``createGeometry`` then reparametrises the patches.

What a route computes from the surface alone (the two-patch split and its cut
loop; the cleaned labels, their disc patches and borders) is prepared once per
route by :func:`prepare_geometry`, not on every remesh attempt.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from liverforce.geometry.surface import Surface
from liverforce.mesh.meshing_info import MeshingError
from liverforce.mesh.patches import cut_loop, disc_patches, two_patch_labels
from liverforce.mesh.surface_labels import clean_labels, label_boundary_edges, patch_majority

__all__ = ["PreparedGeometry", "load_geometry", "prepare_geometry"]


@dataclass(frozen=True)
class PreparedGeometry:
    """Per-face data of a route that depends on the surface (and its labels) only.

    ``"two_patch"``: ``labels`` are the two patches (0, 1), ``loop`` the cut
    between them; ``"labelled"``: ``labels`` are the cleaned labels (each disc
    patch at its majority label), ``patches`` the disc patches, ``border`` the
    edges ``(e, 2)`` between patches; other routes: nothing.
    """

    route: str
    labels: np.ndarray | None = None
    patches: np.ndarray | None = None
    border: np.ndarray | None = None
    loop: np.ndarray | None = None


def prepare_geometry(surface: Surface, route: str, labels: np.ndarray | None = None) -> PreparedGeometry:
    """What :func:`load_geometry` needs besides gmsh, computed once for all attempts of a route."""
    verts, faces = surface.vertices, surface.faces
    if route == "two_patch":
        split = two_patch_labels(verts, faces)
        return PreparedGeometry(route, labels=split, loop=cut_loop(faces[split == 0]))
    if route == "labelled":
        if labels is None:
            raise ValueError("route 'labelled' needs per-triangle labels")
        cleaned = clean_labels(faces, labels)
        patches = clean_labels(faces, disc_patches(verts, faces, cleaned))
        # a patch takes the label most of its triangles have (cleaning moved a few)
        return PreparedGeometry(route, labels=patch_majority(patches, cleaned), patches=patches,
                                border=label_boundary_edges(faces, patches))
    return PreparedGeometry(route)


def load_geometry(gmsh, surface: Surface, route: str, feature_angle_deg: float | None,
                  labels: np.ndarray | None = None, prepared: PreparedGeometry | None = None,
                  ) -> dict[int, int] | None:
    """Put the surface into gmsh as reparametrised discrete patches + a volume.

    Route ``"labelled"``: the label boundaries enter as a discrete curve, which
    ``classifySurfaces`` keeps as patch borders; returns ``{surface tag: label}``.
    ``prepared`` (from :func:`prepare_geometry` for this surface and route) saves
    recomputing the route's patches; without it they are computed from ``labels``.
    """
    if prepared is None:
        prepared = prepare_geometry(surface, route, labels)
    elif prepared.route != route:
        raise ValueError(f"geometry prepared for route {prepared.route!r}, not {route!r}")
    verts, faces = surface.vertices, surface.faces
    patch_labels = None
    gmsh.model.add("liverforce")
    tags = np.arange(1, len(verts) + 1, dtype=np.uint64)
    if route == "two_patch":
        # explicit topology (point, closed curve, two discs): gmsh's own
        # createTopology starts the loop at a memory-order-dependent node,
        # which made meshes differ from run to run
        labels, loop = prepared.labels, prepared.loop
        on_loop = np.zeros(len(verts), dtype=bool)
        on_loop[loop] = True
        p = gmsh.model.addDiscreteEntity(0)
        c = gmsh.model.addDiscreteEntity(1, -1, [p, p])
        s1 = gmsh.model.addDiscreteEntity(2, -1, [c])
        s2 = gmsh.model.addDiscreteEntity(2, -1, [-c])
        gmsh.model.mesh.addNodes(0, p, [int(loop[0]) + 1], verts[loop[0]])
        gmsh.model.mesh.addNodes(1, c, loop[1:] + 1, verts[loop[1:]].ravel())
        for surf, lab in ((s1, 0), (s2, 1)):
            inner = np.unique(faces[labels == lab])
            inner = inner[~on_loop[inner]]
            gmsh.model.mesh.addNodes(2, surf, inner + 1, verts[inner].ravel())
            gmsh.model.mesh.addElementsByType(surf, 2, [], (faces[labels == lab] + 1).ravel())
        gmsh.model.mesh.addElementsByType(c, 1, [], (np.stack([loop, np.roll(loop, -1)], axis=1) + 1).ravel())
    else:
        s1 = gmsh.model.addDiscreteEntity(2)
        gmsh.model.mesh.addNodes(2, s1, tags, verts.ravel())
        gmsh.model.mesh.addElementsByType(s1, 2, [], (faces + 1).ravel())
        if route == "labelled":
            labels, border = prepared.labels, prepared.border
            if len(border):
                c = gmsh.model.addDiscreteEntity(1)
                gmsh.model.mesh.addElementsByType(c, 1, [], (border + 1).ravel())
        angle = np.deg2rad(feature_angle_deg) if feature_angle_deg is not None and route != "classify" else np.pi
        # labelled: the patches are discs already, so gmsh need not split them further (its own
        # splits put extra corner points a few mm apart, which force tiny elements)
        gmsh.model.mesh.classifySurfaces(angle, True, route != "labelled", np.pi)
        if route == "labelled":
            patch_labels = _patch_labels(gmsh, faces, labels)
    gmsh.model.mesh.createGeometry()
    surfaces = [tag for _, tag in gmsh.model.getEntities(2)]
    loop = gmsh.model.geo.addSurfaceLoop(surfaces)
    gmsh.model.geo.addVolume([loop])
    gmsh.model.geo.synchronize()
    return patch_labels


def _patch_labels(gmsh, faces: np.ndarray, labels: np.ndarray) -> dict[int, int]:
    """Label of each classified surface patch (its triangles are the input's, node tags = index + 1)."""
    key = np.sort(faces, axis=1)
    order = np.lexsort((key[:, 2], key[:, 1], key[:, 0]))
    skey = key[order]
    out = {}
    for _, tag in gmsh.model.getEntities(2):
        _, nodes = gmsh.model.mesh.getElementsByType(2, tag)
        tri = np.sort(np.asarray(nodes, dtype=np.int64).reshape(-1, 3) - 1, axis=1)
        if len(tri) == 0:
            continue
        # locate the patch's triangles among the input's: lexicographic search on sorted rows
        idx = _find_rows(skey, tri)
        found = idx >= 0
        if not found.any():
            raise MeshingError("classified patch triangles do not match the input surface")
        vals, counts = np.unique(labels[order[idx[found]]], return_counts=True)
        if len(vals) > 1:
            raise MeshingError(f"surface patch {tag} spans labels {vals.tolist()}: label borders were not kept")
        out[int(tag)] = int(vals[np.argmax(counts)])
    return out


def _find_rows(sorted_rows: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Index of each row of ``rows`` in lexicographically sorted ``sorted_rows`` (-1 if absent)."""
    base = int(max(sorted_rows.max(), rows.max())) + 1
    code_s = (sorted_rows[:, 0] * base + sorted_rows[:, 1]) * base + sorted_rows[:, 2]
    code_r = (rows[:, 0] * base + rows[:, 1]) * base + rows[:, 2]
    pos = np.searchsorted(code_s, code_r)
    pos = np.minimum(pos, len(code_s) - 1)
    return np.where(code_s[pos] == code_r, pos, -1)
