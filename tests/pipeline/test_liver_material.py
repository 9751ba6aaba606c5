"""A lab liver's own material (``geometry.imported[].material``).

A lab that brings a patient's liver often brings an estimate of its stiffness too (elastography, an indentation
of the resected specimen, a fibrosis grade). A held-out liver's cases then take that material as given, instead of
the run's constants x ``validate.material_scale``; a training liver's scenarios draw their constants around it.
"""
from __future__ import annotations

import copy
import functools

import numpy as np
import pytest

from liverforce.config import ConfigError, compose, liver_material
from liverforce.fem.materials import neo_hookean_from_young
from liverforce.pipeline.plan import VALIDATION, Plan
from liverforce.pipeline.sweep import material_checks
from liverforce.sweep.design import ExertionSet, SweepError, build_cases

TWO = "geometry.imported=[{name:a,path:a.stl,units:mm%s},{name:b,path:b.stl,units:mm%s}]"


def _cfg(a: str = "", b: str = "", *more: str) -> dict:
    """The smoke experiment on two imported livers, neo-Hookean unless ``more`` picks another material (a copy of
    one composition per arguments: composing takes about a second)."""
    return copy.deepcopy(_composed(a, b, *more))


@functools.lru_cache(maxsize=None)
def _composed(a: str, b: str, *more: str) -> dict:
    return compose(["experiment=smoke", "material=neo_hookean", TWO % (a, b), *more])


def _run_c10(cfg) -> float:
    return float(cfg["material"]["params_mpa"]["C10"])


@pytest.mark.parametrize("spec, expected", [
    ("{E_pa:9000}", lambda run: neo_hookean_from_young(9000.0, 0.49)[0]["C10"]),
    ("{E_mpa:0.009}", lambda run: neo_hookean_from_young(9000.0, 0.49)[0]["C10"]),
    ("{params_mpa:{C10:0.004}}", lambda run: 0.004),
    ("{scale:1.5}", lambda run: 1.5 * run),
])
def test_each_form_gives_the_livers_constants(spec, expected):
    cfg = _cfg(f",material:{spec}")
    mats = Plan(cfg).liver_materials()
    assert list(mats) == ["imp-a"]  # b brings none
    assert mats["imp-a"]["params_mpa"]["C10"] == pytest.approx(expected(_run_c10(cfg)), rel=1e-12)
    assert set(mats["imp-a"]) == {"params_mpa", "entered"}  # rule params: no derived words


def test_young_modulus_uses_the_runs_poisson_ratio():
    cfg = _cfg(",material:{E_pa:9000}", "", "material.nu=0.45")
    got = Plan(cfg).liver_materials()["imp-a"]["params_mpa"]["C10"]
    assert got == pytest.approx(9000e-6 / (2 * 1.45) / 2, rel=1e-12)


@pytest.mark.parametrize("spec, more, key, words", [
    ("{E_pa:9000,scale:2}", [], "geometry.imported[0].material", "give one of E_pa, E_mpa, params_mpa, scale"),
    ("{youngs:9000}", [], "geometry.imported[0].material", "give one of E_pa, E_mpa, params_mpa, scale"),
    ("{params_mpa:{C01:0.004}}", [], "geometry.imported[0].material.params_mpa",
     "must give the run's neo_hookean constants ['C10']"),
    ("{scale:0}", [], "geometry.imported[0].material.scale", "must be a number > 0"),
    ("{scale:-1.5}", [], "geometry.imported[0].material.scale", "must be a number > 0"),
    ("{E_pa:9000}", ["material=yeoh"], "geometry.imported[0].material.E_pa",
     "Young's modulus defines a neo_hookean material; this run's is 'yeoh'"),
    ("{E_pa:0.009}", [], "geometry.imported[0].material.E_pa", "if 0.009 is in MPa, give E_pa=9000"),
    ("{params_mpa:{C10:2.5}}", [], "geometry.imported[0].material.params_mpa", "if these constants are in Pa"),
    ("{scale:1000}", [], "geometry.imported[0].material.scale", "outside the 1e-05-1 MPa of any liver"),
    ("{scale:true}", [], "geometry.imported[0].material.scale", "must be a number > 0"),
    ("{params_mpa:{C10:true}}", [], "geometry.imported[0].material.params_mpa", "constants must be numbers"),
])
def test_a_wrong_material_is_refused_naming_the_key(spec, more, key, words):
    with pytest.raises(ConfigError) as err:
        _cfg(f",material:{spec}", "", *more)
    msg = str(err.value)
    assert f"config key '{key}'" in msg and words in msg, msg


