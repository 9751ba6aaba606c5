"""A lab's own liver held out of training and validated as an unseen liver (``validate.imported``).

A lab that brings several livers asks what a surgeon asks: does the force estimate hold on a patient the model
never saw? ``validate.imported=[<name>]`` takes an imported liver out of every training scenario and scores the
scenario-IV models on it, after the procedural unseen livers (``validate.livers`` may then be 0).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from liverforce.config import ConfigError, compose
from liverforce.pipeline.plan import VALIDATION, Plan

ROOT = Path(__file__).resolve().parents[2]
SNAKEMAKE = str(Path(sys.executable).with_name("snakemake"))
TWO = "geometry.imported=[{name:a,path:a.stl,units:mm},{name:b,path:b.stl,units:mm}]"


def _plan(*overrides: str) -> Plan:
    return Plan(compose(["experiment=smoke", *overrides]))


def test_a_held_out_liver_is_unseen_and_trains_nothing():
    plan = _plan(TWO, "validate.imported=[b]", "validate.livers=0")
    assert "imp-b" not in plan.train_geometries and "imp-a" in plan.train_geometries
    assert plan.validation_geometries == ["imp-b"]
    assert plan.single_geometry == "imp-a"
    for s in plan.scenarios:
        assert "imp-b" not in plan.scenario_geometries(s)
    assert plan.scenario_geometries(VALIDATION) == ["imp-b"]
    # validate.n_cases per unseen liver, on the held-out one too
    assert plan.scenario_spec(VALIDATION)["n_cases"] == plan.cfg["validate"]["n_cases"]
    assert plan.sweep_params(VALIDATION)["geometries"] == ["imp-b"]


def test_held_out_livers_follow_the_procedural_unseen_ones_and_the_physics_check_can_pick_one():
    plan = _plan(TWO, "validate.imported=[a]", "validate.livers=2", "validate.physics.liver=2")
    assert plan.validation_geometries == ["val-1000", "val-1001", "imp-a"]
    assert plan.scenario_spec(VALIDATION)["n_cases"] == 3 * plan.cfg["validate"]["n_cases"]
    assert plan.single_geometry == "imp-b"  # the first imported liver is held out: I-III take the next
    assert plan.geometry_spec("imp-a")["path"] == "a.stl"  # built as any imported liver


def test_without_the_key_nothing_changes():
    plan = _plan(TWO)
    assert plan.train_geometries[-2:] == ["imp-a", "imp-b"] and plan.single_geometry == "imp-a"
    assert all(g.startswith("val-") for g in plan.validation_geometries)


@pytest.mark.parametrize("overrides, key, words", [
    (["validate.imported=[c]"], "validate.imported[0]", "'c' names no liver of geometry.imported (a, b)"),
    (["validate.imported=[b,b]"], "validate.imported[1]", "'b' is listed twice"),
    (["validate.imported=[a,b]", "geometry.procedural.count=0"], "validate.imported", "no procedural liver is left"),
    (["validate.livers=0"], "validate.livers", "needs at least one unseen liver"),
    (["validate.imported=[b]", "validate.livers=0", "validate.physics.liver=1"], "validate.physics.liver",
     "0 .. 0"),
])
def test_a_wrong_held_out_list_is_refused_naming_the_key(overrides, key, words):
    with pytest.raises(ConfigError) as err:
        compose(["experiment=smoke", TWO, *overrides])
    msg = str(err.value)
    assert f"config key '{key}'" in msg and words in msg, msg


OWN = ("geometry.imported=[{name:a,path:a.stl,units:mm},{name:b,path:b.stl,units:mm,supports:{mode:add,"
       "list:[{name:cava,kind:fixed,sphere:{center_mm:[0,0,0],radius_mm:10}}]}}]")


def test_the_physics_check_takes_a_held_out_liver_with_its_own_supports():
    """It simulates that liver with its own supports (liverforce.pipeline.physics; tests/pipeline/test_physics_lab.py),
    so the config no longer refuses it."""
    plan = _plan(OWN, "validate.imported=[b]", "validate.physics.liver=2")
    assert plan.scenario_geometries(VALIDATION)[plan.cfg["validate"]["physics"]["liver"]] == "imp-b"
    _plan(OWN, "validate.imported=[b]", "validate.livers=0", "validate.physics.liver=0")  # the only unseen liver


def test_scenario_iv_counts_only_the_livers_left_to_train_on():
    with pytest.raises(ConfigError) as err:
        compose(["experiment=smoke", TWO, "geometry.procedural.count=1", "validate.imported=[a,b]"])
    msg = str(err.value)
    assert "geometry.imported: 0 livers to train on and 2 held out as unseen (validate.imported: a, b)" in msg, msg
    compose(["experiment=smoke", TWO, "geometry.procedural.count=1", "validate.imported=[b]"])  # 2 left: taken


# --------------------------------------------------------------------------- the workflow, for real

def _write_livers(tmp: Path) -> None:
    from liverforce.geometry.procedural import LiverShapeParams, procedural_liver

    for name, seed in (("a", 3), ("b", 4)):
        procedural_liver(seed, LiverShapeParams(voxel_mm=6.0)).to_trimesh().export(tmp / f"{name}.stl")


def _overrides(tmp: Path, b: str = "", physics: str = "validate.physics.enabled=false") -> str:
    """The run's overrides: liver ``b`` held out (``b``: more of its geometry.imported entry, e.g. its supports).

    Each lab liver has its own material (geometry.imported[].material): a's cases are drawn around the run's
    constants x 1.2, b's (held out) are at x 0.8 as given."""
    return (f"overrides=geometry.procedural.count=1 geometry.imported=[{{name:a,path:{tmp}/a.stl,units:mm,"
            f"material:{{scale:1.2}}}},{{name:b,path:{tmp}/b.stl,units:mm,material:{{scale:0.8}}{b}}}] "
            f"validate.imported=[b] validate.livers=0 validate.input=any "
            f"{physics} study.enabled=false train.scenarios=[IV] ~sweep.scenarios.I "
            "~sweep.scenarios.II ~sweep.scenarios.III train.variants=[{name:pca_sv,encoder:pca,state_vector:true}]")


