"""Support models a reviewer can choose: unilateral rib contact and gravity (issue #18).

* Unilateral rib: under a pull away from the ribs the rib carries nothing and the
  liver separates; under a push it is the bilateral penalty; its residual is the
  gradient of its energy and its generalised tangent the derivative of the
  residual (finite differences away from the contact kink); Newton converges.
* Gravity: with no tool the supports carry exactly the liver's weight; disabled
  options leave the solution bit for bit as it was.
"""
from types import SimpleNamespace

import numpy as np
import pytest

from liverforce.fem import BoundaryParams, LiverModel, SolverOptions, ToolLoad, make_material
from liverforce.fem.boundary import UnilateralPenalty, body_force_loads, gravity_body_force, vertex_normals
from liverforce.fem.elements import build_discretization
from liverforce.fem.testing import box_mesh, ellipsoid_liver

YEOH = make_material("yeoh", {"C10": 1.61e-3, "C20": 12.5e-3, "C30": 5.31e-3}, nu=0.49)
SUPPORTS = ("ivc", "ligament", "visceral", "rib")


@pytest.fixture(scope="module")
def block():
    """A 40 x 40 x 20 mm block on a soft foundation (bottom), a rib penalty on its +x face."""
    points, tets, facets = box_mesh((4, 4, 2), size=(40.0, 40.0, 20.0))
    X = points[facets]
    region = np.zeros(len(facets), np.int64)
    region[X[:, :, 2].max(axis=1) < 1e-9] = 3
    region[X[:, :, 0].min(axis=1) > 40.0 - 1e-9] = 4
    return points, tets, facets, region


def _block_model(block, rib_contact, formulation="p2_mean_dilatation", **kw):
    points, tets, facets, region = block
    bp = BoundaryParams(0, 0, 0.002, 0.0005, 0.1, 0.0, rib_contact=rib_contact, **kw)
    return LiverModel(points, tets, facets, region, YEOH, bp, SolverOptions(formulation=formulation, tol=1e-10))


TOOL_X0 = np.array([0.0, 20.0, 10.0])  # centre of the -x face, opposite the rib


@pytest.fixture(scope="module")
def liver():
    return ellipsoid_liver(2)


def _liver_model(liver, rib_contact="bilateral", body=(0.0, 0.0, 0.0), **opt):
    P, F, R = liver["points"], liver["facets"], liver["facet_region"]
    bp = BoundaryParams.from_totals(P, F, R, rib_contact=rib_contact, body_force_n_per_mm3=body)
    return LiverModel(P, liver["tets"], F, R, YEOH, bp, SolverOptions(**opt))


# ---------------------------------------------------------------- unilateral rib
def test_unilateral_rib_separates_under_pull(block):
    points, _, facets, region = block
    rib_nodes = np.unique(facets[region == 4])
    bil = _block_model(block, "bilateral").solve(ToolLoad(TOOL_X0, [-1.0, 0, 0], 5.0))
    uni_model = _block_model(block, "unilateral")
    uni = uni_model.solve(ToolLoad(TOOL_X0, [-1.0, 0, 0], 5.0))
    assert bil.converged and uni.converged, (bil.reason, uni.reason)
    # the bilateral rib holds the block back; the unilateral one lets go entirely
    assert bil.reactions["rib"][0] > 0.3
    assert np.all(uni.reactions["rib"] == 0.0)
    assert not uni_model.rib_contact.active(uni.state).any()
    # separation: displacement away from the rib surface (-u.n, n = +x) > 0 at every rib node
    gap = -uni.u_nodes[rib_nodes, 0]
    assert gap.min() > 0.5 and gap.max() > 2.0  # mm: the block swings off the rib
    # the remaining supports take the whole load
    supports = sum(uni.reactions[k] for k in SUPPORTS)
    assert np.linalg.norm(supports + uni.reactions["tool"]) <= 1e-8
    assert np.linalg.norm(uni.reactions["visceral"] - [1.0, 0, 0]) <= 1e-8


