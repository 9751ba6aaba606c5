"""Mesh stage adapter: tetrahedralise a surface, tag regions, features, a picture of the regions."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np

from liverforce.atomic import write_json_atomic
from liverforce.pipeline.shared import load_surface_file

log = logging.getLogger("liverforce")


def exertion_seed(seed: int, gid: str) -> int:
    """Seed of a geometry's candidate exertion points: the config seed and the geometry id."""
    import zlib

    return int(np.random.SeedSequence([int(seed), zlib.crc32(gid.encode())]).generate_state(1)[0])


def make_mesh(surface_path, mesh_cfg: dict, seed: int, mesh_path, features_path, picture_path,
              exertion: dict | None = None) -> dict:
    """Tetrahedralise a surface, tag regions, compute features, draw the regions.

    ``exertion`` (the ``sweep.exertion`` config: ``n_points``, ``min_spacing_mm``):
    the geometry's candidate exertion points are sampled on the visible input
    surface here, refined around (``mesh.refine_radius_mm`` / ``refine_edge_mm``),
    and written to the features JSON, from which every scenario's sweep takes them.

    The tagged regions are then checked for anatomical plausibility in the frame
    the liver was given in (``mesh.regions_check``: ``warn`` logs and records the
    failed checks in the features JSON under ``regions_check``; ``strict`` refuses,
    before meshing on the input surface's tags and again on the mesh's, before
    writing anything; ``off`` skips; the cube phantom is never checked, nor a liver
    whose supports replace the auto-tagged ones).

    An imported geometry may give its own supports and exertion points
    (``geometry.imported[].supports`` / ``.exertion_points``, carried in the
    surface JSON's ``spec``; see :mod:`liverforce.mesh.supports`). Supports are
    applied to the input surface before meshing; the features JSON lists them
    under ``supports`` (facets, snapping distances) and their foundation
    stiffness under ``support_boundary`` (N/mm³, ``BoundaryParams`` fields).
    Given exertion points replace the sampled candidates (``exertion_given``:
    true, snapping distances in ``exertion_snap_mm``).
    """
    from liverforce.mesh.build import build_liver_mesh
    from liverforce.mesh.features import compute_features
    from liverforce.mesh.io import write_mesh
    from liverforce.mesh.plot import plot_regions
    from liverforce.mesh.regions import RegionParams

    surface = load_surface_file(surface_path)
    meta_file = Path(surface_path).with_suffix(".json")
    if meta_file.exists():
        surface.meta.update(json.loads(meta_file.read_text()))
    spec = surface.meta.get("spec") or {}
    user = _user_scene(spec, surface.meta)
    if user["supports"][1] and user["supports"][0] == "replace":
        mesh_cfg = {**mesh_cfg, "regions_check": "off"}  # the user's supports are not anatomy to check
    if mesh_cfg.get("regions_check", "warn") == "strict":  # refuse before meshing: tags of the input surface
        from liverforce.mesh.regions import tag_regions

        region, visible = tag_regions(surface.vertices, surface.faces, RegionParams(**mesh_cfg.get("regions", {})))
        _regions_check(surface.vertices, surface.faces, region, visible, surface.meta, mesh_cfg, Path(mesh_path).stem)
    t0 = time.perf_counter()
    mesh = build_liver_mesh(
        surface,
        target_nodes=mesh_cfg["target_nodes"],
        region_params=RegionParams(**mesh_cfg.get("regions", {})),
        mesher=mesh_cfg["mesher"],
        seed=seed,
        refine_radius_mm=mesh_cfg.get("refine_radius_mm", 0.0),
        refine_edge_mm=mesh_cfg.get("refine_edge_mm"),
        refine_ivc_edge_mm=mesh_cfg.get("refine_ivc_edge_mm"),
        refine_growth=mesh_cfg.get("refine_growth", 0.3),
        supports=user["supports"], support_frame=user["frame"], file_vertices=user["file_vertices"],
        exertion_points=user["exertion_points"],
        exertion_sampling=None if exertion is None or user["exertion_points"] is not None else {
            "n_points": exertion["n_points"], "min_spacing_mm": exertion["min_spacing_mm"],
            "seed": exertion_seed(seed, Path(mesh_path).stem)},
    )
    elapsed = time.perf_counter() - t0
    checked = _regions_check(mesh.points, mesh.facets, mesh.facet_region, mesh.facet_visible, surface.meta,
                             mesh_cfg, Path(mesh_path).stem)
    write_mesh(mesh_path, mesh)
    feats = compute_features(mesh)
    feats["meshing_time_s"] = elapsed
    feats["exertion_candidates_mm"] = mesh.meta.get("exertion_candidates_mm")
    feats["exertion_given"] = bool(mesh.meta.get("exertion_given"))
    feats["exertion_snap_mm"] = mesh.meta.get("exertion_snap_mm")
    feats["supports"] = mesh.meta.get("supports")
    feats["support_boundary"] = _support_boundary(mesh, user["supports"][1])
    feats["refine_points"] = mesh.meta.get("refine_points")
    feats["regions_tagged_on"] = mesh.meta.get("regions_tagged_on")
    feats["regions_check"] = checked
    write_json_atomic(features_path, feats)
    plot_regions(mesh, picture_path)
    log.info("mesh: %d nodes, %d tets in %.1f s", len(mesh.points), len(mesh.tets), elapsed)
    return feats


