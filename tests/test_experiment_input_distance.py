"""benchmarks/experiment_input_distance.py: a GP member's posterior sd (zero at its data, the prior's far from it).
The nearest training case's distance, its own liver left out, is liverforce.learn.gp.nearest_scaled's
(tests/learn/test_input_distance.py)."""
from __future__ import annotations

import numpy as np
import torch

from benchmarks.experiment_input_distance import posterior_sd
from liverforce.learn.gp import GPRegressor


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
