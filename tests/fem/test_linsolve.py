"""Linear-solver layer: CHOLMOD with LDL^T fallback, SuperLU otherwise."""
import numpy as np
import pytest
import scipy.sparse as sp

from liverforce.fem.linsolve import LinearSolver, cholmod_available


def _spd(n=60, seed=0):
    rng = np.random.default_rng(seed)
    A = sp.random(n, n, density=0.1, random_state=seed) + sp.eye(n)
    return sp.csr_matrix(A @ A.T + n * sp.eye(n)), rng.standard_normal(n)


@pytest.mark.parametrize("method", ["auto", "superlu"])
def test_solves_spd_systems(method):
    A, b = _spd()
    s = LinearSolver(method)
    s.factorize(A)
    assert np.allclose(A @ s.solve(b), b, atol=1e-10)
    if method == "superlu" or not cholmod_available():
        assert s.backend == "superlu"
    else:
        assert s.backend == "cholmod-llt"
    # a second matrix with the same pattern reuses the analysis
    s.factorize(A * 2.0)
    assert np.allclose(2.0 * (A @ s.solve(b)), b, atol=1e-10)


@pytest.mark.skipif(not cholmod_available(), reason="scikit-sparse not installed")
def test_indefinite_matrix_falls_back_to_ldlt():
    A, b = _spd()
    A = sp.csr_matrix(A - 1.2 * A.diagonal().min() * sp.eye(A.shape[0]))  # indefinite
    s = LinearSolver("cholmod")
    s.factorize(A)
    assert s.backend in ("cholmod-ldlt", "superlu") and s.n_fallbacks == 1
    assert np.allclose(A @ s.solve(b), b, atol=1e-8)


def test_unknown_method():
    with pytest.raises(ValueError, match="linear_solver"):
        LinearSolver("umfpack")
