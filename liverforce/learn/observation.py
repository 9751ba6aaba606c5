"""Camera observation model: a case's deformed surface -> the unordered cloud a camera sees.

In surgery a stereo endoscope or depth camera gives an unordered, partial,
noisy cloud of the visible deformed liver surface near the tool; FE node ids
are unknown. The shards store the whole deformed surface of every case
(``surface_displacement_mm``), so realistic training clouds can be made
without new FE. This module does that, seeded, with numpy only:

1. **Camera pose.** Distance ``d`` uniform in ``camera_distance_mm``; viewing
   direction (tip -> camera) uniform over the spherical cap of half-angle
   ``cone_half_angle_deg`` around the cone axis (the outward normal at the
   exertion point, or a fixed ``cone_axis`` such as the patient's anterior
   direction); the camera looks at the tool tip. A pose is drawn again (up to
   ``max_camera_draws`` times) when the camera would sit inside the tool
   (closer than ``camera_tool_clearance_mm`` to it) or, with
   ``require_tool_visible``, when the surface blocks the line of sight to
   the tool tip (the camera would be behind another part of the liver or
   inside it). A perspective (pinhole) camera with a square field of view of
   half-angle ``min(half_fov_deg, asin(roi_radius / d))``.
2. **Candidates.** Points uniform by area on the deformed surface triangles
   (barycentric sampling), kept when within ``roi_radius_mm`` (Euclidean) of
   the tool tip.
3. **Visibility**, each candidate given the first reason that applies
   (the record counts them):

   - ``out_of_view``: outside the field of view (or behind the camera);
   - ``backfacing``: its triangle faces away from the camera
     (``n . (c - x) <= min_view_cos |c - x|``, ``n`` the outward normal);
   - ``inside_tool``: inside the tool;
   - ``tool_shadow``: the segment to the camera passes through the tool;
   - ``self_occluded``: another part of the surface is nearer the camera
     along the same ray. The surface triangles are rasterised into a depth
     buffer of ``zbuffer_pixels``² pixels from the camera pose (vectorised
     numpy; 1/depth is interpolated, which is exact for planar triangles under
     perspective), and a point is hidden when it lies deeper than the buffer
     at its pixel by more than ``depth_tolerance_mm`` plus a slope-scaled
     bias (the depth change of its own triangle across 1.5 pixels).
     On a closed, outward-oriented surface only front-facing triangles are
     rasterised (the first surface a ray from outside meets always faces
     it); on an open surface every triangle occludes.

4. **Density.** The number of points ``k`` is drawn log-uniformly in
   ``n_points = (n_min, n_max)``; candidates are drawn in batches until ``k``
   are visible (the first ``k`` visible ones in draw order, so the cloud is
   uniform by area over the visible part of the ROI), or until
   ``max_candidates`` were drawn (then fewer points, see the record).
5. **The instrument** (``instrument_in_cloud``, default off): a camera sees
   the tool too, and a stereo reconstruction that is not told to mask it
   out returns its points with the liver's. Points uniform by area on the
   tool's capsule within the ROI ball, at the liver part's density (the
   cloud's points over the visible ROI area, estimated from the candidates),
   kept where they face the camera (the capsule is convex, so that is its own
   occlusion), lie in view and are not behind the liver (depth buffer, as
   ``self_occluded``); drawn from a stream of their own, so the liver's points
   are those of the same seed without the instrument, and appended after
   them (the cloud is unordered: no model reads the order).
6. **Noise.** Gaussian, standard deviation ``noise_sd_mm`` (or one drawn
   uniformly in a range ``noise_sd_mm = (lo, hi)`` per observation): ``isotropic``
   (every coordinate) or ``ray`` (along the line of sight, as stereo depth
   error).
7. **Outliers** (``outlier_fraction``, default 0): that share of the cloud's
   points moved along their line of sight by a depth error drawn uniformly in
   ``[-outlier_range_mm, outlier_range_mm]``: a stereo mismatch (a specular
   highlight, a texture-less patch, a pixel at a depth edge) puts a point at a
   wrong depth on its own ray, not beside it. Drawn from a stream of their
   own after the noise, so every other point, and the cloud at fraction 0, is
   that of the same seed without them.

The tool
--------
A rigid instrument of radius ``r = tool_radius_mm`` whose rounded tip
touches the surface at the tool tip point ``q``: a sphere of radius ``r``
centred at ``s = q + r a`` and a shaft cylinder of radius ``r`` from ``s``
along the tool axis ``a`` for ``tool_shaft_length_mm`` (a capsule; its far end
is rounded too). The axis ``a`` points from the tissue towards where the tool
comes from: the direction the force pushes from, ``-F/|F|``
(:func:`tool_axes_from_forces`); by default the outward normal. ``r = 0``: no
tool.

API
---
- :class:`ObservationConfig` -- the settings (``to_dict`` / ``from_dict``).
- :func:`observe` -- one deformed surface -> ``(cloud, ObservationRecord)``.
- :func:`observe_many` -- many cases of one geometry from the shards' full-surface displacements
  (:func:`surface_from_mesh` gives the vertex order, :func:`tool_axes_from_forces` the tool axes,
  :func:`case_seed` the per-case seeds).
- :class:`SurfaceTopology` -- triangles checked once per geometry (closedness, orientation).
- :func:`make_view` / :meth:`View.classify_points` -- the visibility of given points from a given
  camera centre (why each point is or is not seen), as :func:`observe` decides it.

Randomness
----------
``seed`` (an int or a sequence of ints, e.g. ``case_seed(observation_seed,
case_id)``) seeds a :class:`numpy.random.SeedSequence` that is split
into four independent streams: camera pose, sampling (count and points),
noise and the instrument's points. The same seed and inputs give the same cloud, bit for bit; the noisy
cloud equals the noise-free cloud of the same seed plus the noise.

Frames and units
----------------
Everything is in the frame of the given vertices (e.g. the CT frame), mm.
Triangles must be outward oriented (right-hand rule), as the mesh stage writes
them; the undeformed topology is used for the deformed surface.

Example
-------
>>> import numpy as np
>>> from liverforce.learn.observation import ObservationConfig, observe
>>> x = np.linspace(-40, 40, 21)
>>> X, Y = np.meshgrid(x, x)
>>> V = np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])
>>> q = np.arange(20 * 21).reshape(20, 21)[:, :20].ravel()
>>> T = np.concatenate([np.column_stack([q, q + 1, q + 22]), np.column_stack([q, q + 22, q + 21])])
>>> cloud, rec = observe(V, T, [0, 0, 0], [0, 0, 1], ObservationConfig(n_points=(500, 500)), seed=1)
>>> cloud.shape, rec.n_points
((500, 3), 500)

Notes
-----
The depth buffer drops triangles that reach behind the camera's near plane
(1 mm): a surface touching the camera lens is not modelled. Specular
highlights, texture-less regions and depth edges are modelled only as their
outliers (point 7), not as holes in the cloud; the cloud holds
liver surface points only unless ``instrument_in_cloud`` adds the tool's.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields

import numpy as np

from liverforce.seeds import derive, spawn_rngs

#: reasons a candidate point is not in the cloud, in the order they are tested
DROP_REASONS = ("outside_roi", "out_of_view", "backfacing", "inside_tool", "tool_shadow", "self_occluded")
VISIBLE = 0  # reason code of a kept point; a dropped point has 1 + DROP_REASONS.index(reason)
NOISE_MODES = ("isotropic", "ray")
_NEAR_MM = 1.0


# --------------------------------------------------------------------------
# settings
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class ObservationConfig:
    """Settings of the camera observation model (JSON-serialisable; store them with a model).

    Parameters
    ----------
    camera_distance_mm : (float, float)
        Range of the camera's distance from the tool tip, drawn uniformly
        (default 60-120 mm, a laparoscope's working distance).
    cone_half_angle_deg : float
        Half-angle of the cone of viewing directions around the cone axis,
        uniform over the spherical cap (default 40 deg; 0 = along the axis).
    cone_axis : (float, float, float) or None
        Axis of the cone in the vertices' frame (e.g. ``(0, 1, 0)`` =
        anterior in the RAS frame of the procedural livers); ``None``
        (default): the outward normal at the exertion point.
    half_fov_deg : float
        Half-angle of the camera's square field of view (default 45 deg).
    roi_radius_mm : float
        Points are sampled within this distance of the tool tip (default
        50 mm; set it from the model's ROI, e.g. the grid half-width x sqrt 2).
    tool_radius_mm : float
        Radius of the tool's tip sphere and shaft (default 2.5 mm: a 5 mm
        instrument); 0 = no tool.
    tool_shaft_length_mm : float
        Length of the shaft from the tip sphere's centre along the tool axis
        (default 150 mm).
    camera_tool_clearance_mm : float
        A camera pose closer than this to the tool's surface is drawn again
        (default 5 mm).
    require_tool_visible : bool
        Draw the pose again when the surface blocks the line of sight from the
        camera to the tool tip (default True).
    max_camera_draws : int
        Pose draws before giving up (the last pose is used and
        ``record.camera_ok`` is False).
    noise_sd_mm : float or (float, float)
        Standard deviation of the Gaussian point noise (default 0.5 mm; a
        pair: drawn uniformly between the two per observation, from a stream
        of its own, so a single value gives the clouds it gave before the
        pair existed). An endoscope's stereo or depth noise is 0.5-1 mm,
        varying with the distance, the texture and the light.
    noise_mode : str
        ``isotropic`` (default) or ``ray`` (along the line of sight).
    n_points : (int, int)
        Range of the number of cloud points, drawn log-uniformly (default
        200-20000).
    max_candidates : int
        Most candidate points drawn per observation (default 2,000,000);
        reached only when very little of the ROI is visible.
    min_view_cos : float
        A point counts as back-facing when the cosine between its triangle's
        normal and the direction to the camera is at most this (default 0;
        e.g. 0.1 drops grazing points, which stereo matching rarely gets).
    zbuffer_pixels : int
        Pixels per side of the depth buffer (default 256).
    depth_tolerance_mm : float
        Depth margin of the self-occlusion test on top of the slope-scaled
        bias (default 0.25 mm).
    instrument_in_cloud : bool
        Add the visible part of the tool's surface to the cloud at the liver
        points' density (default False: the instrument is masked out).
    outlier_fraction : float
        Share of the cloud's points (liver and instrument alike) given a gross
        depth error along their line of sight (default 0: none; in [0, 0.5]).
    outlier_range_mm : float
        The outliers' depth error is uniform in ``[-r, r]`` mm (default 10).
    tool_tilt_deg : float or (float, float)
        The tool's axis tilted this far from the outward normal (a pair: an
        angle drawn uniformly between the two per observation), towards a
        random azimuth, from its own stream (every other draw is unchanged),
        when no tool axis is given (default 0: along the normal). A
        laparoscopic instrument comes in through its trocar, rarely square to
        the surface.
    """

    camera_distance_mm: tuple[float, float] = (60.0, 120.0)
    cone_half_angle_deg: float = 40.0
    cone_axis: tuple[float, float, float] | None = None
    half_fov_deg: float = 45.0
    roi_radius_mm: float = 50.0
    tool_radius_mm: float = 2.5
    tool_shaft_length_mm: float = 150.0
    camera_tool_clearance_mm: float = 5.0
    require_tool_visible: bool = True
    max_camera_draws: int = 50
    noise_sd_mm: tuple[float, float] = (0.5, 0.5)
    noise_mode: str = "isotropic"
    n_points: tuple[int, int] = (200, 20000)
    max_candidates: int = 2_000_000
    min_view_cos: float = 0.0
    zbuffer_pixels: int = 256
    depth_tolerance_mm: float = 0.25
    instrument_in_cloud: bool = False
    tool_tilt_deg: tuple[float, float] = (0.0, 0.0)
    outlier_fraction: float = 0.0
    outlier_range_mm: float = 10.0

    def __post_init__(self) -> None:
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 (frozen dataclass)
        set_("camera_distance_mm", tuple(float(v) for v in _pair(self.camera_distance_mm, "camera_distance_mm")))
        set_("n_points", tuple(int(v) for v in _pair(self.n_points, "n_points")))
        set_("tool_tilt_deg", tuple(float(v) for v in _pair(self.tool_tilt_deg, "tool_tilt_deg")))
        set_("noise_sd_mm", tuple(float(v) for v in _pair(self.noise_sd_mm, "noise_sd_mm")))
        if self.cone_axis is not None:
            ax = np.asarray(self.cone_axis, dtype=np.float64).ravel()
            if ax.shape != (3,) or not np.isfinite(ax).all() or np.linalg.norm(ax) == 0:
                raise ValueError(f"observation cone_axis must be a nonzero 3-vector or null (got {self.cone_axis!r})")
            set_("cone_axis", tuple(float(v) for v in ax))
        for k in ("cone_half_angle_deg", "half_fov_deg", "roi_radius_mm", "tool_radius_mm", "tool_shaft_length_mm",
                  "camera_tool_clearance_mm", "min_view_cos", "depth_tolerance_mm", "outlier_fraction",
                  "outlier_range_mm"):
            set_(k, float(getattr(self, k)))
        for k in ("max_camera_draws", "max_candidates", "zbuffer_pixels"):
            set_(k, int(getattr(self, k)))
        set_("require_tool_visible", bool(self.require_tool_visible))
        set_("instrument_in_cloud", bool(self.instrument_in_cloud))
        d0, d1 = self.camera_distance_mm
        n0, n1 = self.n_points
        checks = {
            "camera_distance_mm": _NEAR_MM < d0 <= d1,
            "cone_half_angle_deg": 0.0 <= self.cone_half_angle_deg < 90.0,
            "half_fov_deg": 0.0 < self.half_fov_deg < 89.0,
            "roi_radius_mm": self.roi_radius_mm > 0,
            "tool_radius_mm": self.tool_radius_mm >= 0,
            "tool_shaft_length_mm": self.tool_shaft_length_mm >= 0,
            "camera_tool_clearance_mm": self.camera_tool_clearance_mm >= 0,
            "max_camera_draws": self.max_camera_draws >= 1,
            "noise_sd_mm": 0.0 <= self.noise_sd_mm[0] <= self.noise_sd_mm[1] < math.inf,
            "noise_mode": self.noise_mode in NOISE_MODES,
            "n_points": 1 <= n0 <= n1,
            "max_candidates": self.max_candidates >= n1,
            "min_view_cos": -1.0 <= self.min_view_cos < 1.0,
            "zbuffer_pixels": 16 <= self.zbuffer_pixels <= 4096,
            "depth_tolerance_mm": self.depth_tolerance_mm >= 0,
            "tool_tilt_deg": 0.0 <= self.tool_tilt_deg[0] <= self.tool_tilt_deg[1] < 90.0,
            "outlier_fraction": 0.0 <= self.outlier_fraction <= 0.5,
            "outlier_range_mm": 0.0 < self.outlier_range_mm < math.inf,
        }
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise ValueError(
                "ObservationConfig: invalid " + ", ".join(f"{k}={getattr(self, k)!r}" for k in bad)
                + " (see the class docstring for the allowed values; noise_mode is one of "
                + f"{NOISE_MODES}, max_candidates must be >= n_points max)"
            )

    def to_dict(self) -> dict:
        """Plain, JSON-serialisable dict (tuples as lists)."""
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict | None) -> "ObservationConfig":
        """From :meth:`to_dict` output or a config slice; missing keys take the defaults, unknown keys are refused."""
        d = dict(d or {})
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown observation setting(s) {unknown}; known: {sorted(known)}")
        return cls(**d)


def _pair(v, name: str) -> tuple:
    t = tuple(v) if not np.isscalar(v) else (v, v)
    if len(t) != 2:
        raise ValueError(f"observation {name} must be a pair [min, max] (got {v!r})")
    return t


# --------------------------------------------------------------------------
# the record
# --------------------------------------------------------------------------


@dataclass
class ObservationRecord:
    """What one observation did (for logging; ``to_dict`` is JSON-serialisable).

    Attributes
    ----------
    camera_position_mm : (3,) camera centre
    camera_distance_mm : distance from the tool tip
    view_angle_deg : angle between the viewing direction (tip -> camera) and the outward normal
    camera_draws : poses drawn (1 = the first was accepted)
    camera_ok : False if no pose met the placement rules within ``max_camera_draws``
    tool_tip_mm, tool_axis : the tool tip point and axis used
    n_target : number of points drawn from ``n_points``
    n_points : number of points in the cloud: the liver's (``< n_target`` only when too little is visible) and
        ``n_instrument_points``
    candidates : candidate points drawn in all
    dropped : candidates dropped per reason (``DROP_REASONS``); with ``candidates`` they
        estimate the area fractions of the ROI hidden by each mechanism
    visible_fraction : visible candidates / candidates within the ROI radius
    n_instrument_points : points of the instrument in the cloud (``instrument_in_cloud``; the last rows)
    noise_sd_mm : the point noise's standard deviation (drawn when ``noise_sd_mm`` is a range)
    n_outliers : points given a gross depth error (``outlier_fraction``)
    """

    camera_position_mm: np.ndarray
    camera_distance_mm: float
    view_angle_deg: float
    camera_draws: int
    camera_ok: bool
    tool_tip_mm: np.ndarray
    tool_axis: np.ndarray
    n_target: int = 0
    n_points: int = 0
    candidates: int = 0
    dropped: dict = field(default_factory=lambda: {r: 0 for r in DROP_REASONS})
    visible_fraction: float = 0.0
    n_instrument_points: int = 0
    noise_sd_mm: float = 0.0
    n_outliers: int = 0

    def to_dict(self) -> dict:
        out = {}
        for k, v in asdict(self).items():
            if isinstance(v, np.ndarray):
                v = [float(x) for x in v]
            elif isinstance(v, (np.floating, np.integer, np.bool_)):
                v = v.item()
            out[k] = v
        return out


# --------------------------------------------------------------------------
# geometry helpers
# --------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class SurfaceTopology:
    """Triangles of one geometry's surface, checked once and reused for every case.

    Attributes
    ----------
    triangles : (m, 3) int64, outward oriented
    closed : True if every edge is shared by exactly two triangles with opposite
        orientation (a closed, consistently oriented surface: back faces are not rasterised)
    """

    triangles: np.ndarray
    closed: bool
    orientation_checked: bool = False

    @classmethod
    def of(cls, triangles, vertices=None) -> "SurfaceTopology":
        """Check ``triangles`` once (a SurfaceTopology is returned unchanged).

        With ``vertices`` (e.g. the undeformed surface) a closed surface's
        orientation is checked here once, instead of at every :func:`observe`
        call; inward-oriented triangles raise ``ValueError``.
        """
        if isinstance(triangles, SurfaceTopology):
            topo = triangles
        else:
            T = np.ascontiguousarray(np.asarray(triangles), dtype=np.int64)
            if T.ndim != 2 or T.shape[1] != 3 or len(T) == 0:
                raise ValueError(f"triangles must be a non-empty (m, 3) integer array (got shape {T.shape})")
            if T.min() < 0:
                raise ValueError("triangles hold negative vertex indices")
            topo = cls(T, _is_closed(T))
        if vertices is not None and topo.closed and not topo.orientation_checked:
            _check_outward(np.asarray(vertices, dtype=np.float64), topo.triangles)
            topo = cls(topo.triangles, True, True)
        return topo

    @property
    def columns(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The three vertex-index columns, contiguous (cached)."""
        c = self.__dict__.get("_columns")
        if c is None:
            c = tuple(np.ascontiguousarray(self.triangles[:, k]) for k in range(3))
            object.__setattr__(self, "_columns", c)
        return c


