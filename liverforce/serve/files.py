"""Files in and out of serving: point clouds, surfaces, context files, results (atomic).

Point clouds (``read_points``), one point per row, mm unless ``units`` says otherwise:

- ``.npy``: an ``(n, 3)`` float array (read with ``allow_pickle=False``);
- ``.csv`` / ``.txt`` / ``.xyz``: three numeric columns ``x, y, z`` (comma, semicolon,
  tab or space separated; one optional header line; ``#`` comments and blank lines
  skipped; extra columns, a garbled first line and an empty file refused; the reader the
  mesh stage reads its point files with, :mod:`liverforce.geometry.point_table`);
- ``.ply``: ASCII or binary (little/big endian), the ``vertex`` element's
  ``x y z`` properties (other vertex properties and other elements ignored;
  :mod:`liverforce.geometry.ply`, the reader the mesh stage reads its point files with);
- ``.pcd``: PCL's Point Cloud Data v0.7 (ROS ``bag_to_pcd``, PCL, Open3D), ``ascii``, ``binary`` or
  ``binary_compressed``, read with pypcd4: the ``x y z`` fields (float32 or float64, in any order; the other
  fields, rgb, intensity, normals, ignored). Its ``VIEWPOINT`` is the sensor's pose when it recorded, not a
  transform of the points: it is not applied (the points are taken as they are, in ``--units`` and ``--frame``).
  An organised cloud (``HEIGHT`` > 1, a depth camera's image) marks a pixel without depth with NaN
  coordinates (a stereo camera's driver a depth out of its range with inf): :func:`read_cloud`, the camera clouds'
  reader, drops every point with a coordinate that is not finite, as PCL's ``isFinite`` does, and says how many
  (:func:`read_points` keeps them, so ordered nodes are refused for them as for any other file). An ``ascii``
  file's values may be separated by any run of spaces or tabs, its lines end in LF or CRLF (a lab's own script,
  MATLAB, a file edited on Windows), as PCL's own reader splits them; a line with another number of values than a
  point's is refused, naming it. A header keyword not in capitals (``data ascii``), lines that end in CR alone and
  an ascii data of more or fewer lines of values than ``POINTS`` are refused, saying so (PCL reads none of them).

A text file whose header names a unit for every column (``x_mm,y_mm,z_mm``, ``X [m]``) is refused when the
coordinates are read in another one (``--units``, the context's ``units`` or the ``--frame`` record's; mm when
none says), naming the header, as the mesh stage refuses its point files
(:func:`liverforce.geometry.point_table.header_unit_clash`); a header that agrees, or names no unit, is read as
declared. ``.npy``, ``.ply`` and ``.pcd`` files name no unit (a PLY vertex's properties are ``x y z``, and PLY has
no units line; nor has PCD).

Surfaces (``read_surface``): ``.ply`` with faces, ``.npz`` with ``points`` and
``facets``, or anything meshio reads (STL, OBJ, OFF, VTU, VTK, ...); a
tetrahedral mesh gives its boundary triangles (its triangle cells, often only
tagged parts of the boundary, are then ignored).

Context files (``read_context`` / ``load_context``): JSON or YAML with

.. code-block:: yaml

    exertion_point_mm: [x, y, z]          # required
    material_params_mpa: [0.0016, 0.0125] # state-vector models
    surface: liver_preop.stl              # undeformed surface (path relative to this file), or
    roi_undeformed: roi.npy               #   the undeformed ROI nodes plus
    frame: {normal: [..], t1: [..], t2: [..]}
    roi_triangles: roi_tri.npy            #   the ROI patch's triangles (the shipped models read them), (m, 3) indices
                                          #   into roi_undeformed from 0 (.npy, .csv or an inline list)
    liver_centroid_mm: [..]               #   and, for state-vector models, the liver features
    inertia_mm5: [[..], [..], [..]]
    tool_thickness_mm: 60.0               # tissue thickness under the tool along the inward normal
    mesh: liver.vtu                       # the liver's tet mesh (the mesh stage's copy, RAS mm, supports
                                          #   tagged): state-vector models' pre-operative stiffness probe and,
                                          #   with no surface or roi_undeformed, the undeformed surface, or
    probe_compliance_mm_per_n: [[..], [..], [..]]   # the probe's compliance itself, in the local frame (t1, t2, n)
                                          #   the model computes in RAS mm (the given frame, converted)
    units: mm                             # mm (default), cm or m: scales every point and the inertia
    input_frame: RAS                      # the frame of every point here: RAS (default; to be said beside the mesh
                                          #   of a liver imported in another frame), LPS, a 4x4 (file mm to
                                          #   RAS mm), or the liver's import record geometry/imp-<name>.json
                                          #   (its units and frame; liverforce.serve.input_frame)

``liverforce predict`` reads its point file and ``--tool-tip`` in the same
``units`` and ``input_frame`` (its ``--units`` and ``--frame`` override both).
"""

