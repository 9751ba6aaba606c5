"""benchmarks/experiment_input_distance.py: the nearest training case's distance, its own liver left out, and a GP
member's posterior sd (zero at its data, the prior's far from it)."""
from __future__ import annotations

import numpy as np
import torch

from benchmarks.experiment_input_distance import nearest, posterior_sd
from liverforce.learn.gp import GPRegressor


def test_nearest_is_the_brute_force_minimum_with_the_excluded_pairs_left_out():
    rng = np.random.default_rng(3)
    A, B = rng.normal(size=(30, 4)), rng.normal(size=(50, 4))
    group_a, group_b = rng.integers(0, 5, 30), rng.integers(0, 5, 50)
    exclude = group_a[:, None] == group_b[None, :]
    got = nearest(A, B, exclude=exclude)
    want = [min(np.linalg.norm(a - b) for b, gb in zip(B, group_b) if gb != ga) for a, ga in zip(A, group_a)]
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(nearest(A, A), 0.0, atol=1e-6)  # a point is its own nearest without the exclusion


def test_posterior_sd_vanishes_at_the_data_and_is_the_prior_sd_far_from_it():
    rng = np.random.default_rng(0)
    X = torch.as_tensor(rng.uniform(-1, 1, size=(40, 3)))
    signal_var = 0.7
    g = GPRegressor(X, torch.zeros(40, 1), torch.full((3,), 2.0), torch.tensor(signal_var), torch.tensor(0.0),
                    torch.tensor(1e-8), shape=2.0)
    at_data = posterior_sd(g, X.numpy()[:5])
    far = posterior_sd(g, np.full((2, 3), 50.0))
    mid = posterior_sd(g, X.numpy()[:5] + 0.3)
    assert at_data.max() < 1e-3
    np.testing.assert_allclose(far, np.sqrt(signal_var), rtol=1e-3)
    assert (mid > at_data).all() and (mid < np.sqrt(signal_var)).all()
