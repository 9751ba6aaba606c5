"""The validation's band on an interval's coverage measured on a few livers (pipeline.validate.coverage_band_by_liver).

A liver's cases share its shape and material, so the band is over livers, not cases: it must hold the population's
coverage about 95 % of the time when livers differ, which a band over independent cases would not.
"""

import numpy as np
from scipy.stats import t

from liverforce.pipeline.validate import coverage_band_by_liver


def _livers(rng, n_livers, n_cases, mean, spread):
    """Per-liver coverage of three components: each liver's own hit rate drawn round ``mean``, then its cases."""
    p = np.clip(rng.normal(mean, spread, size=(n_livers, 3)), 0.0, 1.0)
    return {f"val-{k}": list(rng.binomial(n_cases, p[k]) / n_cases) for k in range(n_livers)}


def test_the_band_is_the_livers_mean_plus_minus_t_times_their_standard_error():
    per = {"a": [0.9, 0.8, 1.0], "b": [1.0, 0.9, 1.0], "c": [0.8, 0.85, 0.95]}
    got = np.array(coverage_band_by_liver(per))
    cov = np.array(list(per.values()))
    half = t.ppf(0.975, 2) * cov.std(axis=0, ddof=1) / np.sqrt(3)
    want = np.stack([np.maximum(cov.mean(0) - half, 0.0), np.minimum(cov.mean(0) + half, 1.0)], axis=1)
    np.testing.assert_allclose(got, want, rtol=1e-12)
    assert got[2, 1] == 1.0  # clipped at full coverage
    same = coverage_band_by_liver({"a": [0.9, 0.9, 0.9], "b": [0.9, 0.9, 0.9]})
    np.testing.assert_allclose(same, [[0.9, 0.9]] * 3)  # livers that agree leave no doubt
    assert coverage_band_by_liver({"a": [0.9, 0.9, 0.9]}) is None  # one liver: no spread to measure


def test_the_band_holds_the_population_coverage_about_95_percent_of_the_time():
    """8 livers x 30 cases, livers whose own coverage differs by 4 points (sd): the population's 0.9 is inside
    the band in 91-98 % of 1,000 draws (binomial sd of that rate 0.7 points); a band that treats the 240 cases as
    independent is too narrow and holds it less often."""
    rng = np.random.default_rng(0)
    inside, naive = 0, 0
    draws = 1000
    for _ in range(draws):
        per = _livers(rng, 8, 30, 0.9, 0.04)
        band = np.array(coverage_band_by_liver(per))
        inside += int(np.sum((band[:, 0] <= 0.9) & (0.9 <= band[:, 1])))
        pooled = np.array(list(per.values())).mean(0)
        se = np.sqrt(pooled * (1 - pooled) / 240)
        naive += int(np.sum(np.abs(pooled - 0.9) <= 1.96 * se))
    rate, naive_rate = inside / (3 * draws), naive / (3 * draws)
    assert 0.91 <= rate <= 0.98, rate
    assert naive_rate < rate - 0.03, (naive_rate, rate)
