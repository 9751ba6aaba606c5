"""The physics study on a lab's liver held out with its own supports (liverforce.pipeline.physics): every choice
keeps the lab's supports, changed as the configured ones are, so its baseline is the validation's simulation."""
from __future__ import annotations

import json

import numpy as np
import pytest
from fake_rows import top_face_cases

from liverforce.config import compose
from liverforce.pipeline.physics import LAB_BASELINE, physics_study, physics_variants

OWN = {"visceral_kn": 0.0005, "visceral_kt": 0.0005}  # N/mm³; the config's 42.6 N/mm gives 0.0014 on this liver
LAB = [{"name": "cava", "kind": "fixed", "selector": "sphere", "region_code": 1, "n_facets": 6},
       {"name": "bed", "kind": "foundation", "selector": "box", "region_code": 3, "n_facets": 40}]
SPEC = {"enabled": True, "liver": 0, "n_cases": 3, "foundation_scale": [2.0], "tangential_ratio": [0.1],
        "rib_contact": ["unilateral", "off"], "gravity": [[0.0, 0.0, -1.0]], "tool": "sphere", "tool_cases": 2,
        "tool_max_force_n": 1.0}


def test_each_choice_changes_the_labs_foundations_as_the_configured_ones():
    cfg = compose([])
    b, sim = cfg["boundary"], cfg["simulate"]
    areas = {0: 5e4, 1: 300.0, 3: 2e4}  # free, a fixed cava, the lab's visceral bed: no ligament, no rib region
    vs = {v["name"]: v for v in physics_variants(b, sim, SPEC, OWN, LAB, areas)}
    assert list(vs) == [LAB_BASELINE, "foundation x2", "kt/kn 0.1", "rib unilateral", "rib off", "gravity upright",
                        "tool: rigid sphere"]
    assert vs[LAB_BASELINE]["supports"] == OWN and "the lab's supports" in vs[LAB_BASELINE]["what"]
    two = vs["foundation x2"]
    assert two["supports"] == {"visceral_kn": 0.001, "visceral_kt": 0.001}  # the lab's stiffness, both springs
    assert two["boundary"]["visceral_total_n_per_mm"] == pytest.approx(2 * b["visceral_total_n_per_mm"])
    assert "the lab's foundation (visceral) 'bed'" in two["what"]
    assert "the lab's fixed 'cava' is not a spring: it stays as it is" in two["what"]
    kt = vs["kt/kn 0.1"]
    assert kt["supports"] == {"visceral_kn": 0.0005, "visceral_kt": pytest.approx(0.00005)}
    assert kt["boundary"]["tangential_ratio"] == 0.1 and "stays as it is" in kt["what"]
    for name in ("rib unilateral", "rib off"):  # no rib region: nothing to change
        assert "no rib region" in vs[name]["skip"]
    for name in ("foundation x2", "kt/kn 0.1", "gravity upright", "tool: rigid sphere"):
        assert "skip" not in vs[name]
    for name in ("rib unilateral", "gravity upright", "tool: rigid sphere"):  # the lab's foundations as they are
        assert vs[name]["supports"] == OWN
    # a rib region (a lab's sliding support): the rib choices act on it
    sliding = [*LAB, {"name": "ribs", "kind": "sliding", "selector": "box", "region_code": 4, "n_facets": 9}]
    vs = {v["name"]: v for v in physics_variants(b, sim, SPEC, OWN, sliding, {**areas, 4: 900.0})}
    assert "skip" not in vs["rib off"] and "the lab's sliding 'ribs'" in vs["rib off"]["what"]
    stay = "the lab's fixed 'cava', sliding 'ribs' are not springs: they stay as they are"
    assert stay in vs["foundation x2"]["what"] and stay in vs["kt/kn 0.1"]["what"]
    # no foundation region at all: the foundation choices would change nothing
    vs = {v["name"]: v for v in physics_variants(b, sim, SPEC, {}, LAB[:1], {0: 5e4, 1: 300.0})}
    assert "no foundation region" in vs["foundation x2"]["skip"] and "no foundation region" in vs["kt/kn 0.1"]["skip"]


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    """A small ellipsoid liver whose only support is the lab's foundation on its visceral face (mode: replace: no
    fixed support, no ligament, no rib), its features JSON as the mesh stage writes it, 8 cases on its top face,
    and the validation's shard of them (simulate_shard, which reads the liver's support_boundary)."""
    from liverforce.dataset import io as dio
    from liverforce.fem.testing import ellipsoid_liver
    from liverforce.mesh.io import write_mesh
    from liverforce.mesh.types import LiverMesh
    from liverforce.pipeline.simulate import simulate_shard

    tmp = tmp_path_factory.mktemp("physics_lab")
    cfg = compose([])
    m = ellipsoid_liver(2)
    m["facet_region"] = np.where(m["facet_region"] == 3, 3, 0).astype(np.int8)  # the lab's bed only
    mesh = LiverMesh(**m)
    mesh_path = tmp / "mesh" / "imp-lab.vtu"
    mesh_path.parent.mkdir()
    write_mesh(mesh_path, mesh)
    bed = [{"name": "bed", "kind": "foundation", "selector": "box", "region_code": 3,
            "n_facets": int((mesh.facet_region == 3).sum())}]
    (tmp / "mesh" / "imp-lab.features.json").write_text(json.dumps({"supports": bed, "support_boundary": OWN}))
    mat = cfg["material"]
    rng = np.random.default_rng(1)
    cases = top_face_cases(mesh, mat, "imp-lab", 8, 2, 1.5, rng)
    cases_path = tmp / "cases.parquet"
    dio.write_case_table(cases, cases_path)
    val = tmp / "V" / "shard-0000.parquet"
    val.parent.mkdir()
    simulate_shard(cases_path, [str(mesh_path)], 0, cfg["simulate"], cfg["boundary"], cfg["dataset"], val,
                   material=mat)
    return {"cfg": cfg, "mesh": mesh_path, "cases": cases_path, "validation": val, "tmp": tmp}


