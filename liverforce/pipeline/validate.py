"""Validate stage adapter: the chosen scenario-IV model on the unseen liver."""

from __future__ import annotations

import json
import math
import logging
from pathlib import Path

import numpy as np

from liverforce.atomic import write_json_atomic
from liverforce.dataset import io as dio
from liverforce.layout import model_of_metrics

log = logging.getLogger("liverforce")


def is_camera_variant(metrics_doc: dict) -> bool:
    """True for a camera-cloud model (``roi_features: cloud``: no node correspondence)."""
    return (metrics_doc.get("model_cfg") or {}).get("roi_features") == "cloud"


def choose_variant(metrics_paths: list, how: str = "auto", input: str = "any") -> tuple[int, str]:
    """Index of the scenario-IV model to validate, and why.

    ``main``: the first listed (the main variant). ``auto``: the lowest
    cross-validation error of the force in N (``cv_mae_n``: the best Ax
    configuration's folds, by liver, training split only: neither the IV test
    livers nor the unseen livers inform the choice; the Ax MSE of older
    metrics files, of scaled targets, when not every variant has it); the
    first listed when no variant was tuned. Else the variant of that name.
    ``input="camera"`` restricts ``auto`` (and ``main``: the first camera
    variant) to the camera-cloud variants when there is one.
    """
    docs = [json.loads(Path(p).read_text()) for p in metrics_paths]
    names = [d.get("variant") or model_of_metrics(p)[1] for d, p in zip(docs, metrics_paths)]
    if input == "camera" and how in ("auto", "main"):
        cams = [i for i, d in enumerate(docs) if is_camera_variant(d)]
        if cams:
            k, why = choose_variant([metrics_paths[i] for i in cams], how, "any")
            return cams[k], f"validate.input=camera (the camera-cloud variants {[names[i] for i in cams]}); {why}"
    if how == "main":
        return 0, "validate.variant=main (the first of train.variants)"
    if how != "auto":
        if how not in names:
            raise ValueError(f"validate.variant '{how}' is not among the trained scenario-IV variants {names}")
        return names.index(how), f"validate.variant={how}"
    for key, what in (("cv_mae_n", "lowest cross-validation MAE (N) on the training livers"),
                      ("cv_mse", "lowest cross-validation MSE (scaled targets) on the training livers")):
        cv = [d.get(key) for d in docs]
        if all(c is not None for c in cv):
            best = int(np.argmin(cv))
            return best, f"{what}: " + ", ".join(f"{n} {c:.4f}" for n, c in zip(names, cv))
    return 0, "first listed variant (not every variant was tuned, no CV score to compare)"


def interval_on_unseen(model_dir, arrays: dict) -> dict | None:
    """Coverage of the model's calibrated interval per local component on the unseen livers (None without one)."""
    from liverforce.learn.model import ForceModel

    return interval_coverage(ForceModel.load(Path(model_dir)), arrays)


def interval_coverage(m, arrays: dict) -> dict | None:
    """:func:`interval_on_unseen` for a loaded :class:`~liverforce.learn.model.ForceModel` ``m``."""
    from liverforce.learn.frames import force_to_local
    from liverforce.learn.interval import coverage_per_component
    from liverforce.learn.metrics import force_bins

    ci = m.interval
    if ci is None:
        return None
    got = m.predict_interval(arrays, observation_seed=int(m.meta.get("eval_observation_seed", 0)))
    true_local = force_to_local(np.asarray(arrays["force_n"], float), got["frame"])
    half = got["half_width_local_n"]
    geo = np.asarray(arrays["geometry_id"]).astype(str)
    per = {g: coverage_per_component(true_local[geo == g], got["force_local_n"][geo == g], half[geo == g])
           for g in sorted(set(geo))}
    mag = np.linalg.norm(true_local, axis=1)  # quintiles of the true |F|: does it hold for the large forces too?
    bins = [{"lo_n": float(lo), "hi_n": float(hi), "n": int(sel.sum()),
             "coverage": coverage_per_component(true_local[sel], got["force_local_n"][sel], half[sel]),
             "half_width_mean_n": [float(v) if np.isfinite(v) else None for v in half[sel].mean(axis=0)]}
            for lo, hi, sel in force_bins(mag, np.quantile(mag, np.linspace(0.0, 1.0, 6)))]
    far = distance_flag_on_unseen(m, got, true_local, np.asarray(arrays["force_n"], float), half, geo)
    return {"nominal": ci.coverage, "bounded": ci.bounded, "n_calibration": ci.n_calibration, "scale": ci.scale,
            "far_factor": None if ci.far_factor is None else list(ci.far_factor),
            "near_factor": None if ci.near_factor is None else list(ci.near_factor),
            "widen": ci.widen, "stiffness_exponent": None if ci.stiffness_exponent is None else
            [float(v) for v in ci.stiffness_exponent], "spread_beta": ci.spread_beta,
            "coverage": coverage_per_component(true_local, got["force_local_n"], half),
            "coverage_by_force": bins,
            "coverage_per_liver": per,
            "coverage_band_by_liver": coverage_band_by_liver(per),
            "half_width_mean_n": [float(v) if np.isfinite(v) else None for v in half.mean(axis=0)],
            "test_coverage": m.meta.get("interval_test_coverage"),
            "input_distance": far}