def _check_outward(V: np.ndarray, T: np.ndarray) -> None:
    P0, P1, P2 = V[T[:, 0]], V[T[:, 1]], V[T[:, 2]]
    if float(np.einsum("ij,ij->i", P0, np.cross(P1 - P0, P2 - P0)).sum()) < 0:
        raise ValueError("the closed surface's triangles are inward oriented; the observation model needs "
                         "outward triangles (right-hand rule), as the mesh stage writes them")


def _is_closed(T: np.ndarray) -> bool:
    a = np.concatenate([T[:, 0], T[:, 1], T[:, 2]])
    b = np.concatenate([T[:, 1], T[:, 2], T[:, 0]])
    n = int(T.max()) + 1
    fwd = np.sort(a * n + b)
    if (np.diff(fwd) == 0).any():  # an edge used twice in the same direction: open/non-manifold/flipped
        return False
    rev = np.sort(b * n + a)
    return bool(np.array_equal(fwd, rev))


def surface_from_mesh(points: np.ndarray, facets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Surface vertices and triangles in the shards' surface node order.

    ``surface_displacement_mm`` lists the mesh's surface nodes sorted by mesh
    point id (as :func:`liverforce.dataset.roi.surface_graph` does); this
    returns ``(vertices (s, 3), triangles (m, 3))`` with triangles indexing
    those ``s`` vertices, so ``vertices + surface_displacement_mm`` is the
    deformed surface.
    """
    facets = np.asarray(facets, dtype=np.int64)
    node_ids = np.unique(facets)
    local = np.full(len(points), -1, dtype=np.int64)
    local[node_ids] = np.arange(node_ids.size)
    return np.asarray(points, dtype=np.float64)[node_ids], local[facets]


def tool_axes_from_forces(forces_n: np.ndarray) -> np.ndarray:
    """Tool axes ``(n, 3)``: the unit direction the force pushes from, ``-F / |F|`` (``F`` in N, any frame)."""
    F = np.atleast_2d(np.asarray(forces_n, dtype=np.float64))
    nrm = np.linalg.norm(F, axis=1, keepdims=True)
    if (nrm == 0).any():
        raise ValueError("a zero force has no direction: give the tool axis explicitly")
    return -F / nrm


def _unit(v, name: str) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64).reshape(3)
    n = np.linalg.norm(v)
    if not np.isfinite(n) or n == 0:
        raise ValueError(f"{name} must be a finite nonzero 3-vector (got {v})")
    return v / n


def _basis(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors completing ``w`` (unit) to a right-handed orthonormal basis (deterministic)."""
    e = np.eye(3)[int(np.argmin(np.abs(w)))]
    a = e - e.dot(w) * w
    a /= np.linalg.norm(a)
    return a, np.cross(w, a)


@dataclass(frozen=True)
class Camera:
    """A pinhole camera at ``position``; rows of ``R`` are (right, up, forward), ``forward`` = optical axis.

    ``half_window`` is the tangent of the square field of view's half-angle:
    a point with camera coordinates ``(x, y, z)`` is in view when ``z > 1 mm``
    and ``|x / z|, |y / z| < half_window``.
    """

    position: np.ndarray
    R: np.ndarray
    half_window: float

    @classmethod
    def looking_at(cls, position, target, half_window: float) -> "Camera":
        c = np.asarray(position, dtype=np.float64).reshape(3)
        f = _unit(np.asarray(target, dtype=np.float64) - c, "camera viewing direction")
        r, u = _basis(f)
        return cls(c, np.stack([r, u, f]), float(half_window))

    def to_camera(self, x: np.ndarray) -> np.ndarray:
        """Camera coordinates ``(k, 3)`` of world points ``(k, 3)``."""
        return (np.asarray(x, dtype=np.float64) - self.position) @ self.R.T

    def to_world(self, xc: np.ndarray) -> np.ndarray:
        """World coordinates of camera coordinates ``(k, 3)``."""
        return self.position + xc @ self.R


@dataclass(frozen=True)
class Tool:
    """Capsule from ``centre`` (the tip sphere's centre) to ``centre + length * axis``, radius ``radius`` (mm)."""

    centre: np.ndarray
    axis: np.ndarray
    radius: float
    length: float

    @classmethod
    def at_tip(cls, tip, axis, radius: float, length: float) -> "Tool":
        """The tool whose rounded tip touches ``tip``, coming from direction ``axis``."""
        a = _unit(axis, "tool axis")
        return cls(np.asarray(tip, dtype=np.float64) + radius * a, a, float(radius), float(length))

    @property
    def end(self) -> np.ndarray:
        return self.centre + self.length * self.axis

    def distance(self, c) -> float:
        """Distance of a point from the tool's surface (negative inside)."""
        c = np.asarray(c, dtype=np.float64)
        t = np.clip((c - self.centre) @ self.axis, 0.0, self.length)
        return float(np.linalg.norm(c - self.centre - t * self.axis) - self.radius)


def _capsule_tests(x, y, z, q0, q1, r: float):
    """Points ``(x, y, z)`` (columns, camera coordinates: the camera at the origin) against the capsule
    ``q0-q1`` of radius ``r``: ``(inside, blocked)``, ``blocked`` = the segment point -> camera passes within
    ``r`` of the axis (Ericson's clamped closest points of two segments)."""
    d2 = q1 - q0
    e = float(d2 @ d2)
    rx, ry, rz = x - q0[0], y - q0[1], z - q0[2]
    f = rx * d2[0] + ry * d2[1] + rz * d2[2]
    if e > 1e-18:
        t = np.clip(f / e, 0.0, 1.0)
        dx, dy, dz = rx - t * d2[0], ry - t * d2[1], rz - t * d2[2]
    else:
        dx, dy, dz = rx, ry, rz
    inside = dx * dx + dy * dy + dz * dz < r * r
    # segment p(s) = X (1 - s), s in [0, 1] (d1 = -X), against q(t) = q0 + t d2
    a = x * x + y * y + z * z
    b = -(x * d2[0] + y * d2[1] + z * d2[2])
    c = -(x * rx + y * ry + z * rz)
    a_safe = np.maximum(a, 1e-300)
    if e > 1e-18:
        denom = a * e - b * b
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(denom > 1e-12 * a * e, np.clip((b * f - c * e) / denom, 0.0, 1.0), 0.0)
        t = (b * s + f) / e
        lo, hi = t < 0.0, t > 1.0
        t = np.clip(t, 0.0, 1.0)
        s = np.where(lo, np.clip(-c / a_safe, 0.0, 1.0), s)
        s = np.where(hi, np.clip((b - c) / a_safe, 0.0, 1.0), s)
    else:
        s = np.clip(-c / a_safe, 0.0, 1.0)
        t = np.zeros_like(s)
    w = 1.0 - s
    gx, gy, gz = x * w - q0[0] - t * d2[0], y * w - q0[1] - t * d2[1], z * w - q0[2] - t * d2[2]
    blocked = gx * gx + gy * gy + gz * gz < r * r
    return inside, blocked


def _segment_hits_surface(o: np.ndarray, c: np.ndarray, V: np.ndarray, topo: "SurfaceTopology") -> bool:
    """Does the segment ``o -> c`` cross a triangle? Vertex outcodes against two planes through the segment
    and its extent prune the triangles; the rest get a Möller-Trumbore test."""
    d = c - o
    L = float(np.linalg.norm(d))
    d = d / L
    w1, w2 = _basis(d)
    rel = V - o
    s1, s2, s3 = rel @ w1, rel @ w2, rel @ d
    code = ((s1 > 0).astype(np.uint8) | ((s1 < 0) << 1) | ((s2 > 0) << 2) | ((s2 < 0) << 3)
            | ((s3 < 0) << 4) | ((s3 > L) << 5)).astype(np.uint8)
    t0, t1, t2 = topo.columns
    cand = np.flatnonzero((code[t0] & code[t1] & code[t2]) == 0)
    if cand.size == 0:
        return False
    A, B, C = V[t0[cand]], V[t1[cand]], V[t2[cand]]
    e1, e2 = B - A, C - A
    h = np.cross(d, e2)
    a = np.einsum("ij,ij->i", e1, h)
    ok = np.abs(a) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, a, 1.0), 0.0)
    s = o - A
    u = inv * np.einsum("ij,ij->i", s, h)
    q = np.cross(s, e1)
    v = inv * (q @ d)
    t = inv * np.einsum("ij,ij->i", e2, q)
    return bool((ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9) & (t < L)).any())


