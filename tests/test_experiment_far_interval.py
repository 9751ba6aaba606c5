"""benchmarks/experiment_far_interval.py: the Mondrian factors are each group's split-conformal quantile, and on
exchangeable scores they bring each group's coverage to the nominal one."""
from __future__ import annotations

import math

import numpy as np

from benchmarks.experiment_far_interval import mondrian_factors


def test_each_groups_factor_is_its_own_conformal_quantile_and_covers_it():
    rng = np.random.default_rng(0)
    n = 4000
    far = rng.random(n) < 0.1
    scale = np.where(far, 1.8, 0.9)[:, None]  # the far cases' scores larger, as the calibration's are
    s = np.abs(rng.normal(size=(n, 3))) * scale
    fk, nk = mondrian_factors(s, far, 0.9)
    k = math.ceil((far.sum() + 1) * 0.9)
    np.testing.assert_array_equal(fk, np.sort(s[far], axis=0)[k - 1])
    assert (fk > nk).all()
    fresh_far = rng.random(n) < 0.1
    t = np.abs(rng.normal(size=(n, 3))) * np.where(fresh_far, 1.8, 0.9)[:, None]
    for grp, fac in ((fresh_far, fk), (~fresh_far, nk)):
        cov = (t[grp] <= fac).mean(axis=0)
        assert np.all(np.abs(cov - 0.9) < 0.04)  # binomial sd on ~400 far cases: 1.5 points
    assert (t[fresh_far] <= 1.0).mean() < 0.6  # without the factor the far cases are under-covered


def test_a_group_too_small_to_bound_the_quantile_gets_an_unbounded_factor():
    s = np.ones((20, 3))
    far = np.zeros(20, dtype=bool)
    far[:3] = True
    fk, nk = mondrian_factors(s, far, 0.9)
    assert np.isinf(fk).all() and np.isfinite(nk).all()
