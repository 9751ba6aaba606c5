"""Force-estimation metrics, in newtons, computed in the source frame.

With errors ``e_i = F^_i - F_i`` (N) over ``m`` evaluated cases:

- ``mae_x, mae_y, mae_z``  = mean_i |e_i,c|
- ``rmse_x, rmse_y, rmse_z`` = sqrt(mean_i e_i,c^2)
- ``mae_vec``  = mean_i ||e_i||            (Euclidean norm of the error vector)
- ``rmse_vec`` = sqrt(mean_i ||e_i||^2)
- ``accuracy_pct`` = 100 (1 - sum_i ||e_i|| / sum_i ||F_i||)

The accuracy is the study's headline number, which the study did not define;
this is our definition: one minus the total vector error relative to the
total force magnitude. It can be negative for a useless model and is 100
only for a perfect one. Per-axis metrics are in the source frame, so they
depend on how the source frame is oriented; the vector metrics do not.

Example
-------
>>> import numpy as np
>>> m = force_metrics(np.array([[3.0, 0, 0]]), np.array([[3.0, 4.0, 0]]))
>>> m["mae_vec"], m["accuracy_pct"]
(4.0, -33.33333333333333)
"""

from __future__ import annotations

import numpy as np

METRIC_NAMES = (
    "mae_x", "mae_y", "mae_z", "mae_vec",
    "rmse_x", "rmse_y", "rmse_z", "rmse_vec",
    "accuracy_pct",
)


def force_metrics(force_true: np.ndarray, force_pred: np.ndarray) -> dict[str, float]:
    """MAE, RMSE (per axis and vector) in N and accuracy % (module docstring).

    Parameters
    ----------
    force_true, force_pred : (m, 3) array_like
        True and predicted forces in the source frame, N.

    Returns
    -------
    dict
        Keys ``METRIC_NAMES``, Python floats.
    """
    t = np.asarray(force_true, dtype=np.float64).reshape(-1, 3)
    p = np.asarray(force_pred, dtype=np.float64).reshape(-1, 3)
    if t.shape != p.shape or len(t) == 0:
        raise ValueError(f"force_true {t.shape} and force_pred {p.shape} must be the same non-empty (m, 3) shape")
    e = p - t
    norm = np.linalg.norm(e, axis=1)
    total = float(np.linalg.norm(t, axis=1).sum())
    out = {}
    for j, ax in enumerate("xyz"):
        out[f"mae_{ax}"] = float(np.mean(np.abs(e[:, j])))
    out["mae_vec"] = float(norm.mean())
    for j, ax in enumerate("xyz"):
        out[f"rmse_{ax}"] = float(np.sqrt(np.mean(e[:, j] ** 2)))
    out["rmse_vec"] = float(np.sqrt(np.mean(norm**2)))
    out["accuracy_pct"] = float(100.0 * (1.0 - norm.sum() / total)) if total > 0 else float("nan")
    return out


def metrics_by_group(force_true: np.ndarray, force_pred: np.ndarray, groups) -> dict:
    """Metrics per group (e.g. per unseen liver) and their mean and spread over the groups.

    Returns
    -------
    dict
        ``per_group`` {group: metrics + ``n``}, ``mean`` and ``sd`` (sample sd,
        ddof 1; 0 for one group) of every metric over the groups (each group
        weighs the same, whatever its number of cases), ``worst`` the group of
        the largest ``mae_vec``, ``n_groups``.
    """
    t = np.asarray(force_true, dtype=np.float64).reshape(-1, 3)
    p = np.asarray(force_pred, dtype=np.float64).reshape(-1, 3)
    g = np.asarray(groups).astype(str)
    per = {}
    for name in sorted(set(g.tolist())):
        sel = g == name
        per[name] = {**force_metrics(t[sel], p[sel]), "n": int(sel.sum())}
    vals = {k: np.array([m[k] for m in per.values()]) for k in METRIC_NAMES}
    return {
        "per_group": per,
        "n_groups": len(per),
        "mean": {k: float(v.mean()) for k, v in vals.items()},
        "sd": {k: float(v.std(ddof=1)) if len(v) > 1 else 0.0 for k, v in vals.items()},
        "worst": max(per, key=lambda k: per[k]["mae_vec"]),
    }


def error_by_force_bin(force_true: np.ndarray, force_pred: np.ndarray, n_bins: int = 5) -> list[dict]:
    """MAE of the force vector in equal-width bins of the true force magnitude (N).

    Each bin: ``force_lo_n``, ``force_hi_n``, ``n``, ``mean_force_n``, ``mae_vec_n`` and
    ``relative_mae`` = MAE / mean force of the bin (a model biased towards a
    constant force shows a large relative error in the lowest bin).
    """
    t = np.asarray(force_true, dtype=np.float64).reshape(-1, 3)
    p = np.asarray(force_pred, dtype=np.float64).reshape(-1, 3)
    err = np.linalg.norm(p - t, axis=1)
    mag = np.linalg.norm(t, axis=1)
    out = []
    for lo, hi, sel in force_bins(mag, np.linspace(0.0, max(float(mag.max()), 1e-9), n_bins + 1)):
        mean_f = float(mag[sel].mean())
        out.append({"force_lo_n": float(lo), "force_hi_n": float(hi), "n": int(sel.sum()),
                    "mean_force_n": mean_f, "mae_vec_n": float(err[sel].mean()),
                    "relative_mae": float(err[sel].mean() / mean_f) if mean_f > 0 else float("nan")})
    return out


def force_bins(magnitude: np.ndarray, edges: np.ndarray):
    """``(lo, hi, mask)`` of each non-empty bin ``[lo, hi)`` of ``magnitude`` (the last bin closed)."""
    n = len(edges) - 1
    for i, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
        sel = (magnitude >= lo) & ((magnitude < hi) if i < n - 1 else (magnitude <= hi))
        if sel.any():
            yield lo, hi, sel
