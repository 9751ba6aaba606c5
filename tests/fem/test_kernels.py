"""The hand-written numba kernels equal the readable scikit-fem forms (test oracle)."""
import numpy as np
import pytest

from liverforce.fem import forms_skfem as oracle
from liverforce.fem.assembly import Assembler, SparsityPattern, formulation_spec
from liverforce.fem.elements import build_discretization
from liverforce.fem.materials import make_material
from liverforce.fem.testing import box_mesh


@pytest.mark.parametrize("formulation", ["p1", "p2", "p2_mean_dilatation"])
@pytest.mark.parametrize("model, params", [
    ("mooney_rivlin_5", {"C10": 0.3, "C01": 0.2, "C20": 0.1, "C11": 0.05, "C02": 0.07}),
    ("ogden", {"mu1": 0.4, "alpha1": 3.0, "mu2": -0.1, "alpha2": -2.0}),
])
def test_fast_kernel_equals_skfem_assembly(formulation, model, params):
    points, tets, _ = box_mesh((2, 2, 1), size=(2.0, 2.0, 1.0))
    order, mean_dil = formulation_spec(formulation)
    disc = build_discretization(points, tets, order)
    mat = make_material(model, params, nu=0.45)
    pattern = SparsityPattern(disc.element_dofs, np.ones(disc.n_dofs, bool))
    u = 0.03 * np.random.default_rng(3).standard_normal(disc.n_dofs)
    ev = Assembler(disc, mean_dil, pattern).evaluate(u, mat)
    assert ev.valid
    basis = oracle.make_basis(points, disc.tets, order)
    dofs = oracle.dof_map(basis, disc.nodes)
    u_sk = np.zeros(basis.N)
    u_sk[dofs] = u
    f_ref = oracle.internal_force(basis, u_sk, mat, mean_dil)[dofs]
    K_ref = oracle.tangent(basis, u_sk, mat, mean_dil).toarray()[np.ix_(dofs, dofs)]
    K = pattern.matrix(ev.data).toarray()
    assert np.abs(ev.f_int - f_ref).max() <= 1e-12 * np.abs(f_ref).max()
    assert np.abs(K - K_ref).max() <= 1e-12 * np.abs(K_ref).max()
    # and the residual is the gradient of the energy (directional finite difference)
    d = 1e-3 * np.random.default_rng(4).standard_normal(disc.n_dofs)
    ep = Assembler(disc, mean_dil, pattern).evaluate(u + 1e-4 * d, mat, tangent=False).energy
    em = Assembler(disc, mean_dil, pattern).evaluate(u - 1e-4 * d, mat, tangent=False).energy
    assert (ep - em) / 2e-4 == pytest.approx(ev.f_int @ d, rel=1e-6)


class _GenericOnly:
    """Hide ``invariant_based`` so the Assembler takes the generic NumPy path."""

    invariant_based = False

    def __init__(self, material):
        self.isochoric, self.volumetric = material.isochoric, material.volumetric


@pytest.mark.parametrize("formulation", ["p1", "p2", "p2_mean_dilatation"])
@pytest.mark.parametrize("model, params", [
    ("mooney_rivlin_5", {"C10": 0.3, "C01": 0.2, "C20": 0.1, "C11": 0.05, "C02": 0.07}),
    ("yeoh", {"C10": 0.3, "C20": 0.2, "C30": 0.1}),
])
def test_fused_numba_path_equals_generic_path(formulation, model, params):
    points, tets, _ = box_mesh((2, 1, 1), size=(2.0, 1.0, 1.0))
    order, mean_dil = formulation_spec(formulation)
    disc = build_discretization(points, tets, order)
    mat = make_material(model, params, nu=0.45)
    asm = Assembler(disc, mean_dil, SparsityPattern(disc.element_dofs, np.ones(disc.n_dofs, bool)))
    u = 0.03 * np.random.default_rng(5).standard_normal(disc.n_dofs)
    fast_r = asm.evaluate(u, mat, tangent=False)
    fast = asm.evaluate(u, mat, tangent=True)
    generic = asm.evaluate(u, _GenericOnly(mat), tangent=True)
    assert fast_r.data is None
    for ev in (fast_r, fast):
        assert ev.energy == pytest.approx(generic.energy, rel=1e-13)
        assert np.abs(ev.f_int - generic.f_int).max() <= 1e-13 * np.abs(generic.f_int).max()
    assert np.abs(fast.data - generic.data).max() <= 1e-12 * np.abs(generic.data).max()
