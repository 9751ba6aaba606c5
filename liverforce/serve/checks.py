"""Input checks against the model's training scale: refuse, never guess.

A force model only knows the range it was trained on. Before predicting,
every case is checked (each failure is a :class:`PredictionInputError` that
names the input and the likely cause):

===========================  ==================================================
check                        refused when
===========================  ==================================================
shape / finiteness           not ``(k, 3)``; NaN or inf anywhere; empty
ROI size                     fewer than ``min_roi_points`` nodes
ROI extent (units)           the ROI's centred tangent half-extent is more than
                             ``scale_factor`` x the model's grid half-width
                             ``h``, or its largest tangent extent is below
                             ``h / scale_factor`` (a liver in m, cm or µm)
exertion point on surface    the exertion point is more than ``surface_tol_mm``
                             from the pre-operative surface: measured to its
                             triangles when the context was built from them
                             (``Preop.surface_point_mm``), else to the ROI's
                             triangles (``roi_triangles``), else the undeformed
                             ROI's height there (a quadratic fit of the nearest
                             nodes in the local frame); or it lies outside its ROI
ROI beyond the tool          (models with ``occlusion: remove``) fewer than 3 ROI nodes
                             (the fewest the model resamples) at the occlusion radius or
                             beyond it, from the exertion point in the tangent plane: the
                             model drops the nodes the tool hides
ROI patch                    (models that read it) ``roi_triangles`` missing, not ``(m, 3)`` whole
                             numbers indexing ``roi_undeformed_mm``, covering
                             none of the grid, or their top sheet more than
                             ``surface_tol_mm`` from the exertion point
displacement (units)         largest ROI displacement above ``scale_factor`` x
                             the largest grid feature seen in training
liver size (units)           ``(tr I / 2)^(1/5)`` outside the training range
                             by more than ``scale_factor`` (inertia in mm⁵)
centroid distance            ``|c_liver - p|`` likewise
material (units)             a constant outside its training range by more
                             than ``scale_factor`` (e.g. Pa or kPa for MPa)
===========================  ==================================================

After the prediction, a force larger than every training case's (``|F|`` above the largest of
``meta["training_scale"]["force_magnitude_n"]``) is returned with a warning (:func:`force_warnings`): the
regressor extrapolates there, and the interval's widths were calibrated on smaller forces. So is a GP model's
case whose inputs lie farther from every training case than the model's training-side quantile
(``meta["input_distance"]``, :mod:`liverforce.learn.interval`; :func:`distance_warnings`). A wrong exertion
point is one way to get there: on the default run's unseen liver val-1000, the exertion point given 5 mm from
where the tool pressed turned a 3.8 N case into 7.5 N, with every input check passed.

The ranges come from ``meta["training_scale"]`` of the bundle
(:func:`liverforce.learn.model.training_scale`); bundles written before it
existed fall back to ranges derived from the fitted scalers (approximate,
said so in :attr:`TrainingScale.source`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from liverforce.learn.frames import local_rotations
from liverforce.learn.state import MATERIAL_START, outside_ranges
from liverforce.serve.errors import OffSurfaceError, PredictionInputError
from liverforce.serve.preop import _points, _vector

#: how the state vector is laid out (liverforce.learn.state)


@dataclass(frozen=True)
class Limits:
    """Tolerances of the input checks (module table)."""

    scale_factor: float = 4.0
    surface_tol_mm: float = 2.0
    min_roi_points: int = 10
    min_cloud_points: int = 20


_RECORDED = "bundle meta training_scale"  #: TrainingScale.source of ranges recorded at training


@dataclass(frozen=True)
class TrainingScale:
    """Ranges of the training inputs of one model (``None``: not known, not checked)."""

    half_width_mm: float
    inertia_length_mm: tuple[float, float] | None
    centroid_distance_mm: tuple[float, float] | None
    material_lo: np.ndarray | None
    material_hi: np.ndarray | None
    feature_abs_max: tuple[float, ...] | None
    n_material: int | None
    source: str
    thickness_mm: tuple[float, float] | None = None
    compliance_trace: tuple[float, float] | None = None
    force_max_n: float | None = None  # the largest |F| of the training cases (N; bundles since it was recorded)

    @property
    def recorded(self) -> bool:
        """The ranges are the training rows' own (``meta["training_scale"]``), not rough ones from the scalers."""
        return self.source == _RECORDED

    @classmethod
    def of(cls, model) -> "TrainingScale":
        """From the bundle's ``meta["training_scale"]``, else approximately from the scalers."""
        rep = model.representation
        ss = model.pre.state_scaler
        n_mat = model.pre.n_material
        rec = (model.meta or {}).get("training_scale")
        if rec:
            lo, hi = (np.asarray(v, dtype=np.float64) for v in rec["material_params_mpa"])
            thick = rec.get("tool_thickness_mm")
            ctr = rec.get("probe_compliance_mm_per_n")
            fmag = rec.get("force_magnitude_n")
            return cls(rep.half_width_mm, tuple(rec["inertia_length_mm"]), tuple(rec["centroid_distance_mm"]),
                       lo, hi, tuple(rec["feature_abs_max"]), n_mat if n_mat is not None else int(lo.size),
                       _RECORDED, None if thick is None else tuple(thick),
                       None if ctr is None else tuple(ctr), None if fmag is None else float(fmag[1]))
        fs = model.pre.feature_scaler
        g2 = rep.grid_size**2
        feat = tuple(float(np.max(np.abs(fs.mean[c * g2:(c + 1) * g2]) + 4 * fs.scale[c * g2:(c + 1) * g2]))
                     for c in range(rep.channels))
        if ss is None:
            return cls(rep.half_width_mm, None, None, None, None, feat, None,
                       "approximate: fitted feature scaler (bundle has no training_scale)")
        m, s = ss.mean, ss.scale
        trace = m[9] + m[12] + m[14]
        length = float(np.power(max(trace, 0.0) / 2.0, 0.2))
        dist = float(np.linalg.norm(m[0:3]))
        mm, ms = m[MATERIAL_START:MATERIAL_START + n_mat], s[MATERIAL_START:MATERIAL_START + n_mat]
        # the scaler may have replaced a tiny spread by 1 (degenerate): then trust the mean alone
        ms = np.where(ms < np.abs(mm), ms, 0.0)
        return cls(rep.half_width_mm, (length, length), (0.5 * dist, 2.0 * dist), mm - 3 * ms, mm + 3 * ms, feat,
                   n_mat, "approximate: fitted scalers (bundle has no training_scale)")