from __future__ import annotations

import io
import json
import re
import zipfile
from pathlib import Path

import numpy as np

from liverforce.atomic import atomic_path
from liverforce.serve.errors import OffSurfaceError, PredictionInputError
from liverforce.serve.input_frame import UNITS_MM, InputFrame, unit_scale
from liverforce.serve.preop import Preop


# --------------------------------------------------------------------------- PLY
def _read_ply(path: Path):
    """The PLY file's vertices and triangles (:func:`liverforce.geometry.ply.read_ply`, the mesh stage's reader
    too), its refusals as :class:`PredictionInputError`."""
    from liverforce.geometry.ply import PlyError, read_ply

    try:
        return read_ply(path)
    except PlyError as exc:
        raise PredictionInputError(str(exc)) from None


# --------------------------------------------------------------------------- PCD
#: the header lines of a PCD v0.7 file, in their order (https://pointclouds.org/documentation/tutorials/
#: pcd_file_format.html)
PCD_HEADER = "VERSION, FIELDS, SIZE, TYPE, COUNT, WIDTH, HEIGHT, VIEWPOINT, POINTS and DATA"


#: the keywords of a PCD header's lines, as PCL reads them (in capitals only)
PCD_KEYWORDS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA")
#: a PCD file whose lines end in CR alone: its refusal ('its' or 'its data's' before it, the file named before that)
PCD_CR_ALONE = ("lines end in CR alone (a classic Mac OS text file), which neither PCL nor pypcd4 reads as lines: "
                "convert its line ends to LF (or CRLF), e.g. tr '\\r' '\\n' < old.pcd > new.pcd for an ascii file")


def _pcd_line(bline: bytes) -> bool:
    """Whether ``bline`` begins as a PCD header's line does: a comment, or a keyword in any case."""
    word = bline.split(None, 1)[:1]
    return bool(word) and (word[0].startswith(b"#") or word[0].upper().decode("latin-1") in PCD_KEYWORDS)


def _pcd_header(fh) -> tuple[bytes, list[str]]:
    """The header of the PCD file ``fh`` (opened binary, at its start) as pypcd4's ``PointCloud.from_fileobj`` reads
    it: its bytes, and its lines stripped (a CRLF's CR too), comments and blank lines skipped, up to ``DATA`` or the
    tenth line; a UTF-8 byte-order mark before it dropped. ``fh`` is left at the data's first byte.

    Refused (:class:`PredictionInputError`, the file not named: the caller names it): lines that end in CR alone (a
    classic Mac OS file: the header would be one line, its keywords reported missing) and a keyword not in capitals
    (``data ascii``: neither PCL nor pypcd4 ends the header there, which then took a line of data for the header's
    and read the points from the next one)."""
    raw, lines = [], []
    for n, bline in enumerate(fh, 1):
        if not raw and bline.startswith(b"\xef\xbb\xbf"):  # UTF-8's byte-order mark, as Windows' Notepad writes it
            bline = bline[3:]
        before, cr, after = bline.partition(b"\r")
        if cr and after.strip(b"\n") and _pcd_line(before):  # a header line, CR, then more: not a CRLF
            raise PredictionInputError(f"its {PCD_CR_ALONE}")
        raw.append(bline)
        if (line := bline.decode("utf-8").strip()).startswith("#") or not line:
            continue
        word = line.split(None, 1)[0]
        if word.upper() in PCD_KEYWORDS and word != word.upper():
            raise PredictionInputError(f"its header's line {n}, '{line}': the keyword '{word}' is not in capitals, "
                                       "which PCL reads only (and pypcd4 ends the header at 'DATA' only, else reads "
                                       f"the points from the wrong line); write '{word.upper()}'")
        lines.append(line)
        if line.startswith("DATA") or len(lines) >= 10:
            break
    return b"".join(raw), lines


def _ascii_pcd_lines(fh, out) -> int:
    """Copy an ascii PCD's data lines from ``fh`` to ``out``, a line for a line, each one's values separated by a
    single space, as PCL writes them and as pypcd4 splits them (on each space): runs of spaces and tabs, the blanks
    at either end and a CRLF's CR dropped; read 1 MB of lines at a time. Returns the number of lines that hold
    values (blank lines and lines of a comment, which ``np.loadtxt`` skips, not counted). Data lines that end in CR
    alone (its first line seen) are refused, as :func:`_pcd_header` refuses such a header."""
    held = 0
    while lines := fh.readlines(1 << 20):
        if not held and b"\r" in lines[0].rstrip(b"\r\n"):  # else read as one line of every point's values
            raise PredictionInputError(f"its data's {PCD_CR_ALONE}")
        lines = [b" ".join(line.split()) for line in lines]
        out.write(data := b"\n".join(lines) + b"\n")
        held += len(lines) - lines.count(b"") - (sum(line.startswith(b"#") for line in lines) if b"#" in data else 0)
    return held


