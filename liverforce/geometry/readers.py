"""Readers of surface and volume-mesh files into plain arrays.

Every reader returns a :class:`RawMesh` in the file's own units and raises
:class:`~liverforce.geometry.errors.GeometryError` (never ``SystemExit``) on
a file it cannot read.  Two formats meshio 5.3.5 cannot read are parsed here:

* legacy VTK ``DATASET POLYDATA`` (ASCII and BINARY, classic and 5.1
  OFFSETS/CONNECTIVITY cell layout), see :func:`read_vtk_polydata`;
* Gmsh MSH version 1 (ASCII ``$NOD``/``$ELM``), see :func:`read_gmsh_v1`.

Everything else goes through trimesh (STL, OBJ, PLY, OFF) or meshio (VTU,
legacy VTK UNSTRUCTURED_GRID, Gmsh MSH 2 and 4, XDMF), each call wrapped so that
meshio's ``sys.exit`` on unknown content becomes a ``GeometryError``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from liverforce.geometry.errors import refuse

#: File suffixes read as triangle surfaces by trimesh.
TRIMESH_SUFFIXES = (".stl", ".obj", ".ply", ".off")


@dataclass
class RawMesh:
    """Arrays as found in a file (file units), before any repair.

    ``triangles`` ``(k, 3)`` and ``tets`` ``(m, 4)`` are 0-based int64 and
    may be empty; ``format`` names the reader used.
    """

    points: np.ndarray
    triangles: np.ndarray
    tets: np.ndarray
    format: str


def _empty(n: int) -> np.ndarray:
    return np.zeros((0, n), dtype=np.int64)


# ---------------------------------------------------------------- legacy VTK
_VTK_TYPES = {
    "bit": None,
    "unsigned_char": "u1",
    "char": "i1",
    "unsigned_short": "u2",
    "short": "i2",
    "unsigned_int": "u4",
    "int": "i4",
    "unsigned_long": "u8",
    "long": "i8",
    "float": "f4",
    "double": "f8",
    "vtktypeint32": "i4",
    "vtktypeint64": "i8",
    "vtktypeuint32": "u4",
    "vtktypeuint64": "u8",
}
_VTK_SECTIONS = (
    "POINTS",
    "VERTICES",
    "LINES",
    "POLYGONS",
    "TRIANGLE_STRIPS",
    "POINT_DATA",
    "CELL_DATA",
    "FIELD",
    "METADATA",
    "OFFSETS",
    "CONNECTIVITY",
)
_KEYWORD_LINE = re.compile(rb"(?m)^[ \t]*[A-Za-z_]")


class _Cursor:
    """Byte cursor over a legacy VTK file (ASCII or big-endian BINARY)."""

    def __init__(self, data: bytes, path: Path, binary: bool):
        self.data, self.path, self.binary, self.pos = data, path, binary, 0

    def line(self) -> str | None:
        """Next non-blank line as text, or ``None`` at end of file."""
        while self.pos < len(self.data):
            end = self.data.find(b"\n", self.pos)
            end = len(self.data) if end < 0 else end
            raw = self.data[self.pos:end]
            self.pos = end + 1
            text = raw.strip()
            if text:
                try:
                    return text.decode("ascii")
                except UnicodeDecodeError:
                    raise refuse(
                        self.path,
                        f"legacy VTK: unreadable bytes where a section keyword was expected "
                        f"(offset {self.pos - len(raw) - 1}); the file is corrupted or its header "
                        "counts do not match its data",
                        "Re-export the surface (e.g. as binary STL or PLY)",
                    ) from None
        return None

    def values(self, count: int, vtk_type: str, what: str) -> np.ndarray:
        """Read ``count`` values of ``vtk_type`` after a section header."""
        dtype = _VTK_TYPES.get(vtk_type.lower())
        if dtype is None:
            raise refuse(self.path, f"legacy VTK: unsupported data type {vtk_type!r} in {what}",
                         "Re-export with float/double coordinates and int cells")
        if self.binary:
            dt = np.dtype(dtype).newbyteorder(">")
            end = self.pos + count * dt.itemsize
            if end > len(self.data):
                raise refuse(
                    self.path,
                    f"legacy VTK: {what} declares {count} values ({count * dt.itemsize} bytes) "
                    f"but only {len(self.data) - self.pos} bytes remain: the file is truncated",
                    "Re-export the surface",
                )
            arr = np.frombuffer(self.data, dtype=dt, count=count, offset=self.pos).astype(
                np.float64 if dt.kind == "f" else np.int64
            )
            self.pos = end
            self._expect_section_or_end(what)
            return arr
        match = _KEYWORD_LINE.search(self.data, self.pos)
        end = match.start() if match else len(self.data)
        text = self.data[self.pos:end]
        self.pos = end
        try:
            arr = np.array(text.split(), dtype=np.float64)
        except ValueError:
            raise refuse(self.path, f"legacy VTK: non-numeric data in {what}",
                         "Check the file is a valid ASCII legacy VTK file") from None
        if len(arr) != count:
            raise refuse(
                self.path,
                f"legacy VTK: {what} declares {count} values but {len(arr)} were found: "
                "the header counts do not match the data",
                "Re-export the surface",
            )
        return arr

    def _expect_section_or_end(self, what: str) -> None:
        """After a binary block only whitespace and then a keyword (or EOF) may follow."""
        rest = self.data[self.pos:self.pos + 64].lstrip()
        if not rest:
            return
        head = rest.split(None, 1)[0]
        if head.decode("ascii", "replace") not in _VTK_SECTIONS:
            raise refuse(
                self.path,
                f"legacy VTK: the binary {what} block is followed by unexpected bytes "
                f"(offset {self.pos}: {rest[:16]!r}) instead of a section keyword; the "
                "file is corrupted (e.g. binary data altered by a text conversion) or its "
                "header counts do not match its data",
                "Re-export the surface (e.g. as binary STL or PLY) and check it opens in ParaView",
            )


def _vtk_header(data: bytes) -> tuple[str, str]:
    """Return (format, dataset) from the 4 header lines of a legacy VTK file."""
    lines = data[:1024].split(b"\n", 4)
    if len(lines) < 4 or not lines[0].lower().startswith(b"# vtk datafile"):
        return "", ""
    fmt = lines[2].strip().decode("ascii", "replace").upper()
    dataset = lines[3].strip().decode("ascii", "replace").upper()
    return fmt, dataset


def is_vtk_polydata(path: Path) -> bool:
    """True if ``path`` is a legacy VTK file with ``DATASET POLYDATA``."""
    with open(path, "rb") as fh:
        _, dataset = _vtk_header(fh.read(1024))
    return dataset.replace(" ", "") == "DATASETPOLYDATA"


def read_vtk_polydata(path: str | Path) -> RawMesh:
    """Read a legacy VTK POLYDATA file (ASCII or BINARY).

    Polygons are fan-triangulated, triangle strips are unrolled; vertices
    and lines are ignored; POINT_DATA/CELL_DATA and anything after them are
    ignored.  Both the classic ``POLYGONS n size`` layout and the VTK 5.1
    ``OFFSETS``/``CONNECTIVITY`` layout are read.

    Raises
    ------
    GeometryError
        On a malformed header, a count that does not match the data, a
        corrupted binary block, or cell indices out of range.
    """
    path = Path(path)
    data = path.read_bytes()
    fmt, dataset = _vtk_header(data)
    if not fmt:
        raise refuse(path, "not a legacy VTK file (first line is not '# vtk DataFile Version')",
                     "Check the file type")
    if fmt not in ("ASCII", "BINARY"):
        raise refuse(path, f"legacy VTK: third header line must be ASCII or BINARY, got {fmt!r}",
                     "Re-export the surface")
    if dataset.replace(" ", "") != "DATASETPOLYDATA":
        raise refuse(path, f"legacy VTK: expected DATASET POLYDATA, got {dataset!r}",
                     "Use read_meshio for unstructured grids")
    cur = _Cursor(data, path, binary=fmt == "BINARY")
    for _ in range(4):
        cur.line()
    points = None
    triangles: list[np.ndarray] = []
    while True:
        line = cur.line()
        if line is None:
            break
        parts = line.split()
        key = parts[0].upper()
        if key in ("POINT_DATA", "CELL_DATA", "FIELD", "METADATA"):
            break  # attributes are not needed
        if key == "POINTS":
            if len(parts) != 3:
                raise refuse(path, f"legacy VTK: malformed line {line!r}", "Re-export the surface")
            n = _int(parts[1], path, line)
            points = cur.values(3 * n, parts[2], f"POINTS ({n} points)").reshape(n, 3)
        elif key in ("POLYGONS", "TRIANGLE_STRIPS", "VERTICES", "LINES"):
            if len(parts) != 3:
                raise refuse(path, f"legacy VTK: malformed line {line!r}", "Re-export the surface")
            n, size = _int(parts[1], path, line), _int(parts[2], path, line)
            cells = _read_cells(cur, n, size, key, path)
            if key == "POLYGONS":
                triangles.extend(_fan(c) for c in cells)
            elif key == "TRIANGLE_STRIPS":
                triangles.extend(_strip(c) for c in cells)
        else:
            raise refuse(path, f"legacy VTK: unexpected section {parts[0]!r}",
                         "The file is corrupted or not a POLYDATA file; re-export it")
    if points is None:
        raise refuse(path, "legacy VTK: no POINTS section", "Re-export the surface")
    tri = np.concatenate(triangles) if triangles else _empty(3)
    if len(tri) and (tri.min() < 0 or tri.max() >= len(points)):
        raise refuse(
            path,
            f"legacy VTK: cell indices out of range [0, {len(points)}) (min {tri.min()}, max {tri.max()})",
            "The file is corrupted; re-export the surface",
        )
    return RawMesh(points, tri.astype(np.int64), _empty(4), "vtk-polydata")


def _int(text: str, path: Path, line: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise refuse(path, f"legacy VTK: expected an integer in {line!r}", "Re-export the surface") from None
    if value < 0:
        raise refuse(path, f"legacy VTK: negative count in {line!r}", "Re-export the surface")
    return value


def _read_cells(cur: _Cursor, n: int, size: int, key: str, path: Path) -> list[np.ndarray]:
    """Cells of one section as a list of index arrays (both VTK layouts)."""
    # VTK >= 5.1: "POLYGONS n_offsets n_connectivity" then OFFSETS and CONNECTIVITY
    if cur.data[cur.pos:cur.pos + 64].lstrip().upper().startswith(b"OFFSETS"):
        nxt = cur.line() or ""
        offsets = cur.values(n, nxt.split()[1], f"{key} OFFSETS").astype(np.int64)
        conn_line = cur.line() or ""
        if not conn_line.upper().startswith("CONNECTIVITY"):
            raise refuse(path, f"legacy VTK: {key} OFFSETS not followed by CONNECTIVITY", "Re-export the surface")
        conn = cur.values(size, conn_line.split()[1], f"{key} CONNECTIVITY").astype(np.int64)
        if len(offsets) == 0 or offsets[0] != 0 or offsets[-1] != len(conn) or np.any(np.diff(offsets) < 0):
            raise refuse(path, f"legacy VTK: {key} offsets inconsistent with connectivity", "Re-export the surface")
        return [conn[a:b] for a, b in zip(offsets[:-1], offsets[1:])]
    flat = cur.values(size, "int", f"{key} ({n} cells)").astype(np.int64)
    # fast path: all cells the same length
    if n and size % n == 0:
        k = size // n
        block = flat.reshape(n, k)
        if k > 1 and np.all(block[:, 0] == k - 1):
            return [block[:, 1:]]
    cells, i = [], 0
    for _ in range(n):
        if i >= len(flat) or flat[i] < 0 or i + 1 + flat[i] > len(flat):
            raise refuse(path, f"legacy VTK: {key} cell list is inconsistent with its size {size}",
                         "The file is corrupted; re-export the surface")
        cells.append(flat[i + 1:i + 1 + flat[i]])
        i += 1 + flat[i]
    if i != len(flat):
        raise refuse(path, f"legacy VTK: {key} declares size {size} but its cells use {i} values",
                     "The file is corrupted; re-export the surface")
    return cells


def _fan(cell: np.ndarray) -> np.ndarray:
    """Fan-triangulate one polygon ``(k,)`` or a block of equal polygons ``(n, k)``."""
    cell = np.atleast_2d(cell)
    k = cell.shape[1]
    if k < 3:
        return _empty(3)
    return np.concatenate([cell[:, [0, i, i + 1]] for i in range(1, k - 1)])


def _strip(cell: np.ndarray) -> np.ndarray:
    """Triangles of one triangle strip (alternating winding kept consistent)."""
    cell = np.atleast_2d(cell)
    out = []
    for row in cell:
        for i in range(len(row) - 2):
            a, b, c = row[i], row[i + 1], row[i + 2]
            out.append((a, b, c) if i % 2 == 0 else (b, a, c))
    return np.array(out, dtype=np.int64).reshape(-1, 3)


# ------------------------------------------------------------------ Gmsh v1
def msh_version(path: Path) -> str:
    """``"1"`` for Gmsh v1 (``$NOD``), else the ``$MeshFormat`` version, ``""`` if unknown."""
    with open(path, "rb") as fh:
        head = fh.read(256).lstrip()
    if head.startswith(b"$NOD") or head.startswith(b"$NOE"):
        return "1"
    if head.startswith(b"$MeshFormat"):
        parts = head.split(b"\n")
        if len(parts) > 1 and parts[1].strip():
            return parts[1].split()[0].decode("ascii", "replace")
    return ""


#: Gmsh element type -> number of nodes (v1/v2 numbering), for skipping.
_GMSH_NODES = {1: 2, 2: 3, 3: 4, 4: 4, 5: 8, 6: 6, 7: 5, 8: 3, 9: 6, 10: 9, 11: 10, 15: 1}


def read_gmsh_v1(path: str | Path) -> RawMesh:
    """Read an ASCII Gmsh MSH version 1 file (``$NOD`` … ``$ELM`` … ``$ENDELM``).

    Triangles (type 2), quadrangles (3, split in two triangles) and linear
    tetrahedra (4) are kept; other elements are ignored.  Node numbers may be
    arbitrary (they are mapped to 0-based indices).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="ascii")
    except UnicodeDecodeError:
        raise refuse(path, "Gmsh v1: the file contains non-ASCII bytes (binary v1 is not supported)",
                     "Save it as ASCII MSH (v1, v2 or v4)") from None
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    try:
        i_nod = next(i for i, ln in enumerate(lines) if ln in ("$NOD", "$NOE"))
        i_elm = next(i for i, ln in enumerate(lines) if ln == "$ELM")
    except StopIteration:
        raise refuse(path, "Gmsh v1: missing $NOD or $ELM section", "Check the file is a Gmsh v1 mesh") from None
    try:
        n_nodes = int(lines[i_nod + 1])
        node_rows = np.array(" ".join(lines[i_nod + 2:i_nod + 2 + n_nodes]).split(), dtype=np.float64)
        node_rows = node_rows.reshape(n_nodes, 4)
        if lines[i_nod + 2 + n_nodes] != "$ENDNOD" and lines[i_nod + 2 + n_nodes] != "$ENDNOE":
            raise ValueError("node count does not match $ENDNOD position")
        n_elm = int(lines[i_elm + 1])
        elm_lines = lines[i_elm + 2:i_elm + 2 + n_elm]
        if lines[i_elm + 2 + n_elm] != "$ENDELM":
            raise ValueError("element count does not match $ENDELM position")
    except (ValueError, IndexError) as exc:
        raise refuse(path, f"Gmsh v1: malformed node or element section ({exc})",
                     "Check the file is a complete Gmsh v1 mesh") from None
    ids = node_rows[:, 0].astype(np.int64)
    lookup = {int(t): k for k, t in enumerate(ids)}
    tris, tets = [], []
    for ln in elm_lines:
        f = ln.split()
        try:
            etype, nn = int(f[1]), int(f[4])
            nodes = [lookup[int(t)] for t in f[5:5 + nn]]
        except (ValueError, IndexError, KeyError) as exc:
            raise refuse(path, f"Gmsh v1: bad element line {ln!r} ({exc!r})",
                         "Check the file is a complete Gmsh v1 mesh") from None
        if len(nodes) != nn:
            raise refuse(path, f"Gmsh v1: element line {ln!r} has fewer nodes than declared",
                         "Check the file")
        if etype == 2:
            tris.append(nodes)
        elif etype == 3:
            tris.extend([[nodes[0], nodes[1], nodes[2]], [nodes[0], nodes[2], nodes[3]]])
        elif etype == 4:
            tets.append(nodes)
    tri = np.array(tris, dtype=np.int64).reshape(-1, 3)
    tet = np.array(tets, dtype=np.int64).reshape(-1, 4)
    return RawMesh(node_rows[:, 1:4].copy(), tri, tet, "gmsh-v1")


