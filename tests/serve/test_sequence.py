"""Reading a recorded sequence of clouds (liverforce.serve.sequence): the files' order, a stack, and refusals."""
from __future__ import annotations

import numpy as np
import pytest

from liverforce.serve.errors import PredictionInputError
from liverforce.serve.sequence import read_sequence, read_tips


def test_a_folder_is_read_in_natural_name_order_and_skips_other_files(tmp_path):
    rng = np.random.default_rng(0)
    want = {}
    for name in ("cam_10.npy", "cam_9.csv", "cam_100.ply", "cam_0.npy"):
        pts = rng.normal(size=(7, 3))
        want[name] = pts
        if name.endswith(".npy"):
            np.save(tmp_path / name, pts)
        elif name.endswith(".csv"):
            np.savetxt(tmp_path / name, pts, delimiter=",")
        else:
            (tmp_path / name).write_text("ply\nformat ascii 1.0\nelement vertex 7\nproperty float x\nproperty float y\n"
                                         "property float z\nend_header\n" + "".join(f"{a:.9g} {b:.9g} {c:.9g}\n"
                                                                                     for a, b, c in pts))
    (tmp_path / "readme.md").write_text("not a cloud")
    (tmp_path / "sub.npy").mkdir()  # a folder named like a cloud: not read
    names, clouds = read_sequence([tmp_path])
    assert names == ["cam_0.npy", "cam_9.csv", "cam_10.npy", "cam_100.ply"]
    for n, c in zip(names, clouds):
        np.testing.assert_allclose(c, want[n], rtol=1e-6 if n.endswith(".ply") else 0)
    # files given one by one keep the order given
    names, _ = read_sequence([tmp_path / "cam_10.npy", tmp_path / "cam_0.npy"])
    assert names == ["cam_10.npy", "cam_0.npy"]


def test_a_stack_of_clouds_and_the_refusals(tmp_path):
    stack = np.arange(2 * 5 * 3, dtype=np.float32).reshape(2, 5, 3)
    np.save(tmp_path / "rec.npy", stack)
    names, clouds = read_sequence([tmp_path / "rec.npy"])
    assert names == ["rec.npy[0]", "rec.npy[1]"] and all(c.dtype == np.float64 for c in clouds)
    np.testing.assert_array_equal(np.stack(clouds), stack)
    np.save(tmp_path / "one.npy", stack[0])  # one (N, 3) cloud: a sequence of one
    assert read_sequence([tmp_path / "one.npy"])[0] == ["one.npy"]
    np.save(tmp_path / "bad.npy", np.zeros((2, 5, 2)))
    with pytest.raises(PredictionInputError, match=r"\(T, N, 3\)"):
        read_sequence([tmp_path / "bad.npy"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(PredictionInputError, match="no point-cloud files"):
        read_sequence([tmp_path / "empty"])
    with pytest.raises(PredictionInputError, match="no such point-cloud file"):
        read_sequence([tmp_path / "missing.ply", tmp_path / "one.npy"])
    np.savetxt(tmp_path / "tips.csv", np.zeros((3, 3)), delimiter=",")
    assert read_tips(tmp_path / "tips.csv", 3).shape == (3, 3)
    with pytest.raises(PredictionInputError, match="3 tips for 2 clouds"):
        read_tips(tmp_path / "tips.csv", 2)


def test_natural_order_is_total_and_takes_only_ascii_digits(tmp_path):
    from liverforce.serve.sequence import _natural

    names = ["f1.npy", "f01.npy", "f10.npy", "f2.npy", "cam1\u00b2.npy"]
    for n in names:
        np.save(tmp_path / n, np.zeros((2, 3)))
    got, _ = read_sequence([tmp_path])
    assert got == sorted(names, key=_natural) == ["cam1\u00b2.npy", "f01.npy", "f1.npy", "f2.npy", "f10.npy"]