def _pcd_fields(meta) -> str:
    """The header's FIELDS as written (pypcd4 renames each of PCL's padding fields '_' to '#$%&~~' + 6 random
    letters)."""
    return " ".join("_" if f.startswith("#$%&~~") else f for f in meta.fields)


def _ascii_pcd_misfit(data, first: int, meta, exc: Exception) -> str:
    """Which line of an ascii PCD's data pypcd4's ``np.loadtxt`` refused with ``exc``, and why (``data``: the
    lines as :func:`_ascii_pcd_lines` wrote them, the first the file's line ``first``): the first line that holds
    another number of values than a point of the header's (comments after '#' and blank lines skipped, as
    ``np.loadtxt`` skips them) or a comment after its values, else the first whose value in the column ``exc``
    names is the one it could not convert. Empty when none is found."""
    per_point = sum(meta.count)
    said = re.search(r"could not convert string '(.*)' to (\w+) at row \d+, column (\d+)", str(exc))
    for n, line in enumerate(data, first):
        before, comment, note = line.partition(b"#")
        values = before.split()
        if not values:
            continue
        if comment and before.endswith(b" ") and len(values) == per_point:  # np.loadtxt: the blank before '#' is
            note = note.rstrip().decode("utf-8", "replace")  # one more (empty) value
            return f"its line {n} holds a comment after its values ('#{note}'): a data line holds only numbers"
        if len(values) != per_point:
            return (f"its line {n} holds {len(values)} value{'s' * (len(values) != 1)}, where a point of its FIELDS "
                    f"{_pcd_fields(meta)} (COUNT {' '.join(str(c) for c in meta.count)}) has {per_point}")
        if said and values[int(said.group(3)) - 1] == said.group(1).encode("latin-1", "replace"):
            return f"its line {n}: its value {said.group(3)}, '{said.group(1)}', is not a {said.group(2)} number"
    return ""


def _read_pcd(path: Path) -> tuple[np.ndarray, int, int]:
    """``(points (n, 3) float64, WIDTH, HEIGHT)`` of a PCD file (pypcd4), NaN points kept; its ``x y z``
    fields only. The ``VIEWPOINT`` (the sensor's pose) is not applied. An ascii file's values may be separated by
    any run of spaces or tabs and its lines end in LF or CRLF: its data lines are handed to pypcd4 as PCL writes
    them, one space between values (:func:`_ascii_pcd_lines`); binary data is read as it is. A file pypcd4 cannot
    read, a header keyword not in capitals or lines that end in CR alone (:func:`_pcd_header`), an ascii line with
    another number of values than a point's (the line named), a header whose ``POINTS`` is not the data's (a
    truncated file; for ascii data, more lines too) or not ``WIDTH`` x ``HEIGHT``, and a cloud without an ``x``,
    ``y`` or ``z`` field are refused, naming the file and what is wrong."""
    from pypcd4 import Encoding, MetaData, PointCloud

    text = None  # an ascii file's header and data lines, made PCL's (binary data is read from the file)
    try:
        with open(path, "rb") as fh:
            head, lines = _pcd_header(fh)
            header = MetaData.parse_header(lines)
            if header.data == Encoding.ASCII:
                text = io.BytesIO()
                text.write(head)
                held = _ascii_pcd_lines(fh, text)
                if held != header.points:  # before np.loadtxt, which warns of no data and reads every line
                    raise PredictionInputError(
                        f"its header says POINTS {header.points}, its ascii data holds {held}: " + (
                            "a truncated file (or a damaged header)" if held < header.points else
                            "more lines of values than its points (lines added after them, or a damaged header): "
                            "correct POINTS (and WIDTH x HEIGHT) or remove the lines that are not points"))
                text.seek(0)
                pc = PointCloud.from_fileobj(text)
            else:
                fh.seek(0)
                pc = PointCloud.from_fileobj(fh)
    except UnicodeDecodeError:
        raise PredictionInputError(f"{path}: not a PCD file (its header is not text; a PCD v0.7 header gives "
                                   f"{PCD_HEADER})") from None
    except PredictionInputError as exc:  # the header's lines or the ascii data's count: the file named here
        raise PredictionInputError(f"{path}: {exc}") from None
    except OSError as exc:  # the file itself (permissions, a disk error), not its data
        raise PredictionInputError(f"{path}: cannot read the file ({type(exc).__name__}: {exc})") from None
    except Exception as exc:  # noqa: BLE001 - pypcd4 raises many types; re-raised with the file named
        errors = getattr(exc, "errors", None)
        if callable(errors):  # pydantic's ValidationError: the header's lines
            said = "; ".join(f"{' '.join(str(k) for k in e['loc']).upper()}: {e['msg']}" for e in errors())
            raise PredictionInputError(f"{path}: not a PCD file pypcd4 can read, its header wrong ({said}); a PCD "
                                       f"v0.7 header gives {PCD_HEADER} (ascii, binary or binary_compressed)"
                                       ) from None
        hint = ("; an ascii PCD holds a line per point, its values numbers separated by spaces or tabs"
                if text is not None else "")
        where = ""
        if text is not None and isinstance(exc, ValueError):  # np.loadtxt's: the line named
            text.seek(len(head))
            where = _ascii_pcd_misfit(text, head.count(b"\n") + 1, header, exc)
        said = f": {where}:" if where else f" ({type(exc).__name__}: {exc}):"
        raise PredictionInputError(f"{path}: cannot read this PCD file's data{said} a truncated or damaged file{hint}"
                                   ) from None
    meta = pc.metadata
    data = np.atleast_1d(pc.pc_data)
    if len(data) != meta.points:
        raise PredictionInputError(f"{path}: its header says POINTS {meta.points}, its {meta.data.value} data holds "
                                   f"{len(data)}: a truncated file (or a damaged header)")
    if meta.width * meta.height != meta.points:
        raise PredictionInputError(f"{path}: its header's WIDTH {meta.width} x HEIGHT {meta.height} is not its "
                                   f"POINTS {meta.points}: a damaged header")
    for axis in "xyz":
        if axis not in meta.fields:
            raise PredictionInputError(f"{path}: no '{axis}' field (FIELDS {_pcd_fields(meta)}); a point "
                                       "cloud's PCD has x, y and z")
        if meta.count[meta.fields.index(axis)] != 1:
            raise PredictionInputError(f"{path}: its '{axis}' field has COUNT {meta.count[meta.fields.index(axis)]}; "
                                       "x, y and z are one number each")
    if not len(data):
        return np.zeros((0, 3)), meta.width, meta.height
    return np.column_stack([data[a] for a in "xyz"]).astype(np.float64), meta.width, meta.height


