"""benchmarks/experiment_loading_path.py: the load steps it simulates and what it reports of a path's frames."""
from __future__ import annotations

import numpy as np
import pytest

from benchmarks.experiment_loading_path import path_summary, step_cases


def test_the_steps_are_fractions_of_the_case_force_ending_at_the_case():
    case = {"case_id": "V-000007", "geometry_id": "val-1000", "force_n": [0.3, -1.2, -2.4], "force_magnitude_n": 2.7,
            "exertion_point_mm": [1.0, 2.0, 3.0]}
    steps = step_cases(case, 4)
    assert [s["case_id"] for s in steps] == ["V-000007-s01", "V-000007-s02", "V-000007-s03", "V-000007-s04"]
    F = np.array([s["force_n"] for s in steps])
    np.testing.assert_allclose(F, np.outer([0.25, 0.5, 0.75, 1.0], case["force_n"]), rtol=1e-15)
    np.testing.assert_allclose([s["force_magnitude_n"] for s in steps], np.linalg.norm(F, axis=1), rtol=1e-15)
    assert all(s["exertion_point_mm"] == case["exertion_point_mm"] for s in steps)  # the same tool position
    assert case["case_id"] == "V-000007"  # the row itself is left as it was
    with pytest.raises(ValueError, match="at least 1"):
        step_cases(case, 0)


def test_the_path_summary_separates_the_errors_mean_from_its_frame_to_frame_noise():
    """A constant local error is all mean and no noise; an alternating one is noise (the sd of its successive
    differences over sqrt 2); the coverage counts the frames whose local error lies within the half-width; a
    refused frame (NaN) is left out and counted."""
    T = 7
    R = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])  # local t1, t2, n of the liver frame
    true = np.outer(np.arange(1, T + 1), [0.0, 0.0, -0.5])
    e_local = np.column_stack([np.full(T, 0.1), 0.2 * (-1.0) ** np.arange(T), np.zeros(T)])
    pred = true + e_local @ R  # local -> liver frame (R orthonormal)
    half = np.tile([0.15, 0.15, 0.05], (T, 1))
    pred[3] = np.nan
    s = path_summary(true, pred, half, R)
    assert s["frames"] == T and s["predicted"] == T - 1
    assert s["mae_n"] == pytest.approx(np.hypot(0.1, 0.2))
    assert s["coverage"] == pytest.approx([1.0, 0.0, 1.0])
    assert s["mean_error_n"][0] == pytest.approx(0.1) and s["mean_error_n"][2] == pytest.approx(0.0)
    assert s["noise_n"][0] == pytest.approx(0.0, abs=1e-12) and s["noise_n"][2] == pytest.approx(0.0, abs=1e-12)
    # the refused 4th frame left out: t2 errors +0.2 -0.2 +0.2 | +0.2 -0.2 +0.2, successive differences
    # -0.4 +0.4 0 -0.4 +0.4 (the gap joins frames 3 and 5)
    d = np.array([-0.4, 0.4, 0.0, -0.4, 0.4])
    assert s["noise_n"][1] == pytest.approx(d.std(ddof=1) / np.sqrt(2.0))
    assert np.isnan(path_summary(true[:2], pred[:2], half[:2], R)["noise_n"]).all()  # too few frames
