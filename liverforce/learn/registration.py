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

Rotation about the normal is left as it is: a smooth patch and a round tool do
not show it; a few degrees turn the tangential force by as much.

Everything here is in the model's frame (mm); :class:`Refinement` holds the
4x4 that maps the camera's points (already in that frame through the nominal
registration) to the corrected ones.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
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
_LEVER_MM = 20.0  # scales the rotations' columns to millimetres at the patch's reach (conditioning only)


class RegistrationError(ValueError):
    """The unloaded cloud cannot refine the registration (the message says why and what to do)."""


@dataclass(frozen=True)
class Refinement:
    """A registration refinement (model frame, mm): ``x -> A x + t`` for the camera's points.

    ``normal_offset_mm``, ``tangential_mm`` and ``tilt_deg``: the correction at the exertion point, along the
    normal, along the surface and the turn of the normal; ``anchor``: what fixed the motion along the surface
    in the last round that moved it (``instrument``, ``contact tip`` or ``none``); ``n_points``: the unloaded
    points over the patch after the fit; ``rms_before_mm`` / ``rms_mm``: their distance to the surface before and after.
    """

    matrix: np.ndarray
    normal_offset_mm: float
    tangential_mm: float
    tilt_deg: float
    anchor: str
    n_points: int
    rms_before_mm: float
    rms_mm: float

    @property
    def A(self) -> np.ndarray:
        return self.matrix[:3, :3]

    @property
    def t(self) -> np.ndarray:
        return self.matrix[:3, 3]

    def points(self, xyz) -> np.ndarray:
        """Points ``(n, 3)`` or one ``(3,)`` corrected."""
        x = np.asarray(xyz, dtype=np.float64)
        return x @ self.A.T + self.t

    def to_dict(self) -> dict:
        return {"matrix": np.round(self.matrix, 12).tolist(),
                "matrix_frame": "the model's frame (RAS mm): corrected point = matrix @ [x, 1], x the camera's point "
                                "after the input frame's conversion",
                "normal_offset_mm": self.normal_offset_mm,
                "tangential_mm": self.tangential_mm, "tilt_deg": self.tilt_deg, "anchor": self.anchor,
                "n_points": self.n_points, "rms_before_mm": self.rms_before_mm, "rms_mm": self.rms_mm}

    def describe(self) -> str:
        along = {"instrument": "along the surface from the instrument's axis",
                 "contact tip": "along the surface from the tool tip at contact",
                 "none": "nothing along the surface (no tool tip at contact given)"}[self.anchor]
        return (f"registration refined from the unloaded cloud ({self.n_points} points): {self.normal_offset_mm:+.2f} "
                f"mm along the normal, {self.tangential_mm:.2f} mm {along}, normal turned {self.tilt_deg:.2f} deg; "
                f"the unloaded points lie {self.rms_before_mm:.2f} -> {self.rms_mm:.2f} mm (rms) from the surface")


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


def refine_registration(reference, spec, unloaded_cloud_mm, contact_tip_mm=None) -> Refinement:
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

    Raises :class:`RegistrationError` when too few points lie over the pre-operative surface, when they do
    not lie on it after the fit (another region, a deformed surface, wrong units) or when the correction is
    too large to be a refinement.
    """
    from liverforce.learn.cloud_features import cloud_grid

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
    Y = X @ Rl.T + tl
    ok = reference.is_covered(Y[:, 0], Y[:, 1])
    rms = _trimmed_rms(Y[ok][:, 2] - reference.height(Y[ok][:, 0], Y[ok][:, 1]))
    if not rms <= MAX_RMS_MM:
        raise RegistrationError(
            f"the unloaded cloud stays {rms:.3g} mm (rms) from the pre-operative surface after the best rigid fit "
            f"(at most {MAX_RMS_MM:g} mm): is it this region of this liver, before the tool pushed (no dent), in the "
            "same units and frame as the loaded cloud?")
    A4 = np.eye(4)
    A4[:3, :3], A4[:3, 3] = M, c
    return Refinement(matrix=A4, normal_offset_mm=float(shift[2]), tangential_mm=float(np.hypot(shift[0], shift[1])),
                      tilt_deg=tilt, anchor=anchor, n_points=int(ok.sum()), rms_before_mm=rms_before, rms_mm=rms)
