"""Train/test splits and k-fold cross-validation folds, leak-free by construction.

- Scenarios I-III: split by case (a case is in train or test, never both).
- Scenario IV (and any scenario with ``group_by="geometry"``): split by
  geometry, so no liver appears in both train and test, and the CV folds
  inside the training split are grouped by geometry as well.
- The test split is drawn once from the seed and is never seen by tuning: CV
  folds partition the training indices only.

Grouped CV needs at least 2 training geometries; with fewer folds than
geometries the fold count is reduced to the number of geometries, and with a
single training geometry the folds fall back to case level (reported in
:attr:`Folds.grouping`, so it is visible in the results).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from liverforce.seeds import derive

GROUPED_SCENARIOS = ("IV",)


def group_key(scenario: str) -> str:
    """``geometry`` for scenario IV, else ``case``."""
    return "geometry" if scenario in GROUPED_SCENARIOS else "case"


@dataclass
class Folds:
    """CV folds: ``(train_idx, val_idx)`` pairs indexing the *full* arrays."""

    pairs: list[tuple[np.ndarray, np.ndarray]]
    grouping: str
    notes: list[str] = field(default_factory=list)


def _one_liver_message(scenario: str, groups) -> str:
    """Why a split by liver is impossible, and the config that gives the scenario a second liver.

    The training livers are ``geometry.procedural.count`` procedural ones (``proc-``), those of
    ``geometry.imported`` (``imp-``) and the cube: the procedural count that suffices is 2 minus the
    others in the data (``liverforce.config`` refuses such a config before any job; here the data
    itself has one liver, e.g. every case of the others failed)."""
    groups = [str(g) for g in groups]
    n_imp = sum(1 for g in groups if g.startswith("imp-"))
    others = n_imp + int("cube" in groups)
    need = max(1, 2 - others)
    named = ([f"the {n_imp} imported liver{'s' * (n_imp != 1)}"] if n_imp else []) + \
        (["the cube"] if "cube" in groups else [])
    besides = f" beside {' and '.join(named)}" if named else ""
    return (f"scenario {scenario} splits by geometry but the data has only {len(groups)} geometry "
            f"({', '.join(groups)}); it needs at least 2: sweep.scenarios.{scenario}.geometries: all and a "
            f"second training liver (geometry.procedural.count >= {need}{besides}, or a second entry in "
            f"geometry.imported); if the config has 2 or more, every case of the others failed (see the "
            "simulate logs)")


def train_test_split(
    geometry_ids: np.ndarray, *, scenario: str, test_fraction: float, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """Indices ``(train, test)`` (sorted) of a held-out test split.

    By case: ``max(1, round(f n))`` random cases (at most ``n - 2``) go to test.
    By geometry (scenario IV): ``max(1, round(f G))`` random geometries (at most
    ``G - 1``) go to test with all their cases.
    """
    geo = np.asarray(geometry_ids).astype(str)
    n = len(geo)
    rng = np.random.default_rng(derive(seed, "split.test"))
    if group_key(scenario) == "geometry":
        groups = np.unique(geo)
        if len(groups) < 2:
            raise ValueError(_one_liver_message(scenario, groups))
        k = int(min(max(1, round(test_fraction * len(groups))), len(groups) - 1))
        test_groups = rng.permutation(groups)[:k]
        is_test = np.isin(geo, test_groups)
    else:
        if n < 3:
            raise ValueError(f"scenario {scenario}: {n} converged cases are too few to split (need >= 3)")
        k = int(min(max(1, round(test_fraction * n)), n - 2))
        is_test = np.zeros(n, dtype=bool)
        is_test[rng.permutation(n)[:k]] = True
    return np.flatnonzero(~is_test), np.flatnonzero(is_test)


def cv_folds(
    train_idx: np.ndarray, geometry_ids: np.ndarray, *, scenario: str, folds: int, seed: int
) -> Folds:
    """k-fold CV inside the training indices (grouped by geometry for scenario IV)."""
    train_idx = np.asarray(train_idx)
    geo = np.asarray(geometry_ids).astype(str)[train_idx]
    rng = np.random.default_rng(derive(seed, "split.cv"))
    notes: list[str] = []
    grouping = group_key(scenario)
    if grouping == "geometry":
        groups = np.unique(geo)
        if len(groups) >= 2:
            k = min(int(folds), len(groups))
            if k < folds:
                notes.append(f"folds reduced from {folds} to {k}: only {len(groups)} training geometries")
            parts = np.array_split(rng.permutation(groups), k)
            pairs = []
            for part in parts:
                va = np.isin(geo, part)
                pairs.append((train_idx[~va], train_idx[va]))
            return Folds(pairs, "geometry", notes)
        notes.append("only one training geometry: CV folds fall back to case level")
        grouping = "case (fallback: one training geometry)"
    n = len(train_idx)
    k = min(int(folds), n)
    if k < 2:
        raise ValueError(f"cannot build {folds} CV folds from {n} training cases")
    parts = np.array_split(rng.permutation(n), k)
    pairs = []
    for part in parts:
        va = np.zeros(n, dtype=bool)
        va[part] = True
        pairs.append((train_idx[~va], train_idx[va]))
    return Folds(pairs, grouping, notes)
