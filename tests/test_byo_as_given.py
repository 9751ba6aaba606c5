"""A liver tet mesh imported as given, through the geometry, mesh, sweep and simulate stages.

A procedural liver is meshed the normal way; the same mesh is then written as a
real Gmsh MSH 4.1 file (gmsh API) in metres and LPS, with its nodes shuffled,
some tets inverted, and its vena-cava and lower-face facets as physical groups.
Imported as given with supports selected by those groups and an exertion point
given as a vertex id of the file, it must keep the file's node numbering, carry
the same regions, and give the same solution as the original mesh (P2 by the
product's simulate loop; P1 against FElupe).
"""

from __future__ import annotations

import numpy as np
import pytest
from test_byo_volume_files import write_gmsh

from liverforce.config import compose
from liverforce.mesh.types import REGION_CODES

LPS = np.array([-1.0, -1.0, 1.0])


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from liverforce.geometry.procedural import procedural_liver
    from liverforce.mesh.build import build_liver_mesh
    from liverforce.pipeline.geometry import make_geometry
    from liverforce.pipeline.mesh import make_mesh

    tmp = tmp_path_factory.mktemp("asgiven")
    orig = build_liver_mesh(procedural_liver(0), target_nodes=400, seed=0)
    perm = np.random.default_rng(0).permutation(len(orig.points))  # file node j = original node perm[j]
    inv = np.argsort(perm)
    tets = inv[orig.tets]
    tets[::3] = tets[::3][:, [0, 1, 3, 2]]  # a third of the tets inverted in the file
    write_gmsh(tmp / "liver.msh", orig.points[perm] * LPS / 1000.0, tets,
               {"cava": (7, inv[orig.facets[orig.facet_region == 1]]),
                "floor": (8, inv[orig.facets[orig.facet_region == 3]])}, 4.1)
    vis = orig.facets[np.flatnonzero(orig.facet_visible)[len(np.flatnonzero(orig.facet_visible)) // 2]]
    vertex_id = int(inv[vis[0]])  # a visible vertex, as the file numbers it
    spec = {"kind": "imported", "name": "lab", "path": str(tmp / "liver.msh"), "units": "m", "label": None,
            "frame": "LPS", "mesh": "auto",
            "supports": {"mode": "replace", "list": [
                {"name": "cava", "kind": "fixed", "group": "cava"},
                {"name": "floor", "kind": "foundation", "region": "visceral", "group": 8,
                 "stiffness": {"total_n_per_mm": 40.0}}]},
            "exertion_points": {"vertex_ids": [vertex_id]}}
    geo = make_geometry(spec, tmp / "imp-lab.ply", tmp / "imp-lab.json")
    cfg = compose(["experiment=smoke", "material=neo_hookean_from_e"])
    feats = make_mesh(tmp / "imp-lab.ply", cfg["mesh"], 0, tmp / "imp-lab.vtu", tmp / "imp-lab.features.json",
                      tmp / "imp-lab.regions.png", exertion=cfg["sweep"]["exertion"])
    return {"orig": orig, "perm": perm, "inv": inv, "spec": spec, "geo": geo, "feats": feats, "cfg": cfg,
            "tmp": tmp, "vertex_id": vertex_id}


def test_the_mesh_keeps_the_files_nodes_in_the_files_order(scene):
    from liverforce.mesh.io import read_mesh

    mesh = read_mesh(scene["tmp"] / "imp-lab.vtu")
    orig, perm = scene["orig"], scene["perm"]
    np.testing.assert_allclose(mesh.points, orig.points[perm], atol=1e-9)  # m -> mm, LPS -> RAS, order kept
    assert len(mesh.tets) == len(orig.tets)
    assert scene["geo"]["mesh_mode"] == "as_given" and scene["feats"]["mesh_mode"] == "as_given"
    assert scene["feats"]["node_numbering"] == "file"
    assert scene["feats"]["given_mesh"]["reoriented_in_file"] == len(orig.tets[::3])
    mesh.validate()  # positive tets, outward facets


def test_supports_by_group_are_exactly_the_tagged_facets(scene):
    from liverforce.mesh.io import read_mesh

    mesh = read_mesh(scene["tmp"] / "imp-lab.vtu")
    orig, perm = scene["orig"], scene["perm"]
    key = lambda f: tuple(sorted(f))  # noqa: E731
    want = {key(perm[f]): r for f, r in zip(mesh.facets, mesh.facet_region)}  # in original node ids
    expected = {key(f): (r if r in (1, 3) else 0) for f, r in zip(orig.facets, orig.facet_region)}
    assert want == expected
    sup = {s["name"]: s for s in scene["feats"]["supports"]}
    assert sup["cava"]["n_facets"] == int((orig.facet_region == 1).sum())
    assert sup["floor"]["n_facets"] == int((orig.facet_region == 3).sum())


def test_an_exertion_point_given_by_vertex_id_is_that_node(scene):
    from liverforce.mesh.io import read_mesh
    from liverforce.pipeline.sweep import exertion_set

    mesh = read_mesh(scene["tmp"] / "imp-lab.vtu")
    cand = np.asarray(scene["feats"]["exertion_candidates_mm"])
    np.testing.assert_array_equal(cand, mesh.points[[scene["vertex_id"]]])
    ex = exertion_set(mesh, 8, 15.0, 0, 5.0, candidates=cand, given=True)
    np.testing.assert_allclose(ex.points, cand, atol=1e-9)


def _case(scene, force):
    cfg = scene["cfg"]
    mat = cfg["material"]
    from liverforce.fem.materials import make_material

    return {"case_id": "c0", "scenario": "I", "geometry_id": "imp-lab", "shard_index": 0, "seed": 0,
            "material_model": mat["model"], "material_param_names": ["C10"],
            "material_params_mpa": [mat["params_mpa"]["C10"]],
            "bulk_modulus_mpa": make_material(mat["model"], mat["params_mpa"], nu=mat["nu"]).bulk,
            "exertion_id": 0, "exertion_point_mm": np.asarray(scene["feats"]["exertion_candidates_mm"][0]),
            "force_n": np.asarray(force, float), "force_magnitude_n": float(np.linalg.norm(force))}


def test_simulate_on_the_mesh_as_given_matches_the_original_mesh(scene):
    """The product's simulate loop (P2 mean dilatation, the user's foundation stiffness) on the imported mesh
    against a LiverModel on the original mesh with the same regions: same displacements, node for node."""
    from liverforce.fem.materials import make_material
    from liverforce.fem.problem import LiverModel, ToolLoad
    from liverforce.mesh.io import read_mesh
    from liverforce.pipeline.simulate import boundary_params, simulate_cases, solver_options

    cfg, orig, perm = scene["cfg"], scene["orig"], scene["perm"]
    mesh = read_mesh(scene["tmp"] / "imp-lab.vtu")
    case = _case(scene, [0.0, -1.0, -1.5])
    sim = {**cfg["simulate"], "tol": 1e-10}
    dataset = {**cfg["dataset"], "store_full_surface": True}
    rows = simulate_cases([case], {"imp-lab": mesh}, sim, cfg["boundary"], dataset,
                          supports={"imp-lab": scene["feats"]["support_boundary"]})
    assert rows[0]["converged"], rows[0]["reason"]

    region = np.where(np.isin(orig.facet_region, [1, 3]), orig.facet_region, 0)
    ref_mesh = type(orig)(orig.points, orig.tets, orig.facets, region, orig.facet_visible)
    bp = boundary_params(ref_mesh, cfg["boundary"]).with_supports(scene["feats"]["support_boundary"])
    assert bp.visceral_kn == pytest.approx(scene["feats"]["support_boundary"]["visceral_kn"])
    mat = make_material("neo_hookean", cfg["material"]["params_mpa"], nu=cfg["material"]["nu"])
    ref = LiverModel(orig.points, orig.tets, orig.facets, region, mat, bp, solver_options(sim)).solve(
        ToolLoad(case["exertion_point_mm"], case["force_n"], sim["tool_radius_mm"]))
    assert ref.converged
    u_ref = ref.u_nodes[perm]  # in the file's node order
    assert np.abs(u_ref).max() > 1.0  # a real indentation, mm
    from liverforce.dataset.roi import surface_graph

    surf = surface_graph(mesh.points, mesh.facets)
    u_surf = np.asarray(rows[0]["surface_displacement_mm"], float)  # float32 in the shard
    np.testing.assert_allclose(u_surf, u_ref[surf.node_ids], atol=1e-5 * np.abs(u_ref).max())
    assert rows[0]["max_displacement_mm"] == pytest.approx(np.linalg.norm(u_ref, axis=1).max(), rel=1e-7)


def test_p1_on_the_imported_mesh_matches_felupe(scene):
    """Same mesh (as imported), fixed support (the 'cava' group), tool load as nodal forces: FElupe 11.3."""
    fem = pytest.importorskip("felupe")
    from liverforce.fem.materials import make_material
    from liverforce.fem.newton import SolverOptions
    from liverforce.fem.problem import BoundaryParams, LiverModel, ToolLoad
    from liverforce.mesh.io import read_mesh

    mesh = read_mesh(scene["tmp"] / "imp-lab.vtu")
    C10, K = 0.0025, 0.25
    fixed_only = np.where(mesh.facet_region == REGION_CODES["ivc"], 1, 0)
    none = BoundaryParams(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    model = LiverModel(mesh.points, mesh.tets, mesh.facets, fixed_only, make_material("neo_hookean", {"C10": C10},
                       bulk_mpa=K), none, SolverOptions(formulation="p1", tol=1e-12))
    load = ToolLoad(scene["feats"]["exertion_candidates_mm"][0], [0.0, -0.2, -0.3], 5.0)
    res = model.solve(load)
    assert res.converged
    F = model.nodal_loads(load).reshape(-1, 3)
    loaded = np.flatnonzero(np.abs(F).sum(axis=1) > 0)
    fixed = np.zeros(len(mesh.points), bool)
    fixed[np.unique(mesh.facets[fixed_only == 1])] = True

    fm = fem.Mesh(mesh.points, mesh.tets, cell_type="tetra")
    field = fem.FieldContainer([fem.Field(fem.RegionTetra(fm), dim=3)])
    solid = fem.SolidBody(fem.NeoHooke(mu=2 * C10, bulk=K), field)
    pl = fem.PointLoad(field, loaded, F[loaded])
    step = fem.Step(items=[solid, pl], ramp={pl: fem.math.linsteps([0, 1], num=4)[:, None, None] * F[loaded]},
                    boundaries={"fixed": fem.dof.Boundary(field[0], mask=fixed)})
    fem.Job(steps=[step]).evaluate(tol=1e-12, verbose=0)
    u_fe = field[0].values
    assert np.abs(u_fe).max() > 1.0
    assert np.abs(res.u_nodes - u_fe).max() <= 1e-6 * np.abs(u_fe).max()


def test_remesh_instead_carries_supports_and_exertion_points_over(scene):
    """mesh: remesh on the same file: a new (gmsh) mesh, the groups transferred, the vertex-id point kept."""
    from liverforce.fem.boundary import region_areas
    from liverforce.mesh.io import read_mesh
    from liverforce.pipeline.geometry import make_geometry
    from liverforce.pipeline.mesh import make_mesh

    tmp, orig = scene["tmp"], scene["orig"]
    spec = {**scene["spec"], "name": "lab2", "mesh": "remesh"}
    geo = make_geometry(spec, tmp / "imp-lab2.ply", tmp / "imp-lab2.json")
    assert geo["mesh_mode"] == "remesh"
    mesh_cfg = {**scene["cfg"]["mesh"], "target_nodes": 600}
    feats = make_mesh(tmp / "imp-lab2.ply", mesh_cfg, 0, tmp / "imp-lab2.vtu", tmp / "imp-lab2.features.json",
                      tmp / "imp-lab2.regions.png", exertion=scene["cfg"]["sweep"]["exertion"])
    assert feats["mesh_mode"] == "remesh" and feats["node_numbering"] == "mesher"
    mesh = read_mesh(tmp / "imp-lab2.vtu")
    assert len(mesh.points) != len(orig.points)
    a_new = region_areas(mesh.points, mesh.facets, mesh.facet_region)
    a_old = region_areas(orig.points, orig.facets, orig.facet_region)
    for code in (REGION_CODES["ivc"], REGION_CODES["visceral"]):  # the coarse file's surface is smoothed: ~
        assert a_new[code] == pytest.approx(a_old[code], rel=0.2)
    assert set(np.unique(mesh.facet_region)) == {0, REGION_CODES["ivc"], REGION_CODES["visceral"]}
    given = orig.points[scene["perm"][scene["vertex_id"]]]
    assert np.linalg.norm(np.asarray(feats["exertion_candidates_mm"][0]) - given) < 5.0


@pytest.mark.parametrize("name, units", [("liver.msh", 40), ("liver2.msh", 120)])
def test_real_sofa_tet_livers_are_taken_as_given_and_solve(shared_livers, tmp_path, name, units):
    """The public SOFA liver tet meshes (Gmsh v1) through the geometry and mesh stages as given, then one P2 case."""
    from liverforce.fem.materials import make_material
    from liverforce.fem.problem import LiverModel, ToolLoad
    from liverforce.geometry.readers import read_gmsh_v1
    from liverforce.mesh.io import read_mesh
    from liverforce.pipeline.geometry import make_geometry
    from liverforce.pipeline.mesh import make_mesh
    from liverforce.pipeline.simulate import boundary_params, solver_options

    spec = {"kind": "imported", "name": "sofa", "path": str(shared_livers / name), "units": units, "label": None,
            "frame": "RAS"}
    geo = make_geometry(spec, tmp_path / "imp-sofa.ply", tmp_path / "imp-sofa.json")
    assert geo["mesh_mode"] == "as_given"
    cfg = compose(["experiment=smoke"])
    feats = make_mesh(tmp_path / "imp-sofa.ply", cfg["mesh"], 0, tmp_path / "imp-sofa.vtu",
                      tmp_path / "imp-sofa.features.json", tmp_path / "imp-sofa.png", exertion=cfg["sweep"]["exertion"])
    mesh = read_mesh(tmp_path / "imp-sofa.vtu")
    file_points = read_gmsh_v1(shared_livers / name).points  # in the file's $NOD order
    np.testing.assert_allclose(mesh.points, file_points * units, atol=1e-9)  # numbering and coordinates kept
    assert feats["node_numbering"] == "file" and len(feats["exertion_candidates_mm"]) == 3
    mat = make_material("neo_hookean", {"C10": 0.0025}, nu=0.49)
    model = LiverModel.from_mesh(mesh, mat, boundary_params(mesh, cfg["boundary"]), solver_options(cfg["simulate"]))
    point = np.asarray(feats["exertion_candidates_mm"][0])
    normal = point - np.asarray(feats["centroid_mm"])
    res = model.solve(ToolLoad(point, -1.0 * normal / np.linalg.norm(normal), 5.0))
    assert res.converged, res.reason
    assert 0.1 < np.linalg.norm(res.u_nodes, axis=1).max() < 50.0  # mm under 1 N
    assert np.linalg.norm(res.reactions["imbalance"]) < 1e-6


def test_the_stiffness_probe_column_and_serving_agree_on_the_users_liver(scene):
    """The shard's probe compliance on the imported liver (the user's supports from its features JSON) is the
    linear compliance of that liver at the reference material, symmetric and positive definite; serving
    recomputes it from the mesh file with the model's recorded settings, to round-off."""
    from liverforce.dataset.roi import local_frame, surface_graph
    from liverforce.fem.materials import make_material
    from liverforce.fem.probe import ComplianceProbe
    from liverforce.fem.problem import LiverModel
    from liverforce.mesh.io import read_mesh
    from liverforce.pipeline.simulate import boundary_params, probe_reference, simulate_cases, solver_options
    from liverforce.serve.preop import Preop
    from liverforce.serve.probe import with_probe

    cfg = scene["cfg"]
    mesh = read_mesh(scene["tmp"] / "imp-lab.vtu")
    case = _case(scene, [0.0, -0.5, -1.0])
    sim = dict(cfg["simulate"])
    ref = probe_reference(cfg["material"])
    assert ref["model"] == "neo_hookean" and ref["params_mpa"] == cfg["material"]["params_mpa"]
    supports = scene["feats"]["support_boundary"]
    rows = simulate_cases([case], {"imp-lab": mesh}, sim, cfg["boundary"], cfg["dataset"],
                          supports={"imp-lab": supports}, probe=ref)
    C = np.asarray(rows[0]["probe_compliance_mm_per_n"], float).reshape(3, 3)
    np.testing.assert_allclose(C, C.T, atol=1e-12)
    assert np.linalg.eigvalsh(C)[0] > 0
    # independently: the rest tangent of this liver with the user's supports, in the row's local frame
    frame = np.stack([rows[0]["frame_t1"], rows[0]["frame_t2"], rows[0]["frame_normal"]])
    p = np.asarray(case["exertion_point_mm"], float)
    np.testing.assert_allclose(frame, local_frame(surface_graph(mesh.points, mesh.facets), p, sim["tool_radius_mm"]))
    mat = make_material(ref["model"], ref["params_mpa"], bulk_mpa=ref["bulk_mpa"])
    fe = LiverModel(mesh.points, mesh.tets, mesh.facets, mesh.facet_region, mat,
                    boundary_params(mesh, cfg["boundary"]).with_supports(supports), solver_options(sim))
    C_direct = ComplianceProbe(fe).compliance(p, frame, sim["tool_radius_mm"])
    np.testing.assert_allclose(C, C_direct, rtol=1e-9, atol=1e-12 * np.abs(C).max())
    # the config's own supports (not the user's) give another compliance (here by ~0.2 %: at this point the
    # local indentation dominates), so the match above is the user's supports, not a coincidence
    fe_cfg = LiverModel(mesh.points, mesh.tets, mesh.facets, mesh.facet_region, mat,
                        boundary_params(mesh, cfg["boundary"]), solver_options(sim))
    C_cfg = ComplianceProbe(fe_cfg).compliance(p, frame, sim["tool_radius_mm"])
    assert np.abs(C_cfg - C).max() > 1e-4 * np.abs(C).max()
    # serving: from the mesh file (supports read from its features JSON) with the bundle's settings
    meta = {"probe": {"reference": ref, "boundary": cfg["boundary"], "simulate": sim,
                      "tool_radius_mm": sim["tool_radius_mm"]}}
    preop = Preop(exertion_point_mm=p, frame=frame, roi_undeformed_mm=np.asarray(rows[0]["roi_undeformed_mm"]))
    served = with_probe(preop, scene["tmp"] / "imp-lab.vtu", meta).probe_compliance_mm_per_n
    np.testing.assert_allclose(served, C, rtol=1e-9, atol=1e-12 * np.abs(C).max())


def test_serving_takes_the_labs_points_in_the_files_frame_through_the_livers_record(scene, tmp_path):
    """The lab's own file (LPS, metres) as the pre-operative surface, an exertion point in that frame mid-edge on
    this coarse mesh (farther than 5 mm from every vertex), and the mesh stage's copy of the mesh (RAS mm) in a
    results folder beside its geometry record: with the record as the input frame, the context is the RAS one and
    the probe runs; without a stated frame it is refused, naming the record (LPS points near a roughly symmetric
    liver could pass the mesh's checks and give another force)."""
    import json
    import shutil
    from types import SimpleNamespace

    from liverforce.dataset.roi import local_frame, surface_graph
    from liverforce.mesh.io import read_mesh
    from liverforce.pipeline.simulate import probe_reference
    from liverforce.serve.errors import PredictionInputError
    from liverforce.serve.files import read_context
    from liverforce.serve.preop import Preop
    from liverforce.serve.probe import with_probe

    root = tmp_path / "results" / "lab"
    (root / "mesh").mkdir(parents=True)
    (root / "geometry").mkdir()
    for name in ("imp-lab.vtu", "imp-lab.features.json"):
        shutil.copy(scene["tmp"] / name, root / "mesh" / name)
    shutil.copy(scene["tmp"] / "imp-lab.json", root / "geometry" / "imp-lab.json")
    mesh = read_mesh(root / "mesh" / "imp-lab.vtu")
    vis = mesh.facets[np.asarray(mesh.facet_visible, bool)]
    edges = np.concatenate([vis[:, [0, 1]], vis[:, [1, 2]], vis[:, [2, 0]]])
    lengths = np.linalg.norm(mesh.points[edges[:, 0]] - mesh.points[edges[:, 1]], axis=1)
    a, b = edges[np.argmax(lengths)]
    p = 0.5 * (mesh.points[a] + mesh.points[b])  # on the surface, mid-edge
    assert np.linalg.norm(mesh.points - p, axis=1).min() > 5.0  # the old vertex-distance check refused it
    cfg = scene["cfg"]
    sim = dict(cfg["simulate"])
    meta = {"probe": {"reference": probe_reference(cfg["material"]), "boundary": cfg["boundary"], "simulate": sim,
                      "tool_radius_mm": sim["tool_radius_mm"]}}
    frame = local_frame(surface_graph(mesh.points, mesh.facets), p, sim["tool_radius_mm"])
    C = with_probe(Preop(exertion_point_mm=p, frame=frame, roi_undeformed_mm=mesh.points[:10]), root / "mesh" /
                   "imp-lab.vtu", meta).probe_compliance_mm_per_n
    assert np.linalg.eigvalsh(C)[0] > 0
    pred = SimpleNamespace(roi_fraction=0.18, frame_radius_mm=sim["tool_radius_mm"],
                           check_preop=lambda preop, frame=None: None,
                           model=SimpleNamespace(uses_state=True, meta=meta))
    doc = {"surface": str(scene["tmp"] / "liver.msh"), "exertion_point_mm": (p * LPS / 1000.0).tolist(),
           "mesh": str(root / "mesh" / "imp-lab.vtu"), "material_params_mpa": [0.0025]}
    with pytest.raises(PredictionInputError, match=r"imported in another frame .*frame LPS.*--frame .*imp-lab\.json"):
        read_context({**doc, "units": "m"}, pred)
    preop, fr = read_context({**doc, "input_frame": str(root / "geometry" / "imp-lab.json")}, pred)
    assert (fr.label, fr.units) == ("LPS", "m")
    np.testing.assert_allclose(preop.exertion_point_mm, p, atol=1e-9)
    np.testing.assert_allclose(preop.frame, frame, atol=1e-9)  # the local frame of the RAS liver (not turned)
    np.testing.assert_allclose(preop.probe_compliance_mm_per_n, C, rtol=1e-9)
    # inputs already in the mesh's RAS mm pass once said so, and give the same context
    ras = {**doc, "surface": str(root / "mesh" / "imp-lab.vtu"), "exertion_point_mm": p.tolist()}
    with pytest.raises(PredictionInputError, match="--frame RAS for inputs already in the mesh's RAS mm"):
        read_context(ras, pred)
    preop_ras, _ = read_context({**ras, "input_frame": "RAS"}, pred)
    np.testing.assert_allclose(preop_ras.probe_compliance_mm_per_n, C, rtol=1e-9)
    # a liver segmented from a label volume: its record's frame is the header's, so the inputs' must be said
    record = json.loads((root / "geometry" / "imp-lab.json").read_text())
    (root / "geometry" / "imp-lab.json").write_text(json.dumps({**record, "label": 1, "conversion": {
        **record["conversion"], "frame": "RAS", "frame_matrix": np.eye(4).tolist()}}))
    with pytest.raises(PredictionInputError, match="label volume.*--frame LPS"):
        read_context(ras, pred)
    with pytest.raises(PredictionInputError, match="label volume.*--frame LPS"):
        read_context({**ras, "input_frame": str(root / "geometry" / "imp-lab.json")}, pred)
    assert read_context({**ras, "input_frame": "RAS"}, pred)[1].identity
