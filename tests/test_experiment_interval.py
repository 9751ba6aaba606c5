"""benchmarks/experiment_interval.py: the line it prints per scale from the validation's interval results."""
from __future__ import annotations

import numpy as np
import pytest

from benchmarks.experiment_interval import interval_form, interval_forms, stiffness_factors, summary
from liverforce.learn.interval import ConformalInterval


def _doc(cov, bins, half=(0.3, 0.3, 0.4)):
    return {"coverage": cov, "half_width_mean_n": list(half),
            "coverage_by_force": [{"coverage": b} for b in bins]}


def test_summary_is_the_mean_and_sd_over_splits_with_the_worst_quintile_and_the_spread():
    b1 = [[1.0, 1.0, 1.0], [0.9, 0.9, 0.9], [0.9, 0.9, 0.9], [0.8, 0.9, 0.9], [0.7, 0.8, 0.9]]
    b2 = [[0.9, 0.9, 0.9]] * 4 + [[0.9, 0.5, 0.9]]
    line = summary([_doc([0.88, 0.90, 0.92], b1), _doc([0.92, 0.90, 0.96], b2, half=(0.5, 0.3, 0.2))])
    assert line.startswith("coverage 90.0 +- 2.8 / 90.0 +- 0.0 / 94.0 +- 2.8 %, half-widths 0.400 / 0.300 / 0.300 N")
    assert "t1 95 90 90 85 80 | t2 95 90 90 90 65 | n 95 90 90 90 90 %" in line
    assert "worst quintile 60.0 %" in line  # (70 + 50) / 2: each split's worst quintile-component
    # range over the quintiles per component: split 1 30 / 20 / 10 points, split 2 0 / 40 / 0 -> mean 16.7
    assert line.endswith("spread over the quintiles 16.7 points")


def test_summary_refuses_a_split_with_an_empty_quintile():
    with pytest.raises(SystemExit, match="fewer than 5"):
        summary([_doc([0.9] * 3, [[0.9] * 3] * 4)])


@pytest.mark.parametrize("scale", ["none", "force", "force_bins"])
def test_interval_form_unwidened_drops_only_the_widening_outside_the_stiffness_range(scale):
    rng = np.random.default_rng(0)
    n = 400
    true = rng.normal(0.0, 1.0, (n, 3))
    pred = true + rng.normal(0.0, 0.1, (n, 3)) * np.array([1.0, 2.0, 3.0])
    cal = {"true_local": true, "pred_local": pred, "stiffness": rng.uniform(0.7, 1.3, (n, 1)), "folds": 4}
    cfg = {"coverage": 0.9, "scale": scale, "bins": 3}
    wide = ConformalInterval.from_dict(interval_form(cal, cfg))
    bare = ConformalInterval.from_dict(interval_form(cal, cfg, widen="none"))
    fitted = ConformalInterval.from_dict(interval_form(cal, cfg, widen="fitted"))
    k_hi = cal["stiffness"].max()
    assert wide.stiffness_range == (cal["stiffness"].min(), k_hi) and bare.stiffness_range is None
    assert wide.widen == "proportional" and fitted.widen == "fitted" and len(fitted.stiffness_exponent) == 3
    f = pred[:5]
    inside, outside = np.full((5, 1), 1.0), np.full((5, 1), 1.4)
    np.testing.assert_allclose(bare.half_widths(inside, f), wide.half_widths(inside, f))  # inside: unchanged
    np.testing.assert_allclose(fitted.half_widths(inside, f), wide.half_widths(inside, f))
    np.testing.assert_allclose(bare.half_widths(outside, f), bare.half_widths(inside, f))  # no widening
    np.testing.assert_allclose(wide.half_widths(outside, f), bare.half_widths(outside, f) * 1.4 / k_hi)
    g = np.clip(fitted.stiffness_exponent, 0.0, 1.0)  # residuals that do not grow with k: g near 0
    np.testing.assert_allclose(fitted.half_widths(outside, f), bare.half_widths(outside, f) * (1.4 / k_hi) ** g)


def test_interval_forms_score_every_scale_once_per_fold_count_and_force_bins_once_per_bin_count():
    forms = interval_forms([4, 8], ["force", "force_bins"], [3, 5])
    assert list(forms) == [(4, "force", None, "proportional", None), (4, "force_bins", 3, "proportional", None),
                           (4, "force_bins", 5, "proportional", None), (8, "force", None, "proportional", None),
                           (8, "force_bins", 3, "proportional", None), (8, "force_bins", 5, "proportional", None)]
    assert forms[(8, "force_bins", 5, "proportional", None)] == "force_bins:5 8 folds"
    both = interval_forms([4], ["none"], [5], ["proportional", "fitted", "none"])
    assert both == {(4, "none", None, "proportional", None): "none 4 folds",
                    (4, "none", None, "fitted", None): "none 4 folds widen fitted",
                    (4, "none", None, "none", None): "none 4 folds unwidened"}
    spread = interval_forms([4], ["force_bins"], [5], ["fitted"], [None, 4.0])
    assert spread == {(4, "force_bins", 5, "fitted", None): "force_bins:5 4 folds widen fitted",
                      (4, "force_bins", 5, "fitted", 4.0): "force_bins:5 4 folds widen fitted spread 4"}


def test_stiffness_factors_are_the_first_constant_over_its_mean():
    arrays = {"material_params_mpa": np.array([[0.001, 0.01, 0.0], [0.003, 0.02, 0.0]])}
    np.testing.assert_allclose(stiffness_factors(arrays), [0.5, 1.5])
