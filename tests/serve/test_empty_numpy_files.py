"""An empty or cut-short NumPy file given as a cloud, a stack of clouds, a surface, triangles or a support's
points is refused naming the file (numpy raises EOFError for it, which the readers did not catch: a traceback)."""

from __future__ import annotations

import numpy as np
import pytest

from liverforce.mesh.supports import SupportError, read_point_file
from liverforce.serve.errors import PredictionInputError
from liverforce.serve.files import _read_triangles, read_cloud, read_points, read_surface
from liverforce.serve.sequence import read_sequence


def _broken(tmp_path, name: str, how: str):
    """An empty file, or a valid .npy / .npz cut after its first 40 bytes."""
    path = tmp_path / name
    if how == "empty":
        path.write_bytes(b"")
        return path
    full = tmp_path / f"full{path.suffix}"
    if path.suffix == ".npz":
        np.savez(full, points=np.zeros((4, 3)), facets=np.zeros((2, 3), dtype=np.int64))
    else:
        np.save(full, np.zeros((50, 3)))
    path.write_bytes(full.read_bytes()[:40])
    return path


@pytest.mark.parametrize("how", ["empty", "cut"])
def test_a_cloud_npy_is_refused_naming_the_file(tmp_path, how):
    path = _broken(tmp_path, "cloud.npy", how)
    for read in (read_points, lambda p: read_cloud(p)):
        with pytest.raises(PredictionInputError, match="cloud.npy: cannot read the point cloud"):
            read(path)


@pytest.mark.parametrize("how", ["empty", "cut"])
def test_a_stack_of_clouds_is_refused_naming_the_file(tmp_path, how):
    path = _broken(tmp_path, "stack.npy", how)
    with pytest.raises(PredictionInputError, match="stack.npy: cannot read the point clouds"):
        read_sequence([path])


def test_a_damaged_npy_frame_in_a_folder_is_its_own_row(tmp_path):
    np.save(tmp_path / "f1.npy", np.ones((5, 3)))
    _broken(tmp_path, "f2.npy", "empty")
    errors: dict = {}
    names, clouds = read_sequence([tmp_path], errors=errors)
    assert names == ["f1.npy", "f2.npy"] and clouds[1] is None
    assert "f2.npy: cannot read the point cloud" in errors[1]


@pytest.mark.parametrize("how", ["empty", "cut"])
def test_a_surface_npz_and_triangles_npy_are_refused_naming_the_file(tmp_path, how):
    with pytest.raises(PredictionInputError, match="surface.npz: cannot read the surface"):
        read_surface(_broken(tmp_path, "surface.npz", how))
    with pytest.raises(PredictionInputError, match="tri.npy: cannot read the triangles"):
        _read_triangles(_broken(tmp_path, "tri.npy", how))


def test_a_surface_npz_without_its_arrays_names_them(tmp_path):
    path = tmp_path / "surface.npz"
    np.savez(path, vertices=np.zeros((4, 3)))
    with pytest.raises(PredictionInputError, match="'points' .* and 'facets'"):
        read_surface(path)


@pytest.mark.parametrize("how", ["empty", "cut"])
def test_a_support_points_npy_is_refused_naming_the_file(tmp_path, how):
    with pytest.raises(SupportError, match="pins.npy: cannot read the array"):
        read_point_file(_broken(tmp_path, "pins.npy", how), units="mm")


def test_a_single_npy_cut_inside_its_data_says_so_not_its_memory_map(tmp_path):
    """A cloud or a stack given alone is first looked at as a stack, memory-mapped: numpy's map of a file cut inside
    its data said only 'mmap length is greater than file size'; its reading says how many values it lacks."""
    for name, shape in (("cloud.npy", (50, 3)), ("stack.npy", (4, 50, 3))):
        full = tmp_path / f"full_{name}"
        np.save(full, np.ones(shape))
        (tmp_path / name).write_bytes(full.read_bytes()[:-100])
        with pytest.raises(PredictionInputError) as exc:
            read_sequence([tmp_path / name])
        said = str(exc.value)
        assert said.startswith(f"{tmp_path / name}: cannot read the point clouds (ValueError: ") and "mmap" not in said
        assert "not fully written" in said