#: an unseen case's error (N) above this is one the input-distance flag should catch (the report's "large errors")
LARGE_ERROR_N = 0.4


def distance_flag_on_unseen(m, got: dict, true_local: np.ndarray, true_force: np.ndarray, half: np.ndarray,
                            geo: np.ndarray) -> dict | None:
    """What the model's input-distance flag (``m.distance_flag``, :mod:`liverforce.learn.interval`) does on the
    unseen livers, from their :meth:`~liverforce.learn.model.ForceModel.predict_interval` ``got``: the threshold
    and quantile, how many cases it flags (per liver too), the mean error (N) of the flagged cases and of the
    others (:func:`~liverforce.learn.train.flagged_errors`), how many errors above :data:`LARGE_ERROR_N` it
    catches, the interval's coverage per component of each group, and how many cases lie above each recorded
    quantile of the training side (``flagged_at``; a liver like the training livers puts 1 - q of its cases
    there) and above the calibration folds' 90 % (``flagged_at_fold_0.9``, the threshold fitted before session
    62, for comparison). None for a model without the flag."""
    from liverforce.learn.interval import coverage_per_component, distance_flags
    from liverforce.learn.train import flagged_errors

    rec = m.distance_flag
    d = got.get("input_distance")
    if rec is None or d is None:
        return None
    f = distance_flags(d, rec)
    counts = flagged_errors(d, rec, true_force, got["force_n"])
    err = np.linalg.norm(np.asarray(got["force_n"], float) - true_force, axis=1)
    big = err > LARGE_ERROR_N

    def cov(sel):
        return coverage_per_component(true_local[sel], got["force_local_n"][sel], half[sel]) if sel.any() else None

    fold = (rec.get("fold_quantiles") or {}).get("0.9")
    return {"quantile": rec["quantile"], "threshold": rec["threshold"], "n_calibration": rec["n_calibration"],
            "left_out": rec.get("left_out"), "n_cases": counts["n"], "n_flagged": counts["n_flagged"],
            "mae_flagged_n": counts["mae_flagged_n"], "mae_others_n": counts["mae_others_n"],
            "large_error_n": LARGE_ERROR_N, "n_large": int(big.sum()), "n_large_flagged": int((big & f).sum()),
            "coverage_flagged": cov(f), "coverage_others": cov(~f),
            "median_distance": float(np.median(d)),
            "flagged_at": {q: int((d > v).sum()) for q, v in rec["calibration_quantiles"].items()},
            "flagged_at_fold_0.9": None if fold is None else int((d > fold).sum()),
            "per_liver": {g: int(f[geo == g].sum()) for g in sorted(set(geo.tolist()))}}


def coverage_band_by_liver(per_liver: dict, level: float = 0.95) -> list | None:
    """How far a coverage measured on a few livers may be from the coverage on the livers' population, per component.

    A liver's cases share its shape and material, so their misses are not independent: the unit is the liver. The
    band is the mean of the per-liver coverages ``+- t_(level, L - 1) sd / sqrt(L)`` (``L`` livers; Student's t on
    the livers' means), clipped to [0, 1]: a list of ``[lo, hi]``, one per component. None with fewer than two livers.
    On 8 livers of 30 cases each a 90 % interval's coverage is known to about +-4 points this way, so a
    measured 94 % does not by itself show that the population's is above 92 %.
    """
    from scipy.stats import t

    cov = np.array(list(per_liver.values()), float)  # (livers, components)
    if len(cov) < 2:
        return None
    mean = cov.mean(axis=0)
    half = t.ppf(0.5 + level / 2.0, len(cov) - 1) * cov.std(axis=0, ddof=1) / np.sqrt(len(cov))
    return [[float(max(m - h, 0.0)), float(min(m + h, 1.0))] for m, h in zip(mean, half)]


