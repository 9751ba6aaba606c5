"""The liver population as a picture: a top view of every liver, training and unseen, and their volumes.

Each liver is drawn as its top view (the projection on the x–y plane of the
RAS frame: +x patient right, +y anterior, seen from superior), filled with the
upward-facing triangles of its closed surface, shaded by their slope and
drawn from low to high so the upper surface covers the lower one. Every panel
has the same millimetre scale, so the panels compare sizes as well as shapes.
Training livers are blue, unseen (validation) livers orange. Below the grid, a
histogram of the volumes (litres) of both groups, with the configured volume
range of the procedural livers shaded.

Example
-------
>>> livers = load_population({"proc-0000": "geometry/proc-0000.ply"}, {"proc-0000": 1.2e6},
...                          training=["proc-0000"])                                  # doctest: +SKIP
>>> population_figure(livers, "report/figures/population.png")                        # doctest: +SKIP
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from liverforce.atomic import atomic_path

#: panel colours (RGB 0-1) of the two groups
COLOURS = {"training": (0.16, 0.42, 0.70), "unseen": (0.90, 0.45, 0.08)}
ROLE_TEXT = {"training": "training", "unseen": "unseen (validation)"}


@dataclass(frozen=True)
class LiverView:
    """What the population figure needs of one liver.

    Attributes
    ----------
    gid : str
        Geometry id (``proc-0003``, ``val-1001``, ``imp-ct01``).
    role : str
        ``training`` or ``unseen``.
    volume_l : float
        Volume in litres (NaN when unknown).
    triangles_xy : numpy.ndarray
        ``(T, 3, 2)`` top-view triangles (mm), centred on the liver's x–y bounding-box centre,
        sorted from low to high (mean z).
    shade : numpy.ndarray
        ``(T,)`` in [0, 1]: Lambert shading of each triangle (light from upper left, above).
    """

    gid: str
    role: str
    volume_l: float
    triangles_xy: np.ndarray
    shade: np.ndarray


def top_view(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Upward-facing triangles of a closed, outward-oriented surface, projected on x–y, low to high.

    Parameters
    ----------
    vertices : (N, 3) float, mm
    faces : (T, 3) int

    Returns
    -------
    triangles_xy : (T', 3, 2) float
        The projected triangles with ``n_z > 0`` (their union is the liver's
        silhouette seen from +z), centred on the x–y bounding-box centre and
        sorted by mean z (ascending, for a painter's algorithm).
    shade : (T',) float
        Lambert shading ``max(0, n · l)`` in [0, 1], ``l`` a light from the
        upper left of the picture and above (-x, +y, +z).
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    tri = v[f]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(normal, axis=1)
    ok = length > 0
    unit = np.zeros_like(normal)
    unit[ok] = normal[ok] / length[ok, None]
    if np.sum(unit[:, 2] * length) < 0:  # inward-oriented surface (signed z-projected area < 0): flip
        unit = -unit
    up = unit[:, 2] > 0
    tri, unit = tri[up], unit[up]
    light = np.array([-0.6, 0.6, 1.0]) / np.linalg.norm([-0.6, 0.6, 1.0])
    shade = np.clip(unit @ light, 0.0, 1.0)
    order = np.argsort(tri[:, :, 2].mean(axis=1), kind="stable")
    xy = tri[order][:, :, :2]
    lo, hi = v[:, :2].min(axis=0), v[:, :2].max(axis=0)
    return xy - (lo + hi) / 2, shade[order]


def load_population(surfaces: dict[str, str | Path], volumes_mm3: dict[str, float], training: list[str] = (),
                    unseen: list[str] = ()) -> list[LiverView]:
    """Read every liver surface (PLY, or anything meshio reads) into a :class:`LiverView`.

    Parameters
    ----------
    surfaces : dict
        geometry id -> surface file.
    volumes_mm3 : dict
        geometry id -> volume (mm³); missing ids get NaN.
    training, unseen : list of str
        The ids of each group; an id in neither is taken as ``unseen`` when it
        starts with ``val-``, else as ``training``.

    Returns
    -------
    list of LiverView
        Training livers first, then unseen ones, each group in the order given
        (ids of neither list sorted after them).
    """
    import meshio

    training, unseen = list(training), list(unseen)

    def role(gid: str) -> str:
        if gid in unseen:
            return "unseen"
        if gid in training:
            return "training"
        return "unseen" if gid.startswith("val-") else "training"

    rank = {g: i for i, g in enumerate(training + unseen)}
    out = []
    for gid in sorted(surfaces, key=lambda g: (role(g) != "training", rank.get(g, len(rank)), g)):
        mesh = meshio.read(surfaces[gid])
        faces = mesh.cells_dict.get("triangle")
        if faces is None:
            raise ValueError(f"{surfaces[gid]}: no triangles to draw the population picture from "
                             f"(cell types {list(mesh.cells_dict)}); the geometry stage writes a triangle surface")
        xy, shade = top_view(mesh.points, faces)
        vol = volumes_mm3.get(gid)
        out.append(LiverView(gid, role(gid), float(vol) / 1e6 if vol is not None else float("nan"), xy, shade))
    return out


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def population_figure(livers: list[LiverView], path: str | Path, volume_range_l: tuple[float, float] | None = None,
                      n_cols: int = 8, max_panels: int = 96) -> Path:
    """Write the population picture (PNG, atomically): a grid of top views and a histogram of volumes.

    Parameters
    ----------
    livers : list of LiverView
        :func:`load_population`.
    path : path
        Output PNG.
    volume_range_l : (float, float), optional
        The configured range of procedural volumes (litres), shaded in the histogram.
    n_cols : int
        Panels per row.
    max_panels : int
        At most this many panels (the training livers first); the histogram
        always counts every liver, and the title says how many are drawn.

    Returns
    -------
    Path
        ``path``.
    """
    from matplotlib.collections import PolyCollection
    from matplotlib.gridspec import GridSpec

    if not livers:
        raise ValueError("no liver to draw: the population picture needs at least one surface")
    plt = _plt()
    shown = livers[:max_panels]
    n_cols = max(1, min(n_cols, len(shown)))
    n_rows = int(np.ceil(len(shown) / n_cols))
    half = max(float(np.abs(lv.triangles_xy).max()) for lv in shown) * 1.04  # same mm scale in every panel
    panel_in = 1.55
    hist_in = 1.9
    fig = plt.figure(figsize=(max(n_cols * panel_in, 7.0), n_rows * panel_in * 0.8 + hist_in + 0.5), dpi=110)
    gs = GridSpec(n_rows + 1, n_cols, figure=fig, height_ratios=[panel_in * 0.8] * n_rows + [hist_in],
                  hspace=0.35, wspace=0.05)
    for i, lv in enumerate(shown):
        ax = fig.add_subplot(gs[i // n_cols, i % n_cols])
        base = np.array(COLOURS[lv.role])
        shade = np.clip(lv.shade, 0.0, 1.0)[:, None]
        face = np.clip(base * (0.45 + 0.75 * shade) + 0.15 * shade ** 8, 0.0, 1.0)  # lit: brighter, with a sheen
        ax.add_collection(PolyCollection(lv.triangles_xy, facecolors=face, edgecolors="none", antialiased=False,
                                         rasterized=True))
        ax.set_xlim(-half, half)
        ax.set_ylim(-half * 0.75, half * 0.75)
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        for s in ax.spines.values():
            s.set_color(base)
            s.set_linewidth(1.2)
        vol = f"{lv.volume_l:.2f} L" if np.isfinite(lv.volume_l) else "? L"
        ax.set_title(f"{lv.gid}  {vol}", fontsize=7, color=base * 0.8, pad=2)
        if i == 0:  # a 100 mm scale bar
            x0, y0 = -half * 0.92, -half * 0.66
            ax.plot([x0, x0 + 100.0], [y0, y0], color="k", lw=1.5)
            ax.text(x0 + 50.0, y0 + half * 0.04, "100 mm", ha="center", va="bottom", fontsize=6)
    n_t = sum(lv.role == "training" for lv in livers)
    n_u = len(livers) - n_t
    drawn = "" if len(shown) == len(livers) else f" (first {len(shown)} drawn)"
    fig.suptitle(f"Liver population, top view (x right, y anterior): {n_t} training (blue), {n_u} unseen "
                 f"(orange){drawn}", fontsize=9)

    ax = fig.add_subplot(gs[n_rows, :])
    vols = {r: np.array([lv.volume_l for lv in livers if lv.role == r and np.isfinite(lv.volume_l)])
            for r in ("training", "unseen")}
    allv = np.concatenate(list(vols.values()))
    if volume_range_l is not None:
        ax.axvspan(float(volume_range_l[0]), float(volume_range_l[1]), color="0.92", zorder=0,
                   label=f"configured range {volume_range_l[0]:g}–{volume_range_l[1]:g} L")
    if len(allv):
        lo = min(allv.min(), volume_range_l[0] if volume_range_l is not None else np.inf)
        hi = max(allv.max(), volume_range_l[1] if volume_range_l is not None else -np.inf)
        step = 0.05 if hi - lo > 0.3 else 0.02  # litres per bin, edges on round numbers
        edges = np.arange(np.floor(lo / step - 1e-9) * step, hi + step, step)
        counts, _, _ = ax.hist([vols["training"], vols["unseen"]], bins=edges, stacked=True,
                color=[COLOURS["training"], COLOURS["unseen"]],
                label=[f"{ROLE_TEXT['training']} (n={len(vols['training'])})",
                       f"{ROLE_TEXT['unseen']} (n={len(vols['unseen'])})"], zorder=2)
        ax.set_ylim(0, max(1.0, float(np.max(counts))) * 1.7)  # head room: the legend never covers a bar
    ax.set_xlabel("liver volume (L)", fontsize=8)
    ax.set_ylabel("livers", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.yaxis.get_major_locator().set_params(integer=True)
    ax.legend(fontsize=7, loc="upper right")
    ax.grid(alpha=0.3, zorder=1)
    fig.subplots_adjust(left=0.05, right=0.98, top=1 - 0.45 / fig.get_figheight(), bottom=0.5 / fig.get_figheight())
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return path
