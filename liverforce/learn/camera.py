"""Camera features: what a model with ``roi_features: cloud`` reads, and nothing else.

In surgery there are no FE node ids. What is known is the pre-operative
surface near the exertion point (and its local frame), the tool tip's position
from the robot's kinematics, and an unordered, partial, noisy cloud of the
visible deformed surface. A ``cloud`` model's feature vector is built from
exactly these (length ``2 g^2 + 3``, ``+ 2`` with the dent fit)::

    [ dz (g^2) | valid (g^2) | (dent (2)) | tip (3) ]

- ``dz``: the cloud's signed normal height change over the pre-operative
  surface on the ``g x g`` tangent-plane grid, invalid cells filled
  (:func:`liverforce.learn.cloud_features.cloud_grid`; no correspondence);
- ``valid``: 1 where the cloud covers the cell, 0 where it was filled (hidden
  by the tool or the liver itself, out of view, too sparse);
- ``dent`` (``camera.grid.dent_radius_mm > 0``, with the instrument fit): the amplitude and the offset of a
  flat punch's profile over a plane, fitted to the liver's points round the tool's axis
  (:func:`liverforce.learn.cloud_features.fit_dent`): the dent the tool makes, read from the ring it leaves
  visible, apart from the liver's own motion there. The regressor reads the amplitude as a force, ``k
  amplitude / C_nn`` (``C_nn`` the probe's normal compliance at the reference material, ``k = C10 / C10_ref``),
  which stays in the training range of the forces on a stiffer liver, and the offset
  (:meth:`liverforce.learn.model.Preprocessor.dent_features`);
- ``tip``: the tool tip's displacement ``R (q - p)`` in the local frame (mm),
  ``q`` the tip position the robot reports, ``p`` the pre-operative exertion
  point. The tip touches the tissue, so this is the surface's displacement at
  the exertion point, tangential part included: the one place where the
  camera's aperture problem does not apply. With the stiffness probe's
  compliance ``C`` it gives the linear force estimate ``f_lin = C^-1 tip``
  (:mod:`liverforce.learn.model`). With ``camera.grid.instrument_radius_mm``
  the cloud may hold the instrument's own points (a camera sees the tool;
  ``camera.observation.instrument_in_cloud`` trains on such clouds): the
  shaft's axis fitted to them replaces the tip's tangential part, which the
  kinematics give to ``tip_noise_mm`` only, and they are dropped from the
  grid (:func:`liverforce.learn.cloud_features.fit_instrument`).

Where the inputs come from
--------------------------
- **Serving / user data**: ``arrays["camera_cloud_mm"]`` (one ``(k_i, 3)`` cloud
  per case) and ``arrays["tool_tip_mm"]`` ``(n, 3)``, in the source frame, and
  the pre-operative ROI patch: ``roi_undeformed_mm`` with its own triangles
  ``roi_triangles`` (``(m_i, 3)`` indices into it; ``Preop.from_surface`` computes
  them), the top sheet of which is the height reference
  (:meth:`~liverforce.learn.cloud_features.ReferenceSurface.from_patch`).
- **Training from the shards** (no new FE): the stored full-surface
  displacements are observed by :func:`liverforce.learn.observation.observe_many`
  (camera pose in a cone, visibility, tool shaft and tip, density, noise), seeded
  per case by ``case_seed(observation_seed, case_id)``; the tip is the exertion
  point moved with the surface plus Gaussian kinematics noise of
  ``tip_noise_mm`` per coordinate (stage ``observation.tip``); with
  ``tip_noise_normal_mm`` set, ``tip_noise_mm`` is the sd along the surface
  (tangential) and ``tip_noise_normal_mm`` the sd along the normal. Needs
  ``arrays["surface_displacement_mm"]``, ``arrays["roi_triangles"]`` and ``arrays["surface_meshes"]``
  (geometry id -> ``(vertices, triangles)`` of :func:`surface_from_mesh`; a
  per-run entry, not a per-case column). The tool's shaft is along the outward
  normal: taking it along ``-F`` would let the shadow's direction tell the model
  the force direction, which a real tool axis only loosely does.

Features of many cases are memoised per process (key: settings, seed, case
id), so repeated splits and tuning folds observe each case once per seed.
"""

