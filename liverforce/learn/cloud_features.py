"""Unordered camera cloud -> fixed-size, correspondence-free grid features.

A camera cloud (:mod:`liverforce.learn.observation`) has no node ids, a
varying number of points, holes where the tool or the liver itself hides the
surface, and noise. This module turns it into a fixed-length vector on the
same tangent-plane grid as :class:`liverforce.learn.representation.Representation`
(``g x g`` points ``(u_j, v_i)``, ``u_j = -h + 2 h j / (g - 1)``, row-major
in ``v`` then ``u``: feature ``i * g + j``), using only what is known in
surgery: the pre-operative surface near the exertion point, the local frame
there, and the cloud.

Per case
--------
1. **Reference** (pre-operative, once per exertion point;
   :meth:`ReferenceSurface.for_case`): the undeformed surface near the
   exertion point is moved into the local frame ``x_loc = R (x - p)`` (rows
   of ``R``: ``t1, t2, n``; :mod:`liverforce.learn.frames`) and its normal
   height ``z_ref(u, v)`` is rasterised on a fine grid, later read
   bilinearly. By default (``reference: surface``) the raster is a z-buffer
   of the ROI patch's triangles (:meth:`ReferenceSurface.from_patch`): the
   highest sheet at each ``(u, v)``, the one a camera above the exertion
   point sees. The ROI reaches tens of mm and can wrap round a thin edge
   of the liver, so another sheet of the surface can lie under the grid;
   the older ``reference: points`` (:meth:`ReferenceSurface.from_rotation`,
   the piecewise-linear Delaunay interpolant of the ROI *points*, which has
   no way to tell the sheets apart) then mixes them, and the cloud's height
   change there is off by the lobe's thickness (10-30 mm on the default
   livers).
2. **Cloud**: points in the local frame; exact duplicate points are merged
   and the rest put in a canonical (sorted) order, so the result depends on
   neither the point order nor repeated points (bit for bit). Each point gets
   its signed normal height over the pre-operative surface
   ``dz = z - z_ref(u, v)`` at its own tangent coordinates (an Eulerian
   height change: no correspondence needed); points with
   ``|dz| > max_abs_height_mm`` (another sheet of the surface, stray points)
   are ignored.
3. **Per cell**: from the points within ``rho = kernel_radius_cells x
   spacing`` of the grid point (``spacing = 2 h / (g - 1)``), weighted by
   the biweight kernel ``w = (1 - d^2/rho^2)^2``: by default (``estimator:
   linear``) the intercept of the weighted least-squares plane
   ``dz ~ a + b du + c dv`` (local linear regression), which has no bias from
   the slope where the points lie on one side only (the edge of the tool's
   shadow, the edge of the view); the weighted mean of ``dz`` where the points
   are too close to a line for a plane, or with ``estimator: mean``.
   Subtracting the reference first means the pre-operative curvature does not
   bias the estimate; only the deformation's own curvature does, by about
   ``rho^2 / 16 x laplacian(dz)`` inside a full disc of points (for a Gaussian
   dent of depth ``D`` and width ``s`` that is ``rho^2 D / (8 s^2)`` at its
   centre). With ``n`` points in the support, noise of standard deviation
   ``s`` averages down to about ``1.2 s / sqrt(n)`` inside the cloud.
4. **Validity and filling**: a cell is *valid* when at least ``min_points``
   distinct points lie within ``rho`` and they surround the grid point well
   enough: its squared Mahalanobis distance from their weighted centroid
   (weighted covariance of ``(du, dv)``) is at most ``max_leverage``. Other
   cells (hidden by the tool, out of view, too sparse, only a thin sliver of
   points at one side) are filled by the ``fill`` rule:

   - ``laplace`` (default): the harmonic interpolant of the valid cells
     (discrete Laplace equation on the 4-neighbour grid, valid cells fixed,
     zero normal slope at the grid border): smooth, no new extrema;
   - ``zero``: 0, i.e. "as pre-operative";
   - ``nearest``: the value of the nearest valid cell (ties: lowest index).

   With no valid cell at all every cell is 0. The validity mask can be
   appended as a second channel (``include_mask``) so a model knows what was
   filled.

Adding :attr:`CloudGrid.reference` back gives the absolute deformed height
in the local frame, the quantity of representation's ``deformed`` features.

Example
-------
>>> import numpy as np
>>> spec = CloudGridSpec(grid_size=5, half_width_mm=10.0)
>>> u = np.linspace(-20, 20, 41)
>>> U = np.array([[a, b, 0.0] for a in u for b in u])          # flat pre-operative patch
>>> ref = ReferenceSurface.build(U, [0, 0, 0], [0, 0, 1], [1, 0, 0], [0, 1, 0], spec)
>>> cloud = U + [0.0, 0.0, -1.0]                                # pushed 1 mm down
>>> np.allclose(cloud_features(cloud, ref, spec), -1.0)
True
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

import numpy as np
from numba.extending import register_jitable

from liverforce.learn.frames import case_rotations, local_rotations
from liverforce.learn.grid import check_triangles, interpolate_to_grid, top_sheet_height

FILL_RULES = ("laplace", "zero", "nearest")
ESTIMATORS = ("linear", "mean")
#: how the pre-operative height is built: a z-buffer of the ROI patch's triangles | the ROI points' Delaunay
#: interpolant (models written before format 7)
REFERENCES = ("surface", "points")
#: input-contract key of the ROI patch's triangles: (m, 3) indices into ``roi_undeformed_mm`` per case
ROI_TRIANGLES_KEY = "roi_triangles"


@dataclass(frozen=True)
class CloudGridSpec:
    """Settings of the cloud -> grid feature map (JSON-serialisable; store them with a model).

    Parameters
    ----------
    grid_size : int
        Grid points per side ``g`` (>= 3), as ``Representation.grid_size``.
    half_width_mm : float
        Half the grid's side ``h`` (mm), as ``Representation.half_width_mm``.
    kernel_radius_cells : float
        Kernel support radius in grid spacings (default 1.0: a point counts
        for every grid point within one spacing).
    min_points : int
        Distinct points within the support for a cell to be valid (default 3;
        see also ``max_leverage``).
    fill : str
        Rule for invalid cells: ``laplace`` (default), ``zero`` or ``nearest``.
    max_abs_height_mm : float
        Points farther than this from the pre-operative surface along the
        normal are ignored (default 25 mm).
    reference_oversample : int
        Resolution of the pre-operative height raster, per grid spacing
        (default 4).
    estimator : str
        ``linear`` (default): kernel-weighted least-squares plane through the
        points, read at the grid point (local linear regression: no bias from
        the slope where points lie on one side only, e.g. at the tool's
        shadow); ``mean``: kernel-weighted mean (Nadaraya-Watson).
    max_leverage : float
        A cell is valid only if its grid point lies within ``sqrt(max_leverage)``
        weighted standard deviations (Mahalanobis distance) of its points'
        weighted centroid (default 4: two), so a plane is never extrapolated far
        from a thin sliver of points.
    reference : str
        ``surface`` (default): the pre-operative height is the top sheet of the
        ROI patch's triangles (a z-buffer seen along the normal), so a sheet
        of the liver under the grid (round a thin edge) is ignored, as the
        camera does; needs the patch's triangles (``roi_triangles``).
        ``points``: the Delaunay interpolant of the ROI points in the
        tangent plane, which mixes such sheets (camera models written before
        bundle format 7).
    instrument_radius_mm : float
        The tool's radius (mm; 0, the default: the cloud holds no tool points
        and the tip is the kinematic one). Else the cloud may hold the
        instrument's points, as a camera sees them: its axis is fitted to them
        and they are dropped (:func:`fit_instrument`); needs the tool tip.
    instrument_rise_mm : float
        A point within the search radius of the kinematic tip's axis counts as
        the instrument's when it stands this far above the pre-operative
        surface (default 2 mm).
    instrument_clearance_mm : float
        Points within this of the shaft's points (:func:`shaft_fit_radius` of
        ``instrument_radius_mm`` and the point sd) from the fitted axis are
        dropped at any height (default 1 mm): the tool's lower part, in the
        dent.
    instrument_min_points : int
        Fewest instrument points to fit the axis to (default 8); below it the
        kinematic tip is kept.
    instrument_max_tilt_deg : float
        0 (default): the shaft runs along the normal (:func:`fit_instrument`).
        Else it may be tilted up to about this far (degrees) and its slope is
        fitted too (:func:`fit_instrument_tilted`); the tip is then the
        kinematic one projected onto the fitted axis, unless the slope is not
        significant or that tip lies beyond the search radius of the kinematic
        one (:func:`tilt_credible`; the fit along the normal is kept then).
    dent_radius_mm : float
        0 (default): no dent fit. Else the liver points within this tangent
        distance of the tool's axis give the dent's amplitude and the plane it
        sits in (:func:`fit_dent`; needs ``instrument_radius_mm > 0``, the
        tool's radius, and the tool tip).
    instrument_point_sd_mm, instrument_tip_sd_mm : float
        The clouds' point noise and the kinematic tip's tangential noise (sd,
        mm) the fit weighs its points and its prior by (the model's observation
        settings; :func:`liverforce.learn.camera.grid_spec` sets them). A
        cloud clearly noisier than ``instrument_point_sd_mm`` is fitted with
        its own noise, estimated from its instrument points
        (:func:`fit_instrument`).
    outlier_mm : float
        0 (default): every point counts. Else a point whose height change is
        farther than this from the plane fitted at its nearest grid point
        (when that grid point is valid and within the kernel's support; else
        at the nearest valid grid point within the support, as at the edge
        of what the camera sees; a point near no valid grid point is kept)
        is dropped, the planes are fitted again without it, and the dent is
        fitted without it: a camera's
        gross depth errors (stereo mismatches, flying pixels), which would
        pull every plane they fall in. Set it well above the point noise and
        the deformation's curvature over a cell (a few mm).
    instrument_point_sd_max_mm : float or None
        The noisiest training clouds' point sd, when the model was trained on
        a range of point noise (``observation.noise_sd_mm: [lo, hi]``; then
        ``instrument_point_sd_mm`` is ``lo``); None: ``instrument_point_sd_mm``.
        Serving warns about clouds noisier than training from it
        (:func:`liverforce.serve.cloud.noisy_cloud`); the features do not read it.
    """

    grid_size: int
    half_width_mm: float
    kernel_radius_cells: float = 1.0
    min_points: int = 3
    fill: str = "laplace"
    max_abs_height_mm: float = 25.0
    reference_oversample: int = 4
    estimator: str = "linear"
    max_leverage: float = 4.0
    reference: str = "surface"
    instrument_radius_mm: float = 0.0
    instrument_rise_mm: float = 2.0
    instrument_clearance_mm: float = 1.0
    instrument_min_points: int = 8
    instrument_point_sd_mm: float = 0.5
    instrument_tip_sd_mm: float = 0.5
    instrument_max_tilt_deg: float = 0.0
    dent_radius_mm: float = 0.0
    instrument_point_sd_max_mm: float | None = None
    outlier_mm: float = 0.0

    def __post_init__(self) -> None:
        for k, f in (("grid_size", int), ("min_points", int), ("reference_oversample", int),
                     ("half_width_mm", float), ("kernel_radius_cells", float), ("max_abs_height_mm", float),
                     ("max_leverage", float), ("instrument_radius_mm", float), ("instrument_rise_mm", float),
                     ("instrument_clearance_mm", float), ("instrument_min_points", int),
                     ("instrument_point_sd_mm", float), ("instrument_tip_sd_mm", float),
                     ("instrument_max_tilt_deg", float), ("dent_radius_mm", float), ("outlier_mm", float)):
            object.__setattr__(self, k, f(getattr(self, k)))
        if self.instrument_point_sd_max_mm is not None:
            object.__setattr__(self, "instrument_point_sd_max_mm", float(self.instrument_point_sd_max_mm))
        checks = {
            "grid_size": self.grid_size >= 3,
            "half_width_mm": self.half_width_mm > 0,
            "kernel_radius_cells": 0.25 <= self.kernel_radius_cells <= 5.0,
            "min_points": self.min_points >= 1,
            "fill": self.fill in FILL_RULES,
            "max_abs_height_mm": self.max_abs_height_mm > 0,
            "reference_oversample": 1 <= self.reference_oversample <= 32,
            "estimator": self.estimator in ESTIMATORS,
            "max_leverage": self.max_leverage > 0,
            "reference": self.reference in REFERENCES,
            "instrument_radius_mm": 0.0 <= self.instrument_radius_mm < math.inf,
            "instrument_rise_mm": self.instrument_rise_mm > 0,
            "instrument_clearance_mm": self.instrument_clearance_mm >= 0,
            "instrument_min_points": self.instrument_min_points >= 3,
            "instrument_point_sd_mm": self.instrument_point_sd_mm >= 0,
            "instrument_tip_sd_mm": self.instrument_tip_sd_mm >= 0,
            "instrument_point_sd_max_mm": self.instrument_point_sd_max_mm is None or (
                self.instrument_point_sd_mm <= self.instrument_point_sd_max_mm < math.inf),
            "instrument_max_tilt_deg": 0 <= self.instrument_max_tilt_deg < 80,
            "dent_radius_mm": self.dent_radius_mm == 0 or (
                self.instrument_radius_mm < self.dent_radius_mm < math.inf and self.instrument_radius_mm > 0),
            "outlier_mm": 0.0 <= self.outlier_mm < math.inf,
        }
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise ValueError(
                "CloudGridSpec: invalid " + ", ".join(f"{k}={getattr(self, k)!r}" for k in bad)
                + f" (grid_size >= 3, half_width_mm > 0, kernel_radius_cells in [0.25, 5], min_points >= 1, "
                f"fill one of {FILL_RULES}, max_abs_height_mm > 0, reference_oversample in [1, 32], "
                f"estimator one of {ESTIMATORS}, max_leverage > 0, reference one of {REFERENCES}, "
                "instrument_radius_mm >= 0 (finite), instrument_rise_mm > 0, instrument_clearance_mm >= 0, "
                "instrument_min_points >= 3, instrument sds >= 0, instrument_point_sd_max_mm null or at least "
                "instrument_point_sd_mm, dent_radius_mm 0 or above instrument_radius_mm > 0, outlier_mm >= 0)"
            )

    @property
    def spacing_mm(self) -> float:
        """Distance between neighbouring grid points, ``2 h / (g - 1)``."""
        return 2.0 * self.half_width_mm / (self.grid_size - 1)

    @property
    def kernel_radius_mm(self) -> float:
        return self.kernel_radius_cells * self.spacing_mm

    def n_features(self, include_mask: bool = False) -> int:
        return (2 if include_mask else 1) * self.grid_size**2

    def grid(self) -> np.ndarray:
        """Grid points ``(g^2, 2)`` mm: exactly ``Representation.grid()`` for the same ``g`` and ``h``."""
        t = np.linspace(-self.half_width_mm, self.half_width_mm, self.grid_size)
        uu, vv = np.meshgrid(t, t)  # uu[i, j] = t[j], vv[i, j] = t[i]
        return np.column_stack([uu.ravel(), vv.ravel()])

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "CloudGridSpec":
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown cloud-grid setting(s) {unknown}; known: {sorted(known)}")
        return cls(**d)


# --------------------------------------------------------------------------
# the pre-operative reference
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class ReferenceSurface:
    """Pre-operative surface height over the tangent plane at one exertion point (local frame).

    Attributes
    ----------
    origin : (3,) exertion point, mm
    R : (3, 3) rotation, rows ``t1, t2, n``
    lo : float            tangent coordinate (mm) of raster node 0 in ``u`` and ``v``
    step : float          raster spacing, mm
    raster : (r, r)       ``z_ref`` at ``(u, v) = (lo + step j, lo + step i)`` (row ``i`` = ``v``)
    grid_height : (g, g)  ``z_ref`` at the feature grid points
    covered : (r, r) bool or None  raster nodes under the patch (:meth:`from_patch`; the others take the
                          nearest covered node's height); None: every node is interpolated
    """

    origin: np.ndarray
    R: np.ndarray
    lo: float
    step: float
    raster: np.ndarray
    grid_height: np.ndarray
    covered: np.ndarray | None = None

    @classmethod
    def build(cls, undeformed_points_mm, exertion_point_mm, normal, t1, t2, spec: CloudGridSpec,
              label: str = "reference") -> "ReferenceSurface":
        """From the pre-operative surface points near the exertion point (e.g. ``roi_undeformed_mm``): their
        Delaunay interpolant in the tangent plane (``reference: points``; a patch that wraps round an edge of
        the liver needs :meth:`from_patch`).

        Parameters
        ----------
        undeformed_points_mm : (k, 3) surface points (any order), source frame
        exertion_point_mm, normal, t1, t2 : (3,) the local frame (``frame_normal``, ``frame_t1``, ``frame_t2``)
        spec : CloudGridSpec
        label : str  names the case in error messages

        With the rotation already at hand use :meth:`from_rotation`.
        """
        R = local_rotations(np.asarray(normal)[None], np.asarray(t1)[None], np.asarray(t2)[None])[0]
        return cls.from_rotation(undeformed_points_mm, exertion_point_mm, R, spec, label=label)

    @classmethod
    def from_rotation(cls, undeformed_points_mm, exertion_point_mm, R, spec: CloudGridSpec,
                      label: str = "reference") -> "ReferenceSurface":
        """As :meth:`build`, from the local rotation ``R`` (3 x 3, rows ``t1, t2, n``) instead of the frame vectors.

        For callers that hold the case's rotation already
        (:func:`liverforce.learn.frames.case_rotations`, ``Preop.rotation``).
        """
        R, p, U = _local_points(undeformed_points_mm, exertion_point_mm, R, label)
        lo, step, axis = _raster_axis(spec)
        uu, vv = np.meshgrid(axis, axis)
        raster = interpolate_to_grid(U[:, :2], U[:, 2:3], np.column_stack([uu.ravel(), vv.ravel()]), label)[:, 0]
        return cls._with_raster(p, R, lo, step, raster.reshape(uu.shape), spec)

    @classmethod
    def from_patch(cls, undeformed_points_mm, triangles, exertion_point_mm, R, spec: CloudGridSpec,
                   label: str = "reference") -> "ReferenceSurface":
        """The top sheet of a triangulated pre-operative patch (``reference: surface``).

        ``triangles`` ``(m, 3)`` index ``undeformed_points_mm`` (the ROI patch's
        own triangles: ``Preop.roi_triangles``, shard loading). Each raster
        node takes the highest ``z`` of the triangles over it (a z-buffer
        along the normal: what a camera above the exertion point sees); a
        node no triangle covers (past the patch's edge) takes the value of
        the nearest covered one.
        """
        R, p, U = _local_points(undeformed_points_mm, exertion_point_mm, R, label)
        T = check_triangles(triangles, len(U), f"{label}: the pre-operative patch's triangles")
        lo, step, axis = _raster_axis(spec)
        raster = _zbuffer(U, T, lo, step, len(axis))
        covered = np.isfinite(raster)
        if not covered.any():
            raise ValueError(f"{label}: the pre-operative patch covers no point of the +-{axis[-1]:.3g} mm grid "
                             "around the exertion point (is the patch the one round this exertion point?)")
        if not covered.all():
            from scipy.ndimage import distance_transform_edt

            _, (ii, jj) = distance_transform_edt(~covered, return_indices=True)
            raster = raster[ii, jj]
        return cls._with_raster(p, R, lo, step, raster, spec, covered)

    @classmethod
    def for_case(cls, undeformed_points_mm, triangles, exertion_point_mm, R, spec: CloudGridSpec,
                 label: str = "reference") -> "ReferenceSurface":
        """The reference ``spec.reference`` asks for: :meth:`from_patch` (``surface``; ``triangles`` needed)
        or :meth:`from_rotation` (``points``; ``triangles`` unused)."""
        if spec.reference == "points":
            return cls.from_rotation(undeformed_points_mm, exertion_point_mm, R, spec, label=label)
        if triangles is None:
            raise ValueError(
                f"{label}: this camera model reads the pre-operative height from the ROI patch's triangles "
                "(reference: surface) and none were given: pass 'roi_triangles' (indices into "
                "'roi_undeformed_mm'; Preop.from_surface computes them from the liver's surface)")
        return cls.from_patch(undeformed_points_mm, triangles, exertion_point_mm, R, spec, label=label)

    @classmethod
    def _with_raster(cls, p, R, lo: float, step: float, raster, spec: CloudGridSpec,
                     covered: np.ndarray | None = None) -> "ReferenceSurface":
        ref = cls(p, R, float(lo), float(step), raster, np.empty(0), covered)
        g = spec.grid()
        object.__setattr__(ref, "grid_height", ref.height(g[:, 0], g[:, 1]).reshape(spec.grid_size, spec.grid_size))
        return ref

    def to_local(self, points_mm) -> np.ndarray:
        """``R (x - p)`` for points ``(k, 3)`` of the source frame."""
        return (np.asarray(points_mm, dtype=np.float64).reshape(-1, 3) - self.origin) @ self.R.T

    def is_covered(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """True where the pre-operative patch lies under ``(u, v)``: the four raster nodes round it covered and
        inside the raster (no height extrapolated past the patch's edge or clamped at the raster's)."""
        r = self.raster.shape[0]
        fu = (np.asarray(u, dtype=np.float64) - self.lo) / self.step
        fv = (np.asarray(v, dtype=np.float64) - self.lo) / self.step
        ok = (fu >= 0) & (fv >= 0) & (fu < r - 1) & (fv < r - 1)
        if self.covered is None:
            return ok
        j = np.where(ok, fu, 0).astype(np.int64)
        i = np.where(ok, fv, 0).astype(np.int64)
        C = self.covered
        return ok & C[i, j] & C[i, j + 1] & C[i + 1, j] & C[i + 1, j + 1]

    def height(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """``z_ref`` at tangent coordinates (bilinear on the raster; clamped to the raster's extent)."""
        r = self.raster.shape[0]
        fu = np.clip((np.asarray(u) - self.lo) / self.step, 0.0, r - 1.000001)
        fv = np.clip((np.asarray(v) - self.lo) / self.step, 0.0, r - 1.000001)
        j, i = fu.astype(np.int64), fv.astype(np.int64)
        a, b = fu - j, fv - i
        Z = self.raster
        return ((1 - a) * (1 - b) * Z[i, j] + a * (1 - b) * Z[i, j + 1]
                + (1 - a) * b * Z[i + 1, j] + a * b * Z[i + 1, j + 1])


def _local_points(points_mm, exertion_point_mm, R, label: str):
    R = np.asarray(R, dtype=np.float64).reshape(3, 3)
    p = np.asarray(exertion_point_mm, dtype=np.float64).reshape(3)
    U = (np.asarray(points_mm, dtype=np.float64).reshape(-1, 3) - p) @ R.T
    if len(U) < 3 or not np.isfinite(U).all():
        raise ValueError(f"{label}: the pre-operative surface needs at least 3 finite points (got {len(U)}, "
                         f"{int((~np.isfinite(U)).any(axis=1).sum())} not finite)")
    return R, p, U


def _raster_axis(spec: CloudGridSpec) -> tuple[float, float, np.ndarray]:
    """``(lo, step, axis)``: the reference raster's first node, spacing and node coordinates (mm), the same in
    ``u`` and ``v`` (``lo`` and ``step`` exactly as bundles before format 7 computed them)."""
    step = spec.spacing_mm / spec.reference_oversample
    reach = spec.half_width_mm + spec.kernel_radius_mm
    n_half = int(math.ceil(reach / step)) + 1
    lo = -n_half * step
    return lo, step, lo + step * np.arange(2 * n_half + 1)


def _zbuffer(U: np.ndarray, T: np.ndarray, lo: float, step: float, r: int) -> np.ndarray:
    """Highest ``z`` of the triangles ``U[T]`` (local frame) at the ``r x r`` raster nodes ``lo + step k``
    (row = ``v``); -inf where none lies over a node: :func:`liverforce.learn.grid.top_sheet_height` on the
    raster, a band of ``_ZBUFFER_ROWS`` rows at a time against the triangles that reach into the band."""
    axis = lo + step * np.arange(r)
    tri = U[T]
    x0, x1 = tri[:, :, 0].min(axis=1), tri[:, :, 0].max(axis=1)
    y0, y1 = tri[:, :, 1].min(axis=1), tri[:, :, 1].max(axis=1)
    Z = np.empty((r, r))
    for i in range(0, r, _ZBUFFER_ROWS):
        v = axis[i:i + _ZBUFFER_ROWS]
        near = (x1 >= axis[0]) & (x0 <= axis[-1]) & (y1 >= v[0]) & (y0 <= v[-1])
        uu, vv = np.meshgrid(axis, v)
        Z[i:i + len(v)] = top_sheet_height(U, T[near], np.column_stack([uu.ravel(), vv.ravel()]))[1].reshape(len(v), r)
    return Z


_ZBUFFER_ROWS = 4  # raster rows per band of the z-buffer (fewer triangles per band, small temporaries)


# --------------------------------------------------------------------------
# the cloud on the grid
# --------------------------------------------------------------------------


@dataclass
class CloudGrid:
    """One cloud on the grid (arrays ``(g, g)``, row ``i`` = ``v_i``, column ``j`` = ``u_j``).

    Attributes
    ----------
    height : signed normal height change over the pre-operative surface (mm), invalid cells filled
    valid : cells with at least ``min_points`` distinct points within the kernel support, around the grid point
    count : distinct points within the kernel support
    weight : sum of kernel weights
    reference : pre-operative height ``z_ref`` at the grid points (local frame, mm)
    n_points : distinct points used (after cropping; the instrument's dropped)
    tip_local : the tool tip in the local frame (mm): the kinematic one, its tangential part from the fitted
        instrument axis when ``spec.instrument_radius_mm > 0`` and enough instrument points were seen; None
        when no tip was given
    n_instrument : the instrument points the axis was fitted to (0: the kinematic tip kept)
    instrument_sd_mm : the cloud's point noise estimated from the instrument's points (sd, mm;
        :func:`instrument_point_sd`), NaN when no axis was fitted
    dent : ``(amplitude, offset)`` of :func:`fit_dent` (mm), with ``spec.dent_radius_mm > 0``; else None
    n_outliers : the points dropped as off their cell's plane (``spec.outlier_mm``)
    n_outlier_tested : the points tested for it (those within the kernel's support of a valid grid point;
        0 without ``outlier_mm``)
    """

    height: np.ndarray
    valid: np.ndarray
    count: np.ndarray
    weight: np.ndarray
    reference: np.ndarray
    n_points: int
    tip_local: np.ndarray | None = None
    n_instrument: int = 0
    instrument_sd_mm: float = math.nan
    dent: np.ndarray | None = None
    n_outliers: int = 0
    n_outlier_tested: int = 0

    def features(self, include_mask: bool = False) -> np.ndarray:
        """Flat feature vector: ``height`` (``g^2``), then the validity mask as 0/1 if ``include_mask``."""
        h = self.height.ravel()
        return np.concatenate([h, self.valid.ravel().astype(np.float64)]) if include_mask else h.copy()


def _canonical(P: np.ndarray) -> np.ndarray:
    """Rows in a canonical order (sorted by ``u``, ties by ``v`` then ``z``), exact duplicates removed."""
    if len(P) < 2:
        return P
    order = np.argsort(P[:, 0])
    Q = P[order]
    tie = Q[1:, 0] == Q[:-1, 0]
    if tie.any():  # equal u (duplicates or coincident tangent coordinate): full lexicographic order
        Q = P[np.lexsort((P[:, 2], P[:, 1], P[:, 0]))]
        keep = np.ones(len(Q), dtype=bool)
        keep[1:] = (Q[1:] != Q[:-1]).any(axis=1)
        Q = Q[keep]
    return Q


def instrument_search_radius(spec: CloudGridSpec, point_sd_mm: float | None = None) -> float:
    """Distance (mm) from the kinematic tip's axis within which points may be the instrument's: its radius plus
    three sds of the tip's tangential error, two of the points' noise (``point_sd_mm``, by default the spec's)
    and half a millimetre."""
    sdp = spec.instrument_point_sd_mm if point_sd_mm is None else point_sd_mm
    return spec.instrument_radius_mm + 3.0 * spec.instrument_tip_sd_mm + 2.0 * sdp + 0.5


_MIN_POINT_SD = 0.05  # mm: floors of the fit's sds (an exact cloud or tracker still weighs its points and prior)
_MIN_TIP_SD = 1e-3
_FIT_ITERATIONS = 25
#: a cloud whose shaft points scatter this many times the model's point sd about the fitted axis is fitted
#: again with its own (:func:`fit_instrument`)
NOISE_REFIT_RATIO = 1.25
_MAD_SD = 1.4826  # sd of a normal variable per median absolute deviation
#: the fitted slope's Wald statistic below which a shaft counts as along the normal (chi-square, 2 degrees of
#: freedom, p = 0.001): the fit that assumes it is then used, its tip far more precise
TILT_WALD = 13.8
#: a tilted axis whose points scatter about it more than this many times as much as about the fit along the normal
#: (the same estimator on the same selection: the points standing above the surface within the search radius of
#: each axis, at every height, with the tilted fit's point sd) is a minimum that is not the tool's, and the fit along
#: the normal is kept (:func:`fit_instrument_tilted`). The normal fit's own estimate reads only its candidates, in
#: the vertical cylinder round the kinematic tip: a tilted shaft leaves it as it rises, so compared with that the gate
#: turned good tilted fits of noisy clouds (1-1.5 mm, tilted 20-30 deg) into the normal's, 2 mm off. On
#: the default run's unseen liver val-1004, case V-000120 pressed in 24 FE load steps, each seen by a new camera
#: draw (benchmarks/experiment_loading_path.py), the tilted fit of 6 of 24 clouds of a shaft along the normal ran
#: to an axis 1.8-3.4 mm off along the surface, its points scattering 1.0-1.4 mm (sd) about it against 0.5-0.7 mm
#: about the normal fit's axis (ratios 1.7-2.4; at most 1.3 in the other 18 frames); the force then erred by
#: 0.5-1.5 N (0.49 N MAE over the 24 frames, 0.30 N with this gate). On one cloud of each of the 240 validation
#: cases of the unseen livers, and of 240 training cases, it never fired (the slope's Wald statistic already sent
#: every fit to the normal's); in the pipeline's many more clouds it does, and moved every camera figure of the
#: default run within its spread over the splits (docs/experiments.md, session 50).
TILT_SD_RATIO = 1.5


# scipy.special has i0e / i1e, but the serving kernel (numba) cannot call them: these two are written out once and
# compiled there from this source (register_jitable), so reference and kernel run the same arithmetic.
@register_jitable  # plain Python here; compiled where the serving kernel calls it
def _i0e(x: float) -> float:
    """``exp(-x) I0(x)`` for ``x >= 0`` (Abramowitz & Stegun 9.8.1-2; against scipy's ``i0e`` on [0, 1000] the
    relative error is below 5e-7). Plain arithmetic, so the compiled kernel runs the same function; its cached
    kernels are not rebuilt when only this module changes: clear ``liverforce/serve/__pycache__`` after an edit
    here (the kernel-against-reference tests then fail until it is)."""
    if x < 3.75:
        t = (x / 3.75) ** 2
        return math.exp(-x) * (1.0 + t * (3.5156229 + t * (3.0899424 + t * (1.2067492 + t * (0.2659732 + t * (
            0.0360768 + t * 0.0045813))))))
    t = 3.75 / x
    return (0.39894228 + t * (0.01328592 + t * (0.00225319 + t * (-0.00157565 + t * (0.00916281 + t * (
        -0.02057706 + t * (0.02635537 + t * (-0.01647633 + t * 0.00392377)))))))) / math.sqrt(x)


@register_jitable
def _i1e(x: float) -> float:
    """``exp(-x) I1(x)`` for ``x >= 0`` (Abramowitz & Stegun 9.8.3-4; relative error below 6e-7 against scipy's
    ``i1e``)."""
    if x < 3.75:
        t = (x / 3.75) ** 2
        return math.exp(-x) * x * (0.5 + t * (0.87890594 + t * (0.51498869 + t * (0.15084934 + t * (0.02658733 + t * (
            0.00301532 + t * 0.00032411))))))
    t = 3.75 / x
    return (0.39894228 + t * (-0.03988024 + t * (-0.00362018 + t * (0.00163801 + t * (-0.01031555 + t * (
        0.02282967 + t * (-0.02895312 + t * (0.01787654 - t * 0.00420059)))))))) / math.sqrt(x)


@register_jitable
def shaft_fit_radius(r: float, sd: float) -> float:
    """The radius a shaft's fit compares its points' distances from the axis with: the tool's radius ``r`` seen
    through Gaussian noise of sd ``sd`` (mm) in each direction across the axis (``r`` for ``sd = 0``)::

        r / k,    k = E[cos theta] = sqrt(pi / 8) rho (I0e(rho^2 / 4) + I1e(rho^2 / 4)),    rho = r / sd

    (``k``: the mean cosine between a noisy point's direction from the axis and its noise-free one, that of the
    projected normal distribution, about ``1 - sd^2 / (2 r^2)``; so ``r / k`` is about ``r + sd^2 / (2 r)`` for a
    small sd, which is used where ``rho`` is so large that the Bessel form would overflow). Noise moves a point
    outwards more often than inwards, so a camera's half of a shaft fitted with ``r`` pulls the axis towards the
    camera: by 0.07 / 0.37 / 0.95 mm at 0.5 / 1 / 1.5 mm of noise round a 2.5 mm tool (least squares, 150 points),
    against the fit's own 0.1-0.2 mm. With ``r / k`` the fit's estimating equation has zero mean at the true axis
    whatever arc of the shaft is seen (the expected residual times the point's direction: ``E[p] = r E[e]`` and
    ``E[p / |p|] = k E[e]``), so only its small nonlinear bias is left; the mean distance (the Rice mean) in place
    of ``r / k`` still leaves 0.07 mm at 1 mm of noise. It assumes isotropic noise across the axis: noise along the
    line of sight (``noise_mode: ray``) is less radial, and ``r / k`` then over-corrects.
    """
    if sd <= 0.0:
        return r
    rho = r / sd
    if rho > 1e4:  # sd below 1e-4 r: the next term, sd^4 / r^3, is below 1e-16 r
        return r + 0.5 * sd * sd / r
    x = 0.25 * rho * rho
    return r / (math.sqrt(0.125 * math.pi) * rho * (_i0e(x) + _i1e(x)))


def tilt_credible(x, c0, search_mm: float) -> bool:
    """Whether a tilted shaft's fitted axis ``x = (cu, cv, su, sv)`` is one its candidates can support: the tip on
    it (the kinematic tip ``c0`` (u, v) projected onto the axis) within the search radius ``search_mm`` of the
    kinematic tip along the surface, where the candidates were searched. From a poor start the undamped
    Gauss-Newton ran off to a near-horizontal axis far away: on the unseen livers with the tool tilted 30 deg, one
    cloud in 240 had its tip 75 mm from the FE tip (a slope of 87 deg), where the kinematic tip is 0.5 mm off per
    coordinate. The fit is damped now (:func:`_fit_tilted`); this stays the guard against a minimum that is not the
    tool's."""
    su, sv = float(x[2]), float(x[3])
    t = ((float(c0[0]) - float(x[0])) * su + (float(c0[1]) - float(x[1])) * sv) / (1.0 + (su * su + sv * sv))
    du, dv = float(x[0]) + t * su - float(c0[0]), float(x[1]) + t * sv - float(c0[1])
    return du * du + dv * dv <= search_mm * search_mm


def _fit_axis(Q: np.ndarray, c: np.ndarray, c0: np.ndarray, r: float, wp: float, wk: float) -> np.ndarray:
    """Gauss-Newton steps from ``c`` on ``wp sum (|q_i - c| - r)^2 + wk |c - c0|^2`` (:func:`fit_instrument`)."""
    c = c.copy()
    for _ in range(_FIT_ITERATIONS):
        D = Q - c
        n = np.maximum(np.hypot(D[:, 0], D[:, 1]), 1e-9)
        res = n - r
        J = -D / n[:, None]  # d res / d c
        H = wp * (J.T @ J) + wk * np.eye(2)
        step = np.linalg.solve(H, wp * (J.T @ res) + wk * (c - c0))
        c = c - step
        if float(step @ step) < 1e-16:
            break
    return c


def fit_instrument(uv: np.ndarray, dz: np.ndarray, tip_uv,
                   spec: CloudGridSpec) -> tuple[np.ndarray, np.ndarray, int, float]:
    """The instrument's axis from a cloud in the local frame; returns ``(axis_uv, keep, n_fitted, point_sd)``.

    The tool's shaft runs along the normal (the local ``w`` axis), as in the observation model. Its points are
    those within :func:`instrument_search_radius` of the kinematic tip's axis ``tip_uv`` that stand
    ``instrument_rise_mm`` above the pre-operative surface (``dz``: the points' height change); the axis is the
    centre ``c`` that best fits them with the radius the tool's points show through their noise,
    ``r_f = shaft_fit_radius(r, sd_p)`` (``r``: the tool's), a Gauss-Newton MAP estimate of
    ``sum (|p_i - c| - r_f)^2 / sd_p^2 + |c - tip_uv|^2 / sd_k^2`` (the kinematic tip as the prior), once more
    without the points off by more than ``3 sd_p + 0.3 mm``. With fewer than ``instrument_min_points`` such
    points ``c`` stays ``tip_uv``. ``keep``: the points that are not the instrument's: not among those fitted,
    beyond ``r_f + instrument_clearance_mm`` of ``c``, and beyond another ``2 sd_p`` where they stand above the
    pre-operative surface (the shaft's lowest points, pushed out by their noise). The points' order does not matter
    beyond rounding (the sums), so give them in a canonical order for bit-equal results.

    ``sd_p`` is the model's point sd (``instrument_point_sd_mm``) unless the cloud is noisier: the candidates'
    distances from the fitted cylinder, ``|p_i - c| - r_f``, estimate the cloud's own point noise (``1.4826`` times
    their median absolute value), and when that exceeds :data:`NOISE_REFIT_RATIO` times the model's sd, the
    search, the fit, its trim and the drop are done again with it (a camera noisier than the training clouds'
    would otherwise leave the shaft's outer points on the grid, standing up to ``max_abs_height_mm`` over it).
    ``point_sd``: the estimate of the last pass (NaN when nothing was fitted). It assumes what the fit does, a
    shaft along the normal and isotropic noise: the points of a tilted shaft scatter more about a vertical
    cylinder (a tilted tool reads as a noisier cloud), and noise along the line of sight (``noise_mode: ray``)
    shows less in the radial residual.
    """
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    dz = np.asarray(dz, dtype=np.float64).reshape(-1)
    c0 = np.asarray(tip_uv, dtype=np.float64).reshape(2)
    r = spec.instrument_radius_mm
    d0 = np.hypot(uv[:, 0] - c0[0], uv[:, 1] - c0[1])
    sdp = spec.instrument_point_sd_mm
    cand = (d0 < instrument_search_radius(spec)) & (dz > spec.instrument_rise_mm)
    c, n_fit = _fit_candidates(uv[cand], c0, spec, sdp)
    rf = shaft_fit_radius(r, sdp)  # where the shaft's points stand, at this pass's point sd
    sd = math.nan
    if n_fit:
        sd = instrument_point_sd(uv[cand], c, rf)
        if sd > NOISE_REFIT_RATIO * max(sdp, _MIN_POINT_SD):
            sdp = sd
            rf = shaft_fit_radius(r, sdp)
            cand = (d0 < instrument_search_radius(spec, sdp)) & (dz > spec.instrument_rise_mm)
            c, n_fit = _fit_candidates(uv[cand], c0, spec, sdp)
            sd = instrument_point_sd(uv[cand], c, rf)  # from the wider search: less cut off
    d = np.hypot(uv[:, 0] - c[0], uv[:, 1] - c[1])
    clear = rf + spec.instrument_clearance_mm
    near = d < clear
    # the shaft's lowest points, at the surface's height, whose noise put them beyond the clearance
    near |= (d < clear + 2.0 * sdp) & (dz > 0)
    return c, ~(near | cand), n_fit, sd


def _tilt_residuals(Q: np.ndarray, H: np.ndarray, x: np.ndarray, r: float):
    """Distances minus ``r`` of points ``Q`` (u, v) at heights ``H`` from the axis ``x = (cu, cv, su, sv)``
    (through ``(cu, cv)`` at height 0, direction ``(su, sv, 1)``), and their Jacobian ``(k, 4)``."""
    s = x[2:]
    D = Q - x[:2] - H[:, None] * s  # horizontal offsets from the axis at each point's height
    kap = 1.0 / (1.0 + s @ s)
    p = D @ s
    d = np.sqrt(np.maximum(np.einsum("ij,ij->i", D, D) - kap * p * p, 1e-18))
    g = D - kap * p[:, None] * s  # d(d^2)/dD / 2
    J = np.empty((len(Q), 4))
    J[:, :2] = -g / d[:, None]
    J[:, 2:] = (-H[:, None] * g - kap * p[:, None] * D + (kap * kap * p * p)[:, None] * s) / d[:, None]
    return d - r, J


#: a Gauss-Newton step of the tilted fit that raises its objective by more than this fraction is halved (rounding
#: near the minimum raises it by far less)
_COST_RTOL = 1e-9


def _fit_tilted(Q, H, x0, prior, r, wp, wk, ws, iterations: int = _FIT_ITERATIONS):
    """Damped Gauss-Newton on ``wp sum res^2 + wk |c - c0|^2 + ws |s - s0|^2`` from ``x0`` (``prior = (c0, s0)``):
    a step that raises the objective (by more than :data:`_COST_RTOL` of it) is halved until it does not, each
    halving one of the ``iterations``; when they run out on a step that raised it, the point before it.
    Undamped, a poor start can oscillate off to a near-horizontal axis far from the tool (the recorded candidates
    of ``tests/learn/data/runaway_shaft.csv``: 89 deg and 91 mm off undamped, 31 deg, the tilt the tool had, and
    0.4 mm from the kinematic tip damped). Where every full step lowers the objective the steps and the result are
    the undamped ones, bit for bit: on a fresh clone of 764e3ee the features of every training-view and
    evaluation-view cloud of I-IV and the unseen livers (2 x 2,140) were the same with and without the damping."""
    x = np.array(x0, dtype=np.float64)
    W = np.array([wk, wk, ws, ws])
    f_prev, x_prev, step_prev, lam = math.inf, x, x, 1.0
    for _ in range(iterations):
        res, J = _tilt_residuals(Q, H, x, r)
        f = wp * float(res @ res) + float(W @ ((x - prior) ** 2))
        if f > f_prev * (1.0 + _COST_RTOL):  # the last step raised the objective: half of it instead
            lam *= 0.5
            x = x_prev - lam * step_prev
            continue
        A = wp * (J.T @ J) + np.diag(W)
        step = np.linalg.solve(A, wp * (J.T @ res) + W * (x - prior))
        x_prev, f_prev, step_prev, lam = x, f, step, 1.0
        x = x - step
        if float(step @ step) < 1e-16:
            break
    else:  # the budget spent: the last step not yet checked
        res, _ = _tilt_residuals(Q, H, x, r)
        if wp * float(res @ res) + float(W @ ((x - prior) ** 2)) > f_prev * (1.0 + _COST_RTOL):
            x = x_prev
    return x


def _slope_wald(Q, H, x, r, wp, wk, ws) -> float:
    """``s^T Cov(s)^-1 s`` of the fitted slope ``s = x[2:]`` (``Cov``: the slope block of the inverse Gauss-Newton
    Hessian at ``x``, the posterior covariance when the point sd is right)."""
    _, J = _tilt_residuals(Q, H, x, r)
    A = wp * (J.T @ J) + np.diag([wk, wk, ws, ws])
    cov = np.linalg.inv(A)[2:, 2:]
    return float(x[2:] @ np.linalg.solve(cov, x[2:]))


def fit_instrument_tilted(uv: np.ndarray, w: np.ndarray, dz: np.ndarray, tip_local,
                          spec: CloudGridSpec) -> tuple[np.ndarray, np.ndarray, int, float]:
    """The instrument's axis when its shaft may be tilted from the normal (``instrument_max_tilt_deg`` > 0);
    returns ``(tip_local, keep, n_fitted, point_sd)``.

    An instrument comes in through its trocar, rarely square to the surface. The axis is a line through
    ``(c_u, c_v)`` at the kinematic tip's height with slope ``(s_u, s_v)`` per mm of height (direction
    ``(s_u, s_v, 1)``, the tilt ``atan |s|``); a point's residual is its distance from that line minus
    ``r_f = shaft_fit_radius(r, sd_p)`` (exact, in 3D; ``r``: the tool's radius). The candidates stand
    ``instrument_rise_mm`` above the pre-operative surface within the search radius of the kinematic tip's axis
    widened by ``tan(max tilt)`` per mm of height above the tip. The slope starts from the least-squares line of
    the candidates' ``(u, v)`` on their height (the visible half of the shaft is off its axis by the same amount
    at every height), then damped Gauss-Newton
    (:func:`_fit_tilted`) on ``sum res^2 / sd_p^2 + |c - tip_uv|^2 / sd_k^2 + |s|^2 / tan(max tilt)^2`` (the
    kinematic tip and the normal as weak priors), twice refitted without the points off by more than
    ``3 sd_p + 0.3 mm``. The tool's
    tip lies on its axis: the kinematic tip projected onto the fitted axis (its tangential part and a small
    change of its height). ``keep``: the points beyond ``r_f + instrument_clearance_mm`` of the axis, beyond
    another ``2 sd_p`` where they stand above the surface, and beyond the search radius where they stand
    ``instrument_rise_mm`` above it. ``point_sd``: the noise estimate below (NaN when fewer than
    ``instrument_min_points`` candidates were found: then the kinematic tip, the axis along the normal). When the
    points cannot tell the slope from 0 (its Wald statistic below :data:`TILT_WALD`), or the fitted axis is not one
    they can support (:func:`tilt_credible`), the fit that assumes the normal is returned instead
    (:func:`fit_instrument`): with a free slope the tip is an extrapolation down the
    axis, about twice as far off on a shaft along the normal (0.25 against 0.11 mm rms along the surface on scenario
    I's clouds). So is it when the points scatter about the tilted axis more than :data:`TILT_SD_RATIO` times as
    much as about the fit along the normal's axis, measured alike (the damped fit can still end in a minimum that
    is not the tool's).
    A cloud clearly noisier than the model's point sd is fitted again with its own, as in
    :func:`fit_instrument` (the estimate here: the points standing ``instrument_rise_mm`` above the surface within
    the search radius of the fitted axis). ``w``: the points' heights along the local normal (the kinematic tip's
    is ``tip_local[2]``).
    """
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    dz = np.asarray(dz, dtype=np.float64).reshape(-1)
    tip = np.asarray(tip_local, dtype=np.float64).reshape(3)
    H = np.asarray(w, dtype=np.float64) - tip[2]  # heights above the kinematic tip along the normal
    r = spec.instrument_radius_mm
    sdp = spec.instrument_point_sd_mm
    x, n_fit, wald = _tilted_pass(uv, H, dz, tip[:2], spec, sdp)
    sd = math.nan
    if n_fit:
        sd = _tilted_point_sd(uv, H, dz, x, spec, sdp)
        if sd > NOISE_REFIT_RATIO * max(sdp, _MIN_POINT_SD):
            sdp = sd
            x, n_fit, wald = _tilted_pass(uv, H, dz, tip[:2], spec, sdp)
            sd = _tilted_point_sd(uv, H, dz, x, spec, sdp)
    normal = fit_instrument(uv, dz, tip[:2], spec) if n_fit else None
    if (wald < TILT_WALD or not tilt_credible(x, tip[:2], instrument_search_radius(spec, sdp))
            or (normal is not None and sd > TILT_SD_RATIO * _tilted_point_sd(
                uv, H, dz, np.array([normal[0][0], normal[0][1], 0.0, 0.0]), spec, sdp))):
        # no tilt the points can tell from the normal, an axis they cannot support, or one they scatter about far
        # more than about the normal's (a minimum that is not the tool's): the fit along the normal
        c, keep, n_fit, sd = normal if normal is not None else fit_instrument(uv, dz, tip[:2], spec)
        return np.array([c[0], c[1], tip[2]]), keep, n_fit, sd
    d_all, _ = _tilt_residuals(uv, H, x, 0.0)  # every point's distance from the fitted axis
    clear = shaft_fit_radius(r, sdp) + spec.instrument_clearance_mm
    near = d_all < clear
    near |= (d_all < clear + 2.0 * sdp) & (dz > 0)
    # points standing above the surface near the axis at their height: the shaft's, however tilted
    near |= (dz > spec.instrument_rise_mm) & (d_all < instrument_search_radius(spec, sdp))
    s = x[2:]
    t = float((tip[:2] - x[:2]) @ s) / (1.0 + float(s @ s))  # the kinematic tip projected onto the axis
    return np.array([x[0] + t * s[0], x[1] + t * s[1], tip[2] + t]), ~near, n_fit, sd


def _tilted_pass(uv, H, dz, c0, spec: CloudGridSpec, sdp: float) -> tuple[np.ndarray, int, float]:
    """One search and fit of :func:`fit_instrument_tilted` with point sd ``sdp``: the axis ``(cu, cv, su, sv)``
    (the kinematic tip along the normal, and 0, with fewer than ``instrument_min_points`` candidates), the points
    fitted and the slope's Wald statistic (:func:`_slope_wald`). The residuals are the distances minus
    :func:`shaft_fit_radius` of ``sdp``."""
    r = shaft_fit_radius(spec.instrument_radius_mm, sdp)
    t_max = math.tan(math.radians(spec.instrument_max_tilt_deg))
    lat0 = np.hypot(uv[:, 0] - c0[0], uv[:, 1] - c0[1])
    cand = (dz > spec.instrument_rise_mm) & (lat0 < instrument_search_radius(spec, sdp) + t_max * np.maximum(H, 0.0))
    x = np.array([c0[0], c0[1], 0.0, 0.0])
    if cand.sum() < spec.instrument_min_points:
        return x, 0, 0.0
    prior = x.copy()
    wp = 1.0 / max(sdp, _MIN_POINT_SD) ** 2
    wk = 1.0 / max(spec.instrument_tip_sd_mm, _MIN_TIP_SD) ** 2
    ws = 1.0 / max(t_max, 1e-3) ** 2
    Q, Hc = uv[cand], H[cand]
    if np.ptp(Hc) > 1.0:  # the slope first: the visible half-shaft's centroid moves with the axis at every height
        sl = np.linalg.lstsq(np.column_stack([np.ones(len(Hc)), Hc]), Q, rcond=None)[0][1]
        if float(np.hypot(*sl)) <= 1.5 * t_max + 0.05:
            x[2:] = sl
    for _ in range(2):  # fit, then again on the points near the fitted axis
        x = _fit_tilted(Q, Hc, x, prior, r, wp, wk, ws)
        res, _ = _tilt_residuals(Q, Hc, x, r)
        use = np.abs(res) <= 3.0 * sdp + 0.3
        if use.sum() < spec.instrument_min_points:
            break
        Q, Hc = Q[use], Hc[use]
    x = _fit_tilted(Q, Hc, x, prior, r, wp, wk, ws)
    return x, len(Q), _slope_wald(Q, Hc, x, r, wp, wk, ws)


def _tilted_point_sd(uv, H, dz, x, spec: CloudGridSpec, sdp: float) -> float:
    """The cloud's point noise about the fitted axis ``x``: ``1.4826`` times the median ``|d - r_fit|`` of the
    points standing ``instrument_rise_mm`` above the surface within the search radius (point sd ``sdp``) of it
    (``r_fit``: :func:`shaft_fit_radius` of ``sdp``)."""
    d, _ = _tilt_residuals(uv, H, x, 0.0)
    sel = (dz > spec.instrument_rise_mm) & (d < instrument_search_radius(spec, sdp))
    rf = shaft_fit_radius(spec.instrument_radius_mm, sdp)
    return _MAD_SD * float(np.median(np.abs(d[sel] - rf))) if sel.any() else math.nan


def instrument_point_sd(Q: np.ndarray, c, r: float) -> float:
    """The point noise (sd, mm) of a cloud from its instrument points ``Q`` (``(k, 2)``, local ``u, v``) about the
    fitted axis ``c`` of a shaft of radius ``r``: ``1.4826 median ||q_i - c| - r|`` (robust to the few liver points
    among them; the radial part of isotropic noise has the points' sd)."""
    Q = np.asarray(Q, dtype=np.float64).reshape(-1, 2)
    return _MAD_SD * float(np.median(np.abs(np.hypot(Q[:, 0] - c[0], Q[:, 1] - c[1]) - r)))


def _fit_candidates(Q: np.ndarray, c0: np.ndarray, spec: CloudGridSpec, sdp: float) -> tuple[np.ndarray, int]:
    """The axis fitted to the candidate points ``Q`` with point sd ``sdp`` (:func:`fit_instrument`), from the
    kinematic tip ``c0``, and the points it rests on (0, and ``c0``, with fewer than ``instrument_min_points``)."""
    if len(Q) < spec.instrument_min_points:
        return c0.copy(), 0
    r = shaft_fit_radius(spec.instrument_radius_mm, sdp)
    wp = 1.0 / max(sdp, _MIN_POINT_SD) ** 2
    wk = 1.0 / max(spec.instrument_tip_sd_mm, _MIN_TIP_SD) ** 2
    c = _fit_axis(Q, c0, c0, r, wp, wk)
    use = np.abs(np.hypot(Q[:, 0] - c[0], Q[:, 1] - c[1]) - r) <= 3.0 * sdp + 0.3
    if spec.instrument_min_points <= use.sum() < len(Q):  # once more without the outliers, from there
        return _fit_axis(Q[use], c, c0, r, wp, wk), int(use.sum())
    return c, len(Q)


#: fewest liver points within ``dent_radius_mm`` for a dent fit (below it: amplitude and offset 0)
DENT_MIN_POINTS = 12
#: a pivot of the dent fit's normal matrix at most this fraction of its diagonal entry: singular (zeros)
DENT_PIVOT_TOL = 1e-10


def fit_dent(u: np.ndarray, v: np.ndarray, dz: np.ndarray, tip_uv, spec: CloudGridSpec) -> np.ndarray:
    """The dent round the tool: ``(amplitude, offset)`` mm of the least-squares fit, over the liver points
    within ``spec.dent_radius_mm`` of the tool's axis ``tip_uv`` (local frame), of::

        dz = offset + s_u (u - u_t) + s_v (v - v_t) + amplitude * (2 / pi) asin(min(1, a / r))

    ``r`` the tangent distance from the axis, ``a = spec.instrument_radius_mm``: a plane (the liver's own
    motion there) plus the outer profile of a flat punch of the tool's radius pressed into a half-space
    (Sneddon 1946; ``amplitude`` is the punch's depth below the plane). Far enough from the supports the
    amplitude scales with the normal force over the stiffness, and the fit reads it from the visible ring
    round the tool, where the tip itself is hidden. Solved by the normal equations' Cholesky factor (the
    compiled serving path does the same sums); fewer than :data:`DENT_MIN_POINTS` points, or a pivot at most
    :data:`DENT_PIVOT_TOL` of its diagonal entry (points on one line through the axis, or on one circle round
    it): zeros.
    """
    a, rd = spec.instrument_radius_mm, spec.dent_radius_mm
    du, dv = u - float(tip_uv[0]), v - float(tip_uv[1])
    r = np.hypot(du, dv)
    sel = r < rd
    if int(sel.sum()) < DENT_MIN_POINTS:
        return np.zeros(2)
    g = (2.0 / math.pi) * np.arcsin(np.minimum(1.0, a / np.maximum(r[sel], 1e-12)))
    A = np.column_stack([np.ones(g.size), du[sel] / rd, dv[sel] / rd, g])  # the slopes per dent radius
    M = A.T @ A
    try:
        L = np.linalg.cholesky(M)
    except np.linalg.LinAlgError:
        return np.zeros(2)
    if not np.all(np.diag(L) ** 2 > DENT_PIVOT_TOL * np.diag(M)):
        return np.zeros(2)
    coef = np.linalg.solve(L.T, np.linalg.solve(L, A.T @ dz[sel]))
    if not np.all(np.isfinite(coef)):
        return np.zeros(2)
    return np.array([coef[3], coef[0]])


def cloud_grid(cloud_mm, reference: ReferenceSurface, spec: CloudGridSpec, tip_mm=None) -> CloudGrid:
    """Grid the cloud of one case (module docstring).

    Parameters
    ----------
    cloud_mm : (k, 3)
        The observed deformed surface points, source frame, mm, any order (may be empty).
    reference : ReferenceSurface
        The pre-operative reference of the same case (same frame and ``spec``).
    spec : CloudGridSpec
    tip_mm : (3,), optional
        The tool tip from the robot's kinematics (source frame, mm); needed when ``spec.instrument_radius_mm > 0``
        (the instrument's points are found around it and dropped, and its axis refines the tip: ``tip_local``).
    """
    g, h = spec.grid_size, spec.half_width_mm
    P = np.asarray(cloud_mm, dtype=np.float64).reshape(-1, 3)
    P = P[np.isfinite(P).all(axis=1)]
    L = reference.to_local(P)
    reach = h + spec.kernel_radius_mm
    L = L[(np.abs(L[:, 0]) < reach) & (np.abs(L[:, 1]) < reach)]
    L = _canonical(L)
    u, v = L[:, 0], L[:, 1]
    dz = L[:, 2] - reference.height(u, v)
    ok = np.abs(dz) <= spec.max_abs_height_mm
    u, v, dz = u[ok], v[ok], dz[ok]
    tip_local, n_inst, inst_sd = None, 0, math.nan
    if tip_mm is not None:
        tip_local = reference.to_local(np.asarray(tip_mm, dtype=np.float64).reshape(1, 3))[0]
    if spec.instrument_radius_mm > 0:
        if tip_local is None:
            raise ValueError("this cloud model finds the instrument's points around the tool tip: give the tip")
        if spec.instrument_max_tilt_deg > 0:
            tip_local, keep, n_inst, inst_sd = fit_instrument_tilted(np.column_stack([u, v]), L[ok, 2], dz,
                                                                     tip_local, spec)
        else:
            axis, keep, n_inst, inst_sd = fit_instrument(np.column_stack([u, v]), dz, tip_local[:2], spec)
            tip_local = np.array([axis[0], axis[1], tip_local[2]])
        u, v, dz = u[keep], v[keep], dz[keep]
    fit = _cell_fit(u, v, dz, spec)
    n_out = n_tested = 0
    if spec.outlier_mm > 0 and len(u):  # points off their cell's plane by more than outlier_mm: dropped, refitted
        off, tested = _off_plane(u, v, dz, fit, spec)
        n_out, n_tested = int(off.sum()), int(tested.sum())
        if n_out:
            u, v, dz = u[~off], v[~off], dz[~off]
            fit = _cell_fit(u, v, dz, spec)
    W, N, S, valid = fit[:4]
    dent = None
    if spec.dent_radius_mm > 0:
        if tip_local is None:
            raise ValueError("this cloud model fits the dent around the tool tip: give the tip")
        dent = fit_dent(u, v, dz, tip_local[:2], spec)
    height = np.zeros(g * g)
    height[valid] = S[valid]
    height = _fill(height.reshape(g, g), valid.reshape(g, g), spec.fill)
    return CloudGrid(height=height, valid=valid.reshape(g, g), count=N.reshape(g, g).astype(np.int64),
                     weight=W.reshape(g, g), reference=reference.grid_height.copy(), n_points=int(len(u)),
                     tip_local=tip_local, n_instrument=n_inst, instrument_sd_mm=inst_sd, dent=dent,
                     n_outliers=n_out, n_outlier_tested=n_tested)


def _cell_fit(u: np.ndarray, v: np.ndarray, dz: np.ndarray, spec: CloudGridSpec) -> tuple:
    """Per grid point, from the points ``(u, v, dz)`` (local frame, mm): ``(W, N, S, valid, slope_u, slope_v)``,
    the kernel weights' sum, the points within the support, the estimate (module docstring, step 3), the validity
    (step 4) and the plane's slopes per grid spacing (0 where no plane was fitted), each of ``g^2``."""
    g, h = spec.grid_size, spec.half_width_mm
    step = spec.spacing_mm
    W = np.zeros(g * g)
    S = np.zeros(g * g)
    N = np.zeros(g * g, dtype=np.int64)
    valid = np.zeros(g * g, dtype=bool)
    bu = np.zeros(g * g)
    bv = np.zeros(g * g)
    if not len(u):
        return W, N, S, valid, bu, bv
    fu, fv = (u + h) / step, (v + h) / step  # grid-index coordinates
    jc, ic = np.rint(fu).astype(np.int64), np.rint(fv).astype(np.int64)
    kr2 = spec.kernel_radius_cells ** 2
    c = int(math.ceil(spec.kernel_radius_cells))
    # every (stencil offset, point) pair at once, offset-major: each point against the grid points
    # within the kernel's reach of its nearest one
    off = np.arange(-c, c + 1)
    I = ic[None, :] + np.repeat(off, off.size)[:, None]
    J = jc[None, :] + np.tile(off, off.size)[:, None]
    DV, DU = fv[None, :] - I, fu[None, :] - J
    Q = (DU * DU + DV * DV) / kr2
    M = (Q < 1.0) & (I >= 0) & (I < g) & (J >= 0) & (J < g)
    cells = (I * g + J)[M]
    w = (1.0 - Q[M]) ** 2
    du, dv = DU[M], DV[M]
    z = np.broadcast_to(dz, Q.shape)[M]

    def wsum(x=None):
        return np.bincount(cells, weights=w if x is None else w * x, minlength=g * g)

    W, N = wsum(), np.bincount(cells, minlength=g * g)
    Wp = np.where(W > 0, W, 1.0)
    zbar = wsum(z) / Wp
    ub, vb = wsum(du) / Wp, wsum(dv) / Wp  # weighted centroid of the points, relative to the grid point
    cuu, cvv, cuv = wsum(du * du) / Wp - ub * ub, wsum(dv * dv) / Wp - vb * vb, wsum(du * dv) / Wp - ub * vb
    det = cuu * cvv - cuv * cuv
    spread = det > 1e-6 * kr2 * kr2  # (a full disc of radius k grid units gives about k^4 / 64)
    dp = np.where(spread, det, 1.0)
    # squared Mahalanobis distance of the grid point from the points' weighted centroid
    leverage = np.where(spread, (cvv * ub * ub - 2.0 * cuv * ub * vb + cuu * vb * vb) / dp, np.inf)
    S = zbar
    if spec.estimator == "linear":
        cuz, cvz = wsum(du * z) / Wp - ub * zbar, wsum(dv * z) / Wp - vb * zbar
        b = (cvv * cuz - cuv * cvz) / dp
        cc = (cuu * cvz - cuv * cuz) / dp
        S = np.where(spread, zbar - b * ub - cc * vb, zbar)
        bu, bv = np.where(spread, b, 0.0), np.where(spread, cc, 0.0)
    valid = (N >= spec.min_points) & (W > 0) & (leverage <= spec.max_leverage)
    return W, N, S, valid, bu, bv


def _off_plane(u: np.ndarray, v: np.ndarray, dz: np.ndarray, fit: tuple, spec: CloudGridSpec) -> tuple:
    """``(off, tested)``, masks of the points: ``off``, those farther than ``spec.outlier_mm`` in height from the
    plane of a valid grid point within the kernel's support of them, read at their own ``(u, v)``: their nearest
    grid point (ties of the rounding: ``np.rint``'s, to even; clamped to the grid) where it is valid and within the
    support, else the nearest valid grid point within the support (the first of equal distances in the order of
    rows, then columns). So a point at the edge of what the camera sees, whose nearest grid point has too few
    points to be valid but which feeds a valid neighbour's plane, is tested against that plane; a flying pixel at a
    depth edge (the tool's silhouette, a fold) lies there. A point within the support of no valid grid point feeds
    no estimate and is not tested. The points dropped are a camera's gross depth errors (stereo mismatches, flying
    pixels), which would pull every plane they fall in; ``tested``: those within the support of a valid grid
    point."""
    g, h = spec.grid_size, spec.half_width_mm
    step = spec.spacing_mm
    S, valid, bu, bv = fit[2], fit[3], fit[4], fit[5]
    kr2 = spec.kernel_radius_cells ** 2
    fu, fv = (u + h) / step, (v + h) / step
    J = np.clip(np.rint(fu), 0, g - 1).astype(np.int64)
    I = np.clip(np.rint(fv), 0, g - 1).astype(np.int64)
    du, dv = fu - J, fv - I
    cell = I * g + J
    near = (du * du + dv * dv < kr2) & valid[cell]
    res = np.where(near, dz - (S[cell] + bu[cell] * du + bv[cell] * dv), 0.0)
    rest = np.flatnonzero(~near)  # the nearest valid grid point within the support, if any
    if rest.size and valid.any():
        c = int(math.ceil(spec.kernel_radius_cells))
        fu_r, fv_r = fu[rest], fv[rest]
        I0, J0 = np.rint(fv_r).astype(np.int64), np.rint(fu_r).astype(np.int64)
        best = np.full(rest.size, kr2)
        r_res = np.zeros(rest.size)
        for di in range(-c, c + 1):
            for dj in range(-c, c + 1):
                Ii, Jj = I0 + di, J0 + dj
                inside = (Ii >= 0) & (Ii < g) & (Jj >= 0) & (Jj < g)
                cl = np.where(inside, Ii * g + Jj, 0)
                ddu, ddv = fu_r - Jj, fv_r - Ii
                d2 = ddu * ddu + ddv * ddv
                take = inside & (d2 < best) & valid[cl]
                best = np.where(take, d2, best)
                r_res = np.where(take, dz[rest] - (S[cl] + bu[cl] * ddu + bv[cl] * ddv), r_res)
        found = best < kr2
        near[rest] = found
        res[rest] = np.where(found, r_res, 0.0)
    return near & (np.abs(res) > spec.outlier_mm), near


def _fill(H: np.ndarray, valid: np.ndarray, rule: str) -> np.ndarray:
    """Fill the invalid cells of ``H`` (module docstring); all zero if nothing is valid."""
    H = H.copy()
    bad = ~valid
    if not bad.any():
        return H
    if not valid.any() or rule == "zero":
        H[bad] = 0.0
        return H
    g = H.shape[0]
    if rule == "nearest":
        from scipy.spatial import cKDTree

        ii, jj = np.indices(H.shape)
        vi = np.flatnonzero(valid.ravel())
        bi = np.flatnonzero(bad.ravel())
        pts = np.column_stack([ii.ravel(), jj.ravel()]).astype(np.float64)
        d, _ = cKDTree(pts[vi]).query(pts[bi], k=1)
        # lowest-index valid cell among those at the nearest distance (deterministic ties)
        for b, dist in zip(bi, d):
            dd = np.hypot(pts[vi, 0] - pts[b, 0], pts[vi, 1] - pts[b, 1])
            H.flat[b] = H.flat[vi[np.flatnonzero(dd <= dist + 1e-9)[0]]]
        return H
    # laplace: for each unknown cell, sum over grid neighbours (f_cell - f_nb) = 0. At most g^2 unknowns
    # (144 for the shipped 12 x 12 grid): a dense solve is faster than building a sparse matrix.
    idx = -np.ones(g * g, dtype=np.int64)
    unk = np.flatnonzero(bad.ravel())
    m = unk.size
    idx[unk] = np.arange(m)
    A = np.zeros((m, m))
    rhs = np.zeros(m)
    diag = np.zeros(m)
    ui, uj = np.divmod(unk, g)
    for di, dj in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        ni, nj = ui + di, uj + dj
        inside = (ni >= 0) & (ni < g) & (nj >= 0) & (nj < g)
        r = np.flatnonzero(inside)
        nb = ni[r] * g + nj[r]
        diag[r] += 1.0
        known = idx[nb] < 0
        rhs[r[known]] += H.flat[nb[known]]
        A[r[~known], idx[nb[~known]]] -= 1.0
    A[np.arange(m), np.arange(m)] += diag
    H.flat[unk] = np.linalg.solve(A, rhs)
    return H


def cloud_features(cloud_mm, reference: ReferenceSurface, spec: CloudGridSpec,
                   include_mask: bool = False) -> np.ndarray:
    """Feature vector of one cloud: ``cloud_grid(...).features(include_mask)``."""
    return cloud_grid(cloud_mm, reference, spec).features(include_mask)


def cloud_feature_matrix(clouds, references, spec: CloudGridSpec, include_mask: bool = False) -> np.ndarray:
    """Feature matrix ``(n, spec.n_features(include_mask))`` for ``n`` clouds and their references."""
    if len(clouds) != len(references):
        raise ValueError(f"{len(clouds)} clouds but {len(references)} references")
    out = np.empty((len(clouds), spec.n_features(include_mask)))
    for i, (c, r) in enumerate(zip(clouds, references)):
        out[i] = cloud_features(c, r, spec, include_mask)
    return out


def references_from_arrays(arrays: dict, spec: CloudGridSpec) -> list[ReferenceSurface]:
    """One :class:`ReferenceSurface` per case from input-contract arrays.

    Uses ``roi_undeformed_mm`` and ``roi_triangles`` (the pre-operative ROI
    patch: known before surgery, no correspondence is used; the triangles
    only with ``spec.reference == "surface"``), ``exertion_point_mm``,
    ``frame_normal``, ``frame_t1``, ``frame_t2``; ``case_id`` names cases in errors.
    """
    ids = arrays.get("case_id")
    tris = arrays.get(ROI_TRIANGLES_KEY)
    R = case_rotations(arrays)
    out = []
    for i, U in enumerate(arrays["roi_undeformed_mm"]):
        out.append(ReferenceSurface.for_case(
            U, None if tris is None else tris[i], arrays["exertion_point_mm"][i], R[i], spec,
            label=f"case {ids[i] if ids is not None else i}"))
    return out
