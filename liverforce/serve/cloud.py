"""From an unordered observed point cloud to the model's inputs (prediction mode (b)).

A camera gives the deformed surface as an unordered cloud: no node of it
corresponds to a node of the pre-operative surface. What a model can be fed
then depends on what it was trained on:

``roi_features: deformed`` without state vector — **exact** (up to how the
    surface is sampled). The features are the deformed height over the
    deformed tangent coordinates; the cloud *is* such a sample. The cloud's
    points on the ROI footprint are used in place of the deformed ROI nodes
    (tool occlusion ``remove`` then drops points by their *deformed* tangent
    distance, which for a camera is what the tool hides). With the same
    points as the simulation's deformed nodes, in any order, the prediction
    equals correspondence mode (a) to rounding; with another sampling of the
    same surface it differs by the interpolation error of the grid
    (quantified in ``tests/serve/test_cloud.py``).

``roi_features: cloud`` (camera-cloud models, with or without the state vector) — **exact**.
    They were trained on camera clouds (:mod:`liverforce.learn.camera`): the
    cloud goes in as it is (any order, density, holes), with the tool tip's
    position from the robot's kinematics (``tool_tip_mm``). Refused, naming the
    reason, when the input leaves what training covered (:func:`camera_checks`):
    too few points near the tool, too little of the grid seen, a height change
    or tip displacement far beyond the training cases'; milder departures come
    back as warnings in ``info["warnings"]``.

``roi_features: displacement`` / ``both``, or any other model with the state vector — **approximate only**
    (``approximate=True``, refused otherwise). Node displacements and the
    deformed ROI centroid need correspondence; tangential sliding of a smooth
    surface does not change its shape (the aperture problem), so it cannot be
    recovered from geometry. The estimate used: each undeformed ROI node
    ``(u_j, v_j, z_j)`` (local frame) moves along the normal only, to the
    observed surface's height there,

        D_j ≈ (u_j, v_j, z_obs(u_j, v_j)),

    with ``z_obs`` the piecewise-linear (Delaunay) interpolant of the cloud
    (nearest point outside its hull), and the deformed ROI centroid is the
    mean of these ``D_j``. The normal displacement is then right to first
    order (error ~ tangential displacement x surface slope); tangential
    displacement is taken as zero, so the tangential force is biased towards
    zero. Use only where that is acceptable.

Measured on synthetic cases (``tests/serve/test_cloud.py``): same points in
any order -> mode (a) to 1e-6 N; a new 300-point sampling of the same surface
-> median 0.25 N (max 0.9 N) off mode (a), below that model's own test error;
the normal-only estimate -> normal force 0.065 N median off, tangential force
0.3-0.5 N median off (not recovered).

Cropping: cloud points count as ROI points when their tangent coordinates
lie in the undeformed ROI's tangent bounding box (grown by 10 % of the grid
half-width ``h``, as deformed boundary nodes move outwards) and they lie within
``scale_factor x`` (largest training feature, mm) of the nearest undeformed
ROI node's height (this drops the tool and far-away surface). Fewer than
``Limits.min_cloud_points`` left, or a footprint covering less than half the
model's grid in either direction, is refused (units, registration, occlusion).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from liverforce.learn import camera
from liverforce.learn.cloud_features import _MIN_POINT_SD
from liverforce.learn.frames import tip_offsets
from liverforce.learn.representation import interpolate_to_grid
from liverforce.serve.checks import Limits, TrainingScale
from liverforce.serve.errors import PredictionInputError
from liverforce.serve.input_frame import as_entered, declared_as, reading_hint, written
from liverforce.serve.preop import Preop, _points


def cloud_support(model) -> str:
    """``"exact"`` if an unordered cloud determines the model's inputs, else ``"approximate"``."""
    rep = model.representation
    return "exact" if rep.is_camera or (rep.features == "deformed" and not model.uses_state) else "approximate"