@pytest.fixture(scope="module")
def study(lab):
    cfg = lab["cfg"]
    spec = {**SPEC, "tangential_ratio": [], "rib_contact": ["unilateral"], "tool": "none"}
    # no features_path: the study finds the liver's features JSON beside its mesh, as the physics rule has it
    return physics_study(lab["cases"], lab["mesh"], [], [], cfg["simulate"], cfg["boundary"], cfg["dataset"],
                         cfg["material"], spec, lab["tmp"] / "physics.json", lab["tmp"] / "physics")


def _rows(shard, case_ids=None) -> dict:
    from liverforce.dataset import io as dio

    rows = dio.read_table(shard).to_pylist()
    return {r["case_id"]: r for r in rows if case_ids is None or r["case_id"] in case_ids}


@pytest.mark.slow  # FE on a small liver (~10 s): CI runs it with -m slow
def test_the_baseline_of_a_lab_liver_is_its_validation_simulation(study, lab):
    """Same supports, same cases: the physics baseline's rows are the validation shard's (to the solver's tolerance
    and float32 storage: a validation shard may warm-start these cases from others of the liver)."""
    assert study["variants"][0]["name"] == LAB_BASELINE
    assert study["own_supports"] == {"supports": json.loads((lab["tmp"] / "mesh" / "imp-lab.features.json")
                                                            .read_text())["supports"], "support_boundary": OWN}
    base = _rows(lab["tmp"] / "physics" / "00" / "shard-0000.parquet")
    val = _rows(lab["validation"], set(study["case_ids"]))
    assert sorted(base) == sorted(val) == ["V-000000", "V-000001", "V-000002"]
    for cid, r in base.items():
        v = val[cid]
        assert r["converged"] and v["converged"]
        u_b = np.asarray(r["surface_displacement_mm"], float)
        u_v = np.asarray(v["surface_displacement_mm"], float)
        assert np.abs(u_v).max() > 0.1  # a displacement to compare
        np.testing.assert_allclose(u_b, u_v, rtol=0, atol=1e-5 * np.abs(u_v).max())
        np.testing.assert_allclose(r["roi_deformed_mm"], v["roi_deformed_mm"], rtol=0, atol=1e-5 * np.abs(u_v).max())
        np.testing.assert_allclose(r["probe_compliance_mm_per_n"], v["probe_compliance_mm_per_n"], rtol=1e-9)


