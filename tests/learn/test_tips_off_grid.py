"""A camera model's training cases whose tool tip lies off its grid along the surface are named when it trains:
serving refuses such a tip (the grid does not see the tool), while a deep press along the normal keeps the tip
over the grid and is served."""
from __future__ import annotations

import logging
import types

import numpy as np

from liverforce.learn.camera import tips_off_grid
from liverforce.learn.train import _warn_tips_off_grid


def _plate_cases(moves) -> dict:
    """A flat 100 x 100 mm plate (z = 0, normal +z) pressed at its centre; case k moves every vertex by
    ``moves[k]`` (mm), so the tool tip moves by it too."""
    x = np.linspace(-50.0, 50.0, 11)
    X, Y = np.meshgrid(x, x)
    V = np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])
    T = []
    for i in range(10):
        for j in range(10):
            a = i * 11 + j
            T += [[a, a + 1, a + 12], [a, a + 12, a + 11]]
    n = len(moves)
    return {"case_id": [f"II-{k:06d}" for k in range(n)], "geometry_id": ["plate"] * n,
            "exertion_point_mm": np.zeros((n, 3)), "frame_normal": np.tile([0.0, 0.0, 1.0], (n, 1)),
            "frame_t1": np.tile([1.0, 0.0, 0.0], (n, 1)), "frame_t2": np.tile([0.0, 1.0, 0.0], (n, 1)),
            "surface_meshes": {"plate": (V, np.array(T))},
            "surface_displacement_mm": [np.tile(np.asarray(m, float), (len(V), 1)) for m in moves]}


MOVES = [(2.0, 1.0, -5.0),     # an ordinary press
         (4.0, -3.0, -26.0),   # a deep press: 26 mm from the exertion point, 4 mm along the surface
         (31.0, 5.0, -8.0),    # the lobe swung 31 mm sideways: off the 20 mm grid
         (-3.0, -24.5, -2.0)]  # 24.5 mm along t2


def test_only_tips_moved_off_the_grid_along_the_surface_are_named():
    off = tips_off_grid(_plate_cases(MOVES), 20.0)
    assert [c for c, _ in off] == ["II-000002", "II-000003"]
    assert np.allclose([a for _, a in off], [31.0, 24.5])
    assert tips_off_grid(_plate_cases(MOVES), 35.0) == []



def test_the_offsets_are_in_each_cases_local_frame_and_given_tips_are_read_as_given():
    """The plate and its frames turned and moved as a whole: the same cases named with the same offsets. Tips
    given with the cases (tool_tip_mm) are judged as given; neither tips nor surfaces: not measured (None)."""
    a = _plate_cases(MOVES)
    Q, _ = np.linalg.qr(np.random.default_rng(3).normal(size=(3, 3)))
    t = np.array([120.0, -40.0, 900.0])
    V, T = a["surface_meshes"]["plate"]
    b = {**a, "surface_meshes": {"plate": (V @ Q.T + t, T)}, "exertion_point_mm": a["exertion_point_mm"] @ Q.T + t,
         "surface_displacement_mm": [u @ Q.T for u in a["surface_displacement_mm"]],
         **{k: a[k] @ Q.T for k in ("frame_normal", "frame_t1", "frame_t2")}}
    got = tips_off_grid(b, 20.0)
    assert [c for c, _ in got] == ["II-000002", "II-000003"] and np.allclose([x for _, x in got], [31.0, 24.5])
    given = {k: v for k, v in b.items() if k not in ("surface_meshes", "surface_displacement_mm")}
    given["tool_tip_mm"] = b["exertion_point_mm"] + np.asarray(MOVES) @ Q.T
    assert tips_off_grid(given, 20.0) == got
    assert tips_off_grid({k: v for k, v in given.items() if k != "tool_tip_mm"}, 20.0) is None


def test_training_a_camera_model_warns_and_records_them(caplog):
    rep = types.SimpleNamespace(features="cloud", half_width_mm=20.0)
    with caplog.at_level(logging.WARNING, logger="liverforce"):
        rec = _warn_tips_off_grid(_plate_cases(MOVES), rep, "II", "cloud_sv")
    assert rec == {"n": 2, "half_width_mm": 20.0, "cases": ["II-000002", "II-000003"], "largest_mm": 31.0}
    msg = " ".join(r.getMessage() for r in caplog.records)
    assert "2 of 4 cases have the tool tip off the camera grid along the surface (beyond 20 mm" in msg
    assert "the largest 31 mm, II-000002" in msg and "serving refuses such a tip" in msg
    node = types.SimpleNamespace(features="displacement", half_width_mm=20.0)
    assert _warn_tips_off_grid(_plate_cases(MOVES), node, "II", "pca_sv") is None
    bare = {k: v for k, v in _plate_cases(MOVES).items() if k != "surface_meshes"}
    assert _warn_tips_off_grid(bare, rep, "II", "cloud_sv")["n"] is None  # not measured, not "none off the grid"