def camera_checks(model, x: np.ndarray, limits: Limits) -> list[str]:
    """Out-of-distribution checks of one camera-cloud feature row ``x``; raises or returns warnings.

    Against ``meta["training_scale"]["camera"]`` (the training rows' ranges):
    the share of grid cells the cloud covers (refused below half the smallest
    training share, warned below it), the largest height change and the tool
    tip's displacement (refused beyond ``limits.scale_factor`` x the training
    maximum, warned beyond the maximum).
    """
    rec = ((model.meta or {}).get("training_scale") or {}).get("camera")
    if not rec:
        return []
    g2 = model.representation.grid_size**2
    seen = float(np.mean(x[g2:2 * g2]))
    height = float(np.max(np.abs(x[:g2][x[g2:2 * g2] > 0.5]))) if seen > 0 else 0.0
    tip = float(np.linalg.norm(x[-3:]))
    out = []
    lo = float(rec["valid_fraction"][0])
    if seen < 0.5 * lo:
        raise PredictionInputError(
            f"cloud: the camera sees only {100 * seen:.0f} % of the model's grid around the tool (training: at least "
            f"{100 * lo:.0f} %); too much is hidden (tool, view angle) or the cloud is not registered to the liver")
    if seen < lo:
        out.append(f"the cloud covers {100 * seen:.0f} % of the grid, less than any training case ({100 * lo:.0f} %)")
    for name, val, top, unit in (("height change over the pre-operative surface", height, rec["height_abs_max_mm"],
                                  "mm"), ("tool tip displacement", tip, rec["tip_displacement_max_mm"], "mm")):
        if val > limits.scale_factor * top:
            raise PredictionInputError(
                f"cloud: the {name} is {val:.3g} {unit}, more than {limits.scale_factor:g} x the largest in training "
                f"({top:.3g} {unit}): check the units (mm), the registration and the tool tip position")
        if val > top:
            out.append(f"the {name} ({val:.3g} {unit}) exceeds every training case's ({top:.3g} {unit})")
    return out


def crop_cloud(cloud_local: np.ndarray, U_loc: np.ndarray, scale: TrainingScale, limits: Limits) -> np.ndarray:
    """Boolean mask of cloud points (local frame) on the ROI footprint (module docstring)."""
    margin = 0.1 * scale.half_width_mm  # deformed boundary nodes move a little outwards
    lo, hi = U_loc[:, :2].min(axis=0) - margin, U_loc[:, :2].max(axis=0) + margin
    inside = ((cloud_local[:, :2] >= lo) & (cloud_local[:, :2] <= hi)).all(axis=1)
    if not inside.any():
        return inside
    ref = max(scale.feature_abs_max) if scale.feature_abs_max else 10.0
    max_off = limits.scale_factor * max(ref, 1.0)
    _, nn = cKDTree(U_loc[:, :2]).query(cloud_local[inside, :2])
    near = np.abs(cloud_local[inside, 2] - U_loc[nn, 2]) <= max_off
    out = inside.copy()
    out[np.flatnonzero(inside)[~near]] = False
    return out