# --------------------------------------------------------------------------
# depth buffer
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class DepthBuffer:
    """Nearest surface depth (mm, along the optical axis) per pixel of a camera's square window.

    Pixel ``(j, i)`` (row ``j`` = image y) covers normalised image coordinates
    ``[-W + i p, -W + (i + 1) p) x [-W + j p, -W + (j + 1) p)``, ``p = 2 W / N``.
    """

    depth: np.ndarray  # (N, N), inf where no surface
    pixel: float
    half_window: float

    @property
    def size(self) -> int:
        return self.depth.shape[0]

    def lookup(self, sx: np.ndarray, sy: np.ndarray) -> np.ndarray:
        """Buffer depth at normalised image coordinates ``(x / z, y / z)`` (clamped to the window)."""
        N = self.size
        i = np.clip(((sx + self.half_window) / self.pixel).astype(np.int64), 0, N - 1)
        j = np.clip(((sy + self.half_window) / self.pixel).astype(np.int64), 0, N - 1)
        return self.depth.ravel()[j * N + i]


def depth_buffer(Xc: np.ndarray, topo: "SurfaceTopology", half_window: float, pixels: int, *,
                 front_only: bool = False, max_depth: float = np.inf) -> DepthBuffer:
    """Rasterise a surface (vertices in camera coordinates ``Xc`` (n, 3)) into a depth buffer.

    Every pixel centre inside a triangle (barycentric test with a tiny margin,
    so shared edges leave no gaps) gets the triangle's depth there (1/depth is
    affine in the image for a planar triangle); the buffer keeps the nearest.
    Triangles wholly outside the window, reaching behind the near plane
    (1 mm), wholly deeper than ``max_depth`` or, with ``front_only``, facing
    away from the camera are skipped.
    """
    N = int(pixels)
    W = float(half_window)
    p = 2.0 * W / N
    buf = np.zeros(N * N)  # 1/depth; 0 = nothing
    x, y, z = Xc[:, 0], Xc[:, 1], Xc[:, 2]
    behind = z <= _NEAR_MM
    zs = np.where(behind, 1.0, z)
    code = ((x < -W * zs).astype(np.uint8) | ((x > W * zs) << 1) | ((y < -W * zs) << 2) | ((y > W * zs) << 3)
            | ((z > max_depth) << 4) | (behind << 5)).astype(np.uint8)
    t0, t1, t2 = topo.columns
    c0, c1, c2 = code[t0], code[t1], code[t2]
    sel = np.flatnonzero((((c0 & c1 & c2) & 0x1F) == 0) & (((c0 | c1 | c2) & 0x20) == 0))
    if sel.size:
        iz_v = 1.0 / zs
        px = (x * iz_v + W) / p - 0.5  # pixel-centre coordinates
        py = (y * iz_v + W) / p - 0.5
        T0, T1, T2 = t0[sel], t1[sel], t2[sel]
        x0, x1, x2 = px[T0], px[T1], px[T2]
        y0, y1, y2 = py[T0], py[T1], py[T2]
        A = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)  # < 0: facing the camera (outward triangles)
        ok = (A < -1e-12) if front_only else (np.abs(A) > 1e-12)
        i0 = np.maximum(np.ceil(np.minimum(np.minimum(x0, x1), x2) - 1e-9), 0).astype(np.int64)
        i1 = np.minimum(np.floor(np.maximum(np.maximum(x0, x1), x2) + 1e-9), N - 1).astype(np.int64)
        j0 = np.maximum(np.ceil(np.minimum(np.minimum(y0, y1), y2) - 1e-9), 0).astype(np.int64)
        j1 = np.minimum(np.floor(np.maximum(np.maximum(y0, y1), y2) + 1e-9), N - 1).astype(np.int64)
        ok &= (i1 >= i0) & (j1 >= j0)
        k = np.flatnonzero(ok)
        if k.size:
            x0, x1, x2, y0, y1, y2, A = (v[k] for v in (x0, x1, x2, y0, y1, y2, A))
            i0, i1, j0, j1 = i0[k], i1[k], j0[k], j1[k]
            w0, w1, w2 = iz_v[T0[k]], iz_v[T1[k]], iz_v[T2[k]]
            # barycentrics l1, l2 and 1/depth are affine in the pixel coordinates: coefficients per triangle
            a1, b1 = (y2 - y0) / A, -(x2 - x0) / A
            a2, b2 = -(y1 - y0) / A, (x1 - x0) / A
            c1, c2 = -(a1 * x0 + b1 * y0), -(a2 * x0 + b2 * y0)
            ai, bi = a1 * (w1 - w0) + a2 * (w2 - w0), b1 * (w1 - w0) + b2 * (w2 - w0)
            ci = w0 + c1 * (w1 - w0) + c2 * (w2 - w0)
            wid = i1 - i0 + 1
            cnt = wid * (j1 - j0 + 1)
            tri = np.repeat(np.arange(k.size), cnt)
            off = np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt)
            wt = wid[tri]
            yoff = off // wt
            xi = i0[tri] + (off - yoff * wt)
            yj = j0[tri] + yoff
            xf, yf = xi.astype(np.float64), yj.astype(np.float64)
            eps = 1e-7
            l1 = a1[tri] * xf + b1[tri] * yf + c1[tri]
            l2 = a2[tri] * xf + b2[tri] * yf + c2[tri]
            inside = np.flatnonzero((l1 >= -eps) & (l2 >= -eps) & (l1 + l2 <= 1.0 + eps))
            t_in = tri[inside]
            xf, yf = xf[inside], yf[inside]
            izp = ai[t_in] * xf + bi[t_in] * yf + ci[t_in]
            np.maximum.at(buf, yj[inside] * N + xi[inside], izp)
    with np.errstate(divide="ignore"):
        depth = np.where(buf > 0, 1.0 / np.where(buf > 0, buf, 1.0), np.inf)
    return DepthBuffer(depth.reshape(N, N), p, W)


