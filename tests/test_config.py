"""The composed configuration: experiments compose, bad values fail with their key."""
from __future__ import annotations

import pytest

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
    assert [v["name"] for v in smoke["train"]["variants"]] == ["pca_sv", "ae_sv"]


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
        ("validate.seed=1", "validate.seed"),
        ("geometry.procedural.shape.lobe_ratio=9", "geometry.procedural.shape"),
    ],
)
def test_bad_values_name_their_key(override, key):
    with pytest.raises(ConfigError) as err:
        compose([override])
    assert f"'{key}'" in str(err.value)


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
