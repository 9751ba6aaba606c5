"""The one PLY reader, for every stage: a point cloud's or a surface's vertices and triangles.

``liverforce predict`` reads its point clouds and surfaces with it (:func:`liverforce.serve.files.read_points`,
:func:`~liverforce.serve.files.read_surface`) and the mesh stage its support and exertion-point files
(:func:`liverforce.mesh.supports.read_point_file`); ``geometry`` is the lowest layer both may import.

The parsing is the ``plyfile`` library's; this module picks the vertices and triangles out of what it read and
words its refusals for our users (the file named, the fault in plain words). What it reads:

- ``format ascii``, ``binary_little_endian`` and ``binary_big_endian`` (1.0); ``comment`` and ``obj_info``
  header lines skipped; LF, CRLF or CR line ends;
- the ``vertex`` element's ``x y z`` (any numeric type; other vertex properties such as normals or colours,
  in any order, ignored);
- the ``face`` element's list property (``vertex_indices`` or ``vertex_index``, else the first list; any count
  and index type) as triangles; other face properties (flags, colours) ignored; a polygon that is not a triangle
  is reported by :attr:`PlyData.polygons` rather than read. Binary triangles (or quads) are read in one block
  (memory mapped); a binary file with faces of mixed lengths is read again row by row;
- any other element (a ``camera``, ``edge``, ...; before or after the vertices) read and ignored.

A ``comment`` or ``obj_info`` line holding bytes that are not ASCII (an exporter's name with an accent, in
Latin-1 or UTF-8) is read with those bytes as ``?``: plyfile would refuse the file for a comment.

What it refuses, naming the file (:class:`PlyError`): no ``ply`` magic line, no ``end_header``, a header line
other than a comment that is not ASCII, ASCII data that is not ASCII, an unknown format or property type, a
count that is not a whole number, a property outside an element, no vertex element with ``x``, ``y`` and ``z``,
a value that is not a number (ASCII: the row and property are named), a row with too few or too many values,
and a file that ends before the header's counts do (truncated: the rows it promised are said). Values are
returned as read (``nan`` included): callers judge them.
"""

from __future__ import annotations

import re
import shutil
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import plyfile

_FACE_LISTS = ("vertex_indices", "vertex_index")
_FORMATS = "ascii, binary_little_endian, binary_big_endian"
_TYPES = "char, uchar, short, ushort, int, uint, float, double, int8, uint8, int16, uint16, int32, uint32, " \
         "float32, float64"


class PlyError(ValueError):
    """A PLY file could not be read; the message names the file and what is wrong."""


@dataclass
class PlyData:
    """What :func:`read_ply` read: ``points`` ``(n, 3)`` float64; ``faces`` ``(m, 3)`` int64 triangles or
    ``None`` (no face element); ``polygons`` the number of faces with other than three vertices (not in
    ``faces``)."""

    points: np.ndarray
    faces: np.ndarray | None
    polygons: int = 0


def read_ply(path: str | Path) -> PlyData:
    """The vertices (and triangles) of a PLY file (module docstring); :class:`PlyError` if unreadable."""
    path = Path(path)
    try:
        if path.stat().st_size == 0:  # plyfile would say it lacks the 'ply' magic line
            raise PlyError(f"{path}: the file is empty (0 bytes: no header, no points; a writer or a copy that "
                           "stopped, a camera's driver for a frame): write or export it again")
        ply = _read(path)
    except OSError as exc:
        raise PlyError(f"{path}: cannot read the file ({exc.strerror or exc})") from None
    except plyfile.PlyHeaderParseError as exc:
        raise PlyError(_header_fault(path, exc)) from None
    except plyfile.PlyElementParseError as exc:
        raise PlyError(_data_fault(path, exc)) from None
    except UnicodeDecodeError:
        why = "not a PLY file (no 'ply' magic line)" if not _head(path).startswith(b"ply") else \
            "the PLY header (or, format ascii, its data) holds a byte that is not ASCII text"
        raise PlyError(f"{path}: {why}") from None
    except OverflowError as exc:  # an ASCII value outside its property's type, e.g. 300 for a uchar
        raise PlyError(f"{path}: a PLY value does not fit its property's type ({exc})") from None
    except MemoryError as exc:
        raise PlyError(f"{path}: the PLY header's element counts need more memory than there is ({exc}); "
                       "a corrupted header?") from None
    except ValueError as exc:  # plyfile: a negative count, two elements or properties of one name
        why = "an element count is negative" if "negative dimensions" in str(exc) else str(exc)
        raise PlyError(f"{path}: not a readable PLY file: {why}") from None
    return _pick(path, ply)