@pytest.mark.slow  # FE on a small liver (~10 s): CI runs it with -m slow
def test_foundation_x2_stiffens_the_labs_own_foundation(study, lab):
    """The liver's only support is the lab's foundation (the config's foundations have no region on it): x2 must
    scale the lab's stiffness, and the liver then gives less under the same force."""
    from liverforce.dataset import io as dio
    from liverforce.mesh.io import read_mesh
    from liverforce.pipeline.simulate import probe_reference, simulate_cases
    from liverforce.report.html import physics_section

    cfg = lab["cfg"]
    by = {v["name"]: v for v in study["variants"]}
    assert list(by) == [LAB_BASELINE, "foundation x2", "gravity upright"]
    assert by["foundation x2"]["converged"] == 3
    # stiffer: smaller under the same force, in every case, far beyond the solver's tolerance (the config's
    # foundations scaled alone would leave this liver as it is: a ratio of 1)
    assert by["foundation x2"]["u_tool_ratio_range"][1] < 0.995
    two = _rows(lab["tmp"] / "physics" / "01" / "shard-0000.parquet")
    meta = dio.read_table(lab["tmp"] / "physics" / "01" / "shard-0000.parquet").schema.metadata
    assert json.loads(meta[b"liverforce.support_boundary"]) == {"visceral_kn": 0.001, "visceral_kt": 0.001}
    # the same cases simulated directly with the lab's stiffness doubled: the choice's rows
    cases = [c for c in dio.read_table(lab["cases"]).to_pylist() if c["case_id"] in two]
    direct = simulate_cases(cases, {"imp-lab": read_mesh(lab["mesh"])}, cfg["simulate"], cfg["boundary"],
                            cfg["dataset"], supports={"imp-lab": {k: 2 * v for k, v in OWN.items()}},
                            probe=probe_reference(cfg["material"]))
    for r in direct:
        u = np.asarray(r["surface_displacement_mm"], float)
        np.testing.assert_allclose(two[r["case_id"]]["surface_displacement_mm"], u, rtol=0,
                                   atol=1e-5 * np.abs(u).max())
    # the rib choice is skipped (the lab's liver has no rib region), recorded and shown in the report
    assert [s["name"] for s in study["skipped"]] == ["rib unilateral"]
    assert "no rib region" in study["skipped"][0]["reason"]
    page = physics_section(study, None)
    assert "assumes the lab's supports of this liver" in page and "bed" in page
    assert "Not simulated: rib unilateral (the liver has no rib region" in page


@pytest.mark.slow  # FE on a small liver (~10 s): CI runs it with -m slow
def test_gravity_sags_the_liver_on_the_labs_supports(study, lab):
    """The sag is measured with the lab's foundation, not the config's."""
    from liverforce.dataset import io as dio
    from liverforce.mesh.io import read_mesh
    from liverforce.pipeline.physics import _sag_max

    cfg = lab["cfg"]
    sag = next(v for v in study["variants"] if v["name"] == "gravity upright")["sag_max_mm"]
    grav = {**cfg["boundary"], "gravity": {**cfg["boundary"]["gravity"], "enabled": True,
                                           "direction": [0.0, 0.0, -1.0]}}
    mesh, case = read_mesh(lab["mesh"]), dio.read_table(lab["cases"]).to_pylist()[0]
    assert sag == pytest.approx(_sag_max(mesh, grav, cfg["simulate"], case, OWN), rel=1e-9)
    assert sag > 1.2 * _sag_max(mesh, grav, cfg["simulate"], case)  # the lab's bed is softer than the config's


@pytest.mark.slow  # the lab fixture's FE (~10 s): CI runs it with -m slow
def test_a_gravity_state_that_fails_fails_that_choice_only(lab, monkeypatch):
    """A liver not held against its weight (a lab's liver on sliding supports alone, say): the gravity choice is
    recorded as failed with the reason, and the study's other choices and its JSON survive."""
    import liverforce.pipeline.physics as physics

    def no_sag(*args, **kwargs):
        raise RuntimeError("the gravity-only state did not converge (test)")

    monkeypatch.setattr(physics, "_sag_max", no_sag)
    cfg = lab["cfg"]
    spec = {**SPEC, "n_cases": 2, "foundation_scale": [], "tangential_ratio": [], "rib_contact": [], "tool": "none"}
    out = physics_study(lab["cases"], lab["mesh"], [], [], cfg["simulate"], cfg["boundary"], cfg["dataset"],
                        cfg["material"], spec, lab["tmp"] / "sagless.json", lab["tmp"] / "sagless")
    by = {e["name"]: e for e in out["variants"]}
    assert by[LAB_BASELINE]["converged"] == 2 and "sag_error" not in by[LAB_BASELINE]
    grav = by["gravity upright"]
    assert grav["sag_max_mm"] is None and "RuntimeError: the gravity-only state did not converge" in grav["sag_error"]
    assert json.loads((lab["tmp"] / "sagless.json").read_text())["variants"][1]["sag_error"] == grav["sag_error"]


