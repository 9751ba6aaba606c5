"""Helpers that two stage adapters really share: reading a stored surface, verified arrays, surface graphs."""

from __future__ import annotations

import glob
from pathlib import Path

import numpy as np

from liverforce.dataset import io as dio
from liverforce.layout import Layout, gid_of


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


def surface_meshes(mesh_paths) -> dict:
    """Geometry id -> ``(vertices, triangles)`` of its mesh surface in the shards' surface-node order
    (:func:`liverforce.learn.observation.surface_from_mesh`): what the camera observation model reads."""
    from liverforce.learn.observation import surface_from_mesh
    from liverforce.mesh.io import read_mesh

    out = {}
    for p in mesh_paths:
        mesh = read_mesh(p)
        out[gid_of(p)] = surface_from_mesh(mesh.points, mesh.facets)
    return out


def camera_arrays(manifest_path, mesh_paths, what: str) -> dict:
    """Converged cases with their full-surface displacements and the geometries' surfaces, for a camera-cloud
    model (:mod:`liverforce.learn.camera`); ``what`` names the user of the data in errors."""
    if not mesh_paths:
        raise ValueError(f"{what}: a camera-cloud model (roi_features: cloud) needs the meshes of its livers")
    arrays = load_study_arrays(manifest_path, full_surface=True)
    arrays["surface_meshes"] = surface_meshes(mesh_paths)
    missing = sorted(set(np.asarray(arrays["geometry_id"]).astype(str)) - set(arrays["surface_meshes"]))
    if missing:
        raise ValueError(f"{what}: no mesh given for the geometries {missing}")
    return arrays


def run_arrays(results_dir, scenario: str | None, camera: bool, what: str, manifest=None) -> dict:
    """One scenario of a finished run (``results_dir``, e.g. ``results/default``): its verified shards as training
    arrays, with the livers' surfaces from ``results_dir/mesh`` for a camera-cloud model (:func:`camera_arrays`).
    ``manifest``: another manifest of the same livers instead of ``shards/<scenario>`` (a physics study's).
    What the benchmark experiments load; ``what`` names them in errors."""
    run = Layout(results_dir)
    manifest = manifest or run.manifest(str(scenario))
    if camera:
        return camera_arrays(manifest, sorted(glob.glob(run.mesh("*"))), what)
    return dio.load_training_arrays(dio.verify_manifest(manifest))


def load_study_arrays(manifest_path, full_surface: bool = False) -> dict:
    """Converged cases of one scenario (verified shards); with ``surface_displacement_mm`` if ``full_surface``."""
    arrays = dio.load_training_arrays(dio.verify_manifest(manifest_path), full_surface=full_surface)
    if full_surface and any(len(x) == 0 for x in arrays["surface_displacement_mm"]):
        raise RuntimeError(
            f"{manifest_path}: the shards hold no full-surface displacements (dataset.store_full_surface "
            "was false when they were simulated); the ROI-fraction study and camera-cloud models need them — "
            "set it to true and re-run the sweep"
        )
    return arrays
