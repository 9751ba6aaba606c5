"""The workflow's bookkeeping: geometry ids, per-scenario slices, shard counts."""
from __future__ import annotations

from liverforce.config import compose
from liverforce.pipeline.plan import VALIDATION, Plan


def test_geometries_per_scenario():
    plan = Plan(compose(["experiment=smoke"]))
    assert plan.train_geometries == ["proc-0000", "proc-0001", "proc-0002"]
    assert plan.scenario_geometries("I") == ["proc-0000"]
    assert plan.scenario_geometries("IV") == plan.train_geometries
    assert plan.scenario_geometries(VALIDATION) == ["val-1000", "val-1001"]
    assert not set(plan.validation_geometries) & set(plan.train_geometries)
    assert plan.scenario_spec(VALIDATION)["n_cases"] == 2 * 4  # livers x cases per liver


def test_unseen_livers_never_share_a_seed_with_training():
    import pytest

    from liverforce.config import ConfigError

    plan = Plan(compose(["geometry.procedural.count=24", "validate.livers=8"]))
    seeds = lambda ids: {int(g.split("-")[1]) for g in ids}  # noqa: E731
    assert len(plan.validation_geometries) == 8
    assert not seeds(plan.validation_geometries) & seeds(plan.train_geometries)
    with pytest.raises(ConfigError, match="validate.seed"):  # 995..1002 overlaps training seeds 995..1018
        compose(["geometry.procedural.seed=995", "geometry.procedural.count=24"])


def test_imported_and_cube_geometries_join_training():
    cfg = compose(["experiment=smoke", "geometry.cube.enabled=true",
                   "geometry.imported=[{name: sofa, path: /x/liver.obj, units: '40'}]"])
    plan = Plan(cfg)
    assert plan.train_geometries[-2:] == ["imp-sofa", "cube"]
    spec = plan.geometry_spec("imp-sofa")
    assert spec["kind"] == "imported" and spec["units"] == "40"


def test_scenarios_get_distinct_seeds_and_validation_unseen_material():
    cfg = compose(["experiment=smoke"])
    plan = Plan(cfg)
    seeds = {plan.sweep_params(s)["seed"] for s in plan.all_scenarios()}
    assert len(seeds) == 5
    val = plan.sweep_params(VALIDATION)["material"]["params_mpa"]
    base = cfg["material"]["params_mpa"]
    scale = cfg["validate"]["material_scale"]
    for k in base:
        # outside the training range p (1 +- vary_rel)
        assert val[k] == base[k] * scale and val[k] > base[k] * (1 + cfg["material"]["vary_rel"])


def test_shard_ids_cover_cases_and_variants_merge_model():
    plan = Plan(compose(["experiment=smoke", "sweep.cases_per_shard=5"]))
    assert plan.shard_ids("I") == ["0000", "0001", "0002"]  # 12 cases / 5 per shard
    v = plan.variants()
    assert list(v) == ["pca_sv", "ae_sv", "cloud_sv"] and v["ae_sv"]["encoder"] == "ae"
    assert v["ae_sv"]["grid_size"] == plan.cfg["model"]["grid_size"]


def test_slices_are_independent():
    a = Plan(compose(["experiment=smoke"]))
    b = Plan(compose(["experiment=smoke", "model.dropout=0.3"]))
    assert a.sweep_params("II") == b.sweep_params("II")
    assert a.variants() != b.variants()
