"""Exertion points and supports given by the user, through the geometry, mesh and sweep stages.

A procedural liver is written as a file in metres and LPS (as 3D Slicer exports it); its exertion
points and supports are given in that file's frame (mm). The case table must carry exactly the
given points (snapped to the surface), and the supports must be where they were put.
"""

from __future__ import annotations

import numpy as np
import pytest

from liverforce.config import ConfigError, compose
from liverforce.geometry.procedural import cube_phantom, procedural_liver
from liverforce.mesh.build import build_liver_mesh
from liverforce.mesh.regions import tag_regions
from liverforce.mesh.supports import SupportError, parse_supports
from liverforce.mesh.types import REGION_CODES

LPS = np.array([-1.0, -1.0, 1.0])  # RAS <-> LPS: x and y negated


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """Geometry + mesh + sweep stages on an imported liver with its own supports and exertion points."""
    import trimesh

    from liverforce.dataset import io as dio
    from liverforce.pipeline.geometry import make_geometry
    from liverforce.pipeline.mesh import make_mesh
    from liverforce.pipeline.plan import Plan
    from liverforce.pipeline.sweep import make_sweep

    tmp = tmp_path_factory.mktemp("scene")
    liver = procedural_liver(0)
    trimesh.Trimesh(liver.vertices * LPS / 1000.0, liver.faces[:, ::-1], process=False).export(tmp / "liver.stl")
    # three points on the visible (anterior-superior) surface, 1 mm off it, in the file frame (LPS mm)
    region, visible = tag_regions(liver.vertices, liver.faces)
    cent = liver.vertices[liver.faces].mean(axis=1)
    vis = np.flatnonzero(visible)
    picks = vis[np.linspace(0, len(vis) - 1, 3).astype(int)]
    tri = liver.vertices[liver.faces[picks]]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    given_ras = cent[picks] + 1.0 * normal
    posterior = cent[np.argmin(cent[:, 1])]
    spec = {
        "kind": "imported", "name": "lab", "path": str(tmp / "liver.stl"), "units": "m", "label": None,
        "frame": "LPS",
        "exertion_points": {"coordinates_mm": (given_ras * LPS).tolist()},
        "supports": {"mode": "replace", "list": [
            {"name": "cava", "kind": "fixed", "sphere": {"center_mm": (posterior * LPS).tolist(), "radius_mm": 20.0}},
            {"name": "floor", "kind": "foundation", "region": "visceral", "stiffness": {"total_n_per_mm": 40.0},
             "box": {"min_mm": [-1e3, -1e3, -1e3], "max_mm": [1e3, 1e3, float(cent[:, 2].min() + 15)]}},
        ]},
    }
    make_geometry(spec, tmp / "imp-lab.ply", tmp / "imp-lab.json")
    cfg = compose(["experiment=smoke"])
    mesh_cfg = {**cfg["mesh"], "target_nodes": 800, "refine_radius_mm": 10.0, "refine_edge_mm": 6.0}
    feats = make_mesh(tmp / "imp-lab.ply", mesh_cfg, 0, tmp / "imp-lab.vtu", tmp / "imp-lab.features.json",
                      tmp / "imp-lab.regions.png", exertion=cfg["sweep"]["exertion"])
    params = Plan(cfg).sweep_params("II")
    params["geometries"] = ["imp-lab"]
    params["spec"] = {**params["spec"], "n_cases": 12}
    report = make_sweep(params, [str(tmp / "imp-lab.vtu")], tmp / "cases.parquet", tmp / "sweep.json")
    cases = dio.read_table(tmp / "cases.parquet").to_pylist()
    return {"given_ras": given_ras, "posterior": posterior, "feats": feats, "report": report, "cases": cases,
            "tmp": tmp, "cfg": cfg}


