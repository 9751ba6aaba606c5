"""Splits (no leakage) and metric formulas (hand-computed)."""

import numpy as np
import pytest

from liverforce.learn.metrics import METRIC_NAMES, force_metrics
from liverforce.learn.scaling import Standardizer
from liverforce.learn.splits import cv_folds, train_test_split


def geometries(n_geo: int, per: int) -> np.ndarray:
    return np.array([f"g{g}" for g in range(n_geo) for _ in range(per)], dtype=object)


def test_scenario_iv_splits_by_geometry_without_leakage():
    geo = geometries(7, 10)
    tr, te = train_test_split(geo, scenario="IV", test_fraction=0.3, seed=1)
    assert set(geo[tr]).isdisjoint(geo[te])
    assert len(set(geo[te])) == 2  # round(0.3 * 7)
    assert sorted(np.concatenate([tr, te]).tolist()) == list(range(70))
    folds = cv_folds(tr, geo, scenario="IV", folds=3, seed=1)
    assert folds.grouping == "geometry" and len(folds.pairs) == 3
    seen_val = []
    for ftr, fva in folds.pairs:
        assert set(geo[ftr]).isdisjoint(geo[fva])  # no geometry in both
        assert set(fva) <= set(tr) and set(ftr) <= set(tr)  # test split never used
        assert set(ftr).isdisjoint(fva)
        seen_val += fva.tolist()
    assert sorted(seen_val) == sorted(tr.tolist())  # every training case validated once


def test_case_split_for_scenarios_i_to_iii():
    geo = geometries(1, 50)
    tr, te = train_test_split(geo, scenario="II", test_fraction=0.2, seed=0)
    assert len(te) == 10 and set(tr).isdisjoint(te)
    again = train_test_split(geo, scenario="II", test_fraction=0.2, seed=0)
    np.testing.assert_array_equal(te, again[1])  # deterministic
    assert not np.array_equal(te, train_test_split(geo, scenario="II", test_fraction=0.2, seed=1)[1])
    folds = cv_folds(tr, geo, scenario="II", folds=4, seed=0)
    assert folds.grouping == "case" and len(folds.pairs) == 4
    assert all(set(f[1]) <= set(tr) for f in folds.pairs)


def test_grouped_cv_with_one_training_geometry_falls_back_visibly():
    geo = geometries(2, 6)
    tr, te = train_test_split(geo, scenario="IV", test_fraction=0.2, seed=0)
    folds = cv_folds(tr, geo, scenario="IV", folds=2, seed=0)
    assert folds.grouping.startswith("case (fallback")
    assert folds.notes


def test_scenario_iv_needs_two_geometries():
    with pytest.raises(ValueError, match="at least 2"):
        train_test_split(geometries(1, 10), scenario="IV", test_fraction=0.2, seed=0)


def test_metrics_hand_computed():
    true = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, -4.0]])
    pred = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 1.0], [3.0, 0.0, 0.0]])
    # errors: (0,0,0), (0,0,1), (3,0,4): norms 0, 1, 5; sum |F| = 1 + 2 + 4 = 7
    m = force_metrics(true, pred)
    assert set(m) == set(METRIC_NAMES)
    assert m["mae_x"] == pytest.approx(1.0)
    assert m["mae_y"] == pytest.approx(0.0)
    assert m["mae_z"] == pytest.approx(5.0 / 3)
    assert m["mae_vec"] == pytest.approx(2.0)
    assert m["rmse_x"] == pytest.approx(np.sqrt(3.0))
    assert m["rmse_z"] == pytest.approx(np.sqrt(17.0 / 3))
    assert m["rmse_vec"] == pytest.approx(np.sqrt(26.0 / 3))
    assert m["accuracy_pct"] == pytest.approx(100 * (1 - 6.0 / 7.0))
    assert force_metrics(true, true)["accuracy_pct"] == 100.0


def test_standardizer_grouped_scale_and_round_trip():
    x = np.array([[0.0, 0.0, 5.0], [2.0, 4.0, 5.0]])
    s = Standardizer.fit(x, groups=np.array([0, 0, 1]))
    # group 0 pools the deviations (+-1, +-2): rms = sqrt(2.5); the constant column keeps scale 1
    np.testing.assert_allclose(s.scale, [np.sqrt(2.5), np.sqrt(2.5), 1.0])
    np.testing.assert_allclose(s.inverse_transform(s.transform(x)), x)
    t = Standardizer.from_dict(s.to_dict())
    np.testing.assert_array_equal(t.mean, s.mean)
    np.testing.assert_array_equal(t.scale, s.scale)


def test_standardizer_scales_small_columns_beside_huge_ones():
    import numpy as np

    from liverforce.learn.scaling import Standardizer

    rng = np.random.default_rng(0)
    x = np.column_stack([4e9 + 1e8 * rng.normal(size=50), 0.0016 + 3e-4 * rng.normal(size=50), np.full(50, 2.0)])
    s = Standardizer.fit(x)
    z = s.transform(x)
    np.testing.assert_allclose(z[:, :2].std(axis=0), 1.0, rtol=1e-12)  # material column is standardised
    assert s.scale[2] == 1.0 and np.all(z[:, 2] == 0.0)  # a constant column stays 0


def test_cv_force_mae_scores_the_same_fits_in_newtons():
    """cv_force_mae refits each fold as cv_score does (same seeds) and maps the outputs back to N."""
    from liverforce.learn.regressor import FitParams, fit_regressor, predict_regressor
    from liverforce.learn.tune import FoldData, cv_force_mae, fold_seed, regressor_from_params

    rng = np.random.default_rng(0)
    z = rng.normal(size=(120, 4))
    y = z[:, :3] * 0.5
    folds = [FoldData(z[:80], y[:80], z[80:], y[80:]), FoldData(z[40:], y[40:], z[:40], y[:40])]
    scale = np.array([2.0, 3.0, 4.0])  # "newtons" = scaled output x scale + 1
    to_n = [lambda out: out * scale + 1.0] * 2
    truth = [f.y_val * scale + 1.0 for f in folds]
    params = {"width": 16, "n_layers": 1, "dropout": 0.0, "lr": 0.01, "batch_size": 16}
    got = cv_force_mae(folds, to_n, truth, params, epochs=30, seed=5)
    manual = []
    for k, f in enumerate(folds):
        net, _ = fit_regressor(f.z_train, f.y_train, regressor_from_params(params, 4),
                               FitParams(lr=0.01, batch_size=16, epochs=30), seed=fold_seed(5, k))
        manual.append(np.linalg.norm(predict_regressor(net, f.z_val) * scale + 1.0 - truth[k], axis=1).mean())
    assert got == pytest.approx(np.mean(manual), rel=1e-12)
    assert 0 < got < 0.5 * np.linalg.norm(truth[0] - truth[0].mean(0), axis=1).mean()  # it learned something