def _outside(value: float, lo: float, hi: float, factor: float) -> bool:
    return value > hi * factor or value < lo / factor


def _fmt_range(lo: float, hi: float) -> str:
    return f"{lo:.4g}" if np.isclose(lo, hi) else f"{lo:.4g}..{hi:.4g}"


def check_material(material: np.ndarray, scale: TrainingScale, limits: Limits, label: str) -> None:
    """Count and magnitude of the material constants (MPa) against the training range."""
    if scale.n_material is not None and material.size != scale.n_material:
        raise PredictionInputError(
            f"{label}material_params_mpa: the model was trained with {scale.n_material} material constants "
            f"(MPa), got {material.size}"
        )
    if scale.material_lo is None:
        return
    for j, (v, lo, hi) in enumerate(zip(material, scale.material_lo, scale.material_hi)):
        a, b = sorted((abs(lo), abs(hi)))
        if lo * hi <= 0:
            a = 0.0
        big = abs(v) > b * limits.scale_factor
        small = a > 0 and abs(v) < a / limits.scale_factor
        if big or small:
            ratio = abs(v) / (b if big else a)
            raise PredictionInputError(
                f"{label}material_params_mpa[{j}] = {v:.6g} MPa is {ratio:.3g}x the training range "
                f"({_fmt_range(lo, hi)} MPa): material constants must be in MPa (N/mm²), not Pa or kPa"
            )


