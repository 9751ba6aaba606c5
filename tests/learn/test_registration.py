"""Refining the camera's registration from its view before the tool pushes (liverforce.learn.registration).

The pre-operative surface is a spherical cap (radius 80 mm) round the exertion point, the unloaded cloud the
camera's noisy view of it with the instrument touching there (liverforce.learn.observation). The camera side
is then moved by a known rigid motion; the refinement must undo it where the model reads it: the exertion
point's position and the surface's height round it. The turn about the normal is not measured (a cap turned
about its own axis is the same cap), so only those are checked.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from liverforce.learn.cloud_features import CloudGridSpec, ReferenceSurface
from liverforce.learn.observation import ObservationConfig, observe
from liverforce.learn.registration import RegistrationError, refine_registration

R_CAP = 80.0
P = np.zeros(3)
CAM = np.array([30.0, -25.0, 80.0])


def cap(radius=R_CAP, half=45.0, n=91, bumps=0.0):
    """A spherical cap through the origin, outward +z (``bumps``: a sinusoid of that amplitude added, mm)."""
    x = np.linspace(-half, half, n)
    X, Y = np.meshgrid(x, x)
    Z = np.sqrt(radius**2 - X**2 - Y**2) - radius + bumps * np.sin(X / 4.0) * np.sin(Y / 4.0)
    q = np.arange((n - 1) * n).reshape(n - 1, n)[:, : n - 1].ravel()
    T = np.concatenate([np.column_stack([q, q + 1, q + n + 1]), np.column_stack([q, q + n + 1, q + n])])
    return np.column_stack([X.ravel(), Y.ravel(), Z.ravel()]), T


def spec(instrument=True):
    return CloudGridSpec(grid_size=16, half_width_mm=20.0, kernel_radius_cells=1.5,
                         instrument_radius_mm=2.5 if instrument else 0.0, instrument_point_sd_mm=0.5,
                         instrument_tip_sd_mm=0.5)


@pytest.fixture(scope="module")
def scene():
    V, T = cap()
    s = spec()
    ref = ReferenceSurface.from_patch(V, T, P, np.eye(3), s)
    cfg = ObservationConfig(n_points=(5000, 5000), noise_sd_mm=0.5, roi_radius_mm=32.0, instrument_in_cloud=True)
    with_tool, rec = observe(V, T, P, [0, 0, 1], cfg, seed=3, camera_position_mm=CAM)
    assert rec.n_instrument_points > 50
    return V, T, ref, with_tool, with_tool[: rec.n_points - rec.n_instrument_points]


def motion(shift_mm, turn_deg, seed=0):
    """A shift in a random direction and a turn about a random axis through the cap's centre (0, 0, -80)."""
    rng = np.random.default_rng(seed)
    d, a = rng.normal(size=3), rng.normal(size=3)
    Q = Rotation.from_rotvec(math.radians(turn_deg) * a / np.linalg.norm(a)).as_matrix()
    c = np.array([0.0, 0.0, -R_CAP])
    return Q, c - Q @ c + shift_mm * d / np.linalg.norm(d)


def height_error(points):
    """Signed distance of points from the cap (mm, outward)."""
    return np.linalg.norm(points - np.array([0.0, 0.0, -R_CAP]), axis=1) - R_CAP


RING = np.array([[15.0 * math.cos(t), 15.0 * math.sin(t), 0.0] for t in np.linspace(0, 2 * math.pi, 12, False)])
RING[:, 2] = np.sqrt(R_CAP**2 - 15.0**2) - R_CAP  # on the cap, 15 mm round the exertion point


TIP_ERROR = np.array([0.4, -0.3, 0.3])  # the robot's tip at contact, off by 0.5 mm along the surface


