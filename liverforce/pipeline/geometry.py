"""Geometry stage adapter: one closed liver surface (procedural, cube or imported) to PLY + JSON.

The JSON records the spec, the repairs and, for imported files, the unit and
frame conversion to RAS mm (``conversion``: units, scale, frame, the 4x4
applied), which the mesh stage reads back to word its plausibility checks.

An imported tet mesh taken as given (``geometry.imported[].mesh``: ``as_given``,
or ``auto`` on a file that holds tetrahedra) is read and checked here
(:func:`liverforce.geometry.volume_mesh.load_volume_mesh`: bad meshes are refused
before any meshing); the PLY is then its boundary, unrepaired, and the JSON says
``mesh_mode: as_given``. The
mesh stage reads the file itself again (checked against the recorded SHA-256).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from liverforce.atomic import write_json_atomic

log = logging.getLogger("liverforce")


def make_geometry(spec: dict, surface_path: str | Path, meta_path: str | Path) -> dict:
    """Build one closed liver surface (procedural, cube or imported) and save it as PLY + JSON."""
    from liverforce.geometry.procedural import LiverShapeParams, cube_phantom, procedural_liver

    kind = spec["kind"]
    messages: list[str] = []
    if kind == "procedural":
        surface = procedural_liver(int(spec["seed"]), LiverShapeParams(**spec.get("shape", {})))
    elif kind == "cube":
        surface = cube_phantom(float(spec["edge_mm"]))
    elif kind == "imported":
        from liverforce.geometry.importers import load_surface

        units = spec.get("units", "mm")
        try:
            units = float(units)
        except (TypeError, ValueError):
            pass
        mode = mesh_mode(spec)
        if mode == "as_given":
            from liverforce.geometry.volume_mesh import boundary_surface, load_volume_mesh

            volume, messages = load_volume_mesh(spec["path"], units=units, frame=spec.get("frame", "RAS"))
            surface = boundary_surface(volume)
        else:
            surface, messages = load_surface(spec["path"], units=units, label=spec.get("label"),
                                             frame=spec.get("frame", "RAS"))  # logs the conversion
        surface.meta["mesh_mode"] = mode
        log.info("geometry %s: mesh %s (geometry.imported[].mesh: %s)", spec.get("name"), mode,
                 spec.get("mesh", "auto"))
    else:
        raise ValueError(f"unknown geometry kind '{kind}'")
    for m in messages:
        log.info("%s: %s", "import" if spec.get("kind") == "imported" and
                 surface.meta.get("mesh_mode") == "as_given" else "repair", m)
    save_surface(surface, surface_path)
    meta = {"frame": "RAS", **surface.meta, "spec": spec, "repairs": messages,
            "volume_mm3": surface.volume_mm3, "area_mm2": surface.area_mm2,
            "extent_mm": surface.extent_mm.tolist()}
    write_json_atomic(meta_path, meta)
    log.info("geometry %s: %d vertices, %.0f mL, extent %s mm", spec, len(surface.vertices),
             surface.volume_mm3 / 1000, np.round(surface.extent_mm, 1).tolist())
    return meta


def mesh_mode(spec: dict) -> str:
    """``as_given`` or ``remesh`` for an imported geometry: ``auto`` (the default) takes a file that
    holds tetrahedra as given and remeshes anything else (surfaces, label volumes)."""
    mode = spec.get("mesh") or "auto"
    if mode != "auto":
        return mode
    from liverforce.geometry.volume_mesh import has_tetrahedra

    return "as_given" if has_tetrahedra(spec["path"]) else "remesh"


def save_surface(surface, path: str | Path) -> None:
    import meshio

    from liverforce.atomic import atomic_path

    with atomic_path(path) as tmp:
        meshio.write(tmp, meshio.Mesh(surface.vertices, [("triangle", surface.faces)]), binary=True)
