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

``roi_features: displacement`` / ``both``, or any model with the state vector — **approximate only**
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

from liverforce.learn.frames import local_rotations
from liverforce.learn.representation import interpolate_to_grid
from liverforce.serve.checks import Limits, TrainingScale
from liverforce.serve.errors import PredictionInputError
from liverforce.serve.preop import Preop, _points


def cloud_support(model) -> str:
    """``"exact"`` if an unordered cloud determines the model's inputs, else ``"approximate"``."""
    return "exact" if model.representation.features == "deformed" and not model.uses_state else "approximate"


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
                    limits: Limits) -> tuple[dict, dict]:
    """One-row input-contract arrays from an unordered cloud; returns ``(arrays, info)``.

    ``info``: ``mode`` (exact/approximate), ``points_given``, ``points_used``.
    """
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
    R = local_rotations(preop.frame[2][None], preop.frame[0][None], preop.frame[1][None])[0]
    U = preop.roi_undeformed_mm
    U_loc = (U - p) @ R.T
    O_loc = (O - p) @ R.T
    keep = crop_cloud(O_loc, U_loc, scale, limits)
    n_used = int(keep.sum())
    if n_used < limits.min_cloud_points:
        med = float(np.median(np.linalg.norm(O - p, axis=1)))
        raise PredictionInputError(
            f"cloud: only {n_used} of {len(O)} points lie on the ROI footprint near the pre-operative surface "
            f"(at least {limits.min_cloud_points} needed; the points are a median {med:.4g} mm from the exertion "
            "point): is the cloud in mm and registered to the liver frame, and does it show the tool region?"
        )
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
        out["roi_undeformed_mm"] = [O_src]
        out["roi_deformed_mm"] = [O_src]
        return out, {"mode": "exact", "points_given": len(O), "points_used": n_used}
    z = interpolate_to_grid(Ok[:, :2], Ok[:, 2:3], U_loc[:, :2], "cloud")[:, 0]
    D_loc = np.column_stack([U_loc[:, :2], z])
    D_est = p + D_loc @ R
    out["roi_centroid_deformed_mm"] = D_est.mean(axis=0)[None]
    if model.representation.features == "deformed":
        out["roi_undeformed_mm"] = [O_src]
        out["roi_deformed_mm"] = [O_src]
    else:
        out["roi_deformed_mm"] = [D_est]
    return out, {"mode": "approximate", "points_given": len(O), "points_used": n_used}
