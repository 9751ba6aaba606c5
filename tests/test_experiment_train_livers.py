"""The learning-curve experiment's subsets: whole livers, the same number of cases from each, seeded."""

import numpy as np

from benchmarks.experiment_train_livers import liver_subset


def _geo():
    return np.repeat([f"proc-{i:04d}" for i in range(6)], [10, 10, 10, 10, 10, 4])


def test_a_subset_takes_whole_livers_and_is_seeded():
    geo = _geo()
    rows = liver_subset(geo, 3, 0, np.random.default_rng(7))
    kept = sorted(set(geo[rows]))
    assert len(kept) == 3
    assert np.array_equal(rows, np.flatnonzero(np.isin(geo, kept)))  # every case of a kept liver, nothing else
    assert np.array_equal(rows, liver_subset(geo, 3, 0, np.random.default_rng(7)))


def test_cases_per_liver_are_capped_by_what_a_liver_has():
    geo = _geo()
    rows = liver_subset(geo, 6, 5, np.random.default_rng(1))
    counts = {g: int(np.sum(geo[rows] == g)) for g in set(geo)}
    assert counts == {**{f"proc-{i:04d}": 5 for i in range(5)}, "proc-0005": 4}
    assert np.all(np.diff(rows) > 0)  # sorted, no case twice
