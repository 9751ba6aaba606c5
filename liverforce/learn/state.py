"""The pre-operative state vector S, expressed in the local frame at the exertion point.

S gives the regressor what the ROI alone cannot: where on the liver the tool
pushes, the liver's shape and the material. To be comparable across exertion
points, geometries and (arbitrary) source frames, every geometric entry is
expressed in the local frame ``R = [t1; t2; n]`` with the exertion point
``p`` as origin (:mod:`liverforce.learn.frames`):

======================  ======  ==================================================
entry                   size    definition (units)
======================  ======  ==================================================
liver_centroid          3       ``R (c_liver - p)``, mm. The exertion point is the
                                origin, so its position on the liver is carried
                                by this offset (and by the inertia below).
roi_centroid_undeformed 3       ``R (c_roi,undef - p)``, mm
roi_centroid_deformed   3       ``R (c_roi,def - p)``, mm
inertia                 6       upper triangle (xx, xy, xz, yy, yz, zz) of
                                ``R I R^T``, mm^5 (unit density). ``I`` must be
                                taken about the liver centroid, so it is
                                translation-invariant and rotates as a tensor.
                                Rotating into the local frame keeps the liver's
                                orientation relative to the surface normal
                                (eigenvalues alone would lose it).
tool_thickness          1       tissue thickness under the tool along the inward
                                normal, mm (a local, physical feature: a thin
                                lobe bends, a thick one indents)
probe_compliance        6       upper triangle (t1t1, t1t2, t1n, t2t2, t2n, nn) of
                                the pre-operative stiffness probe's compliance at
                                the exertion point (:mod:`liverforce.fem.probe`),
                                mm/N, already in the local frame. What the
                                liver's shape, thickness and supports do to the
                                force-displacement map right there, for the
                                experiment's reference material.
material                p       material constants as given, MPa
======================  ======  ==================================================

A rigid motion of the liver (points, frames, centroids, ``I -> Q I Q^T``)
leaves S unchanged.
"""

from __future__ import annotations

import numpy as np

from liverforce.learn.frames import case_rotations, offsets_to_local

STATE_INPUTS = (
    "exertion_point_mm",
    "frame_normal",
    "frame_t1",
    "frame_t2",
    "liver_centroid_mm",
    "roi_centroid_undeformed_mm",
    "roi_centroid_deformed_mm",
    "inertia_mm5",
    "tool_thickness_mm",
    "probe_compliance_mm_per_n",
    "material_params_mpa",
)

_TRIU = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
THICKNESS_COLUMN = 15  #: tool_thickness_mm column of the state vector
COMPLIANCE_COLUMNS = slice(16, 22)  #: probe compliance (upper triangle, local frame) columns
MATERIAL_START = 22  #: first material column of the state vector


def compliance_matrices(state: np.ndarray) -> np.ndarray:
    """The probe compliance ``(n, 3, 3)`` mm/N (local frame) rebuilt from state-vector rows."""
    c = np.asarray(state, dtype=np.float64)[:, COMPLIANCE_COLUMNS]
    out = np.empty((len(c), 3, 3))
    for j, (a, b) in enumerate(_TRIU):
        out[:, a, b] = out[:, b, a] = c[:, j]
    return out


def state_vector(arrays: dict, R: np.ndarray | None = None) -> np.ndarray:
    """State vectors ``(n, 22 + p)`` float64 of the cases in ``arrays`` (module table).

    Parameters
    ----------
    arrays : dict
        The input-contract arrays; uses the keys in ``STATE_INPUTS``.
    R : (n, 3, 3) array, optional
        The cases' local rotations, when already computed
        (:func:`liverforce.learn.frames.case_rotations` of the same arrays);
        computed here otherwise.

    Returns
    -------
    (n, 22 + p) float64
        Columns as in :func:`state_names`.
    """
    missing = [k for k in STATE_INPUTS if k not in arrays]
    if missing:
        raise KeyError(f"state vector needs the columns {missing}; they are missing from the input arrays")
    R = case_rotations(arrays) if R is None else R
    p = np.asarray(arrays["exertion_point_mm"], dtype=np.float64)
    n = len(p)
    inertia = np.asarray(arrays["inertia_mm5"], dtype=np.float64).reshape(n, 3, 3)
    inertia = 0.5 * (inertia + np.transpose(inertia, (0, 2, 1)))
    I_loc = R @ inertia @ np.transpose(R, (0, 2, 1))
    mat = np.asarray(arrays["material_params_mpa"], dtype=np.float64).reshape(n, -1)
    C = np.asarray(arrays["probe_compliance_mm_per_n"], dtype=np.float64).reshape(n, 3, 3)
    C = 0.5 * (C + np.transpose(C, (0, 2, 1)))
    return np.column_stack(
        [
            offsets_to_local(arrays["liver_centroid_mm"], p, R),
            offsets_to_local(arrays["roi_centroid_undeformed_mm"], p, R),
            offsets_to_local(arrays["roi_centroid_deformed_mm"], p, R),
            np.stack([I_loc[:, a, b] for a, b in _TRIU], axis=1),
            np.asarray(arrays["tool_thickness_mm"], dtype=np.float64).reshape(n),
            np.stack([C[:, a, b] for a, b in _TRIU], axis=1),
            mat,
        ]
    )