@pytest.mark.parametrize("shift_mm, turn_deg", [(0.0, 0.0), (2.0, 0.0), (0.0, 2.0), (3.0, 3.0), (6.0, 1.0)])
def test_the_refinement_undoes_the_cameras_misregistration(scene, shift_mm, turn_deg):
    V, T, ref, cloud0, _ = scene
    Q, b = motion(shift_mm, turn_deg)
    fix = refine_registration(ref, spec(), cloud0 @ Q.T + b, Q @ (P + TIP_ERROR) + b)
    assert fix.anchor == "instrument"
    p = fix.points(Q @ P + b)  # where the camera side's exertion point lands
    # along the surface from the instrument's axis, not the tip it started from (0.5 mm off): 0.013-0.038 mm
    assert abs(p[2]) < 0.05 and np.hypot(p[0], p[1]) < 0.1
    ring = fix.points(RING @ Q.T + b)
    assert np.abs(height_error(ring)).max() < 0.1  # the surface round the tool is back on the cap
    assert 0.4 < fix.rms_mm < 0.6  # the cloud's own noise (0.5 mm) is what is left
    moved = np.hypot(*(Q @ P + b)[:2])
    if shift_mm or turn_deg:
        assert fix.rms_before_mm > 2 * fix.rms_mm or moved > 1.0  # a real misregistration was there to undo
    np.testing.assert_allclose(fix.A @ fix.A.T, np.eye(3), atol=1e-12)  # rigid


def test_without_the_instrument_the_contact_tip_gives_the_shift_along_the_surface(scene):
    V, T, ref, _, liver_only = scene
    Q, b = motion(2.0, 2.0)
    tip_error = np.array([0.3, -0.2, 0.4])  # the robot's tip at contact, off by this
    fix = refine_registration(ref, spec(instrument=False), liver_only @ Q.T + b, Q @ (P + tip_error) + b)
    assert fix.anchor == "contact tip"
    p = fix.points(Q @ P + b)
    assert abs(p[2]) < 0.05  # along the normal: from the surface, not the tip
    R3 = fix.A @ Q  # the composite's turn: only about the normal is left
    e = R3 @ tip_error
    np.testing.assert_allclose(p[:2], -e[:2], atol=0.05)  # along the surface: the tip's own error, no more
    # nothing to anchor the shift along the surface: it stays; the height is still corrected. With the instrument
    # in the cloud too: its fit starts from the tip at contact, and without one it is not used (started from the
    # exertion point, its prior would confirm it)
    _, _, _, cloud0, _ = scene
    for s, cloud in ((spec(instrument=False), liver_only), (spec(), cloud0)):
        fix0 = refine_registration(ref, s, cloud @ Q.T + b)
        assert fix0.anchor == "none"
    fix0 = refine_registration(ref, spec(instrument=False), liver_only @ Q.T + b)
    p0 = fix0.points(Q @ P + b)
    assert abs(height_error(p0[None])[0]) < 0.05
    assert np.hypot(*(Q @ P + b)[:2]) > 1.0 and abs(np.hypot(*p0[:2]) - np.hypot(*(Q @ P + b)[:2])) < 0.5


def test_a_cloud_in_metres_is_refused_naming_the_units(scene):
    V, T, ref, cloud0, _ = scene
    with pytest.raises(RegistrationError, match="same units and frame"):
        refine_registration(ref, spec(), cloud0 / 1000.0, P)
    with pytest.raises(RegistrationError, match="not finite"):
        refine_registration(ref, spec(), cloud0, [np.nan, 0.0, 0.0])
    with pytest.raises(RegistrationError, match="one .3,. point"):
        refine_registration(ref, spec(), cloud0, [0.0, 0.0])


def test_a_registration_too_far_off_is_refused(scene):
    V, T, ref, cloud0, _ = scene
    with pytest.raises(RegistrationError, match="register the pre-operative surface to the camera again"):
        refine_registration(ref, spec(), cloud0 + [0.0, 0.0, 12.0], P + [0.0, 0.0, 12.0])


def test_a_cloud_of_another_surface_is_refused(scene):
    V, T, ref, _, _ = scene
    Vb, Tb = cap(bumps=6.0)
    cfg = ObservationConfig(n_points=(5000, 5000), noise_sd_mm=0.5, roi_radius_mm=32.0)
    other, _ = observe(Vb, Tb, P, [0, 0, 1], cfg, seed=4, camera_position_mm=CAM)
    with pytest.raises(RegistrationError, match="rms"):
        refine_registration(ref, spec(), other, P)


