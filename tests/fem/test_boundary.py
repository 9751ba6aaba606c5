"""Boundary terms: tool traction sums to F, foundation springs, reactions balance the load."""
import numpy as np
import pytest

from liverforce.fem import BoundaryParams, LiverModel, SolverOptions, ToolLoad, make_material
from liverforce.fem.boundary import per_area_stiffness, region_areas, spring_matrix, tool_nodal_forces
from liverforce.fem.elements import build_discretization
from liverforce.fem.testing import box_mesh, ellipsoid_liver


@pytest.fixture(scope="module")
def liver():
    return ellipsoid_liver(2)


@pytest.mark.parametrize("order", [1, 2])
@pytest.mark.parametrize("radius", [2.0, 8.0, 40.0])
def test_tool_loads_sum_exactly_to_force(liver, order, radius):
    P, facets = liver["points"], liver["facets"]
    disc = build_discretization(P, liver["tets"], order)
    x0 = P[np.unique(facets[liver["facet_visible"]])][0]
    F = np.array([0.3, -1.1, -2.7])
    f = tool_nodal_forces(disc, P, facets, x0, F, radius).reshape(-1, 3)
    assert np.abs(f.sum(axis=0) - F).max() <= 1e-14 * np.linalg.norm(F)
    # loads sit around the exertion point: load-weighted centroid within ~radius
    w = np.abs(f[:, 2])
    centroid = (w[:, None] * disc.nodes).sum(axis=0) / w.sum()
    assert np.linalg.norm(centroid - x0) < max(radius, 30.0)


def test_tool_load_far_from_surface_is_refused(liver):
    disc = build_discretization(liver["points"], liver["tets"], 1)
    with pytest.raises(ValueError, match="no surface under the tool"):
        tool_nodal_forces(disc, liver["points"], liver["facets"], [1e4, 0, 0], [0, 0, 1], 1.0)


def test_foundation_stiffness_total_over_area():
    assert per_area_stiffness(56.3, 1000.0) == pytest.approx(0.0563)
    with pytest.raises(ValueError):
        per_area_stiffness(1.0, 0.0)


@pytest.mark.parametrize("formulation", ["p1", "p2_mean_dilatation"])
def test_block_on_foundation_translates_by_force_over_total_stiffness(formulation):
    """A stiff block on a soft foundation (bottom, region 3) moves ~ F / (k A)."""
    points, tets, facets = box_mesh((2, 2, 1), size=(20.0, 20.0, 5.0))
    region = np.where(points[facets][:, :, 2].max(axis=1) < 1e-9, 3, 0)
    total_n, total_t = 2.0, 0.5  # N/mm over the 400 mm² bottom
    area = region_areas(points, facets, region)[3]
    assert area == pytest.approx(400.0)
    bp = BoundaryParams(0, 0, per_area_stiffness(total_n, area), per_area_stiffness(total_t, area), 0, 0)
    mat = make_material("neo_hookean", {"C10": 5.0}, nu=0.3)  # stiff body
    model = LiverModel(points, tets, facets, region, mat, bp, SolverOptions(formulation=formulation, tol=1e-10))
    F = np.array([0.01, 0.0, -0.02])
    res = model.solve(ToolLoad([10.0, 10.0, 5.0], F, 3.0))
    assert res.converged, res.reason
    u_mean = res.u_nodes[points[:, 2] < 1e-9].mean(axis=0)  # base (the block may tilt a little)
    assert u_mean[2] == pytest.approx(F[2] / total_n, rel=0.02)
    assert u_mean[0] == pytest.approx(F[0] / total_t, rel=0.02)
    assert np.allclose(res.reactions["visceral"], -F, atol=1e-9)


def test_spring_matrix_is_symmetric_and_separates_normal_and_tangential(liver):
    P, facets, region = liver["points"], liver["facets"], liver["facet_region"]
    disc = build_discretization(P, liver["tets"], 2)
    K = spring_matrix(disc, P, facets, region, {3: (2.0, 0.0)})
    assert abs(K - K.T).max() < 1e-12 * abs(K).max()
    # a rigid translation tangential to a flat patch costs nothing when k_t = 0:
    # check on the energy of a uniform translation u = t: E = 1/2 sum k_n (n.t)^2 dA
    t = np.array([0.3, -0.2, 1.0])
    u = np.tile(t, disc.n_nodes)
    from liverforce.fem.elements import facet_geometry
    area, n = facet_geometry(P, facets)
    sel = region == 3
    expected = 0.5 * 2.0 * np.sum(area[sel] * (n[sel] @ t) ** 2)
    assert 0.5 * u @ (K @ u) == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("formulation", ["p1", "p2_mean_dilatation"])
def test_reactions_balance_the_tool_load(liver, formulation):
    P = liver["points"]
    mat = make_material("yeoh", {"C10": 1.61e-3, "C20": 12.5e-3, "C30": 5.31e-3}, nu=0.49)
    bp = BoundaryParams.from_totals(P, liver["facets"], liver["facet_region"])
    model = LiverModel(P, liver["tets"], liver["facets"], liver["facet_region"], mat, bp,
                       SolverOptions(formulation=formulation))
    x0 = P[np.argmax(P[:, 2] + 0.3 * P[:, 1])]
    F = np.array([0.5, 0.2, -3.0])
    res = model.solve(ToolLoad(x0, F, 5.0))
    assert res.converged, res.reason
    r = res.reactions
    assert np.allclose(r["tool"], F, rtol=1e-13)
    supports = r["ivc"] + r["ligament"] + r["visceral"] + r["rib"]
    assert np.linalg.norm(supports + F) <= 1e-6 * np.linalg.norm(F)
    assert np.linalg.norm(r["imbalance"]) <= 1e-6 * np.linalg.norm(F)
    for name in ("ivc", "ligament", "visceral", "rib"):
        assert np.linalg.norm(r[name]) > 1e-3  # every support carries load
    # rib: no normal motion (penalty) -> small normal displacement there
    fn = liver["facets"][liver["facet_region"] == 4]
    assert np.abs(res.u_nodes[np.unique(fn)]).max() < np.abs(res.u_nodes).max()
