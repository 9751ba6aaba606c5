"""The picture of one case: a real PNG with the ROI outline computed right."""
from __future__ import annotations

import numpy as np
import trimesh

from liverforce.dataset.plot import plot_case, roi_boundary_edges
from liverforce.dataset.roi import extract_roi, surface_graph


def test_roi_outline_is_a_closed_loop_around_the_patch():
    s = trimesh.creation.icosphere(subdivisions=3, radius=50.0)
    pts, tri = np.asarray(s.vertices), np.asarray(s.faces)
    g = surface_graph(pts, tri)
    ids, _ = extract_roi(g, np.array([0, 0, 50.0]), 0.18)
    in_roi = np.zeros(len(pts), bool)
    in_roi[g.node_ids[ids]] = True
    edges = roi_boundary_edges(tri, in_roi)
    assert len(edges) > 10
    # a closed loop: every outline vertex has exactly two outline edges
    _, counts = np.unique(edges.ravel(), return_counts=True)
    assert np.all(counts == 2)
    assert np.all(in_roi[edges])  # the outline runs along the ROI's own nodes


def test_plot_case_writes_a_png(tmp_path):
    s = trimesh.creation.icosphere(subdivisions=3, radius=50.0)
    pts, tri = np.asarray(s.vertices), np.asarray(s.faces)
    g = surface_graph(pts, tri)
    ids, frac = extract_roi(g, np.array([0, 0, 50.0]), 0.18)
    u = np.zeros_like(pts)
    u[:, 2] = -3.0 * np.exp(-np.sum((pts - [0, 0, 50.0]) ** 2, axis=1) / 200.0)
    node_ids = g.node_ids[ids]
    row = {"case_id": "I-000001", "geometry_id": "sphere", "surface_displacement_mm": u[g.node_ids],
           "roi_node_ids": node_ids, "roi_undeformed_mm": pts[node_ids], "roi_deformed_mm": pts[node_ids] + u[node_ids],
           "exertion_point_mm": [0, 0, 50.0], "force_n": [0, 0, -2.0], "roi_area_fraction": frac, "converged": True}
    out = plot_case(pts, tri, row, tmp_path / "case.png", scale=3)
    data = out.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000
    assert not list(tmp_path.glob(".*"))
