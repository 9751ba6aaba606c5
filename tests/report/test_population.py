"""The population picture: top views that cover each liver's silhouette, at one scale, in the group colours."""
from __future__ import annotations

import numpy as np
import pytest

#: a unit cube, outward-oriented triangles
CUBE_V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
CUBE_F = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                   [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])


def box(a, b, c, shift=(0.0, 0.0, 0.0)):
    return CUBE_V * [a, b, c] + shift, CUBE_F.copy()


def area_xy(tri):
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    return float(np.sum(np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])) / 2)


@pytest.mark.parametrize("inward", [False, True])
def test_top_view_covers_the_silhouette_once_centred_and_low_to_high(inward):
    from liverforce.report.population import top_view

    v, f = box(120.0, 80.0, 40.0, shift=(30.0, -7.0, 5.0))
    if inward:
        f = f[:, ::-1]
    xy, shade = top_view(v, f)
    assert area_xy(xy) == pytest.approx(120.0 * 80.0)  # the upward faces tile the x-y silhouette exactly once
    assert xy[..., 0].min() == pytest.approx(-60.0) and xy[..., 1].max() == pytest.approx(40.0)  # centred
    assert np.all((shade >= 0) & (shade <= 1)) and len(shade) == len(xy)


def test_top_view_is_drawn_from_low_to_high():
    from liverforce.report.population import top_view

    v1, f1 = box(10.0, 10.0, 10.0)
    v2, f2 = box(10.0, 10.0, 10.0, shift=(5.0, 0.0, 50.0))
    xy, _ = top_view(np.vstack([v2, v1]), np.vstack([f2, f1 + len(v2)]))
    # two stacked boxes, the upper one listed first: its lid is drawn last (painted on top of the lower one)
    assert len(xy) == 4 and area_xy(xy) == pytest.approx(2 * 100.0)
    assert xy[:2, :, 0].max() == pytest.approx(2.5) and xy[2:, :, 0].max() == pytest.approx(7.5)


def test_population_figure_draws_each_group_in_its_colour_at_one_scale(tmp_path):
    import meshio
    from matplotlib.image import imread

    from liverforce.report.population import COLOURS, load_population, population_figure

    surfaces, volumes = {}, {}
    for gid, (a, b, c) in {"proc-0000": (200, 130, 80), "proc-0001": (100, 65, 40),
                           "val-1000": (180, 120, 70), "val-2000": (150, 100, 60)}.items():
        v, f = box(a, b, c)
        surfaces[gid] = tmp_path / f"{gid}.ply"
        meshio.write(surfaces[gid], meshio.Mesh(v, [("triangle", f)]))
        volumes[gid] = a * b * c
    livers = load_population(surfaces, volumes, training=["proc-0001", "proc-0000"], unseen=["val-1000"])
    # training first in the order given, then unseen; an id of neither list named val- is unseen
    assert [(lv.gid, lv.role) for lv in livers] == [("proc-0001", "training"), ("proc-0000", "training"),
                                                    ("val-1000", "unseen"), ("val-2000", "unseen")]
    assert [lv.volume_l for lv in livers] == pytest.approx([v / 1e6 for v in (100 * 65 * 40, 200 * 130 * 80,
                                                                              180 * 120 * 70, 150 * 100 * 60)])
    # one scale: a liver twice as long and wide covers four times the area
    assert area_xy(livers[1].triangles_xy) == pytest.approx(4 * area_xy(livers[0].triangles_xy))

    path = population_figure(livers, tmp_path / "fig" / "population.png", volume_range_l=(1.0, 2.2))
    img = imread(path)[..., :3]
    assert img.shape[0] > 300 and img.shape[1] > 600
    assert not list(path.parent.glob(".*tmp*"))

    def near(part, colour):  # pixels of that hue (the shading only scales the colour)
        rgb = np.asarray(colour)
        cos = (part @ rgb) / (np.linalg.norm(part, axis=-1) * np.linalg.norm(rgb) + 1e-9)
        return int(np.sum((cos > 0.99) & (part.max(axis=-1) > 0.2)))

    grid = img[: int(0.3 * img.shape[0])]  # the panels (the histogram below is coloured too)
    assert near(grid, COLOURS["training"]) > 2000 and near(grid, COLOURS["unseen"]) > 2000


def test_population_figure_refuses_an_empty_population(tmp_path):
    from liverforce.report.population import population_figure

    with pytest.raises(ValueError, match="no liver to draw"):
        population_figure([], tmp_path / "p.png")