def test_case_table_uses_exactly_the_given_points_snapped(scene):
    given = scene["given_ras"]
    feats = scene["feats"]
    assert feats["exertion_given"] is True
    np.testing.assert_allclose(feats["exertion_snap_mm"], 1.0, atol=0.05)  # 1 mm off a smooth surface
    snapped = np.asarray(feats["exertion_candidates_mm"])
    assert snapped.shape == (3, 3)  # n_points = the number given, not sweep.exertion.n_points (8)
    ex = np.asarray(scene["report"]["exertion_points_mm"]["imp-lab"])
    moved = scene["report"]["exertion_given"]["imp-lab"]["moved_to_mesh_mm"]
    np.testing.assert_allclose(ex, snapped, atol=0.5)  # mesh refined there: the facets follow the input surface
    assert max(moved) < 0.5
    np.testing.assert_allclose(np.linalg.norm(ex - given, axis=1), 1.0, atol=0.5)
    used = {r["exertion_id"] for r in scene["cases"]}
    assert used <= {0, 1, 2} and len(used) >= 2
    for r in scene["cases"]:
        np.testing.assert_allclose(r["exertion_point_mm"], ex[r["exertion_id"]], atol=1e-9)


def test_supports_are_where_they_were_put(scene):
    from liverforce.mesh.io import read_mesh

    mesh = read_mesh(scene["tmp"] / "imp-lab.vtu")
    cent = mesh.points[mesh.facets].mean(axis=1)
    fixed = mesh.facet_region == REGION_CODES["ivc"]
    assert fixed.any() and (np.linalg.norm(cent[fixed] - scene["posterior"], axis=1) <= 20.0 + 6.0).all()
    assert set(np.unique(mesh.facet_region)) == {0, REGION_CODES["ivc"], REGION_CODES["visceral"]}  # replace
    sup = {s["name"]: s for s in scene["feats"]["supports"]}
    assert sup["cava"]["region_code"] == REGION_CODES["ivc"] and sup["floor"]["region_code"] == REGION_CODES["visceral"]
    from liverforce.fem.boundary import region_areas

    area = region_areas(mesh.points, mesh.facets, mesh.facet_region)[REGION_CODES["visceral"]]
    assert scene["feats"]["support_boundary"]["visceral_kn"] == pytest.approx(40.0 / area)


def test_point_far_from_the_surface_is_refused():
    cube = cube_phantom(50.0)
    with pytest.raises(SupportError, match="20 mm from the surface"):
        build_liver_mesh(cube, target_nodes=300, exertion_points=[[0.0, 0.0, 45.0]])


def test_point_on_a_fixed_support_is_refused():
    cube = cube_phantom(50.0)
    sup = parse_supports({"list": [{"kind": "fixed", "box": {"min_mm": [-30, -30, 24], "max_mm": [30, 30, 26]}}]})
    with pytest.raises(SupportError, match="lies on a fixed support"):
        build_liver_mesh(cube, target_nodes=300, supports=sup, exertion_points=[[0.0, 0.0, 25.5]])


def test_a_tool_position_given_twice_is_refused_naming_both():
    """Two ids for one position: a held-out-points fold would test one while training on the other."""
    cube = cube_phantom(50.0)
    with pytest.raises(SupportError, match=r"exertion point 2 \(\[0\.3, 0\.0, 25\.0\];.*\) is the tool position of "
                                           r"exertion point 0 \(\[0\.0, 0\.0, 25\.0\];.*\) again \(0\.3 mm apart.*"
                                           r"List each tool position once"):
        build_liver_mesh(cube, target_nodes=300, exertion_points=[[0.0, 0.0, 25.0], [10.0, 0.0, 25.0],
                                                                  [0.3, 0.0, 25.0]],
                         exertion_labels=["[0.0, 0.0, 25.0]", "[10.0, 0.0, 25.0]", "[0.3, 0.0, 25.0]"])
    mesh = build_liver_mesh(cube, target_nodes=300, exertion_points=[[0.0, 0.0, 25.0], [1.5, 0.0, 25.0]])
    assert len(mesh.meta["exertion_candidates_mm"]) == 2  # 1.5 mm apart: two positions