# ---------------------------------------------------------- meshio, trimesh
def read_meshio_mesh(path: str | Path, file_format: str | None = None):
    """``meshio.read`` with cell data and field data kept, its ``SystemExit``/exceptions as ``GeometryError``."""
    import meshio

    path = Path(path)
    try:
        return meshio.read(path, file_format=file_format)
    except SystemExit as exc:  # meshio 5.3.5 calls sys.exit(1) on unsupported content
        raise refuse(path, f"meshio could not read the file (it called sys.exit({exc.code}); the "
                           "format or version is unsupported or the content is corrupted)",
                     "Convert it to STL, PLY, VTU or Gmsh MSH v4") from None
    except ImportError as exc:  # e.g. XDMF with HDF5 data and no h5py
        raise refuse(path, f"meshio needs a package that is not installed to read this file ({exc})",
                     "Install it (e.g. pip install h5py for XDMF with HDF5 data) or save the mesh as VTU") from None
    except Exception as exc:  # meshio raises many types (ReadError, ValueError, KeyError, ...)
        raise refuse(path, f"meshio could not read the file ({type(exc).__name__}: {exc})",
                     "Check the file opens in ParaView or gmsh, or convert it to STL/PLY/VTU") from None


def read_meshio(path: str | Path, file_format: str | None = None) -> RawMesh:
    """Read with meshio, turning its ``SystemExit``/exceptions into ``GeometryError``."""
    path = Path(path)
    m = read_meshio_mesh(path, file_format)
    tris, tets = [], []
    for block in m.cells:
        if block.type == "triangle":
            tris.append(block.data)
        elif block.type == "quad":
            q = block.data
            tris.append(np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]]))
        elif block.type == "tetra":
            tets.append(block.data)
    tri = np.concatenate(tris).astype(np.int64) if tris else _empty(3)
    tet = np.concatenate(tets).astype(np.int64) if tets else _empty(4)
    return RawMesh(np.asarray(m.points, dtype=np.float64)[:, :3], tri, tet, f"meshio-{file_format or path.suffix[1:]}")


def read_trimesh(path: str | Path) -> RawMesh:
    """Read STL/OBJ/PLY/OFF with trimesh (no processing; scenes are concatenated)."""
    import trimesh

    path = Path(path)
    try:
        mesh = trimesh.load(str(path), force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types on bad content
        raise refuse(path, f"could not parse the file as {path.suffix[1:].upper()} ({type(exc).__name__}: {exc})",
                     "Check the file is a valid triangle surface (open it in MeshLab or ParaView)") from None
    vertices = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), dtype=np.float64)
    faces = np.asarray(getattr(mesh, "faces", _empty(3)), dtype=np.int64).reshape(-1, 3)
    return RawMesh(vertices.reshape(-1, 3), faces, _empty(4), f"trimesh-{path.suffix[1:].lower()}")
