"""Offscreen picture of the tagged boundary regions and the tool positions, for a human check.

It answers "are the supports and the tool positions where I meant them?": every support is named in the legend
(the lab's own as the lab named them, with their kind and selector; the built-in regions by their anatomy) in
its own colour, and the exertion points the sweep presses at are drawn as numbered markers (the number is the
case table's ``exertion_id``) in the views that see them (a point no view sees: hollow, in every view).
:func:`plot_regions` returns what it drew, so the picture's content can be checked against the mesh's supports
and exertion points.
"""

from __future__ import annotations

import textwrap
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
#: The built-in regions as the legend names them (region code -> anatomy and how it holds the liver).
BUILT_IN_NAMES = {
    0: "free surface",
    1: "vena cava patch — fixed",
    2: "ligaments — elastic foundation",
    3: "lower visceral face — elastic foundation",
    4: "rib contact — sliding",
}
#: Colours of the lab's own supports, in their order (none is a built-in region's, the sand or the grey).
SUPPORT_COLOURS = (
    (0.84, 0.15, 0.16),  # red
    (0.50, 0.30, 0.78),  # violet
    (0.00, 0.60, 0.60),  # teal
    (0.55, 0.34, 0.16),  # brown
    (0.12, 0.16, 0.50),  # navy
    (0.58, 0.62, 0.10),  # olive
    (0.35, 0.75, 0.95),  # sky
    (0.98, 0.55, 0.45),  # salmon
)
#: Tool positions: filled black in the views that see them; hollow grey, in every view, one that no view sees.
TOOL_SEEN = {"marker": "o", "s": 34.0, "c": [(0.0, 0.0, 0.0)], "edgecolors": "white", "linewidths": 1.0}
TOOL_HIDDEN = {"marker": "o", "s": 20.0, "facecolors": "none", "edgecolors": [(0.4, 0.4, 0.4)],
               "linewidths": 0.9}
#: Numbers beside the tool positions up to this many points (beyond, they would cover the liver).
MAX_NUMBERED = 40