def changed(x):
    """A smooth change of the cap's shape since the scan (heights, mm): raised, tilted and bent (its curvature
    changed) round the exertion point, about 2 mm at the grid's edge."""
    x = np.asarray(x, dtype=np.float64)
    u, v = x[:, 0], x[:, 1]
    dz = 0.5 + 0.05 * u + 0.004 * u**2 - 0.003 * u * v + 0.0025 * v**2
    return x + np.column_stack([0 * u, 0 * u, dz])


def dent(x, depth=2.5, width=6.0):
    """The tool's dent at the exertion point (mm, into the surface)."""
    x = np.asarray(x, dtype=np.float64)
    return x - np.column_stack([0 * x[:, 0], 0 * x[:, 0], depth * np.exp(-(x[:, 0] ** 2 + x[:, 1] ** 2) / width**2)])


@pytest.fixture(scope="module")
def changed_scene():
    """The cap changed in shape since the scan; its unloaded cloud (the instrument touching at the exertion point
    of the changed surface) and the points of the changed surface with the tool's dent, noise-free."""
    V, T = cap()
    s = spec()
    ref = ReferenceSurface.from_patch(V, T, P, np.eye(3), s)
    V2 = changed(V)
    p2 = changed(P[None])[0]
    cfg = ObservationConfig(n_points=(5000, 5000), noise_sd_mm=0.5, roi_radius_mm=32.0, instrument_in_cloud=True)
    cloud0, _ = observe(V2, T, p2, [0, 0, 1], cfg, seed=5, camera_position_mm=CAM + p2)
    near = V[np.hypot(V[:, 0], V[:, 1]) < 18.0]
    return ref, cloud0, p2, near


def test_a_change_of_shape_since_the_scan_is_taken_off_and_the_dent_kept(changed_scene):
    """The loaded surface is the changed surface with the tool's dent: refined with the change of shape, the
    dent is read against the cap as it would be on the scanned liver; refined rigidly, the bend is left in."""
    ref, cloud0, p2, near = changed_scene
    want = height_error(dent(near))  # the dent on the scanned cap: what the model was trained to read
    loaded = dent(changed(near))  # what the camera sees now (noise-free here)
    fix = refine_registration(ref, spec(), cloud0, p2)
    rigid = refine_registration(ref, spec(), cloud0, p2, shape_degree=0)
    assert not fix.rigid and rigid.rigid and rigid.shape == () and 2.5 < fix.shape_mm < 4.5  # 3.5 mm here
    err = np.abs(height_error(fix.points(loaded)) - want)
    err_rigid = np.abs(height_error(rigid.points(loaded)) - want)
    assert err.max() < 0.15  # fitted to 0.5 mm noise: 0.02 mm here
    assert err_rigid.max() > 0.6 and np.median(err_rigid) > 10 * np.median(err)  # 1.2 mm; medians 0.75, 0.007 mm
    assert 0.4 < fix.rms_shape_mm < 0.6 and fix.rms_shape_mm < fix.rms_mm - 0.05  # the noise is what is left
    # the dent itself is not taken for a change of shape: at the exertion point it is read at its depth
    top = np.argmin(np.hypot(near[:, 0], near[:, 1]))
    assert abs(height_error(fix.points(loaded[top:top + 1]))[0] + 2.5) < 0.15
    # the shape's correction is a function of the point only: the tip at contact lands on the cap
    assert abs(height_error(fix.points(p2[None]))[0]) < 0.1
    d = fix.to_dict()
    assert d["shape_degree"] == 3 and len(d["shape_coefficients"]) == 10 and "change of shape" in fix.describe()
    np.testing.assert_allclose(rigid.points(loaded), loaded @ rigid.A.T + rigid.t)  # rigid: the matrix alone
    # the compiled reshaping is the fitted polynomial: the height taken off along the reference's normal
    from liverforce.learn.registration import _shape_basis

    y = loaded @ fix.A.T + fix.t
    L = (y - fix.shape_origin) @ fix.shape_R.T
    dz = _shape_basis(L[:, 0], L[:, 1], 3, fix.shape_extent_mm) @ np.asarray(fix.shape)
    np.testing.assert_allclose(fix.points(loaded), y - dz[:, None] * fix.shape_R[2], atol=1e-12)
    np.testing.assert_allclose(fix.points(loaded[0]), fix.points(loaded[:1])[0], atol=1e-12)  # one point, (3,)


