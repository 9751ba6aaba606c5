"""Refine the camera's registration to the pre-operative surface from a view before the tool pushes.

A camera-cloud model reads the cloud's height over the pre-operative surface
and the tool tip's displacement from the exertion point. Both are measured
through the registration that places the camera's frame on the pre-operative
surface, and neither forgives it: on the default run's unseen livers, a
registration 0.5 mm off (a random direction) raises the shipped model's error
from 0.19 N to 0.36 N, 1 mm to 0.61 N, a 1 deg turn about the liver's centroid
to 0.62 N (the validation's ``registration`` rows measure it on every run). A
surgical registration is rarely better than a few millimetres.

What the operating room does give is the same view a moment earlier: the
camera's cloud of the undeformed surface, with the tool touching it at the
exertion point (the *unloaded* cloud). :func:`refine_registration` finds the
small rigid motion that puts that cloud back on the pre-operative surface, and
the same motion is then applied to the loaded cloud and the tool tip:

1. In the local frame at the exertion point (rows ``t1, t2, n``), the
   unloaded points outside a disc round the tool (:data:`TOOL_DISC_MM`) are
   fitted to the pre-operative height raster by Gauss-Newton, point to plane:
   an offset along the normal and the two tilts, which the surface's height
   determines. Points further than 3 robust sds from the median residual (the
   tool's shaft, stray points) are left out of each step.
2. The motion along the surface cannot be read from a smooth patch. It is
   read from the tool: the instrument's axis fitted in the unloaded cloud
   (:func:`liverforce.learn.cloud_features.cloud_grid`, the same fit the model
   reads the tip from) meets the surface at the exertion point; without an
   instrument fit, the tool tip the robot reported at contact (``contact_tip_mm``);
   without the tip at contact, nothing is moved along the surface (and
   :attr:`Refinement.anchor` says so): the instrument's fit starts from that tip,
   its prior, and started from the exertion point itself it would confirm it.
3. Steps 1 and 2 alternate (:data:`ROUNDS` times): a shift along a sloping
   surface first shows as a height offset and a tilt.

4. The liver also changes shape between the scan and the operation
   (pneumoperitoneum, breathing, mobilisation), and no rigid motion undoes
   that. After the rigid fit, what the unloaded points still lie above or
   below the surface is fitted by a smooth polynomial of the tangent
   coordinates (:data:`SHAPE_DEGREE`, the same robust trimming; the tool's disc
   is bridged by it) and taken off the height of every point: the loaded cloud
   is then read against the surface as it was before the tool pushed, not as
   it was scanned. The polynomial's offset and slopes at the exertion point
   (the changed surface's tangent plane there) are handed to the rigid motion
   first (:data:`SHAPE_ROUNDS`): the tool pushes the surface as it is, so the
   local frame turns with it. On the default run's unseen livers with the
   surface changed by a smooth field 5 mm in amplitude and 150 mm in
   wavelength, the rigid refinement left 0.295 N and this one 0.232 N (4 of
   240 cases refused by each; the validation's ``shape`` rows); with no
   change it costs 0.006 N (0.206 against 0.200 N). A change of more than
   :data:`MAX_SHAPE_MM` over the model's grid is refused: the pre-operative
   surface, and the state the model reads from it, no longer describe this
   region.

Rotation about the normal is left as it is: a smooth patch and a round tool do
not show it; a few degrees turn the tangential force by as much.

Everything here is in the model's frame (mm); :class:`Refinement` holds the
4x4 that moves the camera's points (already in that frame through the nominal
registration) rigidly, and the polynomial whose height is then taken off them
(:meth:`Refinement.points` applies both).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy.spatial.transform import Rotation

#: radius (mm) of the disc round the exertion point left out of the surface fit: the tool and the instrument's
#: lowest points (a 5 mm instrument, its tip sphere and a margin)
TOOL_DISC_MM = 6.0
#: fewest unloaded points over the reference (outside the tool's disc) for a fit: the offset and tilts of a plane
#: rest on 3 numbers; 30 points of 0.5 mm noise give the offset to about 0.1 mm
MIN_POINTS = 30
#: alternations of the surface fit and the tool's anchor (carrying the first round's instrument fit through the
#: later motions instead of fitting it again left 0.19 mm along the surface instead of 0.06 mm on 5,000-point clouds:
#: the fit reads the points' rise over the surface; benchmarks/bench_registration.py)
ROUNDS = 3
#: the surface fit reads every k-th unloaded point, k chosen to keep about this many (a 20,000-point cloud: 4,000 give
#: the offset to about 0.01 mm at 0.5 mm of noise)
MAX_FIT_POINTS = 4000
#: Gauss-Newton steps per surface fit (it stops earlier once a step moves less than 1e-6 mm)
ITERATIONS = 15
#: the robust residual scale is never taken below this (mm): a noise-free cloud keeps its points
MIN_SD_MM = 0.3
#: refused beyond these: no longer a refinement (register the surface again)
MAX_SHIFT_MM = 10.0
MAX_TURN_DEG = 15.0
#: refused when the unloaded points stay further than this (rms, mm) from the surface after the fit
MAX_RMS_MM = 2.0
#: degree of the polynomial in the tangent coordinates fitted to what the unloaded points still lie off the surface
#: after the rigid fit (0: rigid only). On the default run's unseen livers (the validation's rows: surfaces changed
#: by 0 / 2 / 5 / 5 mm at 150 / 150 / 300 / 150 mm wavelength) degree 3 left 0.206 / 0.211 / 0.212 / 0.232 N, the
#: rigid fit 0.200 / 0.225 / 0.230 / 0.295 N (fresh clone of 23e068c); degree 2 about the same in a prototype
#: (0.201 / 0.207 / 0.212 / 0.233 N). Degree 3: the slopes at the exertion point are read where the tool hides the
#: surface, and a quadratic fitted round it takes a bend's cubic part for a slope (tests/serve/
#: test_registration_serving.py: a 3 mm bend left 0.07-0.29 N with degree 2, 0.02-0.14 N with degree 3, 0.07-0.24 N
#: rigidly)
SHAPE_DEGREE = 3
#: the shape's fits whose tangent plane at the exertion point is handed to the rigid motion before the last fit
SHAPE_ROUNDS = 2
#: fewest kept unloaded points for the shape's fit (fewer: rigid only, and the refinement says so)
SHAPE_MIN_POINTS = 100
#: refused beyond this (mm): the largest height the shape's correction takes off over the model's grid (at the
#: grid nodes the unloaded points reach, and in the tool's disc)
MAX_SHAPE_MM = 5.0
_LEVER_MM = 20.0  # scales the rotations' columns to millimetres at the patch's reach (conditioning only)


class RegistrationError(ValueError):
    """The unloaded cloud cannot refine the registration (the message says why and what to do)."""


@dataclass(frozen=True)
class Refinement:
    """A registration refinement (model frame, mm): ``x -> A x + t`` for the camera's points.

    ``normal_offset_mm``, ``tangential_mm`` and ``tilt_deg``: the correction at the exertion point, along the
    normal, along the surface and the turn of the normal; ``anchor``: what fixed the motion along the surface
    in the last round that moved it (``instrument``, ``contact tip`` or ``none``); ``n_points``: the unloaded
    points over the patch after the fit; ``rms_before_mm`` / ``rms_mm``: their distance to the surface before and
    after the rigid fit.

    The change of shape (step 4 of the module docstring), after the rigid motion: ``shape`` holds the
    polynomial's coefficients (``shape_degree``, 0 and empty: none fitted) of the height taken off each point
    at its tangent coordinates ``(u, v)`` in the local frame ``shape_origin``, ``shape_R`` (the reference's), read
    with ``(u, v)`` clamped to ``shape_extent_mm``; ``shape_mm``: the largest height it takes off over the model's
    grid (:data:`MAX_SHAPE_MM`); ``rms_shape_mm``: the unloaded points' distance to the surface after it.
    """

    matrix: np.ndarray
    normal_offset_mm: float
    tangential_mm: float
    tilt_deg: float
    anchor: str
    n_points: int
    rms_before_mm: float
    rms_mm: float
    shape_degree: int = 0
    shape: tuple = ()
    shape_origin: np.ndarray | None = None
    shape_R: np.ndarray | None = None
    shape_extent_mm: float = 0.0
    shape_mm: float = 0.0
    rms_shape_mm: float | None = None

    @property
    def rigid(self) -> bool:
        """True when only the rigid motion is applied (no change of shape fitted)."""
        return self.shape_degree == 0

    @property
    def A(self) -> np.ndarray:
        return self.matrix[:3, :3]

    @property
    def t(self) -> np.ndarray:
        return self.matrix[:3, 3]

    def points(self, xyz) -> np.ndarray:
        """Points ``(n, 3)`` or one ``(3,)`` corrected: the rigid motion, then the change of shape."""
        x = np.asarray(xyz, dtype=np.float64)
        return self.reshaped(x @ self.A.T + self.t)

    def reshaped(self, xyz) -> np.ndarray:
        """Points ``(n, 3)`` or one ``(3,)`` already moved rigidly, with the change of shape taken off their height."""
        x = np.asarray(xyz, dtype=np.float64)
        if self.rigid:
            return x
        one = x.ndim == 1
        x = np.atleast_2d(x)
        out = np.empty_like(x)
        _reshape(np.ascontiguousarray(x), self.shape_origin, self.shape_R, _padded(self.shape),
                 self.shape_extent_mm, out)
        return out[0] if one else out

    def to_dict(self) -> dict:
        return {"matrix": np.round(self.matrix, 12).tolist(),
                "matrix_frame": "the model's frame (RAS mm): y = matrix @ [x, 1], x the camera's point after the input "
                                "frame's conversion; corrected point = y - p(u, v) n, (u, v, .) = shape_R (y - "
                                "shape_origin) with u, v clamped to +-shape_extent_mm, n = shape_R's last row, p the "
                                "polynomial sum c_k (u / 20)^(d - j) (v / 20)^j over d <= shape_degree, j <= d in that "
                                "order (none: y)",
                "normal_offset_mm": self.normal_offset_mm,
                "tangential_mm": self.tangential_mm, "tilt_deg": self.tilt_deg, "anchor": self.anchor,
                "n_points": self.n_points, "rms_before_mm": self.rms_before_mm, "rms_mm": self.rms_mm,
                "shape_degree": self.shape_degree, "shape_coefficients": [float(c) for c in self.shape],
                "shape_origin": None if self.rigid else np.asarray(self.shape_origin).tolist(),
                "shape_R": None if self.rigid else np.asarray(self.shape_R).tolist(),
                "shape_extent_mm": self.shape_extent_mm, "shape_mm": self.shape_mm, "rms_shape_mm": self.rms_shape_mm}

    def describe(self) -> str:
        along = {"instrument": "along the surface from the instrument's axis",
                 "contact tip": "along the surface from the tool tip at contact",
                 "none": "nothing along the surface (no tool tip at contact given)"}[self.anchor]
        shape = ("no change of shape fitted" if self.rigid else
                 f"a change of shape up to {self.shape_mm:.2f} mm taken off (degree {self.shape_degree}), "
                 f"{self.rms_shape_mm:.2f} mm after it")
        return (f"registration refined from the unloaded cloud ({self.n_points} points): {self.normal_offset_mm:+.2f} "
                f"mm along the normal, {self.tangential_mm:.2f} mm {along}, normal turned {self.tilt_deg:.2f} deg; "
                f"the unloaded points lie {self.rms_before_mm:.2f} -> {self.rms_mm:.2f} mm (rms) from the surface; "
                f"{shape}")


def _shape_basis(u, v, degree: int, extent: float) -> np.ndarray:
    """Columns ``(u / s)^(d - j) (v / s)^j`` for ``d <= degree``, ``j <= d`` (``s`` = ``_LEVER_MM``), ``(u, v)``
    clamped to ``[-extent, extent]``. A lower degree's columns are the first of a higher one's."""
    u = np.clip(np.asarray(u, dtype=np.float64), -extent, extent) * (1.0 / _LEVER_MM)
    v = np.clip(np.asarray(v, dtype=np.float64), -extent, extent) * (1.0 / _LEVER_MM)
    return np.column_stack([u ** (d - j) * v**j for d in range(degree + 1) for j in range(d + 1)])


@njit(cache=True, nogil=True)  # CompiledCloud reshapes a batch's parts in threads
def _reshape(X, o, R, c, extent, out):
    """``out[i] = X[i] - p(u_i, v_i) n`` in one pass, ``(u, v)`` the tangent coordinates of ``X[i]`` in the frame
    ``o``, ``R`` (rows ``t1, t2, n``) clamped as :func:`_shape_basis` clamps them, ``p`` its polynomial with the
    15 coefficients ``c`` of degree 4 (:func:`_padded`: a lower degree's padded with zeros), written out so the
    loop has no inner loop."""
    s = 1.0 / _LEVER_MM
    for i in range(X.shape[0]):
        d0, d1, d2 = X[i, 0] - o[0], X[i, 1] - o[1], X[i, 2] - o[2]
        u = min(max(R[0, 0] * d0 + R[0, 1] * d1 + R[0, 2] * d2, -extent), extent) * s
        v = min(max(R[1, 0] * d0 + R[1, 1] * d1 + R[1, 2] * d2, -extent), extent) * s
        uu, uv, vv = u * u, u * v, v * v
        dz = (c[0] + c[1] * u + c[2] * v + c[3] * uu + c[4] * uv + c[5] * vv
              + c[6] * uu * u + c[7] * uu * v + c[8] * u * vv + c[9] * vv * v
              + c[10] * uu * uu + c[11] * uu * uv + c[12] * uu * vv + c[13] * uv * vv + c[14] * vv * vv)
        out[i, 0] = X[i, 0] - dz * R[2, 0]
        out[i, 1] = X[i, 1] - dz * R[2, 1]
        out[i, 2] = X[i, 2] - dz * R[2, 2]


def _padded(coef) -> np.ndarray:
    """:func:`_shape_basis`'s coefficients of a degree up to 4 as the 15 of degree 4 (its columns come first)."""
    c = np.zeros(15)
    c[: len(coef)] = coef
    return c


def _largest(reference, spec, coef, degree: int, extent: float, Y: np.ndarray) -> float:
    """The largest height the polynomial takes off over the model's grid: at its nodes (``grid_size`` over
    ``+-half_width_mm``) over the pre-operative patch that the fitted points ``Y`` (local) reach (a point within
    half a spacing) or that lie in the tool's disc the fit bridges; inf where there is none."""
    g, hw, step = int(spec.grid_size), float(spec.half_width_mm), float(spec.spacing_mm)
    u, v = spec.grid().T  # node i * g + j at (u_j, v_i)
    j = np.rint((Y[:, 0] + hw) / step).astype(np.int64)
    i = np.rint((Y[:, 1] + hw) / step).astype(np.int64)
    inside = (j >= 0) & (j < g) & (i >= 0) & (i < g)
    seen = np.zeros(g * g, dtype=bool)
    seen[i[inside] * g + j[inside]] = True
    on = reference.is_covered(u, v) & (seen | (u**2 + v**2 <= TOOL_DISC_MM**2))
    if not on.any():
        return math.inf
    return float(np.max(np.abs(_shape_basis(u[on], v[on], degree, extent) @ np.asarray(coef))))


def _fit_shape(reference, Y: np.ndarray, degree: int, extent: float):
    """The change of shape's coefficients from local points ``Y`` already over the patch and outside the tool's
    disc: least squares, refitted twice on the points within 3 robust sds of the fit. Returns the coefficients,
    the points kept and their residuals after it."""
    r = Y[:, 2] - reference.height(Y[:, 0], Y[:, 1])
    B = _shape_basis(Y[:, 0], Y[:, 1], degree, extent)
    w = _kept(r)
    for _ in range(3):
        c = np.linalg.lstsq(B[w], r[w], rcond=None)[0]
        w = _kept(r - B @ c)
    c = np.linalg.lstsq(B[w], r[w], rcond=None)[0]
    return c, w, (r - B @ c)[w], B


def _kept(r: np.ndarray) -> np.ndarray:
    """The residuals within 3 robust sds of their median (the tool's shaft and stray points left out)."""
    med = float(np.median(r))
    sd = max(1.4826 * float(np.median(np.abs(r - med))), MIN_SD_MM)
    return np.abs(r - med) < 3.0 * sd


def _trimmed_rms(r: np.ndarray) -> float:
    r = r[_kept(r)] if len(r) else r
    return float(np.sqrt(np.mean(r**2))) if len(r) else math.inf


def _in_model_frame(reference, Rl: np.ndarray, tl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The local frame's motion ``y -> Rl y + tl`` as ``x -> M x + c`` in the model frame."""
    M = reference.R.T @ Rl @ reference.R
    return M, reference.origin + reference.R.T @ tl - M @ reference.origin


def _surface_step(ref, X: np.ndarray, Rl: np.ndarray, tl: np.ndarray):
    """One Gauss-Newton step of the offset and tilts: the new motion and the points it rests on (None, None and
    their count when too few)."""
    Y = X @ Rl.T + tl
    k = (Y[:, 0] ** 2 + Y[:, 1] ** 2 > TOOL_DISC_MM**2) & ref.is_covered(Y[:, 0], Y[:, 1])
    Y = Y[k]
    if len(Y) < MIN_POINTS:
        return None, None, len(Y)
    r = Y[:, 2] - ref.height(Y[:, 0], Y[:, 1])
    e = 0.5 * ref.step
    hu = (ref.height(Y[:, 0] + e, Y[:, 1]) - ref.height(Y[:, 0] - e, Y[:, 1])) / (2 * e)
    hv = (ref.height(Y[:, 0], Y[:, 1] + e) - ref.height(Y[:, 0], Y[:, 1] - e)) / (2 * e)
    nrm = np.column_stack([-hu, -hv, np.ones(len(Y))])
    w = _kept(r)
    if w.sum() < MIN_POINTS:
        return None, None, int(w.sum())
    # point to plane: d r = n . (w x y + d t); columns: turns about t1 and t2 (scaled to mm), shift along n
    J = np.column_stack([np.cross(Y, nrm)[:, :2] / _LEVER_MM, nrm[:, 2]])[w]
    x = np.linalg.lstsq(J, -r[w], rcond=None)[0]
    dR = Rotation.from_rotvec([x[0] / _LEVER_MM, x[1] / _LEVER_MM, 0.0]).as_matrix()
    return dR @ Rl, dR @ tl + np.array([0.0, 0.0, x[2]]), int(w.sum())


def refine_registration(reference, spec, unloaded_cloud_mm, contact_tip_mm=None, *,
                        shape_degree: int = SHAPE_DEGREE) -> Refinement:
    """The rigid correction that puts the unloaded cloud on the pre-operative surface (module docstring).

    Parameters
    ----------
    reference : :class:`~liverforce.learn.cloud_features.ReferenceSurface`
        The pre-operative height raster at the exertion point (model frame).
    spec : :class:`~liverforce.learn.cloud_features.CloudGridSpec`
        The model's grid settings (its instrument fit anchors the motion along the surface).
    unloaded_cloud_mm : (k, 3)
        The camera's cloud of the same region before the tool pushed, model frame (nominal registration), mm.
    contact_tip_mm : (3,), optional
        The tool tip at contact (robot kinematics, same frame): the instrument's fit starts from it (its prior),
        and it anchors the motion along the surface when the instrument is not fitted. Without it nothing is
        moved along the surface (``anchor: none``): an instrument fit started from the exertion point itself
        would lean on that prior and confirm it.
    shape_degree : int
        The change of shape's polynomial degree (:data:`SHAPE_DEGREE`; 0: the rigid motion only).

    Raises :class:`RegistrationError` when too few points lie over the pre-operative surface, when they do
    not lie on it after the fit (another region, a deformed surface, wrong units) or when the correction is
    too large to be a refinement, or the change of shape too large for the pre-operative surface to describe.
    """
    from liverforce.learn.cloud_features import cloud_grid

    if isinstance(shape_degree, bool) or not isinstance(shape_degree, (int, np.integer)) or not 0 <= shape_degree <= 4:
        raise RegistrationError(f"shape_degree is a whole number from 0 (rigid only) to 4, got {shape_degree!r}")
    try:
        P = np.asarray(unloaded_cloud_mm, dtype=np.float64).reshape(-1, 3)
        tip0 = None if contact_tip_mm is None else np.asarray(contact_tip_mm, dtype=np.float64).reshape(3)
    except (TypeError, ValueError) as exc:
        raise RegistrationError(f"the unloaded cloud is (k, 3) points and the contact tip one (3,) point ({exc})") \
            from None
    if tip0 is not None and not np.isfinite(tip0).all():
        raise RegistrationError(f"the tool tip at contact is not finite ({tip0.tolist()}): give the robot's tip, or "
                                "none")
    P = P[np.isfinite(P).all(axis=1)]
    X = reference.to_local(P)
    over = reference.is_covered(X[:, 0], X[:, 1])
    n_over = int((over & (X[:, 0] ** 2 + X[:, 1] ** 2 > TOOL_DISC_MM**2)).sum())
    if n_over < MIN_POINTS:
        raise RegistrationError(
            f"the unloaded cloud has {n_over} points over the pre-operative patch round the exertion point (outside "
            f"the tool's {TOOL_DISC_MM:g} mm): at least {MIN_POINTS} are needed. Is it the "
            "camera's view of this region before the tool pushed, in the same units and frame as the loaded cloud?")
    rms_before = _trimmed_rms(X[over][:, 2] - reference.height(X[over][:, 0], X[over][:, 1]))
    Rl, tl = np.eye(3), np.zeros(3)
    anchor = "none"
    Xf = X[:: max(1, len(X) // MAX_FIT_POINTS)]  # the surface fit reads at most about MAX_FIT_POINTS of them
    for _ in range(ROUNDS):
        for _ in range(ITERATIONS):
            R1, t1, n_kept = _surface_step(reference, Xf, Rl, tl)
            if R1 is None:
                raise RegistrationError(
                    f"only {n_kept} unloaded points stay over the pre-operative surface near the exertion point as "
                    f"the fit moves them (at least {MIN_POINTS}): the cloud does not lie on this surface; is it "
                    "this region of this liver, before the tool pushed, in the same units and frame?")
            moved = float(np.linalg.norm(t1 - tl)) + _LEVER_MM * float(np.linalg.norm(R1 - Rl))
            Rl, tl = R1, t1
            if moved < 1e-6:
                break
        M, c = _in_model_frame(reference, Rl, tl)
        q = None
        if spec.instrument_radius_mm > 0 and tip0 is not None:  # fitted each round: it reads the points' rise
            try:
                grid = cloud_grid(P @ M.T + c, reference, spec, M @ tip0 + c)
            except ValueError:
                grid = None
            if grid is not None and grid.n_instrument > 0:
                q, anchor = np.asarray(grid.tip_local, dtype=np.float64), "instrument"
        if q is None and tip0 is not None:
            q, anchor = reference.to_local(M @ tip0 + c)[0], "contact tip"
        if q is None:
            break
        tl = tl - np.array([q[0], q[1], 0.0])  # the tool meets the surface at the exertion point
    Y = X @ Rl.T + tl
    ok = reference.is_covered(Y[:, 0], Y[:, 1])
    rigid_fit = (Rl, tl, Y, ok)  # restored if the shape's fit gives up after moving it
    shape: dict = {}
    extent = float(spec.half_width_mm) + TOOL_DISC_MM  # the cloud's points are read this far (the grid's reach)
    for last in [False] * SHAPE_ROUNDS + [True] if shape_degree > 0 else []:
        fit = ok & (Y[:, 0] ** 2 + Y[:, 1] ** 2 > TOOL_DISC_MM**2)
        if fit.sum() < SHAPE_MIN_POINTS:  # too few for it: the rigid fit alone, as it was
            Rl, tl, Y, ok = rigid_fit
            break
        coef, _, res, _ = _fit_shape(reference, Y[fit], int(shape_degree), extent)
        if last:
            shape = dict(shape_degree=int(shape_degree), shape=tuple(float(x) for x in coef),
                         shape_origin=np.asarray(reference.origin, dtype=np.float64).copy(),
                         shape_R=np.asarray(reference.R, dtype=np.float64).copy(), shape_extent_mm=extent,
                         shape_mm=_largest(reference, spec, coef, int(shape_degree), extent, Y[fit]),
                         rms_shape_mm=float(np.sqrt(np.mean(res**2))))
            break
        # the changed surface's tangent plane at the exertion point (the polynomial's offset and slopes there) is
        # taken by the rigid motion: the tool pushes the surface as it is there, so the local frame turns with it
        a0, au, av = coef[0], coef[1] / _LEVER_MM, coef[2] / _LEVER_MM
        dR = Rotation.from_rotvec([-av, au, 0.0]).as_matrix()  # z -> z - au u - av v, to first order
        Rl, tl = dR @ Rl, dR @ tl - np.array([0.0, 0.0, a0])
        Y = X @ Rl.T + tl
        ok = reference.is_covered(Y[:, 0], Y[:, 1])
    # the unloaded points' distance to the surface after the final rigid motion (before the shape is taken off)
    rms = _trimmed_rms(Y[ok][:, 2] - reference.height(Y[ok][:, 0], Y[ok][:, 1]))
    M, c = _in_model_frame(reference, Rl, tl)
    shift = tl  # the exertion point (the local origin) moves by tl: the correction there, local frame
    turn = math.degrees(math.acos(min(1.0, max(-1.0, (float(np.trace(Rl)) - 1.0) / 2.0))))
    tilt = math.degrees(math.acos(min(1.0, max(-1.0, float(Rl[2, 2])))))
    total = float(np.linalg.norm(shift))
    if total > MAX_SHIFT_MM or turn > MAX_TURN_DEG:
        raise RegistrationError(
            f"the unloaded cloud puts the registration {total:.3g} mm and {turn:.3g} deg off at the exertion point, "
            f"beyond a refinement (at most {MAX_SHIFT_MM:g} mm and {MAX_TURN_DEG:g} deg): register the "
            "pre-operative surface to the camera again")
    A4 = np.eye(4)
    A4[:3, :3], A4[:3, 3] = M, c
    left = shape.get("rms_shape_mm", rms)
    if not left <= MAX_RMS_MM:
        fitted = "rigid fit and a smooth change of shape" if shape else "rigid fit"
        raise RegistrationError(
            f"the unloaded cloud stays {left:.3g} mm (rms) from the pre-operative surface after the best {fitted} "
            f"(at most {MAX_RMS_MM:g} mm): is it this region of this liver, before the tool pushed (no dent), in the "
            "same units and frame as the loaded cloud?")
    if shape and shape["shape_mm"] > MAX_SHAPE_MM:
        raise RegistrationError(
            f"the unloaded cloud lies up to {shape['shape_mm']:.3g} mm off the pre-operative surface after the rigid "
            f"fit, in a smooth change of shape (at most {MAX_SHAPE_MM:g} mm): the liver has changed shape here since "
            "the scan, beyond what a local correction can take; update the pre-operative surface (a non-rigid "
            "registration) for this region")
    return Refinement(matrix=A4, normal_offset_mm=float(shift[2]), tangential_mm=float(np.hypot(shift[0], shift[1])),
                      tilt_deg=tilt, anchor=anchor, n_points=int(ok.sum()), rms_before_mm=rms_before, rms_mm=rms,
                      **shape)
