"""Import a tetrahedral volume mesh *as given*: its nodes, their numbering and its tets kept.

For ``geometry.imported[].mesh: as_given`` (the default, ``auto``, for a file that
holds tetrahedra). Formats: Gmsh MSH 2 and 4 (and v1), VTU, legacy VTK
``UNSTRUCTURED_GRID``, XDMF (meshio; XDMF with HDF5 data needs h5py).

What is kept, what is changed
-----------------------------
* Node ``i`` of the result is node ``i`` of the file (the order meshio reads:
  for Gmsh, the order of ``$Nodes``, i.e. node tag − 1 when the tags run 1..n;
  for VTK/VTU/XDMF, the points array), so a supports file or exertion points
  given as vertex ids (0-based) stay valid.
* Coordinates are scaled to mm (``units``) and mapped to RAS (``frame``), as a
  surface import does (:mod:`liverforce.geometry.frames`); the conversion is
  logged and recorded (``meta["conversion"]``, same keys as
  :func:`liverforce.geometry.importers.load_surface`).
* Tets are kept in file order. Tets that are inverted in the file (negative
  volume) are reoriented (two nodes swapped) and *reported*; a frame with a
  negative determinant reorients every tet (stated as part of the conversion).
* Linear tets only: the solver raises them to its quadratic (P2) formulation
  itself (edge nodes appended after the file's nodes).

Refused, with the problem and the fix named:

* no tetrahedra (a surface: import it with ``mesh: remesh``);
* quadratic tets (``tetra10``) or other volume cells (hexahedra, wedges,
  pyramids), alone or beside tets (a second-order file, ``tetra10`` and ``triangle6``
  only, is refused by the surface import too: :func:`refuse_higher_order`);
* tet indices out of range; nodes used by no tet (their numbering could not be
  kept without a solver unknown of zero stiffness);
* zero-volume (flat) tets; faces shared by more than two tets;
* several disconnected pieces (an unsupported piece has no equilibrium).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from liverforce.atomic import file_sha256
from liverforce.geometry import readers
from liverforce.geometry.errors import refuse
from liverforce.geometry.frames import describe_frame, frame_matrix
from liverforce.geometry.units import (LIVER_EXTENT_MM, check_liver_size, guess_units, guessed_words,
                                       inches_fit, parse_units)

log = logging.getLogger(__name__)

#: File suffixes that may hold a tetrahedral mesh.
VOLUME_MESH_SUFFIXES = (".msh", ".vtu", ".vtk", ".xdmf", ".xmf")
#: Volume cell types meshio may report besides linear ``tetra``.
OTHER_VOLUME_CELLS = ("tetra10", "tetra20", "hexahedron", "hexahedron20", "hexahedron27", "wedge", "wedge15",
                      "wedge18", "pyramid", "pyramid13", "pyramid14", "polyhedron")
#: Second- and higher-order cell types meshio reports; liverforce reads linear cells only.
HIGHER_ORDER_CELLS = ("line3", "triangle6", "triangle7", "quad8", "quad9", "tetra10", "tetra20", "hexahedron20",
                      "hexahedron27", "wedge15", "wedge18", "pyramid13", "pyramid14")
#: A tet is flat when ``|V| <= FLAT_REL * mean |V|``.
FLAT_REL = 1e-10
_FIX = "Repair it in the mesher (e.g. gmsh: Mesh > Optimise; ParaView: Clean to Grid) or import it with mesh: remesh"


@dataclass
class VolumeMesh:
    """A tet mesh as given: ``points`` ``(n, 3)`` RAS mm in file order, ``tets`` ``(m, 4)`` positive, file order."""

    points: np.ndarray
    tets: np.ndarray
    meta: dict = field(default_factory=dict)


@dataclass
class TetFile:
    """What a volume-mesh file holds, in file units and frame: points, cell blocks, cell and field data."""

    points: np.ndarray
    cells: list  # [(cell type, (k, n) int64 node ids)]
    cell_data: dict  # name -> [array per block]
    field_data: dict  # name -> array (Gmsh physical names: [tag, dim])
    format: str


def read_tet_file(path: str | Path) -> TetFile:
    """Read a mesh file with its cell blocks, cell data and field data (file units and frame).

    Raises
    ------
    GeometryError
        Unsupported suffix or unreadable content.
    """
    path = Path(path)
    name = path.name.lower()
    if not path.exists():
        raise refuse(path, "file not found", "Check the path")
    if name.endswith(".msh"):
        version = readers.msh_version(path)
        if version == "1":
            raw = readers.read_gmsh_v1(path)
            cells = [(t, a) for t, a in (("triangle", raw.triangles), ("tetra", raw.tets)) if len(a)]
            return TetFile(raw.points, cells, {}, {}, raw.format)
        if not version.startswith(("2", "4")):
            raise refuse(path, f"unrecognised Gmsh file (version {version or 'unknown'})",
                         "Save it from gmsh as MSH v4 or v2")
        fmt = "gmsh"
    elif name.endswith(".vtu"):
        fmt = "vtu"
    elif name.endswith(".vtk"):
        if readers.is_vtk_polydata(path):
            raise refuse(path, "legacy VTK POLYDATA holds a surface, no tetrahedra",
                         "Import it with mesh: remesh (or auto), or export the volume as UNSTRUCTURED_GRID")
        fmt = "vtk"
    elif name.endswith((".xdmf", ".xmf")):
        fmt = "xdmf"
    else:
        raise refuse(path, f"'{path.suffix}' is not a volume-mesh format",
                     f"Use one of {', '.join(VOLUME_MESH_SUFFIXES)}, or import it with mesh: remesh")
    m = readers.read_meshio_mesh(path, fmt)
    cells = [(b.type, np.asarray(b.data, dtype=np.int64)) for b in m.cells]
    cell_data = {k: [np.asarray(a) for a in v] for k, v in m.cell_data.items()}
    return TetFile(np.asarray(m.points, dtype=np.float64)[:, :3], cells, cell_data, dict(m.field_data),
                   f"meshio-{fmt}")


def refuse_higher_order(path: str | Path, counts: dict[str, int]):
    """The refusal (a ``GeometryError``, to raise) of a file whose cells, ``{cell type: count}``, are second
    order (``tetra10``, ``triangle6``, ...) with no linear tetrahedra or triangles beside them; else ``None``.

    Both the surface import (remesh) and the import as given call it, so such a file is refused for what it
    is, wherever it goes, rather than as holding no triangles or tetrahedra.
    """
    higher = {t: n for t, n in counts.items() if t in HIGHER_ORDER_CELLS and n}
    if not higher or any(counts.get(t) for t in ("tetra", "triangle", "quad")):
        return None
    what = ", ".join(f"{n} {t}" for t, n in higher.items())
    return refuse(path, f"the mesh is second order (quadratic tetrahedra or triangles): it holds {what} and no "
                        "linear tetrahedra or triangles; liverforce reads linear (first-order) cells only",
                  "Export linear tetrahedra (first-order elements; liverforce raises them to the solver's quadratic "
                  "formulation itself): in Gmsh set Mesh.ElementOrder = 1 (gmsh -3 -order 1) when meshing, or "
                  "Mesh > Set order 1 on this mesh, then save; meshio: keep the first 4 nodes of each "
                  "tetra10 and the first 3 of each triangle6, then mesh.remove_orphaned_nodes()")


def cell_counts(cells) -> dict[str, int]:
    """``{cell type: count}`` of cell blocks ``[(type, array)]``."""
    counts: dict[str, int] = {}
    for t, a in cells:
        counts[t] = counts.get(t, 0) + int(len(a))
    return counts


def has_tetrahedra(path: str | Path) -> bool:
    """True if ``path`` is a volume-mesh file with at least one linear tet (False for other files)."""
    path = Path(path)
    if not path.name.lower().endswith(VOLUME_MESH_SUFFIXES):
        return False
    if path.name.lower().endswith(".vtk") and readers.is_vtk_polydata(path):
        return False
    return any(t == "tetra" and len(a) for t, a in read_tet_file(path).cells)


def load_volume_mesh(path: str | Path, units="mm", *, frame="RAS",
                     size_range_mm: tuple[float, float] | None = LIVER_EXTENT_MM) -> tuple[VolumeMesh, list[str]]:
    """Read and check a tet mesh as given, in RAS mm with its node numbering kept.

    Parameters
    ----------
    path : str or Path
        Gmsh MSH, VTU, legacy VTK unstructured grid or XDMF.
    units : {"mm", "cm", "m", "auto"} or float
        Unit of the file's coordinates (see :func:`liverforce.geometry.units.parse_units`).
    frame : {"RAS", "LPS"} or (4, 4)
        Frame of the file's coordinates (see :mod:`liverforce.geometry.frames`).
    size_range_mm : (float, float) or None
        Plausible largest extent (mm); outside it the units are taken to be wrong.

    Returns
    -------
    VolumeMesh
        ``meta``: ``source``, ``sha256``, ``format``, ``units``, ``scale_to_mm``,
        ``frame``, ``conversion`` (as a surface import), ``n_nodes``, ``n_tets``,
        ``reoriented_in_file`` (tets inverted in the file), ``cell_types``
        (counts), ``node_numbering: "file"``.
    messages : list of str
        What was changed or ignored (reoriented tets, unit guess, ignored cells).

    Raises
    ------
    GeometryError
        See the module docstring; the message names the problem and the fix.
    """

    path = Path(path)
    scale, unit_label = parse_units(units, path)
    frame_m, frame_label = frame_matrix(frame, path)
    tf = read_tet_file(path)
    msgs: list[str] = []
    counts = cell_counts(tf.cells)
    others = {t: n for t, n in counts.items() if t in OTHER_VOLUME_CELLS and n}
    tets = [a for t, a in tf.cells if t == "tetra"]
    n_tets = sum(len(a) for a in tets)
    if n_tets == 0 and (quadratic := refuse_higher_order(path, counts)) is not None:
        raise quadratic
    if others:
        what = ", ".join(f"{n} {t}" for t, n in others.items())
        raise refuse(path, f"the mesh holds volume cells other than linear tetrahedra ({what}"
                           + (f", beside {n_tets} tetra" if n_tets else "") + "), which would be left out",
                     "Convert them to linear tetrahedra in the mesher, or import the file with mesh: remesh")
    if n_tets == 0:
        found = ", ".join(f"{n} {t}" for t, n in counts.items()) or "no cells"
        raise refuse(path, f"the file holds no tetrahedra ({found}); it is not a volume mesh"
                           + (" (Gmsh saves only elements of physical groups when any is defined: add a "
                              "physical volume, or set Mesh.SaveAll)" if tf.format == "meshio-gmsh" else ""),
                     "Import it with mesh: remesh (or auto) to tetrahedralise the surface")
    tets = np.concatenate(tets).astype(np.int64)
    points = tf.points
    n = len(points)
    if tets.min() < 0 or tets.max() >= n:
        raise refuse(path, f"tetrahedron node ids out of range [0, {n})", "The file is corrupted; re-export it")
    used = np.zeros(n, bool)
    used[tets.ravel()] = True
    if not used.all():
        orphan = np.flatnonzero(~used)
        raise refuse(path, f"{len(orphan)} of {n} nodes belong to no tetrahedron (e.g. node ids "
                           f"{orphan[:5].tolist()}, 0-based); kept as given they would be unknowns without "
                           "stiffness, and dropping them would renumber the nodes",
                     "Remove unused nodes in the mesher (meshio: mesh.remove_orphaned_nodes(); gmsh: no "
                     "geometry-only points) and renumber your vertex-id files to match, or import the file "
                     "with mesh: remesh")
    if len(np.unique(np.sort(tets, axis=1), axis=0)) < len(tets) or (np.diff(np.sort(tets, axis=1), axis=1) == 0).any():
        raise refuse(path, "the mesh has duplicate tetrahedra or tetrahedra with a repeated node",
                     "Remove them in the mesher. " + _FIX)
    vol = _signed_volumes(points, tets)
    flat = np.abs(vol) <= FLAT_REL * np.abs(vol).mean()
    if flat.any():
        ids = np.flatnonzero(flat)
        raise refuse(path, f"{len(ids)} zero-volume (flat) tetrahedra, e.g. cells {ids[:5].tolist()} (0-based, "
                           "in file order)", "Remove or fix them. " + _FIX)
    inverted = vol < 0
    tets = np.where(inverted[:, None], tets[:, [0, 1, 3, 2]], tets)
    if inverted.any():
        msgs.append(f"{int(inverted.sum())} of {len(tets)} tetrahedra were inverted in the file (negative volume, "
                    f"e.g. cells {np.flatnonzero(inverted)[:5].tolist()}): reoriented by swapping their last two "
                    "nodes")
    faces = np.sort(tets[:, [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]].reshape(-1, 3), axis=1)
    _, fcount = np.unique(faces, axis=0, return_counts=True)
    if (fcount > 2).any():
        raise refuse(path, f"{int((fcount > 2).sum())} faces are shared by more than two tetrahedra "
                           "(overlapping or non-conforming elements)", _FIX)
    pieces = _pieces(n, tets)
    if pieces.max() > 0:
        sizes = np.bincount(pieces[tets[:, 0]])
        raise refuse(path, f"the mesh has {len(sizes)} disconnected pieces (tetrahedra per piece: "
                           f"{sorted(sizes.tolist(), reverse=True)[:8]}); a piece without support has no "
                           "equilibrium", "Keep the liver piece only (ParaView: Connectivity, then Threshold on "
                           "RegionId; gmsh: delete the other volumes) or import the file with mesh: remesh")
    if scale is None:
        extent = float(np.ptp(points, axis=0).max())
        scale, unit_label = guess_units(extent, path)
        guess = guessed_words(extent, scale, unit_label)
        if inches_fit(extent):
            log.warning("%s: %s", path, guess)
        msgs.append(guess)
    lin, shift = frame_m[:3, :3], frame_m[:3, 3]
    det = float(np.linalg.det(lin))
    sv = np.linalg.svd(lin, compute_uv=False)
    out = (points * scale) @ lin.T + shift
    if det < 0:
        tets = tets[:, [0, 1, 3, 2]]  # a reflection turns every tet over
    check_liver_size(float(np.ptp(out, axis=0).max()), scale, unit_label, path, size_range_mm)
    finfo = {"determinant": det, "winding_reversed": det < 0, "rigid": bool(np.allclose(sv, 1.0, atol=1e-6)),
             "singular_values": [float(s) for s in sv]}
    summary = (f"units {unit_label} (x{scale:g} to mm); " + describe_frame(frame_label, frame_m, finfo)
               + ("; tetrahedra reoriented for the reflection" if det < 0 else "")
               + f"; volume mesh as given: {n} nodes (numbering kept), {len(tets)} linear tetrahedra")
    ignored = {t: c for t, c in counts.items() if t != "tetra"}
    if ignored:
        msgs.append("cells other than tetrahedra kept only as tags for support groups: "
                    + ", ".join(f"{c} {t}" for t, c in ignored.items()))
    conversion = {
        "units": unit_label, "scale_to_mm": float(scale), "frame": frame_label, "frame_matrix": frame_m.tolist(),
        "to_ras_mm": (frame_m @ np.diag([scale, scale, scale, 1.0])).tolist(),
        "winding_reversed": bool(det < 0), "rigid": finfo["rigid"], "summary": summary,
    }
    meta = {
        "source": str(path), "sha256": file_sha256(path), "format": tf.format, "units": unit_label,
        "scale_to_mm": float(scale), "frame": frame_label, "label": None, "repairs": list(msgs),
        "conversion": conversion, "n_nodes": int(n), "n_tets": int(len(tets)),
        "reoriented_in_file": int(inverted.sum()), "cell_types": counts, "node_numbering": "file",
    }
    log.info("%s: %s", path, summary)
    for m in msgs:
        log.info("%s: %s", path, m)
    return VolumeMesh(np.ascontiguousarray(out), np.ascontiguousarray(tets), meta), msgs


def boundary_surface(vm: VolumeMesh):
    """The outward boundary of ``vm`` as a :class:`~liverforce.geometry.surface.Surface` (RAS mm).

    Only the boundary nodes are kept (in file order), so surface vertex ids are not
    file node ids; the mesh stage reads the file itself for that.
    """
    from liverforce.geometry.surface import Surface

    faces = vm.tets[:, [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]].reshape(-1, 3)
    _, inv, counts = np.unique(np.sort(faces, axis=1), axis=0, return_inverse=True, return_counts=True)
    faces = faces[counts[inv.ravel()] == 1]
    used, local = np.unique(faces, return_inverse=True)
    return Surface(vm.points[used], local.reshape(-1, 3), dict(vm.meta))


def _signed_volumes(points, tets):
    a, b, c, d = (points[tets[:, i]] for i in range(4))
    return np.einsum("ij,ij->i", b - a, np.cross(c - a, d - a)) / 6.0


def _pieces(n: int, tets: np.ndarray) -> np.ndarray:
    """Connected-component label of every node (nodes linked through the tets)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    i = np.repeat(tets[:, 0], 3)
    j = tets[:, 1:].ravel()
    g = coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n))
    _, labels = connected_components(g, directed=False)
    return labels