# --------------------------------------------------------------------------
# classification of points
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class View:
    """One camera pose over one deformed surface: camera, depth buffer and tool, ready to classify points.

    Build it with :func:`make_view` (or let :func:`observe` do it).
    """

    camera: Camera
    zbuf: DepthBuffer
    tool_q0: np.ndarray  # capsule axis ends in camera coordinates
    tool_q1: np.ndarray
    tool_radius: float
    tip_c: np.ndarray  # tool tip in camera coordinates
    config: ObservationConfig

    @classmethod
    def make(cls, camera: Camera, zbuf: DepthBuffer, tool: Tool, tip, config: ObservationConfig) -> "View":
        q = camera.to_camera(np.stack([tool.centre, tool.end, np.asarray(tip, dtype=np.float64)]))
        return cls(camera, zbuf, q[0], q[1], tool.radius, q[2], config)

    def classify_points(self, points_mm, normals) -> np.ndarray:
        """Reason code per point: ``VISIBLE`` (0) or ``1 + DROP_REASONS.index(reason)`` (module docstring).

        Parameters
        ----------
        points_mm : (k, 3) surface points (world frame)
        normals : (k, 3) unit outward normals of their triangles
        """
        P = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        Nn = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        Xc = self.camera.to_camera(P)
        plane = np.einsum("ij,ij->i", Nn, self.camera.position - P)
        return self.classify(np.ascontiguousarray(Xc[:, 0]), np.ascontiguousarray(Xc[:, 1]),
                             np.ascontiguousarray(Xc[:, 2]), plane)

    def classify(self, x, y, z, plane_dist) -> np.ndarray:
        """Reason codes for points ``(x, y, z)`` (camera coordinates, columns); ``plane_dist`` = signed
        distance of the camera from each point's triangle plane (positive on the outward side)."""
        cfg = self.config
        n = len(x)
        code = np.zeros(n, dtype=np.int8)
        dx, dy, dz = x - self.tip_c[0], y - self.tip_c[1], z - self.tip_c[2]
        out = dx * dx + dy * dy + dz * dz > cfg.roi_radius_mm ** 2
        code[out] = 1
        idx = np.flatnonzero(~out)
        x, y, z, plane_dist = x[idx], y[idx], z[idx], plane_dist[idx]
        W = self.camera.half_window
        zs = np.where(z > _NEAR_MM, z, 1.0)
        sx, sy = x / zs, y / zs
        bad = (z <= _NEAR_MM) | (np.abs(sx) >= W) | (np.abs(sy) >= W)
        dist = np.sqrt(x * x + y * y + z * z)
        cosv = plane_dist / np.maximum(dist, 1e-12)
        back = ~bad & (cosv <= cfg.min_view_cos)
        sub = np.full(len(idx), VISIBLE, dtype=np.int8)
        sub[bad] = 2
        sub[back] = 3
        live = np.flatnonzero(sub == VISIBLE)
        r = self.tool_radius
        if r > 0 and live.size:
            # prefilter: a point near the tool or whose ray to the camera meets it lies near the plane through
            # the camera and the tool axis: |X . m| < r max(1, |X| / (delta - r)), delta = camera-axis distance
            q0, q1 = self.tool_q0, self.tool_q1
            m = np.cross(q0, q1)
            mn = float(np.linalg.norm(m))
            d2 = q1 - q0
            e = float(d2 @ d2)
            tt = min(max(float(-(q0 @ d2)) / e, 0.0), 1.0) if e > 0 else 0.0
            delta = float(np.linalg.norm(q0 + tt * d2))
            if mn > 1e-9 * max(float(np.linalg.norm(q0) * np.linalg.norm(q1)), 1e-300) and delta > r:
                m = m / mn
                xl, yl, zl = x[live], y[live], z[live]
                near = np.abs(xl * m[0] + yl * m[1] + zl * m[2]) <= r * np.maximum(1.0, dist[live] / (delta - r)) \
                    * (1 + 1e-9) + 1e-9
                test = live[near]
            else:
                test = live
            if test.size:
                ins, blk = _capsule_tests(x[test], y[test], z[test], q0, q1, r)
                sub[test[ins]] = 4
                sub[test[~ins & blk]] = 5
            live = np.flatnonzero(sub == VISIBLE)
        if live.size:
            zl = z[live]
            zb = self.zbuf.lookup(sx[live], sy[live])
            c = np.clip(np.abs(cosv[live]), 0.05, 1.0)
            # depth change of the point's own plane over 1.5 pixels (footprint z * pixel, times tan(incidence),
            # times 1 / cos of the off-axis angle, at most sqrt(1 + 2 W^2))
            slope = (1.5 * self.zbuf.pixel * math.sqrt(1.0 + 2.0 * W * W)) * zl * np.sqrt(1.0 - c * c) / c
            occ = zl > zb + cfg.depth_tolerance_mm + slope
            sub[live[occ]] = 6
        code[idx] = sub
        return code