@pytest.mark.parametrize("spec, text", [
    ({"vertex_ids": [2, 4690.7]}, r"exertion_points.vertex_ids: must be .*integers >= 0\) \(entry 1 is 4690\.7\)"),
    ({"vertex_ids": [True]}, r"exertion_points.vertex_ids: must be a non-empty list of vertex ids"),
    ({"coordinates_mm": [[float("nan"), 1.0, 2.0]]}, r"exertion_points.coordinates_mm: .*not a finite number"),
])
def test_given_points_that_are_no_vertex_ids_or_coordinates_are_refused_at_the_mesh_stage(spec, text):
    """Not cut to vertex 4690, not a NaN handed to the nearest-point search (a traceback from scipy)."""
    from liverforce.mesh.supports import exertion_points_mesh

    with pytest.raises(SupportError, match=text):
        exertion_points_mesh(spec, file_vertices=lambda: np.zeros((5000, 3)))


def test_supports_leaving_no_visible_surface_are_named_when_the_tool_positions_are_sampled():
    cube = cube_phantom(50.0)
    sup = parse_supports({"list": [{"name": "tray", "kind": "fixed",
                                    "box": {"min_mm": [-30, -30, -30], "max_mm": [30, 30, 30]}}]})
    sampling = {"n_points": 2, "min_spacing_mm": 5.0, "seed": 0}
    with pytest.raises(SupportError, match=r"the lab's supports 'tray' \(fixed, box, \d+ facets\) leave no free "
                                           r"surface facing the camera.*give the tool's positions"):
        build_liver_mesh(cube, target_nodes=300, supports=sup, exertion_sampling=sampling)


def _hydra(v) -> str:
    """A value in Hydra's override grammar (unquoted keys and words)."""
    if isinstance(v, dict):
        return "{" + ",".join(f"{k}:{_hydra(x)}" for k, x in v.items()) + "}"
    if isinstance(v, list):
        return "[" + ",".join(_hydra(x) for x in v) + "]"
    return str(v)


@pytest.mark.parametrize("imp, key", [
    ({"supports": {"mode": "merge", "list": []}}, "geometry.imported[0].supports.mode"),
    ({"supports": {"list": [{"kind": "fixed", "sphere": {"center_mm": [0, 0], "radius_mm": 5}}]}},
     "geometry.imported[0].supports.list[0].sphere"),
    ({"exertion_points": {"coordinates_mm": [[0, 0]]}}, "geometry.imported[0].exertion_points.coordinates_mm"),
    ({"exertion_points": {"points": [[0, 0, 0]]}}, "geometry.imported[0].exertion_points"),
    # a lab's typing mistakes: refused naming the key, not a traceback from float() or dict(), nor accepted
    ({"supports": [{"name": "cava", "kind": "fixed", "sphere": {"center_mm": [0, 0, 0], "radius_mm": 5}}]},
     "geometry.imported[0].supports"),  # the list without mode and list:
    ({"supports": {"list": ["cava"]}}, "geometry.imported[0].supports.list[0]"),
    ({"supports": {"list": {"name": "cava"}}}, "geometry.imported[0].supports.list"),
    ({"supports": {"list": [{"kind": "fixed", "sphere": {"center_mm": [0, 0, 0], "radius_mm": "big"}}]}},
     "geometry.imported[0].supports.list[0].sphere.radius_mm"),
    ({"supports": {"list": [{"kind": "fixed", "box": {"min_mm": [0, "nan", 0], "max_mm": [1, 1, 1]}}]}},
     "geometry.imported[0].supports.list[0].box.min_mm"),
    ({"supports": {"list": [{"kind": "foundation", "stiffness": {"total_n_per_mm": "high"},
                             "sphere": {"center_mm": [0, 0, 0], "radius_mm": 5}}]}},
     "geometry.imported[0].supports.list[0].stiffness"),
    ({"supports": {"list": [{"kind": "foundation", "stiffness": {"total_n_per_mm": "inf"},
                             "sphere": {"center_mm": [0, 0, 0], "radius_mm": 5}}]}},
     "geometry.imported[0].supports.list[0].stiffness"),
    ({"supports": {"list": [{"kind": "fixed", "file": {"path": "cava.csv", "units": "inches"}}]}},
     "geometry.imported[0].supports.list[0].file.units"),
    ({"supports": {"list": [{"kind": "fixed", "file": {"path": "cava.csv", "units": "auto"}}]}},
     "geometry.imported[0].supports.list[0].file.units"),
    ({"supports": {"mode": "replace", "list": []}}, "geometry.imported[0].supports.list"),
    ({"supports": {"list": [{"name": "x", "kind": "fixed", "sphere": {"center_mm": [0, 0, 0], "radius_mm": 5}},
                            {"name": "x", "kind": "sliding", "sphere": {"center_mm": [9, 0, 0], "radius_mm": 5}}]}},
     "geometry.imported[0].supports.list[1].name"),
    ({"exertion_points": [[0, 0, 0]]}, "geometry.imported[0].exertion_points"),
    ({"exertion_points": {"vertex_ids": [4690.7]}}, "geometry.imported[0].exertion_points.vertex_ids"),
    ({"exertion_points": {"vertex_ids": ["a"]}}, "geometry.imported[0].exertion_points.vertex_ids"),
    ({"exertion_points": {"vertex_ids": ["true"]}}, "geometry.imported[0].exertion_points.vertex_ids"),
    ({"exertion_points": {"coordinates_mm": [["nan", 1, 2]]}}, "geometry.imported[0].exertion_points.coordinates_mm"),
    ({"exertion_points": {"coordinates_mm": [["a", "b", "c"]]}}, "geometry.imported[0].exertion_points.coordinates_mm"),
    ({"exertion_points": {"path": "pts.csv", "units": "auto"}}, "geometry.imported[0].exertion_points.units"),
    # units beside coordinates (which are mm) or vertex ids: refused, not ignored
    ({"exertion_points": {"coordinates_mm": [[0, 0, 0]], "units": "m"}}, "geometry.imported[0].exertion_points.units"),
    ({"exertion_points": {"vertex_ids": [4], "units": "m"}}, "geometry.imported[0].exertion_points.units"),
])
def test_config_names_the_bad_key(imp, key):
    base = {"name": "x", "path": "x.stl"}
    ov = [f"geometry.imported=[{_hydra({**base, **imp})}]"]
    with pytest.raises(ConfigError, match=key.replace("[", r"\[").replace("]", r"\]").replace(".", r"\.")):
        compose(ov)