def check_liver(centroid: np.ndarray, inertia: np.ndarray, point: np.ndarray, scale: TrainingScale, limits: Limits,
                label: str) -> None:
    """Liver size (from the inertia tensor) and exertion-point-to-centroid distance against training."""
    inertia = inertia.reshape(3, 3)
    trace = float(np.trace(inertia))
    if not trace > 0:
        raise PredictionInputError(
            f"{label}inertia_mm5: the trace of the inertia tensor is {trace:.4g}; it must be positive "
            "(volume inertia about the centroid, unit density, mm^5)"
        )
    length = (trace / 2.0) ** 0.2
    if scale.inertia_length_mm is not None and _outside(length, *scale.inertia_length_mm, limits.scale_factor):
        lo, hi = scale.inertia_length_mm
        raise PredictionInputError(
            f"{label}the liver's size (tr(I)/2)^(1/5) = {length:.4g} mm is {length / (hi if length > hi else lo):.3g}x "
            f"the training livers' ({_fmt_range(lo, hi)} mm): are the surface and inertia in mm (mm^5)?"
        )
    dist = float(np.linalg.norm(centroid - point))
    if scale.centroid_distance_mm is not None and _outside(dist, *scale.centroid_distance_mm, limits.scale_factor):
        lo, hi = scale.centroid_distance_mm
        raise PredictionInputError(
            f"{label}the exertion point is {dist:.4g} mm from the liver centroid; training cases were "
            f"{_fmt_range(lo, hi)} mm: wrong units, or a point and a liver from different frames?"
        )


def off_surface(d_mm: float, point_mm, nearest_mm, limit_mm: float, frame=None, surface=None,
                what: str = "the pre-operative surface") -> str:
    """The refusal of an exertion point ``d_mm`` from a surface (``point_mm`` and its ``nearest_mm`` point of it
    in the model's frame, RAS mm): the distance, the point as the user gave it and the nearest point in the same
    units and frame (``frame``: the inputs' :class:`~liverforce.serve.input_frame.InputFrame`; None: RAS mm, none
    declared), and, with the surface ``surface`` (a :class:`~liverforce.mesh.supports.TriangleSet` in mm, or its
    triangles (m, 3, 3)), the units or frame under which the value as given would lie on it."""
    from liverforce.serve.input_frame import as_entered, as_given, declared_as, frame_advice, reading_hint

    hint = None
    if surface is not None:
        from liverforce.mesh.supports import TriangleSet

        tris = surface if isinstance(surface, TriangleSet) else TriangleSet(surface)
        # every reading (units x frames) in one query, on the surface's one search tree (a context's, when given)
        hint = reading_hint(frame, as_entered(frame, point_mm),
                            lambda X: tris.closest(X.reshape(-1, 3))[1] <= limit_mm)
    return (f"the exertion point is {d_mm:.3g} mm off {what} (at most {limit_mm:g} mm): it was given as "
            f"{as_given(frame, point_mm)} ({declared_as(frame)}); the nearest point of the surface is "
            f"{as_given(frame, nearest_mm)}: " + (hint or "put the exertion point on the surface (where the tool "
                                                          "touches it), in the units and frame of the other inputs"
                                                          + frame_advice(frame)))


def check_on_surface(point_mm, nearest_mm, limits: Limits, label: str = "", frame=None, surface=None) -> None:
    """The exertion point against the pre-operative surface's triangles (``nearest_mm``: its closest point on
    them, :attr:`Preop.surface_point_mm`): refused (:func:`off_surface`) beyond ``limits.surface_tol_mm``.
    ``surface``: a function giving the surface (:func:`off_surface`'s), called for a refused point only."""
    d = float(np.linalg.norm(np.asarray(point_mm, dtype=np.float64) - np.asarray(nearest_mm, dtype=np.float64)))
    if not d <= limits.surface_tol_mm:
        raise OffSurfaceError(label + off_surface(d, point_mm, nearest_mm, limits.surface_tol_mm, frame,
                                                  None if surface is None else surface()), point_mm)


