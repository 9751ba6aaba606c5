"""Read and write :class:`~liverforce.mesh.types.LiverMesh` as VTU (meshio).

File layout: one VTU with two cell blocks, ``tetra`` then ``triangle`` (the
boundary facets), and two cell-data arrays, ``region`` (int8 codes, 0 on the
tets) and ``visible`` (int8 0/1, 0 on the tets).  ``meta`` is not stored in
the VTU: it goes into the features JSON (:func:`write_json`).  Writes are
atomic: a dot-prefixed temporary file in the same folder, then
``os.replace``.
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
        The mesh; ``meta`` is not written (use :func:`write_json`).
    """
    import meshio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    m = len(mesh.tets)
    out = meshio.Mesh(
        mesh.points,
        [("tetra", mesh.tets), ("triangle", mesh.facets)],
        cell_data={
            "region": [np.zeros(m, dtype=np.int8), mesh.facet_region.astype(np.int8)],
            "visible": [np.zeros(m, dtype=np.int8), mesh.facet_visible.astype(np.int8)],
        },
    )
    with atomic_path(path) as tmp:
        meshio.write(tmp, out, file_format="vtu")


def read_mesh(path: str | Path) -> LiverMesh:
    """Read a VTU written by :func:`write_mesh`.

    Returns
    -------
    LiverMesh
        With ``meta = {"mesh_file": str(path)}``.

    Raises
    ------
    MeshFileError
        If the file is unreadable (meshio's ``SystemExit`` included) or lacks
        the tetra/triangle blocks or the region/visible arrays.
    """
    import meshio

    path = Path(path)
    try:
        m = meshio.read(path, file_format="vtu")
    except SystemExit as exc:
        raise MeshFileError(f"{path}: meshio could not read the file (sys.exit({exc.code})). "
                            "Re-create it with liverforce.mesh.io.write_mesh") from None
    except Exception as exc:  # meshio raises many types
        raise MeshFileError(f"{path}: could not read the mesh ({type(exc).__name__}: {exc}). "
                            "Re-create it with liverforce.mesh.io.write_mesh") from None
    types = [b.type for b in m.cells]
    if "tetra" not in types or "triangle" not in types:
        raise MeshFileError(f"{path}: expected 'tetra' and 'triangle' cell blocks, found {types}. "
                            "Re-create it with liverforce.mesh.io.write_mesh")
    for name in ("region", "visible"):
        if name not in m.cell_data:
            raise MeshFileError(f"{path}: cell data '{name}' missing. Re-create it with write_mesh")
    it, itri = types.index("tetra"), types.index("triangle")
    return LiverMesh(
        points=np.asarray(m.points, dtype=np.float64),
        tets=np.asarray(m.cells[it].data, dtype=np.int64),
        facets=np.asarray(m.cells[itri].data, dtype=np.int64),
        facet_region=np.asarray(m.cell_data["region"][itri]).astype(np.int8),
        facet_visible=np.asarray(m.cell_data["visible"][itri]).astype(bool),
        meta={"mesh_file": str(path)},
    )


def write_json(path: str | Path, obj: dict) -> None:
    """Write ``obj`` as indented, key-sorted JSON atomically (:func:`liverforce.atomic.write_json_atomic`)."""
    write_json_atomic(path, obj)