def test_vertex_ids_refer_to_the_file_as_read(tmp_path):
    """Vertex ids of a PLY in cm and LPS resolve to the same liver points in RAS mm."""
    import trimesh

    from liverforce.pipeline.geometry import make_geometry
    from liverforce.pipeline.mesh import _user_scene
    from liverforce.mesh.supports import select_facets

    liver = procedural_liver(0)
    trimesh.Trimesh(liver.vertices * LPS / 10.0, liver.faces[:, ::-1], process=False).export(tmp_path / "l.ply")
    ids = [5, 200, 4000]
    spec = {"kind": "imported", "name": "cm", "path": str(tmp_path / "l.ply"), "units": "cm", "label": None,
            "frame": "LPS", "exertion_points": {"vertex_ids": ids}}
    meta = make_geometry(spec, tmp_path / "imp-cm.ply", tmp_path / "imp-cm.json")
    scene = _user_scene(spec, meta)
    np.testing.assert_allclose(scene["exertion_points"], liver.vertices[ids], rtol=0, atol=1e-4)  # float32 PLY
    f = liver.faces[0]
    np.savetxt(tmp_path / "ids.txt", f, fmt="%d")
    _, (s,) = parse_supports({"list": [{"kind": "fixed", "file": {"path": str(tmp_path / "ids.txt")}}]})
    mask, info = select_facets(liver.vertices, liver.faces, s, scene["frame"], scene["file_vertices"])
    # the ids mark facet 0's patch: facet 0, and at most a sliver touching its corners (a patch is selected by the
    # facets whose centres lie on it, however the surface was refined; mesh.supports.points_patch)
    sel = np.flatnonzero(mask)
    assert 0 in sel and all(set(liver.faces[k]) & set(f.tolist()) for k in sel), sel
    assert info["snap_mm"]["max"] < 1e-4
