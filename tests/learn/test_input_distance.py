"""The input-distance flag (liverforce.learn.interval, train.interval.distance_quantile): a GP's distance from a
case's inputs to its nearest training row, in the kernel's length scales, against a brute-force distance; the
compiled heads read the same distance off their kernel matrix without changing a force; the threshold is the
calibration cases' quantile, each measured by the fold model that did not see it; and a case shifted away from
the training inputs is flagged while cases drawn like the training rows mostly are not."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from liverforce.learn.gp import GPEnsemble, fit_gp, fit_gp_ensemble, nearest_scaled
from liverforce.learn.interval import distance_flags, fit_input_distance
from liverforce.learn.model import ForceModel
from liverforce.learn.synthetic import synthetic_arrays
from liverforce.learn.train import train_scenario

torch.set_num_threads(1)


def truth(X: np.ndarray) -> np.ndarray:
    return np.stack([np.sin(X[:, 0]) + 0.5 * X[:, 1], 0.5 * X[:, 2] ** 2, 0.3 * X[:, 3] - 0.2 * X[:, 1]], axis=1)


def brute(z: np.ndarray, X: np.ndarray, inv_length: np.ndarray) -> np.ndarray:
    """Each row's distance to the nearest training row, one pair at a time (no matrix identity)."""
    return np.array([min(np.sqrt(np.sum(((zi - xj) * inv_length) ** 2)) for xj in X) for zi in z])


@pytest.fixture(scope="module")
def ensemble():
    rng = np.random.default_rng(0)
    X = rng.uniform(-2, 2, (150, 5))
    gp, _ = fit_gp_ensemble(X, truth(X), [np.array([0, 1, 2]), np.array([0, 1, 2, 3, 4])], seed=0, iterations=40)
    return X, gp


def test_the_distance_is_the_nearest_training_row_in_each_members_length_scales(ensemble):
    X, gp = ensemble
    z = np.random.default_rng(1).uniform(-3, 3, (25, 5))
    each = [brute(z[:, gp.columns(i).numpy()], m.X.numpy(), m.inv_length.numpy()) for i, m in enumerate(gp.members)]
    np.testing.assert_allclose(gp.nearest_distance(z), np.mean(each, axis=0), rtol=1e-9)
    np.testing.assert_allclose(gp.members[1].nearest_distance(z), each[1], rtol=1e-9)
    assert np.allclose(gp.nearest_distance(X[:10]), 0.0, atol=1e-6)  # a training row is at distance 0
    # the length scales matter: a member with longer scales measures the same gap as shorter
    assert not np.allclose(each[0], brute(z[:, :3], X[:, :3], np.ones(3)), rtol=1e-3)


def test_nearest_scaled_in_blocks_is_the_whole_matrix():
    rng = np.random.default_rng(2)
    A, B = rng.normal(size=(37, 4)), rng.normal(size=(20, 4))
    np.testing.assert_allclose(nearest_scaled(A, B, block=5), brute(A, B, np.ones(4)), rtol=1e-10)


def test_nearest_scaled_leaves_out_the_rows_of_the_same_group():
    """With labels, each row's nearest is among the other groups' rows (a case against the other livers), in
    blocks as whole; inf for a row whose group holds every row of ``B``."""
    rng = np.random.default_rng(3)
    A, B = rng.normal(size=(30, 4)), rng.normal(size=(50, 4))
    group_a, group_b = rng.integers(0, 5, 30), rng.integers(0, 5, 50)
    got = nearest_scaled(A, B, block=7, groups_a=group_a, groups_b=group_b)
    want = [min(np.linalg.norm(a - b) for b, gb in zip(B, group_b) if gb != ga) for a, ga in zip(A, group_a)]
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(nearest_scaled(A, A), 0.0, atol=1e-6)  # a row is its own nearest without labels
    assert np.isinf(nearest_scaled(A[:2], B, groups_a=[9, 9], groups_b=np.full(50, 9))).all()
    with pytest.raises(ValueError, match="labels of both"):
        nearest_scaled(A, B, groups_a=group_a)


