"""Tagged groups of a mesh file (Gmsh physical groups, VTU/VTK/XDMF cell data) as support selectors.

A support may select its surface with ``group:`` (see :mod:`liverforce.mesh.supports`):

``group: ivc``
    a Gmsh physical group by name (``$PhysicalNames``), else an integer cell-data
    array of that name whose non-zero cells form the group;
``group: 7``
    a tag value: of the Gmsh physical tags (``gmsh:physical``), or of the file's
    one integer cell-data array (a VTU/VTK with several integer arrays needs the
    explicit form);
``group: {array: CellEntityIds, value: 7}``
    a value of a named cell-data array (``{array: name}`` alone: its non-zero cells).

For a liver segmented from a label volume (NIfTI, NRRD, a 3D Slicer ``.seg.nrrd``) a
group is another label value or segment of the same file, by number or by segment
name or ID (``group: inferior_vena_cava``): the support is where the liver's surface
touches it, the surface facets whose centroid lies within 1.5 voxels (in voxel
indices, so each axis in its own spacing) of the segment's boundary voxels
(:class:`VolumeGroups`).

The group's cells give faces and nodes: triangles (and quads, split in two) are
faces; tetrahedra give their faces that lie on the boundary (a sub-volume, e.g. the
tets next to the vena cava; a group of tets whose faces on the boundary make up more
than 90 % of its area, such as the Gmsh physical volume holding the whole liver, is
refused: it would hold the whole surface); lines and vertices give nodes.
On a surface (the mesh's boundary facets, or the input surface of
a remeshed liver) a facet is selected when the nearest boundary triangle of the
file is a face of the group (exact on a mesh imported as given, whose facets
*are* the file's boundary triangles; a label transfer on a remeshed surface), or,
for a group of nodes only, when its three vertices are the nearest surface
vertices of group nodes (as a file of vertex ids); see
:func:`liverforce.mesh.supports.select_facets`.

meshio 5.3.5 gives Gmsh physical tags as the cell data ``gmsh:physical`` (one
per element) and the names as ``field_data`` ``{name: [tag, dim]}`` for MSH 2.2
and 4.1 alike; its ``cell_sets`` also hold ``gmsh:bounding_entities`` and are not
used here.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: Cell-data arrays that are Gmsh bookkeeping, not user tags.
_GMSH_BOOKKEEPING = ("gmsh:geometrical",)
_DIM = {"vertex": 0, "line": 1, "line3": 1, "triangle": 2, "triangle6": 2, "quad": 2, "tetra": 3, "tetra10": 3}


def faces_among(faces: np.ndarray, among: np.ndarray) -> np.ndarray:
    """Which of the triangles ``faces (k, 3)`` are among ``among (m, 3)`` (node ids, any order within a row):
    a ``(k,)`` bool mask. The sorted rows are matched whole (``np.unique`` over rows), so it holds for any node
    ids, where an integer key ``n^2 a + n b + c`` overflows int64 beyond about 2.09 M nodes."""
    f = np.sort(np.asarray(faces, dtype=np.int64).reshape(-1, 3), axis=1)
    g = np.sort(np.asarray(among, dtype=np.int64).reshape(-1, 3), axis=1)
    if not len(f) or not len(g):
        return np.zeros(len(f), dtype=bool)
    _, inv = np.unique(np.concatenate([f, g]), axis=0, return_inverse=True)
    inv = inv.ravel()
    return np.isin(inv[:len(f)], inv[len(f):])


class GroupError(ValueError):
    """A ``group`` selector names no group of the file."""


@dataclass
class FileGroups:
    """Cells and integer cell data of a mesh file (file units and frame) and its boundary triangles."""

    path: str
    points: np.ndarray
    cells: list  # [(type, (k, n) int64)]
    cell_data: dict  # name -> [array per block]
    field_data: dict  # name -> [tag, dim]
    boundary: np.ndarray  # (b, 3) boundary triangles of the file: faces of exactly one tet, else its triangles

    #: a group of tetrahedra whose faces on the boundary exceed this share of its area is refused as a support
    WHOLE_SURFACE = 0.9

    def describe(self) -> str:
        names = sorted(self.field_data)
        arrays = sorted(self._int_arrays())
        return (f"Gmsh physical names {names or 'none'}; integer cell-data arrays {arrays or 'none'}"
                + (f" (values of gmsh:physical: {self._values('gmsh:physical')})" if "gmsh:physical" in arrays else ""))

    def _int_arrays(self) -> list[str]:
        out = []
        for k, v in self.cell_data.items():
            if k in _GMSH_BOOKKEEPING:
                continue
            if all(np.asarray(a).ndim == 1 and (np.issubdtype(np.asarray(a).dtype, np.integer)
                                                 or np.allclose(a, np.round(a))) for a in v):
                out.append(k)
        return out

    def _values(self, name: str) -> list[int]:
        return sorted({int(x) for a in self.cell_data[name] for x in np.unique(a)})

    def select(self, spec: dict, where: str = "group") -> tuple[np.ndarray, np.ndarray]:
        """Faces ``(k, 3)`` and nodes ``(j,)`` (file node ids) of the group ``spec`` (``name|value|array``).

        Raises :class:`GroupError` naming what the file holds when nothing matches.
        """
        spec = dict(spec)
        masks = self._masks(spec, where)
        faces, nodes = [], []
        for (t, a), m in zip(self.cells, masks):
            if not m.any():
                continue
            sel = a[m]
            if t in ("triangle", "triangle6"):
                faces.append(sel[:, :3])
            elif t == "quad":
                faces += [sel[:, [0, 1, 2]], sel[:, [0, 2, 3]]]
            elif t in ("tetra", "tetra10"):
                faces.append(sel[:, [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]].reshape(-1, 3))
            nodes.append(sel.ravel() if t in ("vertex", "line", "line3") else sel[:, :min(sel.shape[1], 4)].ravel())
        if not nodes:
            raise GroupError(f"{where}: {spec} selects no cell of {self.path}; it holds {self.describe()}")
        self._refuse_whole_surface(spec, masks, where)
        faces = np.concatenate(faces).astype(np.int64) if faces else np.zeros((0, 3), np.int64)
        return faces, np.unique(np.concatenate(nodes)).astype(np.int64)

    def _refuse_whole_surface(self, spec: dict, masks: list[np.ndarray], where: str) -> None:
        """Refuse a group of tetrahedra whose faces on the file's boundary make up more than
        :attr:`WHOLE_SURFACE` of its area: a support there would hold the whole liver, tool side too.

        Such a group is the liver's volume (a Gmsh physical volume, a material array), not a support; a
        sub-volume (e.g. the tets next to the vena cava) gives its faces on the boundary and stays allowed.
        """
        tets = [a[m][:, :4] for (t, a), m in zip(self.cells, masks) if t in ("tetra", "tetra10") and m.any()]
        if not tets or not len(self.boundary):
            return
        t = np.concatenate(tets).astype(np.int64)
        own = faces_among(self.boundary, t[:, [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]].reshape(-1, 3))
        P = self.points[self.boundary]
        area = np.linalg.norm(np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]), axis=1)
        share = float(area[own].sum() / area.sum()) if area.sum() > 0 else float(own.mean())
        if share <= self.WHOLE_SURFACE:
            return
        n_all = sum(len(a) for ty, a in self.cells if ty in ("tetra", "tetra10"))
        held = f"all {n_all} tetrahedra" if len(t) == n_all else f"{len(t)} of the file's {n_all} tetrahedra"
        surfaces = sorted(k for k, v in self.field_data.items()
                          if "gmsh:physical" in self.cell_data and np.asarray(v).size >= 2
                          and int(np.asarray(v).ravel()[1]) == 2)
        listed = (f"its surface groups: {surfaces}" if surfaces else f"it holds {self.describe()}")
        label = repr(str(spec["name"])) if "name" in spec else spec
        raise GroupError(
            f"{where}: {label} is a 3-D (volume) group of {self.path} holding {held}, and its boundary is "
            f"{'the whole' if share >= 0.9995 else f'{100 * share:.1f} % of the'} liver surface "
            f"({int(own.sum())} of {len(own)} boundary triangles): as a support it would hold the whole liver, "
            f"under the tool too. A group of tetrahedra gives its faces on the surface, and is refused when "
            f"they make up more than {100 * self.WHOLE_SURFACE:g} % of the surface's area. Give the support's "
            f"surface (2-D) group instead ({listed}), or select it by sphere, box or file")

    def _masks(self, spec: dict, where: str) -> list[np.ndarray]:
        if "name" in spec:
            name = str(spec["name"])
            if name in self.field_data and "gmsh:physical" in self.cell_data:
                tag, dim = (int(x) for x in np.asarray(self.field_data[name]).ravel()[:2])
                return [(np.asarray(v) == tag) & (_DIM.get(t, -1) == dim)
                        for (t, _), v in zip(self.cells, self.cell_data["gmsh:physical"])]
            if name in self._int_arrays():
                return [np.asarray(v) != 0 for v in self.cell_data[name]]
            raise GroupError(f"{where}: '{name}' is no group of {self.path}; it holds {self.describe()}")
        array = spec.get("array")
        if array is None:
            cands = ["gmsh:physical"] if "gmsh:physical" in self.cell_data else self._int_arrays()
            if len(cands) != 1:
                raise GroupError(f"{where}: a tag value needs one integer cell-data array, {self.path} has "
                                 f"{cands or 'none'}: give group: {{array: <name>, value: {spec.get('value')}}}")
            array = cands[0]
        if array not in self.cell_data:
            raise GroupError(f"{where}: no cell-data array '{array}' in {self.path}; it holds {self.describe()}")
        if "value" not in spec:
            return [np.asarray(v) != 0 for v in self.cell_data[array]]
        value = int(spec["value"])
        masks = [np.asarray(v) == value for v in self.cell_data[array]]
        if not any(m.any() for m in masks):
            raise GroupError(f"{where}: no cell has {array} = {value} in {self.path} (values: "
                             f"{self._values(array) if array in self._int_arrays() else '?'})")
        return masks


@dataclass
class VolumeGroups:
    """The other labels and segments of the label volume a liver was segmented from (module docstring)."""

    path: str
    volume: object  # liverforce.geometry.volumes.LabelVolume
    liver: tuple  # the liver's own (label value, segment ID or None): never a support

    #: facets within this many voxels of the segment's boundary voxels touch it (measured in voxel indices,
    #: so along each axis in that axis's spacing)
    REACH_VOXELS = 1.5

    def contact(self, spec: dict, where: str = "group") -> tuple[np.ndarray, np.ndarray, str]:
        """Boundary voxel indices ``(k, 3)`` of the group ``spec``, the voxel-to-world map (file units and
        frame), and which label or segment it is."""
        from liverforce.geometry.errors import GeometryError
        from liverforce.geometry.volumes import segment_boundary_voxels

        if "array" in spec:
            raise GroupError(f"{where}: {self.path} is a label volume, it has no cell-data arrays; give a label "
                             "value or a segment's name or ID")
        try:
            # a value goes in as text: digits that also name a segment are refused as ambiguous (_as_value)
            ijk, what, value, segment = segment_boundary_voxels(
                self.volume, spec["name"] if "name" in spec else str(spec.get("value")), self.path)
        except GeometryError as exc:
            raise GroupError(f"{where}: {exc}") from None
        if (value, segment) == tuple(self.liver):
            raise GroupError(f"{where}: {what} is the liver itself; a support is another segment it touches")
        return ijk, np.asarray(self.volume.affine, float), what


def read_volume_groups(path, liver_label: int | None, liver_segment: str | None = None) -> VolumeGroups:
    """The label volume ``path`` as support groups (:class:`VolumeGroups`); the liver is ``liver_label``
    (and ``liver_segment``), as the geometry stage recorded it."""
    from liverforce.geometry.volumes import read_label_volume

    return VolumeGroups(str(Path(path)), read_label_volume(path), (liver_label, liver_segment))


def read_file_groups(path) -> FileGroups:
    """Read the cells, cell data and Gmsh names of a mesh file (see the module docstring)."""
    from liverforce.geometry.volume_mesh import read_tet_file

    tf = read_tet_file(path)
    tets = [a for t, a in tf.cells if t == "tetra"]
    if tets:
        t = np.concatenate(tets)
        faces = t[:, [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]].reshape(-1, 3)
        _, inv, counts = np.unique(np.sort(faces, axis=1), axis=0, return_inverse=True, return_counts=True)
        boundary = faces[counts[inv.ravel()] == 1]
    else:
        tris = [a[:, :3] for t, a in tf.cells if t in ("triangle", "triangle6")]
        tris += [q for t, a in tf.cells if t == "quad" for q in (a[:, [0, 1, 2]], a[:, [0, 2, 3]])]
        boundary = np.concatenate(tris) if tris else np.zeros((0, 3), np.int64)
    return FileGroups(str(Path(path)), tf.points, tf.cells, tf.cell_data, tf.field_data,
                      np.asarray(boundary, np.int64))