def test_the_geometry_does_not_depend_on_the_material():
    """Editing a liver's material re-simulates it, never re-meshes it: the geometry and mesh rules' params
    (``Plan.geometry_spec``) are those of the liver without the key."""
    with_mat, without = Plan(_cfg(",material:{E_pa:9000}")), Plan(_cfg())
    assert with_mat.geometry_spec("imp-a") == without.geometry_spec("imp-a")
    assert "material" not in with_mat.geometry_spec("imp-a")


def test_sweep_params_carry_each_scenarios_own_materials_and_nothing_without_them():
    plan = Plan(_cfg(",material:{scale:1.2}", ",material:{E_pa:9000}", "validate.imported=[b]"))
    v = plan.sweep_params(VALIDATION)["material"]
    assert list(v["per_liver"]) == ["imp-b"]  # a procedural unseen liver takes the run's x material_scale
    assert v["per_liver"]["imp-b"]["entered"] == {"E_pa": 9000}
    for s in plan.scenarios:
        own = plan.sweep_params(s)["material"]["per_liver"]
        assert list(own) == ["imp-a"]  # I-III: the first training import; IV: every training liver
    plain = Plan(_cfg())
    assert all("per_liver" not in plain.sweep_params(s)["material"] for s in plain.all_scenarios())


def _exertion(gids):
    frame = np.eye(3)[None]
    return {g: ExertionSet(points=np.zeros((1, 3)), normals=np.array([[0.0, 0.0, 1.0]]), frames=frame)
            for g in gids}


def _build(material, spec, gids, n=60):
    stable, bulk = material_checks(material["stability_stretch"], material["nu"])
    return build_cases(scenario="X", spec={**spec, "n_cases": n}, geometry_ids=gids, exertion=_exertion(gids),
                       material=material, force={"min_n": 0.0, "max_n": 5.0, "cone_deg": 30.0}, design="sobol",
                       seed=7, cases_per_shard=25, stability_check=stable, bulk_modulus=bulk)


def test_a_held_out_livers_cases_take_its_constants_as_given():
    plan = Plan(_cfg("", ",material:{E_pa:9000}", "validate.imported=[b]", "validate.livers=2"))
    params = plan.sweep_params(VALIDATION)
    rows = _build(params["material"], params["spec"], params["geometries"]).rows
    c10 = {g: sorted({r["material_params_mpa"][0] for r in rows if r["geometry_id"] == g})
           for g in params["geometries"]}
    scale = plan.cfg["validate"]["material_scale"]
    assert c10["imp-b"] == [neo_hookean_from_young(9000.0, 0.49)[0]["C10"]]  # not x material_scale
    assert c10["val-1000"] == c10["val-1001"] == [pytest.approx(scale * _run_c10(plan.cfg), rel=1e-12)]
    bulk = {r["geometry_id"]: r["bulk_modulus_mpa"] for r in rows}
    assert bulk["imp-b"] == pytest.approx(bulk["val-1000"] * c10["imp-b"][0] / c10["val-1000"][0], rel=1e-9)


