"""benchmarks/experiment_camera_loss.py: the per-component error and the ideal camera settings it re-observes with."""
from __future__ import annotations

import numpy as np
import pytest

from benchmarks.experiment_camera_loss import IDEAL, component_mae, ideal_camera


def test_component_mae_is_the_mean_over_livers_of_each_livers_mean():
    true = np.zeros((3, 3))
    pred = np.array([[0.3, 0.0, 0.4], [0.0, 0.0, 1.0], [0.0, 2.0, 0.0]])
    got = component_mae(true, pred, ["a", "a", "b"])
    # liver a: |t1| 0.15, |t2| 0, |n| 0.7, |vector| (0.5 + 1) / 2 = 0.75; liver b: 0 / 2 / 0 / 2
    np.testing.assert_allclose(got, [0.075, 1.0, 0.35, 1.375])


def test_component_mae_refuses_mismatched_or_empty_input():
    with pytest.raises(ValueError, match="as many"):
        component_mae(np.zeros((2, 3)), np.zeros((2, 3)), ["a"])
    with pytest.raises(ValueError, match="at least one"):
        component_mae(np.zeros((0, 3)), np.zeros((0, 3)), [])


def test_ideal_camera_sets_one_setting_or_all_and_leaves_the_model_settings_alone():
    cam = {"observation": {"noise_sd_mm": 0.5, "n_points": [200, 20000]}, "tip_noise_mm": 0.5,
           "tip_noise_normal_mm": 1.0, "grid": {}}
    noise0, dense, tip0, ideal = (ideal_camera(cam, w) for w in IDEAL)
    assert noise0["observation"] == {"noise_sd_mm": 0.0, "n_points": [200, 20000]}
    assert noise0["tip_noise_mm"] == 0.5 and noise0["tip_noise_normal_mm"] == 1.0
    assert dense["observation"] == {"noise_sd_mm": 0.5, "n_points": [20000, 20000]}
    assert tip0["observation"] == cam["observation"]
    assert tip0["tip_noise_mm"] == 0.0 and tip0["tip_noise_normal_mm"] is None
    assert ideal["observation"] == {"noise_sd_mm": 0.0, "n_points": [20000, 20000]}
    assert ideal["tip_noise_mm"] == 0.0 and ideal["tip_noise_normal_mm"] is None
    assert cam["observation"] == {"noise_sd_mm": 0.5, "n_points": [200, 20000]} and cam["tip_noise_mm"] == 0.5
    with pytest.raises(ValueError, match="unknown ideal setting"):
        ideal_camera(cam, "perfect")