def make_view(vertices_mm, triangles, exertion_point_mm, camera_position_mm, config: ObservationConfig | None = None,
              *, normal=None, tool_axis=None) -> View:
    """The :class:`View` of a surface from a camera centre (looking at the tool tip), as :func:`observe` builds it.

    ``tool_axis`` defaults to ``normal``; one of them is needed when the tool has a radius.
    """
    cfg = config or ObservationConfig()
    topo = SurfaceTopology.of(triangles)
    V = np.asarray(vertices_mm, dtype=np.float64)
    tip = np.asarray(exertion_point_mm, dtype=np.float64).reshape(3)
    C = np.asarray(camera_position_mm, dtype=np.float64).reshape(3)
    axis = tool_axis if tool_axis is not None else normal
    if axis is None:
        axis = C - tip
    d = float(np.linalg.norm(C - tip))
    camera = Camera.looking_at(C, tip, _half_window(cfg, d))
    zbuf = depth_buffer(camera.to_camera(V), topo, camera.half_window, cfg.zbuffer_pixels, front_only=topo.closed,
                        max_depth=d + cfg.roi_radius_mm + 1.0)
    tool = Tool.at_tip(tip, axis, cfg.tool_radius_mm, cfg.tool_shaft_length_mm)
    return View.make(camera, zbuf, tool, tip, cfg)