# --------------------------------------------------------------------------- clouds and surfaces
def _refuse_empty(path: Path) -> None:
    """Refuse a PLY or PCD point file of 0 bytes as empty (pypcd4 would say its header lacks every line; for a PLY,
    in these words without :func:`_read_ply`'s 'not a readable PLY file' around the PLY reader's own)."""
    if path.suffix.lower() in (".ply", ".pcd") and path.stat().st_size == 0:
        raise PredictionInputError(f"{path}: the file is empty (0 bytes: no header, no points; a writer or a copy "
                                   "that stopped, a camera's driver for a frame): write or export it again")


def read_points(path: str | Path, units: str | None = "mm", *, frame: InputFrame | None = None) -> np.ndarray:
    """An ``(n, 3)`` point cloud in mm from ``.npy``, ``.csv``/``.txt``/``.xyz``, ``.ply`` or ``.pcd`` (module
    docstring; a PCD's NaN points kept: :func:`read_cloud` drops them).

    ``units``: the units the points are scaled from here. ``frame``: the inputs' frame the caller converts the
    points with instead (:meth:`InputFrame.points`; ``units`` left at mm): a text file's header naming a unit is
    checked against its units (:func:`check_header_units`), else against ``units``.
    """
    path = Path(path)
    if not path.is_file():
        raise PredictionInputError(f"{path}: no such point-cloud file")
    from liverforce.geometry.point_table import TEXT_SUFFIXES

    suffix = path.suffix.lower()
    _refuse_empty(path)
    try:
        if suffix == ".npy":
            pts = np.load(path, allow_pickle=False)
        elif suffix in TEXT_SUFFIXES:
            pts = _read_table(path)
            check_header_units(path, frame if frame is not None else InputFrame.resolve(None, units))
        elif suffix == ".ply":
            pts = _read_ply(path).points
        elif suffix == ".pcd":
            pts = _read_pcd(path)[0]
        else:
            raise PredictionInputError(f"{path}: unknown point-cloud format '{suffix}' (use .npy, .csv/.txt/.xyz, "
                                       ".ply or .pcd)")
    except (ValueError, OSError, EOFError) as exc:  # EOFError: numpy's for an empty or cut-short .npy
        if isinstance(exc, PredictionInputError):
            raise
        raise PredictionInputError(f"{path}: cannot read the point cloud ({type(exc).__name__}: {exc})") from exc
    pts = np.asarray(pts)
    if pts.ndim != 2 or pts.shape[1] != 3 or not np.issubdtype(pts.dtype, np.number):
        raise PredictionInputError(f"{path}: expected n rows of x, y, z numbers, got an array of shape {pts.shape}")
    return pts.astype(np.float64) * unit_scale(units)


