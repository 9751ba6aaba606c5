"""A picture of one simulated case, for a human to check.

Deformed surface coloured by displacement magnitude (mm), the ROI outlined,
the tool force drawn as an arrow at the exertion point. Rendered offscreen
(matplotlib Agg), two views.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from liverforce.atomic import atomic_path


def roi_boundary_edges(facets: np.ndarray, in_roi: np.ndarray) -> np.ndarray:
    """Edges between a facet with all nodes in the ROI and one without (the outline)."""
    full = in_roi[facets].all(axis=1)
    edges = np.concatenate([facets[:, [0, 1]], facets[:, [1, 2]], facets[:, [2, 0]]])
    owner = np.tile(full, 3)
    key = np.sort(edges, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    n_in = np.bincount(inv.ravel(), weights=owner.astype(float), minlength=len(counts))
    boundary = (n_in == 1) & (counts == 2)
    return np.unique(key, axis=0)[boundary]


def plot_case(points: np.ndarray, facets: np.ndarray, row: dict, path: str | Path, scale: float = 1.0) -> Path:
    """Draw one case.

    Parameters
    ----------
    points, facets : the geometry's mesh points (mm) and boundary triangles
    row : dict
        One shard row (``surface_displacement_mm``, ``roi_node_ids``,
        ``exertion_point_mm``, ``force_n``, ``case_id`` ...).
    path : output PNG
    scale : displacement magnification for the drawing (1 = true scale)
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection

    surf_ids = np.unique(facets)
    u_surf = np.asarray(row["surface_displacement_mm"], dtype=float).reshape(-1, 3)
    u = np.zeros_like(points)
    if len(u_surf) == len(surf_ids):
        u[surf_ids] = u_surf
    else:  # full surface not stored: only the ROI is known
        u[np.asarray(row["roi_node_ids"])] = np.asarray(row["roi_deformed_mm"]) - np.asarray(row["roi_undeformed_mm"])
    x = points + scale * u
    mag = np.linalg.norm(u, axis=1)
    face_mag = mag[facets].mean(axis=1)
    in_roi = np.zeros(len(points), bool)
    in_roi[np.asarray(row["roi_node_ids"], dtype=int)] = True
    outline = roi_boundary_edges(facets, in_roi)
    p = np.asarray(row["exertion_point_mm"], float)
    f = np.asarray(row["force_n"], float)
    extent = np.ptp(points, axis=0).max()
    arrow = -f / max(np.linalg.norm(f), 1e-12) * 0.25 * extent  # drawn from outside toward the point

    fig = plt.figure(figsize=(12, 5.5))
    norm = matplotlib.colors.Normalize(vmin=0.0, vmax=max(mag.max(), 1e-9))
    cmap = matplotlib.colormaps["viridis"]
    for k, (elev, azim) in enumerate([(25, -60), (60, 30)]):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        roi_face = in_roi[facets].all(axis=1)
        edge = np.where(roi_face[:, None], np.array([[0.85, 0.1, 0.1, 0.9]]), np.array([[0, 0, 0, 0.0]]))
        poly = Poly3DCollection(x[facets], facecolors=cmap(norm(face_mag)), edgecolors=edge, linewidths=0.4)
        ax.add_collection3d(poly)
        if len(outline):
            ax.add_collection3d(Line3DCollection(x[outline], colors="red", linewidths=1.5))
        ax.quiver(*(p - arrow), *arrow, color="black", linewidth=2.5, arrow_length_ratio=0.25)
        lo, hi = x.min(axis=0), x.max(axis=0)
        c, r = (lo + hi) / 2, (hi - lo).max() / 2
        ax.set_xlim(c[0] - r, c[0] + r)
        ax.set_ylim(c[1] - r, c[1] + r)
        ax.set_zlim(c[2] - r, c[2] + r)
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_zlabel("z (mm)")
        ax.view_init(elev=elev, azim=azim)
    sm = matplotlib.cm.ScalarMappable(norm=norm, cmap=cmap)
    fig.colorbar(sm, ax=fig.axes, shrink=0.6, label="|u| (mm)")
    status = "converged" if row.get("converged", True) else f"FAILED: {row.get('reason', '')}"
    fig.suptitle(
        f"{row.get('case_id', '')} on {row.get('geometry_id', '')}: F = {np.round(f, 2).tolist()} N "
        f"(|F| {np.linalg.norm(f):.2f} N), max |u| {mag.max():.2f} mm, ROI {100 * row.get('roi_area_fraction', 0):.1f} % "
        f"(red), {status}" + (f", displacement x{scale:g}" if scale != 1 else "")
    )
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return path
