"""Offscreen picture of the tagged boundary regions, for a human check."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from liverforce.mesh.types import REGION_CODES, LiverMesh

#: Colours per region code (free is light grey; visible free facets are sand).
REGION_COLOURS = {
    0: (0.82, 0.82, 0.82),
    1: (0.10, 0.30, 0.85),  # ivc
    2: (0.95, 0.55, 0.05),  # ligament
    3: (0.20, 0.65, 0.25),  # visceral
    4: (0.80, 0.10, 0.55),  # rib
}
VISIBLE_COLOUR = (0.98, 0.85, 0.55)


def plot_regions(mesh: LiverMesh, path: str | Path, views=None, title: str | None = None, dpi: int = 110) -> None:
    """Draw the boundary facets coloured by region (PNG, matplotlib Agg, no GUI).

    Parameters
    ----------
    mesh : LiverMesh
        Tagged mesh.
    path : str or Path
        Output PNG (written atomically).
    views : list of (elev, azim, label), optional
        Camera angles in degrees in the anatomical frame (right, anterior,
        superior) taken from ``mesh.meta["region_params"]`` (RAS if absent);
        default: anterior-superior from the right, posterior-inferior from
        the left, and straight posterior.
    title : str, optional
        Figure title (default: node/tet counts).
    dpi : int
        Resolution.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from liverforce.atomic import atomic_path
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    views = views or [
        (25.0, 60.0, "anterior-superior, from the right"),
        (-25.0, -120.0, "posterior-inferior, from the left"),
        (5.0, -90.0, "posterior"),
    ]
    frame = _anatomical_frame(mesh)
    pts = mesh.points @ frame.T  # (right, anterior, superior) coordinates
    tri = pts[mesh.facets]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    base = np.array([REGION_COLOURS[int(r)] for r in mesh.facet_region])
    base[mesh.facet_visible] = VISIBLE_COLOUR
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    mid, half = 0.5 * (lo + hi), 0.5 * float((hi - lo).max())

    fig = Figure(figsize=(5.0 * len(views), 5.4))
    FigureCanvasAgg(fig)
    for i, (elev, azim, label) in enumerate(views):
        ax = fig.add_subplot(1, len(views), i + 1, projection="3d")
        e, a = np.deg2rad(elev), np.deg2rad(azim)
        eye = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
        light = eye + np.array([0.0, 0.0, 0.5])
        light /= np.linalg.norm(light)
        shade = 0.45 + 0.55 * np.clip(n @ light, 0.0, 1.0)
        front = n @ eye > -0.05  # back-face culling keeps the drawing readable and fast
        colours = np.clip(base[front] * shade[front, None], 0.0, 1.0)
        ax.add_collection3d(Poly3DCollection(tri[front], facecolors=colours, edgecolors="none"))
        ax.set_xlim(mid[0] - half, mid[0] + half)
        ax.set_ylim(mid[1] - half, mid[1] + half)
        ax.set_zlim(mid[2] - half, mid[2] + half)
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=elev, azim=azim)
        ax.set_xlabel("right (mm)")
        ax.set_ylabel("anterior (mm)")
        ax.set_zlabel("superior (mm)")
        ax.set_title(label, fontsize=9)
    handles = [Patch(color=REGION_COLOURS[c], label=f"{c} {name}") for name, c in REGION_CODES.items()]
    handles.append(Patch(color=VISIBLE_COLOUR, label="visible (free)"))
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8, frameon=False)
    fig.suptitle(title or f"boundary regions: {len(mesh.points)} nodes, {len(mesh.tets)} tets", fontsize=10)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")


def _anatomical_frame(mesh: LiverMesh) -> np.ndarray:
    """Rows right, anterior, superior from the mesh's region parameters (RAS default)."""
    from liverforce.mesh.regions import RegionParams

    rp = mesh.meta.get("region_params") or {}
    try:
        return RegionParams(
            anterior=tuple(rp.get("anterior", (0.0, 1.0, 0.0))), superior=tuple(rp.get("superior", (0.0, 0.0, 1.0)))
        ).frame()
    except (TypeError, ValueError):
        return np.eye(3)