def extrapolation_on_unseen(model_dir, arrays: dict, err: np.ndarray) -> dict | None:
    """Unseen cases whose geometric state lies outside the model's training range, and their error.

    What serving warns about (:func:`liverforce.learn.model.outside_training_range`),
    measured: how many unseen cases it flags, per input, and the mean vector
    error (N) of the flagged cases against the others. None for a model
    without the state vector.
    """
    from liverforce.learn.model import ForceModel, outside_training_range

    got = outside_training_range(ForceModel.load(Path(model_dir)), arrays)
    if got is None:
        return None
    out, masks = got
    geo = np.asarray(arrays["geometry_id"]).astype(str)
    return {"n_cases": int(len(err)), "n_outside": int(out.sum()),
            "by_input": {k: int(v.sum()) for k, v in masks.items()},
            "mae_outside_n": float(err[out].mean()) if out.any() else None,
            "mae_inside_n": float(err[~out].mean()) if (~out).any() else None,
            "per_liver": {g: int(out[geo == g].sum()) for g in sorted(set(geo.tolist()))}}


def camera_sensitivity(model_dir, arrays: dict, grid: dict) -> dict | None:
    """A camera-cloud model's error on the unseen livers as one camera setting at a time changes.

    ``grid``: setting -> values, among ``n_points`` (a fixed number of cloud
    points), ``noise_sd_mm``, ``cone_half_angle_deg`` (the view-angle cone
    around the normal), ``tip_noise_mm`` (robot kinematics, the same sd in
    every direction whatever the model's ``tip_noise_normal_mm``),
    ``instrument_in_cloud`` (the tool's own points in the cloud or masked out), ``tool_tilt_deg`` (the tool's
    axis that far from the normal, as an instrument through its trocar comes in) and ``outlier_fraction`` (that
    share of the points at a gross depth error along their line of sight, the model's ``outlier_range_mm``). The other
    settings stay the model's own; the evaluation observation seed as in
    validation. Returns ``{setting: [{value, mae_vec (mean over livers),
    mae_sd, accuracy_pct, accuracy_sd}]}``, None for a model that is not a
    camera-cloud model.
    """
    import copy

    from liverforce.learn.camera import isotropic_tip
    from liverforce.learn.metrics import metrics_by_group
    from liverforce.learn.model import ForceModel

    m = ForceModel.load(Path(model_dir))
    rep = m.representation
    if not rep.is_camera or not grid:
        return None
    seed = int(m.meta.get("eval_observation_seed", 0))
    out: dict = {"model_settings": rep.camera}
    for key, values in grid.items():
        rows = []
        for val in values:
            cam = copy.deepcopy(rep.camera)
            obs = cam.setdefault("observation", {})
            if key == "tip_noise_mm":  # the same noise in every direction, whatever the model was trained with
                cam = isotropic_tip(cam, val)
            elif key == "n_points":
                obs["n_points"] = [int(val), int(val)]
            elif key in ("noise_sd_mm", "cone_half_angle_deg", "tool_tilt_deg", "outlier_fraction"):
                if isinstance(val, bool) or not isinstance(val, (int, float)):
                    raise ValueError(f"validate.camera_sensitivity.{key}: each value is one number, the setting "
                                     f"itself (got {val!r})")
                obs[key] = float(val)
            elif key == "instrument_in_cloud":
                if not isinstance(val, bool):
                    raise ValueError(f"validate.camera_sensitivity.instrument_in_cloud: values are true / false "
                                     f"(got {val!r})")
                obs[key] = val
            else:
                raise ValueError(f"validate.camera_sensitivity: unknown setting '{key}' (n_points, noise_sd_mm, "
                                 "cone_half_angle_deg, tip_noise_mm, instrument_in_cloud, tool_tilt_deg, "
                                 "outlier_fraction)")
            pred = m.observed_with(cam).predict(arrays, observation_seed=seed)
            g = metrics_by_group(arrays["force_n"], pred, arrays["geometry_id"])
            rows.append({"value": val, "mae_vec": g["mean"]["mae_vec"], "mae_sd": g["sd"]["mae_vec"],
                         "accuracy_pct": g["mean"]["accuracy_pct"], "accuracy_sd": g["sd"]["accuracy_pct"]})
            log.info("camera sensitivity %s=%s: unseen MAE %.3f N", key, val, g["mean"]["mae_vec"])
        out[key] = rows
    return out


