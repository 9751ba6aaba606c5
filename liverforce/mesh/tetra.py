"""Quality tetrahedral meshes of a closed surface: the public entry point, which picks the routes.

Pipeline (one gmsh session per attempt, one thread, no GUI, no config files):

1. The input triangulation becomes discrete gmsh surfaces
   (:mod:`liverforce.mesh.gmsh_geometry`).  Smooth shapes (the default) are
   split in two disc-like patches along a level set of the Fiedler vector
   (:mod:`liverforce.mesh.patches`); shapes with sharp features
   (``feature_angle_deg``, e.g. the cube phantom) are split by gmsh's
   ``classifySurfaces`` at that angle so the edges survive; with
   ``surface_labels`` the label borders are kept as curves
   (:mod:`liverforce.mesh.surface_labels`).  If a route fails the next is
   tried (``classifySurfaces`` with parametrisable patches only).
2. The surface is remeshed and the volume meshed at a uniform edge length
   ``h`` or with refinement zones (:mod:`liverforce.mesh.gmsh_mesher`).
3. When a node count is requested, ``h`` comes from a small model: the
   size field integrated over the volume and the surface,
   ``n ≈ ∫ dV / (1.44 s³) + ∫ dA / (1.19 s²)`` (``V / (1.44 h³) + A / (1.19 h²)``
   without refinement), plus a few size-independent nodes (fitted on livers;
   :mod:`liverforce.mesh.sizing`); it is corrected from the counts obtained,
   for up to ``max_attempts`` remeshes of the same geometry (one is usually
   enough).
4. Every tet is made positively oriented; flat boundary tets (slivers with
   two or more faces on the surface, radius ratio < 0.15, which gmsh's
   optimiser cannot move) are peeled off; unused nodes are dropped
   (:mod:`liverforce.mesh.cleanup`).

With ``mesher="tetgen"`` gmsh makes the surface mesh only and TetGen
(``-pq1.2/15Y``, boundary kept) fills the volume
(:mod:`liverforce.mesh.tetgen_mesher`): it works, but leaves slivers and is
slower here (measured on livers at 5k/20k nodes: min radius ratio
0.04–0.09, min dihedral ≈ 2°, 4–8 s / 18–23 s, vs gmsh 0.18–0.30, 8–12°,
2–2.4 s / 4–6 s).

Determinism: same surface, parameters and seed give identical arrays (one
thread; checked across processes).

gmsh runs in-process and is not re-entrant: do not call this from two
threads of one process (separate processes are fine).
"""

from __future__ import annotations

import numpy as np

from liverforce.geometry.surface import Surface
from liverforce.mesh.gmsh_mesher import mesh_route
from liverforce.mesh.meshing_info import MeshingError, MeshingInfo
from liverforce.mesh.quality import mesh_quality
from liverforce.mesh.sizing import refine_provenance, refinement_zone

__all__ = ["MeshingError", "MeshingInfo", "mesh_quality", "tetrahedralise", "tetrahedralise_with_info"]

#: Default node count when neither ``target_nodes`` nor ``edge_length_mm`` is given.
DEFAULT_TARGET_NODES = 5000


def tetrahedralise(
    surface: Surface,
    target_nodes: int | None = None,
    edge_length_mm: float | None = None,
    refine_points=None,
    refine_radius_mm: float | None = None,
    refine_edge_mm: float | None = None,
    seed: int = 0,
    **options,
) -> tuple[np.ndarray, np.ndarray]:
    """Tetrahedral mesh of the volume enclosed by ``surface``.

    Parameters
    ----------
    surface : Surface
        Closed, outward-oriented triangle surface in mm.
    target_nodes : int, optional
        Wanted node count (reached within ``node_tolerance``, default 15 %,
        in most cases; the count obtained is what it is).  Default 5000 when
        ``edge_length_mm`` is not given either.
    edge_length_mm : float, optional
        Uniform target edge length ``h`` (mm); exclusive with ``target_nodes``.
    refine_points : array_like, optional
        ``(p, 3)`` points (mm) around which to refine, e.g. tool exertion points.
    refine_radius_mm : float, optional
        Radius (mm) around each point meshed at ``refine_edge_mm``.
    refine_edge_mm : float, optional
        Edge length (mm) inside the refined balls (< ``h``).
    seed : int
        Seed for gmsh's random perturbations (``Mesh.RandomSeed``); the same
        input and seed give the same mesh.
    **options
        ``mesher`` (``"gmsh"``, default: surface and volume by gmsh;
        ``"tetgen"``: gmsh surface, TetGen ``-pq1.2/15Y`` volume — faster
        but with slivers), ``feature_angle_deg`` (float or None; default
        from ``surface.meta["feature_angle_deg"]``), ``refine_growth``
        (0.3), ``node_tolerance`` (0.15), ``max_attempts`` (3).

    Returns
    -------
    points : numpy.ndarray
        ``(n, 3)`` float64 node coordinates, mm.
    tets : numpy.ndarray
        ``(m, 4)`` int64, positively oriented (``det[b−a, c−a, d−a] > 0``).

    Raises
    ------
    MeshingError
        If gmsh fails on both surface routes or the result is invalid.
    """
    points, tets, _ = tetrahedralise_with_info(
        surface, target_nodes, edge_length_mm, refine_points, refine_radius_mm, refine_edge_mm, seed, **options
    )
    return points, tets


