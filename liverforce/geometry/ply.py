"""The one PLY reader, for every stage: a point cloud's or a surface's vertices and triangles.

``liverforce predict`` reads its point clouds and surfaces with it (:func:`liverforce.serve.files.read_points`,
:func:`~liverforce.serve.files.read_surface`) and the mesh stage its support and exertion-point files
(:func:`liverforce.mesh.supports.read_point_file`); ``geometry`` is the lowest layer both may import.

What it reads:

- ``format ascii``, ``binary_little_endian`` and ``binary_big_endian`` (1.0); ``comment`` and ``obj_info``
  header lines skipped; CRLF line ends accepted;
- the ``vertex`` element's ``x y z`` (any numeric type; other vertex properties such as normals or colours,
  in any order, ignored);
- the ``face`` element's list property (``vertex_indices`` or ``vertex_index``, any count and index type) as
  triangles; other face properties (flags, colours) skipped; a polygon that is not a triangle is reported by
  :attr:`PlyData.polygons` rather than read;
- any other element (a ``camera``, ``edge``, ...; before or after the vertices) skipped, list properties
  included.

What it refuses, naming the file (:class:`PlyError`): no ``ply`` magic line, no ``end_header``, an unknown
format or property type, a count that is not a whole number, a property outside an element, no vertex element
with ``x``, ``y`` and ``z``, a value that is not a number, and a file that ends before the header's counts do
(truncated: the vertices it promised are said). Values are returned as read (``nan`` included): callers judge
them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2",
    "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}
_FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")
_FACE_LISTS = ("vertex_indices", "vertex_index")


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


@dataclass
class _Element:
    name: str
    count: int
    props: list  # (name, dtype) or (name, count dtype, item dtype) for a list


def _header(path: Path, raw: bytes) -> tuple[str, list[_Element], int]:
    if not raw.startswith(b"ply"):
        raise PlyError(f"{path}: not a PLY file (no 'ply' magic line)")
    end = raw.find(b"end_header")
    if end < 0:
        raise PlyError(f"{path}: the PLY header has no end_header")
    body = raw.find(b"\n", end)
    body = len(raw) if body < 0 else body + 1
    fmt, elements = None, []
    for n, line in enumerate(raw[:end].decode("ascii", "replace").splitlines()[1:], start=2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format":
            fmt = words[1] if len(words) > 1 else ""
            if fmt not in _FORMATS:
                raise PlyError(f"{path}: unsupported PLY format '{fmt}' (header line {n}; expected one of "
                               f"{', '.join(_FORMATS)})")
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise PlyError(f"{path}: PLY header line {n} '{line.strip()}': expected 'element <name> <count>' "
                               "with a whole-number count")
            elements.append(_Element(words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise PlyError(f"{path}: PLY header line {n} '{line.strip()}': a property before any element")
            types = words[2:-1] if words[1:2] == ["list"] else words[1:-1]
            bad = [t for t in types if t not in _TYPES]
            if len(words) < 3 or bad or (words[1] == "list" and len(types) != 2):
                raise PlyError(f"{path}: PLY header line {n} '{line.strip()}': unknown property type "
                               f"{bad[0] if bad else '(missing)'} (known: {', '.join(sorted(set(_TYPES)))})")
            elements[-1].props.append((words[-1], *(_TYPES[t] for t in types)))
        else:
            raise PlyError(f"{path}: PLY header line {n} '{line.strip()}' is not a PLY header line")
    if fmt is None:
        raise PlyError(f"{path}: the PLY header has no format line")
    return fmt, elements, body


def read_ply(path: str | Path) -> PlyData:
    """The vertices (and triangles) of a PLY file (module docstring); :class:`PlyError` if unreadable."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise PlyError(f"{path}: cannot read the file ({exc.strerror or exc})") from None
    fmt, elements, pos = _header(path, raw)
    read = _read_ascii if fmt == "ascii" else _read_binary
    points = faces = None
    polygons = 0
    got = read(path, raw, pos, elements, ">" if fmt == "binary_big_endian" else "<")
    for el, values in zip(elements, got):
        if el.name == "vertex":
            names = [p[0] for p in el.props]
            missing = [a for a in "xyz" if a not in names]
            if missing:
                raise PlyError(f"{path}: the PLY vertex element has no {', '.join(missing)} property "
                               f"(it has {', '.join(names) or 'none'})")
            points = np.column_stack([np.asarray(values[names.index(a)], np.float64) for a in "xyz"]) \
                if el.count else np.zeros((0, 3))
        elif el.name == "face":
            lists = [i for i, p in enumerate(el.props) if len(p) == 3]
            pick = [i for i in lists if el.props[i][0] in _FACE_LISTS] or lists
            if not pick:
                continue
            rows = values[pick[0]]
            if isinstance(rows, np.ndarray):  # every face with the same count (binary)
                faces = rows if rows.shape[1] == 3 else np.zeros((0, 3), np.int64)
                polygons = 0 if rows.shape[1] == 3 else len(rows)
            else:
                tri = [r for r in rows if len(r) == 3]
                polygons = len(rows) - len(tri)
                faces = np.asarray(tri, np.int64).reshape(-1, 3)
    if points is None:
        raise PlyError(f"{path}: the PLY file has no vertex element with x, y, z")
    if faces is not None and len(faces) and (faces.min() < 0 or faces.max() >= len(points)):
        raise PlyError(f"{path}: a PLY face refers to a vertex that does not exist (indices "
                       f"{faces.min()}..{faces.max()}, {len(points)} vertices)")
    return PlyData(points, faces, polygons)


