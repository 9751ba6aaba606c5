"""Metrics per unseen liver and per force bin (validation)."""
import numpy as np
import pytest


def test_metrics_by_group_weighs_each_liver_equally_and_names_the_worst():
    from liverforce.learn.metrics import metrics_by_group

    t = np.array([[1.0, 0, 0]] * 4 + [[0, 2.0, 0]] * 2)
    p = t.copy()
    p[:4, 0] += 0.1          # liver a: error 0.1 N on 4 cases
    p[4:, 1] -= 0.5          # liver b: error 0.5 N on 2 cases
    g = ["a"] * 4 + ["b"] * 2
    out = metrics_by_group(t, p, g)
    assert out["n_groups"] == 2 and out["worst"] == "b"
    assert out["per_group"]["a"]["n"] == 4 and out["per_group"]["a"]["mae_vec"] == pytest.approx(0.1)
    assert out["mean"]["mae_vec"] == pytest.approx(0.3)          # (0.1 + 0.5) / 2, not case-weighted (0.233)
    assert out["sd"]["mae_vec"] == pytest.approx(np.std([0.1, 0.5], ddof=1))
    assert out["mean"]["accuracy_pct"] == pytest.approx((90.0 + 75.0) / 2)


def test_error_by_force_bin_shows_a_bias_towards_a_constant():
    from liverforce.learn.metrics import error_by_force_bin

    mags = np.linspace(0.1, 5.0, 50)
    t = np.column_stack([mags, 0 * mags, 0 * mags])
    p = np.full_like(t, 0.0)
    p[:, 0] = 2.5            # always predicts 2.5 N
    bins = error_by_force_bin(t, p, n_bins=5)
    assert sum(b["n"] for b in bins) == 50 and len(bins) == 5
    assert bins[0]["relative_mae"] > 2.0          # small forces: error several times the force
    assert bins[2]["relative_mae"] < 0.2          # around the constant: small
    for b in bins:
        assert b["force_lo_n"] <= b["mean_force_n"] <= b["force_hi_n"]
        assert b["mae_vec_n"] == pytest.approx(b["relative_mae"] * b["mean_force_n"])
