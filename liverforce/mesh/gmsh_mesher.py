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

With a node count, ``h`` comes from the node-count model
(:class:`liverforce.mesh.sizing.NodeCountModel`: the size field integrated over
the surface and volume, plus a few size-independent nodes), corrected from the
counts obtained, for up to ``max_attempts`` remeshes.
"""

from __future__ import annotations

import numpy as np

from liverforce.mesh.cleanup import PEEL_BOUND, compact_with_ids, peel_boundary_slivers, relax_slivers
from liverforce.mesh.gmsh_geometry import load_geometry, prepare_geometry
from liverforce.mesh.gmsh_session import gmsh_session, last_errors
from liverforce.mesh.meshing_info import MeshingError, MeshingInfo
from liverforce.mesh.quality import orient_positive, radius_ratio, signed_volumes
from liverforce.mesh.sizing import NodeCountModel, RefinementZone
from liverforce.mesh.tetgen_mesher import tetgen_volume

__all__ = ["LABELLED_MIN_RADIUS_RATIO", "generate_mesh", "mesh_route"]

#: A mesh conforming to surface labels below this minimum radius ratio is
#: refused (the unlabelled routes are tried next): label borders with corners
#: a few mm apart can force tiny elements.
LABELLED_MIN_RADIUS_RATIO = 0.1

#: gmsh ``Mesh.LcIntegrationPrecision`` with a refinement field (gmsh's default, kept otherwise: 1e-9).
LC_INTEGRATION_PRECISION = 1e-3


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
    tried: list[tuple[float, int]] = []
    best = None
    attempts = 1 if edge_length_mm is not None else max(1, int(max_attempts))
    # the route's patches depend on the surface and labels only: once, not per attempt
    try:
        prepared = prepare_geometry(surface, route, labels)
    except Exception as exc:
        raise MeshingError(f"surface reparametrisation failed ({exc})") from exc
    model = h_cap = None
    if edge_length_mm is None:
        n_patches = len(np.unique(prepared.patches)) if prepared.patches is not None else 0
        model = NodeCountModel(volume, area, refine, surface.vertices, surface.faces, n_patches)
        # the bulk size never exceeds twice the uniform mesh's for the same count
        h_cap = 2.0 * model.uniform().edge_for(target_nodes)
    scale, shift = 1.0, 0.0
    for attempt in range(attempts):
        if edge_length_mm is not None:
            h = edge_length_mm
        else:
            h = _aim(model, target_nodes, node_tolerance, scale, shift, h_cap)
            if tried:  # trust region: at most a factor 2 from the attempt closest to the target
                h_near = min(tried, key=lambda a: abs(np.log(a[1] / target_nodes)))[0]
                h = float(np.clip(h, 0.5 * h_near, 2.0 * h_near))
                if any(abs(h / t - 1.0) < 1e-6 for t, _ in tried):
                    break  # the same size again would give the same mesh
        # a fresh session per attempt: gmsh cannot re-mesh reparametrised
        # discrete geometry after mesh.clear() (it hangs), so reload it
        with gmsh_session(seed) as gmsh:
            info.gmsh_version = gmsh.__version__
            try:
                patch_labels = load_geometry(gmsh, surface, route, feature_angle_deg, prepared=prepared)
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
        tried.append((h, n))
        scale, shift = _correct_model(model, tried, target_nodes)
    points, tets, h, boundary = best[0], best[1], best[2], best[4]
    info.edge_length_mm = float(h)
    mesh_volume = float(signed_volumes(points, tets).sum())
    if abs(mesh_volume / volume - 1.0) > 0.05:
        raise MeshingError(
            f"meshed volume {mesh_volume:.4g} mm³ differs from the surface volume "
            f"{volume:.4g} mm³ by more than 5 %"
        )
    return points, tets, boundary


def _aim(model: NodeCountModel, target: int, tolerance: float, scale: float, shift: float, h_cap: float) -> float:
    """Bulk size for ``target`` nodes by the (corrected) model, at most ``h_cap``.

    When refinement zones need about the whole budget (even ``h_cap`` gives
    more than the target), the bulk is coarsened only as far as needed to land
    within half the tolerance above the target (or to ``h_cap``).
    """
    h = model.edge_for(target, scale, shift, h_max=h_cap)
    if model.expected(h, scale, shift) > target * (1.0 + 1e-3):
        h = model.edge_for(target * (1.0 + 0.5 * tolerance), scale, shift, h_max=h_cap)
    return h


def _correct_model(model: NodeCountModel, tried: list[tuple[float, int]], target: int) -> tuple[float, float]:
    """``(scale, shift)`` making the model match the counts obtained (see :meth:`NodeCountModel.expected`).

    Through the two attempts closest to the target, ``n - offset(h) = scale ·
    integral(h) + shift`` (a secant) when that gives a scale in [0.5, 2];
    otherwise (or after one attempt) the closest attempt's count sets the scale
    of the size-field part (within [0.25, 4]), a shift taking up the rest.
    """
    ranked = sorted(tried, key=lambda a: abs(np.log(a[1] / target)))
    h1, n1 = ranked[0]
    i1 = model.integral(h1)
    if len(ranked) >= 2:
        h2, n2 = ranked[1]
        i2 = model.integral(h2)
        if abs(i1 - i2) > 1e-9 * max(i1, i2):
            scale = ((n1 - model.offset(h1)) - (n2 - model.offset(h2))) / (i1 - i2)
            if 0.5 <= scale <= 2.0:
                return float(scale), float(n1 - model.expected(h1, scale))
    scale = float(np.clip((n1 - model.offset(h1)) / i1, 0.25, 4.0)) if n1 > model.offset(h1) else 1.0
    return scale, float(n1 - model.expected(h1, scale))


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
        # 1D meshing integrates the size along each curve to place its nodes; with the refinement
        # field at gmsh's default precision (1e-9) that took ~1.2 s per attempt (many Distance
        # evaluations), at 1e-3 0.1 s, for the same node count within ~1 %. Uniform meshes keep
        # the default (cheap there, and their meshes unchanged)
        opts["Mesh.LcIntegrationPrecision"] = LC_INTEGRATION_PRECISION
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
