"""Boundary regions of a liver mesh, computed from geometry (no painting).

Frame: the anatomical directions come from :class:`RegionParams`
(``anterior`` and ``superior`` unit vectors, default the RAS frame of the
procedural livers: anterior = +y, superior = +z); patient right is
``anterior × superior`` (+x in RAS).  Imported livers are converted to RAS
at import from the frame they state (``geometry.imported[].frame``), so the
defaults apply to them; other directions are for meshes built in another
frame.  Whether the tags look anatomical is checked by
:mod:`liverforce.mesh.plausibility`.

Normalised coordinates of a facet centroid ``c``: ``r, a, s ∈ [0, 1]`` along
right, anterior and superior, measured over the liver's extent (0 = most
left / posterior / inferior point).  Normals are facet normals averaged over
a ball of ``normal_smoothing_mm`` (area-weighted) to ignore facet noise.

Regions (codes as :data:`~liverforce.mesh.types.REGION_CODES`):

* **3 visceral** – lower (visceral) face: smoothed normal within
  ``visceral_angle_deg`` of inferior.
* **4 rib** – anterior(-superior) face of the right lobe, under the ribs:
  normal within ``rib_cone_deg`` of the direction ``rib_direction`` (weights
  on right, anterior, superior) and ``r ≥ rib_min_right``.
* **2 ligament** – coronary/triangular ligament band on the
  posterior-superior face: ``a ≤ ligament_band_fraction`` and normal with a
  superior component ``n·S ≥ cos(ligament_angle_deg)``.
* **1 IVC** – patch of radius ``ivc_radius_mm`` on the posterior face around
  the most posterior surface point near ``(r, s) = ivc_position``.

Later regions override earlier ones (order visceral, rib, ligament, IVC).
Small specks (connected pieces under ``min_patch_fraction`` of their
region's area) are returned to free.  ``visible`` = free facets whose normal
is within ``visible_cone_deg`` of the viewing direction (anterior tilted
``visible_tilt_deg`` toward superior) and at least ``visible_margin_mm`` from
any tagged facet.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from liverforce.mesh.boundary import facet_normals
from liverforce.mesh.types import REGION_CODES


@dataclass(frozen=True)
class RegionParams:
    """Parameters of :func:`tag_regions` (lengths in mm, angles in degrees).

    Parameters
    ----------
    anterior, superior : tuple of 3 float
        Anatomical directions in the mesh frame (normalised internally; must
        not be parallel).  Default RAS: anterior +y, superior +z.
    ivc_radius_mm : float
        Radius of the IVC patch (default 20 mm).
    ivc_position : tuple of 2 float
        ``(r, s)`` normalised right/superior position of the IVC centre on
        the posterior face (default 0.55, 0.6: just right of the middle,
        upper half).
    ligament_band_fraction : float
        Posterior fraction of the antero-posterior extent holding the
        ligament band (default 0.3).
    ligament_angle_deg : float
        Ligament facets face up: angle of the normal to superior at most
        this (default 65°).
    visceral_angle_deg : float
        Visceral facets: angle of the normal to inferior at most this
        (default 50°).
    rib_direction : tuple of 3 float
        Weights (right, anterior, superior) of the rib-contact direction
        (default 0.7, 0.5, 0.5).
    rib_cone_deg : float
        Half-angle of the rib normal cone (default 40°).
    rib_min_right : float
        Rib facets lie right of this normalised ``r`` (default 0.5).
    visible_tilt_deg : float
        Viewing direction = anterior tilted this much toward superior
        (default 30°).
    visible_cone_deg : float
        Half-angle of the visible normal cone (default 60°).
    visible_margin_mm : float
        Minimum distance of visible facets from tagged facets (default 5 mm).
    normal_smoothing_mm : float
        Radius of the normal averaging ball (default 8 mm; 0 = raw normals).
    min_patch_fraction : float
        Connected pieces below this fraction of their region's area are
        dropped (default 0.05).
    """

    anterior: tuple[float, float, float] = (0.0, 1.0, 0.0)
    superior: tuple[float, float, float] = (0.0, 0.0, 1.0)
    ivc_radius_mm: float = 20.0
    ivc_position: tuple[float, float] = (0.55, 0.6)
    ligament_band_fraction: float = 0.3
    ligament_angle_deg: float = 65.0
    visceral_angle_deg: float = 50.0
    rib_direction: tuple[float, float, float] = (0.7, 0.5, 0.5)
    rib_cone_deg: float = 40.0
    rib_min_right: float = 0.5
    visible_tilt_deg: float = 30.0
    visible_cone_deg: float = 60.0
    visible_margin_mm: float = 5.0
    normal_smoothing_mm: float = 8.0
    min_patch_fraction: float = 0.05

    def __post_init__(self) -> None:
        a = np.asarray(self.anterior, dtype=float)
        s = np.asarray(self.superior, dtype=float)
        if a.shape != (3,) or s.shape != (3,) or np.linalg.norm(a) == 0 or np.linalg.norm(s) == 0:
            raise ValueError("RegionParams: anterior and superior must be non-zero 3-vectors")
        if np.linalg.norm(np.cross(a, s)) < 0.5 * np.linalg.norm(a) * np.linalg.norm(s):
            raise ValueError("RegionParams: anterior and superior must be far from parallel (> 30°)")
        if self.ivc_radius_mm <= 0 or self.visible_margin_mm < 0 or self.normal_smoothing_mm < 0:
            raise ValueError("RegionParams: ivc_radius_mm > 0, visible_margin_mm >= 0, normal_smoothing_mm >= 0")
        for name in ("ligament_band_fraction", "rib_min_right", "min_patch_fraction"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"RegionParams: {name} must be in [0, 1]")

    def frame(self) -> np.ndarray:
        """Rows: unit right, anterior, superior (right-handed, superior orthogonalised)."""
        a = np.asarray(self.anterior, dtype=float)
        a = a / np.linalg.norm(a)
        s = np.asarray(self.superior, dtype=float)
        s = s - (s @ a) * a
        s = s / np.linalg.norm(s)
        return np.stack([np.cross(a, s), a, s])


def tag_regions(points: np.ndarray, facets: np.ndarray, params: RegionParams | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Region code and visibility of each boundary facet.

    Parameters
    ----------
    points : numpy.ndarray
        ``(n, 3)`` node coordinates, mm.
    facets : numpy.ndarray
        ``(k, 3)`` outward-oriented boundary triangles.
    params : RegionParams, optional
        Defaults if ``None``.

    Returns
    -------
    facet_region : numpy.ndarray
        ``(k,)`` int8 codes (0 free, 1 ivc, 2 ligament, 3 visceral, 4 rib).
    facet_visible : numpy.ndarray
        ``(k,)`` bool; ``True`` only where ``facet_region == 0``.
    """
    p = params or RegionParams()
    points = np.asarray(points, dtype=np.float64)
    facets = np.asarray(facets, dtype=np.int64)
    R = p.frame()  # rows right, anterior, superior
    centre = points[facets].mean(axis=1)
    raw = facet_normals(points, facets, unit=False)
    area = 0.5 * np.linalg.norm(raw, axis=1)
    normal = classified_normals(points, facets, p)
    local = centre @ R.T  # (right, anterior, superior) coordinates
    lo, hi = local.min(axis=0), local.max(axis=0)
    frac = (local - lo) / np.maximum(hi - lo, 1e-12)
    n_loc = normal @ R.T

    region = np.zeros(len(facets), dtype=np.int8)
    visceral = n_loc[:, 2] <= -np.cos(np.deg2rad(p.visceral_angle_deg))
    region[visceral] = REGION_CODES["visceral"]

    d_rib = np.asarray(p.rib_direction, dtype=float)
    d_rib = d_rib / np.linalg.norm(d_rib)
    rib = (n_loc @ d_rib >= np.cos(np.deg2rad(p.rib_cone_deg))) & (frac[:, 0] >= p.rib_min_right)
    region[rib] = REGION_CODES["rib"]

    ligament = (frac[:, 1] <= p.ligament_band_fraction) & (n_loc[:, 2] >= np.cos(np.deg2rad(p.ligament_angle_deg)))
    region[ligament] = REGION_CODES["ligament"]

    ivc = _ivc_patch(local, frac, n_loc, p)
    region[ivc] = REGION_CODES["ivc"]

    region = _drop_specks(facets, region, area, p.min_patch_fraction)
    return region, _visible(points, facets, region, n_loc, area, p)