class _CameraCases:
    """What the registration and shape rows share: the validated camera model, the unseen cases' observation
    (:meth:`observe`: the evaluation's seed; their unloaded views with their own), the pre-operative references
    and the scores per liver."""

    def __init__(self, m, arrays: dict):
        from liverforce.learn.camera import grid_spec
        from liverforce.learn.cloud_features import ReferenceSurface
        from liverforce.learn.frames import case_rotations
        from liverforce.seeds import derive

        rep = m.representation
        self.m, self.arrays, self.rep = m, arrays, rep
        self.seed = int(m.meta.get("eval_observation_seed", 0))
        self.unloaded_seed = derive(self.seed, "validate.registration.unloaded")
        self.spec = grid_spec(rep.grid_size, rep.half_width_mm, rep.camera)
        self.P = np.asarray(arrays["exertion_point_mm"], dtype=np.float64)
        self.centre = np.asarray(arrays["liver_centroid_mm"], dtype=np.float64)
        self.ids = np.asarray(arrays["case_id"]).astype(str)
        R = case_rotations(arrays)
        tris = arrays.get("roi_triangles")
        self.refs = [ReferenceSurface.for_case(arrays["roi_undeformed_mm"][i], None if tris is None else tris[i],
                                               self.P[i], R[i], self.spec, label=f"case {self.ids[i]}")
                     for i in range(len(self.ids))]

    def observe(self, arrays: dict, seed: int | None = None):
        from liverforce.learn.camera import observe_cases

        rep = self.rep
        return observe_cases(arrays, rep.camera, rep.half_width_mm, rep.grid_size, self.seed if seed is None else seed)

    def scores(self, moved: list, rows) -> dict:
        """The metrics over the livers of the clouds and tips ``moved`` of cases ``rows``."""
        from liverforce.learn.camera import CLOUD_KEY, TIP_KEY
        from liverforce.learn.metrics import metrics_by_group
        from liverforce.learn.model import subset

        rows = np.asarray(rows)
        sub = subset(self.arrays, rows) if len(rows) < len(self.ids) else self.arrays
        pred = self.m.predict({**sub, CLOUD_KEY: [c for c, _ in moved], TIP_KEY: np.array([t for _, t in moved])})
        g = metrics_by_group(np.asarray(self.arrays["force_n"])[rows], pred,
                             np.asarray(self.arrays["geometry_id"])[rows])
        return {"mae_vec": g["mean"]["mae_vec"], "mae_sd": g["sd"]["mae_vec"],
                "accuracy_pct": g["mean"]["accuracy_pct"], "accuracy_sd": g["sd"]["accuracy_pct"]}

    def refined(self, clouds, tips, clouds0, tips0, what: str, **kwargs) -> dict:
        """Each case's registration refined from its unloaded view (``refine_registration(**kwargs)``) and applied
        to its cloud and tip: the scores over the cases not refused, ``n_refused`` and ``anchors``."""
        from liverforce.learn.registration import RegistrationError, refine_registration

        out, kept, anchors = [], [], {}
        for i in range(len(self.ids)):
            try:
                fix = refine_registration(self.refs[i], self.spec, clouds0[i], tips0[i], **kwargs)
            except RegistrationError as exc:
                log.info("%s, case %s: refused (%s)", what, self.ids[i], exc)
                continue
            kept.append(i)
            anchors[fix.anchor] = anchors.get(fix.anchor, 0) + 1
            out.append((fix.points(clouds[i]), fix.points(tips[i])))
        scored = self.scores(out, kept) if kept else {}
        return {**scored, "n_refused": len(self.ids) - len(kept), "anchors": anchors}


def unloaded(arrays: dict) -> dict:
    """The cases with the tool not pushing: every surface displacement zero (the camera's unloaded view)."""
    still = dict(arrays)
    still["surface_displacement_mm"] = [np.zeros_like(np.asarray(d)) for d in arrays["surface_displacement_mm"]]
    return still


