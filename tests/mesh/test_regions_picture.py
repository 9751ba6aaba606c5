"""The regions picture (``mesh/<gid>.regions.png``) answers "are my supports and my tool positions where I meant
them?": each support is named in the legend as the lab named it (name, kind, selector) in its own colour over the
facets it holds, the built-in regions by their anatomy, and the exertion points the sweep presses at are drawn,
those a view cannot see told apart. Before, the legend named only the region codes (ivc, ligament, ...), two lab
supports of one kind shared a colour, and no tool position was drawn.

The picture is checked through what :func:`plot_regions` reports it drew, against the mesh's supports and points.
"""

from __future__ import annotations

import numpy as np
import pytest

from liverforce.mesh.build import build_liver_mesh
from liverforce.mesh.given import build_given_mesh
from liverforce.mesh.plot import BUILT_IN_NAMES, REGION_COLOURS, _seen, plot_regions
from liverforce.mesh.regions import tag_regions
from liverforce.mesh.supports import Support, parse_supports, selector_words
from liverforce.mesh.types import REGION_CODES, LiverMesh

N_SAMPLED = 6


def _labels(drawn):
    return [e["label"] for e in drawn["legend"]]


def _tool_label(drawn):
    (label,) = [e["label"] for e in drawn["legend"] if e["label"].startswith("tool positions:")]
    return label


def _view(drawn, word):
    (v,) = [v for v in drawn["views"] if v["label"].startswith(word)]
    return v


def _partition(drawn, n_facets):
    """The legend's region entries cover every facet once."""
    facets = np.concatenate([e["facets"] for e in drawn["legend"] if e["facets"] is not None])
    assert np.array_equal(np.sort(facets), np.arange(n_facets))


@pytest.fixture(scope="module")
def scene(liver_surface):
    """Where the lab puts its supports and tool positions on the procedural liver (mesh frame, mm)."""
    V, F = liver_surface.vertices, liver_surface.faces
    region, visible = tag_regions(V, F)
    cent = V[F].mean(axis=1)
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    cava = cent[np.argmin(cent[:, 1])]  # the most posterior point
    left = cent[np.argmin(cent[:, 0] - 0.5 * cent[:, 2])]  # far left, up
    facing = n @ np.array([0.0, np.cos(np.pi / 6), np.sin(np.pi / 6)]) > 0.9  # the camera's view, head on
    vis = np.flatnonzero(visible & facing & (np.abs(cent[:, 0]) < 80))  # not on a thin lobe's tip
    front = cent[vis[np.linspace(0, len(vis) - 1, 4).astype(int)]]
    back = np.flatnonzero((n[:, 1] < -0.9) & (np.linalg.norm(cent - cava, axis=1) > 60)
                          & (np.linalg.norm(cent - left, axis=1) > 40) & (cent[:, 2] > cent[:, 2].min() + 25))
    tools = np.vstack([front, cent[back[0]]])  # four on the camera side, the last on the back
    assert (np.linalg.norm(tools - cava, axis=1) > 25).all() and (np.linalg.norm(tools - left, axis=1) > 20).all()
    floor = float(cent[:, 2].min() + 15)
    supports = [
        {"name": "cava", "kind": "fixed", "sphere": {"center_mm": cava.tolist(), "radius_mm": 20.0}},
        {"name": "left vein", "kind": "fixed", "sphere": {"center_mm": left.tolist(), "radius_mm": 15.0}},
        {"name": "floor", "kind": "foundation", "region": "visceral", "stiffness": {"total_n_per_mm": 40.0},
         "box": {"min_mm": [-1e3, -1e3, -1e3], "max_mm": [1e3, 1e3, floor]}},
    ]
    return {"cava": cava, "left": left, "floor": floor, "tools": tools, "supports": supports}


@pytest.fixture(scope="module")
def lab_mesh(liver_surface, scene):
    """The liver meshed with the lab's supports (replace) and tool positions."""
    return build_liver_mesh(liver_surface, target_nodes=600, seed=0, exertion_points=scene["tools"],
                            supports=parse_supports({"mode": "replace", "list": scene["supports"]}))


