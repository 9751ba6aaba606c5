"""The report's held-out-exertion-points cell, and the floor below which an accuracy is flagged.

The accuracy is ``100 (1 - sum |e| / sum |F|)``: below :data:`ACCURACY_FLOOR_PCT` (0 %) the errors add up to
more than the forces themselves, worse than predicting no force at all, which a trained model does only when
it extrapolates. Such a number is never printed bare.
"""

from __future__ import annotations

import html

import numpy as np

#: an accuracy (%) below this is flagged as extrapolation (the errors exceed the forces: worse than predicting 0 N)
ACCURACY_FLOOR_PCT = 0.0


def number(v, nd: int = 3) -> str:
    """``v`` with ``nd`` decimals, in scientific notation when it is huge (a flagged extrapolation); ``–`` when
    it is unknown (None, NaN). The report's one way to print a measured number."""
    if v is None or not np.isfinite(float(v)):
        return "–"
    v = float(v)
    return f"{v:.2e}" if abs(v) >= 1e5 else f"{v:.{nd}f}"


def pm(mean, sd, nd: int = 3) -> str:
    """``mean ± sd`` (:func:`number` of each); the mean alone when the sd is unknown (None: no spread, as of
    one fold or split), ``–`` when the mean is."""
    if mean is None or not np.isfinite(float(mean)):
        return "–"
    if sd is None or not np.isfinite(float(sd)):
        return number(mean, nd)
    return f"{number(mean, nd)} ± {number(sd, nd)}"


def below_floor(v) -> bool:
    """True for a finite accuracy (%) below :data:`ACCURACY_FLOOR_PCT`."""
    return v is not None and np.isfinite(float(v)) and float(v) < ACCURACY_FLOOR_PCT


def flag_accuracy(text: str, values) -> str:
    """``text`` (an accuracy cell) flagged as extrapolation when any of ``values`` (%) is below the floor."""
    low = [float(v) for v in values if below_floor(v)]
    if not low:
        return text
    return (f"<span class='why'><b class='flag'>⚠ extrapolation: {text} <small>(below {ACCURACY_FLOOR_PCT:.0f} %: "
            f"the errors exceed the forces, worse than predicting 0 N; lowest {number(min(low), 1)} %)"
            "</small></b></span>")


def heldout_cell(hp: dict | None) -> str:
    """The models table's held-out-exertion-points cell of one model's ``heldout_points`` record.

    Not measured (every fold trained on too few points): the reason, no number. Partly scored: the mean ± sd
    of the scored folds (the mean alone of one scored fold: no spread) and why the others were not. Any scored
    fold below the floor: flagged as extrapolation with its lowest fold, never bare.
    """
    if not hp:
        return "–"
    folds, n_points = hp.get("folds"), hp.get("n_points")
    if hp.get("not_measured") or hp.get("metrics_mean") is None:
        why = hp.get("not_measured") or "no fold was scored"
        return f"<span class='why'><b class='flag'>not measured</b>: {html.escape(str(why))}</span>"
    per = hp.get("per_fold") or []
    scored = [f for f in per if "metrics" in f]
    n_scored = hp.get("n_scored", len(scored))
    mean = hp["metrics_mean"].get("accuracy_pct")
    # one scored fold has no spread: its sd is None (an earlier run's record may give 0), and no ± is printed
    sd = (hp.get("metrics_sd") or {}).get("accuracy_pct") if n_scored >= 2 else None
    text = flag_accuracy(pm(mean, sd, 1), [mean] + [f["metrics"].get("accuracy_pct") for f in scored])
    if n_scored == folds:
        return text + f" <small>({folds} folds of {n_points} points)</small>"
    skipped = [html.escape(str(f["skipped"])) for f in per if f.get("skipped")]
    return (f"<span class='why'>{text} <small>({n_scored} of {folds} folds of {n_points} points scored; "
            "not scored: " + "; ".join(skipped) + ")</small></span>")