# --------------------------------------------------------------------------
# camera pose
# --------------------------------------------------------------------------


def _draw_direction(rng: np.random.Generator, axis: np.ndarray, half_angle_deg: float) -> np.ndarray:
    cos_max = math.cos(math.radians(half_angle_deg))
    ct = 1.0 - rng.random() * (1.0 - cos_max)
    st = math.sqrt(max(0.0, 1.0 - ct * ct))
    phi = 2.0 * math.pi * rng.random()
    a, b = _basis(axis)
    return ct * axis + st * (math.cos(phi) * a + math.sin(phi) * b)


def _half_window(config: ObservationConfig, d: float) -> float:
    ang = min(math.radians(config.half_fov_deg), math.asin(min(config.roi_radius_mm / d, 1.0)))
    return math.tan(max(ang, 1e-3))


# --------------------------------------------------------------------------
# observation
# --------------------------------------------------------------------------


def _in_range(pair: tuple[float, float], rng: np.random.Generator) -> float:
    """A value drawn uniformly in ``pair = (lo, hi)``; ``lo`` itself, drawing nothing, when ``hi <= lo``."""
    lo, hi = pair
    return float(lo + (hi - lo) * rng.random()) if hi > lo else float(lo)


def _streams(seed) -> tuple[np.random.Generator, ...]:
    """Camera pose, sampling, noise, instrument, tool-tilt, noise-level and outlier streams (each as before the
    later ones existed: ``SeedSequence.spawn`` keys a child by its index)."""
    try:
        return tuple(spawn_rngs(seed, 7))
    except ValueError:
        raise ValueError(f"observation seeds must be non-negative integers (got {seed!r})") from None


def instrument_points(camera: Camera, zbuf: DepthBuffer, tool: Tool, tip, density_per_mm2: float,
                      rng: np.random.Generator, config: ObservationConfig) -> np.ndarray:
    """The tool's visible surface points ``(k, 3)`` (world frame, noise-free) within the ROI ball.

    Candidates uniform by area over the capsule's tip hemisphere and its shaft up to the ROI radius, their number
    ``density x area`` (rounded); kept when within ``roi_radius_mm`` of ``tip``, in view, facing the camera (the
    capsule is convex: a front-facing point of it is not hidden by the tool itself; ``min_view_cos`` as for the
    liver) and no deeper than the liver's depth buffer plus ``depth_tolerance_mm``.
    """
    r = tool.radius
    if r <= 0 or density_per_mm2 <= 0:
        return np.empty((0, 3))
    tip = np.asarray(tip, dtype=np.float64).reshape(3)
    a = tool.axis
    e1, e2 = _basis(a)
    L = min(tool.length, config.roi_radius_mm + r)
    a_cyl, a_hem = 2.0 * math.pi * r * L, 2.0 * math.pi * r * r
    m = int(round(density_per_mm2 * (a_cyl + a_hem)))
    if m == 0:
        return np.empty((0, 3))
    phi = 2.0 * math.pi * rng.random(m)
    on_cyl = rng.random(m) < a_cyl / (a_cyl + a_hem)
    t = np.where(on_cyl, rng.random(m) * L, 0.0)
    ct = np.where(on_cyl, 0.0, -rng.random(m))  # hemisphere below the centre: cos(polar angle from -a) uniform
    st = np.sqrt(1.0 - ct * ct)
    nrm = (st * np.cos(phi))[:, None] * e1 + (st * np.sin(phi))[:, None] * e2 + ct[:, None] * a
    X = tool.centre + t[:, None] * a + r * nrm
    keep = np.einsum("ij,ij->i", X - tip, X - tip) <= config.roi_radius_mm ** 2
    Xc = camera.to_camera(X)
    z = Xc[:, 2]
    zs = np.where(z > _NEAR_MM, z, 1.0)
    sx, sy = Xc[:, 0] / zs, Xc[:, 1] / zs
    W = camera.half_window
    keep &= (z > _NEAR_MM) & (np.abs(sx) < W) & (np.abs(sy) < W)
    to_cam = camera.position - X
    cosv = np.einsum("ij,ij->i", nrm, to_cam) / np.maximum(np.linalg.norm(to_cam, axis=1), 1e-12)
    keep &= cosv > config.min_view_cos
    keep &= z <= zbuf.lookup(sx, sy) + config.depth_tolerance_mm
    return X[keep]


def draw_count(rng: np.random.Generator, config: ObservationConfig) -> int:
    """Number of cloud points: ``round(exp(U(log n_min, log n_max)))``, within ``n_points``."""
    n0, n1 = config.n_points
    k = int(round(math.exp(rng.uniform(math.log(n0), math.log(n1))))) if n1 > n0 else n0
    return min(max(k, n0), n1)