def test_a_built_in_liver_names_its_regions_and_draws_the_sampled_tool_positions(tmp_path, liver_surface):
    mesh = build_liver_mesh(liver_surface, target_nodes=600, seed=0,
                            exertion_sampling={"n_points": N_SAMPLED, "min_spacing_mm": 15.0, "seed": 3})
    drawn = plot_regions(mesh, tmp_path / "regions.png")
    assert [p.name for p in tmp_path.iterdir()] == ["regions.png"]
    labels = _labels(drawn)
    for code in range(1, 5):  # each region by its anatomy, in its colour, over exactly its facets
        (entry,) = [e for e in drawn["legend"] if e["label"] == BUILT_IN_NAMES[code]]
        assert entry["colour"] == REGION_COLOURS[code] and entry["support"] is None
        np.testing.assert_array_equal(entry["facets"], np.flatnonzero(mesh.facet_region == code))
    assert not any("built-in" in label for label in labels)  # no lab supports to tell them from
    _partition(drawn, len(mesh.facets))
    # the sweep's candidates, as the features JSON records them, all on the camera side
    assert drawn["tool_points"] == "sampled"
    np.testing.assert_array_equal(drawn["tool_points_mm"], np.asarray(mesh.meta["exertion_candidates_mm"]))
    assert len(drawn["tool_points_mm"]) == N_SAMPLED
    assert _tool_label(drawn).startswith(f"tool positions: {N_SAMPLED} sampled on the visible surface")
    assert _view(drawn, "anterior")["seen"] == list(range(N_SAMPLED))
    assert _view(drawn, "posterior-inferior")["hidden"] == list(range(N_SAMPLED))


def test_the_labs_supports_are_named_as_given_each_in_its_colour_over_its_facets(tmp_path, lab_mesh, scene):
    mesh = lab_mesh
    drawn = plot_regions(mesh, tmp_path / "regions.png")
    by_label = {e["label"]: e for e in drawn["legend"]}
    cava = by_label["cava — fixed (sphere r 20 mm)"]
    vein = by_label["left vein — fixed (sphere r 15 mm)"]
    floor = by_label["floor — foundation visceral (box)"]
    assert [cava["support"], vein["support"], floor["support"]] == [0, 1, 2]
    assert len({cava["colour"], vein["colour"], floor["colour"]} | set(REGION_COLOURS.values())) == 8
    # two fixed supports: one region code, told apart by where each lies
    cent = mesh.points[mesh.facets].mean(axis=1)
    slack = 8.0  # a mesh facet's centroid vs the input facets the sphere selected
    assert (np.linalg.norm(cent[cava["facets"]] - scene["cava"], axis=1) <= 20.0 + slack).all()
    assert (np.linalg.norm(cent[vein["facets"]] - scene["left"], axis=1) <= 15.0 + slack).all()
    assert (cent[floor["facets"]][:, 2] <= scene["floor"] + slack).all()
    np.testing.assert_array_equal(np.sort(np.concatenate([cava["facets"], vein["facets"]])),
                                  np.flatnonzero(mesh.facet_region == REGION_CODES["ivc"]))
    np.testing.assert_array_equal(floor["facets"], np.flatnonzero(mesh.facet_region == REGION_CODES["visceral"]))
    assert not any(label.startswith("built-in") for label in by_label)  # replace: no built-in region is left
    _partition(drawn, len(mesh.facets))


def test_the_labs_tool_positions_are_drawn_after_snapping_and_the_hidden_one_told_apart(tmp_path, lab_mesh, scene):
    drawn = plot_regions(lab_mesh, tmp_path / "regions.png")
    tools = drawn["tool_points_mm"]
    assert drawn["tool_points"] == "given"
    np.testing.assert_array_equal(tools, np.asarray(lab_mesh.meta["exertion_candidates_mm"]))
    np.testing.assert_allclose(tools, scene["tools"], atol=1e-6)  # given on the surface: snapped in place
    label = _tool_label(drawn)
    assert label.startswith("tool positions: 5 given by the lab, snapped < 0.01 mm")
    assert "off the visible area: 4" in label  # the back one, as the features JSON lists it
    assert _view(drawn, "anterior")["seen"] == [0, 1, 2, 3] and _view(drawn, "anterior")["hidden"] == [4]
    assert 4 in _view(drawn, "posterior-inferior")["seen"]
    assert drawn["never_seen"] == [] and "no view sees" not in " ".join(_labels(drawn))


def test_a_tool_position_no_view_sees_is_drawn_hollow_and_named(tmp_path, lab_mesh):
    drawn = plot_regions(lab_mesh, tmp_path / "regions.png", views=[(0.0, 90.0, "anterior")])
    assert drawn["views"][0]["seen"] == [0, 1, 2, 3] and drawn["never_seen"] == [4]
    assert _tool_label(drawn).endswith("; no view sees: 4 (numbers: exertion_id)")
    assert _labels(drawn)[-1].startswith("tool position no view sees")


