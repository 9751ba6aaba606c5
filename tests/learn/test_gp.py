"""The Gaussian-process regressor (liverforce.learn.gp, model.regressor: gp): it learns a known smooth map
from few noise-free samples, finds the inputs that matter, is reproducible, caps its training rows, and
a trained model with it round-trips through its bundle exactly. Both kernels (rational quadratic, squared
exponential): the closed-form likelihood gradient against autograd, the limit that joins them, the compiled
head against the module, and a bundle written before the kernel was a choice."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from liverforce.learn import gp as gp_module
from liverforce.learn.gp import JITTER, MIN_LENGTH, GPRegressor, _shape_kernel, fit_gp, neg_log_likelihood
from liverforce.learn.model import ForceModel
from liverforce.learn.regressor import fit_params
from liverforce.learn.synthetic import synthetic_arrays
from liverforce.learn.train import train_scenario
from liverforce.seeds import derive

torch.set_num_threads(1)


def truth(X: np.ndarray) -> np.ndarray:
    """Three outputs: a nonlinear one, a quadratic one and a linear one; input 4 is irrelevant."""
    return np.stack([np.sin(X[:, 0]) + 0.5 * X[:, 1], 0.5 * X[:, 2] ** 2, 0.3 * X[:, 3] - 0.2 * X[:, 1]], axis=1)


def test_the_closed_form_likelihood_gradient_is_the_exact_gaussian_likelihoods():
    """Value and gradient against an independent likelihood: torch's MultivariateNormal log density of each
    output column under the kernel, differentiated by autograd."""
    rng = np.random.default_rng(3)
    n, d = 120, 4
    X = torch.from_numpy(rng.normal(size=(n, d)))
    Y = torch.from_numpy(rng.normal(size=(n, 3)))
    raw = [torch.from_numpy(rng.normal(0.0, 0.5, d)), torch.tensor(0.3, dtype=torch.float64),
           torch.tensor(-0.7, dtype=torch.float64), torch.tensor(-1.2, dtype=torch.float64)]
    v, grads, alpha = neg_log_likelihood(X, Y, *raw)
    p = [r.clone().requires_grad_(True) for r in raw]
    a = X / (MIN_LENGTH + torch.exp(p[0]))
    _check_against_the_gaussian_density(X, Y, p, torch.exp(-0.5 * torch.cdist(a, a) ** 2), v, grads, alpha, rtol=1e-9)


def _check_against_the_gaussian_density(X, Y, p, stationary, v, grads, alpha, *, rtol):
    """``v``, ``grads`` and ``alpha`` against -log N(Y_j; 0, K) per row and output, differentiated by autograd,
    ``K = s_f^2 stationary + s_l^2 X X^T + (s_n^2 + jitter) I`` from the raw parameters ``p``."""
    n = len(X)
    K = (torch.exp(2 * p[1]) * stationary + torch.exp(2 * p[2]) * X @ X.T
         + (torch.exp(2 * p[3]) + JITTER) * torch.eye(n, dtype=torch.float64))
    mvn = torch.distributions.MultivariateNormal(torch.zeros(n, dtype=torch.float64), covariance_matrix=K)
    ref = -sum(mvn.log_prob(Y[:, j]) for j in range(Y.shape[1])) / (Y.shape[1] * n)
    ref.backward()
    assert v == pytest.approx(float(ref.detach()), rel=1e-12)
    assert len(grads) == len(p)
    for g, q in zip(grads, p):
        np.testing.assert_allclose(g.numpy(), q.grad.numpy(), rtol=rtol, atol=1e-12)
    np.testing.assert_allclose((K.detach() @ alpha).numpy(), Y.numpy(), atol=1e-8)


def test_the_rational_quadratic_likelihood_gradient_is_the_exact_gaussian_likelihoods():
    """The same check for the rational-quadratic kernel ``(1 + r^2 / (2 a))^-a``, its shape ``a`` included
    (the fifth raw parameter, ``log a``): the reference kernel is written from its definition."""
    rng = np.random.default_rng(4)
    n, d = 110, 4
    X = torch.from_numpy(rng.normal(size=(n, d)))
    Y = torch.from_numpy(rng.normal(size=(n, 3)))
    for log_a in (-1.5, 0.0, 1.2):
        raw = [torch.from_numpy(rng.normal(0.0, 0.5, d)), torch.tensor(0.2, dtype=torch.float64),
               torch.tensor(-0.9, dtype=torch.float64), torch.tensor(-1.0, dtype=torch.float64),
               torch.tensor(log_a, dtype=torch.float64)]
        v, grads, alpha = neg_log_likelihood(X, Y, *raw)
        p = [r.clone().requires_grad_(True) for r in raw]
        a = X / (MIN_LENGTH + torch.exp(p[0]))
        shape = torch.exp(p[4])
        rq = (1.0 + torch.cdist(a, a) ** 2 / (2.0 * shape)) ** (-shape)
        _check_against_the_gaussian_density(X, Y, p, rq, v, grads, alpha, rtol=1e-8)
        fixed = neg_log_likelihood(X, Y, *raw, shape_gradient=False)  # a fixed shape: the other four, the same
        assert fixed[0] == v and len(fixed[1]) == 4
        for g, h in zip(fixed[1], grads):
            np.testing.assert_array_equal(g.numpy(), h.numpy())


def test_the_shape_gradient_holds_where_the_kernel_is_nearly_the_squared_exponential():
    """At a large shape (a = 3e6, B = 1 + d2 / (2a) within 1e-6 of 1) the shape derivative's ``1 - 1/B - log B``
    loses its digits if ``1 - 1/B`` is formed first (this test fails that way), and autograd through the kernel
    cancels the same way: check it against a central difference of the likelihood's value, which log1p keeps
    exact."""
    rng = np.random.default_rng(6)
    X = torch.from_numpy(rng.normal(size=(80, 3)))
    Y = torch.from_numpy(rng.normal(size=(80, 2)))
    raw = [torch.from_numpy(rng.normal(0.0, 0.3, 3)), torch.tensor(0.1, dtype=torch.float64),
           torch.tensor(-0.8, dtype=torch.float64), torch.tensor(-1.1, dtype=torch.float64)]
    for log_a in (15.0, 2.0):
        _, grads, _ = neg_log_likelihood(X, Y, *raw, torch.tensor(log_a, dtype=torch.float64))
        h = 1e-3
        up = neg_log_likelihood(X, Y, *raw, torch.tensor(log_a + h, dtype=torch.float64), gradient=False)[0]
        down = neg_log_likelihood(X, Y, *raw, torch.tensor(log_a - h, dtype=torch.float64), gradient=False)[0]
        assert float(grads[4]) == pytest.approx((up - down) / (2 * h), rel=1e-4)


def test_the_rational_quadratic_tends_to_the_squared_exponential_and_has_heavier_tails():
    """``(1 + r^2 / (2 a))^-a -> exp(-r^2 / 2)`` as ``a`` grows (a scale mixture of squared exponentials); at any
    finite ``a`` it is above the squared exponential away from ``r = 0``, farther out the smaller ``a``."""
    d2 = torch.linspace(0.0, 30.0, 301, dtype=torch.float64)
    se = torch.exp(-0.5 * d2)
    np.testing.assert_allclose(_shape_kernel(d2, 1e9).numpy(), se.numpy(), rtol=1e-6, atol=1e-300)
    np.testing.assert_array_equal(_shape_kernel(d2, float("inf")).numpy(), se.numpy())
    k1, k2 = _shape_kernel(d2, 1.0), _shape_kernel(d2, 2.0)
    assert float(k1[0]) == float(k2[0]) == 1.0
    assert bool((k1[1:] > k2[1:]).all() and (k2[1:] > se[1:]).all())
    np.testing.assert_allclose(k1.numpy(), 1.0 / (1.0 + d2.numpy() / 2.0), rtol=1e-12)  # a = 1: Cauchy-like


@pytest.fixture(scope="module")
def fitted():
    rng = np.random.default_rng(0)
    X = rng.uniform(-2, 2, (250, 5))
    gp, info = fit_gp(X, truth(X), seed=0)
    return X, gp, info


def test_learns_a_smooth_map_from_noise_free_samples(fitted):
    X, gp, _ = fitted
    Xt = np.random.default_rng(1).uniform(-1.8, 1.8, (300, 5))
    err = gp(torch.from_numpy(Xt)).numpy() - truth(Xt)
    rmse = np.sqrt(np.mean(err**2, axis=0))
    assert (rmse < 0.01 * truth(Xt).std(axis=0)).all(), rmse  # < 1 % of each output's spread
    # noise-free targets are interpolated
    np.testing.assert_allclose(gp(torch.from_numpy(X)).numpy(), truth(X), atol=1e-3)


def test_ard_finds_the_irrelevant_input(fitted):
    _, _, info = fitted
    ls = np.asarray(info["length_scales"])
    # input 4 enters no output: its length scale is far longer than those of the inputs 0 and 2 (nonlinear)
    assert ls[4] > 100 * max(ls[0], ls[2])


def test_numpy_head_equals_the_module(fitted):
    X, gp, _ = fitted
    Xt = np.random.default_rng(2).uniform(-2, 2, (64, 5))
    head = gp.numpy_head()
    np.testing.assert_allclose(head(Xt), gp(torch.from_numpy(Xt)).numpy(), rtol=0, atol=1e-6)
    np.testing.assert_array_equal(head(np.asfortranarray(Xt[::2])), head(Xt[::2]))  # any memory layout
    assert head(Xt[:0]).shape == (0, 3)
    for bad in (Xt[0], Xt[:, :4]):  # one row without its row axis, or too few inputs: an error, not a guess
        with pytest.raises(ValueError, match="rows of 5 inputs"):
            head(bad)


def test_numpy_head_with_fixed_inputs_equals_the_module_on_rows_with_those_inputs(fitted):
    """``numpy_head(fixed)`` (a compiled context's state held in the head) takes the other columns and gives
    the module's posterior mean of the full rows, also at and next to training inputs (distances cancel; the
    module's own rounding there is ~1e-7 with this fit's large weights, hence the siblings' 1e-6)."""
    X, gp, _ = fitted
    rng = np.random.default_rng(3)
    k = 7
    fixed = {1: float(X[k, 1]), 3: float(X[k, 3])}
    free = [0, 2, 4]
    head = gp.numpy_head(fixed)
    for Z in (np.repeat(X[k:k + 1], 8, 0) + rng.normal(0, 1e-3, (8, 5)), X[k:k + 1], rng.uniform(-2, 2, (64, 5))):
        Z = Z.copy()
        Z[:, 1], Z[:, 3] = fixed[1], fixed[3]
        np.testing.assert_allclose(head(Z[:, free]), gp(torch.from_numpy(Z)).numpy(), rtol=0, atol=1e-6)
    with pytest.raises(ValueError, match="rows of 3 inputs"):
        head(Z)
    for bad in ({5: 0.0}, {1.5: 0.0}, {-1: 0.0}):
        with pytest.raises(ValueError, match="fixed columns must index the 5 inputs"):
            gp.numpy_head(bad)
    with pytest.raises(ValueError, match="the fixed input 1 must be finite"):
        gp.numpy_head({1: float("nan")})


@pytest.mark.parametrize("kernel, shape", [("squared_exponential", None), ("rational_quadratic", 2.0),
                                           ("rational_quadratic", None)])
def test_each_kernel_learns_the_map_and_its_numpy_head_equals_the_module(kernel, shape):
    """Every kernel choice fits the smooth map; a fixed shape stays as given, a fitted one is recorded; the
    compiled serving head (NumPy) gives the module's posterior mean."""
    rng = np.random.default_rng(0)
    X = rng.uniform(-2, 2, (200, 5))
    gp, info = fit_gp(X, truth(X), seed=0, iterations=60, kernel=kernel, shape=shape)
    assert info["kernel"] == gp.kernel == kernel
    if kernel == "squared_exponential":
        assert info["shape"] is None and np.isinf(float(gp.shape))
    elif shape is not None:
        assert info["shape"] == float(gp.shape) == shape
    else:
        assert info["shape"] == pytest.approx(float(gp.shape)) and info["shape"] != 1.0  # moved from its start
    Xt = np.random.default_rng(1).uniform(-1.8, 1.8, (300, 5))
    pred = gp(torch.from_numpy(Xt)).numpy()
    rmse = np.sqrt(np.mean((pred - truth(Xt)) ** 2, axis=0))
    assert (rmse < 0.02 * truth(Xt).std(axis=0)).all(), rmse
    np.testing.assert_allclose(gp.numpy_head()(Xt), pred, rtol=0, atol=1e-6)


@pytest.mark.parametrize("use_numpy", [True, False])
def test_the_heads_exp_and_log1p_by_numpy_and_by_torch_are_exact_to_a_few_ulp(use_numpy, monkeypatch):
    """The head computes exp and log1p in place with NumPy or torch, whichever is faster on the CPU
    (``gp._numpy_avx512``); each path is checked here, whatever this host picks: against the correctly rounded
    ``math`` functions over the head's range, and the compiled head of both kernels against the module."""
    exp_, log1p_ = gp_module._in_place("exp", use_numpy), gp_module._in_place("log1p", use_numpy)
    x = np.linspace(-60.0, 0.0, 20001)
    E = x.copy()
    exp_(E)
    ref = np.array([math.exp(v) for v in x])
    assert np.all(np.abs(E - ref) <= 4 * np.spacing(ref))
    y = np.linspace(0.0, 40.0, 20001)
    L = y.copy()
    log1p_(L)
    ref = np.array([math.log1p(v) for v in y])
    assert np.all(np.abs(L - ref) <= 4 * np.spacing(np.maximum(ref, 1e-300)))
    monkeypatch.setattr(gp_module, "_exp_", exp_)
    monkeypatch.setattr(gp_module, "_log1p_", log1p_)
    rng = np.random.default_rng(0)
    X = rng.uniform(-2, 2, (120, 5))
    Xt = rng.uniform(-2, 2, (50, 5))
    for kernel, shape in (("squared_exponential", None), ("rational_quadratic", 2.5)):  # 2.5: log1p, then exp
        gp, _ = fit_gp(X, truth(X), seed=0, iterations=20, kernel=kernel, shape=shape)
        np.testing.assert_allclose(gp.numpy_head()(Xt), gp(torch.from_numpy(Xt)).numpy(), rtol=0, atol=1e-9)
    assert isinstance(gp_module._numpy_avx512("exp"), bool) and gp_module._numpy_avx512("no_such_ufunc") is False


def test_a_gp_saved_before_the_kernel_was_a_choice_loads_as_the_squared_exponential():
    """Bundles of format 5 and older hold no ``shape`` buffer: their GP is read as the squared exponential it was."""
    rng = np.random.default_rng(5)
    X = rng.uniform(-2, 2, (80, 5))
    gp, _ = fit_gp(X, truth(X), seed=0, iterations=30, kernel="squared_exponential")
    state = {k: v for k, v in gp.state_dict().items() if k != "shape"}
    old = GPRegressor.from_state_dict(state)
    assert old.kernel == "squared_exponential"
    Xt = rng.uniform(-2, 2, (20, 5))
    np.testing.assert_array_equal(old(torch.from_numpy(Xt)).numpy(), gp(torch.from_numpy(Xt)).numpy())
    rq = GPRegressor.from_state_dict({**state, "shape": torch.tensor(1.0, dtype=torch.float64)})
    assert rq.kernel == "rational_quadratic"
    assert not np.allclose(rq(torch.from_numpy(Xt)).numpy(), gp(torch.from_numpy(Xt)).numpy(), atol=1e-3)
    with pytest.raises(ValueError, match="shape must be positive"):
        GPRegressor.from_state_dict({**state, "shape": torch.tensor(0.0, dtype=torch.float64)})
    with pytest.raises(ValueError, match="model.gp.kernel"):
        fit_gp(X, truth(X), seed=0, kernel="cauchy")
    with pytest.raises(ValueError, match="model.gp.shape"):
        fit_gp(X, truth(X), seed=0, shape=-1.0)


def test_same_seed_same_fit_and_the_cap_draws_a_seeded_subset():
    rng = np.random.default_rng(3)
    X = rng.uniform(-2, 2, (120, 3))
    y = truth(np.hstack([X, X[:, :2]]))
    a, ia = fit_gp(X, y, seed=5, max_points=60, iterations=50)
    b, ib = fit_gp(X, y, seed=5, max_points=60, iterations=50)
    c, _ = fit_gp(X, y, seed=6, max_points=60, iterations=50)
    assert ia["n_used"] == 60 and a.n_train == 60
    assert torch.equal(a.X, b.X) and torch.equal(a.alpha, b.alpha)
    assert not torch.equal(a.X, c.X)  # another seed, another subset


def test_bad_training_data_is_refused_by_name():
    X = np.zeros((10, 2))
    with pytest.raises(ValueError, match="non-finite"):
        fit_gp(np.where(np.eye(10, 2) > 0, np.nan, X), np.zeros((10, 3)), seed=0)
    with pytest.raises(ValueError, match="same n"):
        fit_gp(X, np.zeros((9, 3)), seed=0)
    with pytest.raises(ValueError, match="model.regressor: unknown 'forest'"):
        fit_params({"regressor": "forest"}, lr=1e-3, batch_size=8, epochs=1)


def test_a_gp_force_model_round_trips_through_its_bundle(tmp_path):
    arrays = synthetic_arrays(90, n_geometries=3, seed=2, material_varies=True)
    model_cfg = {"encoder": "pca", "code_size": 4, "state_vector": True, "grid_size": 8, "hidden": [8],
                 "dropout": 0.0, "occlusion": {"radius_mm": 0.0, "mode": "remove"}, "noise_mm": 0.0,
                 "regressor": "gp", "gp": {"max_points": 500, "iterations": 100}}
    train = {"test_fraction": 0.25, "epochs": 5, "batch_size": 16, "lr": 3e-3, "weight_decay": 0.0, "seed": 0}
    tune = {"enabled": False, "trials": 1, "folds": 2, "sobol_trials": 1, "epochs": 1}
    res = train_scenario(arrays, model_cfg, train, tune, "IV", "gp", out_dir=tmp_path)
    assert res["best_params"]["regressor"] == "gp" and res["cv_mae_n"] > 0  # no Ax search; still cross-validated
    model = ForceModel.load(res["model_path"])
    assert isinstance(model.regressor, GPRegressor) and model.regressor_spec.kind == "gp"
    assert model.regressor.kernel == "rational_quadratic" and model.meta["gp"]["shape"] == 2.0  # the config's default
    assert model.meta["gp"]["n_used"] == res["n_train"]
    test = [list(arrays["case_id"]).index(c) for c in model.meta["test_case_ids"]]
    from liverforce.learn.model import subset

    a = subset(arrays, test)
    again = ForceModel.load(model.save(tmp_path / "copy")).predict(a)
    np.testing.assert_array_equal(again, model.predict(a))
    # and it learned the synthetic force map better than predicting the mean force
    true = np.asarray(a["force_n"])
    assert np.linalg.norm(model.predict(a) - true, axis=1).mean() < 0.5 * np.linalg.norm(true - true.mean(0), axis=1).mean()


def test_a_format_5_bundle_with_a_squared_exponential_gp_loads_and_predicts_as_before(tmp_path):
    """A model written before the kernel was a choice (format 5, no ``shape`` in the GP's state) loads as the
    squared-exponential GP it is and predicts exactly what the same model written today predicts."""
    import json

    arrays = synthetic_arrays(60, n_geometries=3, seed=3, material_varies=True)
    model_cfg = {"encoder": "pca", "code_size": 4, "state_vector": True, "grid_size": 8, "hidden": [8],
                 "dropout": 0.0, "occlusion": {"radius_mm": 0.0, "mode": "remove"}, "noise_mm": 0.0,
                 "regressor": "gp", "gp": {"max_points": 500, "iterations": 40, "kernel": "squared_exponential"}}
    train = {"test_fraction": 0.25, "epochs": 5, "batch_size": 16, "lr": 3e-3, "weight_decay": 0.0, "seed": 0}
    tune = {"enabled": False, "trials": 1, "folds": 2, "sobol_trials": 1, "epochs": 1}
    res = train_scenario(arrays, model_cfg, train, tune, "IV", "gp", out_dir=tmp_path / "run")
    model = ForceModel.load(res["model_path"])
    assert model.regressor.kernel == "squared_exponential"
    path = model.save(tmp_path / "old")
    state = torch.load(path / "regressor.pt", weights_only=True)
    del state["shape"]
    torch.save(state, path / "regressor.pt")
    doc = json.loads((path / "model.json").read_text())
    doc["format_version"] = 5
    (path / "model.json").write_text(json.dumps(doc))
    old = ForceModel.load(path)
    assert old.regressor.kernel == "squared_exponential"
    np.testing.assert_array_equal(old.predict(arrays), model.predict(arrays))


def test_noisy_targets_give_a_noise_variance_not_an_interpolating_kernel():
    """Noisy targets: the GP explains the noise as noise and averages it out, with every length scale at or
    above the floor MIN_LENGTH (on one scenario-III camera split of the default run the likelihood sent a length
    scale to zero without the floor and interpolated the noise; that data is not in the test set)."""
    from liverforce.learn.gp import MIN_LENGTH

    rng = np.random.default_rng(4)
    X = rng.normal(size=(300, 12))  # standardised inputs, most of them irrelevant
    clean = np.stack([np.sin(X[:, 0]), 0.5 * X[:, 1], np.cos(X[:, 2])], axis=1)
    y = clean + rng.normal(scale=0.2, size=clean.shape)
    gp, info = fit_gp(X, y, seed=0)
    assert min(info["length_scales"]) >= MIN_LENGTH
    assert 0.02 < info["noise_var"] < 0.08  # the true noise variance is 0.04
    Xt = rng.normal(size=(300, 12))
    truth_t = np.stack([np.sin(Xt[:, 0]), 0.5 * Xt[:, 1], np.cos(Xt[:, 2])], axis=1)
    mse = np.mean((gp.numpy_head()(Xt) - truth_t) ** 2)
    assert mse < 0.01  # a quarter of the noise variance: it averages the noise out instead of fitting it


def _noisy_views(seed: int, n: int = 200, d: int = 12):
    """Cases seen through two noisy views (as a camera model's training rows): the first 3 inputs carry the force
    and are observed with noise per view; the other inputs are exact and identical in both views (as the state
    vector is), so they name the case without telling much about its force."""
    rng = np.random.default_rng(seed)

    def f(X):
        return np.stack([2 * X[:, 0] + 0.3 * np.sin(X[:, 3]), X[:, 1] + 0.2 * X[:, 4], 1.5 * X[:, 2]], axis=1)

    sd = np.array([0.3, 0.3, 0.3] + [0.0] * (d - 3))
    X = rng.normal(size=(n, d))
    Z = np.vstack([X + rng.normal(size=X.shape) * sd for _ in range(2)])
    Xt = rng.normal(size=(500, d))
    return Z, np.vstack([f(X), f(X)]), np.tile(np.arange(n), 2), Xt + rng.normal(size=Xt.shape) * sd, f(Xt)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_views_of_one_case_do_not_teach_the_gp_to_interpolate_their_noise(seed):
    """Fitted on every view, the likelihood rewards explaining a case's twin views exactly (they share the exact
    inputs and the force): the noise variance falls to the jitter and the GP fits the training rows exactly (with
    the default rational-quadratic kernel on every seed here; the squared exponential did it on seed 1). With the
    views grouped, the hyper-parameters come from one row per case: the input noise shows up as a noise variance
    (the targets' share of it: about 0.1-0.2 here) and the test error stays near that floor, below the
    interpolating fit's, while the posterior still uses both views."""
    Z, Y, groups, Zt, Yt = _noisy_views(seed)
    gp, info = fit_gp(Z, Y, seed=0, groups=groups)
    assert info["n_likelihood"] == len(Z) // 2 and info["n_used"] == len(Z)
    assert gp.n_train == len(Z)  # the posterior keeps both views
    np.testing.assert_allclose(gp.X.numpy(), Z)
    assert info["noise_var"] > 0.05
    grouped = np.mean((gp.numpy_head()(Zt) - Yt) ** 2)
    assert grouped < 0.25
    gp_all, info_all = fit_gp(Z, Y, seed=0)
    assert info_all["noise_var"] < 10 * JITTER
    assert np.mean((gp_all.numpy_head()(Z) - Y) ** 2) < 1e-4  # interpolates its training rows
    assert np.mean((gp_all.numpy_head()(Zt) - Yt) ** 2) > 1.1 * grouped


def test_groups_must_label_every_row_and_name_two_cases():
    Z, Y, groups, _, _ = _noisy_views(0, n=20)
    with pytest.raises(ValueError, match="groups must label every row"):
        fit_gp(Z, Y, seed=0, groups=groups[:-1])
    with pytest.raises(ValueError, match="single case"):
        fit_gp(Z, Y, seed=0, groups=np.zeros(len(Z), int))


def test_one_view_per_case_is_the_plain_fit_and_the_cap_keeps_one_row_per_case_for_the_likelihood():
    """Groups that are all different change nothing; with the max_points cap the likelihood takes one kept row
    per case and the posterior every kept row."""
    Z, Y, groups, _, _ = _noisy_views(0, n=60)
    plain, _ = fit_gp(Z[:60], Y[:60], seed=0, iterations=30)
    same, info = fit_gp(Z[:60], Y[:60], seed=0, iterations=30, groups=np.arange(60))
    assert info["n_likelihood"] == 60
    for k, v in plain.state_dict().items():
        assert torch.equal(v, same.state_dict()[k]), k
    capped, info = fit_gp(Z, Y, seed=0, iterations=30, max_points=70, groups=groups)
    assert info["n_used"] == 70 and capped.n_train == 70
    rng = np.random.default_rng(derive(0, "gp.subset"))
    kept = np.sort(rng.choice(len(Z), size=70, replace=False))
    assert info["n_likelihood"] == len(np.unique(groups[kept]))



# --------------------------------------------------------------------------
# the GP ensemble over nested PCA code sizes (model.gp.code_members)
# --------------------------------------------------------------------------


def test_an_ensemble_is_the_mean_of_its_members_each_fitted_alone_on_its_columns(fitted):
    """Each member is exactly fit_gp on its own columns (own hyper-parameters); the ensemble predicts
    their plain mean, through the module, the NumPy head and a saved-and-loaded state."""
    from liverforce.learn.gp import GPEnsemble, fit_gp_ensemble
    from liverforce.learn.regressor import RegressorSpec, load_regressor

    X, _, _ = fitted
    cols = [np.array([0, 3, 4]), np.array([0, 1, 2, 3, 4])]
    ens, info = fit_gp_ensemble(X, truth(X), cols, seed=0)
    alone = [fit_gp(X[:, c], truth(X), seed=0)[0] for c in cols]
    Xt = torch.from_numpy(np.random.default_rng(5).uniform(-1.8, 1.8, (200, 5)))
    want = 0.5 * (alone[0](Xt[:, cols[0]]) + alone[1](Xt[:, cols[1]])).numpy()
    np.testing.assert_allclose(ens(Xt).numpy(), want, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(ens.numpy_head()(Xt.numpy()), want, rtol=0, atol=1e-6)  # as a single GP's head
    assert info["member_inputs"] == [3, 5] and len(info["members"]) == 2 and ens.n_train == len(X)
    state = {k: v.clone() for k, v in ens.state_dict().items()}
    again = load_regressor(RegressorSpec(5, (), 0.0, kind="gp"), state)
    assert isinstance(again, GPEnsemble)
    np.testing.assert_array_equal(again(Xt).numpy(), ens(Xt).numpy())
    # the member on columns 0, 3, 4 cannot see inputs 1 and 2: the ensemble's error lies between its members'
    err = [np.abs(m(Xt[:, c]).numpy() - truth(Xt.numpy())).mean() for m, c in zip(alone, cols)]
    err_ens = np.abs(ens(Xt).numpy() - truth(Xt.numpy())).mean()
    assert err[0] > 2 * err[1] and err[1] < err_ens < err[0]


def test_ensemble_columns_out_of_range_are_refused():
    from liverforce.learn.gp import fit_gp_ensemble

    X = np.random.default_rng(0).normal(size=(20, 3))
    with pytest.raises(ValueError, match="columns must index the 3 inputs"):
        fit_gp_ensemble(X, truth(np.c_[X, X[:, :2]]), [np.array([0, 3])], seed=0)


def test_a_code_member_ensemble_model_fits_pca_at_the_largest_size_and_round_trips(tmp_path):
    """``model.gp.code_members``: the PCA encoder keeps the largest member's components, member k sees the
    leading k code components and every state column, the bundle reloads to the same predictions and the
    compiled (NumPy) head of the served path gives them too."""
    from liverforce.learn.gp import GPEnsemble
    from liverforce.learn.model import subset
    from liverforce.serve.compiled import regressor_head

    arrays = synthetic_arrays(90, n_geometries=3, seed=2, material_varies=True)
    model_cfg = {"encoder": "pca", "code_size": 4, "state_vector": True, "grid_size": 8, "hidden": [8],
                 "dropout": 0.0, "occlusion": {"radius_mm": 0.0, "mode": "remove"}, "noise_mm": 0.0,
                 "regressor": "gp", "gp": {"max_points": 500, "iterations": 100, "code_members": [6, 2, 4]}}
    train = {"test_fraction": 0.25, "epochs": 5, "batch_size": 16, "lr": 3e-3, "weight_decay": 0.0, "seed": 0}
    tune = {"enabled": False, "trials": 1, "folds": 2, "sobol_trials": 1, "epochs": 1}
    res = train_scenario(arrays, model_cfg, train, tune, "IV", "gp", out_dir=tmp_path)
    assert res["best_params"]["code_members"] == [2, 4, 6] and res["cv_mae_n"] > 0
    model = ForceModel.load(res["model_path"])
    reg = model.regressor
    assert isinstance(reg, GPEnsemble) and model.pre.encoder.code_size == 6
    n_state = model.pre.n_inputs - 6
    for i, k in enumerate((2, 4, 6)):
        np.testing.assert_array_equal(reg.columns(i).numpy(), np.r_[np.arange(k), np.arange(6, 6 + n_state)])
    assert model.meta["gp"]["member_inputs"] == [2 + n_state, 4 + n_state, 6 + n_state]
    a = subset(arrays, [list(arrays["case_id"]).index(c) for c in model.meta["test_case_ids"]])
    np.testing.assert_array_equal(ForceModel.load(model.save(tmp_path / "copy")).predict(a), model.predict(a))
    z = np.random.default_rng(0).normal(size=(7, model.pre.n_inputs))
    np.testing.assert_allclose(regressor_head(reg)(z), reg(torch.from_numpy(z)).numpy(), rtol=0, atol=1e-6)
    # the state held in the head (a compiled context): each member gets its share, the head reads the codes
    fixed = {6 + j: float(z[0, 6 + j]) for j in range(n_state)}
    z[:, 6:] = z[0, 6:]
    np.testing.assert_allclose(regressor_head(reg, fixed)(z[:, :6]), reg(torch.from_numpy(z)).numpy(), rtol=0,
                               atol=1e-6)
    with pytest.raises(ValueError, match="fixed columns must index"):
        regressor_head(reg, {6 + n_state: 0.0})


def test_code_members_apply_to_pca_gps_only_and_bad_lists_are_refused():
    from liverforce.learn.model import encoder_code_size
    from liverforce.learn.regressor import gp_code_members

    cfg = {"encoder": "pca", "code_size": 16, "regressor": "gp", "gp": {"code_members": [32, 8, 16]}}
    assert gp_code_members(cfg) == (8, 16, 32) and encoder_code_size(16, gp_code_members(cfg)) == 32
    assert fit_params(cfg, lr=1e-3, batch_size=8, epochs=1).gp_code_members == (8, 16, 32)
    for other in ({"encoder": "ae"}, {"regressor": "mlp"}, {"gp": {"code_members": None}}):
        c = {**cfg, **other}
        assert gp_code_members(c) == () and encoder_code_size(16, gp_code_members(c)) == 16
    for bad in ([8, 8], [0, 4]):
        with pytest.raises(ValueError, match="code_members"):
            gp_code_members({**cfg, "gp": {"code_members": bad}})


def test_members_larger_than_the_pca_code_are_capped_at_it():
    """PCA keeps at most as many components as training rows: on 6 training cases the members [2, 4, 32]
    become [2, 4, 6] (the largest capped at the 6 components PCA keeps), and the model trains and predicts."""
    from liverforce.learn.gp import GPEnsemble
    from liverforce.learn.model import fit_force_model, prepare, view_seeds
    from liverforce.learn.regressor import FitParams
    from liverforce.learn.representation import representation_from_config

    arrays = synthetic_arrays(6, n_geometries=1, seed=4, material_varies=True)
    cfg = {"grid_size": 6, "occlusion": {"radius_mm": 0.0, "mode": "remove"}, "noise_mm": 0.0}
    rep = representation_from_config(cfg, arrays)
    prep = prepare(arrays, rep, observation_seeds=view_seeds(0, 1))
    fit = FitParams(0.0, 1, 0, regressor="gp", gp_iterations=20, gp_code_members=(2, 4, 32))
    model, _ = fit_force_model(prep, rep, encoder="pca", code_size=16, use_state=True, hidden=[], dropout=0.0,
                               fit=fit, seed=0)
    assert isinstance(model.regressor, GPEnsemble) and model.pre.encoder.code_size == 6
    assert model.meta["gp"]["code_members"] == [2, 4, 6]
    assert np.isfinite(model.predict(arrays)).all()


@pytest.fixture(scope="module")
def fitted_per_output():
    rng = np.random.default_rng(0)
    X = rng.uniform(-2, 2, (200, 5))
    return X, *fit_gp(X, truth(X), seed=0, iterations=60, kernel="squared_exponential", per_output=True)


def test_one_kernel_per_output_is_each_output_fitted_alone(fitted_per_output):
    """``per_output``: output k's kernel, weights and prediction are exactly those of fit_gp on output k alone,
    and each output's length scales find its own inputs, which one shared kernel cannot: output 1 (0.5 x2^2)
    reads input 2 only, so its kernel ignores inputs 0, 1, 3 and 4 while output 0's needs input 0."""
    X, gp, info = fitted_per_output
    Xt = torch.from_numpy(np.random.default_rng(1).uniform(-1.8, 1.8, (200, 5)))
    pred = gp(Xt).numpy()
    ls = np.asarray(info["length_scales"])
    assert gp.per_output and ls.shape == (3, 5) and np.asarray(info["noise_var"]).shape == (3,)
    for k in range(3):
        alone, info_k = fit_gp(X, truth(X)[:, k:k + 1], seed=0, iterations=60, kernel="squared_exponential")
        np.testing.assert_allclose(pred[:, k:k + 1], alone(Xt).numpy(), rtol=0, atol=1e-12)
        np.testing.assert_allclose(ls[k], info_k["length_scales"], rtol=1e-12)
    assert ls[1, [0, 1, 3, 4]].min() > 10 * ls[1, 2] and ls[0, 0] < 0.1 * ls[1, 0]
    shared, info_s = fit_gp(X, truth(X), seed=0, iterations=60, kernel="squared_exponential")
    assert np.asarray(info_s["length_scales"]).shape == (5,) and not shared.per_output
    # on the output whose inputs differ most from the others', its own kernel predicts better than the shared one
    err = np.abs(pred - truth(Xt.numpy())).mean(0)
    err_s = np.abs(shared(Xt).numpy() - truth(Xt.numpy())).mean(0)
    assert err[1] < err_s[1], (err, err_s)


def test_a_per_output_gp_numpy_head_and_saved_state_equal_the_module(fitted_per_output):
    """The compiled serving head (with and without fixed inputs) and a saved-and-loaded state give the module's
    posterior mean; so does an ensemble of per-output members."""
    from liverforce.learn.gp import GPEnsemble, fit_gp_ensemble
    from liverforce.learn.regressor import RegressorSpec, load_regressor

    X, gp, _ = fitted_per_output
    Xt = np.random.default_rng(2).uniform(-2, 2, (64, 5))
    want = gp(torch.from_numpy(Xt)).numpy()
    # this fit's weights sum to ~1.2e4 in |alpha| on an output: the module and the head are each ~1e-6 from the
    # posterior mean evaluated in long double (6.7e-7 and 9.9e-7 with NumPy 2.4.6), so they agree to 3e-6
    np.testing.assert_allclose(gp.numpy_head()(Xt), want, rtol=0, atol=3e-6)
    Z = Xt.copy()
    Z[:, 1] = 0.3
    np.testing.assert_allclose(gp.numpy_head({1: 0.3})(Z[:, [0, 2, 3, 4]]), gp(torch.from_numpy(Z)).numpy(),
                               rtol=0, atol=3e-6)
    again = load_regressor(RegressorSpec(5, (), 0.0, kind="gp"), {k: v.clone() for k, v in gp.state_dict().items()})
    assert isinstance(again, GPRegressor) and again.per_output
    np.testing.assert_array_equal(again(torch.from_numpy(Xt)).numpy(), want)
    ens, _ = fit_gp_ensemble(X, truth(X), [np.array([0, 2]), np.arange(5)], seed=0, iterations=30,
                             kernel="rational_quadratic", per_output=True)
    assert all(m.per_output for m in ens.members)
    ens2 = GPEnsemble.from_state_dict(ens.state_dict())
    np.testing.assert_allclose(ens.numpy_head()(Xt), ens2(torch.from_numpy(Xt)).numpy(), rtol=0, atol=1e-6)


def test_per_output_with_a_fitted_shape_is_refused_with_the_fix():
    from liverforce.config import ConfigError, compose

    X = np.random.default_rng(0).uniform(-2, 2, (20, 2))
    with pytest.raises(ValueError, match="per_output.*shape must be fixed"):
        fit_gp(X, truth(np.c_[X, X, X[:, :1]]), seed=0, kernel="rational_quadratic", shape=None, per_output=True)
    with pytest.raises(ConfigError, match="gp.per_output.*set model.gp.shape to a number"):
        compose(["train.variants=[{name: v, gp: {per_output: true, shape: null}}]", "validate.variant=main"])
    with pytest.raises(ValueError, match=r"\(outputs, inputs\)"):
        GPRegressor(torch.zeros(4, 2), torch.zeros(4, 3), torch.ones(2, 2), torch.ones(2), torch.ones(2),
                    torch.ones(2))


def test_a_per_output_gp_force_model_trains_through_the_pipeline_and_round_trips(tmp_path):
    arrays = synthetic_arrays(60, n_geometries=3, seed=2, material_varies=True)
    model_cfg = {"encoder": "pca", "code_size": 4, "state_vector": True, "grid_size": 8, "hidden": [8],
                 "dropout": 0.0, "occlusion": {"radius_mm": 0.0, "mode": "remove"}, "noise_mm": 0.0,
                 "regressor": "gp", "gp": {"max_points": 500, "iterations": 40, "per_output": True,
                                           "code_members": [2, 4]}}
    train = {"test_fraction": 0.25, "epochs": 5, "batch_size": 16, "lr": 3e-3, "weight_decay": 0.0, "seed": 0}
    tune = {"enabled": False, "trials": 1, "folds": 2, "sobol_trials": 1, "epochs": 1}
    res = train_scenario(arrays, model_cfg, train, tune, "IV", "gp", out_dir=tmp_path)
    assert res["best_params"]["per_output"] is True
    model = ForceModel.load(res["model_path"])
    assert all(m.per_output for m in model.regressor.members)
    assert all(m["per_output"] for m in model.meta["gp"]["members"])
    again = ForceModel.load(model.save(tmp_path / "copy"))
    np.testing.assert_array_equal(again.predict(arrays), model.predict(arrays))


@pytest.mark.parametrize("shape", [1.0, 2.0, 3.0, 4.0, 5.0])
def test_a_whole_shape_head_is_the_module_by_products_and_a_reciprocal(shape, monkeypatch):
    """For a whole rational-quadratic shape up to POW_SHAPE_MAX_HEAD the head computes ``1 / B^a`` by products
    and never calls exp or log1p (5: through them); either way it gives the module's posterior mean, also at
    and next to the training inputs."""
    calls = []
    for name in ("_exp_", "_log1p_"):
        f = getattr(gp_module, name)
        monkeypatch.setattr(gp_module, name, lambda E, f=f, name=name: (calls.append(name), f(E)))
    rng = np.random.default_rng(0)
    X = rng.uniform(-2, 2, (120, 5))
    gp, _ = fit_gp(X, truth(X), seed=0, iterations=20, kernel="rational_quadratic", shape=shape)
    for Xt in (rng.uniform(-2, 2, (50, 5)), X[:10], X[:10] + 1e-6):
        np.testing.assert_allclose(gp.numpy_head()(Xt), gp(torch.from_numpy(Xt)).numpy(), rtol=0, atol=1e-9)
    assert (calls == []) == (shape <= gp_module.POW_SHAPE_MAX_HEAD), calls


@pytest.mark.parametrize("outputs", [3, 1, 2])
def test_the_fused_rational_quadratic_pass_equals_the_numpy_formula(outputs):
    """``_rq_power_mean`` (the head's one pass for a whole shape) adds ``(1 - E / a)^-a @ alpha`` for every whole
    shape the head takes it for and any number of outputs (a per-output GP's heads have one), row for row."""
    rng = np.random.default_rng(outputs)
    E = -rng.uniform(0.0, 6.0, (17, 1999))  # -d2 / 2 <= 0; an odd count leaves a vector loop's remainder
    E[0, :5] = 0.0  # at a training input: the kernel is 1
    alphaT = rng.normal(size=(outputs, 1999))
    for a in range(1, gp_module.POW_SHAPE_MAX_HEAD + 1):
        out0 = rng.normal(size=(17, outputs))
        out = out0.copy()
        gp_module._rq_power_mean(E, 1.0 / a, a, alphaT, out)
        want = out0 + (1.0 - E / a) ** -float(a) @ alphaT.T
        np.testing.assert_allclose(out, want, rtol=1e-12, atol=1e-12 * np.abs(alphaT).sum())
        buf = np.empty(E.shape[1] + 1)  # the row alone, copied to other memory, one element off the block's alignment
        buf[1:] = E[5]
        one = out0[5:6].copy()
        gp_module._rq_power_mean(buf[1:].reshape(1, -1), 1.0 / a, a, alphaT, one)
        np.testing.assert_array_equal(one, out[5:6])  # a row alone gives the bits it gets in a block


def test_a_noise_floor_is_a_noise_variance_added_to_the_fitted_one_in_the_likelihood_and_the_posterior():
    """``model.gp.noise_floor``: the likelihood with a floor f at raw noise s is the likelihood at the noise whose
    variance is exp(2 s) + f, with the same value, alpha and gradients of the other parameters (the noise's own
    gradient is that of exp(2 s) alone); a fit with it reports a noise variance of at least f and its posterior
    weights solve (K + noise I) alpha = Y with that noise; a negative or non-finite floor is refused by name, in
    fit_gp and in the config."""
    from liverforce.config import ConfigError, compose

    rng = np.random.default_rng(7)
    n, d, f = 90, 3, 0.05
    X = torch.from_numpy(rng.normal(size=(n, d)))
    Y = torch.from_numpy(rng.normal(size=(n, 3)))
    log_l, log_sf, log_sl = torch.zeros(d, dtype=torch.float64), torch.tensor(0.2, dtype=torch.float64), \
        torch.tensor(-1.0, dtype=torch.float64)
    s = -2.0
    log_a = torch.tensor(math.log(2.0), dtype=torch.float64)
    v, g, alpha = neg_log_likelihood(X, Y, log_l, log_sf, log_sl, torch.tensor(s, dtype=torch.float64), log_a,
                                     noise_floor=f)
    s_eq = 0.5 * math.log(math.exp(2 * s) + f)
    v2, g2, alpha2 = neg_log_likelihood(X, Y, log_l, log_sf, log_sl, torch.tensor(s_eq, dtype=torch.float64), log_a)
    assert v == pytest.approx(v2, rel=1e-12)
    torch.testing.assert_close(alpha, alpha2, rtol=1e-10, atol=1e-12)
    for a, b in zip(g[:3], g2[:3]):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12)
    # d v / d s = d v / d s_eq * (exp(2 s) / (exp(2 s) + f)): the chain rule through the added variance
    assert float(g[3]) == pytest.approx(float(g2[3]) * math.exp(2 * s) / (math.exp(2 * s) + f), rel=1e-9)
    assert float(neg_log_likelihood(X, Y, log_l, log_sf, log_sl, torch.tensor(s, dtype=torch.float64), log_a,
                                    gradient=False)[0]) != pytest.approx(v, rel=1e-6)  # the floor changes it

    Xn = rng.uniform(-2, 2, (80, 2))
    Yn = truth(np.c_[Xn, Xn, Xn[:, :1]])
    gp, info = fit_gp(Xn, Yn, seed=0, iterations=40, noise_floor=0.02)
    assert info["noise_floor"] == 0.02
    assert float(gp.noise_var) >= 0.02 + JITTER and info["noise_var"] == pytest.approx(float(gp.noise_var))
    K = gp_module._kernel(gp.X, gp.X, gp.inv_length, gp.signal_var, gp.linear_var, float(gp.shape))
    K += float(gp.noise_var) * torch.eye(len(K), dtype=torch.float64)
    torch.testing.assert_close(K @ gp.alpha, torch.from_numpy(Yn), rtol=0, atol=1e-8)
    plain, plain_info = fit_gp(Xn, Yn, seed=0, iterations=40)
    assert plain_info["noise_var"] < 0.02  # noise-free targets: without the floor the noise is far below it
    for bad in (-0.1, math.nan, math.inf):
        with pytest.raises(ValueError, match="model.gp.noise_floor must be a finite variance >= 0"):
            fit_gp(Xn, Yn, seed=0, iterations=5, noise_floor=bad)
    for bad in ("-0.01", "abc", "true", "'0.003'", "null"):  # in a variant: not type-checked by the structured config
        with pytest.raises(ConfigError, match="gp.noise_floor"):
            compose([f"train.variants=[{{name: v, gp: {{noise_floor: {bad}}}}}]", "validate.variant=main"])
    for bad in ("-0.01", "abc", "true"):
        with pytest.raises(ConfigError, match="gp.noise_floor"):
            compose([f"model.gp.noise_floor={bad}", "validate.variant=main"])


def test_the_floor_reaches_every_likelihood_evaluation_and_the_posterior_over_every_view(monkeypatch):
    """Views of one case (the camera model's rows): every likelihood evaluation of the fit, the optimiser's and the
    posterior's over all views, sees the floor, and the posterior weights over both views solve (K + noise I) alpha
    = Y with the reported noise variance."""
    Z, Y, groups, _, _ = _noisy_views(0, n=60)
    seen = []
    real = gp_module.neg_log_likelihood

    def spy(X, Yy, *args, **kw):
        seen.append((len(X), kw.get("noise_floor", 0.0)))
        return real(X, Yy, *args, **kw)

    monkeypatch.setattr(gp_module, "neg_log_likelihood", spy)
    gp, info = fit_gp(Z, Y, seed=0, iterations=15, groups=groups, noise_floor=0.04)
    assert info["n_likelihood"] == 60 and gp.n_train == 120
    assert len(seen) > 3 and {f for _, f in seen} == {0.04}
    assert seen[-1][0] == 120  # the last evaluation: the posterior over both views
    K = gp_module._kernel(gp.X, gp.X, gp.inv_length, gp.signal_var, gp.linear_var, float(gp.shape))
    K += float(gp.noise_var) * torch.eye(len(K), dtype=torch.float64)
    assert float(gp.noise_var) >= 0.04 + JITTER
    torch.testing.assert_close(K @ gp.alpha, torch.from_numpy(Y), rtol=0, atol=1e-8)


def test_a_noise_floor_in_the_config_reaches_every_member_of_a_trained_model(tmp_path, monkeypatch):
    arrays = synthetic_arrays(60, n_geometries=3, seed=2, material_varies=True)
    model_cfg = {"encoder": "pca", "code_size": 4, "state_vector": True, "grid_size": 8, "hidden": [8],
                 "dropout": 0.0, "occlusion": {"radius_mm": 0.0, "mode": "remove"}, "noise_mm": 0.0,
                 "regressor": "gp", "gp": {"max_points": 500, "iterations": 20, "noise_floor": 0.03,
                                           "code_members": [2, 4]}}
    train = {"test_fraction": 0.25, "epochs": 5, "batch_size": 16, "lr": 3e-3, "weight_decay": 0.0, "seed": 0,
             "repeats": 2, "final_fit": True, "interval": {"coverage": 0.9, "folds": 2, "scale": "none"}}
    tune = {"enabled": False, "trials": 1, "folds": 2, "sobol_trials": 1, "epochs": 1}
    floors = []
    real = gp_module.fit_gp

    def spy(*args, **kw):
        floors.append(kw.get("noise_floor"))
        return real(*args, **kw)

    monkeypatch.setattr(gp_module, "fit_gp", spy)
    res = train_scenario(arrays, model_cfg, train, tune, "IV", "gp", out_dir=tmp_path)
    # every GP (2 members each): the CV's 2 folds, the 2 splits, the final fit and the interval's folds (18 calls)
    assert len(floors) >= 2 * 7 and set(floors) == {0.03}
    assert res["best_params"]["noise_floor"] == 0.03
    model = ForceModel.load(res["model_path"])
    assert [m["noise_floor"] for m in model.meta["gp"]["members"]] == [0.03, 0.03]
    assert all(float(m.noise_var) >= 0.03 + JITTER for m in model.regressor.members)
