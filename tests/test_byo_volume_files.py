"""Tet meshes imported as given: every format keeps the node numbering; bad meshes are refused by name.

The files are real: Gmsh MSH 2.2 and 4.1 written by the gmsh API (as Gmsh itself
saves them), VTU, legacy VTK and XDMF written by meshio. The nodes are shuffled
before writing, so "node ids kept" is a check that can fail. The helpers here
are shared with tests/mesh/test_support_groups.py and tests/test_byo_as_given.py.
"""

from __future__ import annotations

import numpy as np
import pytest

from liverforce.fem.testing import box_mesh
from liverforce.geometry.errors import GeometryError
from liverforce.geometry.volume_mesh import has_tetrahedra, load_volume_mesh

FORMATS = ("msh22", "msh41", "vtu", "vtk", "xdmf")
SUFFIX = {"msh22": ".msh", "msh41": ".msh", "vtu": ".vtu", "vtk": ".vtk", "xdmf": ".xdmf"}


def write_gmsh(path, points, tets, groups: dict, version: float) -> None:
    """A Gmsh MSH file written by the gmsh API: nodes tagged 1..n in order (meshio reads them 0..n-1),
    one discrete volume (physical 'liver', tag 1) and per group ``{name: (tag, triangles or nodes)}``
    a discrete surface of triangles ``(k, 3)`` or a discrete point set of nodes ``(k,)``, 0-based."""
    import gmsh

    gmsh.initialize(["-noenv"])
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("liver")
        gmsh.model.addDiscreteEntity(3, 1)
        n = len(points)
        gmsh.model.mesh.addNodes(3, 1, np.arange(1, n + 1), np.asarray(points, float).ravel())
        gmsh.model.mesh.addElementsByType(1, 4, [], (np.asarray(tets, np.int64) + 1).ravel())
        gmsh.model.addPhysicalGroup(3, [1], tag=1, name="liver")
        for e, (name, (tag, cells)) in enumerate(groups.items(), start=1):
            cells = np.asarray(cells, np.int64)
            dim, etype = (2, 2) if cells.ndim == 2 else (0, 15)
            gmsh.model.addDiscreteEntity(dim, e, [])
            gmsh.model.mesh.addElementsByType(e, etype, [], (cells + 1).ravel())
            gmsh.model.addPhysicalGroup(dim, [e], tag=tag, name=name)
        gmsh.option.setNumber("Mesh.MshFileVersion", version)
        gmsh.option.setNumber("Mesh.Binary", 0)
        gmsh.write(str(path))
    finally:
        gmsh.finalize()


def write_volume(path, fmt: str, points, tets, groups: dict | None = None, extra_cells=()) -> None:
    """``points``/``tets`` (0-based) with tagged triangle groups ``{name: (tag, triangles)}`` in format ``fmt``:
    Gmsh physical groups for MSH, an integer cell-data array ``tag`` (0 on the tets) for VTU/VTK/XDMF."""
    import meshio

    groups = groups or {}
    if fmt in ("msh22", "msh41"):
        assert not extra_cells
        write_gmsh(path, points, tets, groups, 2.2 if fmt == "msh22" else 4.1)
        return
    cells = [("tetra", np.asarray(tets, np.int64))]
    tags = [np.zeros(len(tets), np.int32)]
    for tag, tri in groups.values():
        cells.append(("triangle", np.asarray(tri, np.int64)))
        tags.append(np.full(len(tri), tag, np.int32))
    for ctype, data in extra_cells:
        cells.append((ctype, np.asarray(data, np.int64)))
        tags.append(np.zeros(len(data), np.int32))
    mesh = meshio.Mesh(np.asarray(points, float), cells, cell_data={"tag": tags})
    if fmt == "xdmf":
        meshio.write(path, mesh, file_format="xdmf", data_format="XML")
    else:
        meshio.write(path, mesh, file_format=fmt)


def shuffled_box(seed: int = 0, shape=(3, 2, 2), size=(30.0, 20.0, 20.0)):
    """A box of tets with its nodes in a random order: ``(points, tets, perm)``, file node j = box node perm[j]."""
    p, t, _ = box_mesh(shape, size=size)
    perm = np.random.default_rng(seed).permutation(len(p))
    inv = np.argsort(perm)
    return p[perm], inv[t], perm


def _same_tets(a, b) -> bool:
    """Same tets in the same order (node order within a tet may differ: reorientation)."""
    return np.array_equal(np.sort(a, axis=1), np.sort(b, axis=1))