def test_the_report_says_why_a_gravity_choice_failed():
    from liverforce.report.html import physics_section

    phys = {"liver": "imp-lab", "n_cases": 2, "forces_n": [0.5, 1.0], "variants": [
        {"name": LAB_BASELINE, "what": "the lab's supports", "converged": 2, "n_cases": 2, "models": {}},
        {"name": "gravity upright", "what": "self-weight", "converged": 0, "n_cases": 2, "models": {},
         "compared_with": LAB_BASELINE, "sag_max_mm": None,
         "sag_error": "RuntimeError: the gravity-only state did not converge"}]}
    assert "failed: RuntimeError: the gravity-only state did not converge" in physics_section(phys, None)


@pytest.mark.slow  # the lab fixture's FE and one baseline case (~15 s): CI runs it with -m slow
def test_the_spheres_cap_follows_a_lab_livers_own_stiffness(lab):
    """``tool_max_force_n`` is set for the procedural unseen livers' stiffness; on a lab liver of its own material
    the rule scales it (``tool_force_scale``, Plan.physics_spec): a liver so soft that no case is under the scaled
    cap skips the sphere, saying why, instead of pushing a 2.5 mm tip deeper than the mesh resolves."""
    cfg = lab["cfg"]
    spec = {**SPEC, "n_cases": 1, "foundation_scale": [], "tangential_ratio": [], "rib_contact": [], "gravity": [],
            "tool": "sphere", "tool_max_force_n": 1.0, "tool_force_scale": 0.01}
    from liverforce.dataset import io as dio

    forces = [np.linalg.norm(c["force_n"]) for c in dio.read_table(lab["cases"]).to_pylist()]
    assert min(forces) <= 1.0 < min(forces) / 0.01  # unscaled, the sphere would have run
    out = physics_study(lab["cases"], lab["mesh"], [], [], cfg["simulate"], cfg["boundary"], cfg["dataset"],
                        cfg["material"], spec, lab["tmp"] / "soft.json", lab["tmp"] / "soft")
    assert [e["name"] for e in out["variants"]] == [LAB_BASELINE]
    assert out["tool_max_force_n"] == pytest.approx(0.01) and out["tool_force_scale"] == 0.01
    (skip,) = out["skipped"]
    assert skip["name"] == "tool: rigid sphere"
    assert "of at most 0.01 N" in skip["reason"] and "x 0.01, this liver's own stiffness" in skip["reason"]
    assert json.loads((lab["tmp"] / "soft.json").read_text())["skipped"] == out["skipped"]


def test_the_report_gives_the_spheres_cap_and_its_scale():
    from liverforce.pipeline.physics import _tool_cap
    from liverforce.report.html import physics_section

    assert _tool_cap({"tool_max_force_n": 1.2}) == (1.2, False)
    assert _tool_cap({"tool_max_force_n": 1.2, "tool_force_scale": 0.5}) == (0.6, True)
    phys = {"liver": "imp-lab", "n_cases": 2, "forces_n": [0.5, 1.0], "tool_max_force_n": 0.6,
            "tool_force_scale": 0.5, "variants": [
                {"name": LAB_BASELINE, "what": "the lab's supports", "converged": 2, "n_cases": 2, "models": {}}]}
    text = physics_section(phys, None)
    assert "runs the light cases only (at most 0.60 N: <code>validate.physics.tool_max_force_n</code> x 0.5" in text
    assert "(at most 1.20 N)" in physics_section({**phys, "tool_max_force_n": 1.2, "tool_force_scale": None}, None)
    assert "at most" not in physics_section({k: v for k, v in phys.items() if k != "tool_max_force_n"}, None)