from __future__ import annotations

import hashlib
import json
import math

import numpy as np

from liverforce.learn.cloud_features import ROI_TRIANGLES_KEY, CloudGridSpec, ReferenceSurface, cloud_grid
from liverforce.learn.frames import case_rotations, tip_offsets
from liverforce.seeds import derive

#: per-run (not per-case) entry of a training arrays dict: geometry id -> (surface vertices, triangles)
SURFACES_KEY = "surface_meshes"
#: serving inputs of a cloud model
CLOUD_KEY = "camera_cloud_mm"
TIP_KEY = "tool_tip_mm"
#: the feature rows of those clouds, when already computed (serving: computed once, checked, then predicted)
FEATURES_KEY = "camera_features"

#: grid settings of cloud_features a config may set (the grid size and half-width come from the representation)
GRID_KEYS = ("kernel_radius_cells", "min_points", "fill", "max_abs_height_mm", "reference_oversample",
             "estimator", "max_leverage", "reference", "instrument_radius_mm", "instrument_rise_mm",
             "instrument_clearance_mm", "instrument_min_points", "instrument_point_sd_mm", "instrument_tip_sd_mm",
             "instrument_max_tilt_deg", "dent_radius_mm", "instrument_point_sd_max_mm", "outlier_mm")

_CACHE: dict[tuple, np.ndarray] = {}
_CACHE_MAX = 200_000


def n_features(grid_size: int, dent: bool = False) -> int:
    return 2 * grid_size**2 + (N_DENT if dent else 0) + 3


#: columns of the dent fit (``camera.grid.dent_radius_mm > 0``), between the mask and the tip: amplitude, offset
N_DENT = 2


def channel_groups(grid_size: int, dent: bool = False) -> np.ndarray:
    """Scaling groups: the height channel, the mask, (the dent fit,) the tip displacement."""
    g2 = grid_size**2
    mid = [np.full(N_DENT, 3)] if dent else []
    return np.concatenate([np.zeros(g2, int), np.ones(g2, int), *mid, np.full(3, 2)])


def isotropic_tip(camera: dict, sd_mm: float) -> dict:
    """These camera settings with the tool tip's kinematics noise ``sd_mm`` in every direction (a split along
    the normal dropped); the cloud is observed as before (the tip's noise has its own seed stream,
    ``observation.tip``)."""
    return {**camera, "tip_noise_mm": float(sd_mm), "tip_noise_normal_mm": None}


def exact_tip(camera: dict) -> dict:
    """These camera settings with an exact tool tip (:func:`isotropic_tip` at 0 mm)."""
    return isotropic_tip(camera, 0.0)


def instrument_sds(camera: dict, half_width_mm: float, grid_size: int) -> dict:
    """The sds an instrument fit weighs its points and its prior by, from these camera settings: the
    observation's point noise (the least of a range: the fit refits a noisier cloud with its own,
    :func:`~liverforce.learn.cloud_features.fit_instrument`; a range's most too, for serving's warning, unless
    the grid sets the point sd) and the kinematic tip's tangential noise (``tip_noise_mm``)."""
    lo, hi = observation_config(camera, half_width_mm, grid_size).noise_sd_mm
    out = {"instrument_point_sd_mm": lo, "instrument_tip_sd_mm": float(camera.get("tip_noise_mm", 0.0))}
    if hi > lo and "instrument_point_sd_mm" not in (camera.get("grid") or {}):
        out["instrument_point_sd_max_mm"] = hi  # not where the grid holds the point sd: a trained model's (it
        # records both; re-observed with other noise, it keeps its own) or one the config sets
    return out


