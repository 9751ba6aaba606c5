"""A lab's own liver in the plan: scenarios I-III on it, the procedural livers for IV; the shipped
experiments (no imported liver) plan exactly as before.

Config-only: the config is composed and planned, no FE.
"""
from __future__ import annotations

import logging

import pytest

from liverforce.config import compose
from liverforce.pipeline.plan import VALIDATION, Plan

LAB = "geometry.imported=[{name:lab01,path:/lab/liver_lps_m.stl,units:m,frame:LPS}]"


DEFAULT_SEEDS = {"I": 666586745, "II": 2018024019, "III": 641103784, "IV": 1665022272, VALIDATION: 1705727896}


@pytest.mark.parametrize("experiment,n_train,n_val", [("default", 40, 8), ("smoke", 3, 2)])
def test_the_shipped_experiments_plan_as_before(experiment, n_train, n_val):
    """No imported liver: the same livers in the same scenarios with the same seeds as before labs' livers
    moved to I-III (the ids and seeds below are those the plan gave then)."""
    plan = Plan(compose([f"experiment={experiment}"]))
    procs = [f"proc-{i:04d}" for i in range(n_train)]
    livers = {"I": ["proc-0000"], "II": ["proc-0000"], "III": ["proc-0000"], "IV": procs,
              VALIDATION: [f"val-{1000 + i}" for i in range(n_val)]}
    assert plan.train_geometries == procs
    for s, seed in DEFAULT_SEEDS.items():  # only what the plan had before (this test passes on it too)
        params = plan.sweep_params(s)
        assert plan.scenario_geometries(s) == livers[s] == params["geometries"] and params["seed"] == seed
    assert plan.train_seed() == 1436740723
    if hasattr(plan, "scenario_livers"):
        assert plan.scenario_livers() == livers and plan.single_geometry == "proc-0000"


def test_scenarios_i_to_iii_use_the_lab_liver_and_the_procedural_ones_serve_iv(caplog):
    with caplog.at_level(logging.INFO, logger="liverforce.plan"):
        plan = Plan(compose(["experiment=smoke", LAB, "geometry.procedural.count=1"]))
    assert plan.train_geometries == ["proc-0000", "imp-lab01"]  # the order (IV, its seeds) as before
    for s in ("I", "II", "III"):
        assert plan.scenario_geometries(s) == ["imp-lab01"] == plan.sweep_params(s)["geometries"]
        assert plan.sweep_params(s)["seed"] == DEFAULT_SEEDS[s]
    assert plan.scenario_geometries("IV") == ["proc-0000", "imp-lab01"]
    assert plan.scenario_geometries(VALIDATION) == ["val-1000", "val-1001"]
    assert "I-III on the first imported liver, imp-lab01" in caplog.text and "IV proc-0000, imp-lab01" in caplog.text


def test_with_several_lab_livers_the_first_listed_serves_i_to_iii():
    two = LAB[:-1] + ",{name:lab02,path:/lab/b.stl}]"
    plan = Plan(compose(["experiment=smoke", two, "geometry.cube.enabled=true"]))
    assert plan.single_geometry == "imp-lab01"
    assert plan.scenario_geometries("IV") == ["proc-0000", "proc-0001", "proc-0002", "imp-lab01", "imp-lab02",
                                              "cube"]
