"""Helpers that two stage adapters really share: reading a stored surface, verified arrays, surface graphs."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from liverforce.dataset import io as dio
from liverforce.layout import gid_of


def load_surface_file(path: str | Path):
    import meshio

    from liverforce.geometry.surface import Surface

    m = meshio.read(path)
    return Surface(m.points.astype(np.float64), m.get_cells_type("triangle").astype(np.int64), {"source": str(path)})


def surface_graphs(mesh_paths) -> dict:
    """Geometry id (mesh file stem) -> surface graph of its mesh, as the simulation built it (ROI re-growing)."""
    from liverforce.dataset.roi import surface_graph
    from liverforce.mesh.io import read_mesh

    out = {}
    for p in mesh_paths:
        mesh = read_mesh(p)
        out[gid_of(p)] = surface_graph(mesh.points, mesh.facets)
    return out


def load_study_arrays(manifest_path, full_surface: bool = False) -> dict:
    """Converged cases of one scenario (verified shards); with ``surface_displacement_mm`` if ``full_surface``."""
    arrays = dio.load_training_arrays(dio.verify_manifest(manifest_path), full_surface=full_surface)
    if full_surface and any(len(x) == 0 for x in arrays["surface_displacement_mm"]):
        raise RuntimeError(
            f"{manifest_path}: the shards hold no full-surface displacements (dataset.store_full_surface "
            "was false when they were simulated); the ROI-fraction study needs them — set it to true and "
            "re-run the sweep"
        )
    return arrays
