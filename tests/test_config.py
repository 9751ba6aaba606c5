"""The composed configuration: experiments compose, bad values fail with their key."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from liverforce import config as config_mod
from liverforce.config import ConfigError, compose, config_hash


@pytest.mark.parametrize("experiment", ["smoke", "default", "thesis"])
def test_every_experiment_composes(experiment):
    cfg = compose([f"experiment={experiment}"])
    assert cfg["experiment"] == experiment
    assert set(cfg["sweep"]["scenarios"]) == {"I", "II", "III", "IV"}
    # plain containers only: no DictConfig leaves liverforce.config
    assert type(cfg) is dict and type(cfg["sweep"]["force"]) is dict


def test_experiment_overrides_defaults_and_cli_overrides_experiment():
    smoke = compose(["experiment=smoke"])
    default = compose([])
    assert smoke["mesh"]["target_nodes"] < default["mesh"]["target_nodes"]
    assert compose(["experiment=smoke", "mesh.target_nodes=950"])["mesh"]["target_nodes"] == 950
    # variants are a list: an experiment replaces them, it does not merge them
    assert [v["name"] for v in smoke["train"]["variants"]] == ["pca_sv", "ae_sv", "cloud_sv"]


def test_thesis_is_the_study_scale():
    cfg = compose(["experiment=thesis"])
    assert cfg["geometry"]["procedural"]["count"] == 24
    assert cfg["tune"]["trials"] == 200 and cfg["tune"]["folds"] == 10
    assert cfg["sweep"]["scenarios"]["IV"]["n_cases"] >= 24 * 1000


@pytest.mark.parametrize(
    "override, key",
    [
        ("sweep.force.min_n=-1", "sweep.force.min_n"),
        ("sweep.force.max_n=0", "sweep.force.max_n"),
        ("dataset.roi_fraction=0", "dataset.roi_fraction"),
        ("dataset.roi_fraction=1.5", "dataset.roi_fraction"),
        ("material.model=rubber", "material.model"),
        ("material.nu=0.5", "material.nu"),
        ("sweep.scenarios.I.n_cases=0", "sweep.scenarios.I.n_cases"),
        ("sweep.cases_per_shard=abc", "sweep.cases_per_shard"),
        ("mesh.mesher=magic", "mesh.mesher"),
        ("model.encoder=vae", "model.encoder"),
        ("model.gp.code_members=[8,8]", "model.gp.code_members"),
        ("model.gp.code_members=[0,16]", "model.gp.code_members"),
        ("model.gp.kernel=cauchy", "model.gp.kernel"),
        ("model.gp.shape=0", "model.gp.shape"),
        ("model.gp.shape=inf", "model.gp.shape"),
        ("model.camera.tip_noise_normal_mm=-0.5", "model.camera.tip_noise_normal_mm"),
        ("model.camera.grid.instrument_radius_mm=-1", "model.camera.grid"),
        ("model.camera.grid.dent_radius_mm=10", "model.camera.grid"),  # a dent fit needs the tool's radius
        ("model.camera.observation.tool_tilt_deg=90", "model.camera.observation"),
        ("+validate.camera_sensitivity.tool_tilt=[10]", "validate.camera_sensitivity"),
        ("validate.camera_sensitivity.outlier_fraction=[3]", "validate.camera_sensitivity.outlier_fraction"),
        ("model.camera.grid.outlier_mm=-1", "model.camera.grid"),
        ("model.camera.observation.outlier_fraction=0.7", "model.camera.observation"),
        ("validate.registration_errors=[[1,-1]]", "validate.registration_errors"),
        ("validate.registration_errors=[2]", "validate.registration_errors"),
        ("validate.shape_changes=[[2,0]]", "validate.shape_changes"),
        ("validate.shape_changes=[[-1,150]]", "validate.shape_changes"),
        ("model.camera.grid.instrument_radius_mm=2.5", "model.camera.grid.instrument_radius_mm"),
        ("validate.seed=1", "validate.seed"),
        ("geometry.procedural.shape.lobe_ratio=9", "geometry.procedural.shape"),
        ("train.interval.distance_quantile=1.0", "train.interval.distance_quantile"),
        ("train.interval.distance_quantile=0.2", "train.interval.distance_quantile"),
        ("train.interval.distance_quantile=true", "train.interval.distance_quantile"),
        ("train.interval.far_widths=maybe", "train.interval.far_widths"),
    ],
)
def test_bad_values_name_their_key(override, key):
    with pytest.raises(ConfigError) as err:
        compose([override])
    assert f"'{key}'" in str(err.value)


@pytest.mark.parametrize(
    "overrides, key, why",
    [
        (["model.camera.observation.instrument_in_cloud=true", "model.camera.observation.tool_radius_mm=0"],
         "model.camera.observation.instrument_in_cloud", "no instrument to see"),
        (["model.camera.observation.instrument_in_cloud=true", "model.camera.grid.instrument_radius_mm=3.0"],
         "model.camera.grid.instrument_radius_mm", "not the observed tool's"),
        (["model.camera.grid.instrument_radius_mm=2.5"], "model.camera.grid.instrument_radius_mm",
         "trained on clouds that show it"),
        (["model.camera.observation.instrument_in_cloud=true", "model.camera.grid.outlier_mm=3.0"],
         "model.camera.grid.outlier_mm", "nothing removes its points"),
    ],
)
def test_the_instrument_settings_must_agree(overrides, key, why):
    with pytest.raises(ConfigError) as err:
        compose(overrides)
    assert f"'{key}'" in str(err.value) and why in str(err.value)
    ok = compose(["model.camera.observation.instrument_in_cloud=true", "model.camera.grid.instrument_radius_mm=2.5"])
    assert ok["model"]["camera"]["grid"]["instrument_radius_mm"] == 2.5


def test_a_variant_changes_only_the_keys_of_a_group_it_names():
    """``gp: {kernel: ...}`` in a variant updates ``model.gp`` key by key (the other GP settings stay the model's);
    a key the group does not have is refused by its dotted name, as an unknown top-level key is."""
    from liverforce.config import variant_model
    from liverforce.pipeline.plan import Plan

    cfg = compose([])
    cloud = Plan(cfg).variants()["cloud_sv"]
    assert cloud["gp"] == {**cfg["model"]["gp"], "code_members": [8, 16, 32, 48, 64], "noise_floor": 0.003}
    assert cloud["gp"]["kernel"] == "rational_quadratic" and cloud["gp"]["shape"] == 2.0
    assert cloud["gp"]["max_points"] == cfg["model"]["gp"]["max_points"]
    assert Plan(cfg).variants()["pca_sv"]["gp"] == cfg["model"]["gp"]
    got = variant_model({"gp": {"kernel": "a", "shape": None}, "encoder": "pca", "camera": {"o": {"x": 1, "y": 2}}},
                        {"name": "v", "gp": {"shape": 2.0}, "encoder": "ae", "camera": {"o": {"y": 3}}})
    assert got == {"gp": {"kernel": "a", "shape": 2.0}, "encoder": "ae", "camera": {"o": {"x": 1, "y": 3}}}
    deep = Plan(compose(["train.variants=[{name: v, camera: {observation: {noise_sd_mm: 1.0}}}]",
                         "validate.variant=main"])).variants()["v"]["camera"]["observation"]
    assert deep == {**cfg["model"]["camera"]["observation"], "noise_sd_mm": 1.0}
    with pytest.raises(ConfigError, match=r"train.variants.v.*gp.kernal"):
        compose(["train.variants=[{name: v, gp: {kernal: squared_exponential}}]", "validate.variant=main"])
    with pytest.raises(ConfigError, match=r"train.variants.v.*camera.observation.noise_sd"):
        compose(["train.variants=[{name: v, camera: {observation: {noise_sd: 1.0}}}]", "validate.variant=main"])
    with pytest.raises(ConfigError, match=r"train.variants.v.*gp.kernel"):
        compose(["train.variants=[{name: v, gp: {kernel: cauchy}}]", "validate.variant=main"])


def test_unknown_key_is_refused():
    with pytest.raises(ConfigError, match="sweep.nonsense"):
        compose(["sweep.nonsense=1"])
    with pytest.raises(ConfigError, match="experiment"):
        compose(["experiment=does_not_exist"])


def test_hydra_leaves_no_outputs_and_keeps_cwd(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    compose(["experiment=smoke"])
    assert list(tmp_path.iterdir()) == []


def test_config_hash_is_stable_and_sensitive():
    a = compose(["experiment=smoke"])
    b = compose(["experiment=smoke"])
    c = compose(["experiment=smoke", "sweep.seed=1"])
    assert config_hash(a) == config_hash(b)
    assert config_hash(a["sweep"]) != config_hash(c["sweep"])
    assert config_hash(a["mesh"]) == config_hash(c["mesh"])


# --------------------------------------------------------------------------
# choice keys: checked against the registry of the module that implements them
# --------------------------------------------------------------------------

ROOT = Path(__file__).resolve().parents[1]


def _variant_choices():
    names = [v["name"] for v in compose([])["train"]["variants"]] or ["default"]
    return ["main", "auto", *names]


# (override with a bad value, dotted key, bad value, the valid choices)
BAD_CHOICES = [
    ("material.model=rubber", "material.model", "rubber", config_mod.material_models),
    ("material.on_unstable=ignore", "material.on_unstable", "ignore", lambda: ("refuse", "clip")),
    ("simulate.formulation=p3", "simulate.formulation", "p3", config_mod.formulations),
    ("simulate.linear_solver=mumps", "simulate.linear_solver", "mumps", config_mod.linear_solvers),
    ("sweep.design=grid", "sweep.design", "grid", config_mod.sweep_designs),
    ("sweep.scenarios.I.exertion=random", "sweep.scenarios.I.exertion", "random", lambda: ("fixed", "varies")),
    ("sweep.scenarios.I.material=random", "sweep.scenarios.I.material", "random", lambda: ("fixed", "varies")),
    ("sweep.scenarios.I.geometries=3", "sweep.scenarios.I.geometries", "3", lambda: ("1", "all")),
    ("mesh.mesher=magic", "mesh.mesher", "magic", lambda: config_mod.MESHERS),
    ("mesh.regions_check=loud", "mesh.regions_check", "loud", lambda: ("warn", "strict", "off")),
    ("dataset.compression=lz4", "dataset.compression", "lz4", lambda: ("zstd", "snappy", "gzip", "none")),
    ("model.encoder=vae", "model.encoder", "vae", config_mod.encoders),
    ("model.roi_features=curvature", "model.roi_features", "curvature", config_mod.roi_features),
    ("model.occlusion.mode=blur", "model.occlusion.mode", "blur", config_mod.occlusion_modes),
    ("model.force_scaling=log", "model.force_scaling", "log", config_mod.force_scalings),
    ("train.interval.widen=double", "train.interval.widen", "double", config_mod.interval_widenings),
    ("train.interval.scale=log", "train.interval.scale", "log", config_mod.interval_scales),
    ("validate.variant=nope", "validate.variant", "nope", _variant_choices),
    ("report.format=pdf", "report.format", "pdf", lambda: config_mod.REPORT_FORMATS),
    ("study.hyper_parameters=best", "study.hyper_parameters", "best", lambda: ("main", "config")),
    ("study.encoder.values=[vae]", "study.encoder.values", "vae", config_mod.encoders),
    ("study.state_vector.encoder=vae", "study.state_vector.encoder", "vae", config_mod.encoders),
    ("study.occlusion.encoders=[vae]", "study.occlusion.encoders", "vae", config_mod.encoders),
    ("study.occlusion.modes=[blur]", "study.occlusion.modes", "blur", config_mod.occlusion_modes),
]


@pytest.mark.parametrize("override, key, bad, choices", BAD_CHOICES, ids=[b[1] for b in BAD_CHOICES])
def test_a_bad_choice_names_the_key_the_value_and_the_valid_choices(override, key, bad, choices):
    with pytest.raises(ConfigError) as err:
        compose([override])
    msg = str(err.value)
    assert msg.startswith(f"config key '{key}': "), msg
    assert f"'{bad}'" in msg, msg
    valid = tuple(choices())
    assert valid and bad not in valid
    assert "choose one of " + ", ".join(map(str, valid)) in msg, msg


def test_registries_are_the_implementations_own():
    from liverforce.fem import linsolve
    from liverforce.fem.assembly import FORMULATIONS
    from liverforce.fem.materials import available_models
    from liverforce.sweep.design import DESIGNS

    names = config_mod._learn_names()
    assert config_mod.material_models() == tuple(available_models())
    assert config_mod.formulations() == tuple(FORMULATIONS)
    assert config_mod.linear_solvers() == tuple(linsolve.METHODS)
    assert config_mod.sweep_designs() == tuple(DESIGNS)
    assert config_mod.encoders() == tuple(names.ENCODERS)
    assert config_mod.roi_features() == tuple(names.ROI_FEATURE_CHANNELS)
    assert config_mod.occlusion_modes() == tuple(names.OCCLUSION_MODES)
    from liverforce.learn import interval
    assert config_mod.interval_widenings() == interval.WIDENINGS and config_mod.interval_scales() == interval.SCALES


# every name of a registry is accepted by the config
ACCEPTED = [
    ("material.model", config_mod.material_models),
    ("simulate.formulation", config_mod.formulations),
    ("simulate.linear_solver", config_mod.linear_solvers),
    ("sweep.design", config_mod.sweep_designs),
    ("model.encoder", config_mod.encoders),
    ("model.roi_features", config_mod.roi_features),
    ("model.occlusion.mode", config_mod.occlusion_modes),
    ("mesh.mesher", lambda: config_mod.MESHERS),
    ("report.format", lambda: config_mod.REPORT_FORMATS),
    ("validate.variant", _variant_choices),
    ("train.interval.widen", config_mod.interval_widenings),
    ("train.interval.scale", config_mod.interval_scales),
]


@pytest.mark.parametrize("key, choices", ACCEPTED, ids=[a[0] for a in ACCEPTED])
def test_every_registered_name_is_accepted(key, choices):
    for name in choices():
        cfg = compose([f"{key}={name}"])
        node = cfg
        for part in key.split("."):
            node = node[part]
        assert node == name


# constants for the models that have no config/material/*.yaml (every registered model needs one of the two)
EXTRA_MATERIAL_PARAMS = {
    "mooney_rivlin_2": {"C10": 0.002, "C01": 0.0005},
    "mooney_rivlin_3": {"C10": 0.002, "C01": 0.0005, "C11": 0.001},
    "ogden": {"mu1": 0.005, "alpha1": 2.0, "mu2": 0.001, "alpha2": -2.0},
}


def test_make_material_builds_every_registered_model():
    from liverforce.fem.materials import make_material

    params = dict(EXTRA_MATERIAL_PARAMS)
    for path in sorted((ROOT / "config" / "material").glob("*.yaml")):
        y = yaml.safe_load(path.read_text())
        if y.get("params_mpa"):
            params.setdefault(y["model"], y["params_mpa"])
    missing = [m for m in config_mod.material_models() if m not in params]
    assert not missing, f"give constants for {missing} (a config/material yaml or EXTRA_MATERIAL_PARAMS)"
    for model in config_mod.material_models():
        mat = make_material(model, params[model], nu=0.49)
        assert mat.model == model and mat.mu0 > 0 and mat.bulk > mat.mu0
    # the composed configs build too (the Young's modulus one is derived at compose time)
    for group in ("yeoh", "neo_hookean", "neo_hookean_from_e"):
        m = compose([f"material={group}"])["material"]
        assert make_material(m["model"], m["params_mpa"], nu=m["nu"]).model == m["model"]


def test_every_formulation_has_a_spec():
    from liverforce.fem.assembly import formulation_spec

    for name in config_mod.formulations():
        order, mean_dilatation = formulation_spec(name)
        assert order in (1, 2) and isinstance(mean_dilatation, bool)
    assert formulation_spec(compose([])["simulate"]["formulation"]) == (2, True)


def test_every_linear_solver_method_solves_or_says_what_it_needs():
    import scipy.sparse as sp

    from liverforce.fem.linsolve import LinearSolver, cholmod_available

    n = 30
    A = sp.diags([-np.ones(n - 1), 4 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1], format="csc")
    b = np.arange(1.0, n + 1)
    for method in config_mod.linear_solvers():
        if method == "cholmod" and not cholmod_available():
            with pytest.raises(ImportError, match="scikit-sparse"):
                LinearSolver(method)
            continue
        solver = LinearSolver(method)
        solver.factorize(A)
        np.testing.assert_allclose(A @ solver.solve(b), b, rtol=1e-10)
    with pytest.raises(ValueError, match="linear_solver"):
        LinearSolver("mumps")


def test_every_sweep_design_samples_the_unit_cube():
    from liverforce.sweep.design import SweepError, _unit_samples

    for design in config_mod.sweep_designs():
        u = _unit_samples(design, 10, 4, seed=3)
        assert u.shape == (10, 4) and np.all((u >= 0) & (u < 1))
        np.testing.assert_array_equal(u, _unit_samples(design, 10, 4, seed=3))
    with pytest.raises(SweepError, match="sobol"):
        _unit_samples("grid", 10, 4, seed=3)


def test_every_encoder_roi_feature_and_occlusion_mode_fits():
    from liverforce.learn.model import fit_preprocessor, prepare
    from liverforce.learn.representation import Representation
    from liverforce.learn.synthetic import synthetic_arrays

    arrays = synthetic_arrays(24, seed=1, nodes=(200, 300))
    for features in config_mod.roi_features():
        if features == "cloud":  # a camera cloud: the camera model's own occlusion, no node occlusion
            from liverforce.learn.synthetic import synthetic_surface_arrays

            rep = Representation(grid_size=5, half_width_mm=14.0, features=features, camera={})
            prep = prepare(synthetic_surface_arrays(6, seed=1, n_vertices=3000), rep, observation_seeds=[0])
            assert prep.x_obs.shape[-1] == rep.n_features == 2 * 25 + 3
            continue
        for mode in config_mod.occlusion_modes():
            rep = Representation(grid_size=5, half_width_mm=14.0, features=features,
                                 occlusion_radius_mm=4.0, occlusion_mode=mode)
            prep = prepare(arrays, rep, observation_seeds=[0])
            assert prep.x_obs.shape[-1] == rep.n_features
    for encoder in config_mod.encoders():
        pre = fit_preprocessor(prep, rep, encoder=encoder, code_size=2, use_state=False, seed=0, epochs=2,
                               lr=1e-3, batch_size=8)
        assert pre.encoder.code_size == 2 and pre.encoder.kind == encoder


def test_config_reads_the_registries_not_a_copy(monkeypatch):
    from liverforce.fem import assembly, linsolve, materials
    from liverforce.sweep import design

    names = config_mod._learn_names()
    monkeypatch.setitem(materials._MODELS, "soft_tissue", materials._MODELS["neo_hookean"])
    monkeypatch.setitem(assembly.FORMULATIONS, "p2_new", (2, False))
    monkeypatch.setattr(linsolve, "METHODS", (*linsolve.METHODS, "pardiso"))
    monkeypatch.setitem(design.DESIGNS, "halton", design.DESIGNS["sobol"])
    monkeypatch.setattr(names, "ENCODERS", (*names.ENCODERS, "vae"))
    monkeypatch.setitem(names.ROI_FEATURE_CHANNELS, "normals", 3)
    monkeypatch.setattr(names, "OCCLUSION_MODES", (*names.OCCLUSION_MODES, "blur"))
    cfg = compose(["material.model=soft_tissue", "simulate.formulation=p2_new", "simulate.linear_solver=pardiso",
                   "sweep.design=halton", "model.encoder=vae", "model.roi_features=normals",
                   "model.occlusion.mode=blur", "study.encoder.values=[vae]", "study.occlusion.modes=[blur]"])
    assert cfg["material"]["model"] == "soft_tissue" and cfg["model"]["encoder"] == "vae"
    assert cfg["model"]["roi_features"] == "normals" and cfg["sweep"]["design"] == "halton"
    # and the implementations see the same names: the representation accepts the new feature name
    assert "normals" in config_mod.roi_features() and "halton" in design.design_names()
    assert "soft_tissue" in materials.available_models()


def test_composing_does_not_import_torch():
    code = ("import sys; from liverforce.config import compose; compose([]); "
            "assert 'torch' not in sys.modules, 'torch imported'; "
            "assert 'liverforce.learn.model' not in sys.modules, 'the learn package loaded its model'; "
            "import liverforce.learn.representation as r, liverforce.learn.names as n; "
            "assert r.names is n is sys.modules['liverforce.learn.names']")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT, timeout=120)


# --------------------------------------------------------------------------
# defaults are written once: in config/*.yaml, never in the schema or the stage adapters
# --------------------------------------------------------------------------

#: list-entry schemas: no YAML file holds defaults for the entries of a list, so theirs live in the schema only
ENTRY_SCHEMAS = {"ImportedGeometry"}


def _schema_fields(cls, prefix=""):
    """(dotted key, field, resolved type) of every field reachable from ``cls``; list / dict entries as ``key[]``."""
    import dataclasses
    import typing

    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        key, typ = f"{prefix}{f.name}", hints[f.name]
        yield key, f, typ
        inner = [a for a in typing.get_args(typ) if dataclasses.is_dataclass(a)]
        if dataclasses.is_dataclass(typ):
            yield from _schema_fields(typ, key + ".")
        for entry in inner:
            if entry.__name__ not in ENTRY_SCHEMAS:
                yield from _schema_fields(entry, key + "[].")


def test_the_schema_carries_no_defaults():
    """Every value comes from config/*.yaml: a schema field has no default (MISSING), a group is its dataclass."""
    import dataclasses

    import omegaconf

    assert config_mod.MISSING == omegaconf.MISSING
    with_default = []
    for key, f, typ in _schema_fields(config_mod.RootConfig):
        if dataclasses.is_dataclass(typ):  # a nested group: structure, not a default
            assert f.default_factory is typ, key
        elif f.default is not config_mod.MISSING or f.default_factory is not dataclasses.MISSING:
            with_default.append(key)
    assert not with_default, f"defaults belong in config/*.yaml, not in liverforce/config.py: {with_default}"
    assert compose([])["geometry"]["imported"] == []  # the one entry schema has no YAML entry to disagree with


def test_a_key_the_yaml_does_not_give_is_an_error_not_a_default(tmp_path, monkeypatch):
    import shutil

    conf = tmp_path / "config"
    shutil.copytree(config_mod.CONFIG_DIR, conf)
    text = (conf / "mesh" / "default.yaml").read_text()
    (conf / "mesh" / "default.yaml").write_text("\n".join(ln for ln in text.splitlines()
                                                          if not ln.startswith("refine_growth:")))
    monkeypatch.setattr(config_mod, "CONFIG_DIR", conf)
    with pytest.raises(ConfigError, match="mesh.refine_growth"):
        compose([])


def test_stage_adapters_default_nothing_the_config_gives(tmp_path, monkeypatch):
    """validate_model takes the variant and experiment name from its rule; the mesh stage takes every mesh key
    from the composed config (no silent refine_growth 0.3 beside the YAML's 0.6)."""
    import inspect

    import liverforce.mesh.build as build
    from liverforce.pipeline.geometry import make_geometry
    from liverforce.pipeline.mesh import make_mesh
    from liverforce.pipeline.validate import validate_model

    sig = inspect.signature(validate_model)
    assert all(sig.parameters[k].default is inspect.Parameter.empty for k in ("variant", "experiment_name"))

    cfg = compose([])
    make_geometry({"kind": "cube", "edge_mm": 50.0}, tmp_path / "cube.ply", tmp_path / "cube.json")
    seen = {}

    class Stop(Exception):
        pass

    def fake_build(surface, **kw):
        seen.update(kw)
        raise Stop

    monkeypatch.setattr(build, "build_liver_mesh", fake_build)
    out = [tmp_path / n for n in ("cube.vtu", "cube.features.json", "cube.regions.png")]
    with pytest.raises(Stop):
        make_mesh(tmp_path / "cube.ply", cfg["mesh"], 7, *out)
    assert seen["refine_growth"] == cfg["mesh"]["refine_growth"] == 0.6
    assert seen["refine_radius_mm"] == cfg["mesh"]["refine_radius_mm"] and seen["seed"] == 7
    partial = {k: v for k, v in cfg["mesh"].items() if k != "refine_growth"}
    with pytest.raises(KeyError, match="refine_growth"):
        make_mesh(tmp_path / "cube.ply", partial, 7, *out)