@pytest.mark.parametrize("formulation", ["p2", "p2_mean_dilatation"])
def test_unilateral_rib_equals_bilateral_under_push(block, formulation):
    """(On this coarse block the locking P1 tets bend the rib face partly off the rib: not a push there.)"""
    load = ToolLoad(TOOL_X0, [1.0, 0.0, 0.0], 5.0)
    bil = _block_model(block, "bilateral", formulation).solve(load)
    uni_model = _block_model(block, "unilateral", formulation)
    uni = uni_model.solve(load)
    assert bil.converged and uni.converged
    assert uni_model.rib_contact.active(uni.state).all()  # the whole rib face in contact
    scale = np.abs(bil.u_nodes).max()
    assert np.abs(uni.u_nodes - bil.u_nodes).max() <= 1e-8 * scale
    for k in SUPPORTS:
        assert np.abs(uni.reactions[k] - bil.reactions[k]).max() <= 1e-8, k
    assert bil.reactions["rib"][0] < -0.3  # the rib pushes back


def test_unilateral_penalty_energy_force_tangent_consistent(liver):
    """Force = dE/du and tangent = dF/du by central differences, at a state with part of the rib in contact."""
    P, F, R = liver["points"], liver["facets"], liver["facet_region"]
    disc = build_discretization(P, liver["tets"], 2)
    rib = F[R == 4]
    term = UnilateralPenalty(disc, P, rib, 0.1, vertex_normals(P, rib))
    rng = np.random.default_rng(3)
    u = rng.normal(scale=0.5, size=disc.n_dofs)
    un = term.normal_displacement(u)
    act = un >= 0
    assert 0.1 < act.mean() < 0.9  # a mixed active set
    h = 1e-6
    assert np.abs(un).min() > 100 * h * 10  # no quadrature point at the kink within the differences
    E, f = term.energy_force(u)
    assert E > 0
    K = term.tangent_matrix(u)
    assert abs(K - K.T).max() <= 1e-14 * abs(K).max()
    for _ in range(3):
        d = rng.normal(size=disc.n_dofs)
        Ep, fp = term.energy_force(u + h * d)
        Em, fm = term.energy_force(u - h * d)
        assert (Ep - Em) / (2 * h) == pytest.approx(f @ d, rel=1e-7)
        fd = (fp - fm) / (2 * h)
        assert np.linalg.norm(fd - K @ d) <= 1e-7 * np.linalg.norm(fd)
    # the energy is the unilateral part of the bilateral one: 0.5 k sum W <u.n>_+^2
    assert E == pytest.approx(0.5 * 0.1 * np.sum(term.W * np.maximum(un, 0) ** 2), rel=1e-13)


def test_system_tangent_with_unilateral_rib_is_consistent(liver):
    """The assembled residual (material + springs + unilateral rib) against its Newton matrix."""
    model = _liver_model(liver, "unilateral")
    system = model.system
    rng = np.random.default_rng(0)
    u = np.zeros(model.n_dofs)
    rib_dofs = model.rib_contact.dofs.ravel()
    u[rib_dofs] = rng.normal(scale=0.3, size=rib_dofs.size)  # rib points in and out of contact
    u[system.fixed] = 0.0
    act = model.rib_contact.active(u)
    assert 0.2 < act.mean() < 0.8
    f_load = np.zeros(model.n_dofs)
    ev, R, _ = system._evaluate(u, YEOH, f_load, tangent=True)
    K = system.tangent_matrix(ev.data, u)
    free = system.free
    h = 1e-6
    for _ in range(3):
        d = np.zeros(model.n_dofs)
        d[free] = rng.normal(size=free.sum())
        Rp = system._evaluate(u + h * d, YEOH, f_load, tangent=False)[1]
        Rm = system._evaluate(u - h * d, YEOH, f_load, tangent=False)[1]
        fd = ((Rp - Rm) / (2 * h))[free]
        assert np.linalg.norm(fd - K @ d[free]) <= 1e-6 * np.linalg.norm(fd)
    # at rest the rib counts as touching: the rest tangent is the bilateral one (stiffness probe)
    bil = _liver_model(liver, "bilateral")
    ev0 = system.assembler.evaluate(np.zeros(model.n_dofs), YEOH, True)
    K_uni, K_bil = system.tangent_matrix(ev0.data), bil.system.tangent_matrix(ev0.data)
    assert abs(K_uni - K_bil).max() <= 1e-13 * abs(K_bil).max()