def _read(path: Path) -> plyfile.PlyData:
    """plyfile's reading of the file. Binary faces all of one length (triangles; else quads) are memory-mapped
    in one block, which plyfile can do only when told the length; if the first face is not a triangle the file is
    tried again with quads, and if the faces' lengths differ it is read again with the faces row by row. A header
    plyfile would refuse for its form alone (:func:`_plain_header`) is rewritten, with the data after it, to a
    temporary file that plyfile reads (and memory-maps) in its place; the arrays are copied out before it goes."""
    header = _plain_header(path)
    if header is None:
        return _read_as_is(path)
    text, end = header
    with tempfile.TemporaryDirectory(prefix="liverforce-ply-") as tmp:
        plain = Path(tmp) / "plain.ply"
        with open(path, "rb") as src, open(plain, "wb") as dst:
            dst.write(text)
            src.seek(end)
            shutil.copyfileobj(src, dst, 1 << 20)
        return _copied(_read_as_is(plain))


def _read_as_is(path: Path) -> plyfile.PlyData:
    with warnings.catch_warnings():  # numpy's, on an empty ASCII list (a face of no vertices: counted as a polygon)
        warnings.filterwarnings("ignore", message="loadtxt: input contained no data")
        for n in (3, 4):
            try:
                return plyfile.PlyData.read(path, known_list_len={"face": dict.fromkeys(_FACE_LISTS, n)})
            except plyfile.PlyElementParseError as exc:
                if exc.message != "unexpected list length" or exc.row:
                    break
        return plyfile.PlyData.read(path)


def _copied(ply: plyfile.PlyData) -> plyfile.PlyData:
    """``ply`` with every element's data in memory (not mapped from a file about to be deleted)."""
    for el in ply.elements:
        el.data = np.array(el.data)
    return ply


_END = re.compile(rb"(?:^|\r\n|\r|\n)end_header[ \t]*(\r\n|\r|\n)")
_EOL = re.compile(rb"\r\n|\r|\n")
_COMMENT = re.compile(rb"^[ \t]*(?:comment|obj_info)\b")


def _plain_header(path: Path) -> tuple[bytes, int] | None:
    """``(header, end)``: the header (through ``end_header``'s line end, which starts the data) in the form plyfile
    reads, and where the file's own header ends, when that form differs from the file's; else None (the file is
    read as it is, and refused by plyfile if it must be). The form: every line ending as the ``end_header`` line's
    (plyfile takes it from the ``ply`` line, and an exporter may mix them), no trailing blanks, and in
    ``comment`` and ``obj_info`` lines the bytes that are not ASCII (an exporter's name with an accent) as ``?``.
    A keyword line that is not ASCII is left for plyfile to refuse."""
    head = _head(path, 1 << 16)  # a header; the file itself is plyfile's to read
    m = _END.search(head)
    if not head.startswith(b"ply") or m is None:
        return None
    eol, end = m.group(1), m.end()
    lines = _EOL.split(head[:m.start()])
    plain = []
    for line in lines:
        if not line.isascii():
            if not _COMMENT.match(line):
                return None
            line = bytes(c if c < 128 else 63 for c in line)
        plain.append(line.rstrip(b" \t"))
    text = eol.join([*plain, b"end_header"]) + eol
    return None if text == head[:end] else (text, end)


def _pick(path: Path, ply: plyfile.PlyData) -> PlyData:
    if "vertex" not in ply:
        raise PlyError(f"{path}: the PLY file has no vertex element with x, y, z")
    vertex = ply["vertex"]
    names = [p.name for p in vertex.properties]
    missing = [a for a in "xyz" if a not in names]
    if missing:
        raise PlyError(f"{path}: the PLY vertex element has no {', '.join(missing)} property "
                       f"(it has {', '.join(names) or 'none'})")
    lists = [p.name for p in vertex.properties if p.name in "xyz" and isinstance(p, plyfile.PlyListProperty)]
    if lists:
        raise PlyError(f"{path}: the PLY vertex property {lists[0]} is a list, not one number per vertex")
    points = np.column_stack([np.asarray(vertex.data[a], np.float64) for a in "xyz"]).reshape(-1, 3)
    faces, polygons = None, 0
    if "face" in ply:
        lists = [p.name for p in ply["face"].properties if isinstance(p, plyfile.PlyListProperty)]
        pick = [n for n in lists if n in _FACE_LISTS] or lists
        if pick:
            prop = ply["face"].ply_property(pick[0])
            if np.dtype(prop.val_dtype).kind not in "iu":
                raise PlyError(f"{path}: the PLY face list {pick[0]} holds {np.dtype(prop.val_dtype).name} values; "
                               "vertex indices are whole numbers (an integer type such as int or uint)")
            rows = ply["face"].data[pick[0]]
            if rows.dtype != object:  # memory-mapped: every face of one length
                triangles = rows.ndim == 2 and rows.shape[1] == 3
                faces = rows.astype(np.int64) if triangles else np.zeros((0, 3), np.int64)
                polygons = 0 if triangles else len(rows)
            else:
                tri = np.array([len(r) == 3 for r in rows], bool)
                polygons = int((~tri).sum())
                faces = np.stack(rows[tri]).astype(np.int64) if tri.any() else np.zeros((0, 3), np.int64)
    if faces is not None and len(faces) and (faces.min() < 0 or faces.max() >= len(points)):
        raise PlyError(f"{path}: a PLY face refers to a vertex that does not exist (indices "
                       f"{faces.min()}..{faces.max()}, {len(points)} vertices)")
    return PlyData(points, faces, polygons)