def grid_spec(grid_size: int, half_width_mm: float, camera: dict) -> CloudGridSpec:
    """The cloud-grid settings of these camera settings. An instrument fit's sds are the grid's own where it
    records them (a trained model's: ``representation_from_config``), else :func:`instrument_sds`."""
    extra = {k: camera["grid"][k] for k in GRID_KEYS if k in (camera.get("grid") or {})}
    if float(extra.get("instrument_radius_mm") or 0.0) > 0:
        extra = {**instrument_sds(camera, half_width_mm, grid_size), **extra}
    return CloudGridSpec(grid_size=int(grid_size), half_width_mm=float(half_width_mm), **extra)


def observation_config(camera: dict, half_width_mm: float, grid_size: int):
    """The :class:`ObservationConfig` of these settings; ``roi_radius_mm: null`` -> the grid's reach."""
    from liverforce.learn.observation import ObservationConfig

    obs = dict(camera.get("observation") or {})
    if obs.get("roi_radius_mm") is None:
        spacing = 2.0 * half_width_mm / (grid_size - 1)
        obs["roi_radius_mm"] = math.sqrt(2.0) * half_width_mm + 2.0 * spacing
    return ObservationConfig.from_dict(obs)


def observe_cases(arrays: dict, camera: dict, half_width_mm: float, grid_size: int, seed: int,
                  rows: np.ndarray | None = None, *, records: bool = False) -> tuple:
    """Camera clouds and noisy tool-tip positions ``(clouds, tips)`` of the cases ``rows`` (all by default), from
    the shards. ``records``: also each cloud's :class:`~liverforce.learn.observation.ObservationRecord` (camera
    position, the tool tip it was observed with, counts), as a third item."""
    from liverforce.learn.observation import observe_many

    if SURFACES_KEY not in arrays or "surface_displacement_mm" not in arrays:
        raise KeyError(
            "a camera-cloud model needs each case's camera cloud and tool tip ('camera_cloud_mm', "
            "'tool_tip_mm') or, to observe simulated cases, the full-surface displacements "
            "('surface_displacement_mm') and the geometries' surfaces ('surface_meshes')")
    cfg = observation_config(camera, half_width_mm, grid_size)
    tip_sd = float(camera.get("tip_noise_mm", 0.0))
    tip_sd_n = camera.get("tip_noise_normal_mm")  # None: isotropic; else tip_sd is the tangential sd
    n = len(arrays["exertion_point_mm"])
    rows = np.arange(n) if rows is None else np.asarray(rows)
    geo = np.asarray(arrays["geometry_id"]).astype(str)
    ids = np.asarray(arrays["case_id"]).astype(str)
    P = np.asarray(arrays["exertion_point_mm"], dtype=np.float64)
    N = np.asarray(arrays["frame_normal"], dtype=np.float64)
    clouds: list = [None] * len(rows)
    recs: list = [None] * len(rows)
    tips = np.empty((len(rows), 3))
    for g in sorted(set(geo[rows])):
        if g not in arrays[SURFACES_KEY]:
            raise KeyError(f"no surface for geometry '{g}' (needed to observe its cases with a camera)")
        V, T = arrays[SURFACES_KEY][g]
        pos = np.flatnonzero(geo[rows] == g)
        sel = rows[pos]
        disp = [arrays["surface_displacement_mm"][i] for i in sel]
        cl, rec = observe_many(V, T, disp, P[sel], N[sel], cfg, seed=seed, case_keys=list(ids[sel]))
        q = _moved_points(V, T, P[sel], disp)
        for k, i in enumerate(pos):
            clouds[i] = cl[k]
            recs[i] = rec[k]
            if tip_sd > 0 or tip_sd_n:
                rng = np.random.default_rng(derive(seed, "observation.tip", ids[rows[i]]))
                if tip_sd_n is None:
                    q[k] = q[k] + rng.normal(0.0, tip_sd, 3)
                else:  # the same draw, its normal and tangential parts scaled apart
                    e = rng.normal(0.0, 1.0, 3)
                    nrm = N[rows[i]] / np.linalg.norm(N[rows[i]])
                    e_n = float(e @ nrm)
                    q[k] = q[k] + tip_sd * (e - e_n * nrm) + float(tip_sd_n) * e_n * nrm
            tips[i] = q[k]
    return (clouds, tips, recs) if records else (clouds, tips)