@pytest.mark.parametrize("modified_newton", [False, True])
def test_newton_converges_with_unilateral_rib_on_a_liver(liver, modified_newton):
    P, F, R = liver["points"], liver["facets"], liver["facet_region"]
    vn = vertex_normals(P, F[R == 4])
    rib_nodes = np.unique(F[R == 4])
    x0 = P[np.argmin(P[:, 0])]  # far side from the (right lateral) ribs
    bil_model = _liver_model(liver, "bilateral", modified_newton=modified_newton)
    uni_model = _liver_model(liver, "unilateral", modified_newton=modified_newton)
    for force in ([-2.0, 0.0, 0.0], [2.0, 0.0, 0.0]):  # pull off the ribs, push into them
        bil = bil_model.solve(ToolLoad(x0, force, 5.0))
        uni = uni_model.solve(ToolLoad(x0, force, 5.0))
        assert uni.converged, uni.reason
        assert uni.newton_iterations <= bil.newton_iterations + 6
        assert np.linalg.norm(uni.reactions["imbalance"]) <= 1e-6 * 2.0
        if force[0] < 0:
            assert np.all(uni.reactions["rib"] == 0.0)
            assert np.all(np.einsum("ij,ij->i", uni.u_nodes[rib_nodes], vn[rib_nodes]) < 0)  # separated
        else:  # almost all of the rib in contact: close to the bilateral support
            rib_bil = bil.reactions["rib"]
            assert np.linalg.norm(uni.reactions["rib"] - rib_bil) <= 0.01 * np.linalg.norm(rib_bil)


def test_unilateral_rib_refuses_a_tangential_spring():
    with pytest.raises(ValueError, match="frictionless"):
        BoundaryParams(rib_kt=0.01, rib_contact="unilateral")
    with pytest.raises(ValueError, match="rib_contact"):
        BoundaryParams(rib_contact="sticky")


# ---------------------------------------------------------------- gravity
def test_gravity_body_force_units():
    b = gravity_body_force(1060.0, [0, 0, -2])
    assert b == pytest.approx([0, 0, -1060.0 * 9.80665e-9], rel=1e-15)  # kg/m^3 * m/s^2 = N/m^3; 1e-9 m^3/mm^3
    with pytest.raises(ValueError):
        gravity_body_force(1060.0, [0, 0, 0])


@pytest.mark.parametrize("order", [1, 2])
def test_body_force_loads_sum_to_the_weight(liver, order):
    disc = build_discretization(liver["points"], liver["tets"], order)
    b = np.array([0.1, -0.2, 1.0])
    f = body_force_loads(disc, b).reshape(-1, 3)
    assert np.abs(f.sum(axis=0) - b * disc.volume.sum()).max() <= 1e-12 * disc.volume.sum()


@pytest.mark.parametrize("rib_contact", ["bilateral", "unilateral"])
def test_supports_carry_the_weight_under_gravity_alone(liver, rib_contact):
    P, T = liver["points"], liver["tets"]
    X = P[T]
    volume = np.abs(np.linalg.det(X[:, 1:] - X[:, :1])).sum() / 6.0  # mm^3, independent of the FE code
    b = gravity_body_force(1060.0, [0.0, 0.0, -1.0])
    weight = volume * 1060.0 * 9.80665 * 1e-9  # N
    model = _liver_model(liver, rib_contact, body=b, tol=1e-9)
    res = model.solve(ToolLoad(P[np.argmax(P[:, 2])], [0.0, 0.0, 0.0], 5.0))  # no tool force
    assert res.converged, res.reason
    assert res.reactions["gravity"] == pytest.approx([0, 0, -weight], abs=1e-12 * weight)
    assert np.all(res.reactions["tool"] == 0.0)
    supports = sum(res.reactions[k] for k in SUPPORTS)
    assert np.abs(supports - [0, 0, weight]).max() <= 1e-7 * weight
    assert res.u_nodes[:, 2].min() < -0.1  # it sags