def state_names(n_material: int) -> list[str]:
    """Column names of :func:`state_vector` for ``n_material`` material constants."""
    names = []
    for base in ("liver_centroid", "roi_centroid_undeformed", "roi_centroid_deformed"):
        names += [f"{base}_{ax}_mm" for ax in ("t1", "t2", "n")]
    names += [f"inertia_{'xyz'[a]}{'xyz'[b]}_mm5" for a, b in _TRIU]
    names += ["tool_thickness_mm"]
    names += [f"probe_compliance_{('t1', 't2', 'n')[a]}{('t1', 't2', 'n')[b]}_mm_per_n" for a, b in _TRIU]
    names += [f"material_{j}_mpa" for j in range(n_material)]
    return names


# --------------------------------------------------------------------------
# the geometric state against the training range (serving warnings, IV test breakdown)
# --------------------------------------------------------------------------

#: relative margin of a training bound in :func:`outside_ranges`. A lab gives its exertion point rounded, often
#: in metres: on the SOFA liver (the mesh stage's context, 8 cases), rounding it to 1 / 10 / 100 um moved the
#: thickness, the probe's compliance and the centroid distance by up to 6.5e-6 / 5.7e-5 / 5.6e-4 of their values,
#: and a test case at a training case's own exertion point was warned of as 'thinner than in every training case'.
#: Within 0.1 % of a bound is inside: no model's error changes over that.
_BOUND_TOL = 1e-3
#: geometric state inputs compared with the training range: name -> (what, unit, word below, word above)
STATE_RANGES = {
    "tool_thickness_mm": ("the tissue under the tool", "mm", "thinner", "thicker"),
    "probe_compliance_mm_per_n": ("the probe compliance (trace)", "mm/N", "stiffer", "softer"),
    "liver_size_mm": ("the liver's size (tr(I)/2)^(1/5)", "mm", "smaller", "larger"),
    "centroid_distance_mm": ("the exertion point's distance from the liver centroid", "mm", "nearer", "farther"),
}


def state_range_values(arrays: dict) -> dict[str, np.ndarray]:
    """Per row, the inputs of :data:`STATE_RANGES` from input-contract ``arrays`` (absent inputs left out).

    The same quantities as ``liverforce.learn.model.training_scale`` records
    (traces and distances do not depend on the frame)."""
    out = {}
    if "tool_thickness_mm" in arrays:
        out["tool_thickness_mm"] = np.asarray(arrays["tool_thickness_mm"], dtype=np.float64).reshape(-1)
    if "probe_compliance_mm_per_n" in arrays:
        C = np.asarray(arrays["probe_compliance_mm_per_n"], dtype=np.float64).reshape(-1, 9)
        out["probe_compliance_mm_per_n"] = C[:, [0, 4, 8]].sum(axis=1)
    if "inertia_mm5" in arrays:
        inertia = np.asarray(arrays["inertia_mm5"], dtype=np.float64).reshape(-1, 9)
        out["liver_size_mm"] = np.power(np.maximum(inertia[:, [0, 4, 8]].sum(axis=1), 0.0) / 2.0, 0.2)
    if "liver_centroid_mm" in arrays:
        c = np.asarray(arrays["liver_centroid_mm"], dtype=np.float64).reshape(-1, 3)
        out["centroid_distance_mm"] = np.linalg.norm(
            c - np.asarray(arrays["exertion_point_mm"], dtype=np.float64).reshape(-1, 3), axis=1)
    return out


def recorded_ranges(training_scale: dict) -> dict:
    """The ``[min, max]`` of each :data:`STATE_RANGES` input from a bundle's ``meta["training_scale"]``."""
    keys = {"tool_thickness_mm": "tool_thickness_mm", "probe_compliance_mm_per_n": "probe_compliance_mm_per_n",
            "liver_size_mm": "inertia_length_mm", "centroid_distance_mm": "centroid_distance_mm"}
    return {k: (None if training_scale.get(r) is None else tuple(training_scale[r])) for k, r in keys.items()}


def outside_ranges(arrays: dict, ranges: dict) -> tuple[dict[str, np.ndarray], list[list[str]]]:
    """Rows whose geometric state lies outside ``ranges``: ``(masks by input, warnings per row)``.

    ``ranges``: ``[min, max]`` (or None: not checked) per :data:`STATE_RANGES`
    input, the training cases' (:func:`recorded_ranges`). Outside them the
    model extrapolates, and the warning says so with the value, the range and
    the direction. Material constants are not checked: the models scale force
    by the material's stiffness (``model.force_scaling``), so they extrapolate
    there by construction. A value within ``_BOUND_TOL`` (0.1 %, relative) of a bound is inside.
    """
    n = len(arrays["exertion_point_mm"])
    masks, warnings = {}, [[] for _ in range(n)]
    for key, v in state_range_values(arrays).items():
        rng = ranges.get(key)
        if rng is None:
            continue
        lo, hi = rng
        low, high = v < lo - _BOUND_TOL * abs(lo), v > hi + _BOUND_TOL * abs(hi)
        masks[key] = low | high
        what, unit, below, above = STATE_RANGES[key]
        span = f"{lo:.4g}" if np.isclose(lo, hi) else f"{lo:.4g}..{hi:.4g}"
        for i in np.flatnonzero(masks[key]):
            warnings[i].append(f"{what} is {v[i]:.4g} {unit}, {below if low[i] else above} than in every training "
                               f"case ({span} {unit}): the model extrapolates, expect a larger error")
    return masks, warnings
