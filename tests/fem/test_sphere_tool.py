"""Force-controlled rigid sphere (LiverIndenter.push_to_force) against physics on a small liver-like body.

The ellipsoid stand-in liver (129 vertices, P2, ~2.5k dofs) with the model's supports; a sphere of
R = 10 mm (the body's facets are ~20 mm: a smaller sphere would fall between quadrature points).
Targets are forces a displacement-controlled push produces or nearby ones, so no number is hard-coded:
* the prescribed vector is reached (normal and 25 deg tilted) and the supports balance it;
* force control and displacement control give the same state at the same force;
* a force the frictionless sphere cannot hold within the allowed slide fails with that reason;
* a force below the tolerance is the sphere touching at rest.
"""

import numpy as np
import pytest

from liverforce.fem import BoundaryParams, LiverModel, make_material
from liverforce.fem.indenter import LiverIndenter
from liverforce.fem.testing import ellipsoid_liver

R = 10.0


@pytest.fixture(scope="module")
def liver():
    m = ellipsoid_liver(nrefs=2)
    mat = make_material("yeoh", {"C10": 1.61e-3, "C20": 12.5e-3, "C30": 5.31e-3}, nu=0.49)
    bp = BoundaryParams.from_totals(m["points"], m["facets"], m["facet_region"])
    model = LiverModel(m["points"], m["tets"], m["facets"], m["facet_region"], mat, bp)
    P = m["points"][np.unique(m["facets"][m["facet_visible"]])]
    x0 = P[np.argmax(P[:, 1] + P[:, 2])]  # anterior-superior, away from the IVC patch
    return model, x0


def _indenter(liver, direction=None):
    model, x0 = liver
    return LiverIndenter(model, x0, radius_mm=R, direction=direction, candidate_radius_mm=100.0)


def _tilted(ind, deg):
    n = ind.normal
    t = np.cross(n, [0.0, 1.0, 0.0])
    t /= np.linalg.norm(t)
    a = np.radians(deg)
    return -np.cos(a) * n + np.sin(a) * t


def _check_balance(res):
    F = res.force_on_liver
    np.testing.assert_allclose(res.reactions["indenter"], F, atol=0)  # the force of the sphere on the liver
    supports = sum(res.reactions[k] for k in ("ivc", "ligament", "visceral", "rib"))
    assert np.linalg.norm(supports + F) < 1e-6 * np.linalg.norm(F)  # reactions + tool force = 0
    assert np.linalg.norm(res.reactions["imbalance"]) < 1e-6 * np.linalg.norm(F)


@pytest.mark.parametrize("deg", [0.0, 25.0])
def test_force_control_reaches_the_prescribed_vector(liver, deg):
    ind = _indenter(liver)
    ref = ind.push([6.0])  # the force scale of a 6 mm push along the normal
    assert ref.converged, ref.reason
    mag = float(np.linalg.norm(ref.results[0].force_on_sphere))
    target = mag * _tilted(ind, deg)
    res = ind.push_to_force(target, max_slide_mm=30.0, first_depth_mm=4.0)
    assert res.converged, res.reason
    F = res.force_on_liver
    assert np.linalg.norm(F - target) <= max(0.01 * mag, 1e-3)
    # the label is what the contact exerts at the returned state
    np.testing.assert_allclose(F, -ind.contact.force_on_sphere(res.state), rtol=1e-12, atol=1e-15)
    ang = np.degrees(np.arccos(-F @ ind.normal / np.linalg.norm(F)))
    assert abs(ang - deg) < 1.0
    _check_balance(res)
    assert res.newton_iterations > 0 and res.outer_iterations >= 1 and res.final_residual < 1e-6
    assert res.min_principal_stretch < 1.0 < res.max_principal_stretch
    if deg > 0:  # frictionless: the inclined force needs the sphere off the normal line
        assert res.slide_mm > 0.1


def test_force_and_displacement_control_give_the_same_state(liver):
    ind = _indenter(liver)
    d = _tilted(ind, 15.0)
    ind.direction, ind.start = d, ind.point - R * d
    path = ind.push([6.0])
    assert path.converged, path.reason
    ref = path.results[0]
    F_ref = -ref.force_on_sphere
    res = _indenter(liver).push_to_force(F_ref, rtol=1e-5, atol=1e-7, max_slide_mm=30.0, first_depth_mm=4.0)
    assert res.converged, res.reason
    assert np.linalg.norm(res.force_on_liver - F_ref) <= 1e-5 * np.linalg.norm(F_ref)
    # same force -> same sphere position and the same body state (to the force tolerance)
    assert np.linalg.norm(res.centre - ref.centre) < 1e-3 * 6.0, (res.centre, ref.centre)
    du = np.abs(res.u_nodes - ref.u_nodes).max()
    assert du < 1e-3 * np.abs(ref.u_nodes).max(), du


def test_a_force_the_frictionless_sphere_cannot_hold_fails_with_a_reason(liver):
    ind = _indenter(liver)
    ref = ind.push([6.0])
    mag = float(np.linalg.norm(ref.results[0].force_on_sphere))
    res = ind.push_to_force(mag * _tilted(ind, 25.0), max_slide_mm=0.5, first_depth_mm=4.0)
    assert not res.converged
    assert "cannot hold" in res.reason and "tool_max_slide_mm" in res.reason
    # the state returned is an equilibrium whose force is honest (not the target)
    assert np.linalg.norm(res.force_on_liver - mag * _tilted(ind, 25.0)) > 0.01 * mag
    assert res.force_error_n == pytest.approx(np.linalg.norm(res.force_on_liver - res.target_force))


def test_a_force_below_tolerance_is_the_sphere_touching_at_rest(liver):
    res = _indenter(liver).push_to_force([0.0, 0.0, -1e-4])
    assert res.converged and res.newton_iterations == 0
    assert np.all(res.u_nodes == 0.0) and np.all(res.force_on_liver == 0.0)