def cloud_to_arrays(model, cloud_mm, preop: Preop, *, approximate: bool, scale: TrainingScale,
                    limits: Limits, tool_tip_mm=None, frame=None, given=None) -> tuple[dict, dict]:
    """One-row input-contract arrays from an unordered cloud; returns ``(arrays, info)``.

    ``info``: ``mode`` (exact/approximate), ``points_given``, ``points_used``.
    ``tool_tip_mm``: the tool tip's position (camera-cloud models need it).
    ``frame``: the units and frame the user declared for the points (an
    :class:`~liverforce.serve.input_frame.InputFrame`; None: none, RAS mm), for the refusals, which give the
    inputs back as entered; ``given``: the cloud and the tip as the caller got them, in the model's frame
    (before a registration moved them; default: the ones passed), taken back through ``frame`` for a refusal only
    (:func:`~liverforce.serve.input_frame.as_entered`).
    """
    given = (cloud_mm, tool_tip_mm) if given is None else given
    if model.representation.is_camera:
        return _camera_arrays(model, cloud_mm, preop, tool_tip_mm, limits, frame, given)
    support = cloud_support(model)
    if support != "exact" and not approximate:
        why = []
        if model.representation.features != "deformed":
            why.append(f"roi_features '{model.representation.features}' reads node displacements")
        if model.uses_state:
            why.append("its state vector needs the deformed ROI centroid")
        raise PredictionInputError(
            "this model cannot be fed exactly from an unordered point cloud: " + " and ".join(why) + ", which need "
            "node correspondence (tangential sliding is invisible to geometry). Pass tracked ROI nodes "
            "(Predictor.predict), train with model.roi_features=deformed and model.state_vector=false, or accept the "
            "documented normal-only estimate with approximate=True"
        )
    O = _points("cloud", cloud_mm, min_points=1)
    p = preop.exertion_point_mm
    R = preop.rotation
    U = preop.roi_undeformed_mm
    U_loc = (U - p) @ R.T
    O_loc = (O - p) @ R.T
    keep = crop_cloud(O_loc, U_loc, scale, limits)
    n_used = int(keep.sum())
    if n_used < limits.min_cloud_points:
        med = float(np.median(np.linalg.norm(O - p, axis=1)))
        hint = cloud_hint(frame, as_entered(frame, given[0]), p, scale.half_width_mm, limits.min_cloud_points)
        raise PredictionInputError(
            f"cloud: only {n_used} of {len(O)} points lie on the ROI footprint near the pre-operative surface "
            f"(at least {limits.min_cloud_points} needed; the points are a median {med:.4g} mm from the exertion "
            f"point; {declared_as(frame)}): "
            + (hint or f"is the cloud {_in_what(frame)}registered to the liver frame, and does it show the tool "
                       "region?"))
    Ok = O_loc[keep]
    h = scale.half_width_mm
    span = Ok[:, :2].max(axis=0) - Ok[:, :2].min(axis=0)
    if (span < h).any():
        raise PredictionInputError(
            f"cloud: the points on the ROI cover only {span[0]:.3g} x {span[1]:.3g} mm of the model's "
            f"{2 * h:.3g} x {2 * h:.3g} mm grid: the observed region is too small (or the units are off)"
        )
    O_src = O[keep]
    out = preop.to_arrays(U)
    if support == "exact":
        out.pop("roi_triangles", None)  # the ROI becomes the cloud (a deformed-height model reads no triangles)
        out["roi_undeformed_mm"] = [O_src]
        out["roi_deformed_mm"] = [O_src]
        return out, {"mode": "exact", "points_given": len(O), "points_used": n_used}
    z = interpolate_to_grid(Ok[:, :2], Ok[:, 2:3], U_loc[:, :2], "cloud")[:, 0]
    D_loc = np.column_stack([U_loc[:, :2], z])
    D_est = p + D_loc @ R
    out["roi_centroid_deformed_mm"] = D_est.mean(axis=0)[None]
    if model.representation.features == "deformed":
        out.pop("roi_triangles", None)  # they index the ROI nodes, which the cloud replaces
        out["roi_undeformed_mm"] = [O_src]
        out["roi_deformed_mm"] = [O_src]
    else:
        out["roi_deformed_mm"] = [D_est]
    return out, {"mode": "approximate", "points_given": len(O), "points_used": n_used}


def tool_tip_of(tool_tip_mm) -> np.ndarray:
    """The tool tip (3,) mm, refused when missing or not 3 finite numbers (the camera models need it)."""
    if tool_tip_mm is None:
        raise PredictionInputError(
            "this camera-cloud model needs the tool tip's position (from the robot's kinematics, mm in the liver "
            "frame) with the cloud: --tool-tip X Y Z, or tool_tip_mm=")
    tip = np.asarray(tool_tip_mm, dtype=np.float64).reshape(-1)
    if tip.shape != (3,) or not np.isfinite(tip).all():
        raise PredictionInputError(f"tool_tip_mm: need 3 finite coordinates (mm), got {tool_tip_mm!r}")
    return tip