def read_cloud(path: str | Path, units: str | None = "mm", *, frame: InputFrame | None = None,
               empty: bool = False) -> tuple[np.ndarray, str | None]:
    """A camera cloud: :func:`read_points`, and for a ``.pcd`` file its points that are not finite dropped (NaN: an
    organised cloud's pixels without depth, PCL's convention; inf: a stereo camera's depth out of its range, as
    some drivers mark it; a point with any such coordinate, as PCL's ``isFinite``), with a note that says how many
    of how many (None when none were).

    Other formats are read as :func:`read_points` reads them (a NaN in them is refused by the checks, as before). A
    PCD none of whose points is finite is refused; with ``empty`` (a frame of a sequence, whose other frames go on)
    it is read as no points, which the predictor refuses as that frame's row, and the note says why.
    """
    path = Path(path)
    if path.suffix.lower() != ".pcd" or not path.is_file():
        return read_points(path, units, frame=frame), None
    _refuse_empty(path)
    pts, width, height = _read_pcd(path)
    pts = pts * unit_scale(units)
    bad = ~np.isfinite(pts).all(axis=1)
    if not bad.any():
        return pts, None
    nan, inf = np.isnan(pts).any(), np.isinf(pts).any()
    what = " or ".join(w for w, found in (("NaN", nan), ("inf", inf)) if found)
    why = "; ".join(w for w, found in (
        (f"PCL's mark of a pixel without depth in an organised cloud, here {width} x {height}" if height > 1
         else "PCL's mark of a point without a measurement", nan),
        (f"{'inf: ' if nan else ''}a depth camera's mark of a depth out of its range", inf)) if found)
    if bad.all():
        said = (f"{path}: every one of its {len(pts)} points is {what} ({why}): the camera saw no surface in this "
                "frame")
        if empty:
            return pts[:0], said
        raise PredictionInputError(f"{said}; give a frame that sees the liver")
    return pts[~bad], (f"{path}: {int(bad.sum())} of {len(pts)} points dropped, their coordinates {what} ({why}); "
                       f"{int((~bad).sum())} read")


def _read_table(path: Path) -> np.ndarray:
    """The ``(n, 3)`` rows of a text point file, read as the mesh stage reads its own
    (:func:`liverforce.geometry.point_table.read_table`)."""
    from liverforce.geometry.point_table import PointTableError, read_table

    try:
        return read_table(path, columns=(3,))[0]
    except PointTableError as exc:
        raise PredictionInputError(f"{exc}; expected exactly x, y, z numbers per row") from None


def check_header_units(path: str | Path, frame: InputFrame) -> None:
    """Refuse a text point file whose header names a unit for every column (``x_mm,y_mm,z_mm``) other than the
    units ``frame`` reads every point input in (``--units``, the context's ``units``, the ``--frame`` record's;
    mm when none says), in the mesh stage's words (:func:`liverforce.geometry.point_table.header_unit_clash`).
    A header that agrees or names no unit, and a file that is not a text point file, pass."""
    from liverforce.geometry.point_table import TEXT_SUFFIXES, header_unit_clash

    path = Path(path)
    if path.suffix.lower() not in TEXT_SUFFIXES:
        return
    clash = header_unit_clash(path, frame.scale, frame.units)
    if clash is None:
        return
    said = clash[0]
    fix = f"convert this file to {frame.units}" if said not in UNITS_MM else (
        f"declare --units {said} (units: {said} in a context file) if every point input is in {said}, else "
        f"convert this file to {frame.units}")
    raise PredictionInputError(f"{clash[1]}: {fix} (or correct its header)")