def _short(path, el: _Element, done: int):
    return PlyError(f"{path}: the PLY file ends early: its header promises {el.count} {el.name} rows, the data "
                    f"holds {done} (a truncated or interrupted write: export the file again)")


def _read_ascii(path, raw: bytes, pos: int, elements: list[_Element], _endian) -> list[list]:
    tokens = raw[pos:].split()
    at, out = 0, []
    for el in elements:
        if not any(len(p) == 3 for p in el.props):  # fixed width: one block
            width = len(el.props)
            block = tokens[at:at + width * el.count]
            if len(block) < width * el.count:
                raise _short(path, el, len(block) // max(width, 1))
            try:
                vals = np.asarray(block, dtype=np.float64).reshape(el.count, width)
            except ValueError:
                bad = next(i for i, t in enumerate(block) if not _is_number(t))
                raise PlyError(f"{path}: PLY {el.name} row {bad // width} holds '{block[bad].decode(errors='replace')}'"
                               ", not a number") from None
            out.append([vals[:, i] for i in range(width)])
            at += width * el.count
            continue
        cols = [[] for _ in el.props]
        for row in range(el.count):
            for i, p in enumerate(el.props):
                try:
                    if len(p) == 3:
                        n = int(tokens[at])
                        cols[i].append([int(t) for t in tokens[at + 1:at + 1 + n]])
                        if len(cols[i][-1]) < n:
                            raise IndexError
                        at += 1 + n
                    else:
                        cols[i].append(float(tokens[at]))
                        at += 1
                except IndexError:
                    raise _short(path, el, row) from None
                except ValueError:
                    raise PlyError(f"{path}: PLY {el.name} row {row} holds '{tokens[at].decode(errors='replace')}' "
                                   "where a whole number (a list's count or index) is expected") from None
        out.append(cols)
    return out


def _is_number(token: bytes) -> bool:
    try:
        float(token)
        return True
    except ValueError:
        return False


def _read_binary(path, raw: bytes, pos: int, elements: list[_Element], endian: str) -> list[list]:
    out = []
    for el in elements:
        lists = [p for p in el.props if len(p) == 3]
        if not lists:
            dt = np.dtype([(f"p{i}", endian + p[1]) for i, p in enumerate(el.props)])
            if len(raw) - pos < dt.itemsize * el.count:
                raise _short(path, el, (len(raw) - pos) // max(dt.itemsize, 1))
            block = np.frombuffer(raw, dtype=dt, count=el.count, offset=pos)
            out.append([block[f"p{i}"] for i in range(len(el.props))])
            pos += dt.itemsize * el.count
            continue
        fast = _binary_constant_lists(raw, pos, el, endian)
        if fast is not None:
            cols, pos = fast
            out.append(cols)
            continue
        cols = [[] for _ in el.props]
        for row in range(el.count):
            for i, p in enumerate(el.props):
                size = np.dtype(p[1]).itemsize
                if pos + size > len(raw):
                    raise _short(path, el, row)
                value = np.frombuffer(raw, endian + p[1], 1, pos)[0]
                pos += size
                if len(p) == 3:
                    n, isz = int(value), np.dtype(p[2]).itemsize
                    if pos + n * isz > len(raw):
                        raise _short(path, el, row)
                    cols[i].append(np.frombuffer(raw, endian + p[2], n, pos).astype(np.int64).tolist())
                    pos += n * isz
                else:
                    cols[i].append(value)
        out.append(cols)
    return out


def _binary_constant_lists(raw: bytes, pos: int, el: _Element, endian: str):
    """An element whose lists all hold the same count as the first row's (all triangles): one strided read, or
    ``None`` when the rows differ (read row by row then)."""
    fields, at = [], pos
    for i, p in enumerate(el.props):
        if len(p) == 3:
            if at + np.dtype(p[1]).itemsize > len(raw):
                return None
            n = int(np.frombuffer(raw, endian + p[1], 1, at)[0])
            fields += [(f"n{i}", endian + p[1]), (f"p{i}", endian + p[2], (n,))]
            at += np.dtype(p[1]).itemsize + n * np.dtype(p[2]).itemsize
        else:
            fields.append((f"p{i}", endian + p[1]))
            at += np.dtype(p[1]).itemsize
    dt = np.dtype(fields)
    if el.count == 0 or len(raw) - pos < dt.itemsize * el.count:
        return None
    block = np.frombuffer(raw, dtype=dt, count=el.count, offset=pos)
    for i, p in enumerate(el.props):
        if len(p) == 3 and (block[f"n{i}"] != dt[f"p{i}"].shape[0]).any():
            return None
    cols = [block[f"p{i}"].astype(np.int64) if len(p) == 3 else block[f"p{i}"] for i, p in enumerate(el.props)]
    return cols, pos + dt.itemsize * el.count