@pytest.mark.parametrize("members", [False, True])
def test_the_heads_distance_is_the_modules_and_leaves_the_force_unchanged(ensemble, members):
    X, gp = ensemble
    z = np.random.default_rng(3).uniform(-3, 3, (40, 5))
    plain = gp.numpy_head(members=members)(z)
    got = gp.numpy_head(members=members, distance=True)(z)
    assert len(got) == (3 if members else 2)
    for a, b in zip(plain if members else (plain,), got[:-1]):
        np.testing.assert_array_equal(a, b)  # the same bits: the distance only reads the kernel matrix
    np.testing.assert_allclose(got[-1], gp.nearest_distance(z), rtol=1e-9, atol=1e-12)
    # with fixed inputs (a compiled context's state) the fixed columns' share is in every row's distance
    fixed = {3: 0.4, 4: -1.1}
    zf = z.copy()
    zf[:, 3], zf[:, 4] = 0.4, -1.1
    got_f = gp.numpy_head(fixed, members=members, distance=True)(z[:, :3])
    np.testing.assert_allclose(got_f[-1], gp.nearest_distance(zf), rtol=1e-9, atol=1e-12)


def test_a_per_output_gp_averages_its_outputs_distances():
    rng = np.random.default_rng(4)
    X = rng.uniform(-2, 2, (120, 5))
    gp, _ = fit_gp(X, truth(X), seed=0, iterations=30, kernel="squared_exponential", per_output=True)
    z = rng.uniform(-3, 3, (15, 5))
    il = gp.inv_length.numpy()
    want = np.mean([brute(z, X, il[k]) for k in range(3)], axis=0)
    assert np.ptp(il, axis=0).max() > 1e-3  # the outputs' length scales differ, so the mean is not one of them
    np.testing.assert_allclose(gp.nearest_distance(z), want, rtol=1e-9)
    out, near = gp.numpy_head(distance=True)(z)
    np.testing.assert_array_equal(out, gp.numpy_head()(z))
    np.testing.assert_allclose(near, want, rtol=1e-9, atol=1e-12)


def test_the_threshold_is_the_calibration_quantile_and_bad_quantiles_are_refused():
    d = np.random.default_rng(5).gamma(2.0, 0.2, 500)
    rec = fit_input_distance(np.append(d, np.nan), 0.9)  # a calibration case without a distance is left out
    assert rec["threshold"] == pytest.approx(np.quantile(d, 0.9)) and rec["n_calibration"] == 500
    assert rec["calibration_quantiles"]["0.99"] == pytest.approx(np.quantile(d, 0.99))
    assert distance_flags(d, rec).mean() == pytest.approx(0.1, abs=0.005)
    assert not distance_flags(d, None).any() and not distance_flags([np.nan], rec).any()
    for q in (0.3, 1.0, 1.5):
        with pytest.raises(ValueError, match="distance_quantile"):
            fit_input_distance(d, q)
    with pytest.raises(ValueError, match="no finite"):
        fit_input_distance([np.nan], 0.9)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A node GP ensemble model on 4 synthetic livers with a cross-conformal interval and the input-distance flag."""
    arrays = synthetic_arrays(120, n_geometries=4, seed=2, nodes=(160, 220), material_varies=True)
    model = {"encoder": "pca", "code_size": 6, "state_vector": True, "grid_size": 8, "hidden": [16], "dropout": 0.0,
             "occlusion": {"radius_mm": 0.0, "mode": "remove"}, "noise_mm": 0.0, "regressor": "gp",
             "gp": {"max_points": 2000, "iterations": 40, "code_members": [3, 6]}}
    train = {"test_fraction": 0.25, "epochs": 1, "batch_size": 32, "lr": 3e-3, "weight_decay": 0.0, "seed": 0,
             "interval": {"coverage": 0.9, "calibration_fraction": 0.25, "folds": 3, "scale": "none",
                          "distance_quantile": 0.8}}
    tune = {"enabled": False, "trials": 1, "folds": 2, "sobol_trials": 1, "epochs": 1}
    out = tmp_path_factory.mktemp("distance")
    res = train_scenario(arrays, model, train, tune, "IV", "gp", out_dir=out)
    return arrays, res, out


def test_training_fits_the_threshold_on_each_training_cases_distance_to_the_other_livers_rows(trained):
    """The threshold is the quantile of the training cases' distances, each (in its evaluation view) to the served
    GP's training rows of the other livers, measured here by brute force with the rows' livers found by matching
    them to the training views; the calibration's fold-model distances are kept beside it for comparison."""
    from liverforce.learn.model import eval_seed, n_views_for, prepare, regressor_data, subset, view_groups, view_seeds

    arrays, res, out = trained
    m = ForceModel.load(res["model_path"])
    rec = m.distance_flag
    assert rec["quantile"] == 0.8 and rec["left_out"] == "liver"
    test = set(m.meta["test_case_ids"])
    a = subset(arrays, [i for i, c in enumerate(arrays["case_id"]) if c not in test])
    rep = m.representation
    prep = prepare(a, rep, observation_seeds=view_seeds(0, n_views_for(rep)))
    z_all, _ = regressor_data(m.pre, prep)
    liver_of = {z_all[r].tobytes(): a["geometry_id"][k] for r, k in enumerate(view_groups(prep))}
    full = m.regressor.members[-1]  # the largest member reads every input column
    assert m.regressor.columns(len(m.regressor.members) - 1).numel() == z_all.shape[1]
    row_liver = np.array([liver_of[x.tobytes()] for x in full.X.numpy()])
    z_eval = np.float32(regressor_data(m.pre, prepare(a, rep, observation_seeds=[eval_seed(0)]),
                                       all_views=False)[0]).astype(np.float64)
    own = np.asarray(a["geometry_id"])
    each = []
    for i, g in enumerate(m.regressor.members):
        c = m.regressor.columns(i).numpy()
        il = g.inv_length.numpy()
        each.append([brute(z_eval[k:k + 1, c], g.X.numpy()[row_liver != own[k]], il)[0] for k in range(len(own))])
    d = np.mean(each, axis=0)
    assert rec["n_calibration"] == len(own)
    assert rec["threshold"] == pytest.approx(np.quantile(d, 0.8), rel=1e-9)
    assert rec["calibration_quantiles"]["0.5"] == pytest.approx(np.median(d), rel=1e-9)
    with np.load(out / "interval_calibration.npz") as z:
        fold = z["input_distance"]
        assert len(fold) == len(z["true_local"])
    assert rec["fold_quantiles"]["0.9"] == pytest.approx(np.quantile(fold, 0.9))
    # each calibration case was measured by a fold model that did not see it: none sits on a training row
    assert fold.min() > 1e-3
    # the split's test livers: how the flag splits them is in the result, from the served model's distances
    flag = res["interval"]["input_distance"]
    idx = [list(arrays["case_id"]).index(c) for c in m.meta["test_case_ids"]]
    dt = m.forward(subset(arrays, idx), observation_seed=eval_seed(0)).input_distance
    assert flag["n"] == len(idx) and flag["n_flagged"] == int((dt > rec["threshold"]).sum())


