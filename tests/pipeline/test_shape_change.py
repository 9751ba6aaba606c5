"""The validation's change of a liver's shape since its scan (liverforce.pipeline.validate.changed_shape): a
smooth field bounded by its amplitude, seeded per liver, and the tool's dent carried with the local frame."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from liverforce.pipeline.validate import changed_shape, local_turn, shape_field


def test_the_field_is_smooth_bounded_and_seeded_per_liver():
    rng = np.random.default_rng(0)
    x = rng.uniform(-100.0, 100.0, size=(5000, 3))
    f = shape_field(7, "L1", 5.0, 150.0, np.zeros(3))
    d = np.linalg.norm(f(x) - x, axis=1)
    assert d.max() <= np.sqrt(3) * 5.0 + 1e-9
    assert abs(np.sqrt(np.mean(d**2)) - 5.0 / np.sqrt(2)) < 0.1 * 5.0  # a sinusoid's rms over a few wavelengths
    np.testing.assert_array_equal(f(x), shape_field(7, "L1", 5.0, 150.0, np.zeros(3))(x))  # same seed, same field
    assert np.abs(shape_field(7, "L2", 5.0, 150.0, np.zeros(3))(x) - f(x)).max() > 0.5  # another liver, another
    np.testing.assert_array_equal(shape_field(7, "L1", 0.0, 150.0, np.zeros(3))(x), x)
    # smooth: its gradient is at most 2 pi a / wavelength (times the three modes' sqrt 3)
    h = 1e-3
    g = np.linalg.norm(f(x + [h, 0, 0]) - f(x - [h, 0, 0]), axis=1) / (2 * h)
    assert np.abs(g - 1.0).max() < 2 * np.pi * 5.0 / 150.0 * np.sqrt(3) + 1e-6


def test_the_local_frame_turns_with_the_surface():
    # a rigid turn: its own rotation
    Q = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix()
    np.testing.assert_allclose(local_turn(lambda x: x @ Q.T + 5.0, np.array([1.0, 2.0, 3.0]), [0, 0, 1], [1, 0, 0]), Q,
                               atol=1e-8)
    # a bend of the plane z = 0 along its normal, z += 0.1 u: the normal turns to (-0.1, 0, 1), t1 to (1, 0, 0.1)
    Rw = local_turn(lambda x: x + np.array([0.0, 0.0, 0.1 * x[0]]), np.zeros(3), [0, 0, 1], [1, 0, 0])
    n2 = np.array([-0.1, 0.0, 1.0]) / np.hypot(0.1, 1.0)
    np.testing.assert_allclose(Rw @ [0, 0, 1], n2, atol=1e-9)
    np.testing.assert_allclose(Rw @ [1, 0, 0], np.array([1.0, 0.0, 0.1]) / np.hypot(0.1, 1.0), atol=1e-9)
    np.testing.assert_allclose(Rw @ Rw.T, np.eye(3), atol=1e-12)


def test_changed_cases_carry_the_dent_with_the_local_frame():
    V = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0], [10.0, 10.0, 1.0]])
    T = np.array([[0, 1, 2], [1, 3, 2]])
    u = np.array([[0.0, 0.0, -2.0], [0.5, 0.0, -0.5], [0.0, 0.0, -0.5], [0.0, 0.0, 0.0]])
    arrays = {"geometry_id": np.array(["L1"]), "liver_centroid_mm": np.zeros((1, 3)),
              "exertion_point_mm": np.zeros((1, 3)), "frame_normal": np.array([[0.0, 0.0, 1.0]]),
              "frame_t1": np.array([[1.0, 0.0, 0.0]]), "frame_t2": np.array([[0.0, 1.0, 0.0]]),
              "surface_displacement_mm": [u], "surface_meshes": {"L1": (V, T)}}
    out = changed_shape(arrays, 3, 4.0, 120.0)
    f = shape_field(3, "L1", 4.0, 120.0, np.zeros(3))
    np.testing.assert_allclose(out["surface_meshes"]["L1"][0], f(V))
    np.testing.assert_allclose(out["exertion_point_mm"][0], f(np.zeros(3)))
    Rw = local_turn(f, np.zeros(3), [0, 0, 1], [1, 0, 0])
    np.testing.assert_allclose(out["surface_displacement_mm"][0], u @ Rw.T)
    frame = np.stack([out["frame_t1"][0], out["frame_t2"][0], out["frame_normal"][0]])
    np.testing.assert_allclose(frame @ frame.T, np.eye(3), atol=1e-12)  # still a frame
    # in the carried frame the dent reads as it did: the local force label is unchanged
    np.testing.assert_allclose(out["surface_displacement_mm"][0] @ frame.T, u, atol=1e-12)
    assert arrays["surface_displacement_mm"][0] is u and (arrays["exertion_point_mm"] == 0).all()  # input untouched