def registration_sensitivity(model_dir, arrays: dict, errors) -> dict | None:
    """A camera-cloud model's error on the unseen livers when the camera's registration to the pre-operative
    surface is off, as registered and refined from the unloaded view (:mod:`liverforce.learn.registration`).

    ``errors``: ``[shift_mm, turn_deg]`` pairs. Each case's camera side (the cloud and the tool tip) is moved
    by a rigid motion: a shift of ``shift_mm`` in a random direction and a turn of ``turn_deg`` about a random
    axis through the liver's centroid (the directions seeded per case, the same for every pair). The unloaded
    view is the undeformed surface observed with the model's camera settings, its tool tip at contact with the
    kinematics' noise (its own observation seed), moved by the same motion. Returns ``{"rows": [{shift_mm,
    turn_deg, as_registered: {mae_vec, mae_sd, accuracy_pct, accuracy_sd}, refined: {... , n_refused, anchors}}]}``
    (the refined metrics over the cases not refused), None for a model that is not a camera-cloud model.
    """
    from scipy.spatial.transform import Rotation

    from liverforce.learn.model import ForceModel
    from liverforce.seeds import derive

    m = ForceModel.load(Path(model_dir))
    if not m.representation.is_camera or not errors:
        return None
    cases = _CameraCases(m, arrays)
    loaded, still = cases.observe(arrays), cases.observe(unloaded(arrays), cases.unloaded_seed)
    draws = []
    for cid in cases.ids:
        rng = np.random.default_rng(derive(cases.seed, "validate.registration", cid))
        d, a = rng.normal(size=3), rng.normal(size=3)
        draws.append((d / np.linalg.norm(d), a / np.linalg.norm(a)))
    out = []
    for shift, turn in errors:
        moves = []
        for i, (d, a) in enumerate(draws):
            Q = Rotation.from_rotvec(math.radians(float(turn)) * a).as_matrix()
            moves.append((Q, cases.centre[i] - Q @ cases.centre[i] + float(shift) * d))

        def move(items):
            return [np.asarray(x, dtype=np.float64) @ Q.T + b for x, (Q, b) in zip(items, moves)]

        clouds, tips = move(loaded[0]), move(loaded[1])
        row = {"shift_mm": float(shift), "turn_deg": float(turn),
               "as_registered": cases.scores(list(zip(clouds, tips)), np.arange(len(cases.ids))),
               "refined": cases.refined(clouds, tips, move(still[0]), move(still[1]),
                                        f"registration {shift} mm / {turn} deg")}
        log.info("registration off by %s mm and %s deg: unseen MAE %.3f N as registered, %s refined", shift, turn,
                 row["as_registered"]["mae_vec"],
                 f"{row['refined']['mae_vec']:.3f} N" if "mae_vec" in row["refined"] else "every case refused")
        out.append(row)
    return {"rows": out}


def shape_field(seed: int, geometry_id: str, amplitude_mm: float, wavelength_mm: float, centre):
    """A smooth change of a liver's shape since its scan: ``x -> x + d(x)``, ``d(x) = (a / sqrt 3) sum_j e_j
    sin(2 pi k_j . (x - centre) / wavelength + phi_j)`` over three modes, ``k_j`` and ``e_j`` unit vectors and
    ``phi_j`` phases drawn per liver (``validate.shape [liver]``): over space its rms is ``a / sqrt 2``, a single
    sinusoid's of amplitude ``a``, and ``|d| <= sqrt(3) a``. Returns the map (points ``(n, 3)`` or one ``(3,)``)."""
    from liverforce.seeds import derive

    rng = np.random.default_rng(derive(seed, "validate.shape", str(geometry_id)))
    k = rng.normal(size=(3, 3))
    k /= np.linalg.norm(k, axis=1, keepdims=True)
    e = rng.normal(size=(3, 3))
    e /= np.linalg.norm(e, axis=1, keepdims=True)
    phase = rng.uniform(0.0, 2.0 * math.pi, 3)
    c = np.asarray(centre, dtype=np.float64)
    scale = float(amplitude_mm) / math.sqrt(3.0)

    def f(x):
        x = np.asarray(x, dtype=np.float64)
        return x + scale * (np.sin((x - c) @ k.T * (2.0 * math.pi / float(wavelength_mm)) + phase) @ e)

    return f


