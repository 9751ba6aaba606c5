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
