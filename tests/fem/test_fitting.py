"""Least-squares fitting recovers known constants from synthetic data."""
import numpy as np
import pytest

from liverforce.fem.fitting import fit_material
from liverforce.fem.homogeneous import nominal_stress
from liverforce.fem.materials import make_material


def _data(mat, modes=("uniaxial", "equibiaxial", "planar")):
    lam = np.linspace(0.75, 1.35, 31)
    return {m: (lam, nominal_stress(mat, m, lam)) for m in modes}


@pytest.mark.parametrize(
    "model, params",
    [
        ("yeoh", {"C10": 1.61e-3, "C20": 12.5e-3, "C30": 5.31e-3}),
        ("mooney_rivlin_5", {"C10": 0.02, "C01": 0.01, "C20": 0.004, "C11": -0.002, "C02": 0.003}),
        ("neo_hookean", {"C10": 0.4}),
    ],
)
def test_recovers_invariant_models(model, params):
    true = make_material(model, params, nu=0.49)
    fit = fit_material(model, _data(true))
    assert fit.success
    for k, v in params.items():
        assert fit.params[k] == pytest.approx(v, rel=1e-6, abs=1e-12)
    assert fit.nrmse < 1e-9


def test_recovers_two_term_ogden():
    params = {"mu1": 0.02, "alpha1": 4.0, "mu2": -0.01, "alpha2": -3.0}
    true = make_material("ogden", params, nu=0.49)
    fit = fit_material("ogden", _data(true), x0={"mu1": 0.015, "alpha1": 3.0, "mu2": -0.005, "alpha2": -2.0})
    for k, v in params.items():
        assert fit.params[k] == pytest.approx(v, rel=1e-5)
    assert fit.nrmse < 1e-8


def test_nrmse_is_rmse_over_range():
    true = make_material("neo_hookean", {"C10": 0.5}, nu=0.45)
    lam = np.linspace(0.8, 1.2, 11)
    T = nominal_stress(true, "uniaxial", lam)
    noise = 0.01 * (T.max() - T.min()) * np.where(np.arange(11) % 2, 1.0, -1.0)
    fit = fit_material("neo_hookean", {"uniaxial": (lam, T + noise)})
    pred = nominal_stress(make_material("neo_hookean", fit.params, nu=0.45), "uniaxial", lam)
    rmse = np.sqrt(np.mean((pred - (T + noise)) ** 2))
    assert fit.nrmse == pytest.approx(rmse / np.ptp(T + noise))
    assert 0.005 < fit.nrmse < 0.02
    assert fit.nrmse_per_mode["uniaxial"] == pytest.approx(fit.nrmse)


def test_bad_data():
    with pytest.raises(ValueError, match="unknown test mode"):
        fit_material("yeoh", {"biaxial": ([1.0], [0.0])})
    with pytest.raises(ValueError, match="unknown material model"):
        fit_material("foo", {"uniaxial": ([1.0, 1.1], [0.0, 0.1])})