def observe(
    vertices_mm,
    triangles,
    exertion_point_mm,
    normal,
    config: ObservationConfig | None = None,
    seed=0,
    *,
    tool_axis=None,
    camera_position_mm=None,
) -> tuple[np.ndarray, ObservationRecord]:
    """The cloud a camera sees of one deformed surface; returns ``(cloud (k, 3) mm, record)``.

    Parameters
    ----------
    vertices_mm : (n, 3)
        Deformed surface vertex positions, mm (any frame; the cloud is in the same one).
    triangles : (m, 3) int or SurfaceTopology
        Outward-oriented triangles (the undeformed topology). Pass a
        :class:`SurfaceTopology` to skip the per-call closedness check.
    exertion_point_mm : (3,)
        The tool tip: where the tool touches the *deformed* surface (the
        exertion point moved with the surface; :func:`observe_many` computes
        it). Centre of the ROI ball and the point the camera looks at.
    normal : (3,)
        Outward surface normal at the exertion point (pre-operative is fine):
        the default cone axis and tool axis.
    config : ObservationConfig, optional
        Settings (defaults if ``None``).
    seed : int or sequence of int
        Seed (module docstring); e.g. ``case_seed(observation_seed, case_id)``.
    tool_axis : (3,), optional
        Direction the tool comes from (``-F/|F|``); default ``normal``, tilted by ``config.tool_tilt_deg``.
    camera_position_mm : (3,), optional
        A fixed camera centre (looking at the tip) instead of a random pose.

    Returns
    -------
    cloud : (k, 3) float64
        Unordered points, mm. ``k`` is the drawn count unless too little of
        the ROI is visible (then ``record.n_points < record.n_target``).
    record : ObservationRecord
    """
    cfg = config or ObservationConfig()
    topo = SurfaceTopology.of(triangles)
    V = np.asarray(vertices_mm, dtype=np.float64)
    if V.ndim != 2 or V.shape[1] != 3 or not np.isfinite(V).all():
        raise ValueError(f"vertices must be a finite (n, 3) array in mm (got shape {V.shape})")
    if int(topo.triangles.max()) >= len(V):
        raise ValueError(f"triangles index vertex {int(topo.triangles.max())} but only {len(V)} vertices were given")
    if topo.closed and not topo.orientation_checked:
        _check_outward(V, topo.triangles)
    tip = np.asarray(exertion_point_mm, dtype=np.float64).reshape(3)
    n_out = _unit(normal, "normal")
    rng_cam, rng_smp, rng_noise, rng_inst, rng_tilt, rng_sd, rng_out = _streams(seed)
    a_tool = n_out if tool_axis is None else _unit(tool_axis, "tool_axis")
    if tool_axis is None and cfg.tool_tilt_deg[1] > 0:  # tilted by that angle, towards a random azimuth
        a, b = _basis(n_out)
        phi = 2.0 * math.pi * rng_tilt.random()
        th = math.radians(_in_range(cfg.tool_tilt_deg, rng_tilt))
        a_tool = math.cos(th) * n_out + math.sin(th) * (math.cos(phi) * a + math.sin(phi) * b)
    cone = n_out if cfg.cone_axis is None else _unit(cfg.cone_axis, "cone_axis")
    tool = Tool.at_tip(tip, a_tool, cfg.tool_radius_mm, cfg.tool_shaft_length_mm)
    t0, t1, t2 = topo.columns

    # ---- camera pose
    draws, ok = 0, False
    while True:
        draws += 1
        if camera_position_mm is not None:
            C = np.asarray(camera_position_mm, dtype=np.float64).reshape(3)
        else:
            d0, d1 = cfg.camera_distance_mm
            d = rng_cam.uniform(d0, d1) if d1 > d0 else d0
            C = tip + d * _draw_direction(rng_cam, cone, cfg.cone_half_angle_deg)
        ok = cfg.tool_radius_mm <= 0 or tool.distance(C) > cfg.camera_tool_clearance_mm
        if ok and cfg.require_tool_visible:
            target = tool.centre if cfg.tool_radius_mm > 0 else tip + 0.5 * n_out
            ok = not _segment_hits_surface(target, C, V, topo)
        if ok or camera_position_mm is not None or draws >= cfg.max_camera_draws:
            break
    dist_c = float(np.linalg.norm(C - tip))
    if dist_c <= _NEAR_MM:
        raise ValueError(f"the camera is {dist_c:.3g} mm from the tool tip; it must be farther than {_NEAR_MM} mm")
    camera = Camera.looking_at(C, tip, _half_window(cfg, dist_c))
    rec = ObservationRecord(
        camera_position_mm=C.copy(), camera_distance_mm=dist_c,
        view_angle_deg=float(np.degrees(np.arccos(np.clip((C - tip) @ n_out / dist_c, -1.0, 1.0)))),
        camera_draws=draws, camera_ok=bool(ok), tool_tip_mm=tip.copy(), tool_axis=a_tool.copy(),
    )
    k_target = draw_count(rng_smp, cfg)
    rec.n_target = k_target

    # ---- orientation check (closed surfaces) and candidate triangles: those reaching into the ROI ball
    Xc = camera.to_camera(V)
    R_ = cfg.roi_radius_mm
    rel = V - tip
    box = ((rel[:, 0] < -R_).astype(np.uint8) | ((rel[:, 0] > R_) << 1) | ((rel[:, 1] < -R_) << 2)
           | ((rel[:, 1] > R_) << 3) | ((rel[:, 2] < -R_) << 4) | ((rel[:, 2] > R_) << 5)).astype(np.uint8)
    cand = np.flatnonzero((box[t0] & box[t1] & box[t2]) == 0)
    A0, A1, A2 = Xc[t0[cand]], Xc[t1[cand]], Xc[t2[cand]]
    E1, E2 = A1 - A0, A2 - A0
    nrm = np.cross(E1, E2)
    area2 = np.sqrt(np.einsum("ij,ij->i", nrm, nrm))
    cen = (A0 + A1 + A2) / 3.0
    rad2 = np.maximum(np.maximum(np.einsum("ij,ij->i", A0 - cen, A0 - cen), np.einsum("ij,ij->i", A1 - cen, A1 - cen)),
                      np.einsum("ij,ij->i", A2 - cen, A2 - cen))
    tip_c = camera.to_camera(tip[None])[0]
    dc = np.sqrt(np.einsum("ij,ij->i", cen - tip_c, cen - tip_c))
    keep = (dc - np.sqrt(rad2) <= R_) & (area2 > 0)
    cand, A0, E1, E2, nrm, area2 = cand[keep], A0[keep], E1[keep], E2[keep], nrm[keep], area2[keep]
    if cand.size == 0:
        return np.empty((0, 3)), rec
    plane_dist = -np.einsum("ij,ij->i", nrm, A0) / area2  # camera (origin) to the triangle plane, + = outward side

    # ---- depth buffer
    zbuf = depth_buffer(Xc, topo, camera.half_window, cfg.zbuffer_pixels, front_only=topo.closed,
                        max_depth=dist_c + R_ + 1.0)
    view = View.make(camera, zbuf, tool, tip, cfg)

    # ---- draw candidates until k_target are visible
    cum = np.cumsum(area2)
    total = cum[-1]
    cols = [np.ascontiguousarray(a[:, j]) for a in (A0, E1, E2) for j in range(3)]
    kept, n_kept = [], 0
    counts = np.zeros(1 + len(DROP_REASONS), dtype=np.int64)
    f_est = 0.5
    while n_kept < k_target and counts.sum() < cfg.max_candidates:
        m = int(math.ceil(1.15 * (k_target - n_kept) / max(f_est, 1e-3))) + 64
        m = min(m, cfg.max_candidates - int(counts.sum()))
        t = np.minimum(np.searchsorted(cum, rng_smp.random(m) * total, side="right"), cand.size - 1)
        r1, r2 = rng_smp.random(m), rng_smp.random(m)
        s = np.sqrt(r1)
        b1, b2 = s * (1.0 - r2), s * r2
        x = cols[0][t] + b1 * cols[3][t] + b2 * cols[6][t]
        y = cols[1][t] + b1 * cols[4][t] + b2 * cols[7][t]
        z = cols[2][t] + b1 * cols[5][t] + b2 * cols[8][t]
        code = view.classify(x, y, z, plane_dist[t])
        counts += np.bincount(code, minlength=counts.size)
        vis = np.flatnonzero(code == VISIBLE)[: k_target - n_kept]
        kept.append(np.column_stack([x[vis], y[vis], z[vis]]))
        n_kept += vis.size
        if counts[VISIBLE] == 0 and counts.sum() - counts[1] >= 20000:  # (almost) nothing of the ROI is visible
            break
        f_est = max(counts[VISIBLE] / max(counts.sum(), 1), 1e-3)
    cloud = camera.to_world(np.concatenate(kept)) if kept else np.empty((0, 3))
    rec.candidates = int(counts.sum())
    rec.dropped = {r: int(counts[1 + i]) for i, r in enumerate(DROP_REASONS)}
    in_roi = int(counts.sum() - counts[1])
    rec.visible_fraction = float(counts[VISIBLE] / in_roi) if in_roi else 0.0
    if cfg.instrument_in_cloud and len(cloud):
        # the liver part's density: its points over the visible area (candidate area x visible share)
        visible_area = 0.5 * total * counts[VISIBLE] / counts.sum()
        inst = instrument_points(camera, zbuf, tool, tip, len(cloud) / visible_area, rng_inst, cfg)
        rec.n_instrument_points = int(len(inst))
        cloud = np.concatenate([cloud, inst])
    rec.n_points = int(len(cloud))

    # ---- noise
    sd = _in_range(cfg.noise_sd_mm, rng_sd)
    rec.noise_sd_mm = sd
    if sd > 0 and len(cloud):
        if cfg.noise_mode == "isotropic":
            cloud = cloud + rng_noise.normal(0.0, sd, size=cloud.shape)
        else:
            ray = cloud - C
            ray /= np.linalg.norm(ray, axis=1, keepdims=True)
            cloud = cloud + rng_noise.normal(0.0, sd, size=len(cloud))[:, None] * ray

    # ---- outliers: a wrong depth along the point's own line of sight
    k_out = int(round(cfg.outlier_fraction * len(cloud)))
    if k_out:
        idx = rng_out.choice(len(cloud), size=k_out, replace=False)
        ray = cloud[idx] - C
        ray /= np.linalg.norm(ray, axis=1, keepdims=True)
        cloud = cloud.copy()
        cloud[idx] += rng_out.uniform(-cfg.outlier_range_mm, cfg.outlier_range_mm, size=k_out)[:, None] * ray
    rec.n_outliers = k_out
    return cloud, rec