def test_under_add_the_built_in_regions_beneath_keep_their_anatomical_names(tmp_path, liver_surface, scene):
    mesh = build_liver_mesh(liver_surface, target_nodes=600, seed=0,
                            supports=parse_supports({"mode": "add", "list": scene["supports"][1:2]}))
    drawn = plot_regions(mesh, tmp_path / "regions.png")
    by_label = {e["label"]: e for e in drawn["legend"]}
    vein = by_label["left vein — fixed (sphere r 15 mm)"]
    ivc = by_label["built-in " + BUILT_IN_NAMES[REGION_CODES["ivc"]]]
    assert ivc["colour"] == REGION_COLOURS[REGION_CODES["ivc"]] and vein["colour"] != ivc["colour"]
    cent = mesh.points[mesh.facets].mean(axis=1)
    assert (np.linalg.norm(cent[vein["facets"]] - scene["left"], axis=1) <= 15.0 + 8.0).all()
    assert np.linalg.norm(cent[ivc["facets"]] - scene["left"], axis=1).min() > 15.0
    assert {f"built-in {BUILT_IN_NAMES[c]}" for c in range(1, 5)} <= set(by_label)
    assert drawn["tool_points"] is None and drawn["tool_points_mm"].shape == (0, 3)
    _partition(drawn, len(mesh.facets))


def test_a_mesh_as_given_names_its_supports_over_exactly_the_facets_they_hold(tmp_path, liver_mesh, scene):
    sup = parse_supports({"mode": "replace", "list": scene["supports"]})
    mesh = build_given_mesh(liver_mesh.points, liver_mesh.tets, supports=sup)
    drawn = plot_regions(mesh, tmp_path / "regions.png")
    held = {e["support"]: len(e["facets"]) for e in drawn["legend"] if e["support"] is not None}
    assert held == {i: r["n_facets"] for i, r in enumerate(mesh.meta["supports"])}


def test_a_mesh_read_back_without_its_support_record_names_each_region_by_its_supports(tmp_path, liver_mesh):
    meta = {"supports": [{"name": "cava", "kind": "fixed", "selected_by": "group vena_cava", "region_code": 1},
                         {"name": "hv", "kind": "fixed", "selected_by": "box", "region_code": 1}]}
    mesh = LiverMesh(liver_mesh.points, liver_mesh.tets, liver_mesh.facets, liver_mesh.facet_region,
                     liver_mesh.facet_visible, meta)
    drawn = plot_regions(mesh, tmp_path / "regions.png")
    (entry,) = [e for e in drawn["legend"] if e["label"] == "cava — fixed (group vena_cava); hv — fixed (box)"]
    np.testing.assert_array_equal(entry["facets"], np.flatnonzero(mesh.facet_region == 1))


def test_a_view_along_an_axis_leaves_that_axis_unlabelled(tmp_path, liver_surface):
    """The straight posterior view looks along the anterior axis: its ticks would pile up in one spot, so that
    axis is left without tick labels or name; the oblique views keep all three."""
    mesh = build_liver_mesh(liver_surface, target_nodes=300, seed=0)
    drawn = plot_regions(mesh, tmp_path / "regions.png")
    unlabelled = {v["label"].split("\n")[0]: v["unlabelled_axes"] for v in drawn["views"]}
    assert unlabelled == {"anterior-superior, from the right": [], "posterior-inferior, from the left": [],
                          "posterior": ["anterior"]}


def test_a_point_behind_another_part_of_the_surface_is_not_seen():
    square = np.array([[[0, 0, 0], [1, 0, 0], [1, 1, 0]], [[0, 0, 0], [1, 1, 0], [0, 1, 0]]], float)
    tri = np.concatenate([square, square + [0, 0, 1], square + [3, 0, 1]])  # a lid over the first square
    normals = np.tile([0.0, 0.0, 1.0], (len(tri), 1))
    q = np.array([[0.6, 0.3, 0.0], [3.6, 0.3, 1.0]])
    up = np.array([0.0, 0.0, 1.0])
    np.testing.assert_array_equal(_seen(tri, normals, q, np.array([0, 4]), up), [False, True])
    np.testing.assert_array_equal(_seen(tri, normals, q, np.array([0, 4]), -up), [False, False])  # facing away


@pytest.mark.parametrize("selector, words", [
    (("group", {"name": "vena_cava"}), "group vena_cava"),
    (("group", {"value": 3}), "group 3"),
    (("group", {"array": "tag", "value": 3}), "group tag=3"),
    (("sphere", {"center_mm": [0, 0, 0], "radius_mm": 12.5}), "sphere r 12.5 mm"),
    (("box", {"min_mm": [0, 0, 0], "max_mm": [1, 1, 1]}), "box"),
    (("file", {"path": "/lab/cava.csv"}), "file cava.csv"),
])
def test_selector_words(selector, words):
    assert selector_words(Support("s", "fixed", selector)) == words


def test_the_support_record_says_how_it_was_selected(lab_mesh):
    assert [r["selected_by"] for r in lab_mesh.meta["supports"]] == ["sphere r 20 mm", "sphere r 15 mm", "box"]
    assert lab_mesh.facet_support is not None and lab_mesh.validate() is None