def test_a_training_livers_cases_are_drawn_around_its_own_constants():
    plan = Plan(_cfg(",material:{scale:2.0}"))
    params = plan.sweep_params("IV")
    rows = _build(params["material"], params["spec"], params["geometries"], n=120).rows
    r, run = plan.cfg["material"]["vary_rel"], _run_c10(plan.cfg)
    for gid, centre in (("imp-a", 2.0 * run), ("proc-0000", run)):
        c = np.array([row["material_params_mpa"][0] for row in rows if row["geometry_id"] == gid])
        assert len(c) > 5
        assert c.min() >= centre * (1 - r) - 1e-15 and c.max() <= centre * (1 + r) + 1e-15
        assert c.max() - c.min() > centre * r  # drawn across the range, not one value
    a = [row["material_params_mpa"][0] for row in rows if row["geometry_id"] == "imp-a"]
    others = [row["material_params_mpa"][0] for row in rows if row["geometry_id"] != "imp-a"]
    assert min(a) > max(others)  # 2x the run's, +-30 %: apart from every procedural liver's


def test_an_unstable_own_material_is_refused_naming_the_liver():
    mat = dict(Plan(_cfg()).cfg["material"])
    mat["per_liver"] = {"imp-a": {"params_mpa": {"C10": -0.002}}}
    with pytest.raises(SweepError) as err:
        _build(mat, {"exertion": "fixed", "material": "fixed"}, ["imp-a"])
    assert "the liver imp-a's own material" in str(err.value) and "not Drucker-stable" in str(err.value)


def test_liver_material_is_the_configs_check():
    """The Plan, the sweep and the workflow's stability check resolve a material with the same function."""
    cfg = _cfg(",material:{E_pa:9000}")
    params, note = liver_material({"E_pa": 9000}, cfg["material"], "k")
    assert Plan(cfg).liver_materials()["imp-a"]["params_mpa"] == params and "kPa" in note


def _setup(plan: Plan) -> dict:
    """The report rule's setup slices (workflow/rules/report.smk) that the material's words read."""
    return {"material": plan.cfg["material"], "validate": plan.cfg["validate"], "sweep": plan.cfg["sweep"],
            "liver_materials": plan.liver_materials(),
            "population": {"training": plan.train_geometries, "unseen": plan.validation_geometries}}


@pytest.mark.parametrize("e_pa, where", [(14900 * 1.2, "within"), (14900 * 2.0, "outside")])
def test_the_report_says_whether_a_held_out_livers_own_material_lies_in_the_training_range(e_pa, where):
    from liverforce.report.html import _scale_words

    plan = Plan(_cfg("", f",material:{{E_pa:{e_pa}}}", "validate.imported=[b]", "validate.material_scale=1.4"))
    words = _scale_words(_setup(plan))
    assert words.startswith("outside the training range; ")  # the procedural unseen livers: x1.4 against +-30 %
    assert "<code>imp-b</code>: its own, C10 " in words and words.endswith(f"MPa, {where} the training range")
    # with no procedural unseen liver only its own is named
    alone = Plan(_cfg("", f",material:{{E_pa:{e_pa}}}", "validate.imported=[b]", "validate.livers=0"))
    assert _scale_words(_setup(alone)).startswith("<code>imp-b</code>: its own, C10 ")


def test_the_report_names_a_training_livers_own_constants():
    from liverforce.report.html import _own_materials

    got = _own_materials(_setup(Plan(_cfg(",material:{scale:2.0}"))))
    assert got["unseen"] == [] and [g for g, _, _ in got["training"]] == ["imp-a"]
    assert got["training"][0][2] == {"scale": 2.0}


def test_the_scaled_unseen_livers_are_judged_against_the_training_livers_own_ranges():
    """A training liver with its own constants x 1.4 widens the training range to hold the unseen livers' x 1.4."""
    from liverforce.report.html import _scale_words

    plan = Plan(_cfg(",material:{scale:1.4}", "", "validate.material_scale=1.4"))
    assert _scale_words(_setup(plan)) == "within the training range"
    plain = Plan(_cfg("", "", "validate.material_scale=1.4"))
    assert _scale_words(_setup(plain)) == "outside the training range"


