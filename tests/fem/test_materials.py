"""Materials: stress and tangent against finite differences of the energy, registry errors."""
import numpy as np
import pytest

from liverforce.fem.materials import available_models, bulk_from_poisson, make_material

MATERIALS = {
    "neo_hookean": {"C10": 0.5},
    "mooney_rivlin_2": {"C10": 0.3, "C01": 0.2},
    "mooney_rivlin_3": {"C10": 0.3, "C01": 0.2, "C11": 0.1},
    "mooney_rivlin_5": {"C10": 0.3, "C01": 0.2, "C20": 0.1, "C11": 0.05, "C02": 0.07},
    "yeoh": {"C10": 0.3, "C20": 0.2, "C30": 0.1},
    "ogden": {"mu1": 0.4, "alpha1": 3.0, "mu2": -0.1, "alpha2": -2.0},
}


def _deformations():
    rng = np.random.default_rng(0)
    F = np.eye(3) + 0.25 * rng.standard_normal((6, 3, 3))
    F[0] = np.diag([1.2, 1.2, 0.8])  # two equal stretches (Ogden eigen-degeneracy)
    F[1] = np.eye(3) * 1.1  # all equal
    F[2] = np.eye(3) + np.array([[0, 0.4, 0], [0, 0, 0], [0, 0, 0]])  # simple shear
    assert np.all(np.linalg.det(F) > 0.2)
    return F


@pytest.mark.parametrize("model", sorted(MATERIALS))
def test_stress_and_tangent_match_finite_differences(model):
    mat = make_material(model, MATERIALS[model], nu=0.45)
    F = _deformations()
    P, A = mat.stress(F), mat.tangent(F)
    h = 1e-6
    P_fd, A_fd = np.zeros_like(P), np.zeros_like(A)
    for i in range(3):
        for j in range(3):
            d = np.zeros((3, 3))
            d[i, j] = h
            P_fd[:, i, j] = (mat.energy(F + d) - mat.energy(F - d)) / (2 * h)
            A_fd[..., i, j] = (mat.stress(F + d) - mat.stress(F - d)) / (2 * h)
    assert np.abs(P - P_fd).max() <= 1e-7 * np.abs(P).max()
    assert np.abs(A - A_fd).max() <= 1e-7 * np.abs(A).max()
    # major symmetry of a hyperelastic tangent
    assert np.allclose(A, np.einsum("niJkL->nkLiJ", A), atol=1e-12 * np.abs(A).max())


@pytest.mark.parametrize("model", sorted(MATERIALS))
def test_stress_free_reference_and_small_strain_moduli(model):
    nu = 0.3
    mat = make_material(model, MATERIALS[model], nu=nu)
    assert np.abs(mat.stress(np.eye(3))).max() < 1e-14
    # linearised tangent at F = I is the isotropic elasticity tensor with mu0 and K
    A = mat.tangent(np.eye(3))
    I = np.eye(3)
    lam = mat.bulk - 2.0 / 3.0 * mat.mu0
    C = (lam * np.einsum("ij,kl->ijkl", I, I) + mat.mu0 * (np.einsum("ik,jl->ijkl", I, I)
         + np.einsum("il,jk->ijkl", I, I)))
    assert np.allclose(A, C, atol=1e-12 * mat.bulk)
    assert mat.poisson_ratio == pytest.approx(nu)


@pytest.mark.parametrize("model", sorted(MATERIALS))
def test_objectivity(model):
    mat = make_material(model, MATERIALS[model], nu=0.45)
    F = _deformations()
    th = 0.7
    Q = np.array([[np.cos(th), -np.sin(th), 0], [np.sin(th), np.cos(th), 0], [0, 0, 1]])
    assert np.allclose(mat.energy(Q @ F), mat.energy(F), rtol=1e-12)
    assert np.allclose(mat.stress(Q @ F), Q @ mat.stress(F), atol=1e-12)


def test_ogden_with_alpha_two_is_neo_hookean():
    og = make_material("ogden", {"mu1": 0.6, "alpha1": 2.0}, bulk_mpa=5.0)
    nh = make_material("neo_hookean", {"C10": 0.3}, bulk_mpa=5.0)
    F = _deformations()
    assert og.mu0 == pytest.approx(nh.mu0)
    assert np.allclose(og.tangent(F), nh.tangent(F), atol=1e-12)


def test_bulk_from_poisson_ratio():
    mat = make_material("yeoh", {"C10": 1.61e-3, "C20": 12.5e-3, "C30": 5.31e-3}, nu=0.49)
    mu0 = 2 * 1.61e-3
    assert mat.mu0 == pytest.approx(mu0)
    assert mat.bulk == pytest.approx(2 * mu0 * 1.49 / (3 * 0.02))
    assert bulk_from_poisson(1.0, 0.25) == pytest.approx(5.0 / 3.0)


def test_registry_errors_are_clear():
    assert "mooney_rivlin_5" in available_models()
    with pytest.raises(ValueError, match="unknown material model"):
        make_material("gent", {"mu": 1.0}, nu=0.45)
    with pytest.raises(ValueError, match="missing \\['C30'\\]"):
        make_material("yeoh", {"C10": 1.0, "C20": 0.0}, nu=0.45)
    with pytest.raises(ValueError, match="unknown \\['C99'\\]"):
        make_material("neo_hookean", {"C10": 1.0, "C99": 0.0}, nu=0.45)
    with pytest.raises(ValueError, match="exactly one of nu"):
        make_material("neo_hookean", {"C10": 1.0})
    with pytest.raises(ValueError, match="exactly one of nu"):
        make_material("neo_hookean", {"C10": 1.0}, nu=0.4, bulk_mpa=3.0)
    with pytest.raises(ValueError, match="mu0"):
        make_material("mooney_rivlin_2", {"C10": -1.0, "C01": 0.5}, nu=0.45)
    with pytest.raises(ValueError, match="Ogden"):
        make_material("ogden", {"mu1": 1.0}, nu=0.45)
    with pytest.raises(ValueError, match="Poisson"):
        make_material("neo_hookean", {"C10": 1.0}, nu=0.5)
    # aliases
    assert make_material("MR5", MATERIALS["mooney_rivlin_5"], nu=0.4).model == "mooney_rivlin_5"