@pytest.mark.parametrize("fmt", FORMATS)
def test_every_format_keeps_the_node_numbering_and_the_tets(tmp_path, fmt):
    if fmt == "xdmf":
        pytest.importorskip("h5py", reason="meshio 5.3.5 reads and writes XDMF only with h5py installed")
    points, tets, _ = shuffled_box()
    top = np.flatnonzero(np.isclose(points[:, 2], 20.0))
    path = tmp_path / f"box{SUFFIX[fmt]}"
    write_volume(path, fmt, points, tets, {"top": (3, _faces_on(points, tets, 2, 20.0))})
    assert has_tetrahedra(path)
    vm, msgs = load_volume_mesh(path, units="mm", size_range_mm=None)
    np.testing.assert_array_equal(vm.points, points)  # node i of the file is node i: ids stay valid
    assert _same_tets(vm.tets, tets)
    assert vm.meta["n_nodes"] == len(points) and vm.meta["node_numbering"] == "file"
    assert vm.meta["reoriented_in_file"] == 0 and not any("inverted" in m for m in msgs)
    assert len(top) and vm.points[top][:, 2].min() == 20.0


def _faces_on(points, tets, axis, value):
    from liverforce.mesh.boundary import boundary_facets

    f = boundary_facets(tets)
    return f[np.isclose(points[f][:, :, axis], value).all(axis=1)]


def test_units_and_frame_convert_to_ras_mm_keeping_the_order(tmp_path):
    points, tets, _ = shuffled_box()
    lps_m = points * [-1, -1, 1] / 1000.0  # the same box in metres, LPS
    write_volume(tmp_path / "m.vtu", "vtu", lps_m, tets)
    vm, _ = load_volume_mesh(tmp_path / "m.vtu", units="m", frame="LPS", size_range_mm=None)
    np.testing.assert_allclose(vm.points, points, atol=1e-12)
    assert vm.meta["conversion"]["scale_to_mm"] == 1000.0 and vm.meta["conversion"]["frame"] == "LPS"
    assert "units m (x1000 to mm)" in vm.meta["conversion"]["summary"]


def test_a_reflecting_frame_reorients_every_tet_without_calling_them_inverted(tmp_path):
    from liverforce.mesh.quality import signed_volumes

    points, tets, _ = shuffled_box()
    write_volume(tmp_path / "b.vtu", "vtu", points, tets)
    mirror = [[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    vm, msgs = load_volume_mesh(tmp_path / "b.vtu", frame=mirror, size_range_mm=None)
    assert (signed_volumes(vm.points, vm.tets) > 0).all()
    assert vm.meta["reoriented_in_file"] == 0 and not any("inverted" in m for m in msgs)
    assert "reoriented for the reflection" in vm.meta["conversion"]["summary"]


def test_inverted_tets_are_reoriented_and_reported(tmp_path):
    from liverforce.mesh.quality import signed_volumes

    points, tets, _ = shuffled_box()
    bad = tets.copy()
    bad[[1, 4, 7]] = bad[[1, 4, 7]][:, [1, 0, 2, 3]]
    write_volume(tmp_path / "inv.vtk", "vtk", points, bad)
    vm, msgs = load_volume_mesh(tmp_path / "inv.vtk", size_range_mm=None)
    assert (signed_volumes(vm.points, vm.tets) > 0).all()
    assert vm.meta["reoriented_in_file"] == 3
    assert any("3 of" in m and "inverted" in m and "[1, 4, 7]" in m for m in msgs)


@pytest.mark.parametrize("defect, message", [
    ("flat", r"1 zero-volume \(flat\) tetrahedra, e\.g\. cells \[\d+\].*Remove or fix them"),
    ("hexahedra_only", r"volume cells other than linear tetrahedra \(1 hexahedron\).*Convert them"),
    ("hexahedra_beside_tets", r"1 hexahedron, beside \d+ tetra\).*mesh: remesh"),
    ("quadratic", r"quadratic tetrahedra.*Export linear tetrahedra"),
    ("surface_only", r"holds no tetrahedra \(\d+ triangle\).*mesh: remesh"),
    ("two_pieces", r"2 disconnected pieces \(tetrahedra per piece: \[\d+, \d+\]\).*Keep the liver piece"),
    ("orphan_node", r"1 of \d+ nodes belong to no tetrahedron.*remove_orphaned_nodes"),
])
def test_bad_volume_meshes_are_refused_naming_problem_and_fix(tmp_path, defect, message):
    import meshio

    points, tets, _ = shuffled_box()
    path = tmp_path / "bad.vtu"
    if defect == "flat":
        p = np.vstack([points, points[tets[0, :3]].mean(axis=0)])  # a tet on a face's centroid: flat
        t = np.vstack([tets, [tets[0, 0], tets[0, 1], tets[0, 2], len(points)]])
        write_volume(path, "vtu", p, t)
    elif defect == "hexahedra_only":
        cube = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1.]])
        meshio.write(path, meshio.Mesh(cube * 100, [("hexahedron", [np.arange(8)])]))
    elif defect == "hexahedra_beside_tets":
        n = len(points)
        cube = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1.]])
        write_volume(path, "vtu", np.vstack([points, cube * 10 + [30, 0, 0]]), tets,
                     extra_cells=[("hexahedron", [np.arange(n, n + 8)])])
    elif defect == "quadratic":
        meshio.write(path, meshio.Mesh(np.random.default_rng(0).random((10, 3)), [("tetra10", [np.arange(10)])]))
    elif defect == "surface_only":
        meshio.write(path, meshio.Mesh(points, [("triangle", _faces_on(points, tets, 2, 20.0))]))
    elif defect == "two_pieces":
        write_volume(path, "vtu", np.vstack([points, points + [100, 0, 0]]), np.vstack([tets, tets + len(points)]))
    elif defect == "orphan_node":
        write_volume(path, "vtu", np.vstack([points, [[500.0, 0, 0]]]), tets)
    with pytest.raises(GeometryError, match=message):
        load_volume_mesh(path, size_range_mm=None)