def visible_facets(points: np.ndarray, facets: np.ndarray, facet_region: np.ndarray,
                   params: RegionParams | None = None) -> np.ndarray:
    """The ``visible`` mask of :func:`tag_regions` for given region codes.

    Used when the regions come from elsewhere (e.g. transferred from the
    input surface to a mesh that conforms to them).
    """
    p = params or RegionParams()
    points = np.asarray(points, dtype=np.float64)
    facets = np.asarray(facets, dtype=np.int64)
    R = p.frame()
    area = 0.5 * np.linalg.norm(facet_normals(points, facets, unit=False), axis=1)
    n_loc = classified_normals(points, facets, p) @ R.T
    return _visible(points, facets, np.asarray(facet_region), n_loc, area, p)


def classified_normals(points: np.ndarray, facets: np.ndarray, params: RegionParams | None = None) -> np.ndarray:
    """``(k, 3)`` unit outward normals (mesh frame) of the facets as :func:`tag_regions` and
    :func:`visible_facets` classify them: facet normals averaged over ``normal_smoothing_mm``
    (:func:`_smoothed_normals`, over cells of facets on a dense surface). With :func:`view_cosines` they give
    the angle to the view direction that put a facet in, or out of, the visible area."""
    p = params or RegionParams()
    points = np.asarray(points, dtype=np.float64)
    facets = np.asarray(facets, dtype=np.int64)
    return _smoothed_normals(points[facets].mean(axis=1), facet_normals(points, facets, unit=False),
                             p.normal_smoothing_mm)