def test_a_case_far_from_the_training_inputs_is_flagged(trained):
    arrays, res, _ = trained
    m = ForceModel.load(res["model_path"])
    rec = m.distance_flag
    from liverforce.learn.model import eval_seed, subset

    test = [list(arrays["case_id"]).index(c) for c in m.meta["test_case_ids"]]
    a = subset(arrays, test)
    d = m.forward(a, observation_seed=eval_seed(0)).input_distance
    assert distance_flags(d, rec).mean() < 0.6  # cases like the training livers': most within the line
    # the same cases pressed deeper, to twice the largest displacement of any training case: a dent no training
    # case has (a small dent made three times deeper can be a training case's, so depth alone is not the test)
    train = [i for i in range(len(arrays["case_id"])) if i not in set(test)]

    def peak(k):
        return np.linalg.norm(np.asarray(arrays["roi_deformed_mm"][k]) - arrays["roi_undeformed_mm"][k], axis=1).max()

    top = max(peak(k) for k in train)
    f = np.array([2.0 * top / peak(k) for k in test])
    deep = {**a, "roi_deformed_mm": [u + g * (dd - u) for u, dd, g in zip(a["roi_undeformed_mm"],
                                                                          a["roi_deformed_mm"], f)],
            "roi_centroid_deformed_mm": a["roi_centroid_undeformed_mm"]
            + f[:, None] * (a["roi_centroid_deformed_mm"] - a["roi_centroid_undeformed_mm"])}
    d2 = m.forward(deep, observation_seed=eval_seed(0)).input_distance
    assert (d2 > d).all() and distance_flags(d2, rec).all()


def test_an_mlp_has_no_distance_and_no_flag(trained, tmp_path):
    arrays, res, _ = trained
    m = ForceModel.load(res["model_path"])
    assert isinstance(m.regressor, GPEnsemble)
    from liverforce.learn.regressor import RegressorSpec, build_mlp

    spec = RegressorSpec(m.pre.n_inputs, (8,), 0.0)
    mlp = ForceModel(m.representation, m.pre, spec, build_mlp(spec), m.meta)
    assert mlp.distance_flag is None and "input_distance" in mlp.meta
    assert mlp.forward(arrays, observation_seed=0).input_distance is None


