"""The physics study (issue 18): one liver's cases simulated again with one modelling choice changed at a time,
scored by the trained models (liverforce.pipeline.physics), on a small ellipsoid liver."""
from __future__ import annotations

import json

import numpy as np
import pytest
from fake_rows import top_face_cases

from liverforce.config import ConfigError, compose
from liverforce.pipeline.physics import BASELINE, physics_study, physics_variants

SPEC = {"enabled": True, "liver": 0, "n_cases": 6, "foundation_scale": [0.25, 4.0], "tangential_ratio": [0.1],
        "rib_contact": ["unilateral", "off"], "gravity": [[0.0, -1.0, 0.0]], "tool": "none", "tool_cases": 2, "tool_max_force_n": 5.0}


def test_each_variant_changes_one_choice_and_the_baseline_comes_first():
    cfg = compose([])
    b, sim = cfg["boundary"], cfg["simulate"]
    vs = physics_variants(b, sim, {**SPEC, "tool": "sphere"})
    assert vs[0]["name"] == BASELINE and vs[0]["boundary"] == b and vs[0]["simulate"] == sim
    changed = {v["name"]: ({k for k in b if v["boundary"][k] != b[k]}, {k for k in sim if v["simulate"].get(k) != sim[k]}
                           | (set(v["simulate"]) - set(sim))) for v in vs[1:]}
    assert changed == {
        "foundation x0.25": ({"ligament_total_n_per_mm", "visceral_total_n_per_mm"}, set()),
        "foundation x4": ({"ligament_total_n_per_mm", "visceral_total_n_per_mm"}, set()),
        "kt/kn 0.1": ({"tangential_ratio"}, set()),
        "rib unilateral": ({"rib_contact"}, set()),
        "rib off": ({"rib_normal_n_per_mm3"}, set()),
        "gravity supine": ({"gravity"}, set()),
        "tool: rigid sphere": (set(), {"tool_model"}),
    }
    four = next(v for v in vs if v["name"] == "foundation x4")["boundary"]
    assert four["visceral_total_n_per_mm"] == pytest.approx(4 * b["visceral_total_n_per_mm"])
    grav = next(v for v in vs if v["name"] == "gravity supine")["boundary"]["gravity"]
    assert grav["enabled"] and grav["direction"] == [0.0, -1.0, 0.0]
    assert next(v for v in vs if v["name"] == "rib off")["boundary"]["rib_normal_n_per_mm3"] == 0.0