def check_roi(U_loc: np.ndarray, scale: TrainingScale, limits: Limits, label: str, fit_height: bool = True) -> None:
    """ROI extent (units) and exertion point on the undeformed surface, in the local frame. ``fit_height``:
    the point's height over the ROI's quadratic fit too (not when it was measured to the surface's triangles)."""
    h = scale.half_width_mm
    f = limits.scale_factor
    tang = U_loc[:, :2]
    centred = float(min(tang[:, 0].max(), -tang[:, 0].min(), tang[:, 1].max(), -tang[:, 1].min()))
    largest = float(np.abs(tang).max())
    if centred > f * h:
        raise PredictionInputError(
            f"{label}the ROI spans +-{centred:.4g} mm around the exertion point, {centred / h:.3g}x the model's grid "
            f"(+-{h:.4g} mm): are the points in mm (a unit 10x or 1000x too small)? "
            "Pass the ROI patch, not the whole liver"
        )
    if largest < h / f:
        raise PredictionInputError(
            f"{label}the ROI reaches only {largest:.3g} mm from the exertion point, {h / max(largest, 1e-300):.3g}x "
            f"smaller than the model's grid (+-{h:.4g} mm): are the points in mm (not cm or m)? Too few points?"
        )
    r = np.hypot(tang[:, 0], tang[:, 1])
    n_fit = min(len(r), 12)
    # the nodes nearest in 3-D, not in the tangent plane: near a thin edge the ROI also holds nodes of the
    # opposite face, which project next to the point but lie tens of mm below it
    d3 = np.linalg.norm(U_loc, axis=1)
    near = np.argpartition(d3, n_fit - 1)[:n_fit] if n_fit < len(r) else np.arange(len(r))
    if r[near].min() > h:
        raise PredictionInputError(
            f"{label}the exertion point lies {r[near].min():.3g} mm (in the tangent plane) from the nearest ROI node: "
            "it is not inside its ROI"
        )
    if not fit_height:
        return
    u, v, z = tang[near, 0], tang[near, 1], U_loc[near, 2]
    cols = [np.ones_like(u), u, v] + ([u * u, u * v, v * v] if n_fit >= 9 else [])
    A = np.column_stack(cols)
    coef, *_ = np.linalg.lstsq(A, z, rcond=None)
    z0 = float(coef[0])
    if not np.isfinite(z0) or abs(z0) > limits.surface_tol_mm:
        raise PredictionInputError(
            f"{label}the exertion point is {abs(z0):.3g} mm off the undeformed surface (along its normal; tolerance "
            f"{limits.surface_tol_mm} mm): put it on the pre-operative surface (same frame and units as the ROI)"
        )


def roi_patch(arrays: dict, i: int, n_points: int) -> np.ndarray | None:
    """Row ``i``'s ``roi_triangles`` as ``(m, 3)`` indices into its ``n_points`` ROI nodes, or None where the
    arrays give none (or none usable: a model that reads them refuses them by name, :func:`check_patch`)."""
    from liverforce.learn.grid import check_triangles

    tris = arrays.get("roi_triangles")
    if tris is None or len(tris) <= i or tris[i] is None:
        return None
    try:
        return check_triangles(tris[i], n_points, "roi_triangles")
    except (TypeError, ValueError):
        return None


def nearest_on_roi(point_mm: np.ndarray, tri: np.ndarray) -> tuple[np.ndarray, float]:
    """The point of the triangles ``tri (m, 3, 3)`` (mm) nearest ``point_mm`` and its distance, every triangle
    tested: a ROI has a few hundred (about 0.25 ms on the default run's, faster there than a search tree over
    their centroids, which would need this as its fallback anyway)."""
    from trimesh.triangles import closest_point

    p = np.asarray(point_mm, dtype=np.float64)
    near = closest_point(tri, np.broadcast_to(p, (len(tri), 3)))
    dist = np.linalg.norm(near - p, axis=1)
    j = int(np.argmin(dist))
    return near[j], float(dist[j])


