"""Quality tetrahedral meshes of a closed surface, with gmsh.

Pipeline (one gmsh session per call, one thread, no GUI, no config files):

1. The input triangulation becomes discrete gmsh surfaces.  Smooth shapes
   (the default) are split in two disc-like patches along a level set of the
   Fiedler vector (:mod:`liverforce.mesh.patches`), given to gmsh with an
   explicit topology (gmsh's own ``createTopology`` made runs differ);
   shapes with sharp features (``feature_angle_deg``, e.g. the cube phantom)
   are split by gmsh's ``classifySurfaces`` at that angle so the edges
   survive; if a route fails the next is tried (``classifySurfaces`` with
   parametrisable patches only).  ``createGeometry`` reparametrises the
   patches.
2. The surface is remeshed (Frontal-Delaunay) and the volume meshed
   (Delaunay + gmsh's optimiser) at a uniform edge length ``h`` or with a
   background field that refines to ``refine_edge_mm`` within
   ``refine_radius_mm`` of given points and grows back to ``h`` at a rate of
   ``refine_growth`` (mm per mm).
3. When a node count is requested, ``h`` comes from a small model
   ``n ≈ k (V / (1.44 h³) + A / (1.19 h²))`` (fitted on livers) and the
   factor ``k`` is corrected from the count obtained, for up to
   ``max_attempts`` remeshes of the same geometry.
4. Every tet is made positively oriented; flat boundary tets (slivers with
   two or more faces on the surface, radius ratio < 0.15, which gmsh's
   optimiser cannot move) are peeled off; unused nodes are dropped.

With ``mesher="tetgen"`` gmsh makes the surface mesh only and TetGen
(``-pq1.2/15Y``, boundary kept) fills the volume: it works, but leaves
slivers and is slower here (measured on livers at 5k/20k nodes: min
radius ratio 0.04–0.09, min dihedral ≈ 2°, 4–8 s / 18–23 s, vs gmsh
0.18–0.30, 8–12°, 2–2.4 s / 4–6 s).

Determinism: same surface, parameters and seed give identical arrays (one
thread; checked across processes).

gmsh runs in-process and is not re-entrant: do not call this from two
threads of one process (separate processes are fine).
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from liverforce.geometry.surface import Surface
from liverforce.mesh.cleanup import compact, peel_boundary_slivers
from liverforce.mesh.patches import cut_loop, disc_patches, two_patch_labels
from liverforce.mesh.quality import mesh_quality, orient_positive, radius_ratio, signed_volumes

__all__ = ["MeshingError", "MeshingInfo", "mesh_quality", "tetrahedralise", "tetrahedralise_with_info"]

#: Default node count when neither ``target_nodes`` nor ``edge_length_mm`` is given.
DEFAULT_TARGET_NODES = 5000
#: Boundary tets below this radius ratio with >= 2 boundary faces are peeled off.
PEEL_BOUND = 0.15
#: A mesh conforming to surface labels below this minimum radius ratio is
#: refused (the unlabelled routes are tried next): label borders with corners
#: a few mm apart can force tiny elements.
LABELLED_MIN_RADIUS_RATIO = 0.1


class MeshingError(RuntimeError):
    """The mesher could not produce a valid tetrahedral mesh."""


@dataclass
class MeshingInfo:
    """How a mesh was made (JSON-friendly via :meth:`as_dict`)."""

    mesher: str = "gmsh"
    gmsh_version: str = ""
    route: str = ""
    edge_length_mm: float = 0.0
    target_nodes: int | None = None
    attempts: list[dict] = field(default_factory=list)
    refine: dict | None = None
    seed: int = 0
    #: with ``surface_labels``: boundary triangles of the output (indices into
    #: the returned points) and the label of the surface patch each lies on
    #: (not serialised by :meth:`as_dict`)
    boundary_triangles: np.ndarray | None = field(default=None, repr=False)
    boundary_labels: np.ndarray | None = field(default=None, repr=False)

    def as_dict(self) -> dict:
        return {
            "mesher": self.mesher,
            "gmsh_version": self.gmsh_version,
            "route": self.route,
            "edge_length_mm": self.edge_length_mm,
            "target_nodes": self.target_nodes,
            "attempts": self.attempts,
            "refine": self.refine,
            "seed": self.seed,
        }


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
    refine = [z for z in [_refinement(refine_points, refine_radius_mm, refine_edge_mm, refine_growth)] if z]
    for zone in refine_zones or []:
        z = _refinement(zone.get("points"), zone.get("radius_mm"), zone.get("edge_mm"), zone.get("growth", refine_growth))
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

    info = MeshingInfo(mesher=mesher, target_nodes=target_nodes, seed=int(seed), refine=_refine_dict(refine))
    routes = ["features", "classify"] if feature_angle_deg is not None else ["two_patch", "classify"]
    if labels is not None and mesher == "gmsh":
        routes = ["labelled"] + routes
    errors = []
    for route in routes:
        try:
            points, tets, boundary = _mesh_route(
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


@dataclass(frozen=True)
class _Refinement:
    points: np.ndarray
    radius_mm: float
    edge_mm: float
    growth: float

    def as_dict(self) -> dict:
        return {
            "points_mm": self.points.tolist(),
            "radius_mm": self.radius_mm,
            "edge_mm": self.edge_mm,
            "growth": self.growth,
        }


def _refine_dict(zones: list[_Refinement]) -> dict | None:
    """JSON provenance of the refinement zones (the first zone's keys at the top level, as before)."""
    if not zones:
        return None
    out = zones[0].as_dict()
    if len(zones) > 1:
        out["zones"] = [{k: v for k, v in z.as_dict().items() if k != "points_mm"} | {"n_points": len(z.points)}
                        for z in zones]
    return out


def _refinement(points, radius, edge, growth) -> _Refinement | None:
    if points is None:
        return None
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return None
    if radius is None or edge is None or radius < 0 or edge <= 0:
        raise ValueError("refine_points need refine_radius_mm >= 0 and refine_edge_mm > 0")
    if not 0 < growth <= 2:
        raise ValueError(f"refine_growth must be in (0, 2], got {growth}")
    return _Refinement(pts, float(radius), float(edge), float(growth))


def _expected_nodes(h: float, volume: float, area: float, refine: list[_Refinement]) -> float:
    """Node-count model ``V/(1.44 h³) + A/(1.19 h²)`` + refined zones.

    A zone of isolated points adds refined half balls; a zone whose points
    cover a surface patch densely (closer than their reach) adds a refined
    layer: its surface at ``edge_mm`` plus the volume under it.
    """
    n = volume / (1.44 * h**3) + area / (1.19 * h**2)
    for z in refine:
        if z.edge_mm >= h:
            continue
        hf = z.edge_mm
        t = (h - hf) / z.growth
        reach = z.radius_mm + t
        r = np.linspace(0.0, reach, 200)
        size = np.clip(hf + (r - z.radius_mm) / max(t, 1e-9) * (h - hf), hf, h)
        balls = _disjoint_balls(z.points, reach)
        if balls >= 0.5 * len(z.points):
            n += len(z.points) * np.trapezoid(2.0 * np.pi * r**2 * (1.0 / size**3 - 1.0 / h**3), r) / 1.44
        else:
            patch = _covered_area(z.points, hf)
            n += patch * ((1.0 / hf**2 - 1.0 / h**2) / 1.19 + np.trapezoid(1.0 / size**3 - 1.0 / h**3, r) / 1.44)
    return float(n)


def _disjoint_balls(points: np.ndarray, radius: float) -> float:
    """Effective number of balls of ``radius`` around ``points`` (area covered / one disc)."""
    if len(points) <= 1 or radius <= 0:
        return float(len(points))
    cell = max(radius, 1e-9)
    occupied = len(np.unique(np.floor(points / cell).astype(np.int64), axis=0))
    return float(min(len(points), occupied * cell**2 / (np.pi * radius**2)))


def _covered_area(points: np.ndarray, cell: float) -> float:
    """Area (mm²) of the surface patch sampled by ``points`` (occupied cells of a grid, ~1.5 per cell² of area)."""
    cell = max(cell, 1e-6)
    return len(np.unique(np.floor(points / cell).astype(np.int64), axis=0)) * cell**2 / 1.5


def _edge_for_nodes(target: int, k: float, volume: float, area: float, refine) -> float:
    """Solve ``k · expected_nodes(h) = target`` for ``h`` by bisection (log scale)."""
    lo, hi = 1e-3 * volume ** (1 / 3), 2.0 * volume ** (1 / 3)
    for _ in range(80):
        mid = np.sqrt(lo * hi)
        if k * _expected_nodes(mid, volume, area, refine) > target:
            lo = mid
        else:
            hi = mid
    return float(np.sqrt(lo * hi))


@contextmanager
def _gmsh_session(seed: int):
    """Initialise gmsh quietly with one thread; always finalise."""
    import gmsh

    if gmsh.isInitialized():
        raise MeshingError("gmsh is already initialised in this process; tetrahedralise is not re-entrant")
    gmsh.initialize(readConfigFiles=False, interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.Verbosity", 2)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.option.setNumber("Mesh.MaxNumThreads2D", 1)
        gmsh.option.setNumber("Mesh.MaxNumThreads3D", 1)
        gmsh.option.setNumber("Mesh.RandomSeed", int(seed) + 1)
        gmsh.logger.start()
        yield gmsh
    finally:
        gmsh.finalize()


def _last_errors(gmsh) -> str:
    try:
        msgs = [m for m in gmsh.logger.get() if "Error" in m or "error" in m]
    except Exception:  # pragma: no cover - logger unavailable
        msgs = []
    return " | ".join(msgs[-3:])


def _mesh_route(
    surface, route, feature_angle_deg, target_nodes, edge_length_mm, refine,
    node_tolerance, max_attempts, seed, info, volume, area, mesher, labels=None,
) -> tuple[np.ndarray, np.ndarray, tuple | None]:
    k = 1.0
    tried: list[tuple[float, int]] = []
    best = None
    attempts = 1 if edge_length_mm is not None else max(1, int(max_attempts))
    for attempt in range(attempts):
        h = edge_length_mm if edge_length_mm is not None else _edge_for_nodes(
            target_nodes, k, volume, area, refine
        )
        # a fresh session per attempt: gmsh cannot re-mesh reparametrised
        # discrete geometry after mesh.clear() (it hangs), so reload it
        with _gmsh_session(seed) as gmsh:
            info.gmsh_version = gmsh.__version__
            try:
                patch_labels = _load_geometry(gmsh, surface, route, feature_angle_deg, labels)
            except MeshingError:
                raise
            except Exception as exc:
                raise MeshingError(f"surface reparametrisation failed ({exc}; {_last_errors(gmsh)})") from exc
            point_tags: list[list[int]] = []
            for z in refine:  # free points: only used by the Distance fields
                point_tags.append([gmsh.model.geo.addPoint(*map(float, p)) for p in z.points])
            if refine:
                gmsh.model.geo.synchronize()
            points, tets, boundary = _generate(gmsh, h, refine, point_tags, mesher, patch_labels)
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
        k *= n / _expected_nodes(h, volume, area, refine)
        tried.append((h, n))
        if len(tried) >= 2:  # secant in log-log through the two attempts closest to the target
            (h1, n1), (h2, n2) = sorted(tried, key=lambda a: abs(np.log(a[1] / target_nodes)))[:2]
            if n1 != n2 and h1 != h2:
                slope = np.log(n2 / n1) / np.log(h2 / h1)
                if slope < -0.5:
                    h_next = h1 * (target_nodes / n1) ** (1.0 / slope)
                    k = target_nodes / _expected_nodes(h_next, volume, area, refine)
    points, tets, h, boundary = best[0], best[1], best[2], best[4]
    info.edge_length_mm = float(h)
    mesh_volume = float(signed_volumes(points, tets).sum())
    if abs(mesh_volume / volume - 1.0) > 0.05:
        raise MeshingError(
            f"meshed volume {mesh_volume:.4g} mm³ differs from the surface volume "
            f"{volume:.4g} mm³ by more than 5 %"
        )
    return points, tets, boundary


def _edge_pairs(faces: np.ndarray):
    """Interior edges of a closed triangulation: (edge keys (e, 2), triangle a (e,), triangle b (e,))."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    owner = np.tile(np.arange(len(faces)), 3)
    key = np.sort(edges, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, owner = key[order], owner[order]
    same = np.all(key[1:] == key[:-1], axis=1)
    return key[:-1][same], owner[:-1][same], owner[1:][same]


def clean_labels(faces: np.ndarray, labels: np.ndarray, passes: int = 20) -> np.ndarray:
    """Labels a mesher can follow: no spikes, no patch touching itself at a single vertex.

    1. A triangle whose edge neighbours agree (two or three) on another label
       takes that label (removes one-triangle spikes and notches).
    2. At a vertex where a label occupies two or more separate sectors of the
       triangle fan (a "pinch", which no patch parametrisation accepts), the
       triangles of that label around the vertex take the fan's most common
       other label.
    Repeated until nothing changes (at most ``passes`` times). Changes are at
    the scale of one triangle of ``faces``.
    """
    faces = np.asarray(faces, dtype=np.int64)
    lab = np.asarray(labels, dtype=np.int64).copy()
    _, ta, tb = _edge_pairs(faces)
    k = len(faces)
    nl = int(lab.max()) + 1 if lab.size else 1
    for _ in range(passes):
        changed = False
        # 1. majority of the edge neighbours
        nbr = np.full((k, 3), -1, dtype=np.int64)
        fill = np.zeros(k, dtype=np.int64)
        for x, y in ((ta, tb), (tb, ta)):
            for t, o in zip(x, y):
                nbr[t, fill[t]] = o
                fill[t] += 1
        nl_ = lab[nbr]
        agree = np.where(nl_[:, 0] == nl_[:, 1], nl_[:, 0], np.where(nl_[:, 1] == nl_[:, 2], nl_[:, 1],
                                                                     np.where(nl_[:, 0] == nl_[:, 2], nl_[:, 0], -1)))
        flip = (agree >= 0) & (agree != lab)
        if flip.any():
            lab[flip] = agree[flip]
            changed = True
        # 2. pinches: sectors(v, L) = #triangles(v, L) - #edges(v, L) between two L triangles
        v_of = faces.ravel()
        code_t = v_of * nl + np.repeat(lab, 3)
        n_t = np.bincount(code_t, minlength=len(v_of) and (faces.max() + 1) * nl)
        same = lab[ta] == lab[tb]
        keys, _, _ = _edge_pairs(faces)
        ev = keys[same].ravel()
        code_e = ev * nl + np.repeat(lab[ta][same], 2)
        n_e = np.bincount(code_e, minlength=n_t.size)
        pinch = np.flatnonzero(n_t - n_e >= 2)
        if pinch.size:
            for code in pinch:
                v, L = divmod(int(code), nl)
                fan = np.flatnonzero((faces == v).any(axis=1))
                mine = fan[lab[fan] == L]
                others = lab[fan][lab[fan] != L]
                if others.size:
                    lab[mine] = np.bincount(others).argmax()
            changed = True
        if not changed:
            break
    return lab


def _patch_majority(patches: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Per-face label = the most common label of the face's patch."""
    out = labels.copy()
    for p in np.unique(patches):
        sel = patches == p
        out[sel] = np.bincount(labels[sel]).argmax()
    return out


def _label_boundary_edges(faces: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Edges ``(e, 2)`` shared by two triangles of different labels."""
    k, a, b = _edge_pairs(faces)
    return k[labels[a] != labels[b]]


def _load_geometry(gmsh, surface: Surface, route: str, feature_angle_deg: float | None,
                   labels: np.ndarray | None = None) -> dict[int, int] | None:
    """Put the surface into gmsh as reparametrised discrete patches + a volume.

    Route ``"labelled"``: the label boundaries enter as a discrete curve, which
    ``classifySurfaces`` keeps as patch borders; returns ``{surface tag: label}``.
    """
    verts, faces = surface.vertices, surface.faces
    patch_labels = None
    gmsh.model.add("liverforce")
    tags = np.arange(1, len(verts) + 1, dtype=np.uint64)
    if route == "two_patch":
        # explicit topology (point, closed curve, two discs): gmsh's own
        # createTopology starts the loop at a memory-order-dependent node,
        # which made meshes differ from run to run
        labels = two_patch_labels(verts, faces)
        loop = cut_loop(faces[labels == 0])
        on_loop = np.zeros(len(verts), dtype=bool)
        on_loop[loop] = True
        p = gmsh.model.addDiscreteEntity(0)
        c = gmsh.model.addDiscreteEntity(1, -1, [p, p])
        s1 = gmsh.model.addDiscreteEntity(2, -1, [c])
        s2 = gmsh.model.addDiscreteEntity(2, -1, [-c])
        gmsh.model.mesh.addNodes(0, p, [int(loop[0]) + 1], verts[loop[0]])
        gmsh.model.mesh.addNodes(1, c, loop[1:] + 1, verts[loop[1:]].ravel())
        for surf, lab in ((s1, 0), (s2, 1)):
            inner = np.unique(faces[labels == lab])
            inner = inner[~on_loop[inner]]
            gmsh.model.mesh.addNodes(2, surf, inner + 1, verts[inner].ravel())
            gmsh.model.mesh.addElementsByType(surf, 2, [], (faces[labels == lab] + 1).ravel())
        gmsh.model.mesh.addElementsByType(c, 1, [], (np.stack([loop, np.roll(loop, -1)], axis=1) + 1).ravel())
    else:
        s1 = gmsh.model.addDiscreteEntity(2)
        gmsh.model.mesh.addNodes(2, s1, tags, verts.ravel())
        gmsh.model.mesh.addElementsByType(s1, 2, [], (faces + 1).ravel())
        if route == "labelled":
            labels = clean_labels(faces, labels)
            patches = clean_labels(faces, disc_patches(verts, faces, labels))
            # a patch takes the label most of its triangles have (cleaning moved a few)
            labels = _patch_majority(patches, labels)
            border = _label_boundary_edges(faces, patches)
            if len(border):
                c = gmsh.model.addDiscreteEntity(1)
                gmsh.model.mesh.addElementsByType(c, 1, [], (border + 1).ravel())
        angle = np.deg2rad(feature_angle_deg) if feature_angle_deg is not None and route != "classify" else np.pi
        # labelled: the patches are discs already, so gmsh need not split them further (its own
        # splits put extra corner points a few mm apart, which force tiny elements)
        gmsh.model.mesh.classifySurfaces(angle, True, route != "labelled", np.pi)
        if route == "labelled":
            patch_labels = _patch_labels(gmsh, faces, labels)
    gmsh.model.mesh.createGeometry()
    surfaces = [tag for _, tag in gmsh.model.getEntities(2)]
    loop = gmsh.model.geo.addSurfaceLoop(surfaces)
    gmsh.model.geo.addVolume([loop])
    gmsh.model.geo.synchronize()
    return patch_labels


def _patch_labels(gmsh, faces: np.ndarray, labels: np.ndarray) -> dict[int, int]:
    """Label of each classified surface patch (its triangles are the input's, node tags = index + 1)."""
    key = np.sort(faces, axis=1)
    order = np.lexsort((key[:, 2], key[:, 1], key[:, 0]))
    skey = key[order]
    out = {}
    for _, tag in gmsh.model.getEntities(2):
        _, nodes = gmsh.model.mesh.getElementsByType(2, tag)
        tri = np.sort(np.asarray(nodes, dtype=np.int64).reshape(-1, 3) - 1, axis=1)
        if len(tri) == 0:
            continue
        # locate the patch's triangles among the input's: lexicographic search on sorted rows
        idx = _find_rows(skey, tri)
        found = idx >= 0
        if not found.any():
            raise MeshingError("classified patch triangles do not match the input surface")
        vals, counts = np.unique(labels[order[idx[found]]], return_counts=True)
        if len(vals) > 1:
            raise MeshingError(f"surface patch {tag} spans labels {vals.tolist()}: label borders were not kept")
        out[int(tag)] = int(vals[np.argmax(counts)])
    return out


def _find_rows(sorted_rows: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Index of each row of ``rows`` in lexicographically sorted ``sorted_rows`` (-1 if absent)."""
    base = int(max(sorted_rows.max(), rows.max())) + 1
    code_s = (sorted_rows[:, 0] * base + sorted_rows[:, 1]) * base + sorted_rows[:, 2]
    code_r = (rows[:, 0] * base + rows[:, 1]) * base + rows[:, 2]
    pos = np.searchsorted(code_s, code_r)
    pos = np.minimum(pos, len(code_s) - 1)
    return np.where(code_s[pos] == code_r, pos, -1)


def _generate(
    gmsh, h: float, refine: list[_Refinement], point_tags: list[list[int]], mesher: str = "gmsh",
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
        raise MeshingError(f"gmsh generate({dim}) failed at h = {h:.3g} mm ({exc}; {_last_errors(gmsh)})") from exc
    node_tags, coords, _ = gmsh.model.mesh.getNodes()
    node_tags = np.asarray(node_tags, dtype=np.int64)
    coords = np.asarray(coords, dtype=np.float64).reshape(-1, 3)
    lookup = np.full(node_tags.max() + 1, -1, dtype=np.int64)
    lookup[node_tags] = np.arange(len(node_tags))
    boundary = None
    if mesher == "gmsh":
        _, tet_nodes = gmsh.model.mesh.getElementsByType(4)
        if len(tet_nodes) == 0:
            raise MeshingError(f"gmsh produced no tetrahedra at h = {h:.3g} mm ({_last_errors(gmsh)})")
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
        points, tets = _tetgen_volume(coords, tris, h)
    ids = np.arange(len(points))
    points, tets, ids = _compact_with_ids(points, tets, ids)
    try:
        tets = orient_positive(points, tets)
    except ValueError as exc:
        raise MeshingError(f"{mesher} output has {exc}") from exc
    tets = peel_boundary_slivers(points, tets, PEEL_BOUND)
    points, tets, ids = _compact_with_ids(points, tets, ids)
    if patch_labels is not None:
        points = relax_slivers(points, tets, PEEL_BOUND)
    if boundary is not None:
        new_index = np.full(len(coords), -1, dtype=np.int64)
        new_index[ids] = np.arange(len(ids))
        tris = new_index[boundary[0]]
        keep = (tris >= 0).all(axis=1)
        boundary = (tris[keep], boundary[1][keep])
    return points, tets, boundary


def relax_slivers(points: np.ndarray, tets: np.ndarray, bound: float = PEEL_BOUND, passes: int = 4) -> np.ndarray:
    """Move interior nodes of tets below radius ratio ``bound`` toward their neighbours' mean.

    A node moves (by 1, 1/2 or 1/4 of the way to the mean of the nodes of
    its star) only if the worst radius ratio of its star improves and no tet
    inverts; boundary nodes never move (the surface is kept). Slivers with a
    face on the boundary and an interior apex near that face's plane occur
    next to region borders of a conforming mesh, where gmsh's optimisers
    leave them. Returns new points (same topology).
    """
    from liverforce.mesh.boundary import boundary_facets

    points = np.array(points, dtype=np.float64, copy=True)
    fixed = np.zeros(len(points), dtype=bool)
    fixed[boundary_facets(tets).ravel()] = True
    order = np.argsort(tets.ravel(), kind="stable")
    owner = np.repeat(np.arange(len(tets)), 4)[order]
    start = np.searchsorted(tets.ravel()[order], np.arange(len(points) + 1))
    for _ in range(passes):
        rr = radius_ratio(points, tets)
        bad = np.flatnonzero(rr < bound)
        nodes = np.unique(tets[bad].ravel())
        nodes = nodes[~fixed[nodes]]
        if nodes.size == 0:
            break
        moved = False
        for v in nodes:
            star = owner[start[v]:start[v + 1]]
            q0 = radius_ratio(points, tets[star]).min()
            nbrs = np.unique(tets[star].ravel())
            target = points[nbrs[nbrs != v]].mean(axis=0)
            old = points[v].copy()
            for w in (1.0, 0.5, 0.25):
                points[v] = old + w * (target - old)
                if (signed_volumes(points, tets[star]) > 0).all() and radius_ratio(points, tets[star]).min() > q0:
                    moved = True
                    break
                points[v] = old
        if not moved:
            break
    return points


def _compact_with_ids(points, tets, ids):
    """:func:`compact`, carrying the original index of every kept node."""
    both, tets = compact(np.column_stack([points, ids]), tets)
    return np.ascontiguousarray(both[:, :3]), tets, both[:, 3].astype(np.int64)


@contextmanager
def _quiet_stdout():
    """Silence C-level writes to file descriptor 1 for the duration of the block."""
    import os
    import sys

    sys.stdout.flush()
    try:
        saved = os.dup(1)
    except OSError:  # no real stdout (e.g. some embedded runners)
        yield
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


def _tetgen_volume(points: np.ndarray, tris: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """TetGen volume mesh inside a gmsh surface mesh (boundary kept, ``-pq1.2/15YQa``).

    Notes
    -----
    Max tet volume ``1.5 h³ / (6√2)`` (1.5 × a regular tet of edge ``h``).
    TetGen's radius-edge bound does not exclude slivers: measured on a
    5k-node liver, min radius ratio ≈ 0.03 vs ≈ 0.3 for gmsh.
    """
    import tetgen

    used = np.unique(tris)
    pts, tri = compact(points, tris) if len(used) < len(points) else (points, tris)
    maxvol = 1.5 * h**3 / (6.0 * np.sqrt(2.0))
    try:
        with _quiet_stdout():  # the tetgen extension prints to the C stdout even with -Q
            out = tetgen.TetGen(np.ascontiguousarray(pts), np.ascontiguousarray(tri, dtype=np.int32)).tetrahedralize(
                switches=f"pq1.2/15YQa{maxvol:.6g}"
            )
    except Exception as exc:  # tetgen raises RuntimeError and others
        raise MeshingError(f"tetgen failed ({exc})") from exc
    nodes, elems = np.asarray(out[0], dtype=np.float64), np.asarray(out[1], dtype=np.int64)
    if len(elems) == 0:
        raise MeshingError("tetgen produced no tetrahedra")
    return nodes, elems[:, :4]


def _set_refinement_field(gmsh, h: float, zones: list[_Refinement], point_tags: list[list[int]]) -> None:
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