def test_one_training_liver_must_hold_every_constant():
    """A Yeoh set whose C10 lies in one liver's range and C20 in another's was no training liver's."""
    from liverforce.report.html import _own_materials

    setup = {"material": {"params_mpa": {"C10": 1.0, "C20": 1.0}, "vary_rel": 0.1},
             "sweep": {"scenarios": {"IV": {"material": "varies"}}},
             "liver_materials": {"imp-a": {"params_mpa": {"C10": 2.0, "C20": 1.0}}},
             "population": {"training": ["imp-a", "proc-0000"], "unseen": []}}
    inside = _own_materials(setup)["inside"]
    assert inside({"C10": 2.05, "C20": 1.05}) and inside({"C10": 1.05, "C20": 0.95})
    assert not inside({"C10": 2.05, "C20": 2.0}) and not inside({"C10": 1.5, "C20": 1.0})


def test_a_lab_entered_constants_read_as_words():
    from liverforce.learn.provenance import own_material_lines
    from liverforce.report.html import _entered_words

    assert _entered_words({"params_mpa": {"C10": 0.0015}}) == "params_mpa C10 0.0015"
    assert _entered_words({"E_pa": 9000}) == "E_pa 9000"
    line = own_material_lines({"per_liver": {"imp-a": {"params_mpa": {"C10": 0.0015},
                                                       "entered": {"params_mpa": {"C10": 0.0015}}}}})
    assert line == ["material of imp-a: its own, C10 0.0015 MPa (entered as params_mpa C10 0.0015)"]


def test_the_physics_check_scales_the_spheres_cap_by_a_held_out_livers_own_stiffness():
    """validate.physics.tool_max_force_n is set for the procedural unseen livers (the run's constants x
    validate.material_scale); a held-out lab liver with its own constants takes it in their ratio, and a run
    without such a liver, or without the sphere, keeps validate.physics as it is (its physics rule's params, and
    its results)."""
    held = ("validate.imported=[b]", "validate.livers=1", "validate.physics.liver=1", "validate.physics.tool=sphere")
    cfg = _cfg("", ",material:{scale:0.8}", *held)
    spec = Plan(cfg).physics_spec()
    assert spec["tool_force_scale"] == pytest.approx(0.8 / cfg["validate"]["material_scale"], rel=1e-12)
    assert {k: v for k, v in spec.items() if k != "tool_force_scale"} == cfg["validate"]["physics"]
    procedural = _cfg("", ",material:{scale:0.8}", *held[:2], "validate.physics.liver=0", held[3])
    assert Plan(procedural).physics_spec() == procedural["validate"]["physics"]
    no_own = _cfg("", "", *held)
    assert Plan(no_own).physics_spec() == no_own["validate"]["physics"]
    own_a = _cfg(",material:{E_pa:9000}", "", *held)  # a training liver's own material: not the checked liver
    assert "tool_force_scale" not in Plan(own_a).physics_spec()
    no_sphere = _cfg("", ",material:{scale:0.8}", *held[:3], "validate.physics.tool=none")  # no cap to scale
    assert Plan(no_sphere).physics_spec() == no_sphere["validate"]["physics"]


def test_the_spheres_cap_scale_is_the_initial_shear_modulus_ratio_whatever_the_model():
    """Mooney-Rivlin's small-strain stiffness is mu0 = 2 (C10 + C01), not C10: a held-out liver stiffer in C01
    alone is stiffer (a larger cap, not a smaller one), and a run with C10 = 0 (stable, its mu0 from C01) still
    plans its physics check (the first constant's ratio divided by zero when the workflow was read)."""
    held = ("validate.imported=[b]", "validate.livers=1", "validate.physics.liver=1", "validate.physics.tool=sphere")
    mr = ("material.model=mooney_rivlin_2", "+material.params_mpa.C01=0.002", "material.params_mpa.C10=0.0005")
    cfg = _cfg("", ",material:{params_mpa:{C10:0.0005,C01:0.004}}", *held, *mr)
    scale = cfg["validate"]["material_scale"]
    assert Plan(cfg).physics_spec()["tool_force_scale"] == pytest.approx(0.009 / (0.005 * scale), rel=1e-12)
    zero = _cfg("", ",material:{scale:0.8}", *held, *mr[:2], "material.params_mpa.C10=0.0")
    assert Plan(zero).physics_spec()["tool_force_scale"] == pytest.approx(0.8 / scale, rel=1e-12)