def local_turn(f, x: np.ndarray, normal, t1, h: float = 1e-3) -> np.ndarray:
    """The rotation ``(3, 3)`` that carries the local frame at point ``x`` (``normal``, ``t1``) with a map ``f``:
    the normal to the mapped surface's (``J^-T n``), ``t1`` to its mapped direction in that tangent plane
    (central differences for the Jacobian ``J``)."""
    J = np.column_stack([(f(x + h * u) - f(x - h * u)) / (2.0 * h) for u in np.eye(3)])
    n = np.asarray(normal, dtype=np.float64) / np.linalg.norm(normal)
    a = np.asarray(t1, dtype=np.float64) / np.linalg.norm(t1)
    n2 = np.linalg.solve(J.T, n)
    n2 /= np.linalg.norm(n2)
    a2 = J @ a - (J @ a @ n2) * n2
    a2 /= np.linalg.norm(a2)
    return np.column_stack([a2, np.cross(n2, a2), n2]) @ np.stack([a, np.cross(n, a), n])


def changed_shape(arrays: dict, seed: int, amplitude_mm: float, wavelength_mm: float) -> dict:
    """The cases on livers whose shape changed since the scan (:func:`shape_field`): each liver's surface moved by
    its field; each case's exertion point and normal carried by it, and the tool's dent (the surface
    displacements) turned with the local frame the field carries there (:func:`local_turn`), so the tool pushes
    the changed surface as it pushed the scanned one in its local frame (the force label unchanged)."""
    from liverforce.learn.camera import SURFACES_KEY

    if float(amplitude_mm) == 0.0:  # no change: the cases exactly as they are (no rounding of a unit turn)
        return dict(arrays)
    geo = np.asarray(arrays["geometry_id"]).astype(str)
    centre = np.asarray(arrays["liver_centroid_mm"], dtype=np.float64)
    P = np.asarray(arrays["exertion_point_mm"], dtype=np.float64)
    N = np.asarray(arrays["frame_normal"], dtype=np.float64)
    T1 = np.asarray(arrays["frame_t1"], dtype=np.float64)
    T2 = np.asarray(arrays["frame_t2"], dtype=np.float64)
    fields = {g: shape_field(seed, g, amplitude_mm, wavelength_mm, centre[np.flatnonzero(geo == g)[0]])
              for g in sorted(set(geo))}
    out = dict(arrays)
    out[SURFACES_KEY] = {g: (fields[g](V), T) if g in fields else (V, T) for g, (V, T) in arrays[SURFACES_KEY].items()}
    P2, N2, A2, B2, disp = P.copy(), N.copy(), T1.copy(), T2.copy(), []
    for i, g in enumerate(geo):
        Rw = local_turn(fields[g], P[i], N[i], T1[i])
        P2[i], N2[i], A2[i], B2[i] = fields[g](P[i]), Rw @ N[i], Rw @ T1[i], Rw @ T2[i]
        disp.append(np.asarray(arrays["surface_displacement_mm"][i], dtype=np.float64) @ Rw.T)
    out.update({"exertion_point_mm": P2, "frame_normal": N2, "frame_t1": A2, "frame_t2": B2,
                "surface_displacement_mm": disp})
    return out


def shape_sensitivity(model_dir, arrays: dict, changes) -> dict | None:
    """A camera-cloud model's error on the unseen livers when each liver has changed shape since its scan
    (:func:`changed_shape`; the pre-operative surface the model reads stays the scanned one): predicted as the
    camera sees it, with the registration refined rigidly from the unloaded view, and refined with the change of
    shape as well (:mod:`liverforce.learn.registration`, step 4).

    ``changes``: ``[amplitude_mm, wavelength_mm]`` pairs. Returns ``{"rows": [{amplitude_mm, wavelength_mm,
    as_registered: {...}, rigid: {..., n_refused, anchors}, refined: {...}}]}``, None for a model that is not a
    camera-cloud model.
    """
    from liverforce.learn.model import ForceModel

    m = ForceModel.load(Path(model_dir))
    if not m.representation.is_camera or not changes:
        return None
    cases = _CameraCases(m, arrays)
    out = []
    for amp, wave in changes:
        changed = changed_shape(arrays, cases.seed, float(amp), float(wave))
        clouds, tips = cases.observe(changed)
        clouds0, tips0 = cases.observe(unloaded(changed), cases.unloaded_seed)
        what = f"shape changed {amp} mm / {wave} mm"
        row = {"amplitude_mm": float(amp), "wavelength_mm": float(wave),
               "as_registered": cases.scores(list(zip(clouds, tips)), np.arange(len(cases.ids))),
               "rigid": cases.refined(clouds, tips, clouds0, tips0, what + " (rigid)", shape_degree=0),
               "refined": cases.refined(clouds, tips, clouds0, tips0, what)}
        log.info("%s: unseen MAE %.3f N as registered, rigid %s, refined %s", what, row["as_registered"]["mae_vec"],
                 *(f"{row[k]['mae_vec']:.3f} N" if "mae_vec" in row[k] else "every case refused"
                   for k in ("rigid", "refined")))
        out.append(row)
    return {"rows": out}