def _user_scene(spec: dict, surface_meta: dict) -> dict:
    """Supports, exertion points (mesh frame, mm) and the file frame of an imported geometry's spec."""
    from liverforce.mesh.supports import PointFrame, exertion_points_mesh, parse_supports

    frame = PointFrame.from_surface_meta(surface_meta)
    cache: dict = {}

    def file_vertices():  # the geometry file's vertices as read (file units and frame): what vertex ids index
        if "v" not in cache:
            from liverforce.geometry.importers import _read_mesh_file
            from liverforce.geometry.volumes import is_volume_file
            from liverforce.mesh.supports import SupportError

            path = Path(spec["path"])
            if is_volume_file(path):
                raise SupportError(f"geometry.imported[{name}]: {path} is a label volume, it has no vertex ids; "
                                   "give coordinates (coordinates_mm or a file of x, y, z) instead")
            cache["v"] = _read_mesh_file(path, path.name.lower()).points
        return cache["v"]

    name = spec.get("name", "?")
    supports = parse_supports(spec.get("supports"), where=f"geometry.imported[{name}].supports")
    points = spec.get("exertion_points")
    if points is not None:
        points = exertion_points_mesh(points, frame, file_vertices if spec.get("path") else None)
    return {"supports": supports, "exertion_points": points, "frame": frame,
            "file_vertices": file_vertices if spec.get("path") else None}


def _support_boundary(mesh, supports) -> dict:
    """Foundation stiffness (N/mm³) of the user's foundations on this mesh (``BoundaryParams`` fields)."""
    from liverforce.fem.boundary import region_areas
    from liverforce.mesh.supports import support_stiffness

    return support_stiffness(supports, region_areas(mesh.points, mesh.facets, mesh.facet_region))


def _regions_check(points, facets, region, visible, surface_meta: dict, mesh_cfg: dict, gid: str) -> dict:
    """Plausibility of tagged regions for the stated frame (raises under ``strict``)."""
    from liverforce.mesh.plausibility import regions_check
    from liverforce.mesh.regions import RegionParams

    mode = mesh_cfg.get("regions_check", "warn")
    if (surface_meta.get("spec") or {}).get("kind") == "cube" or surface_meta.get("source") == "cube_phantom":
        mode = "off"  # a phantom has no anatomy to check
    return regions_check(points, facets, region, visible, mode=mode,
                         params=RegionParams(**mesh_cfg.get("regions", {})), frame=surface_meta.get("frame"),
                         where=f"{gid} ({surface_meta.get('source', '?')})")
