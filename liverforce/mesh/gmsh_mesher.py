"""Mesh a surface with gmsh along one route, at an edge length or to a node count.

Per attempt (a fresh gmsh session each: gmsh cannot re-mesh reparametrised
discrete geometry after ``mesh.clear()``):

1. the surface is loaded as discrete patches (:mod:`liverforce.mesh.gmsh_geometry`);
2. it is remeshed (Frontal-Delaunay; MeshAdapt on labelled patches) and the
   volume meshed (Delaunay + gmsh's optimiser) at a uniform edge length ``h``
   or with a background field that refines to each zone's ``edge_mm`` within
   its ``radius_mm`` and grows back to ``h`` at ``growth`` mm per mm; with
   ``mesher="tetgen"`` gmsh makes the surface only and TetGen fills the volume
   (:mod:`liverforce.mesh.tetgen_mesher`);
3. every tet is made positively oriented, flat boundary slivers are peeled,
   unused nodes dropped (:mod:`liverforce.mesh.cleanup`).

With a node count, ``h`` comes from :func:`liverforce.mesh.sizing.edge_for_nodes`
and the model's factor is corrected from the count obtained, for up to
``max_attempts`` remeshes.
"""

from __future__ import annotations

import numpy as np

from liverforce.mesh.cleanup import PEEL_BOUND, compact_with_ids, peel_boundary_slivers, relax_slivers
from liverforce.mesh.gmsh_geometry import load_geometry
from liverforce.mesh.gmsh_session import gmsh_session, last_errors
from liverforce.mesh.meshing_info import MeshingError, MeshingInfo
from liverforce.mesh.quality import orient_positive, radius_ratio, signed_volumes
from liverforce.mesh.sizing import RefinementZone, edge_for_nodes, expected_nodes
from liverforce.mesh.tetgen_mesher import tetgen_volume

__all__ = ["LABELLED_MIN_RADIUS_RATIO", "generate_mesh", "mesh_route"]

#: A mesh conforming to surface labels below this minimum radius ratio is
#: refused (the unlabelled routes are tried next): label borders with corners
#: a few mm apart can force tiny elements.
LABELLED_MIN_RADIUS_RATIO = 0.1


def mesh_route(
    surface, route, feature_angle_deg, target_nodes, edge_length_mm, refine,
    node_tolerance, max_attempts, seed, info: MeshingInfo, volume, area, mesher, labels=None,
) -> tuple[np.ndarray, np.ndarray, tuple | None]:
    """Mesh ``surface`` along ``route``; return points, positive tets and the labelled boundary (or None).

    Records every attempt in ``info.attempts`` and the edge length kept in
    ``info.edge_length_mm``. Raises :class:`MeshingError` if gmsh fails, a
    labelled mesh is too poor (radius ratio < ``LABELLED_MIN_RADIUS_RATIO``)
    or the meshed volume is off the surface's by more than 5 %.
    """
    k = 1.0
    tried: list[tuple[float, int]] = []
    best = None
    attempts = 1 if edge_length_mm is not None else max(1, int(max_attempts))
    for attempt in range(attempts):
        h = edge_length_mm if edge_length_mm is not None else edge_for_nodes(
            target_nodes, k, volume, area, refine
        )
        # a fresh session per attempt: gmsh cannot re-mesh reparametrised
        # discrete geometry after mesh.clear() (it hangs), so reload it
        with gmsh_session(seed) as gmsh:
            info.gmsh_version = gmsh.__version__
            try:
                patch_labels = load_geometry(gmsh, surface, route, feature_angle_deg, labels)
            except MeshingError:
                raise
            except Exception as exc:
                raise MeshingError(f"surface reparametrisation failed ({exc}; {last_errors(gmsh)})") from exc
            point_tags: list[list[int]] = []
            for z in refine:  # free points: only used by the Distance fields
                point_tags.append([gmsh.model.geo.addPoint(*map(float, p)) for p in z.points])
            if refine:
                gmsh.model.geo.synchronize()
            points, tets, boundary = generate_mesh(gmsh, h, refine, point_tags, mesher, patch_labels)
        if route == "labelled":
            rr = float(radius_ratio(points, tets).min())
            if rr < LABELLED_MIN_RADIUS_RATIO:
                raise MeshingError(f"mesh conforming to the surface labels has a radius ratio of {rr:.3f} "
                                   f"at h = {h:.3g} mm (< {LABELLED_MIN_RADIUS_RATIO})")
        n = len(points)
        info.attempts.append({"edge_length_mm": float(h), "n_nodes": int(n)})
        if target_nodes is None:
            best = (points, tets, h, 0.0, boundary)
            break
        err = abs(n / target_nodes - 1.0)
        if best is None or err < best[3]:
            best = (points, tets, h, err, boundary)
        if err <= node_tolerance:
            break
        k *= n / expected_nodes(h, volume, area, refine)
        tried.append((h, n))
        if len(tried) >= 2:  # secant in log-log through the two attempts closest to the target
            (h1, n1), (h2, n2) = sorted(tried, key=lambda a: abs(np.log(a[1] / target_nodes)))[:2]
            if n1 != n2 and h1 != h2:
                slope = np.log(n2 / n1) / np.log(h2 / h1)
                if slope < -0.5:
                    h_next = h1 * (target_nodes / n1) ** (1.0 / slope)
                    k = target_nodes / expected_nodes(h_next, volume, area, refine)
    points, tets, h, boundary = best[0], best[1], best[2], best[4]
    info.edge_length_mm = float(h)
    mesh_volume = float(signed_volumes(points, tets).sum())
    if abs(mesh_volume / volume - 1.0) > 0.05:
        raise MeshingError(
            f"meshed volume {mesh_volume:.4g} mm³ differs from the surface volume "
            f"{volume:.4g} mm³ by more than 5 %"
        )
    return points, tets, boundary