def plot_regions(mesh: LiverMesh, path: str | Path, views=None, title: str | None = None, dpi: int = 110) -> dict:
    """Draw the boundary facets coloured by support, and the tool positions (PNG, matplotlib Agg, no GUI).

    Parameters
    ----------
    mesh : LiverMesh
        Tagged mesh. Its ``meta`` gives the lab's supports (``supports``: name, kind, ``selected_by``,
        ``region_code``; which facets each holds from ``mesh.facet_support``) and the tool positions
        (``exertion_candidates_mm``: the user's points after snapping when ``exertion_given``, else the
        candidates sampled on the visible area, which the sweep presses at; ``exertion_snap_mm``,
        ``exertion_not_visible``). A mesh read back from its VTU has neither: its built-in regions are
        named by their codes' anatomy.
    path : str or Path
        Output PNG (written atomically).
    views : list of (elev, azim, label), optional
        Camera angles in degrees in the anatomical frame (right, anterior,
        superior) taken from ``mesh.meta["region_params"]`` (RAS if absent);
        default: anterior-superior from the right, posterior-inferior from
        the left, and straight posterior. Orthographic projection.
    title : str, optional
        Figure title (default: node/tet counts).
    dpi : int
        Resolution.

    Returns
    -------
    dict
        What was drawn: ``legend``, one entry per legend item in order, each ``{"label", "colour" (r, g, b),
        "facets" (indices of the facets drawn in that colour, or None for the tool markers), "support" (index
        into ``meta["supports"]``, or None)}``; ``tool_points_mm`` (``(p, 3)``, mesh frame, the markers'
        positions, numbered 0..p-1 as ``exertion_id``); ``tool_points`` (``"given"``, ``"sampled"`` or None);
        ``views``, one per view ``{"label", "seen", "hidden"}``: the tool positions the view sees (drawn filled)
        and those on a facet facing away from it or behind another part of the liver (not drawn, unless no
        view sees them: then hollow, numbered in grey, and listed in the legend); ``never_seen``, those.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch
    from matplotlib.patheffects import withStroke
    from matplotlib.ticker import NullFormatter
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    from liverforce.atomic import atomic_path

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
    legend = _legend_entries(mesh)
    base = np.empty((len(mesh.facets), 3))
    for entry in legend:
        base[entry["facets"]] = entry["colour"]
    tools, source = _tool_points(mesh)
    q = tools @ frame.T
    q_on, on = _on_facets(tri, q)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    mid, half = 0.5 * (lo + hi), 0.5 * float((hi - lo).max())

    eyes = [_eye(elev, azim) for elev, azim, _ in views]
    seen_by = [_seen(tri, n, q_on, on, eye) for eye in eyes]
    never = ~np.any(seen_by, axis=0) if len(q) else np.zeros(0, bool)  # drawn hollow in every view
    handles = [Patch(color=entry["colour"]) for entry in legend]
    if len(q):
        legend.append({"label": _tool_words(mesh, source, len(q), np.flatnonzero(never).tolist()),
                       "colour": (0.0, 0.0, 0.0), "facets": None, "support": None})
        handles.append(Line2D([], [], linestyle="none", marker="o", markersize=6, markerfacecolor="black",
                              markeredgecolor="white"))
    if never.any():
        legend.append({"label": "tool position no view sees (drawn through the liver in every view)",
                       "colour": TOOL_HIDDEN["edgecolors"][0], "facets": None, "support": None})
        handles.append(Line2D([], [], linestyle="none", marker="o", markersize=5, markerfacecolor="none",
                              markeredgecolor=legend[-1]["colour"]))
    ncol = max(1, min(3, len(views), len(handles)))
    wrapped = [textwrap.fill(entry["label"], width=75, subsequent_indent="  ") for entry in legend]
    lines = [w.count("\n") + 1 for w in wrapped]
    rows = -(-len(lines) // ncol)  # the legend fills its columns one after the other
    legend_in = 0.16 * sum(max(lines[r::rows]) for r in range(rows)) + 0.3
    height = 5.0 + legend_in
    fig = Figure(figsize=(5.0 * len(views), height))
    FigureCanvasAgg(fig)
    drawn_views = []
    for i, ((elev, azim, label), eye, seen) in enumerate(zip(views, eyes, seen_by)):
        ax = fig.add_subplot(1, len(views), i + 1, projection="3d")
        ax.set_proj_type("ortho")  # parallel rays: what the tool positions' visibility is judged with
        ax.computed_zorder = False  # the markers over the surface: only those the view sees are drawn filled
        light = eye + np.array([0.0, 0.0, 0.5])
        light /= np.linalg.norm(light)
        shade = 0.45 + 0.55 * np.clip(n @ light, 0.0, 1.0)
        front = n @ eye > -0.05  # back-face culling keeps the drawing readable and fast
        colours = np.clip(base[front] * shade[front, None], 0.0, 1.0)
        ax.add_collection3d(Poly3DCollection(tri[front], facecolors=colours, edgecolors="none", zorder=1))
        if never.any():
            ax.scatter(*q[never].T, depthshade=False, zorder=3, **TOOL_HIDDEN)
        if seen.any():
            ax.scatter(*q[seen].T, depthshade=False, zorder=4, **TOOL_SEEN)
        if len(q) <= MAX_NUMBERED:
            for j in np.flatnonzero(seen | never):
                ax.text(*q[j], f"  {j}", fontsize=7, zorder=5, va="bottom", color="black" if seen[j] else "0.4",
                        path_effects=[withStroke(linewidth=2.0, foreground="white")])
        drawn_views.append({"label": label, "seen": np.flatnonzero(seen).tolist(),
                            "hidden": np.flatnonzero(~seen).tolist()})
        if len(q):
            label += f"\ntool positions seen here: {int(seen.sum())} of {len(q)}"
        ax.set_xlim(mid[0] - half, mid[0] + half)
        ax.set_ylim(mid[1] - half, mid[1] + half)
        ax.set_zlim(mid[2] - half, mid[2] + half)
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=elev, azim=azim)
        axes = (ax.xaxis, ax.yaxis, ax.zaxis)
        for k, (axis, name) in enumerate(zip(axes, ("right", "anterior", "superior"))):
            if abs(eye[k]) > 0.95:  # the view looks along this axis: its ticks would pile up in one place
                axis.set_major_formatter(NullFormatter())
            else:
                axis.set_label_text(f"{name} (mm)")
        drawn_views[-1]["unlabelled_axes"] = [name for axis, name in zip(axes, ("right", "anterior", "superior"))
                                              if isinstance(axis.get_major_formatter(), NullFormatter)
                                              and not axis.get_label_text()]
        ax.set_title(label, fontsize=9, pad=28)
    for handle, text in zip(handles, wrapped):
        handle.set_label(text)
    fig.legend(handles=handles, loc="lower center", ncol=ncol, fontsize=8, frameon=False)
    fig.subplots_adjust(bottom=legend_in / height, top=1.0 - 0.6 / height)
    fig.suptitle(title or f"boundary regions: {len(mesh.points)} nodes, {len(mesh.tets)} tets", fontsize=10)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    return {"legend": legend, "tool_points_mm": tools, "tool_points": source, "views": drawn_views,
            "never_seen": np.flatnonzero(never).tolist()}


def _legend_entries(mesh: LiverMesh) -> list[dict]:
    """The legend's region entries (see :func:`plot_regions`), each with the facets drawn in its colour.

    The lab's supports (``meta["supports"]``) are named as the lab named them, ``name — kind (selector)``, each
    in its own colour over the facets ``mesh.facet_support`` gives it; the auto-tagged regions left (all of them
    without the lab's supports; those beneath under ``mode: add``) by their anatomy. Without ``facet_support``
    (a mesh read back from its VTU, given the features JSON's ``supports``) the facets of one support cannot be
    told from another's: a region code is named by the supports that hold it, in its built-in colour. Empty
    regions are left out."""
    region, visible = mesh.facet_region, mesh.facet_visible
    supports = mesh.meta.get("supports") or []
    owner = mesh.facet_support
    prefix = "built-in " if supports else ""
    out = []
    free = np.flatnonzero((region == 0) & ~visible)
    if free.size:
        out.append({"label": BUILT_IN_NAMES[0], "colour": REGION_COLOURS[0], "facets": free, "support": None})
    if visible.any():
        out.append({"label": "visible (free): camera side, where sampled tool positions lie",
                    "colour": VISIBLE_COLOUR, "facets": np.flatnonzero(visible), "support": None})
    for code in sorted(c for c in REGION_COLOURS if c):
        facets = np.flatnonzero(region == code)
        if owner is not None:
            facets = facets[owner[facets] < 0]
        elif supports:
            names = [_support_words(s) for s in supports if s.get("region_code") == code]
            if names and facets.size:
                out.append({"label": "; ".join(names), "colour": REGION_COLOURS[code], "facets": facets,
                            "support": None})
                continue
        if facets.size:
            out.append({"label": prefix + BUILT_IN_NAMES[code], "colour": REGION_COLOURS[code], "facets": facets,
                        "support": None})
    if owner is not None:
        for i, s in enumerate(supports):
            facets = np.flatnonzero(owner == i)
            if facets.size:
                out.append({"label": _support_words(s), "colour": SUPPORT_COLOURS[i % len(SUPPORT_COLOURS)],
                            "facets": facets, "support": i})
    return out


def _support_words(report: dict) -> str:
    """A lab support as the legend names it: ``cava — fixed (group vena_cava)``, a foundation with its slot."""
    kind = report.get("kind", "?")
    if kind == "foundation":
        slot = {REGION_CODES["ligament"]: "ligament", REGION_CODES["visceral"]: "visceral"}.get(
            report.get("region_code"))
        kind = f"foundation {slot}" if slot else kind
    how = report.get("selected_by") or report.get("selector")
    return f"{report.get('name', '?')} — {kind}" + (f" ({how})" if how else "")


def _tool_points(mesh: LiverMesh) -> tuple[np.ndarray, str | None]:
    """The exertion points recorded on the mesh (mm, mesh frame) and whose they are."""
    cand = mesh.meta.get("exertion_candidates_mm")
    if cand is None:
        return np.zeros((0, 3)), None
    return np.asarray(cand, float).reshape(-1, 3), "given" if mesh.meta.get("exertion_given") else "sampled"


def _tool_words(mesh: LiverMesh, source: str | None, count: int, never: list[int]) -> str:
    """The legend entry of the tool positions: how many, whose, how far snapped, which lie off the visible area,
    which no view sees (``never``)."""
    if source == "given":
        snap = max(mesh.meta.get("exertion_snap_mm") or [0.0])
        text = (f"tool positions: {count} given by the lab, snapped "
                + (f"≤ {snap:.2g} mm" if snap >= 0.01 else "< 0.01 mm") + " onto the surface")
    else:
        text = f"tool positions: {count} sampled on the visible surface"
    off = [int(r["point"]) for r in mesh.meta.get("exertion_not_visible") or [] if "point" in r]
    if off:
        text += f"; off the visible area: {', '.join(map(str, off))}"
    if never:
        text += f"; no view sees: {', '.join(map(str, never))}"
    return text + (" (numbers: exertion_id)" if count <= MAX_NUMBERED else "")


def _on_facets(tri: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each tool position's closest point on the facets ``tri`` and that facet (a point of the input surface
    may lie a little off the mesh's)."""
    if not len(q):
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    from liverforce.mesh.supports import closest_on_triangles

    p, _, facet = closest_on_triangles(tri, q, k=16)
    return p, facet


def _eye(elev: float, azim: float) -> np.ndarray:
    """Unit vector toward the viewer of a view at ``elev``, ``azim`` degrees (matplotlib's 3D convention)."""
    e, a = np.deg2rad(elev), np.deg2rad(azim)
    return np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])


