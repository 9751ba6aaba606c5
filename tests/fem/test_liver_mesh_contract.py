"""Contract with the mesh stage: a real LiverMesh solves, regions all carry load."""
import numpy as np

from liverforce.fem import BoundaryParams, LiverModel, SolverOptions, ToolLoad, make_material
from liverforce.geometry import procedural
from liverforce.mesh import build


def test_procedural_liver_mesh_solves_with_balanced_reactions():
    mesh = build.build_liver_mesh(procedural.procedural_liver(0), target_nodes=300)
    mat = make_material("yeoh", {"C10": 1.61e-3, "C20": 12.5e-3, "C30": 5.31e-3}, nu=0.49)
    bp = BoundaryParams.from_totals(mesh.points, mesh.facets, mesh.facet_region)
    model = LiverModel.from_mesh(mesh, mat, bp, SolverOptions(modified_newton=True))
    cand = np.unique(mesh.facets[mesh.facet_visible])
    x0 = mesh.points[cand[np.argmax(mesh.points[cand, 2])]]
    res = model.solve(ToolLoad(x0, [0.0, 0.0, -3.0], 5.0))
    assert res.converged, res.reason
    assert res.u_nodes.shape == mesh.points.shape
    assert np.linalg.norm(res.reactions["imbalance"]) < 1e-6 * 3.0
    assert 1.0 < np.abs(res.u_nodes).max() < 50.0  # mm at 3 N on a soft liver