def test_xdmf_without_h5py_is_refused_with_the_install_line(tmp_path, monkeypatch):
    """meshio 5.3.5 imports h5py even for XDMF with inline XML data: without it the user is told what to install."""
    import builtins

    points, tets, _ = shuffled_box()
    xml = (tmp_path / "b.xdmf")
    xml.write_text(f"""<?xml version="1.0"?>
<Xdmf Version="3.0"><Domain><Grid Name="g" GridType="Uniform">
<Topology TopologyType="Tetrahedron" NumberOfElements="{len(tets)}">
<DataItem Dimensions="{len(tets)} 4" NumberType="Int" Format="XML">{" ".join(map(str, tets.ravel()))}</DataItem>
</Topology><Geometry GeometryType="XYZ">
<DataItem Dimensions="{len(points)} 3" NumberType="Float" Precision="8" Format="XML">{" ".join(map(repr, points.ravel()))}</DataItem>
</Geometry></Grid></Domain></Xdmf>""")
    real_import = builtins.__import__

    def no_h5py(name, *args, **kwargs):
        if name == "h5py":
            raise ImportError("No module named 'h5py'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_h5py)
    with pytest.raises(GeometryError, match=r"b\.xdmf: meshio needs a package that is not installed.*pip install h5py"):
        load_volume_mesh(xml, size_range_mm=None)


def test_auto_takes_tet_files_as_given_and_remeshes_surfaces(tmp_path):
    import meshio
    import trimesh

    from liverforce.pipeline.geometry import mesh_mode

    points, tets, _ = shuffled_box()
    write_volume(tmp_path / "v.vtu", "vtu", points, tets)
    meshio.write(tmp_path / "s.vtu", meshio.Mesh(points, [("triangle", _faces_on(points, tets, 2, 20.0))]))
    trimesh.creation.box().export(tmp_path / "s.stl")
    assert mesh_mode({"path": str(tmp_path / "v.vtu")}) == "as_given"
    assert mesh_mode({"path": str(tmp_path / "s.vtu")}) == "remesh"
    assert mesh_mode({"path": str(tmp_path / "s.stl")}) == "remesh"
    assert mesh_mode({"path": str(tmp_path / "v.vtu"), "mesh": "remesh"}) == "remesh"


@pytest.mark.parametrize("entry, key, text", [
    ("{name:a,path:/x/liver.msh,mesh:keep}", "geometry.imported[0].mesh", "unknown mesh mode 'keep' — choose one of auto, as_given, remesh"),
    ("{name:a,path:/x/liver.stl,mesh:as_given}", "geometry.imported[0].mesh", "as_given needs a tetrahedral mesh"),
    ("{name:a,path:/x/liver.msh,mesh:as_given,supports:{list:[{kind:fixed,group:[1]}]}}",
     "geometry.imported[0].supports.list[0].group", "must be a group name, a tag number"),
])
def test_mesh_mode_and_group_are_checked_in_the_config(entry, key, text):
    import re

    from liverforce.config import ConfigError, compose

    with pytest.raises(ConfigError, match=rf"'{re.escape(key)}'.*{text}"):
        compose([f"geometry.imported=[{entry}]"])


def test_a_config_with_an_imported_tet_mesh_composes():
    from liverforce.config import compose

    cfg = compose(["geometry.imported=[{name:a,path:/x/liver.msh,units:m,frame:LPS,mesh:as_given,"
                   "supports:{mode:replace,list:[{name:cava,kind:fixed,group:cava},"
                   "{name:floor,kind:foundation,region:visceral,group:{array:tag,value:3},"
                   "stiffness:{total_n_per_mm:40}}]},exertion_points:{vertex_ids:[12,40]}}]"])
    imp = cfg["geometry"]["imported"][0]
    assert imp["mesh"] == "as_given" and imp["supports"]["list"][1]["group"] == {"array": "tag", "value": 3}