def read_surface(path: str | Path, units: str | None = "mm") -> tuple[np.ndarray, np.ndarray]:
    """``(points (s, 3) mm, triangles (m, 3))`` of a surface or volume mesh file."""
    path = Path(path)
    if not path.is_file():
        raise PredictionInputError(f"{path}: no such surface file")
    scale = unit_scale(units)
    suffix = path.suffix.lower()
    if suffix == ".ply":
        ply = _read_ply(path)
        if ply.polygons:
            raise PredictionInputError(f"{path}: only triangular faces are supported ({ply.polygons} of the PLY "
                                       "file's faces are not triangles: triangulate it, e.g. in MeshLab or Slicer)")
        if ply.faces is None or not len(ply.faces):
            raise PredictionInputError(f"{path}: a surface needs faces; this PLY file holds only points")
        return ply.points * scale, ply.faces
    if suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as z:
                return np.asarray(z["points"], dtype=np.float64) * scale, np.asarray(z["facets"], dtype=np.int64)
        except (ValueError, OSError, EOFError, KeyError, zipfile.BadZipFile) as exc:  # KeyError: without those arrays
            raise PredictionInputError(f"{path}: cannot read the surface ({type(exc).__name__}: {exc}); an .npz "
                                       "surface holds 'points' (s, 3) and 'facets' (m, 3)") from None
    import meshio

    try:
        mesh = meshio.read(path)
    except SystemExit as exc:  # meshio 5.3.5 calls sys.exit on some unreadable files
        raise PredictionInputError(f"{path}: meshio cannot read this file (exit {exc.code})") from None
    except Exception as exc:  # noqa: BLE001 - meshio raises many types; re-raised with the file named
        raise PredictionInputError(f"{path}: meshio cannot read this file ({type(exc).__name__}: {exc})") from exc
    tets = [c.data for c in mesh.cells if c.type == "tetra"]
    if tets:  # a volume mesh's surface is its tets' boundary: triangle cells beside them (Gmsh physical groups,
        # tagged supports) may cover only part of it
        pts = np.asarray(mesh.points, dtype=np.float64)[:, :3]
        return pts * scale, tet_boundary(np.vstack(tets), pts)
    tris = [c.data for c in mesh.cells if c.type == "triangle"]
    if tris:
        return np.asarray(mesh.points, dtype=np.float64)[:, :3] * scale, np.vstack(tris).astype(np.int64)
    raise PredictionInputError(f"{path}: no triangles or tetrahedra in this mesh")