def _moved_points(V: np.ndarray, T: np.ndarray, P: np.ndarray, disp) -> np.ndarray:
    """Points ``P (k, 3)`` on the undeformed surface ``(V, T)`` moved with it (``disp``: one displacement field
    per point): where :func:`observe_cases` places a case's tool tip, before its noise."""
    from liverforce.learn.observation import surface_point_displacement

    return P + surface_point_displacement(V, T, P, disp)


def tips_off_grid(arrays: dict, half_width_mm: float) -> list[tuple[str, float]] | None:
    """The cases whose tool tip lies off the camera grid along the surface: ``(case id, the tip's offset along
    the surface in the local frame, mm)`` (:func:`~liverforce.learn.frames.tip_offsets`) where it exceeds
    ``half_width_mm``. The tips given with the cases (``tool_tip_mm``), else placed as :func:`observe_cases`
    places them (before their noise); None when neither is there (not measured). Serving refuses such a tip
    (the grid does not see the tool); a deep press along the normal keeps it over the grid. Usually a lobe
    swinging on loose supports."""
    P = np.asarray(arrays["exertion_point_mm"], dtype=np.float64)
    ids = np.asarray(arrays["case_id"]).astype(str)
    if "tool_tip_mm" in arrays:
        tips = np.asarray(arrays["tool_tip_mm"], dtype=np.float64).reshape(-1, 3)
    elif SURFACES_KEY in arrays and "surface_displacement_mm" in arrays:
        geo = np.asarray(arrays["geometry_id"]).astype(str)
        tips = np.empty_like(P)
        for g in sorted(set(geo)):
            V, T = arrays[SURFACES_KEY][g]
            sel = np.flatnonzero(geo == g)
            tips[sel] = _moved_points(V, T, P[sel], [arrays["surface_displacement_mm"][i] for i in sel])
    else:
        return None
    along, _ = tip_offsets(tips, P, case_rotations(arrays))
    return sorted((str(ids[i]), float(along[i])) for i in np.flatnonzero(along > half_width_mm))


def features_from_clouds(clouds, tips, arrays: dict, spec: CloudGridSpec,
                         rows: np.ndarray | None = None, R: np.ndarray | None = None,
                         fitted: list | None = None, point_sd: list | None = None,
                         outliers: list | None = None) -> np.ndarray:
    """Feature rows ``(len(rows), 2 g^2 + 3)`` from clouds and tip positions (source frame) of cases ``rows``.

    ``R``: the local rotations of all cases of ``arrays`` (:func:`liverforce.learn.frames.case_rotations`),
    when already computed. ``fitted``: a list that gets, per row, the instrument points its axis was fitted to
    (0: the kinematic tip; with ``spec.instrument_radius_mm > 0``); ``point_sd``: one that gets the cloud's
    point noise estimated from the fit's candidates (mm, NaN when nothing was fitted;
    :func:`liverforce.learn.cloud_features.fit_instrument`); ``outliers``: one that gets, per row, the points
    dropped as gross depth errors and the points tested for them (``spec.outlier_mm``; ``(0, 0)`` without it).
    """
    n = len(arrays["exertion_point_mm"])
    rows = np.arange(n) if rows is None else np.asarray(rows)
    P = np.asarray(arrays["exertion_point_mm"], dtype=np.float64)
    R = case_rotations(arrays) if R is None else R
    ids = arrays.get("case_id")
    tris = arrays.get(ROI_TRIANGLES_KEY)
    tips = np.asarray(tips, dtype=np.float64).reshape(-1, 3)
    if len(clouds) != len(rows) or len(tips) != len(rows):
        raise ValueError(f"need one cloud and one tool tip per case ({len(rows)}); got {len(clouds)} and {len(tips)}")
    dent = spec.dent_radius_mm > 0
    g2 = 2 * spec.grid_size**2
    out = np.empty((len(rows), n_features(spec.grid_size, dent)))
    refs: dict = {}
    for k, i in enumerate(rows):
        key = tuple(np.round(P[i], 6)) + tuple(np.round(R[i].ravel(), 9)) + (len(arrays["roi_undeformed_mm"][i]),)
        ref = refs.get(key)
        if ref is None:
            label = f"case {ids[i] if ids is not None else i}"
            ref = refs[key] = ReferenceSurface.for_case(arrays["roi_undeformed_mm"][i],
                                                        None if tris is None else tris[i], P[i], R[i], spec,
                                                        label=label)
        cloud = np.asarray(clouds[k], dtype=np.float64).reshape(-1, 3)
        if spec.instrument_radius_mm > 0:  # the instrument's points dropped, its axis the tip's tangential part
            grid = cloud_grid(cloud, ref, spec, tips[k])
            out[k, :g2] = grid.features(include_mask=True)
            if dent:
                out[k, g2:g2 + N_DENT] = grid.dent
            out[k, -3:] = grid.tip_local
            if fitted is not None:
                fitted.append(grid.n_instrument)
            if point_sd is not None:
                point_sd.append(grid.instrument_sd_mm)
        else:
            grid = cloud_grid(cloud, ref, spec)
            out[k, :-3] = grid.features(include_mask=True)
            out[k, -3:] = R[i] @ (tips[k] - P[i])
        if outliers is not None:
            outliers.append((grid.n_outliers, grid.n_outlier_tested))
    return out