REGISTRATION_NORMAL_ONLY = (
    "the registration was refined along the normal only: without the tool tip at contact nothing fixed the shift "
    "along the surface, which the tip's displacement reads (give the robot's tip at contact: --contact-tip, "
    "contact_tip_mm)")


def registration_warnings(fix) -> list[str]:
    """The warning of a registration refinement (:meth:`liverforce.serve.Predictor.refine_registration`; None:
    none) that fixed nothing along the surface, as every path gives it after the cloud's own warnings."""
    return [REGISTRATION_NORMAL_ONLY] if fix is not None and fix.anchor == "none" else []


def metres_cloud(O: np.ndarray, half_width_mm: float, min_points: int, frame=None) -> str | None:
    """The refusal of a cloud ``O`` (finite points, model frame) in metres read as mm, else None: at least
    ``min_points`` points spanning less than a fiftieth of the grid's half-width (0.4 mm for the shipped 20 mm; no
    view of a liver is that small) but at least a thousandth of it once read as metres (a few identical points are
    not named). ``frame``: the units and frame declared (None: none); a cloud declared in metres is not named."""
    if len(O) < min_points:
        return None
    said = frame is not None and frame.declared
    if said and frame.scale >= 1000.0:
        return None
    span = float(np.max(np.ptp(O, axis=0)))
    if not 0.001 * half_width_mm <= span < 0.02 * half_width_mm:
        return None
    if said:
        return (f"cloud: its {len(O)} points span {span:.3g} mm, too small for a view of the liver: it looks like "
                f"metres while {frame.units} was declared ({declared_as(frame)}); give it in {frame.units}, as the "
                "other inputs")
    return (f"cloud: its {len(O)} points span {span:.3g} mm, too small for a view of the liver: it looks like metres "
            "read as mm; give --units m (in Python, convert to mm or compile_cloud(..., units='m'); the MLflow "
            "pyfunc: params units='m')")


def _in_what(frame) -> str:
    """The question a refusal asks of the units: none declared, "in mm and " (the model's); else nothing (the
    declared ones hold, or another reading would have been named)."""
    return "" if frame is not None and frame.declared else "in mm and "


#: a refused cloud's points read in other units or frames (:func:`cloud_hint`): at most this many of them
_HINT_POINTS = 2000