def check_on_roi_triangles(point_mm: np.ndarray, U: np.ndarray, T: np.ndarray, limits: Limits, label: str,
                           frame=None) -> None:
    """The exertion point against the undeformed ROI's own triangles ``T`` (indices into its nodes ``U``, mm):
    refused (:class:`OffSurfaceError`, :func:`off_surface`) beyond ``limits.surface_tol_mm``. Exact on any mesh,
    where a quadratic fit of the nearest nodes (:func:`check_roi`) misreads a coarse one (nodes 20 mm and more
    from the point). ``frame``: the inputs' declared :class:`~liverforce.serve.input_frame.InputFrame` (None:
    RAS mm), in which the refusal gives the point and its nearest point of the ROI back."""
    p = np.asarray(point_mm, dtype=np.float64)
    tri = U[T]
    nearest, d = nearest_on_roi(p, tri)
    if not d <= limits.surface_tol_mm:
        raise OffSurfaceError(label + off_surface(d, p, nearest, limits.surface_tol_mm, frame, tri,
                                                  what="the undeformed surface (the ROI's triangles)"), p)


def check_displacement(disp_max_mm: float, scale: TrainingScale, limits: Limits, label: str) -> None:
    """The largest ROI displacement (mm) against the largest grid feature seen in training."""
    if scale.feature_abs_max is None:
        return
    ref = max(scale.feature_abs_max[:3] if len(scale.feature_abs_max) >= 3 else scale.feature_abs_max)
    if disp_max_mm > limits.scale_factor * max(ref, 1e-6):
        raise PredictionInputError(
            f"{label}the ROI moved by up to {disp_max_mm:.4g} mm, {disp_max_mm / ref:.3g}x the largest displacement "
            f"in training ({ref:.4g} mm): are the deformed and undeformed points in the same units (mm) and frame, "
            "and in the same node order?"
        )