def cloud0_of_cap(V, T):
    cfg = ObservationConfig(n_points=(3000, 3000), noise_sd_mm=0.5, roi_radius_mm=32.0)
    return observe(V, T, P, [0, 0, 1], cfg, seed=8, camera_position_mm=CAM)[0]


def test_a_change_of_shape_beyond_a_local_correction_is_refused(scene):
    V, T, ref, _, _ = scene
    V2 = V.copy()
    V2[:, 2] += 0.016 * (V[:, 0] ** 2 - V[:, 1] ** 2)  # a saddle: 6.4 mm up and down 20 mm from the exertion point
    cfg = ObservationConfig(n_points=(5000, 5000), noise_sd_mm=0.5, roi_radius_mm=32.0)
    other, _ = observe(V2, T, P, [0, 0, 1], cfg, seed=6, camera_position_mm=CAM)
    with pytest.raises(RegistrationError, match="changed shape here since the scan"):
        refine_registration(ref, spec(instrument=False), other, P)
    with pytest.raises(RegistrationError, match=r"after the best rigid fit \("):  # rigid only: not on the surface
        refine_registration(ref, spec(instrument=False), other, P, shape_degree=0)
    # too few points for the change of shape: the rigid fit as it was, and it says so
    import liverforce.learn.registration as rg

    few = refine_registration(ref, spec(instrument=False), cloud0_of_cap(V, T), P)
    assert not few.rigid
    keep = rg.SHAPE_MIN_POINTS
    try:
        rg.SHAPE_MIN_POINTS = 10**6
        few = refine_registration(ref, spec(instrument=False), cloud0_of_cap(V, T), P)
    finally:
        rg.SHAPE_MIN_POINTS = keep
    rigid = refine_registration(ref, spec(instrument=False), cloud0_of_cap(V, T), P, shape_degree=0)
    assert few.rigid and "no change of shape fitted" in few.describe()
    np.testing.assert_array_equal(few.matrix, rigid.matrix)
    for bad in (-1, 5, 2.0, True):
        with pytest.raises(RegistrationError, match="shape_degree"):
            refine_registration(ref, spec(), other, P, shape_degree=bad)


@pytest.mark.parametrize("degree", [1, 2, 3, 4])
def test_the_compiled_reshaping_is_the_fitted_polynomial_of_each_degree(degree):
    from liverforce.learn.registration import Refinement, _shape_basis

    rng = np.random.default_rng(degree)
    R = Rotation.from_rotvec([0.2, -0.1, 0.4]).as_matrix()
    o = np.array([5.0, -3.0, 2.0])
    n = (degree + 1) * (degree + 2) // 2
    fix = Refinement(matrix=np.eye(4), normal_offset_mm=0.0, tangential_mm=0.0, tilt_deg=0.0, anchor="none",
                     n_points=0, rms_before_mm=0.0, rms_mm=0.0, shape_degree=degree,
                     shape=tuple(rng.normal(size=n)), shape_origin=o, shape_R=R, shape_extent_mm=26.0)
    x = o + rng.normal(size=(500, 3)) * 15.0  # some beyond the extent: clamped alike
    L = (x - o) @ R.T
    dz = _shape_basis(L[:, 0], L[:, 1], degree, 26.0) @ np.asarray(fix.shape)
    np.testing.assert_allclose(fix.points(x), x - dz[:, None] * R[2], atol=1e-12)