def cloud_hint(frame, cloud_given, p: np.ndarray, half_width_mm: float, min_points: int) -> str | None:
    """The units or frame a refused cloud (``cloud_given``: as the user entered it) looks like it is in, said
    against the declared ones (:func:`~liverforce.serve.input_frame.reading_hint`): the reading that puts
    ``min_points`` of its points within 1.5 grid half-widths of the exertion point ``p`` (model frame); None."""
    G = np.asarray(cloud_given, dtype=np.float64).reshape(-1, 3)
    G = G[np.isfinite(G).all(axis=1)]
    G = G[:: max(1, len(G) // _HINT_POINTS)]
    need = min(min_points, len(G))
    if need == 0:
        return None
    return reading_hint(frame, G,
                        lambda X: (np.linalg.norm(X - p, axis=-1) <= 1.5 * half_width_mm).sum(axis=-1) >= need)


def few_points(O: np.ndarray, p: np.ndarray, n_used: int, half_width_mm: float, min_points: int, frame=None,
               given=None) -> str:
    """Why a cloud ``O`` (model frame) with ``n_used`` points over the grid round ``p`` is refused. ``frame``:
    the units and frame declared (None: none); ``given``: the cloud as entered (default ``O``)."""
    med = float(np.median(np.linalg.norm(O - p, axis=1)))
    hint = cloud_hint(frame, O if given is None else given, p, half_width_mm, min_points)
    return (f"cloud: only {n_used} of {len(O)} points lie over the model's {2 * half_width_mm:.3g} mm grid around the "
            f"exertion point (at least {min_points} needed; the points are a median {med:.4g} mm from it; "
            f"{declared_as(frame)}): "
            + (hint or f"is the cloud {_in_what(frame)}registered to the liver frame, and does it show the tool "
                       "region?"))


#: how far above the liver (outward along the exertion point's normal) a tool tip may lie: the training tips never
#: rise above it (they press in, down to 30 mm along the normal in the default data); a tracked tip has about
#: 0.5 mm of noise. A tip higher than this does not touch the liver at this exertion point
TIP_ABOVE_MM = 5.0


def tip_off_grid(tip, p: np.ndarray, R: np.ndarray, half_width_mm: float):
    """Whether a tool tip (model frame, mm; one ``(3,)`` or many ``(..., 3)``) at the exertion point ``p`` (local
    rotation ``R``) is refused as off the grid: more than ``half_width_mm`` from ``p`` along the surface (the grid
    does not see the tool), or more than :data:`TIP_ABOVE_MM` above the liver (the tool does not touch it). A
    deep press along the normal is neither (the training range of tip displacements judges it,
    :func:`camera_checks`). Returns ``(off, along, above)`` (:func:`~liverforce.learn.frames.tip_offsets`)."""
    along, above = tip_offsets(tip, p, R)
    return (along > half_width_mm) | (above > TIP_ABOVE_MM), along, above


def far_tip(tip, half_width_mm: float, p: np.ndarray, R: np.ndarray, tip_given, frame=None) -> str:
    """Why a tool tip ``tip`` (model frame) refused by :func:`tip_off_grid` is refused: its offset along the
    surface beyond the grid, or its height above the liver, the tip as entered (``tip_given``) with the units and
    frame declared (``frame``; None: none), and the units or frame it looks like it is in if another reading
    puts it on the grid."""
    _, along, above = tip_off_grid(tip, p, R, half_width_mm)
    hint = reading_hint(frame, tip_given, lambda X: ~tip_off_grid(X, p, R, half_width_mm)[0])
    where = (f"is {float(along):.4g} mm from the exertion point along the surface, beyond the model's grid "
             f"(+-{half_width_mm:.3g} mm)" if along > half_width_mm else
             f"lies {float(above):.4g} mm above the liver at the exertion point (outward along its normal; at most "
             f"{TIP_ABOVE_MM:g} mm): the tool does not touch it there")
    return (f"tool_tip_mm {where}: it was given as {written(frame, tip_given)} ({declared_as(frame)}): "
            + (hint or f"is the tip {_in_what(frame)}in the frame of the exertion point, and is the tool at this "
                       "exertion point?"))


def check_camera_cloud(rep, O: np.ndarray, tip: np.ndarray, p: np.ndarray, R: np.ndarray, limits: Limits,
                       frame=None, given=None, *, n_used: int | None = None, entered=None) -> int:
    """The refusals of one camera cloud ``O`` (finite points, model frame, mm) with the tool tip ``tip`` at the
    exertion point ``p`` (local ``rotation`` R) for a camera model ``rep``, in their order: a cloud in metres read
    as mm (:func:`metres_cloud`), too few points over the model's grid (:func:`few_points`), a tip off the grid
    (:func:`tip_off_grid`, :func:`far_tip`); returns the points over the grid. ``frame``: the units and frame
    declared (None: none); ``given``: the cloud and the tip in the model's frame before a registration moved
    them (default ``(O, tip)``), given back as entered in a refusal; ``entered``: a function giving the cloud and
    the tip as the user entered them, when the caller holds them (default: ``given`` converted back,
    :func:`as_entered`; only a refusal calls it);
    ``n_used``: the points over the grid when the caller counted them already (the compiled kernel does).
    The one order and wording of every path: the reference ones (``Predictor.predict_cloud``,
    ``predict_arrays``, the MLflow pyfunc) and the compiled one (``CompiledCloud._refusal``)."""
    given = (O, tip) if given is None else given
    if entered is None:
        def entered():
            return as_entered(frame, given[0]), as_entered(frame, given[1])
    metres = metres_cloud(O, rep.half_width_mm, limits.min_cloud_points, frame)
    if metres:
        raise PredictionInputError(metres)
    if n_used is None:
        O_loc = (O - p) @ R.T
        reach = rep.half_width_mm * (1.0 + 2.0 / (rep.grid_size - 1))
        n_used = int((np.abs(O_loc[:, :2]) <= reach).all(axis=1).sum())
    if n_used < limits.min_cloud_points:
        raise PredictionInputError(few_points(O, p, n_used, rep.half_width_mm, limits.min_cloud_points, frame,
                                              entered()[0]))
    if tip_off_grid(tip, p, R, rep.half_width_mm)[0]:
        raise PredictionInputError(far_tip(tip, rep.half_width_mm, p, R, entered()[1], frame))
    return int(n_used)


def _camera_arrays(model, cloud_mm, preop: Preop, tool_tip_mm, limits: Limits, frame,
                   given: tuple) -> tuple[dict, dict]:
    """Arrays of a camera-cloud model: the cloud as given, the tool tip, the pre-operative context (``frame``,
    ``given``: :func:`cloud_to_arrays`)."""
    tip = tool_tip_of(tool_tip_mm)
    O = _points("cloud", cloud_mm, min_points=1)
    rep = model.representation
    p = preop.exertion_point_mm
    R = preop.rotation
    n_used = check_camera_cloud(rep, O, tip, p, R, limits, frame, given)
    info = {"mode": "exact", "points_given": len(O), "points_used": n_used}
    n_shaft = check_instrument(rep, O, tip, preop.roi_undeformed_mm, preop.roi_triangles, p, R)
    if n_shaft is not None:
        info["instrument_points"] = n_shaft
    out = preop.to_arrays(preop.roi_undeformed_mm)
    out["camera_cloud_mm"] = [O]
    out["tool_tip_mm"] = tip[None]
    return out, info


#: the serving check for the instrument's points in a cloud (:func:`shaft_points`): points within the tool's
#: radius plus SHAFT_MARGIN_MM of the kinematic tip's axis (the normal) standing SHAFT_RISE_MM above the mean
#: height change of the ring SHAFT_RING_MM wide round them (the liver round a tool pushing into it lies no higher
#: than that ring, and a cloud shifted along the normal shifts the ring too); SHAFT_POINTS of them are an
#: instrument
SHAFT_MARGIN_MM = 2.5
SHAFT_RING_MM = 4.0
SHAFT_RISE_MM = 6.0
SHAFT_POINTS = 8
#: the warning of a model that fits the instrument's axis when the cloud shows too little of it to fit
MASKED_INSTRUMENT = ("too few points of the tool's shaft to fit its axis (the instrument masked out of the cloud, or "
                     "a sparse cloud): the tip along the surface is the kinematic one, less precise than the "
                     "instrument's axis")


#: a cloud whose instrument points scatter this many times the training clouds' point noise about the fitted
#: shaft is warned about (:func:`noisy_cloud`). On clouds of the synthetic livers (tests/learn/test_instrument.py's
#: observation, 2,500 points, 100 clouds per level) the estimate was at most 1.33x the noise at the training
#: noise (1.53x the most seen in other draws); 5 / 76-84 / 97-100 % of the clouds at 1.5 / 2 / 3x it pass 1.75x
NOISY_CLOUD_RATIO = 1.75


def _trained_sd_mm(spec) -> float:
    """The training clouds' point sd (``spec.instrument_point_sd_mm``; trained on a range, its most,
    ``instrument_point_sd_max_mm``), floored as the instrument fit floors it."""
    most = spec.instrument_point_sd_max_mm
    return max(float(spec.instrument_point_sd_mm if most is None else most), _MIN_POINT_SD)


def noisy_threshold_mm(spec) -> float:
    """The point noise (sd, mm) above which :func:`noisy_cloud` warns: :data:`NOISY_CLOUD_RATIO` times the
    training clouds' (:func:`_trained_sd_mm`)."""
    return NOISY_CLOUD_RATIO * _trained_sd_mm(spec)


def noisy_cloud(point_sd_mm: float, spec) -> str | None:
    """The warning for a cloud noisier than the model's training clouds, or None: its point noise estimated from
    the instrument's points (:func:`liverforce.learn.cloud_features.instrument_point_sd`; NaN when nothing was
    fitted: None) above :func:`noisy_threshold_mm`, :data:`NOISY_CLOUD_RATIO` times the training clouds'.
    The fit has used the cloud's own noise (:func:`~liverforce.learn.cloud_features.fit_instrument`); the
    regressor has not seen such clouds."""
    trained = _trained_sd_mm(spec)
    sd = float(point_sd_mm)
    if not sd > noisy_threshold_mm(spec):
        return None
    most = "noisiest " if spec.instrument_point_sd_max_mm is not None else ""
    return (f"the cloud's points scatter {sd:.2g} mm (sd) about the tool's shaft, {sd / trained:.1f} times the "
            f"{trained:g} mm noise of the model's {most}training clouds: a noisier camera than the model was trained "
            "for; its error grows with the point noise (the report's camera sensitivity)")


#: a cloud with more than this share of its tested points dropped as off the surface through their neighbours is
#: warned about (:func:`outlier_cloud`): the report's camera sensitivity scores up to 10 % of the points at gross
#: depth errors (of which about 70 % lie beyond the shipped 3 mm). Clean clouds lose points too where the camera
#: sees the surface edge-on (no height field there): on 40 clean views of the unseen livers, 2 of about 700 points
#: lost 12 and 17 %, the others under 1 %
OUTLIER_WARN_SHARE = 0.10


def outlier_cloud(n_out: float, n_tested: float, spec) -> str | None:
    """The warning for a cloud with more than :data:`OUTLIER_WARN_SHARE` of its points tested dropped as gross
    depth errors (``spec.outlier_mm``; :func:`liverforce.learn.cloud_features.cloud_grid`), or None."""
    n_out, n_tested = int(n_out), int(n_tested)
    if not spec.outlier_mm > 0 or n_tested <= 0 or not n_out > OUTLIER_WARN_SHARE * n_tested:
        return None
    return (f"{100 * n_out / n_tested:.0f} % of the cloud's points ({n_out} of the {n_tested} on the model's grid) "
            f"lay more than {spec.outlier_mm:g} mm off the surface fitted through their neighbours and were dropped: "
            "gross depth errors (stereo mismatches, flying pixels at depth edges) or a surface seen edge-on; more "
            "than the report's camera sensitivity scores (up to 10 % of the points at such errors)")


def cloud_warnings(spec, fitted: int | None, point_sd_mm: float | None, dropped: tuple) -> list[str]:
    """A camera cloud's own warnings, in their order: too little of the instrument to fit its axis (``fitted``
    0: the kinematic tip; None: no fit), a cloud noisier than training (:func:`noisy_cloud`; ``point_sd_mm``
    None: not estimated), gross depth errors dropped (:func:`outlier_cloud`; ``dropped``: dropped, tested).
    The reference paths' (``Predictor.predict_cloud``, ``predict_arrays``); the compiled one gates its
    batches by the same functions."""
    noisy = noisy_cloud(point_sd_mm, spec) if point_sd_mm is not None else None
    gross = outlier_cloud(*dropped, spec)
    return [w for w in ([MASKED_INSTRUMENT] if fitted == 0 else []) + [noisy, gross] if w]


def instrument_check_radius(rep, spec) -> float:
    """The tool radius the serving check for the instrument's points uses, 0 for none: models trained on
    clouds without the instrument (those trained with it see it as in training), whose height reference is the
    patch's top sheet (``reference: points`` mixes in another sheet of a thin lobe, 10-30 mm off)."""
    cfg = camera.observation_config(rep.camera, rep.half_width_mm, rep.grid_size)
    if cfg.instrument_in_cloud or spec.reference != "surface":
        return 0.0
    return cfg.tool_radius_mm


def check_instrument(rep, cloud_mm, tip_mm, roi_undeformed_mm, roi_triangles, exertion_point_mm,
                     rotation) -> int | None:
    """The serving check for the instrument in one cloud (model frame, mm) of a camera model ``rep``: None for a
    model that does not check (:func:`instrument_check_radius`), else the points on the shaft
    (:func:`shaft_points`); refused (:func:`instrument_refusal`) from ``SHAFT_POINTS`` on."""
    spec = camera.grid_spec(rep.grid_size, rep.half_width_mm, rep.camera)
    r_tool = instrument_check_radius(rep, spec)
    if r_tool <= 0:
        return None
    p = np.asarray(exertion_point_mm, dtype=np.float64)
    n_shaft = shaft_points((np.asarray(cloud_mm, dtype=np.float64).reshape(-1, 3) - p) @ rotation.T,
                           (np.asarray(tip_mm, dtype=np.float64) - p) @ rotation.T, r_tool, spec, roi_undeformed_mm,
                           roi_triangles, p, rotation)
    if n_shaft >= SHAFT_POINTS:
        raise PredictionInputError(instrument_refusal(n_shaft, r_tool))
    return n_shaft


def instrument_refusal(n_shaft: int, tool_radius_mm: float) -> str:
    """Why a model trained on clouds without the instrument refuses one with ``n_shaft`` points on its shaft."""
    return (f"cloud: {n_shaft} points within {tool_radius_mm + SHAFT_MARGIN_MM:g} mm of the tool's axis stand "
            f"{SHAFT_RISE_MM:g} mm or more above the surface round them: the instrument is in the cloud, and this "
            "model was trained on clouds without it. Mask the instrument out of the reconstruction, or use a model "
            "trained with it (camera.observation.instrument_in_cloud, and camera.grid.instrument_radius_mm to fit "
            "its axis)")


def shaft_points(cloud_local: np.ndarray, tip_local: np.ndarray, tool_radius_mm: float, spec, roi_undeformed_mm,
                 roi_triangles, exertion_point_mm, rotation) -> int:
    """Points of a cloud (local frame of the exertion point) on the tool's shaft: over the grid's reach (as the
    features read them), within ``tool_radius_mm + SHAFT_MARGIN_MM`` of the axis through the (kinematic) tip
    along the normal, ``SHAFT_RISE_MM`` or more above the mean height change over the pre-operative surface
    (``spec``'s reference of the pre-operative ROI patch, at the exertion point with the local ``rotation``) of
    the points in the ring ``SHAFT_RING_MM`` wide round them (0 if the ring is empty); 0 when fewer than
    ``SHAFT_POINTS`` points lie that near the axis at all."""
    from liverforce.learn.cloud_features import ReferenceSurface

    reach = spec.half_width_mm + spec.kernel_radius_mm
    d = np.hypot(cloud_local[:, 0] - tip_local[0], cloud_local[:, 1] - tip_local[1])
    inner = tool_radius_mm + SHAFT_MARGIN_MM
    near = np.flatnonzero((d < inner + SHAFT_RING_MM) & (np.abs(cloud_local[:, 0]) < reach)
                          & (np.abs(cloud_local[:, 1]) < reach))
    if np.count_nonzero(d[near] < inner) < SHAFT_POINTS:
        return 0
    try:
        ref = ReferenceSurface.for_case(roi_undeformed_mm, roi_triangles, exertion_point_mm, rotation, spec,
                                        label="pre-operative context")
    except ValueError as exc:
        raise PredictionInputError(str(exc)) from None
    L = cloud_local[near]
    dz = L[:, 2] - ref.height(L[:, 0], L[:, 1])
    ring = (d[near] >= inner) & (np.abs(dz) <= spec.max_abs_height_mm)
    base = float(np.sum(dz[ring]) / np.count_nonzero(ring)) if ring.any() else 0.0
    return int(np.count_nonzero((d[near] < inner) & (dz >= base + SHAFT_RISE_MM)))
