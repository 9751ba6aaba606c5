"""VTU round trip, atomic writes, contract validation, region picture."""

from __future__ import annotations

import meshio
import numpy as np
import pytest

from liverforce.mesh.io import MeshFileError, read_mesh, write_json, write_mesh
from liverforce.mesh.plot import plot_regions
from liverforce.mesh.types import LiverMesh


def test_round_trip(tmp_path, liver_mesh):
    path = tmp_path / "sub" / "liver.vtu"
    write_mesh(path, liver_mesh)
    assert sorted(p.name for p in path.parent.iterdir()) == ["liver.vtu"], "no temporary files left"
    back = read_mesh(path)
    for name in ("points", "tets", "facets", "facet_region", "facet_visible"):
        a, b = getattr(liver_mesh, name), getattr(back, name)
        assert a.dtype == b.dtype and np.array_equal(a, b), name
    back.validate()
    raw = meshio.read(path)
    assert [c.type for c in raw.cells] == ["tetra", "triangle"]
    assert set(raw.cell_data) == {"region", "visible"}
    assert not raw.cell_data["region"][0].any() and not raw.cell_data["visible"][0].any()


def test_rewrite_is_byte_identical(tmp_path, liver_mesh):
    write_mesh(tmp_path / "a.vtu", liver_mesh)
    write_mesh(tmp_path / "b.vtu", liver_mesh)
    assert (tmp_path / "a.vtu").read_bytes() == (tmp_path / "b.vtu").read_bytes()


def test_read_refuses_non_liver_files(tmp_path):
    bad = tmp_path / "bad.vtu"
    bad.write_bytes(b"\x00\x01garbage")
    with pytest.raises(MeshFileError, match=r"bad\.vtu"):
        read_mesh(bad)
    surf = tmp_path / "surf.vtu"
    meshio.write(surf, meshio.Mesh(np.eye(3), [("triangle", np.array([[0, 1, 2]]))]))
    with pytest.raises(MeshFileError, match=r"surf\.vtu: expected 'tetra' and 'triangle'"):
        read_mesh(surf)


def test_validate_catches_broken_contracts(liver_mesh):
    liver_mesh.validate()
    flipped = LiverMesh(liver_mesh.points, liver_mesh.tets[:, [0, 1, 3, 2]], liver_mesh.facets,
                        liver_mesh.facet_region, liver_mesh.facet_visible)
    with pytest.raises(ValueError, match="positively oriented"):
        flipped.validate()
    inward = LiverMesh(liver_mesh.points, liver_mesh.tets, liver_mesh.facets[:, ::-1],
                       liver_mesh.facet_region, liver_mesh.facet_visible)
    with pytest.raises(ValueError, match="outward-oriented boundary"):
        inward.validate()
    vis = liver_mesh.facet_visible.copy()
    vis[np.flatnonzero(liver_mesh.facet_region == 1)[0]] = True
    with pytest.raises(ValueError, match="visible facets must all be free"):
        LiverMesh(liver_mesh.points, liver_mesh.tets, liver_mesh.facets, liver_mesh.facet_region, vis).validate()


def test_write_json_is_atomic_and_sorted(tmp_path):
    path = tmp_path / "f.json"
    write_json(path, {"b": 1, "a": [1.5, 2]})
    assert path.read_text() == '{\n  "a": [\n    1.5,\n    2\n  ],\n  "b": 1\n}\n'
    assert [p.name for p in tmp_path.iterdir()] == ["f.json"]


def test_region_picture(tmp_path, liver_mesh):
    path = tmp_path / "regions.png"
    plot_regions(liver_mesh, path)
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000
    assert [p.name for p in tmp_path.iterdir()] == ["regions.png"]
