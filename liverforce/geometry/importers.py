"""Import a segmented liver: surface/volume meshes or label volumes → Surface (mm).

Supported inputs (by suffix, then by content where a suffix is ambiguous):

=================================  ==========================================
STL, OBJ, PLY, OFF                 trimesh
legacy VTK ``DATASET POLYDATA``    own reader (ASCII and BINARY)
legacy VTK other datasets, VTU     meshio (boundary of tets, else triangles)
Gmsh MSH v1                        own reader (ASCII)
Gmsh MSH v2, v4                    meshio
XDMF ``.xdmf``/``.xmf``             meshio (HDF5 data needs h5py)
NIfTI ``.nii``/``.nii.gz``, NRRD   label volume → marching cubes (mm)
=================================  ==========================================

Volume meshes give their boundary surface (faces of exactly one tet).  The
result is then scaled to mm (``units``), converted from the file's stated
``frame`` (RAS, LPS or a 4×4, see :mod:`liverforce.geometry.frames`) to RAS,
checked/repaired by :func:`~liverforce.geometry.repair.repair_surface`, and
checked for a liver-like size.  What was converted is logged and recorded in
``Surface.meta["conversion"]``.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from liverforce.atomic import file_sha256 as sha256_file  # re-exported (__all__)
from liverforce.geometry import readers
from liverforce.geometry.errors import GeometryError, refuse
from liverforce.geometry.frames import describe_frame, frame_matrix, to_ras
from liverforce.geometry.repair import repair_surface
from liverforce.geometry.surface import Surface
from liverforce.geometry.units import (LIVER_EXTENT_MM, check_liver_size, guess_units, guessed_words,
                                       inches_fit, parse_units)
from liverforce.geometry.volumes import is_volume_file, label_surface, read_label_volume

__all__ = ["GeometryError", "SUPPORTED_SUFFIXES", "load_surface", "sha256_file"]

log = logging.getLogger(__name__)

SUPPORTED_SUFFIXES = (".stl", ".obj", ".ply", ".off", ".vtk", ".vtu", ".msh", ".xdmf", ".xmf", ".nii", ".nii.gz",
                      ".nrrd", ".nhdr")


def load_surface(
    path: str | Path,
    units="mm",
    label: int | str | None = None,
    *,
    frame="RAS",
    size_range_mm: tuple[float, float] | None = LIVER_EXTENT_MM,
    check_self_intersections: bool = True,
    max_edge_mm: float | None = 5.0,
) -> tuple[Surface, list[str]]:
    """Read a liver surface or label volume as a closed surface in mm.

    Parameters
    ----------
    path : str or Path
        Input file (see module docstring for formats).
    units : {"mm", "cm", "m", "auto"} or float
        Unit of the file's coordinates, or mm per file unit (e.g. ``40``),
        or ``"auto"``: guessed from the largest bounding-box extent so that
        the liver is 100–450 mm (label volumes: the unit stated in the
        header; guessed from the size if it states none); the guess is logged
        and reported.
    label : int or str, optional
        Label value of the liver in a label volume (required if the volume
        holds several labels), or for a 3D Slicer segmentation (``.seg.nrrd``)
        a segment's name or ID; a segmentation with one segment named "liver"
        needs none.  Ignored for meshes.
    frame : {"RAS", "LPS"} or array_like (4, 4)
        Frame of the file's coordinates (see :mod:`liverforce.geometry.frames`):
        ``"RAS"`` (default, kept), ``"LPS"`` (3D Slicer models, DICOM:
        x and y negated), or a 4×4 affine mapping file coordinates *after
        unit scaling* (mm) to RAS mm (column vectors, translation in mm).
        Label volumes are converted to RAS from their header; for them only
        ``"RAS"`` or a 4×4 (applied after the header's map) are accepted.
    size_range_mm : (float, float) or None
        Plausible largest extent (mm) after scaling; outside it the units
        are taken to be wrong and the file refused.  ``None`` disables it.
    check_self_intersections : bool
        Detect self-intersections (skipped for label volumes, whose
        marching-cubes surfaces cannot self-intersect); local ones are
        repaired by replacing the triangles round them (MeshFix; a voxel
        remesh of the whole surface if that fails), many are refused.
    max_edge_mm : float or None
        A coarse surface (mean edge longer than this, e.g. the boundary of a
        toy tet mesh) is smoothed and refined by Loop subdivision until its
        mean edge is below it, so the mesher does not resolve facet creases
        as slivers; reported.  ``None`` keeps the facets.

    Returns
    -------
    surface : Surface
        Closed, manifold, outward-oriented surface in RAS mm, with ``meta``:
        ``source``, ``sha256``, ``format``, ``units``, ``scale_to_mm``,
        ``frame``, ``label`` (volumes), ``repairs`` and ``conversion``
        (``units``, ``scale_to_mm``, ``frame``, ``frame_matrix`` (file mm →
        RAS mm), ``to_ras_mm`` (file units → RAS mm, scale included),
        ``winding_reversed``, ``summary``: one line, also logged).
    messages : list of str
        Repairs and guesses made (empty if the file was clean; the unit and
        frame conversion is in ``meta["conversion"]``).

    Raises
    ------
    GeometryError
        Naming the file, the problem and what to do.
    """
    path = Path(path)
    if not path.exists():
        raise refuse(path, "file not found", "Check the path")
    if path.is_dir():
        raise refuse(path, "is a folder, not a file", "Give the path of a surface or label-volume file")
    if path.stat().st_size == 0:
        raise refuse(path, "the file is empty (0 bytes)", "Export the liver surface again")
    scale, unit_label = parse_units(units, path)
    frame_m, frame_label = frame_matrix(frame, path)
    name = path.name.lower()
    msgs: list[str] = []
    used_label = used_segment = None
    if is_volume_file(path):
        if frame_label == "LPS":
            raise refuse(path, "frame LPS given for a label volume, whose header already states its frame "
                               "(NIfTI: RAS; NRRD: its 'space', converted to RAS on reading)",
                         "Leave frame at RAS for label volumes (a 4x4 is applied after the header's map)")
        volume = read_label_volume(path)
        for m in volume.messages:  # an assumed frame: a warning, not only a line in the record
            log.warning("%s: %s", path, m)
        vertices, faces, vmsgs, used_label, used_segment = label_surface(volume, label, path)
        msgs += volume.messages + vmsgs
        if scale is None and volume.units:
            scale, unit_label = {"mm": 1.0, "m": 1000.0, "um": 1e-3}[volume.units], volume.units
            msgs.append(f"units '{volume.units}' taken from the image header")
        elif scale is None:  # guessed from the liver's size below, as a mesh's (an affine in metres, no unit)
            msgs.append("the image header states no units: guessed from the liver's size")
        fmt = volume.format
        check_si = False
    else:
        raw = _read_mesh_file(path, name)
        vertices, faces = _surface_of(raw, path)
        fmt = raw.format
        check_si = check_self_intersections
        if label is not None:
            msgs.append(f"label={label} ignored (not a label volume)")
    if len(faces) == 0:
        _refuse_higher_order(path, name)
        raise refuse(path, "the file contains no triangles or tetrahedra",
                     "Export the liver as a closed triangle surface or a tetrahedral mesh")
    if scale is None:
        used = np.unique(faces)
        extent = float(np.ptp(vertices[used], axis=0).max())
        scale, unit_label = guess_units(extent, path)
        guess = guessed_words(extent, scale, unit_label)
        (log.warning if inches_fit(extent) else log.info)("%s: %s", path, guess)
        msgs.append(guess)
    vertices = np.asarray(vertices, dtype=np.float64) * scale
    vertices, faces, finfo = to_ras(vertices, faces, frame_m)
    vertices, faces, rmsgs = repair_surface(vertices, faces, path, check_self_intersections=check_si, unit="mm",
                                            locate=_file_locator(scale, unit_label, frame_m, frame_label,
                                                                 is_volume_file(path)),
                                            corners_apart=fmt == "trimesh-stl")  # STL: each triangle's own corners
    msgs += rmsgs
    extent_mm = float(np.ptp(vertices, axis=0).max())
    check_liver_size(extent_mm, scale, unit_label, path, size_range_mm)
    if max_edge_mm is not None:
        vertices, faces, smsg = _refine_coarse(vertices, faces, max_edge_mm)
        msgs += smsg
    to_ras_mm = frame_m @ np.diag([scale, scale, scale, 1.0])
    summary = (f"units {unit_label} (x{scale:g} to mm); " + describe_frame(frame_label, frame_m, finfo)
               + ("; label volume: header frame converted to RAS first" if is_volume_file(path) else ""))
    conversion = {
        "units": unit_label,
        "scale_to_mm": float(scale),
        "frame": frame_label,
        "frame_matrix": frame_m.tolist(),
        "to_ras_mm": to_ras_mm.tolist(),
        "winding_reversed": bool(finfo["winding_reversed"]),
        "rigid": finfo["rigid"],
        "summary": summary,
    }
    meta = {
        "source": str(path),
        "sha256": sha256_file(path),
        "format": fmt,
        "units": unit_label,
        "scale_to_mm": float(scale),
        "frame": frame_label,
        "label": used_label,
        "segment": used_segment,
        "repairs": list(msgs),
        "conversion": conversion,
    }
    log.info("%s: %s", path, summary)
    if not finfo["rigid"]:
        log.warning("%s: the frame matrix is not rigid: the liver is scaled/sheared (singular values %s)",
                    path, np.round(finfo["singular_values"], 4).tolist())
    for m in msgs:
        log.info("%s: %s", path, m)
    return Surface(vertices, faces, meta), msgs


def _file_locator(scale: float, unit_label: str, frame_m: np.ndarray, frame_label: str, volume: bool):
    """``RAS mm point -> 'x, y, z in the file (units, frame)'`` for repair messages, or ``None`` when the file's
    coordinates are RAS mm already (or a label volume's, whose voxels are no coordinates a lab looks up)."""
    to_ras_mm = frame_m @ np.diag([scale, scale, scale, 1.0])
    if volume or np.allclose(to_ras_mm, np.eye(4)):
        return None
    back = np.linalg.inv(to_ras_mm)

    def locate(p):
        q = back[:3, :3] @ np.asarray(p, float) + back[:3, 3]
        return f"in the file: {[float(f'{x:.6g}') for x in q]} {unit_label}, {frame_label}"

    return locate


def _refine_coarse(vertices: np.ndarray, faces: np.ndarray, max_edge_mm: float):
    """Loop-subdivide (smoothing) while the mean edge exceeds ``max_edge_mm`` (≤ 400k triangles)."""
    import trimesh

    from liverforce.geometry.surface import signed_volume

    def mean_edge(v, f):
        return float(np.linalg.norm(v[f] - v[np.roll(f, 1, axis=1)], axis=2).mean())

    before, vol0 = mean_edge(vertices, faces), signed_volume(vertices, faces)
    levels = 0
    while mean_edge(vertices, faces) > max_edge_mm and 4 * len(faces) <= 400_000:
        vertices, faces = trimesh.remesh.subdivide_loop(vertices, faces, iterations=1)
        levels += 1
    if not levels:
        return vertices, faces, []
    change = 100.0 * (signed_volume(vertices, faces) / vol0 - 1.0)
    return vertices, np.asarray(faces, dtype=np.int64), [
        f"coarse surface (mean edge {before:.3g} mm) smoothed by {levels} levels of Loop subdivision "
        f"(mean edge now {mean_edge(vertices, faces):.3g} mm, volume change {change:+.2g} %)"
    ]


def _refuse_higher_order(path: Path, name: str) -> None:
    """Refuse a volume-mesh file of second-order cells only (``tetra10``, ``triangle6``: the readers keep linear
    cells, and find none) for what it is, naming its cells and the fix
    (:func:`liverforce.geometry.volume_mesh.refuse_higher_order`)."""
    from liverforce.geometry.volume_mesh import VOLUME_MESH_SUFFIXES, cell_counts, read_tet_file, refuse_higher_order

    if not name.endswith(VOLUME_MESH_SUFFIXES) or (name.endswith(".vtk") and readers.is_vtk_polydata(path)):
        return
    quadratic = refuse_higher_order(path, cell_counts(read_tet_file(path).cells))
    if quadratic is not None:
        raise quadratic


def _read_mesh_file(path: Path, name: str) -> readers.RawMesh:
    """Dispatch on suffix (and content for .vtk/.msh) to a reader."""
    if name.endswith(readers.TRIMESH_SUFFIXES):
        return readers.read_trimesh(path)
    if name.endswith(".vtk"):
        if readers.is_vtk_polydata(path):
            return readers.read_vtk_polydata(path)
        with open(path, "rb") as fh:
            if not fh.read(64).lower().startswith(b"# vtk datafile"):
                raise refuse(path, "not a legacy VTK file (first line is not '# vtk DataFile Version')",
                             "Check the file type or extension")
        return readers.read_meshio(path, "vtk")
    if name.endswith(".vtu"):
        return readers.read_meshio(path, "vtu")
    if name.endswith((".xdmf", ".xmf")):
        return readers.read_meshio(path, "xdmf")
    if name.endswith(".msh"):
        version = readers.msh_version(path)
        if version == "1":
            return readers.read_gmsh_v1(path)
        if version.startswith(("2", "4")):
            return readers.read_meshio(path, "gmsh")
        raise refuse(path, f"unrecognised Gmsh file (version {version or 'unknown'}; expected a "
                           "'$NOD' (v1) or '$MeshFormat' 2.x/4.x header)", "Save it from gmsh as MSH v4 or v2")
    raise refuse(path, f"unsupported file type '{path.suffix}'",
                 f"Use one of {', '.join(SUPPORTED_SUFFIXES)}")


def _surface_of(raw: readers.RawMesh, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Boundary of the tets if any, else the triangles (units unchanged)."""
    if len(raw.tets):
        return raw.points, _tet_boundary(raw.points, raw.tets, path)
    return raw.points, raw.triangles


def _tet_boundary(points: np.ndarray, tets: np.ndarray, path: Path) -> np.ndarray:
    """Outward boundary triangles of a tet mesh of any orientation.

    Zero-volume tets are dropped, negative ones reoriented; a face is on the
    boundary if exactly one tet has it.
    """
    if tets.min() < 0 or tets.max() >= len(points):
        raise refuse(path, "tetrahedron indices out of range", "The file is corrupted; re-export it")
    a, b, c, d = (points[tets[:, i]] for i in range(4))
    vol = np.einsum("ij,ij->i", b - a, np.cross(c - a, d - a))
    flat = np.abs(vol) <= 1e-14 * max(np.abs(vol).max(), 1e-300)
    tets = tets[~flat]
    tets = np.where((vol[~flat] < 0)[:, None], tets[:, [0, 1, 3, 2]], tets)
    # outward faces of a positive tet (a, b, c, d): opposite node i
    faces = tets[:, [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]].reshape(-1, 3)
    _, inv, counts = np.unique(np.sort(faces, axis=1), axis=0, return_inverse=True, return_counts=True)
    if (counts > 2).any():
        raise refuse(path, f"invalid tetrahedral mesh ({int((counts > 2).sum())} faces shared by more "
                           "than two tetrahedra)", "Re-export the volume mesh")
    return faces[counts[inv.ravel()] == 1]
