"""A second-order mesh file (``tetra10`` / ``triangle6``) is refused for what it is (audit 96, defect 6).

It used to stop at the surface import with "the file contains no triangles or tetrahedra" (the readers keep
linear cells only), before the import as given, which names quadratic tets, was ever reached.
"""

from __future__ import annotations

import numpy as np
import pytest

from liverforce.fem.testing import box_mesh
from liverforce.geometry.errors import GeometryError
from liverforce.geometry.importers import load_surface
from liverforce.geometry.volume_mesh import load_volume_mesh
from liverforce.mesh.boundary import boundary_facets

_TET10_EDGES = [(0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3)]  # meshio / VTK / Gmsh order
_TRI6_EDGES = [(0, 1), (1, 2), (0, 2)]


def _quadratic_box():
    """A box of tetra10 with its boundary as triangle6: ``(points, tet10, tri6)``."""
    p, t, _ = box_mesh((3, 2, 2), size=(30.0, 20.0, 20.0))
    f = boundary_facets(t)
    edges = np.sort(np.concatenate([t[:, e] for e in _TET10_EDGES]), axis=1)
    uniq = np.unique(edges, axis=0)
    mid = {tuple(e): len(p) + i for i, e in enumerate(uniq)}
    points = np.vstack([p, p[uniq].mean(axis=1)])

    def higher(cells, pairs):
        extra = [[mid[tuple(sorted((c[a], c[b])))] for a, b in pairs] for c in cells]
        return np.hstack([cells, np.array(extra, np.int64)])

    return points, higher(t, _TET10_EDGES), higher(f, _TRI6_EDGES)


def _gmsh_order_2(path) -> tuple[int, int]:
    """A box meshed by Gmsh itself with Mesh.ElementOrder = 2, physical surface and volume, MSH 4.1."""
    import gmsh

    gmsh.initialize(["-noenv"])
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("box")
        gmsh.model.occ.addBox(0, 0, 0, 30, 20, 20)
        gmsh.model.occ.synchronize()
        gmsh.model.addPhysicalGroup(2, [s for _, s in gmsh.model.getEntities(2)], name="capsule")
        gmsh.model.addPhysicalGroup(3, [1], name="liver")
        gmsh.option.setNumber("Mesh.MeshSizeMax", 10.0)
        gmsh.option.setNumber("Mesh.ElementOrder", 2)
        gmsh.model.mesh.generate(3)
        gmsh.option.setNumber("Mesh.MshFileVersion", 4.1)
        gmsh.write(str(path))
        count = lambda dim: sum(len(t) for t in gmsh.model.mesh.getElements(dim)[1])  # noqa: E731
        return count(3), count(2)
    finally:
        gmsh.finalize()


@pytest.fixture(scope="module", params=["gmsh22", "gmsh41", "vtu"])
def quadratic_file(request, tmp_path_factory):
    import meshio

    fmt = request.param
    if fmt == "gmsh41":
        path = tmp_path_factory.mktemp("q") / "liver_order2.msh"
        n_tet10, n_tri6 = _gmsh_order_2(path)
        return path, n_tet10, n_tri6
    points, tet10, tri6 = _quadratic_box()
    path = tmp_path_factory.mktemp("q") / f"liver_tet10.{'vtu' if fmt == 'vtu' else 'msh'}"
    cells = [("triangle6", tri6), ("tetra10", tet10)]
    data = {}
    if fmt != "vtu":  # Gmsh: a physical surface and volume, as a mesher writes them
        tags = [np.full(len(tri6), 2), np.full(len(tet10), 1)]
        data = {"gmsh:physical": tags, "gmsh:geometrical": tags}
    meshio.write(path, meshio.Mesh(points, cells, cell_data=data), file_format=fmt,
                 **({"binary": False} if fmt != "vtu" else {}))
    return path, len(tet10), len(tri6)


def _check(message: str, n_tet10: int, n_tri6: int) -> None:
    assert "no triangles or tetrahedra" not in message
    assert "second order (quadratic tetrahedra or triangles)" in message
    assert f"{n_tet10} tetra10" in message and f"{n_tri6} triangle6" in message
    assert "Mesh.ElementOrder = 1" in message and "-order 1" in message


def test_the_surface_import_names_the_quadratic_cells_and_the_fix(quadratic_file):
    """The path of mesh: remesh, and of mesh: auto (a file with no linear tets is remeshed)."""
    path, n_tet10, n_tri6 = quadratic_file
    with pytest.raises(GeometryError) as err:
        load_surface(path, units="mm", size_range_mm=None)
    _check(str(err.value), n_tet10, n_tri6)


def test_the_import_as_given_names_the_quadratic_cells_and_the_same_fix(quadratic_file):
    path, n_tet10, n_tri6 = quadratic_file
    with pytest.raises(GeometryError) as err:
        load_volume_mesh(path, units="mm", size_range_mm=None)
    _check(str(err.value), n_tet10, n_tri6)
    assert "mesh: remesh" not in str(err.value)  # the surface import refuses it too


def test_a_file_with_no_cells_at_all_keeps_its_own_message(tmp_path):
    import meshio

    path = tmp_path / "lines.vtu"
    meshio.write(path, meshio.Mesh(np.eye(3), [("line", np.array([[0, 1], [1, 2]]))]))
    with pytest.raises(GeometryError, match="the file contains no triangles or tetrahedra"):
        load_surface(path, units="mm", size_range_mm=None)