def check_case(arrays: dict, i: int, model, scale: TrainingScale, limits: Limits, *, label: str | None = None,
               correspondence: bool = True, rotation: np.ndarray | None = None,
               on_surface: bool = False, input_frame=None) -> np.ndarray:
    """Check row ``i`` of input-contract ``arrays`` (module table); raise :class:`PredictionInputError`.

    ``rotation``: the row's local rotation (3 x 3) when the caller holds it already
    (``Preop.rotation``, which checked the frame); computed from the row's frame
    otherwise. Returns the rotation, for the prediction that follows the check.
    ``on_surface``: the exertion point was checked against the pre-operative surface's triangles
    (:func:`check_on_surface`): the ROI's quadratic fit is not read for it. Otherwise the point is measured to the
    row's ``roi_triangles`` where it has them (:func:`check_on_roi_triangles`), to the quadratic fit where not.
    ``input_frame``: the units and frame the user declared for the arrays (an
    :class:`~liverforce.serve.input_frame.InputFrame`, which they were converted from; None: RAS mm), in which an
    off-surface refusal gives the point back.
    """
    if label is None:
        ids = arrays.get("case_id")
        many = len(arrays["exertion_point_mm"]) > 1
        label = f"case {ids[i]}: " if ids is not None else (f"row {i}: " if many else "")
    try:
        camera = model.representation.is_camera  # a camera cloud, no deformed ROI nodes (serve.cloud checks it)
        correspondence = correspondence and not camera
        U = _points("roi_undeformed_mm", arrays["roi_undeformed_mm"][i], min_points=limits.min_roi_points)
        D = U if camera else _points("roi_deformed_mm", arrays["roi_deformed_mm"][i], min_points=limits.min_roi_points)
        p = _vector("exertion_point_mm", arrays["exertion_point_mm"][i], 3)
        frame = [_vector(k, arrays[k][i], 3) for k in ("frame_normal", "frame_t1", "frame_t2")]
    except PredictionInputError as exc:
        raise PredictionInputError(f"{label}{exc}") from None
    if correspondence and U.shape != D.shape:
        raise PredictionInputError(
            f"{label}roi_undeformed_mm has {len(U)} nodes but roi_deformed_mm has {len(D)}: in correspondence mode "
            "they list the same nodes in the same order (for an unordered camera cloud use Predictor.predict_cloud)"
        )
    if rotation is not None:
        R = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
    else:
        try:
            R = local_rotations(*(f[None] for f in frame))[0]
        except ValueError as exc:
            raise PredictionInputError(f"{label}{exc}") from None
    U_loc = (U - p) @ R.T
    patch = None if on_surface else roi_patch(arrays, i, len(U))
    check_roi(U_loc, scale, limits, label, fit_height=not on_surface and patch is None)
    if patch is not None:  # the point's height measured to the ROI's own triangles, not to a fit of its nodes
        check_on_roi_triangles(p, U, patch, limits, label, input_frame)
    check_occlusion(U_loc, model.representation, label)
    if model.representation.uses_triangles:
        check_patch(arrays, i, U_loc, model, limits, label)
    if correspondence:
        check_displacement(float(np.abs(D - U).max()), scale, limits, label)
    if model.uses_state:
        try:
            c = _vector("liver_centroid_mm", arrays["liver_centroid_mm"][i], 3)
            inertia = _vector("inertia_mm5", arrays["inertia_mm5"][i], 9)
            mat = _vector("material_params_mpa", arrays["material_params_mpa"][i])
            for k in ("roi_centroid_undeformed_mm",) + (() if camera else ("roi_centroid_deformed_mm",)):
                _vector(k, arrays[k][i], 3)
        except KeyError as exc:
            raise PredictionInputError(
                f"{label}the model uses the state vector and needs {exc.args[0]} (liver centroid and inertia from "
                "the closed pre-operative surface, material constants in MPa)"
            ) from None
        except PredictionInputError as exc:
            raise PredictionInputError(f"{label}{exc}") from None
        check_liver(c, inertia, p, scale, limits, label)
        check_material(mat, scale, limits, label)
        check_thickness(arrays, i, scale, limits, label)
        check_compliance(arrays, i, scale, limits, label)
    return R


#: the fewest ROI nodes left beyond the tool's occlusion radius that the model resamples (fewer:
#: ``Representation._observe`` raises ValueError)
MIN_VISIBLE_NODES = 3


def check_occlusion(U_loc: np.ndarray, rep, label: str) -> None:
    """The undeformed ROI nodes ``U_loc`` (local frame) against a model that drops those the tool hides
    (``occlusion: remove``, :class:`~liverforce.learn.representation.Representation`): at least
    :data:`MIN_VISIBLE_NODES` must lie at or beyond its occlusion radius (tangent distance), as the model's
    resampling needs."""
    r = float(rep.occlusion_radius_mm)
    if rep.is_camera or r <= 0 or rep.occlusion_mode != "remove":
        return
    visible = int((~(np.hypot(U_loc[:, 0], U_loc[:, 1]) < r)).sum())
    if visible < MIN_VISIBLE_NODES:
        raise PredictionInputError(
            f"{label}only {visible} of the {len(U_loc)} ROI nodes lie {r:g} mm or more from the exertion point (in "
            f"the tangent plane): the model leaves out the nodes the tool hides (its occlusion radius, {r:g} mm) and "
            f"needs {MIN_VISIBLE_NODES} or more to resample; give the ROI round the exertion point beyond the tool, "
            "not only the nodes under it")