def validate_model(model_dir, model_metrics_path, manifest_path, train_manifest_path, tracking_uri, out_path, *,
                   experiment_name: str, variant: str, input: str = "any", mesh_paths=None,
                   sensitivity: dict | None = None, registration_errors=None, shape_changes=None) -> dict:
    """Predict the unseen livers' cases with the chosen scenario-IV model.

    ``model_dir`` / ``model_metrics_path`` may be lists (every scenario-IV
    variant): :func:`choose_variant` picks one by ``variant``
    (``validate.variant``). ``experiment_name``: the MLflow experiment
    (``Plan.experiment_name("validation")``).

    Reports MAE / RMSE (N) and accuracy % over all cases, per unseen liver
    with their mean ± sd over the livers and the worst liver named, the error
    in bins of force magnitude (absolute and relative to the bin's mean
    force), and the error against the distance of the exertion point from the
    nearest training exertion point (both livers centred on their centroids,
    since they are different shapes). Refuses to run when an unseen liver is
    also a training liver of the model. ``input="camera"`` makes the choice
    among the camera-cloud variants; ``sensitivity`` (``validate.camera_sensitivity``)
    re-observes the unseen livers with other camera settings for the chosen
    model if it is a camera-cloud model (:func:`camera_sensitivity`); ``registration_errors``
    (``validate.registration_errors``) measures it with the camera's registration off, as registered and refined
    from the unloaded view (:func:`registration_sensitivity`); ``shape_changes`` (``validate.shape_changes``) with
    each unseen liver's shape changed since its scan, as registered, refined rigidly and refined with the change of
    shape (:func:`shape_sensitivity`).
    """
    from liverforce.learn.metrics import error_by_force_bin, force_metrics, metrics_by_group
    from liverforce.learn.model import ForceModel
    from liverforce.tracking import Tracker

    def predict(d):
        m = ForceModel.load(Path(d))
        return m.predict(arrays, observation_seed=int(m.meta.get("eval_observation_seed", 0)))

    choice = "the only model given"
    others = {}
    docs = [json.loads(Path(p).read_text()) for p in
            (model_metrics_path if isinstance(model_metrics_path, (list, tuple)) else [model_metrics_path])]
    if any(is_camera_variant(d) for d in docs):  # camera models observe the unseen livers' full surfaces
        from liverforce.pipeline.shared import camera_arrays

        arrays = camera_arrays(manifest_path, mesh_paths, "validation")
    else:
        arrays = dio.load_training_arrays(dio.verify_manifest(manifest_path))
    n = len(arrays["case_id"])
    if n == 0:
        raise RuntimeError(f"{manifest_path}: no converged validation case to evaluate")
    if isinstance(model_metrics_path, (list, tuple)):
        k, choice = choose_variant(list(model_metrics_path), variant, input)
        preds = [predict(d) for d in model_dir]  # every candidate on the unseen liver, for the report
        for p, mp in zip(preds, model_metrics_path):
            grouped = metrics_by_group(arrays["force_n"], p, arrays["geometry_id"])
            others[model_of_metrics(mp)[1]] = {"metrics": force_metrics(arrays["force_n"], p),
                                            "livers": {"mean": grouped["mean"], "sd": grouped["sd"],
                                                       "worst": grouped["worst"]},
                                            "error_by_force_magnitude": error_by_force_bin(arrays["force_n"], p),
                                            "model_run_id": json.loads(Path(mp).read_text()).get("run_id")}
        model_dir, model_metrics_path, pred = list(model_dir)[k], list(model_metrics_path)[k], preds[k]
    else:
        pred = predict(model_dir)
    log.info("validated %s (%s)", model_dir, choice)
    train = dio.load_training_arrays(dio.verify_manifest(train_manifest_path))
    unseen = set(np.asarray(arrays["geometry_id"]).astype(str).tolist())
    shared = sorted(unseen & set(np.asarray(train["geometry_id"]).astype(str).tolist()))
    if shared:
        raise RuntimeError(f"validation livers {shared} are also training livers of {model_dir}: "
                           "the validation would not be on unseen livers")
    true = arrays["force_n"]
    metrics = force_metrics(true, pred)
    err = np.linalg.norm(pred - true, axis=1)
    rel_v = arrays["exertion_point_mm"] - arrays["liver_centroid_mm"]
    rel_t = train["exertion_point_mm"] - train["liver_centroid_mm"]
    dist = np.min(np.linalg.norm(rel_v[:, None, :] - rel_t[None, :, :], axis=2), axis=1)
    by_mag = error_by_force_bin(true, pred)
    by_liver = metrics_by_group(true, pred, arrays["geometry_id"])
    model_metrics = json.loads(Path(model_metrics_path).read_text())
    interval = interval_on_unseen(model_dir, arrays)
    sens = camera_sensitivity(model_dir, arrays, sensitivity or {})
    registration = registration_sensitivity(model_dir, arrays, registration_errors or [])
    shape = shape_sensitivity(model_dir, arrays, shape_changes or [])
    extrapolation = extrapolation_on_unseen(model_dir, arrays, err)
    result = {
        "n_cases": n,
        "metrics": metrics,
        "per_liver": by_liver["per_group"],
        "livers": {"n": by_liver["n_groups"], "mean": by_liver["mean"], "sd": by_liver["sd"],
                   "worst": by_liver["worst"]},
        "error_by_force_magnitude": by_mag,
        "error_vs_distance": {"distance_mm": dist.tolist(), "error_n": err.tolist()},
        "corr_error_distance": float(np.corrcoef(dist, err)[0, 1]) if n > 2 and dist.std() > 0 else float("nan"),
        "model_run_id": model_metrics.get("run_id"),
        "model_variant": model_metrics.get("variant") or model_of_metrics(model_metrics_path)[1],
        "variant_choice": choice,
        "all_variants": others,
        "interval": interval,
        "camera_sensitivity": sens,
        "registration": registration,
        "shape": shape,
        "outside_training": extrapolation,
        "predictions": {"case_id": [str(c) for c in arrays["case_id"]], "true_n": true.tolist(), "pred_n": pred.tolist()},
    }
    out_dir = Path(out_path).parent
    out_dir.mkdir(parents=True, exist_ok=True)
    from liverforce.learn.plots import evaluation_figures

    figures = evaluation_figures(true, pred, out_dir / "figures", title="unseen livers")
    result["figures"] = [str(Path(f).relative_to(out_dir)) for f in figures]
    tracker = Tracker(tracking_uri, experiment_name)
    run_id = tracker.start_run("validation", params={"model_run_id": str(result["model_run_id"]), "n_cases": n,
                                                     "model_variant": result["model_variant"]},
                               tags={"rule": "validate", "model_run_id": str(result["model_run_id"])})
    cov = {} if not interval else {f"interval_coverage_{ax}": v for ax, v in zip(("t1", "t2", "n"), interval["coverage"])}
    tracker.log_metrics(run_id, {**metrics, **cov, **{f"{k}_livers_mean": v for k, v in by_liver["mean"].items()},
                                 **{f"{k}_livers_sd": v for k, v in by_liver["sd"].items()},
                                 "n_livers": by_liver["n_groups"],
                                 **({} if not extrapolation else {"n_outside_training": extrapolation["n_outside"]})})
    for f in figures:
        tracker.log_artifact(run_id, f)
    tracker.end_run(run_id)
    result["run_id"] = run_id
    write_json_atomic(out_path, result)
    log.info("validation on %d unseen livers: MAE %.3f +- %.3f N (mean +- sd over livers), accuracy %.1f +- %.1f %%;"
             " worst liver %s (MAE %.3f N); %d cases", by_liver["n_groups"], by_liver["mean"]["mae_vec"],
             by_liver["sd"]["mae_vec"], by_liver["mean"]["accuracy_pct"], by_liver["sd"]["accuracy_pct"],
             by_liver["worst"], by_liver["per_group"][by_liver["worst"]]["mae_vec"], n)
    return result


