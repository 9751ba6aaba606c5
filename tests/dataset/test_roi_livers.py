"""ROI area fraction on real liver meshes (issue 5: within ±2 % of the target area).

Two livers meshed the way the mesh stage does it (``build_liver_mesh`` at the
default experiment's ``mesh.target_nodes``): a procedural liver
(``liverforce.geometry.procedural``) and the SOFA ``liver-smooth.obj``
imported with ``units=40`` (skipped with a reason when ../shared/data/livers
is absent). For several exertion points (sampled on the visible surface as the
sweep samples them) and target fractions 0.05, 0.18 and 0.5, the ROI's area,
recomputed here from the triangles, must be within 2 % of the target area
(|achieved − f| ≤ 0.02 f of the total surface area), agree with the fraction
``extract_roi`` reports, and be one connected patch around the exertion point.
"""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from liverforce.dataset.roi import extract_roi, nearest_surface_node, surface_graph
from liverforce.geometry.importers import load_surface
from liverforce.geometry.procedural import procedural_liver
from liverforce.mesh.build import build_liver_mesh
from liverforce.sweep.design import sample_exertion_points

FRACTIONS = (0.05, 0.18, 0.5)
N_POINTS = 5
REL_TOL = 0.02  # of the target area


@pytest.fixture(scope="module")
def target_nodes() -> int:
    from liverforce.config import compose

    return int(compose([])["mesh"]["target_nodes"])


@pytest.fixture(scope="module")
def procedural_mesh(target_nodes):
    return build_liver_mesh(procedural_liver(0), target_nodes=target_nodes, seed=0)


@pytest.fixture(scope="module")
def sofa_mesh(shared_livers, target_nodes):
    surface, _ = load_surface(shared_livers / "liver-smooth.obj", units=40)
    return build_liver_mesh(surface, target_nodes=target_nodes, seed=0)


def roi_area_fraction(mesh, node_ids: np.ndarray) -> float:
    """Area of the ROI nodes (one third of each adjacent boundary triangle), over the total area."""
    p = mesh.points[mesh.facets]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    inside = np.isin(mesh.facets, node_ids).sum(axis=1)
    return float((area * inside / 3.0).sum() / area.sum())


def check_rois(mesh, fraction):
    surf = surface_graph(mesh.points, mesh.facets)
    points = sample_exertion_points(mesh.points, mesh.facets, mesh.facet_visible, N_POINTS, 15.0, seed=3)
    assert len(points) == N_POINTS
    problems = []
    for k, point in enumerate(points):
        local, achieved = extract_roi(surf, point, fraction)
        node_ids = surf.node_ids[local]
        area = roi_area_fraction(mesh, node_ids)
        assert area == pytest.approx(achieved, rel=1e-9)
        if abs(area - fraction) > REL_TOL * fraction:
            problems.append(f"point {k} {np.round(point, 1).tolist()}: ROI area {100 * area:.3f} % "
                            f"for a target of {100 * fraction:g} % ± {100 * REL_TOL * fraction:.3f} %")
        # one connected patch that contains the node under the tool
        assert nearest_surface_node(surf, point) in set(local.tolist())
        sub = surf.graph[local][:, local]
        n_comp, _ = connected_components(sp.csr_matrix(sub), directed=False)
        assert n_comp == 1, f"point {k}: ROI in {n_comp} pieces"
    return surf, problems


@pytest.mark.parametrize("fraction", FRACTIONS)
def test_roi_area_on_a_procedural_liver(procedural_mesh, fraction):
    surf, problems = check_rois(procedural_mesh, fraction)
    assert not problems, f"{len(surf.node_ids)} surface nodes:\n" + "\n".join(problems)


@pytest.mark.parametrize("fraction", FRACTIONS)
def test_roi_area_on_the_imported_sofa_liver(sofa_mesh, fraction):
    surf, problems = check_rois(sofa_mesh, fraction)
    assert not problems, f"{len(surf.node_ids)} surface nodes:\n" + "\n".join(problems)

