"""Mesh stage adapter: tetrahedralise a surface, tag regions, features, a picture of the regions."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

from liverforce.atomic import write_json_atomic
from liverforce.layout import gid_of, surface_meta_of
from liverforce.pipeline.shared import load_surface_file
from liverforce.seeds import derive

log = logging.getLogger("liverforce")


def make_mesh(surface_path, mesh_cfg: dict, seed: int, mesh_path, features_path, picture_path,
              exertion: dict | None = None) -> dict:
    """Tetrahedralise a surface, tag regions, compute features, draw the regions.

    The picture (``picture_path``, :func:`liverforce.mesh.plot.plot_regions`) names each support in its own
    colour (a lab's by its name, kind and selector; the built-in ones by their anatomy) and draws the tool
    positions the sweep presses at, numbered by ``exertion_id``, in the views that see them.

    ``mesh_cfg`` is the composed ``mesh`` group (every key; its values come from
    ``config/mesh/``, none is defaulted here). ``seed`` is the geometry's mesh
    seed (:meth:`liverforce.pipeline.plan.Plan.seed` ``("mesh", gid)``): the
    mesher's, and through ``derive(seed, "mesh.exertion")`` the candidate
    exertion points' (:mod:`liverforce.seeds`).

    ``exertion`` (the ``sweep.exertion`` config: ``n_points``, ``min_spacing_mm``):
    the geometry's candidate exertion points are sampled on the visible input
    surface here, refined around (``mesh.refine_radius_mm`` / ``refine_edge_mm``),
    and written to the features JSON, from which every scenario's sweep takes them.

    The tagged regions are then checked for anatomical plausibility in the frame
    the liver was given in (``mesh.regions_check``: ``warn`` logs and records the
    failed checks in the features JSON under ``regions_check``; ``strict`` refuses,
    before meshing on the input surface's tags and again on the mesh's, before
    writing anything; ``off`` skips; the cube phantom is never checked). A liver
    whose own supports replace the auto-tagged ones is still checked for its frame
    (``right_lobe``) and visible region; the checks of the built-in supports are
    skipped for it, and listed with the reason under ``regions_check.skipped``
    (:func:`liverforce.mesh.plausibility.skipped_checks`). Under ``mode: add``
    those checks run on the auto-tagged regions beneath the lab's supports, before
    meshing, and are recorded under ``regions_check.built_in``.

    An imported geometry may give its own supports and exertion points
    (``geometry.imported[].supports`` / ``.exertion_points``, carried in the
    surface JSON's ``spec``; see :mod:`liverforce.mesh.supports`). Supports are
    applied to the input surface before meshing; the features JSON lists them
    under ``supports`` (facets on the input surface, ``index`` in the VTU's ``support``
    array and ``n_mesh_facets`` there, snapping distances; for a file of points, ``frame_check``: how it fits the
    surface as read and mirrored in x and y, a likely RAS/LPS mix-up warned, refused under
    ``mesh.regions_check: strict``, :func:`liverforce.mesh.supports.check_support_frame`; for a sphere, its
    centre's distances, :func:`liverforce.mesh.supports.check_sphere_frame`) and their foundation
    stiffness under ``support_boundary`` (N/mm³, ``BoundaryParams`` fields). Supports that leave the liver free
    to move as a rigid body (no fixed support, and a rigid motion only sliding supports or foundations without
    tangential stiffness resist) are refused before meshing (:func:`liverforce.mesh.supports.check_held`), as
    are supports that leave no visible area to sample the tool's positions on when the lab gives none.
    Given exertion points replace the sampled candidates (``exertion_given``:
    true, snapping distances in ``exertion_snap_mm``; two snapped within 1 mm of
    each other are one position given twice, refused); one off the visible area
    (facing away from the camera, e.g. a point file read as LPS for RAS) is logged
    as a warning and listed under ``exertion_not_visible``, refused under
    ``mesh.regions_check: strict`` (:func:`liverforce.mesh.supports.check_exertion_facing`).

    An imported tet mesh taken as given (the geometry JSON's ``mesh_mode:
    as_given``) is not remeshed: the VTU holds the file's nodes in the file's
    order (RAS mm) and its tets, regions are tagged on its boundary facets
    (:func:`liverforce.mesh.given.build_given_mesh`), and the features JSON says
    ``mesh_mode: as_given`` and ``node_numbering: file``. ``mesh.target_nodes``,
    ``mesher`` and ``refine_*`` do not apply to it.
    """
    from liverforce.mesh.features import compute_features
    from liverforce.mesh.io import support_records, write_mesh
    from liverforce.mesh.plot import plot_regions
    from liverforce.mesh.regions import RegionParams

    gid = gid_of(mesh_path)
    surface = load_surface_file(surface_path)
    meta_file = surface_meta_of(surface_path)
    if meta_file.exists():
        surface.meta.update(json.loads(meta_file.read_text()))
    spec = surface.meta.get("spec") or {}
    user = _user_scene(spec, surface.meta)
    skip = _skipped_checks(user)  # the user's supports are not anatomy to check; the liver's frame still is
    add = bool(user["supports"][1]) and user["supports"][0] == "add"
    built_in, auto = None, None
    if mesh_cfg["regions_check"] == "strict" or add and mesh_cfg["regions_check"] != "off":
        # refuse before meshing: tags of the input surface; under add, the built-in regions beneath the lab's
        # supports are checked here (the final regions hold the lab's supports, which are no anatomy)
        from liverforce.mesh.plausibility import built_in_only
        from liverforce.mesh.regions import tag_regions

        region, visible = tag_regions(surface.vertices, surface.faces, RegionParams(**mesh_cfg["regions"]))
        pre_skip = (built_in_only() if mesh_cfg["regions_check"] != "strict" else {}) if add else skip
        built_in = _regions_check(surface.vertices, surface.faces, region, visible, surface.meta, mesh_cfg,
                                  gid + (" (built-in regions, beneath the lab's supports)" if add else ""), pre_skip)
        auto = (region, visible)  # meshing starts from these: tagged once
    t0 = time.perf_counter()
    if surface.meta.get("mesh_mode") == "as_given":
        mesh = _given_mesh(surface.meta, spec, user, mesh_cfg, exertion, seed, gid)
    else:
        mesh = _remeshed(surface, user, mesh_cfg, exertion, seed, gid, auto)
    elapsed = time.perf_counter() - t0
    checked = _regions_check(mesh.points, mesh.facets, mesh.facet_region, mesh.facet_visible, surface.meta,
                             mesh_cfg, gid, skip)
    write_mesh(mesh_path, mesh)
    feats = compute_features(mesh)
    feats["meshing_time_s"] = elapsed
    feats["mesh_mode"] = surface.meta.get("mesh_mode", "remesh")
    feats["node_numbering"] = mesh.meta.get("node_numbering", "mesher")
    if feats["mesh_mode"] == "as_given":
        feats["given_mesh"] = {k: mesh.meta["meshing"][k] for k in ("n_nodes", "n_tets", "mean_boundary_edge_mm")}
        feats["given_mesh"]["reoriented_in_file"] = surface.meta.get("reoriented_in_file", 0)
    feats["exertion_candidates_mm"] = mesh.meta.get("exertion_candidates_mm")
    feats["exertion_given"] = bool(mesh.meta.get("exertion_given"))
    feats["exertion_snap_mm"] = mesh.meta.get("exertion_snap_mm")
    feats["exertion_not_visible"] = mesh.meta.get("exertion_not_visible")
    feats["supports"] = support_records(mesh)  # meta["supports"] with each one's index in the VTU's support array
    feats["support_boundary"] = _support_boundary(mesh, user["supports"][1])
    feats["refine_points"] = mesh.meta.get("refine_points")
    feats["regions_tagged_on"] = mesh.meta.get("regions_tagged_on")
    feats["regions_check"] = {**checked, "built_in": built_in} if add else checked
    write_json_atomic(features_path, feats)
    plot_regions(mesh, picture_path)
    log.info("mesh: %d nodes, %d tets in %.1f s", len(mesh.points), len(mesh.tets), elapsed)
    return feats


def _scene_kwargs(user: dict, mesh_cfg: dict, exertion: dict | None, seed: int) -> dict:
    """What both mesh builders take of the lab's scene (:func:`_user_scene`): supports, given exertion points
    (checked against the visible area under ``mesh.regions_check``), else the sampling of candidates."""
    return dict(
        supports=user["supports"], support_frame=user["frame"], file_vertices=user["file_vertices"],
        require_held=user["where"] if user["supports"][1] else None,  # a lab's may leave out the fixed IVC
        file_groups=user["file_groups"], exertion_points=user["exertion_points"],
        exertion_labels=user["exertion_labels"], exertion_reading=user.get("exertion_reading"),
        regions_check=mesh_cfg["regions_check"],
        exertion_sampling=None if exertion is None or user["exertion_points"] is not None else {
            "n_points": exertion["n_points"], "min_spacing_mm": exertion["min_spacing_mm"],
            "seed": derive(seed, "mesh.exertion")})


def _remeshed(surface, user: dict, mesh_cfg: dict, exertion: dict | None, seed: int, gid: str, auto_regions=None):
    """Tetrahedralise the stage's input surface (procedural livers, surfaces, remeshed volume files); its
    auto-tagged ``auto_regions`` (region, visible) when the regions check tagged them already."""
    from liverforce.mesh.build import build_liver_mesh
    from liverforce.mesh.regions import RegionParams

    return build_liver_mesh(
        surface,
        target_nodes=mesh_cfg["target_nodes"],
        region_params=RegionParams(**mesh_cfg["regions"]),
        mesher=mesh_cfg["mesher"],
        seed=seed,
        refine_radius_mm=mesh_cfg["refine_radius_mm"],
        refine_edge_mm=mesh_cfg["refine_edge_mm"],
        refine_ivc_edge_mm=mesh_cfg["refine_ivc_edge_mm"],
        refine_growth=mesh_cfg["refine_growth"],
        **_scene_kwargs(user, mesh_cfg, exertion, seed),
        auto_regions=auto_regions,
    )


def _given_mesh(meta: dict, spec: dict, user: dict, mesh_cfg: dict, exertion: dict | None, seed: int, gid: str):
    """The imported tet mesh as given (its nodes and tets), regions tagged on its boundary."""
    from liverforce.geometry.volume_mesh import load_volume_mesh
    from liverforce.mesh.given import build_given_mesh
    from liverforce.mesh.regions import RegionParams

    path = Path(spec["path"])
    volume, _ = load_volume_mesh(path, units=spec.get("units", "mm"), frame=spec.get("frame", "RAS"))
    if meta.get("sha256") and volume.meta["sha256"] != meta["sha256"]:
        from liverforce.geometry.errors import refuse

        raise refuse(path, "the file changed since the geometry stage read it (SHA-256 differs)",
                     f"Re-run the geometry stage for {gid} (e.g. snakemake --forcerun geometry)")
    ignored = [k for k in ("target_nodes", "mesher", "refine_radius_mm", "refine_edge_mm", "refine_ivc_edge_mm")
               if k in mesh_cfg]
    log.info("%s: mesh as given (%d nodes, %d tets, node numbering of the file); mesh settings %s do not apply "
             "(geometry.imported[].mesh: remesh to use them)", gid, len(volume.points), len(volume.tets), ignored)
    return build_given_mesh(
        volume.points, volume.tets, {**meta, **{k: volume.meta[k] for k in ("n_nodes", "n_tets")}},
        RegionParams(**mesh_cfg["regions"]),
        **_scene_kwargs(user, mesh_cfg, exertion, seed),
        coarse_edge_mm=2 * float(mesh_cfg["refine_edge_mm"] or 0) or None,
    )


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

    def file_groups():  # the geometry file's tagged cells (Gmsh physical groups, cell data) or other segments
        if "g" not in cache:
            from liverforce.geometry.volume_mesh import VOLUME_MESH_SUFFIXES
            from liverforce.geometry.volumes import is_volume_file
            from liverforce.mesh.groups import read_file_groups, read_volume_groups
            from liverforce.mesh.supports import SupportError

            path = Path(spec["path"])
            if is_volume_file(path):  # the segments beside the liver's (label values, a segmentation's names)
                cache["g"] = read_volume_groups(path, surface_meta.get("label"), surface_meta.get("segment"))
            elif not path.name.lower().endswith(VOLUME_MESH_SUFFIXES):
                raise SupportError(f"geometry.imported[{name}]: {path} carries no tagged groups (only Gmsh MSH, "
                                   "VTU, VTK, XDMF files and label volumes do); select the support by sphere, box "
                                   "or file")
            else:
                cache["g"] = read_file_groups(path)
        return cache["g"]

    name = spec.get("name", "?")
    supports = parse_supports(spec.get("supports"), where=f"geometry.imported[{name}].supports")
    points, labels, reading = spec.get("exertion_points"), [], []
    if points is not None:
        points = exertion_points_mesh(points, frame, file_vertices if spec.get("path") else None, labels=labels,
                                      reading=reading)
    return {"supports": supports, "exertion_points": points, "exertion_labels": labels,
            "exertion_reading": reading[0] if reading else None, "frame": frame,
            "where": f"geometry.imported[{name}].supports",
            "file_vertices": file_vertices if spec.get("path") else None,
            "file_groups": file_groups if spec.get("path") else None}


def _support_boundary(mesh, supports) -> dict:
    """Foundation stiffness (N/mm³) of the user's foundations on this mesh (``BoundaryParams`` fields)."""
    from liverforce.fem.boundary import region_areas
    from liverforce.mesh.supports import support_stiffness

    return support_stiffness(supports, region_areas(mesh.points, mesh.facets, mesh.facet_region))


def _skipped_checks(user: dict) -> dict:
    """The regions checks that do not apply to the user's own supports and exertion points, with why."""
    from liverforce.mesh.plausibility import skipped_checks

    mode = user["supports"][0] if user["supports"][1] else None
    return skipped_checks(mode, user["exertion_points"] is not None)


def _regions_check(points, facets, region, visible, surface_meta: dict, mesh_cfg: dict, gid: str,
                   skip: dict | None = None) -> dict:
    """Plausibility of tagged regions for the stated frame (raises under ``strict``)."""
    from liverforce.mesh.plausibility import regions_check
    from liverforce.mesh.regions import RegionParams

    mode = mesh_cfg["regions_check"]
    if (surface_meta.get("spec") or {}).get("kind") == "cube" or surface_meta.get("source") == "cube_phantom":
        mode = "off"  # a phantom has no anatomy to check
    return regions_check(points, facets, region, visible, mode=mode,
                         params=RegionParams(**mesh_cfg["regions"]), frame=surface_meta.get("frame"),
                         where=f"{gid} ({surface_meta.get('source', '?')})", skip=skip)