# --------------------------------------------------------------------------
# many cases of one geometry
# --------------------------------------------------------------------------


def surface_point_displacement(vertices_mm: np.ndarray, triangles: np.ndarray, points_mm: np.ndarray,
                               displacements_mm: np.ndarray) -> np.ndarray:
    """Displacement ``(n, 3)`` at points on the undeformed surface (one displacement field per point).

    Each point is located on its nearest undeformed triangle (closest point,
    barycentric coordinates clamped to the triangle) and the vertex
    displacements are interpolated linearly there.

    Parameters
    ----------
    vertices_mm : (s, 3) undeformed vertices; triangles : (m, 3)
    points_mm : (n, 3) points on (or very near) the surface, e.g. the exertion points
    displacements_mm : (n, s, 3) or list of (s, 3) -- field ``i`` is evaluated at point ``i``
    """
    tri, bary = _locate_on_surface(np.asarray(vertices_mm, dtype=np.float64), np.asarray(triangles),
                                   np.atleast_2d(np.asarray(points_mm, dtype=np.float64)))
    T = np.asarray(triangles)[tri]
    out = np.empty((len(tri), 3))
    for i in range(len(tri)):
        u = np.asarray(displacements_mm[i], dtype=np.float64).reshape(-1, 3)
        out[i] = bary[i] @ u[T[i]]
    return out


def _locate_on_surface(V: np.ndarray, T: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest triangle and clamped barycentrics of each point (exact closest point among 32 nearby triangles)."""
    from scipy.spatial import cKDTree

    A, B, Cc = V[T[:, 0]], V[T[:, 1]], V[T[:, 2]]
    k = min(32, len(T))
    _, near = cKDTree((A + B + Cc) / 3.0).query(pts, k=k)
    near = np.asarray(near).reshape(len(pts), k)
    tri = np.empty(len(pts), dtype=np.int64)
    bary = np.empty((len(pts), 3))
    for i, p in enumerate(pts):
        c = near[i]
        q, lam = _closest_on_triangles(p, A[c], B[c], Cc[c])
        j = int(np.argmin(np.einsum("ij,ij->i", q - p, q - p)))
        tri[i], bary[i] = c[j], lam[j]
    return tri, bary


def _closest_on_triangles(p, A, B, C):
    """Closest points on triangles to ``p`` and their barycentrics (projection, then edges if outside)."""
    e1, e2 = B - A, C - A
    d = p - A
    d11, d12, d22 = (np.einsum("ij,ij->i", x, y) for x, y in ((e1, e1), (e1, e2), (e2, e2)))
    r1, r2 = np.einsum("ij,ij->i", d, e1), np.einsum("ij,ij->i", d, e2)
    det = np.where(np.abs(d11 * d22 - d12 * d12) > 1e-300, d11 * d22 - d12 * d12, 1.0)
    v = (d22 * r1 - d12 * r2) / det
    w = (d11 * r2 - d12 * r1) / det
    lam = np.stack([1.0 - v - w, v, w], axis=1)
    inside = (lam >= 0).all(axis=1)
    best_q = np.where(inside[:, None], A + v[:, None] * e1 + w[:, None] * e2, np.nan)
    best_l = lam.copy()
    # outside: closest point on each edge, keep the nearest
    best_d = np.where(inside, np.einsum("ij,ij->i", best_q - p, best_q - p), np.inf)
    for (P, Q, ia, ib) in ((A, B, 0, 1), (B, C, 1, 2), (C, A, 2, 0)):
        e = Q - P
        t = np.clip(np.einsum("ij,ij->i", p - P, e) / np.maximum(np.einsum("ij,ij->i", e, e), 1e-300), 0.0, 1.0)
        q = P + t[:, None] * e
        dq = np.einsum("ij,ij->i", q - p, q - p)
        better = ~inside & (dq < best_d)
        best_d = np.where(better, dq, best_d)
        best_q[better] = q[better]
        lt = np.zeros_like(lam)
        lt[:, ia], lt[:, ib] = 1.0 - t, t
        best_l[better] = lt[better]
    return best_q, best_l


def case_seed(observation_seed: int, key) -> int:
    """Per-case seed ``derive(observation_seed, "observation.camera", key)`` (:mod:`liverforce.seeds`).

    ``key``: a case id (or a row index). Using the case id rather than a row
    index makes the draw independent of the row order (as
    :mod:`liverforce.learn.representation` does).
    """
    return derive(observation_seed, "observation.camera", key)


def observe_many(
    undeformed_mm,
    triangles,
    displacements_mm,
    exertion_points_mm,
    normals,
    config: ObservationConfig | None = None,
    seed: int = 0,
    *,
    case_keys=None,
    tool_axes=None,
) -> tuple[list[np.ndarray], list[ObservationRecord]]:
    """Observe many cases of one geometry (the triangle checks are done once).

    Parameters
    ----------
    undeformed_mm : (s, 3)
        Undeformed surface vertices (e.g. from :func:`surface_from_mesh`).
    triangles : (m, 3) int or SurfaceTopology
        Outward triangles indexing ``undeformed_mm``.
    displacements_mm : (n, s, 3) array or list of (s, 3)
        Per case, every surface vertex's displacement (the shards'
        ``surface_displacement_mm`` in that vertex order).
    exertion_points_mm : (n, 3)
        Exertion points on the *undeformed* surface (as in the shards); the
        tool tip is each point moved with the surface
        (:func:`surface_point_displacement`).
    normals : (n, 3)
        Outward normals at the exertion points (``frame_normal``).
    config : ObservationConfig, optional
    seed : int
        The observation seed; case ``i`` uses ``case_seed(seed, case_keys[i])``.
    case_keys : sequence of str or int, optional
        Per-case keys (e.g. ``case_id``), so each draw is independent of the
        row order; default the row index.
    tool_axes : (n, 3), optional
        Per-case tool axes (e.g. :func:`tool_axes_from_forces` of ``force_n``); default the normals.

    Returns
    -------
    clouds : list of (k_i, 3) float64 arrays
    records : list of ObservationRecord
    """
    U = np.asarray(undeformed_mm, dtype=np.float64)
    topo = SurfaceTopology.of(triangles, U)
    P = np.atleast_2d(np.asarray(exertion_points_mm, dtype=np.float64))
    Nn = np.atleast_2d(np.asarray(normals, dtype=np.float64))
    n = len(P)
    if len(displacements_mm) != n or len(Nn) != n:
        raise ValueError(f"need one displacement field and one normal per exertion point ({n}); got "
                         f"{len(displacements_mm)} and {len(Nn)}")
    keys = list(range(n)) if case_keys is None else list(case_keys)
    if len(keys) != n:
        raise ValueError(f"case_keys has {len(keys)} entries for {n} cases")
    axes = None if tool_axes is None else np.atleast_2d(np.asarray(tool_axes, dtype=np.float64))
    _, first, inv = np.unique(np.round(P, 9), axis=0, return_index=True, return_inverse=True)
    tri, bary = _locate_on_surface(U, topo.triangles, P[first])
    clouds, records = [], []
    for i in range(n):
        u = np.asarray(displacements_mm[i], dtype=np.float64).reshape(-1, 3)
        if u.shape != U.shape:
            raise ValueError(f"case {keys[i]}: {len(u)} displacements for {len(U)} surface vertices (the shards "
                             "must store the full surface, in the order of surface_from_mesh)")
        j = int(np.ravel(inv)[i])
        tip = P[i] + bary[j] @ u[topo.triangles[tri[j]]]
        c, r = observe(U + u, topo, tip, Nn[i], config, case_seed(seed, keys[i]),
                       tool_axis=None if axes is None else axes[i])
        clouds.append(c)
        records.append(r)
    return clouds, records