def camera_features(arrays: dict, camera: dict, grid_size: int, half_width_mm: float,
                    observation_seed: int | None, R: np.ndarray | None = None) -> np.ndarray:
    """The feature matrix of a ``cloud`` representation (module docstring).

    ``R``: the cases' local rotations (:func:`liverforce.learn.frames.case_rotations`), when already computed.
    """
    spec = grid_spec(grid_size, half_width_mm, camera)
    if FEATURES_KEY in arrays:  # already computed from these arrays' clouds (serving checks them first)
        return np.asarray(arrays[FEATURES_KEY], dtype=np.float64)
    if CLOUD_KEY in arrays:
        if TIP_KEY not in arrays:
            raise KeyError("a camera-cloud model needs the tool tip position ('tool_tip_mm', from the robot's "
                           "kinematics) with each cloud")
        return features_from_clouds(arrays[CLOUD_KEY], arrays[TIP_KEY], arrays, spec, R=R)
    if observation_seed is None:
        raise ValueError("a camera-cloud model predicts from camera clouds ('camera_cloud_mm' and 'tool_tip_mm'); "
                         "to observe simulated cases give an observation seed")
    n = len(arrays["exertion_point_mm"])
    ids = np.asarray(arrays["case_id"]).astype(str)
    settings = json.dumps([camera, grid_size, half_width_mm], sort_keys=True, default=str)
    disp = arrays.get("surface_displacement_mm")
    tris = arrays.get(ROI_TRIANGLES_KEY)

    def digest(*parts) -> str:
        h = hashlib.blake2b(digest_size=16)
        for a in parts:
            if a is not None:
                h.update(np.ascontiguousarray(a).tobytes())
        return h.hexdigest()

    # the key holds what the row's features are made of: the surface's motion and the pre-operative patch
    keys = [(settings, int(observation_seed), cid,
             digest(None if disp is None else disp[i], arrays["roi_undeformed_mm"][i],
                    None if tris is None else np.asarray(tris[i], dtype=np.int64)))
            for i, cid in enumerate(ids)]
    todo = np.array([i for i in range(n) if keys[i] not in _CACHE], dtype=np.int64)
    if todo.size:
        clouds, tips = observe_cases(arrays, camera, half_width_mm, grid_size, int(observation_seed), todo)
        rows = features_from_clouds(clouds, tips, arrays, spec, todo, R=R)
        if len(_CACHE) + len(todo) > _CACHE_MAX:
            _CACHE.clear()
        for k, i in enumerate(todo):
            _CACHE[keys[i]] = rows[k]
    return np.stack([_CACHE[k] for k in keys]) if n else np.empty((0, n_features(grid_size, spec.dent_radius_mm > 0)))