def tet_boundary(tets: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Boundary triangles of a tet mesh (faces used by one tet), oriented outwards.

    Tets are first made positively oriented (a swap of two vertices where the
    signed volume is negative), so the faces ``(1 2 3), (0 3 2), (0 1 3), (0 2 1)``
    point out of their tet.
    """
    tets = np.asarray(tets, dtype=np.int64).copy()
    e = points[tets[:, 1:]] - points[tets[:, :1]]
    neg = np.einsum("ti,ti->t", e[:, 0], np.cross(e[:, 1], e[:, 2])) < 0
    tets[neg] = tets[neg][:, [0, 2, 1, 3]]
    faces = np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 3, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 1]]])
    key = np.sort(faces, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return faces[counts[inv.ravel()] == 1]


# --------------------------------------------------------------------------- context
def _read_doc(path: Path) -> dict:
    text = path.read_text()
    try:
        if path.suffix.lower() in (".yaml", ".yml"):
            import yaml

            doc = yaml.safe_load(text)
        else:
            doc = json.loads(text)
    except Exception as exc:  # noqa: BLE001 - JSON and YAML parse errors, re-raised with the file named
        raise PredictionInputError(f"{path}: not valid {path.suffix.lstrip('.').upper()} ({exc})") from exc
    if not isinstance(doc, dict):
        raise PredictionInputError(f"{path}: the context must be a mapping of keys to values")
    return doc


def _read_triangles(path: Path) -> np.ndarray:
    """``(m, 3)`` vertex indices from ``.npy`` or a comma/space-separated text file (``.csv``, ``.txt``)."""
    if not path.is_file():
        raise PredictionInputError(f"{path}: no such triangles file")
    try:
        if path.suffix.lower() == ".npy":
            return np.load(path, allow_pickle=False)
        return np.loadtxt(path, delimiter="," if path.suffix.lower() == ".csv" else None, ndmin=2)
    except (OSError, ValueError, EOFError) as exc:
        raise PredictionInputError(f"{path}: cannot read the triangles ({type(exc).__name__}: {exc})") from None


CONTEXT_KEYS = {"exertion_point_mm", "material_params_mpa", "surface", "roi_undeformed", "frame", "liver_centroid_mm",
                "inertia_mm5", "tool_thickness_mm", "units", "roi_fraction", "frame_radius_mm", "mesh",
                "probe_compliance_mm_per_n", "roi_triangles", "input_frame"}


def load_context(source: str | Path | dict, predictor, *, overrides: dict | None = None) -> Preop:
    """A checked :class:`Preop` from a context file (module docstring) or dict, plus ``overrides``.

    Relative file paths in a file are taken relative to it. ``roi_fraction``
    and ``frame_radius_mm`` default to the model's (bundle meta or shipped
    defaults). The context comes in the model's frame (RAS mm) whatever ``input_frame`` says; forces predicted
    from it are in RAS: :func:`read_context` also returns the inputs' frame to give them back in.
    """
    return read_context(source, predictor, overrides=overrides)[0]


def read_context(source: str | Path | dict, predictor, *, overrides: dict | None = None) -> tuple[Preop, InputFrame]:
    """:func:`load_context`, and the :class:`~liverforce.serve.input_frame.InputFrame` of its points.

    Every point of the context (and of the file it is read from) is in ``units`` and in ``input_frame`` (RAS,
    LPS, a 4x4, a file of one, or the liver's import record ``results/<exp>/geometry/imp-<name>.json``; default
    RAS); the :class:`Preop` is in the model's frame, RAS mm. The tet ``mesh`` is the mesh stage's copy,
    already in RAS mm; beside the mesh of a liver imported in another frame or segmented from a label volume,
    ``input_frame`` must be given (``RAS`` for inputs already in RAS mm): the record beside the mesh says so.
    """
    if isinstance(source, dict):
        doc, base = dict(source), Path.cwd()
    elif source is None:
        doc, base = {}, Path.cwd()
    else:
        path = Path(source)
        if not path.is_file():
            raise PredictionInputError(f"{path}: no such context file")
        doc, base = _read_doc(path), path.parent
    doc.update({k: v for k, v in (overrides or {}).items() if v is not None})
    unknown = set(doc) - CONTEXT_KEYS
    if unknown:
        raise PredictionInputError(f"context: unknown keys {sorted(unknown)}; known: {sorted(CONTEXT_KEYS)}")
    if "exertion_point_mm" not in doc:
        raise PredictionInputError("context: exertion_point_mm is required (the tool contact point, mm)")
    if "mesh" in doc and doc.get("input_frame") is None:
        _frame_must_be_said(base / doc["mesh"] if not Path(doc["mesh"]).is_absolute() else Path(doc["mesh"]))
    fr = InputFrame.resolve(doc.get("input_frame"), doc.get("units"), base=base)
    point = fr.points(doc["exertion_point_mm"])
    material = doc.get("material_params_mpa")

    def rel(p):
        p = Path(p)
        return p if p.is_absolute() else base / p

    computed = [k for k in ("liver_centroid_mm", "inertia_mm5", "tool_thickness_mm", "roi_triangles") if k in doc]
    if "surface" in doc or ("mesh" in doc and "roi_undeformed" not in doc):
        if computed:
            what = "a surface" if "surface" in doc else "the tet 'mesh' alone (its surface is then used)"
            raise PredictionInputError(f"context: give either {what} or {'/'.join(computed)} with roi_undeformed "
                                       f"and frame, not both (they are computed from the surface)")
        if "surface" in doc:
            pts, tri = fr.surface(*read_surface(rel(doc["surface"])))
        else:
            # no surface given: the tet mesh's own surface, the one the training cases were cut from (RAS mm, as
            # the mesh stage wrote it: not converted by input_frame). A lab's segmented surface differs from it by
            # the geometry stage's repairs and smoothing and by the mesher, and ROI, thickness and size would too.
            pts, tri = read_surface(rel(doc["mesh"]))
        preop = Preop.from_surface(pts, tri, point, material,
                                   roi_fraction=float(doc.get("roi_fraction", predictor.roi_fraction)),
                                   frame_radius_mm=float(doc.get("frame_radius_mm", predictor.frame_radius_mm)))
    elif "roi_undeformed" in doc:
        if "frame" not in doc:
            raise PredictionInputError("context: with roi_undeformed, give the local frame {normal, t1, t2} too")
        if fr.reflects:
            raise PredictionInputError("context: the input frame reflects, which would turn the given local frame "
                                       "{normal, t1, t2} left-handed; give the undeformed 'surface' instead (the "
                                       "frame is then computed in the model's frame)")
        fr_doc = doc["frame"]
        try:
            frame = fr.directions(np.array([fr_doc["t1"], fr_doc["t2"], fr_doc["normal"]], dtype=np.float64))
        except (KeyError, TypeError, ValueError) as exc:
            raise PredictionInputError(f"context: frame must be {{normal: [3], t1: [3], t2: [3]}} ({exc})") from exc
        roi = doc["roi_undeformed"]
        roi = fr.points(read_points(rel(roi), frame=fr) if isinstance(roi, (str, Path)) else roi)
        tris = doc.get("roi_triangles")
        if isinstance(tris, (str, Path)):
            tris = _read_triangles(rel(tris))
        preop = Preop(
            exertion_point_mm=point, frame=frame, roi_undeformed_mm=roi, material_params_mpa=material,
            liver_centroid_mm=None if "liver_centroid_mm" not in doc else fr.points(doc["liver_centroid_mm"]),
            inertia_mm5=None if "inertia_mm5" not in doc else fr.inertia(doc["inertia_mm5"]),
            tool_thickness_mm=None if "tool_thickness_mm" not in doc else fr.length(doc["tool_thickness_mm"]),
            roi_triangles=tris,
        )
    else:
        raise PredictionInputError("context: give the undeformed 'surface' file, the tet 'mesh' (its own surface is "
                                   "then used), or 'roi_undeformed' with 'frame'")
    if "probe_compliance_mm_per_n" in doc:
        if "mesh" in doc:
            raise PredictionInputError("context: give either the tet 'mesh' or probe_compliance_mm_per_n, not both")
        # in the model's local frame (t1, t2, n) at the point: the one computed from the surface in RAS mm, or the
        # given frame converted; only its units change (m/N -> mm/N with units: m)
        C = np.asarray(doc["probe_compliance_mm_per_n"], dtype=np.float64) * fr.scale
        preop = preop.with_compliance(C)
    try:
        if "probe_compliance_mm_per_n" not in doc and "mesh" in doc and predictor.model.uses_state:
            from liverforce.serve.probe import with_probe

            preop = with_probe(preop, rel(doc["mesh"]), predictor.model.meta, frame=fr)
        predictor.check_preop(preop, frame=fr)
    except OffSurfaceError as exc:
        if "mesh" not in doc:
            raise
        raise OffSurfaceError(str(exc) + _simulated_points(rel(doc["mesh"]), predictor, fr, exc.point_mm),
                              exc.point_mm) from None
    return preop, fr


#: a refused exertion point within this distance (mm) of where the sweep pressed on its liver is told where
SIMULATED_NEAR_MM = 50.0


def _simulated_points(mesh: Path, predictor, frame: InputFrame, point_mm) -> str:
    """Where the sweep of the model's scenario pressed on the liver of ``mesh`` (``<root>/mesh/<gid>.vtu``), as
    ``<root>/sweep/<scenario>/sweep.json`` records it (``exertion_points_mm``, RAS mm, each on the mesh's
    surface; a lab's points were moved onto it): the one nearest ``point_mm`` in the inputs' units and frame,
    and where to find them all. Empty when there is no such record (a mesh outside a results layout, a model
    without its scenario, a sweep of other livers)."""
    from liverforce.layout import Layout, gid_of
    from liverforce.serve.input_frame import as_given

    try:
        path = Path(mesh).resolve()
        scenario = (predictor.model.meta or {}).get("scenario")
        if path.parent.name != "mesh" or not scenario or point_mm is None:
            return ""
        layout = Layout(path.parent.parent)
        report = Path(layout.sweep_report(str(scenario)))
        pts = np.asarray(json.loads(report.read_text())["exertion_points_mm"][gid_of(path)],
                         dtype=np.float64).reshape(-1, 3)
    except (OSError, ValueError, KeyError, TypeError):
        return ""
    if not len(pts) or not np.isfinite(pts).all():
        return ""
    dist = np.linalg.norm(pts - np.asarray(point_mm, dtype=np.float64), axis=1)
    if not dist.min() <= SIMULATED_NEAR_MM:  # a point far off the liver (units, frame): no case is near it
        return ""
    near = pts[int(np.argmin(dist))]
    return (f". The sweep of scenario {scenario} pressed on this liver at {len(pts)} points on the mesh's surface "
            f"(given points were moved onto it), the nearest at {as_given(frame, near)}: see {report} "
            f"(exertion_points_mm, RAS mm) and {layout.cases(str(scenario))} (exertion_point_mm of each case)")


def _frame_must_be_said(mesh: Path) -> None:
    """Refuse inputs of unstated frame beside the mesh of a liver the geometry stage turned into RAS.

    Such inputs may be in the liver file's own frame or already in RAS: near a surface that is roughly symmetric,
    either can pass the mesh's checks and give a different force, so the frame has to be said."""
    from liverforce.layout import surface_meta_of_mesh

    try:
        record = surface_meta_of_mesh(mesh)
    except ValueError:  # not a file of the results layout: nothing recorded
        return
    if not record.is_file():
        return
    try:  # the record read as an input frame: a label volume's is refused there (its header set the frame)
        recorded = InputFrame.resolve(record)
    except PredictionInputError as exc:
        raise PredictionInputError(f"the mesh {mesh}: {exc}") from None
    if not np.array_equal(recorded.matrix, np.eye(4)):
        raise PredictionInputError(
            f"the mesh {mesh} is of a liver imported in another frame ({recorded.describe()}): say which frame "
            f"these inputs are in, --frame {record} for the liver file's own frame and units (input_frame: in a "
            "context file), or --frame RAS for inputs already in the mesh's RAS mm")


# --------------------------------------------------------------------------- atomic writes
def write_frame(df, path: str | Path) -> Path:
    """Write a pandas DataFrame as Parquet (``.parquet``) or CSV (``.csv``) atomically."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".parquet", ".csv"):
        raise PredictionInputError(f"{path}: results are written as .parquet or .csv")
    with atomic_path(path) as tmp:
        if suffix == ".parquet":
            df.to_parquet(tmp, index=False)
        else:
            df.to_csv(tmp, index=False, float_format="%.9g")
    return path