@pytest.mark.parametrize("override, key", [
    ("validate.physics.n_cases=999", "validate.physics.n_cases"),
    ("validate.physics.liver=8", "validate.physics.liver"),
    ("validate.physics.rib_contact=[glued]", "validate.physics.rib_contact"),
    ("validate.physics.tool=cylinder", "validate.physics.tool"),
    ("validate.physics.gravity=[[0,0,0]]", "validate.physics.gravity"),
    ("validate.physics.tool_cases=31", "validate.physics.tool_cases"),
    ("validate.physics.tool_max_force_n=0", "validate.physics.tool_max_force_n"),
])
def test_a_wrong_physics_setting_names_its_key(override, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        compose([override])


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """An ellipsoid liver, 40 cases on it (the first 6 the study's), and a small PCA model trained on the
    other 34 cases' baseline simulation."""
    from liverforce.dataset import io as dio
    from liverforce.fem.testing import ellipsoid_liver
    from liverforce.learn.train import train_scenario
    from liverforce.mesh.io import write_mesh
    from liverforce.mesh.types import LiverMesh
    from liverforce.pipeline.simulate import probe_reference, simulate_cases

    tmp = tmp_path_factory.mktemp("physics")
    cfg = compose([])
    mesh = LiverMesh(**ellipsoid_liver(2))
    mesh_path = tmp / "mesh" / "val-1000.vtu"
    mesh_path.parent.mkdir()
    write_mesh(mesh_path, mesh)
    mat = cfg["material"]
    rng = np.random.default_rng(0)
    cases = top_face_cases(mesh, mat, "val-1000", 40, 3, 3.0, rng)
    cases_path = tmp / "cases.parquet"
    dio.write_case_table(cases, cases_path)
    rows = simulate_cases(cases[6:], {"val-1000": mesh}, cfg["simulate"], cfg["boundary"], cfg["dataset"],
                          probe=probe_reference(mat))
    dio.write_shard(rows, tmp / "train.parquet")
    arrays = dio.load_training_arrays([tmp / "train.parquet"])
    model_cfg = {**cfg["model"], "encoder": "pca", "code_size": 4, "hidden": [32], "grid_size": 8}
    train = {**cfg["train"], "epochs": 60, "repeats": 1, "interval": {**cfg["train"]["interval"], "folds": 0},
             "heldout_points": {**cfg["train"]["heldout_points"], "scenarios": []}}
    tune = {**cfg["tune"], "enabled": False}
    res = train_scenario(arrays, model_cfg, train, tune, "III", "pca_sv", out_dir=tmp / "models" / "IV" / "pca_sv")
    metrics = tmp / "models" / "IV" / "pca_sv" / "metrics.json"
    metrics.write_text(json.dumps({"variant": "pca_sv"}))
    return {"cfg": cfg, "mesh": mesh_path, "cases": cases_path, "model": res["model_path"], "metrics": metrics,
            "tmp": tmp}


@pytest.fixture(scope="module")
def study(setup):
    cfg = setup["cfg"]
    return physics_study(setup["cases"], setup["mesh"], [setup["model"]], [setup["metrics"]], cfg["simulate"],
                         cfg["boundary"], cfg["dataset"], cfg["material"], SPEC, setup["tmp"] / "physics.json",
                         setup["tmp"] / "physics")


@pytest.mark.slow  # the study's FE setup (~20 s): CI runs it with -m slow
def test_the_study_moves_the_tool_displacement_the_way_the_supports_do(study, setup):
    by = {v["name"]: v for v in study["variants"]}
    assert list(by) == [BASELINE, "foundation x0.25", "foundation x4", "kt/kn 0.1", "rib unilateral", "rib off",
                        "gravity supine"]
    assert study["case_ids"] == [f"V-{i:06d}" for i in range(6)]
    assert all(v["converged"] == 6 for v in study["variants"])
    base = by[BASELINE]
    assert base["u_tool_ratio_median"] == 1.0 and base["roi_change_pct_max"] == 0.0
    # softer supports: the liver gives more under the same force; stiffer: less
    assert by["foundation x0.25"]["u_tool_ratio_median"] > 1.0 > by["foundation x4"]["u_tool_ratio_median"]
    assert by["foundation x0.25"]["roi_change_pct_mean"] > 0.5
    # a sliding foundation lets the ROI move more, not less
    assert by["kt/kn 0.1"]["u_tool_ratio_median"] >= 1.0
    assert by["gravity supine"]["sag_max_mm"] > 0.1 and by[BASELINE]["sag_max_mm"] is None
    assert by[BASELINE]["compared_with"] is None and by["rib off"]["compared_with"] == BASELINE
    for v in study["variants"]:
        m = v["models"]["pca_sv"]
        assert np.isfinite(m["mae_vec"]) and 0 <= m["mae_vec"] < 10
    assert json.loads((setup["tmp"] / "physics.json").read_text()) == json.loads(json.dumps(study))


@pytest.mark.slow  # the study's FE setup (~20 s): CI runs it with -m slow
def test_the_models_are_scored_on_the_changed_cases_with_the_baseline_probe(study, setup):
    """Every shard holds the same cases; a changed choice keeps the baseline's stiffness probe (the model's
    assumption) while its displacements differ."""
    from liverforce.dataset import io as dio

    shards = sorted((setup["tmp"] / "physics").glob("*/shard-0000.parquet"))
    assert len(shards) == len(study["variants"])
    a = dio.load_training_arrays([shards[0]])
    b = dio.load_training_arrays([shards[1]])  # foundation x0.25
    assert list(a["case_id"]) == list(b["case_id"])
    np.testing.assert_array_equal(a["probe_compliance_mm_per_n"], b["probe_compliance_mm_per_n"])
    du = max(np.abs(np.asarray(x) - np.asarray(y)).max() for x, y in zip(a["roi_deformed_mm"], b["roi_deformed_mm"]))
    assert du > 0.05
    meta = dio.read_table(shards[1]).schema.metadata
    assert b"foundation x0.25" in b"".join(meta.values())


@pytest.mark.slow  # the study's FE setup (~20 s): CI runs it with -m slow
def test_with_gravity_the_rows_hold_the_tools_increment_over_the_sag(setup):
    """simulate_cases with gravity: a zero-force case shows no displacement (the sagged state is the
    reference, as in the pre-operative image); with a force, the increment is close to the no-gravity
    solution (small sag, mild nonlinearity) but not equal to it."""
    from liverforce.dataset import io as dio
    from liverforce.mesh.io import read_mesh
    from liverforce.pipeline.physics import _sag_max
    from liverforce.pipeline.simulate import probe_reference, simulate_cases

    cfg = setup["cfg"]
    mesh = read_mesh(setup["mesh"])
    case = dio.read_table(setup["cases"]).to_pylist()[0]
    zero = {**case, "case_id": "V-000099", "force_n": [0.0, 0.0, 0.0], "force_magnitude_n": 0.0}
    grav = {**cfg["boundary"], "gravity": {**cfg["boundary"]["gravity"], "enabled": True,
                                            "direction": [0.0, 0.0, -1.0]}}
    args = ({"val-1000": mesh}, cfg["simulate"])
    rows = simulate_cases([zero, case], *args, grav, cfg["dataset"], probe=probe_reference(cfg["material"]))
    plain = simulate_cases([case], *args, cfg["boundary"], cfg["dataset"], probe=probe_reference(cfg["material"]))
    assert all(r["converged"] for r in rows + plain)
    assert _sag_max(mesh, grav, cfg["simulate"], case) > 0.1
    assert np.abs(rows[0]["roi_deformed_mm"] - rows[0]["roi_undeformed_mm"]).max() < 1e-4
    assert np.abs(rows[0]["surface_displacement_mm"]).max() < 1e-4 and rows[0]["max_displacement_mm"] < 1e-4
    inc = rows[1]["roi_deformed_mm"] - rows[1]["roi_undeformed_mm"]
    ref = plain[0]["roi_deformed_mm"] - plain[0]["roi_undeformed_mm"]
    rel = np.linalg.norm(inc - ref) / np.linalg.norm(ref)
    assert 1e-4 < rel < 0.3


@pytest.mark.slow  # the study's FE setup (~20 s): CI runs it with -m slow
def test_the_report_shows_the_physics_table(study):
    from liverforce.report.html import physics_section

    page = physics_section(study, "pca_sv")
    assert "What the modelling choices cost" in page and "val-1000" in page
    assert page.count("<tr class='physics'") == len(study["variants"])
    d = study["variants"][1]["models"]["pca_sv"]["mae_vec"] - study["variants"][0]["models"]["pca_sv"]["mae_vec"]
    assert f"({d:+.3f})" in page
    assert physics_section(None, "pca_sv") == ""


@pytest.mark.slow  # the study's FE setup (~20 s): CI runs it with -m slow
def test_the_sphere_is_compared_with_the_traction_of_its_own_forces(setup):
    """The frictionless sphere exerts a force near the surface normal whatever the push direction; the study
    compares it with the traction carrying the very force vectors it exerted, on the first tool_cases cases."""
    from liverforce.dataset import io as dio

    cfg = setup["cfg"]
    sim = {**cfg["simulate"], "tool_tip_radius_mm": 10.0}  # the ellipsoid's facets are ~15 mm
    spec = {**SPEC, "n_cases": 1, "foundation_scale": [], "tangential_ratio": [], "rib_contact": [], "gravity": [],
            "tool": "sphere", "tool_cases": 2, "tool_max_force_n": 2.0}  # the sphere's cases beyond the baseline's
    st = physics_study(setup["cases"], setup["mesh"], [setup["model"]], [setup["metrics"]], sim, cfg["boundary"],
                       cfg["dataset"], cfg["material"], spec, setup["tmp"] / "tool.json", setup["tmp"] / "tool")
    names = [v["name"] for v in st["variants"]]
    assert names == [BASELINE, "tool: rigid sphere", "traction at the sphere's forces"]
    sph, trac = st["variants"][1], st["variants"][2]
    assert sph["n_cases"] == 2 and sph["converged"] == 2 and trac["converged"] == 2
    assert sph["compared_with"] == "traction at the sphere's forces" and trac["compared_with"] is None
    assert sph["u_tool_ratio_median"] > 0 and sph["roi_change_pct_max"] > 0
    a = dio.load_training_arrays([setup["tmp"] / "tool" / "01" / "shard-0000.parquet"])
    b = dio.load_training_arrays([setup["tmp"] / "tool" / "02" / "shard-0000.parquet"])
    np.testing.assert_allclose(a["force_n"], b["force_n"], rtol=1e-6)
    cases = {c["case_id"]: c for c in dio.read_table(setup["cases"]).to_pylist()}
    light = [c for c in sorted(cases) if cases[c]["force_magnitude_n"] <= 2.0][:2]  # the liver's first light cases
    assert list(a["case_id"]) == light
    for cid, f in zip(a["case_id"], a["force_n"]):  # the case's magnitude, within the sphere's tolerance
        assert np.linalg.norm(f) == pytest.approx(cases[cid]["force_magnitude_n"], rel=0.011)
    assert set(sph["models"]) == {"pca_sv"}
    from liverforce.report.html import physics_section

    page = physics_section(st, "pca_sv")  # the sphere's MAE change is against the traction of its own forces
    assert f"({sph['models']['pca_sv']['mae_vec'] - trac['models']['pca_sv']['mae_vec']:+.3f})" in page