def _seen(tri: np.ndarray, normals: np.ndarray, q: np.ndarray, on: np.ndarray, eye: np.ndarray) -> np.ndarray:
    """Whether a view along ``-eye`` (parallel rays) sees each point ``q[j]`` lying on facet ``on[j]``: the facet
    faces the viewer and no other facet crosses the ray from the point toward the viewer."""
    seen = normals[on] @ eye > 0.0
    scale = float(np.ptp(tri.reshape(-1, 3), axis=0).max())
    reach = float(np.linalg.norm(tri - tri.mean(axis=1, keepdims=True), axis=2).max())  # largest facet's radius
    cent = tri.mean(axis=1)
    across = cent - np.outer(cent @ eye, eye)  # centroids projected along the view
    for j in np.flatnonzero(seen):
        p = q[j]
        near = np.flatnonzero((np.linalg.norm(across - (p - (p @ eye) * eye), axis=1) <= reach)
                              & (cent @ eye > p @ eye - reach))
        near = near[near != on[j]]
        seen[j] = not _ray_hits(tri[near], p, eye, 1e-6 * scale).any()
    return seen


def _ray_hits(tri: np.ndarray, origin: np.ndarray, direction: np.ndarray, eps: float) -> np.ndarray:
    """Which triangles the ray ``origin + t direction`` (``t > eps``) crosses (Möller–Trumbore)."""
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    h = np.cross(direction, e2)
    det = np.einsum("ij,ij->i", e1, h)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = origin - tri[:, 0]
    u = np.einsum("ij,ij->i", s, h) * inv
    qv = np.cross(s, e1)
    v = (qv @ direction) * inv
    t = np.einsum("ij,ij->i", e2, qv) * inv
    return ok & (u >= 0.0) & (v >= 0.0) & (u + v <= 1.0) & (t > eps)


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