def check_patch(arrays: dict, i: int, U_loc: np.ndarray, model, limits: Limits, label: str) -> None:
    """The ROI patch a model reads its grid from (a camera model's height reference, a node model's top
    sheet): ``roi_triangles`` present, an ``(m, 3)`` array of whole numbers indexing ``roi_undeformed_mm``
    (``U_loc``: in the local frame), covering some of the grid, with its top sheet through the exertion point
    (within ``surface_tol_mm``: triangles saved against another point order would not be). Cheap: the top
    sheet at the grid points only."""
    from liverforce.learn.grid import check_triangles, top_sheet_height

    tris = arrays.get("roi_triangles")
    if tris is None:
        raise PredictionInputError(
            f"{label}this model reads the ROI patch's top sheet from its triangles: give roi_triangles, (m, 3) "
            "indices into roi_undeformed_mm (Preop.from_surface and `liverforce predict --surface` or --mesh "
            "compute them from the liver's surface; shards of schema 1.4 hold them)")
    try:
        T = check_triangles(tris[i], len(U_loc), "roi_triangles")
    except ValueError as exc:
        raise PredictionInputError(f"{label}{exc}") from None
    grid = model.representation.grid()
    covered, z = top_sheet_height(U_loc, T, np.vstack([np.zeros((1, 2)), grid]))
    if not covered[1:].any():
        raise PredictionInputError(
            f"{label}roi_triangles: the patch covers no point of the model's +-{model.representation.half_width_mm:.3g}"
            " mm grid around the exertion point (is the patch the one round this exertion point?)")
    if covered[0] and abs(z[0]) > limits.surface_tol_mm:
        raise PredictionInputError(
            f"{label}roi_triangles: the patch's top sheet passes {z[0]:.3g} mm from the exertion point along the "
            f"normal (at most {limits.surface_tol_mm:g} mm): is the exertion point on the pre-operative surface, in "
            "its frame and units (--exertion-point: where the tool touches it)? With a context file's patch: do the "
            "triangles index roi_undeformed_mm in its own point order?")


def check_compliance(arrays: dict, i: int, scale: TrainingScale, limits: Limits, label: str) -> None:
    """The probe compliance (3 x 3, mm/N): present, positive definite, trace within ``scale_factor`` of training."""
    if "probe_compliance_mm_per_n" not in arrays:
        raise PredictionInputError(
            f"{label}the model uses the state vector and needs probe_compliance_mm_per_n (the liver's pre-operative "
            "stiffness at the exertion point): give the liver's tet mesh (`liverforce predict --mesh liver.vtu`, "
            "liverforce.serve.probe.with_probe) or the 3x3 compliance in the context")
    C = _vector("probe_compliance_mm_per_n", np.asarray(arrays["probe_compliance_mm_per_n"][i]).ravel(), 9)
    C = C.reshape(3, 3)
    ev = np.linalg.eigvalsh(0.5 * (C + C.T))
    if not ev[0] > 0:
        raise PredictionInputError(f"{label}probe_compliance_mm_per_n: not positive definite (eigenvalues "
                                   f"{np.round(ev, 6).tolist()} mm/N)")
    tr = float(np.trace(C))
    if scale.compliance_trace is not None and _outside(tr, *scale.compliance_trace, limits.scale_factor):
        raise PredictionInputError(
            f"{label}probe_compliance_mm_per_n: trace {tr:.4g} mm/N is far outside the training range "
            f"({_fmt_range(*scale.compliance_trace)} mm/N): is it in mm/N, for the model's reference material "
            "and supports (liverforce.serve.probe computes it with the model's settings)?")


def outside_training(arrays: dict, scale: TrainingScale) -> tuple[dict[str, np.ndarray], list[list[str]]]:
    """Rows whose geometric state lies outside the training range: ``(masks by input, warnings per row)``.

    Inside ``scale_factor`` x the range (else :func:`check_case` refuses) but
    outside the range itself, the model extrapolates
    (:func:`liverforce.learn.state.outside_ranges`: the tissue thickness
    under the tool, the probe compliance's trace, the liver's size and the
    exertion point's distance from the liver centroid). Only ranges recorded
    in the bundle count: a bundle without ``training_scale`` has only the
    scalers' rough ranges, and nothing is flagged.
    """
    if not scale.recorded:
        return {}, [[] for _ in range(len(arrays["exertion_point_mm"]))]
    return outside_ranges(arrays, {"tool_thickness_mm": scale.thickness_mm,
                                   "probe_compliance_mm_per_n": scale.compliance_trace,
                                   "liver_size_mm": scale.inertia_length_mm,
                                   "centroid_distance_mm": scale.centroid_distance_mm})