def tetrahedralise_with_info(
    surface: Surface,
    target_nodes: int | None = None,
    edge_length_mm: float | None = None,
    refine_points=None,
    refine_radius_mm: float | None = None,
    refine_edge_mm: float | None = None,
    seed: int = 0,
    *,
    feature_angle_deg: float | None = None,
    mesher: str = "gmsh",
    refine_growth: float = 0.3,
    node_tolerance: float = 0.15,
    max_attempts: int = 3,
    surface_labels=None,
    refine_zones=None,
) -> tuple[np.ndarray, np.ndarray, MeshingInfo]:
    """As :func:`tetrahedralise`, also returning a :class:`MeshingInfo`.

    Extra keyword arguments
    -----------------------
    surface_labels : array_like of int, optional
        One label per triangle of ``surface`` (e.g. boundary-region codes).
        The mesh then *conforms* to the label boundaries: they become curves
        of the gmsh geometry (route ``"labelled"``), so every boundary facet
        lies on one labelled patch and ``info.boundary_triangles`` /
        ``info.boundary_labels`` give each output boundary triangle its
        label. A region then has the same geometry at every mesh size (its
        outline is resampled, not re-approximated by whole facets). If that
        route fails, the unlabelled routes are tried and the label arrays
        stay ``None``.
    refine_zones : list of dict, optional
        Further refinement zones, each ``{"points": (p, 3), "radius_mm",
        "edge_mm", "growth"}`` (same meaning as the ``refine_*`` arguments);
        the mesh size is the minimum over all zones.
    """
    if target_nodes is not None and edge_length_mm is not None:
        raise ValueError("give either target_nodes or edge_length_mm, not both")
    if mesher not in ("gmsh", "tetgen"):
        raise ValueError(f"unknown mesher {mesher!r}: use 'gmsh' or 'tetgen'")
    if target_nodes is None and edge_length_mm is None:
        target_nodes = DEFAULT_TARGET_NODES
    if target_nodes is not None and target_nodes < 50:
        raise ValueError(f"target_nodes must be >= 50, got {target_nodes}")
    if edge_length_mm is not None and edge_length_mm <= 0:
        raise ValueError(f"edge_length_mm must be > 0, got {edge_length_mm}")
    refine = [z for z in [refinement_zone(refine_points, refine_radius_mm, refine_edge_mm, refine_growth)] if z]
    for zone in refine_zones or []:
        z = refinement_zone(zone.get("points"), zone.get("radius_mm"), zone.get("edge_mm"),
                            zone.get("growth", refine_growth))
        if z is not None:
            refine.append(z)
    labels = None
    if surface_labels is not None:
        labels = np.asarray(surface_labels, dtype=np.int64).ravel()
        if labels.shape != (len(surface.faces),):
            raise ValueError(f"surface_labels must have one entry per surface triangle ({len(surface.faces)}), "
                             f"got {labels.shape}")
    if feature_angle_deg is None:
        feature_angle_deg = surface.meta.get("feature_angle_deg")
    volume, area = surface.volume_mm3, surface.area_mm2
    if volume <= 0:
        raise MeshingError(
            f"surface encloses a non-positive volume ({volume:.3g} mm³): it must be closed "
            "and outward oriented (load it through liverforce.geometry.load_surface)"
        )

    info = MeshingInfo(mesher=mesher, target_nodes=target_nodes, seed=int(seed), refine=refine_provenance(refine))
    routes = ["features", "classify"] if feature_angle_deg is not None else ["two_patch", "classify"]
    if labels is not None and mesher == "gmsh":
        routes = ["labelled"] + routes
    errors = []
    for route in routes:
        try:
            points, tets, boundary = mesh_route(
                surface, route, feature_angle_deg, target_nodes, edge_length_mm, refine,
                node_tolerance, max_attempts, seed, info, volume, area, mesher, labels,
            )
            info.route = route
            if boundary is not None:
                info.boundary_triangles, info.boundary_labels = boundary
            return points, tets, info
        except MeshingError as exc:
            errors.append(f"{route}: {exc}")
            info.attempts = []
    raise MeshingError(
        "gmsh could not mesh the surface ("
        + "; ".join(errors)
        + "). Check the surface is closed, manifold and free of self-intersections, "
        "or try a smaller edge length"
    )