def _snakemake(work: Path, tmp: Path, *args, overrides: str | None = None) -> subprocess.CompletedProcess:
    cmd = [SNAKEMAKE, "--snakefile", str(ROOT / "Snakefile"), "--directory", str(work), "--cores", "2", *args,
           "--config", "experiment=smoke", overrides or _overrides(tmp)]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=1500,
                          env={**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"})
    if proc.returncode != 0:
        raise AssertionError(f"{' '.join(cmd)} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return proc


def test_the_dry_run_meshes_the_held_out_liver_for_the_validation_only(tmp_path):
    _write_livers(tmp_path)
    work = tmp_path / "work"
    work.mkdir()
    text = (lambda p: p.stdout + p.stderr)(_snakemake(work, tmp_path, "-n", "validate"))
    assert "results/smoke/mesh/imp-b.vtu" in text and "results/smoke/shards/V/" in text
    assert "results/smoke/shards/II" not in text  # the run asked for IV and the validation only


def test_the_physics_job_takes_the_held_out_lab_liver(tmp_path):
    """The physics rule runs on the held-out liver with its own supports; it reads them from the features JSON the
    mesh rule writes beside that liver's mesh (as the simulate rule does), so its inputs are the default run's."""
    _write_livers(tmp_path)
    work = tmp_path / "work"
    work.mkdir()
    own = ",supports:{mode:add,list:[{name:cava,kind:fixed,sphere:{center_mm:[0,0,0],radius_mm:10}}]}"
    proc = _snakemake(work, tmp_path, "-n", "results/smoke/validate/physics.json",
                      overrides=_overrides(tmp_path, own, "validate.physics.liver=0"))
    text = proc.stdout + proc.stderr
    job = text[text.index("rule physics:"):]
    inputs = next(line for line in job.splitlines() if line.strip().startswith("input:"))
    assert "results/smoke/mesh/imp-b.vtu" in inputs and "features.json" not in inputs, inputs


@pytest.mark.slow
@pytest.mark.workflow
def test_a_held_out_lab_liver_is_scored_as_unseen_and_never_trained_on(tmp_path):
    """The smoke loop to the validation with liver b held out: its cases are the validation's, none is IV's; b has
    its own material and its own foundation, and the physics check runs on it with that foundation."""
    import pyarrow.parquet as pq

    from liverforce.pipeline.physics import LAB_BASELINE

    _write_livers(tmp_path)
    work = tmp_path / "work"
    work.mkdir()
    own = (",supports:{mode:add,list:[{name:bed,kind:foundation,region:visceral,stiffness:{total_n_per_mm:20.0},"
           "box:{min_mm:[-40,-40,-60],max_mm:[40,40,-35]}}]}")
    _snakemake(work, tmp_path, "validate", "results/smoke/validate/physics.json",
               overrides=_overrides(tmp_path, own, "validate.physics.liver=0"))
    res = work / "results" / "smoke"
    phys = json.loads((res / "validate" / "physics.json").read_text())
    assert phys["liver"] == "imp-b" and phys["variants"][0]["name"] == LAB_BASELINE
    assert [s["name"] for s in phys["own_supports"]["supports"]] == ["bed"]
    assert all(e["converged"] == e["n_cases"] for e in phys["variants"]), phys["variants"]
    val = json.loads((work / Plan(compose(["experiment=smoke"])).paths.validation_metrics()).read_text())
    assert list(val["per_liver"]) == ["imp-b"]
    assert val["livers"]["n"] == 1 and val["per_liver"]["imp-b"]["n"] >= 1
    iv = np.unique(np.concatenate([pq.read_table(p, columns=["geometry_id"]).column(0).to_numpy(zero_copy_only=False)
                                   for p in sorted((res / "shards" / "IV").glob("*.parquet"))]).astype(str))
    assert "imp-b" not in iv and {"imp-a", "proc-0000"} <= set(iv)
    # the livers' own materials: b's validation cases at the run's constants x 0.8 (not x validate.material_scale),
    # a's IV cases within +-vary_rel of x 1.2, the procedural liver's of x 1
    cfg = compose(["experiment=smoke"])
    run, r = np.array([cfg["material"]["params_mpa"][k] for k in sorted(cfg["material"]["params_mpa"])]), \
        cfg["material"]["vary_rel"]

    def constants(scenario, gid):
        t = pq.read_table(res / "sweep" / scenario / "cases.parquet").to_pylist()
        return np.array([c["material_params_mpa"] for c in t if c["geometry_id"] == gid])

    b = constants("V", "imp-b")
    assert len(b) == cfg["validate"]["n_cases"]
    np.testing.assert_allclose(b, np.tile(0.8 * run, (len(b), 1)), rtol=1e-12)
    for gid, centre in (("imp-a", 1.2), ("proc-0000", 1.0)):
        c = constants("IV", gid) / run
        assert len(c) and (c >= centre * (1 - r) - 1e-12).all() and (c <= centre * (1 + r) + 1e-12).all(), gid