def force_warnings(force: np.ndarray, scale: TrainingScale, camera: bool = True) -> list[list[str]]:
    """Per row of predicted forces ``(n, 3)`` N: a warning where ``|F|`` exceeds every training case's (module
    docstring). A row that is not finite (a refused cloud's NaN) gets none; nor does any row of a model whose
    bundle did not record its training forces. ``camera``: the advice names the tool tip and the registration
    (a camera-cloud model's inputs), else the ROI nodes."""
    F = np.asarray(force, dtype=np.float64).reshape(-1, 3)
    out: list[list[str]] = [[] for _ in range(len(F))]
    top = scale.force_max_n
    if top is None or not scale.recorded:
        return out
    mag = np.sqrt(np.einsum("ij,ij->i", F, F))
    check = "the tool tip and the registration" if camera else "the ROI nodes and their order"
    for i in np.flatnonzero(mag > top):  # NaN compares False
        out[i] = [f"the predicted force ({mag[i]:.4g} N) exceeds every training case's (at most {top:.4g} N): the "
                  f"model extrapolates there and its interval was calibrated on smaller forces; check the exertion "
                  f"point, {check}"]
    return out


def distance_warnings(distance, record: dict | None, camera: bool = True) -> list[list[str]]:
    """Per row of input distances ``(n,)`` (``Forward.input_distance``; None: none known): a warning where the
    case's GP inputs lie farther from every training row than the model's training-side quantile
    (``record``: ``ForceModel.distance_flag``, :func:`liverforce.learn.interval.fit_input_distance`). No record,
    or no distances: no warning. ``camera`` words the advice as :func:`force_warnings` does."""
    from liverforce.learn.interval import distance_flags

    if distance is None:
        return []
    d = np.asarray(distance, dtype=np.float64).reshape(-1)
    out: list[list[str]] = [[] for _ in range(len(d))]
    if not record:
        return out
    thr, q = float(record["threshold"]), 100.0 * float(record["quantile"])
    other = "the other livers'" if record.get("left_out", "liver") == "liver" else "the other cases'"
    check = "the tool tip and the registration" if camera else "the ROI nodes and their order"
    for i in np.flatnonzero(distance_flags(d, record)):
        out[i] = [f"the case lies far from every training case: its inputs are {d[i]:.3g} from the nearest (in the "
                  f"model's GP length scales, no unit), farther than {q:.0f} % of the training cases lie from "
                  f"{other} ({thr:.3g}); the force and its interval are less reliable there. Check the exertion "
                  f"point, {check}; if they are right, read the force as an extrapolation"]
    return out


def check_thickness(arrays: dict, i: int, scale: TrainingScale, limits: Limits, label: str) -> None:
    """Tissue thickness under the tool (mm): present, positive, and within ``scale_factor`` of training."""
    if "tool_thickness_mm" not in arrays:
        raise PredictionInputError(f"{label}the model uses the state vector and needs tool_thickness_mm (the tissue "
                                   "thickness under the tool, from the closed pre-operative surface)")
    t = float(_vector("tool_thickness_mm", np.atleast_1d(arrays["tool_thickness_mm"][i]), 1)[0])
    if not t > 0:
        raise PredictionInputError(f"{label}tool_thickness_mm = {t:.4g} mm: it must be positive")
    if scale.thickness_mm is not None and _outside(t, scale.thickness_mm[0], scale.thickness_mm[1],
                                                   limits.scale_factor):
        raise PredictionInputError(
            f"{label}tool_thickness_mm = {t:.4g} mm is far outside the training range "
            f"({_fmt_range(*scale.thickness_mm)} mm): is it in mm?")
