"""Read and write :class:`~liverforce.mesh.types.LiverMesh` as VTU (meshio).

File layout: one VTU with two cell blocks, ``tetra`` then ``triangle`` (the
boundary facets), and the cell-data arrays ``region`` (int8 codes, 0 on the
tets) and ``visible`` (int8 0/1, 0 on the tets). A liver with its own supports
(``geometry.imported[].supports``) also has ``support`` (int32): which of the
lab's supports holds each facet, -1 on the tets and on the facets no lab
support holds (free ones, and under ``mode: add`` the auto-tagged regions
beneath). Its value is the support's place in the lab's list, which is the
order of the features JSON's ``supports``: each entry there states it as
``index``, with ``n_mesh_facets``, the number of facets with ``support ==
index`` (its ``n_facets`` counts the facets it holds on the input surface,
which for a remeshed liver is not the mesh); :func:`support_records` makes the
entries. A mesh without the lab's supports (every built-in liver) is written
without ``support``, and a file without it reads back with
``facet_support=None``. ``meta`` is not stored in the VTU: it goes into the
features JSON (:func:`write_json`). Writes are atomic: a dot-prefixed
temporary file in the same folder, then ``os.replace``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from liverforce.atomic import atomic_path, write_json_atomic
from liverforce.mesh.types import LiverMesh


class MeshFileError(ValueError):
    """A mesh file could not be read as a liver mesh."""


def write_mesh(path: str | Path, mesh: LiverMesh) -> None:
    """Write ``mesh`` as VTU atomically (see module docstring for the layout).

    Parameters
    ----------
    path : str or Path
        Target ``.vtu`` file; its folder is created if needed.
    mesh : LiverMesh
        The mesh; ``meta`` is not written (use :func:`write_json`). Its
        ``facet_support``, when set, is written as the ``support`` array.

    Raises
    ------
    ValueError
        If ``facet_support`` does not have one entry per facet, or holds what :func:`read_mesh` would refuse
        (a value below -1, a support on a free facet, one support over two region codes).
    """
    import meshio

    path = Path(path)
    m = len(mesh.tets)
    cell_data = {
        "region": [np.zeros(m, dtype=np.int8), mesh.facet_region.astype(np.int8)],
        "visible": [np.zeros(m, dtype=np.int8), mesh.facet_visible.astype(np.int8)],
    }
    if mesh.facet_support is not None:
        if mesh.facet_support.shape != (len(mesh.facets),):
            raise ValueError(f"{path}: facet_support has shape {mesh.facet_support.shape}, the mesh "
                             f"{len(mesh.facets)} facets: give one support index (or -1) per facet")
        try:  # what read_mesh would refuse is never written
            held = _facet_support(path, mesh.facet_support, mesh.facet_region,
                                  redo="Not written: the mesh's facet_support and facet_region disagree")
        except MeshFileError as exc:
            raise ValueError(str(exc)) from None
        cell_data["support"] = [np.full(m, -1, dtype=np.int32), held.astype(np.int32)]
    path.parent.mkdir(parents=True, exist_ok=True)
    out = meshio.Mesh(mesh.points, [("tetra", mesh.tets), ("triangle", mesh.facets)], cell_data=cell_data)
    with atomic_path(path) as tmp:
        meshio.write(tmp, out, file_format="vtu")


def read_mesh(path: str | Path) -> LiverMesh:
    """Read a VTU written by :func:`write_mesh`.

    Returns
    -------
    LiverMesh
        With ``meta = {"mesh_file": str(path)}``; ``facet_support`` from the
        ``support`` array, None in a file without it.

    Raises
    ------
    MeshFileError
        If the file is unreadable (meshio's ``SystemExit`` included) or lacks
        the tetra/triangle blocks or the region/visible arrays, if it holds more
        than one piece or a cell-data array does not hold one value per cell
        (:func:`_check_cell_data_lengths`),
        or if its ``support`` array is malformed (:func:`_facet_support`).
    """
    path = Path(path)
    try:
        m = _read_vtu(path)
    except (MeshFileError, ImportError):  # ours; or meshio's private reader moved (pinned 5.3.5): not the file
        raise
    except SystemExit as exc:
        raise MeshFileError(f"{path}: meshio could not read the file (sys.exit({exc.code})). "
                            "Re-create it with liverforce.mesh.io.write_mesh") from None
    except Exception as exc:  # meshio raises many types
        redo = "Re-create it with liverforce.mesh.io.write_mesh"
        if "Incompatible cell data" in str(exc):  # meshio's words for a cell-data array of the wrong length
            redo = ("A cell-data array (region, visible or support) does not hold one value per cell: was it "
                    "edited? Re-run the mesh stage (e.g. snakemake --forcerun mesh), or re-create it with "
                    "liverforce.mesh.io.write_mesh")
        raise MeshFileError(f"{path}: could not read the mesh ({type(exc).__name__}: {exc}). {redo}") from None
    types = [b.type for b in m.cells]
    if "tetra" not in types or "triangle" not in types:
        raise MeshFileError(f"{path}: expected 'tetra' and 'triangle' cell blocks, found {types}. "
                            "Re-create it with liverforce.mesh.io.write_mesh")
    for name in ("region", "visible"):
        if name not in m.cell_data:
            raise MeshFileError(f"{path}: cell data '{name}' missing. Re-create it with write_mesh")
    it, itri = types.index("tetra"), types.index("triangle")
    cell = {k: [_one_value_per_cell(a) for a in v] for k, v in m.cell_data.items()}
    region = np.asarray(cell["region"][itri]).astype(np.int8)
    return LiverMesh(
        points=np.asarray(m.points, dtype=np.float64),
        tets=np.asarray(m.cells[it].data, dtype=np.int64),
        facets=np.asarray(m.cells[itri].data, dtype=np.int64),
        facet_region=region,
        facet_visible=np.asarray(cell["visible"][itri]).astype(bool),
        meta={"mesh_file": str(path)},
        facet_support=(_facet_support(path, cell["support"][itri], region) if "support" in cell else None),
    )


def _one_value_per_cell(a):
    """A cell-data array of one component as a vector: VTK writers that state ``NumberOfComponents="1"`` (which
    ParaView and ours leave out) make meshio read it as a column, shape (n, 1)."""
    a = np.asarray(a)
    return a[:, 0] if a.ndim == 2 and a.shape[1] == 1 else a


#: what to do about a malformed ``support`` array in a file read
_SUPPORT_REDO = ("Re-run the mesh stage (e.g. snakemake --forcerun mesh) to write it again, or delete the "
                 "'support' array to read the mesh without the lab's supports")


def _read_vtu(path: Path):
    """The VTU as ``meshio.read(path, file_format="vtu")`` reads it, its cell-data arrays' lengths in the file
    checked first (:func:`_check_cell_data_lengths`)."""
    import meshio
    from meshio.vtu._vtu import VtuReader

    reader = VtuReader(path)
    _check_cell_data_lengths(path, reader)
    return meshio.Mesh(reader.points, reader.cells, point_data=reader.point_data, cell_data=reader.cell_data,
                       field_data=reader.field_data)


def _check_cell_data_lengths(path: Path, reader) -> None:
    """Refuse a cell-data array of the VTU that does not hold one value per cell (the tets', then the facets'),
    naming the file, the array and both counts.

    meshio's VTU reader (5.3.5) hands each cell block its slice of an array: one longer than the cells loses its
    values beyond the last cell without a word, so a ``support`` array edited by hand (a value inserted in
    ParaView) or by a broken writer would read as supports that look right and are not; a shorter one fails with
    words that name no array. The lengths are the file's own, decoded as meshio decodes them (``reader``: its
    ``VtuReader`` of ``path``; ASCII, inline or appended binary, compressed or not).

    A file of more than one ``Piece`` is refused too: meshio 5.3.5 keeps the last piece's cells only (on all the
    pieces' points), without a word.
    """
    from xml.etree import ElementTree as ET

    from meshio.vtu._vtu import _parse_raw_binary

    try:
        root = ET.parse(str(path)).getroot()
    except ET.ParseError:  # raw binary appended data, as meshio's reader takes it
        root = _parse_raw_binary(str(path))
    pieces = list(root.iter("Piece"))
    if len(pieces) > 1:
        raise MeshFileError(f"{path}: the file holds {len(pieces)} pieces (<Piece> elements); a mesh is read from one "
                            "(meshio would keep the last piece's cells only, without a word). Write it as one piece "
                            "(in ParaView: Merge Blocks, then save), or re-run the mesh stage (e.g. snakemake "
                            "--forcerun mesh) to write it again")
    blocks = ", ".join(f"{len(b)} {b.type}" for b in reader.cells)
    for piece in pieces:
        cells = int(piece.attrib["NumberOfCells"])
        for array in piece.iterfind("CellData/DataArray"):
            name = array.attrib.get("Name", "")
            n = len(reader.read_data(array))
            if n == cells:
                continue
            if name == "support":
                redo = _SUPPORT_REDO
            elif name in ("region", "visible"):
                redo = ("Re-run the mesh stage (e.g. snakemake --forcerun mesh) to write it again, or re-create it "
                        "with liverforce.mesh.io.write_mesh")
            else:
                redo = (f"liverforce does not read '{name}': delete that array, or give it one value per cell; or "
                        "re-run the mesh stage (e.g. snakemake --forcerun mesh) to write the file again")
            beyond = (f" (meshio would keep the first {cells} without a word: the wrong ones if a value was "
                      "inserted)" if n > cells else "")
            raise MeshFileError(f"{path}: cell data '{name}' holds {n} values, but the file has {cells} cells "
                                f"({blocks}) and takes one value per cell, the tets' then the facets'{beyond}. "
                                f"Was it edited (e.g. in ParaView)? {redo}")


def _facet_support(path: Path, raw, region: np.ndarray, redo: str | None = None) -> np.ndarray:
    """The ``support`` array on the facets, checked: one integer per facet, -1 or a support index, no index on a
    free facet (region 0), one region code per support (a lab support sets one code on all it holds). ``redo``:
    what to do, in the error (default: a file's reader's)."""
    a = np.asarray(raw)
    redo = redo or _SUPPORT_REDO
    if a.ndim != 1 or len(a) != len(region):
        raise MeshFileError(f"{path}: cell data 'support' has shape {a.shape} on the triangles, expected one value "
                            f"per facet ({len(region)},). {redo}")
    if not (np.issubdtype(a.dtype, np.integer) or np.isfinite(a).all() and np.array_equal(a, np.round(a))):
        raise MeshFileError(f"{path}: cell data 'support' holds non-integer values (dtype {a.dtype}); it gives the "
                            f"index of the lab's support holding each facet, -1 for none. {redo}")
    a = a.astype(np.int64)
    if (a < -1).any():
        raise MeshFileError(f"{path}: cell data 'support' holds {int(a.min())} on facet {int(np.argmin(a))}; values "
                            f"are a support's index (0, 1, ...) or -1 where none holds the facet. {redo}")
    free = np.flatnonzero((a >= 0) & (region == 0))
    if free.size:
        raise MeshFileError(f"{path}: {free.size} free facets (region 0, e.g. facet {int(free[0])}) are held by a "
                            f"support (cell data 'support' = {int(a[free[0]])}); a held facet has its support's "
                            f"region code. {redo}")
    for i in np.unique(a[a >= 0]):
        codes = np.unique(region[a == i])
        if codes.size > 1:
            raise MeshFileError(f"{path}: support {int(i)} holds facets of region codes {codes.tolist()}; a support "
                                f"sets one code on every facet it holds. {redo}")
    return a


def support_records(mesh: LiverMesh) -> list[dict] | None:
    """The lab's supports as the features JSON lists them: each entry of ``mesh.meta["supports"]`` (in the lab's
    order) with its ``index``, the value of the VTU's ``support`` array on the facets it holds, and
    ``n_mesh_facets``, how many mesh facets those are (without ``facet_support``, only the ``index``). None for
    a mesh without the lab's supports.

    ``meta["supports"]`` itself is left as it is (new dicts are returned).
    """
    records = mesh.meta.get("supports")
    if records is None:
        return None
    if mesh.facet_support is None:
        return [{**r, "index": i} for i, r in enumerate(records)]
    held = np.bincount(mesh.facet_support[mesh.facet_support >= 0], minlength=len(records))
    if len(held) != len(records):
        raise ValueError(f"facet_support holds support index {len(held) - 1}, but meta['supports'] lists "
                         f"{len(records)} supports: they must come from the same assign_supports call")
    return [{**r, "index": i, "n_mesh_facets": int(held[i])} for i, r in enumerate(records)]


def write_json(path: str | Path, obj: dict) -> None:
    """Write ``obj`` as indented, key-sorted JSON atomically (:func:`liverforce.atomic.write_json_atomic`)."""
    write_json_atomic(path, obj)