def test_the_validation_counts_the_flagged_unseen_cases_and_their_error(trained):
    """``validate`` reports the flag on the unseen livers (liverforce.pipeline.validate.distance_flag_on_unseen):
    here the split's held-out livers stand in for them, with the threshold moved to their median distance."""
    import copy

    from liverforce.learn.model import eval_seed, subset
    from liverforce.pipeline.validate import LARGE_ERROR_N, interval_coverage

    arrays, res, _ = trained
    m = ForceModel.load(res["model_path"])
    a = subset(arrays, [list(arrays["case_id"]).index(c) for c in m.meta["test_case_ids"]])
    fw = m.forward(a, observation_seed=eval_seed(0))
    meta = copy.deepcopy(m.meta)
    meta["input_distance"]["threshold"] = float(np.median(fw.input_distance))
    moved = ForceModel(m.representation, m.pre, m.regressor_spec, m.regressor, meta)
    far = interval_coverage(moved, a)["input_distance"]
    f = fw.input_distance > meta["input_distance"]["threshold"]
    err = np.linalg.norm(fw.force_source - a["force_n"], axis=1)
    assert far["n_cases"] == len(f) and far["n_flagged"] == int(f.sum()) == len(f) // 2
    assert far["mae_flagged_n"] == pytest.approx(err[f].mean())
    assert far["mae_others_n"] == pytest.approx(err[~f].mean())
    assert far["n_large"] == int((err > LARGE_ERROR_N).sum()) and far["n_large_flagged"] == int((err[f] > 0.4).sum())
    geo = np.asarray(a["geometry_id"]).astype(str)
    assert far["per_liver"] == {g: int(f[geo == g].sum()) for g in sorted(set(geo))}
    assert len(far["coverage_flagged"]) == 3 and far["threshold"] == meta["input_distance"]["threshold"]
    meta.pop("input_distance")
    bare = ForceModel(m.representation, m.pre, m.regressor_spec, m.regressor, meta)
    assert interval_coverage(bare, a)["input_distance"] is None


def test_the_final_fit_measures_every_case_and_keeps_the_split_models_test_counts(tmp_path):
    """``train.final_fit``: the saved model's threshold rests on every case of the scenario (each against the other
    livers' rows of the model fitted on all of them); the main split's counts on its test livers are kept beside
    it. An MLP gets no flag and no note."""
    from liverforce.learn.model import eval_seed, n_views_for, prepare, training_distances, view_seeds

    arrays = synthetic_arrays(90, n_geometries=4, seed=5, nodes=(150, 200), material_varies=True)
    model = {"encoder": "pca", "code_size": 4, "state_vector": True, "grid_size": 6, "hidden": [16], "dropout": 0.0,
             "occlusion": {"radius_mm": 0.0, "mode": "remove"}, "noise_mm": 0.0, "regressor": "gp",
             "gp": {"max_points": 2000, "iterations": 30, "code_members": [2, 4]}}
    train = {"test_fraction": 0.25, "epochs": 2, "batch_size": 32, "lr": 3e-3, "weight_decay": 0.0, "seed": 0,
             "final_fit": True, "interval": {"coverage": 0.9, "calibration_fraction": 0.25, "folds": 3,
                                              "scale": "none", "distance_quantile": 0.9}}
    tune = {"enabled": False, "trials": 1, "folds": 2, "sobol_trials": 1, "epochs": 1}
    res = train_scenario(arrays, model, train, tune, "IV", "gp", out_dir=tmp_path / "gp")
    m = ForceModel.load(res["model_path"])
    rec = m.distance_flag
    assert m.meta["final_fit"] and rec["n_calibration"] == len(arrays["case_id"])
    rep = m.representation
    prep = prepare(arrays, rep, observation_seeds=view_seeds(0, n_views_for(rep)))
    d = training_distances(m, prep, prepare(arrays, rep, observation_seeds=[eval_seed(0)]),
                           arrays["geometry_id"], 0)
    assert rec["threshold"] == pytest.approx(np.quantile(d, 0.9), rel=1e-12)
    split = res["interval"]["split_input_distance"]
    assert split["n"] == len(m.meta["split_test_case_ids"]) and "n_flagged" in split
    with pytest.raises(RuntimeError, match="not the given training rows"):  # rows other than the fitted ones
        training_distances(m, prep.rows(np.arange(60)), prep, arrays["geometry_id"][:60], 0)
    mlp = train_scenario(arrays, {**model, "regressor": "mlp"}, {**train, "final_fit": False}, tune, "IV", "mlp",
                         out_dir=tmp_path / "mlp")
    m2 = ForceModel.load(mlp["model_path"])
    assert "input_distance" not in m2.meta and "input_distance" not in mlp["interval"]
    assert not any("input-distance" in n for n in mlp.get("notes", []))