# --------------------------------------------------------------------------- plyfile's faults in our words
def _head(path: Path, size: int = 1 << 20) -> bytes:
    try:
        with open(path, "rb") as f:
            return f.read(size)
    except OSError:
        return b""


def _header_fault(path: Path, exc: plyfile.PlyHeaderParseError) -> str:
    n, what = exc.line or 1, exc.message
    if n == 1:
        return f"{path}: not a PLY file (no 'ply' magic line)"
    lines = _head(path).splitlines()  # the file's own lines (LF, CRLF or CR), as plyfile counts them
    text = lines[n - 1].decode("ascii", "replace").strip()[:80] if n <= len(lines) else None
    ends = any(line.strip() == b"end_header" for line in lines[n - 1:])
    where = f"PLY header line {n} '{text}'"
    if what == "early end-of-file":
        if text == "" and ends:
            return f"{path}: PLY header line {n} is blank (a PLY header has no blank lines)"
        return f"{path}: the PLY header has no end_header"
    if what.startswith("expected one of"):
        keyword = (text or "").split()[0] if (text or "").split() else ""
        if "format" in what:
            return f"{path}: the PLY header has no format line ({where} comes first)"
        if keyword == "property":
            return f"{path}: {where}: a property before any element"
        if not ends:
            return f"{path}: the PLY header has no end_header ({where} is not a header line)"
        return f"{path}: {where} is not a PLY header line ({what})"
    if what in ("expected integer count", 'expected "element {name} {count}"'):
        return f"{path}: {where}: expected 'element <name> <count>' with a whole-number count"
    if what.startswith("don't understand format"):
        fmt = what.split("format", 1)[1].strip().strip("'")
        return f"{path}: unsupported PLY format '{fmt}' (header line {n}; expected one of {_FORMATS})"
    if what.startswith("expected version") or what.startswith('expected "format'):
        return f"{path}: {where}: expected 'format <{_FORMATS.replace(', ', '|')}> 1.0'"
    if what.startswith("field type"):
        bad = what.split("'")[1] if what.count("'") >= 2 else "?"
        return f"{path}: {where}: unknown property type {bad} (known: {_TYPES})"
    if "property" in what:
        return (f"{path}: {where}: expected 'property <type> <name>' or "
                "'property list <count type> <index type> <name>'")
    return f"{path}: {where}: {what}"


def _data_fault(path: Path, exc: plyfile.PlyElementParseError) -> str:
    el, row, prop, what = exc.element, exc.row, exc.prop, exc.message
    name = el.name if el is not None else "?"
    has = ", ".join(p.name for p in el.properties) if el is not None else "?"
    if what == "early end-of-file":
        return (f"{path}: the PLY file ends early: its header promises {el.count} {name} rows, the data holds "
                f"{row} (a truncated or interrupted write: export the file again)")
    if what == "early end-of-line":
        end = f"the end of its {prop.name} list" if isinstance(prop, plyfile.PlyListProperty) else \
            f"its {prop.name} value"
        return f"{path}: PLY {name} row {row} stops before {end} (each row holds {has}): a row cut short, or a " \
            "truncated file"
    if what == "expected end-of-line":
        return f"{path}: PLY {name} row {row} holds more values than its header's properties ({has})"
    if what == "malformed input":
        if isinstance(prop, plyfile.PlyListProperty):
            return (f"{path}: PLY {name} row {row}: its {prop.name} list holds a value that is not a whole number "
                    "(a count, then that many indices)")
        kind = "number" if prop.val_dtype.startswith("f") else "whole number"
        return f"{path}: PLY {name} row {row}: its {prop.name} value is not a {kind}"
    return f"{path}: PLY {name} row {row}: {exc}"