def _view_local(p: RegionParams) -> np.ndarray:
    """The view direction in (right, anterior, superior) coordinates: anterior tilted toward superior."""
    return np.array([0.0, np.cos(np.deg2rad(p.visible_tilt_deg)), np.sin(np.deg2rad(p.visible_tilt_deg))])


def view_direction(params: RegionParams | None = None) -> np.ndarray:
    """Unit direction (mesh frame) the visible area faces: ``anterior`` tilted ``visible_tilt_deg`` toward
    ``superior``; a facet is visible (if free and away from tagged facets) when its classified normal is within
    ``visible_cone_deg`` of it."""
    p = params or RegionParams()
    return p.frame().T @ _view_local(p)


def view_cosines(normals: np.ndarray, params: RegionParams | None = None) -> np.ndarray:
    """Cosine of the angle between each normal (mesh frame, e.g. :func:`classified_normals`) and
    :func:`view_direction`, computed as the visible area's classification computes it."""
    p = params or RegionParams()
    return (np.asarray(normals, dtype=np.float64) @ p.frame().T) @ _view_local(p)


def _visible(points, facets, region, n_loc, area, p: RegionParams) -> np.ndarray:
    """Free facets facing the viewer, ``visible_margin_mm`` away from tagged facets, specks dropped."""
    visible = (region == 0) & (n_loc @ _view_local(p) >= np.cos(np.deg2rad(p.visible_cone_deg)))
    tagged = region != 0
    if p.visible_margin_mm > 0 and tagged.any() and visible.any():
        from scipy.spatial import cKDTree

        tagged_pts = points[np.unique(facets[tagged])]
        dist, _ = cKDTree(tagged_pts).query(points[facets[visible]].reshape(-1, 3))
        near = (dist.reshape(-1, 3) < p.visible_margin_mm).any(axis=1)
        idx = np.flatnonzero(visible)
        visible[idx[near]] = False
    vis_code = np.where(visible, 1, 0).astype(np.int8)
    return _drop_specks(facets, vis_code, area, p.min_patch_fraction) == 1


#: above this many estimated neighbour pairs the normals are smoothed over cells of facets instead (a
#: 600k-triangle CT surface has about 5e8 facet pairs within 8 mm: 22 GB at once, the mesh job killed for memory
#: without a word)
SMOOTHING_PAIRS_AT_ONCE = 20_000_000