def generate_mesh(
    gmsh, h: float, refine: list[RefinementZone], point_tags: list[list[int]], mesher: str = "gmsh",
    patch_labels: dict[int, int] | None = None,
) -> tuple[np.ndarray, np.ndarray, tuple | None]:
    """Mesh the loaded geometry at size ``h``; return nodes, positive tets and, with
    ``patch_labels``, the labelled boundary triangles ``(triangles, labels)`` (else None)."""
    opts = {
        "Mesh.MeshSizeFromPoints": 0,
        "Mesh.MeshSizeFromCurvature": 0,
        "Mesh.MeshSizeExtendFromBoundary": 0,
        "Mesh.Algorithm": 6,
        "Mesh.Algorithm3D": 1,
        "Mesh.Optimize": 1,
        "Mesh.MeshSizeMax": h,
        "Mesh.MeshSizeMin": h,
    }
    active = [(z, t) for z, t in zip(refine, point_tags) if z.edge_mm < h]
    if patch_labels is not None:
        # many small patches with corners: MeshAdapt gives far better surface triangles there than
        # Frontal-Delaunay (min tet radius ratio 0.19-0.37 vs 0.05-0.12 on livers at h = 10-15 mm),
        # and Netgen's optimiser improves the volume mesh further
        opts["Mesh.Algorithm"] = 1
        opts["Mesh.OptimizeNetgen"] = 1
    if active:
        opts["Mesh.MeshSizeMin"] = min(z.edge_mm for z, _ in active)
        _set_refinement_field(gmsh, h, [z for z, _ in active], [t for _, t in active])
    for key, value in opts.items():
        gmsh.option.setNumber(key, value)
    dim = 3 if mesher == "gmsh" else 2
    try:
        gmsh.model.mesh.generate(dim)
    except Exception as exc:
        raise MeshingError(f"gmsh generate({dim}) failed at h = {h:.3g} mm ({exc}; {last_errors(gmsh)})") from exc
    node_tags, coords, _ = gmsh.model.mesh.getNodes()
    node_tags = np.asarray(node_tags, dtype=np.int64)
    coords = np.asarray(coords, dtype=np.float64).reshape(-1, 3)
    lookup = np.full(node_tags.max() + 1, -1, dtype=np.int64)
    lookup[node_tags] = np.arange(len(node_tags))
    boundary = None
    if mesher == "gmsh":
        _, tet_nodes = gmsh.model.mesh.getElementsByType(4)
        if len(tet_nodes) == 0:
            raise MeshingError(f"gmsh produced no tetrahedra at h = {h:.3g} mm ({last_errors(gmsh)})")
        points, tets = coords, lookup[np.asarray(tet_nodes, dtype=np.int64).reshape(-1, 4)]
        if patch_labels is not None:
            tris, labs = [], []
            for tag, lab in patch_labels.items():
                _, tn = gmsh.model.mesh.getElementsByType(2, tag)
                t = lookup[np.asarray(tn, dtype=np.int64).reshape(-1, 3)]
                tris.append(t)
                labs.append(np.full(len(t), lab, dtype=np.int64))
            boundary = (np.concatenate(tris), np.concatenate(labs))
    else:
        _, tri_nodes = gmsh.model.mesh.getElementsByType(2)
        tris = lookup[np.asarray(tri_nodes, dtype=np.int64).reshape(-1, 3)]
        points, tets = tetgen_volume(coords, tris, h)
    ids = np.arange(len(points))
    points, tets, ids = compact_with_ids(points, tets, ids)
    try:
        tets = orient_positive(points, tets)
    except ValueError as exc:
        raise MeshingError(f"{mesher} output has {exc}") from exc
    tets = peel_boundary_slivers(points, tets, PEEL_BOUND)
    points, tets, ids = compact_with_ids(points, tets, ids)
    if patch_labels is not None:
        points = relax_slivers(points, tets, PEEL_BOUND)
    if boundary is not None:
        new_index = np.full(len(coords), -1, dtype=np.int64)
        new_index[ids] = np.arange(len(ids))
        tris = new_index[boundary[0]]
        keep = (tris >= 0).all(axis=1)
        boundary = (tris[keep], boundary[1][keep])
    return points, tets, boundary


def _set_refinement_field(gmsh, h: float, zones: list[RefinementZone], point_tags: list[list[int]]) -> None:
    """Background size: per zone ``edge_mm`` within the radius, linear growth to ``h``; minimum over zones."""
    for tag in gmsh.model.mesh.field.list():
        gmsh.model.mesh.field.remove(tag)
    thresholds = []
    for z, tags in zip(zones, point_tags):
        dist = gmsh.model.mesh.field.add("Distance")
        gmsh.model.mesh.field.setNumbers(dist, "PointsList", tags)
        thr = gmsh.model.mesh.field.add("Threshold")
        gmsh.model.mesh.field.setNumber(thr, "InField", dist)
        gmsh.model.mesh.field.setNumber(thr, "SizeMin", z.edge_mm)
        gmsh.model.mesh.field.setNumber(thr, "SizeMax", h)
        gmsh.model.mesh.field.setNumber(thr, "DistMin", z.radius_mm)
        gmsh.model.mesh.field.setNumber(thr, "DistMax", z.radius_mm + (h - z.edge_mm) / z.growth)
        thresholds.append(thr)
    field = thresholds[0]
    if len(thresholds) > 1:
        field = gmsh.model.mesh.field.add("Min")
        gmsh.model.mesh.field.setNumbers(field, "FieldsList", thresholds)
    gmsh.model.mesh.field.setAsBackgroundMesh(field)