def test_gravity_with_a_warm_start_keeps_the_whole_weight(liver):
    P = liver["points"]
    model = _liver_model(liver, body=gravity_body_force(1060.0, [0, 0, -1]), tol=1e-9)
    x0 = P[np.argmax(P[:, 2] + 0.3 * P[:, 1])]
    first = model.solve(ToolLoad(x0, [0.0, 0.0, -1.0], 5.0))
    warm = model.solve(ToolLoad(x0, [0.5, 0.0, -2.0], 5.0), u0=first)
    cold = model.solve(ToolLoad(x0, [0.5, 0.0, -2.0], 5.0))
    assert first.converged and warm.converged and cold.converged
    for k in ("gravity", "tool"):
        assert np.abs(warm.reactions[k] - cold.reactions[k]).max() <= 1e-12
    assert warm.reactions["tool"] == pytest.approx([0.5, 0.0, -2.0], abs=1e-12)
    assert np.abs(warm.u_nodes - cold.u_nodes).max() <= 1e-6 * np.abs(cold.u_nodes).max()
    assert np.linalg.norm(warm.reactions["imbalance"]) <= 1e-7


# ---------------------------------------------------------------- config wiring, defaults unchanged
def test_disabled_options_leave_the_solution_bit_identical(liver):
    from liverforce.config import compose
    from liverforce.pipeline.simulate import boundary_params

    cfg = compose([])["boundary"]
    assert cfg["rib_contact"] == "bilateral" and cfg["gravity"]["enabled"] is False
    mesh = SimpleNamespace(points=liver["points"], facets=liver["facets"], facet_region=liver["facet_region"])
    bp = boundary_params(mesh, cfg)
    legacy = boundary_params(mesh, {k: v for k, v in cfg.items() if k not in ("rib_contact", "gravity")})
    before = BoundaryParams.from_totals(liver["points"], liver["facets"], liver["facet_region"], 56.3, 42.6, 1.0, 0.1)
    assert bp == legacy == before
    assert bp.body_force_n_per_mm3 == (0.0, 0.0, 0.0) and bp.rib_contact == "bilateral"
    P = liver["points"]
    load = ToolLoad(P[np.argmax(P[:, 2])], [0.3, 0.0, -2.0], 5.0)
    a = LiverModel(P, liver["tets"], liver["facets"], liver["facet_region"], YEOH, bp).solve(load)
    assert a.converged
    assert np.array_equal(a.u_nodes, _liver_model(liver).solve(load).u_nodes)
    assert np.all(a.reactions["gravity"] == 0.0)

    on = boundary_params(mesh, {**cfg, "rib_contact": "unilateral",
                                "gravity": {"enabled": True, "density_kg_per_m3": 1000.0, "direction": [0, -2, 0]}})
    assert on.rib_contact == "unilateral"
    assert on.body_force_n_per_mm3 == pytest.approx((0.0, -9.80665e-6, 0.0), rel=1e-14)


@pytest.mark.parametrize("override, key", [
    ("boundary.rib_contact=sticky", "boundary.rib_contact"),
    ("boundary.gravity.density_kg_per_m3=1.06", "boundary.gravity.density_kg_per_m3"),
    ("boundary.gravity.direction=[0,0,0]", "boundary.gravity.direction"),
])
def test_config_refuses_bad_support_options(override, key):
    from liverforce.config import ConfigError, compose

    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        compose([override])