def _smoothed_normals(centre: np.ndarray, raw: np.ndarray, radius: float) -> np.ndarray:
    """Area-weighted average of facet normals within ``radius`` (unit vectors).

    On a surface dense enough that the facet pairs within ``radius`` would exceed
    :data:`SMOOTHING_PAIRS_AT_ONCE`, facets are first summed into cubic cells (their area-weighted centre and
    normal; the cell edge chosen for a quarter of that many cell pairs, about 1.1 mm for a liver's 84,000 mm²
    and the default 8 mm) and each facet takes its cell's smoothed normal: the same average to within a cell's
    width of the ball's edge, in bounded memory whatever the density. Coarser surfaces are smoothed facet by
    facet, as always."""
    if radius <= 0:
        return raw / np.maximum(np.linalg.norm(raw, axis=1, keepdims=True), 1e-300)
    k = len(centre)
    area = 0.5 * np.linalg.norm(raw, axis=1)
    total = float(area.sum())
    if k * np.pi * radius ** 2 / max(total / max(k, 1), 1e-300) / 2 <= SMOOTHING_PAIRS_AT_ONCE:
        return _ball_sums(centre, raw, radius)
    cell = (total * np.pi * radius ** 2 / (2.0 * SMOOTHING_PAIRS_AT_ONCE / 4)) ** 0.25  # a quarter of the pairs
    key = np.floor((centre - centre.min(axis=0)) / cell).astype(np.int64)
    _, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.ravel()
    m = int(inv.max()) + 1
    w = np.bincount(inv, area, m)
    cc = np.column_stack([np.bincount(inv, area * centre[:, i], m) for i in range(3)]) / np.maximum(w, 1e-300)[:, None]
    cn = np.column_stack([np.bincount(inv, raw[:, i], m) for i in range(3)])
    return _ball_sums(cc, cn, radius)[inv]


def _ball_sums(centre: np.ndarray, raw: np.ndarray, radius: float) -> np.ndarray:
    import scipy.sparse as sp
    from scipy.spatial import cKDTree

    k = len(centre)
    pairs = cKDTree(centre).query_pairs(radius, output_type="ndarray")
    rows = np.concatenate([pairs[:, 0], pairs[:, 1], np.arange(k)])
    cols = np.concatenate([pairs[:, 1], pairs[:, 0], np.arange(k)])
    W = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(k, k)).tocsr()
    raw = W @ raw  # raw normals have length 2 × area: area weighting built in
    return raw / np.maximum(np.linalg.norm(raw, axis=1, keepdims=True), 1e-300)


def _ivc_patch(local: np.ndarray, frac: np.ndarray, n_loc: np.ndarray, p: RegionParams) -> np.ndarray:
    """Facets of the IVC patch: a ball around the most posterior point near the IVC line."""
    posterior = n_loc[:, 1] <= -0.3
    if not posterior.any():
        return np.zeros(len(local), dtype=bool)
    span = local.max(axis=0) - local.min(axis=0)
    target = np.array(p.ivc_position)
    d_rs = np.hypot((frac[:, 0] - target[0]) * span[0], (frac[:, 2] - target[1]) * span[2])
    near = posterior & (d_rs <= max(p.ivc_radius_mm, np.sort(d_rs[posterior])[0] + 1e-9))
    centre = local[np.flatnonzero(near)[np.argmin(local[near, 1])]]
    return (np.linalg.norm(local - centre, axis=1) <= p.ivc_radius_mm) & (n_loc[:, 1] < 0.0)


def _drop_specks(facets: np.ndarray, region: np.ndarray, area: np.ndarray, fraction: float) -> np.ndarray:
    """Return connected pieces smaller than ``fraction`` of their region's area to 0."""
    if fraction <= 0:
        return region
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    region = region.copy()
    k = len(facets)
    edges = np.concatenate([facets[:, [0, 1]], facets[:, [1, 2]], facets[:, [2, 0]]])
    key = np.sort(edges, axis=1)
    owner = np.tile(np.arange(k), 3)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, owner = key[order], owner[order]
    same = np.all(key[1:] == key[:-1], axis=1)
    a, b = owner[:-1][same], owner[1:][same]
    for code in np.unique(region):
        if code == 0:
            continue
        member = region == code
        keep_edge = member[a] & member[b]
        g = sp.coo_matrix((np.ones(keep_edge.sum()), (a[keep_edge], b[keep_edge])), shape=(k, k))
        _, comp = connected_components(g, directed=False)
        comp_area = np.bincount(comp[member], weights=area[member], minlength=comp.max() + 1)
        total = area[member].sum()
        small = comp_area < fraction * total
        region[member & small[comp]] = 0
    return region
