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


def _damaged_folder(folder):
    """A folder of 5 frames, 3 of them damaged (a binary PCD, a CSV with a line broken, a binary PLY cut short);
    returns the good clouds by position."""
    from tests.serve.test_predict_cli import write_ply
    from tests.serve.test_read_pcd import write_pcd, xyz

    folder.mkdir()
    rng = np.random.default_rng(3)
    good = {0: rng.normal(size=(40, 3)), 4: rng.normal(size=(30, 3))}
    np.save(folder / "f0.npy", good[0])
    np.save(folder / "f4.npy", good[4])
    pcd = write_pcd(folder / "f1.pcd", xyz(rng.normal(size=(60, 3))), "binary")
    pcd.write_bytes(pcd.read_bytes()[:-100])
    np.savetxt(folder / "f2.csv", rng.normal(size=(20, 3)), delimiter=",")
    lines = (folder / "f2.csv").read_text().splitlines()
    (folder / "f2.csv").write_text("\n".join(lines[:5] + ["1.0,2.0,"] + lines[6:]) + "\n")
    write_ply(folder / "f3.ply", rng.normal(size=(50, 3)), binary=True)
    (folder / "f3.ply").write_bytes((folder / "f3.ply").read_bytes()[:-40])
    return good


def test_a_file_that_cannot_be_read_is_its_frames_reason_when_errors_are_taken(tmp_path):
    from liverforce.serve.files import read_cloud

    frames = tmp_path / "frames"
    good = _damaged_folder(frames)
    said = {}
    for name in ("f1.pcd", "f2.csv", "f3.ply"):  # what one cloud's predict says of each
        with pytest.raises(PredictionInputError) as exc:
            read_cloud(frames / name)
        said[name] = str(exc.value)
    with pytest.raises(PredictionInputError, match="f1.pcd"):  # without errors: the first refuses them all
        read_sequence([frames])
    errors: dict = {}
    names, clouds = read_sequence([frames], errors=errors)
    assert names == ["f0.npy", "f1.pcd", "f2.csv", "f3.ply", "f4.npy"] and sorted(errors) == [1, 2, 3]
    for k, c in enumerate(clouds):
        if k in good:
            np.testing.assert_array_equal(c, good[k])
        else:
            assert c is None and errors[k].startswith(said[names[k]]) and str(frames / names[k]) in errors[k]
            assert "remove it and its row of tool tips" in errors[k]
    # files named one by one: the same, in their order; a file named that is not there is still refused
    errors = {}
    names, clouds = read_sequence([frames / "f4.npy", frames / "f3.ply", frames / "f0.npy"], errors=errors)
    assert list(errors) == [1] and errors[1].startswith(said["f3.ply"]) and clouds[1] is None
    with pytest.raises(PredictionInputError, match="missing.npy: no such point-cloud file"):
        read_sequence([frames / "f0.npy", frames / "missing.npy"], errors={})
    # none readable: refused, naming the first file's problem and the count; one file: its own words
    for name in ("f0.npy", "f4.npy"):
        (frames / name).unlink()
    with pytest.raises(PredictionInputError) as exc:
        read_sequence([frames], errors={})
    assert str(exc.value).startswith(f"none of the 3 files of the sequence could be read as a point cloud; the "
                                     f"first: {said['f1.pcd']}. A sequence's folder")
    with pytest.raises(PredictionInputError) as exc:
        read_sequence([frames / "f2.csv"], errors={})
    assert str(exc.value) == said["f2.csv"]


def test_a_tips_count_that_does_not_match_names_the_files_not_read(tmp_path):
    np.savetxt(tmp_path / "tips.csv", np.zeros((4, 3)), delimiter=",")
    assert read_tips(tmp_path / "tips.csv", 4, unreadable=["notes.txt"]).shape == (4, 3)
    with pytest.raises(PredictionInputError) as exc:
        read_tips(tmp_path / "tips.csv", 5)
    assert "could not be read" not in str(exc.value)
    with pytest.raises(PredictionInputError, match=r"4 tips for 5 clouds; .*\. 1 of the 5 files could not be read "
                                                   r"as clouds \(notes\.txt\), each counted as a frame: if one is "
                                                   r"not a frame of the recording, move it out"):
        read_tips(tmp_path / "tips.csv", 5, unreadable=["notes.txt"])
    with pytest.raises(PredictionInputError, match=r"4 of the 6 files could not be read as clouds \(a, b, c and 1 "
                                                   r"more\)"):
        read_tips(tmp_path / "tips.csv", 6, unreadable=["a", "b", "c", "d"])


def test_predict_sequence_takes_the_files_not_read_only_with_their_reasons():
    from types import SimpleNamespace

    from liverforce.serve.sequence import predict_sequence

    camera = SimpleNamespace(model=SimpleNamespace(representation=SimpleNamespace(is_camera=True)))
    clouds, tips = [np.zeros((5, 3)), None], np.zeros((2, 3))
    with pytest.raises(ValueError, match=r"clouds: \[1\] are None without their reason"):
        predict_sequence(camera, None, None, clouds, tips)
    with pytest.raises(ValueError, match=r"positions \[2\]"):
        predict_sequence(camera, None, None, clouds, tips, unreadable={1: "cut short", 2: "?"})
    with pytest.raises(PredictionInputError, match=r"one x, y, z tip per cloud \(2, the unreadable ones too\), got 1"):
        predict_sequence(camera, None, None, clouds, tips[:1], unreadable={1: "cut short"})
    with pytest.raises(PredictionInputError, match="none of the 2 clouds of the sequence could be read; the first: "
                                                   "f0 cut short"):
        predict_sequence(camera, None, None, [None, None], tips, unreadable={1: "f1 cut short", 0: "f0 cut short"})


def test_a_file_gone_between_listing_and_reading_is_its_row_saying_so(tmp_path, monkeypatch):
    """A frame moved or deleted after the folder was listed (a recording still being copied) is its own row, which
    says so: 'no such point-cloud file' and 'repair or export it again' named a file the folder had just listed."""
    from pathlib import Path

    import liverforce.serve.sequence as sequence

    for k in range(4):
        np.save(tmp_path / f"f{k}.npy", np.full((5, 3), float(k)))
    read = sequence.read_cloud

    def moved(path, *args, **kwargs):
        if Path(path).name in ("f0.npy", "f2.npy"):  # the first one too: each its own row
            Path(path).unlink()
        return read(path, *args, **kwargs)

    monkeypatch.setattr(sequence, "read_cloud", moved)
    errors: dict = {}
    names, clouds = read_sequence([tmp_path], errors=errors)
    assert names == ["f0.npy", "f1.npy", "f2.npy", "f3.npy"] and sorted(errors) == [0, 2]
    assert clouds[0] is None and clouds[2] is None and clouds[3][0, 0] == 3.0
    for k in (0, 2):
        assert errors[k].startswith(f"{tmp_path / f'f{k}.npy'}: this file was listed with the sequence's files but "
                                    "was gone when it was read: moved or deleted meanwhile; is the recording still "
                                    "being written or copied? (this file could not be read as a cloud")
