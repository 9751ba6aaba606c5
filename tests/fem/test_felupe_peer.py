"""Peer check against FElupe 11.3 on the same P1 mesh, material and nodal loads."""
import numpy as np
import pytest

from liverforce.fem import DiscreteSystem, SolverOptions, make_material
from liverforce.fem.testing import box_mesh

fem = pytest.importorskip("felupe")


def test_same_displacements_as_felupe():
    points, tets, _ = box_mesh((4, 2, 2), size=(40.0, 10.0, 10.0))
    C10, K = 0.01, 0.5
    fixed = points[:, 0] < 1e-9
    tip = np.flatnonzero(points[:, 0] > 40 - 1e-9)
    F = np.zeros((len(tip), 3))
    F[:, 1], F[:, 2] = 0.004 / len(tip), -0.02 / len(tip)

    # FElupe: nearly incompressible neo-Hooke mu/2 (I1b - 3) + K/2 (J - 1)^2
    mesh = fem.Mesh(points, tets, cell_type="tetra")
    field = fem.FieldContainer([fem.Field(fem.RegionTetra(mesh), dim=3)])
    solid = fem.SolidBody(fem.NeoHooke(mu=2 * C10, bulk=K), field)
    load = fem.PointLoad(field, tip, F)
    step = fem.Step(items=[solid, load], ramp={load: fem.math.linsteps([0, 1], num=4)[:, None, None] * F},
                    boundaries={"fixed": fem.dof.Boundary(field[0], mask=fixed)})
    fem.Job(steps=[step]).evaluate(tol=1e-12, verbose=0)
    u_felupe = field[0].values

    mat = make_material("neo_hookean", {"C10": C10}, bulk_mpa=K)
    dofs = (3 * np.flatnonzero(fixed)[:, None] + np.arange(3)).ravel()
    system = DiscreteSystem(points, tets, dofs, options=SolverOptions(formulation="p1", tol=1e-12))
    f = np.zeros(points.size)
    f.reshape(-1, 3)[tip] = F
    res = system.solve(mat, f_ext=f)
    assert res.converged
    u = res.u.reshape(-1, 3)
    assert np.abs(u).max() > 1.0  # a large-deformation case (mm)
    assert np.abs(u - u_felupe).max() <= 1e-6 * np.abs(u_felupe).max()
