"""A lab's own liver in the config: what one liver allows (scenario IV needs two).

Config-only: every test composes the config and calls the validation or the
planner (no FE); the dry runs stop before any job.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from liverforce.config import ConfigError, compose

ROOT = Path(__file__).resolve().parents[1]
SNAKEMAKE = str(Path(sys.executable).with_name("snakemake"))
LAB = "geometry.imported=[{name:lab01,path:/lab/liver_lps_m.stl,units:m,frame:LPS}]"
ONE_LIVER = [LAB, "geometry.procedural.count=0", "train.scenarios=[II]", "study.enabled=false"]


# ------------------------------------------------- A: one liver and scenario IV

def test_one_lab_liver_with_scenario_iv_is_refused_naming_the_keys_and_the_fixes():
    with pytest.raises(ConfigError) as err:
        compose(["experiment=smoke", *ONE_LIVER])  # the audit's run: default target, IV in the sweep
    msg = str(err.value)
    assert msg.startswith("config key 'sweep.scenarios.IV':")
    assert "at least 2 training livers" in msg and "gives it 1" in msg and "imp-lab01" in msg
    assert "geometry.procedural.count=0" in msg and "geometry.imported: 1 liver" in msg
    for needs in ("validation on the unseen livers", "physics study", "report (the default target"):
        assert needs in msg
    assert "train.scenarios (which lists IV)" not in msg  # II only: IV is asked for by the validation
    # the fixes that work: one procedural liver beside the lab's, or IV left out and the models target
    assert "geometry.procedural.count=1 (beside the 1 imported liver)" in msg
    assert "a second entry in geometry.imported" in msg
    assert "train.scenarios=[II] ~sweep.scenarios.IV" in msg and "snakemake --cores 2 models" in msg


def test_each_fix_the_refusal_names_composes():
    compose(["experiment=smoke", *ONE_LIVER, "geometry.procedural.count=1"])
    cfg = compose(["experiment=smoke", *ONE_LIVER, "~sweep.scenarios.IV"])
    assert list(cfg["sweep"]["scenarios"]) == ["I", "II", "III"]
    two_labs = LAB[:-1] + ",{name:lab02,path:/lab/b.stl}]"
    compose(["experiment=smoke", *ONE_LIVER[1:], two_labs])


def test_iv_in_train_scenarios_and_the_studies_are_named_with_their_fix():
    with pytest.raises(ConfigError) as err:
        compose(["experiment=smoke", LAB, "geometry.procedural.count=0"])
    msg = str(err.value)
    assert "train.scenarios (which lists IV)" in msg
    assert "train.scenarios=[I,II,III] ~sweep.scenarios.IV study.enabled=false" in msg
    cfg = compose(["experiment=smoke", LAB, "geometry.procedural.count=0", "train.scenarios=[I,II,III]",
                   "~sweep.scenarios.IV", "study.enabled=false"])
    assert cfg["train"]["scenarios"] == ["I", "II", "III"]


def test_one_procedural_liver_or_iv_on_one_liver_is_refused():
    with pytest.raises(ConfigError, match=r"geometry.procedural.count=2 or a second entry"):
        compose(["experiment=smoke", "geometry.procedural.count=1"])
    with pytest.raises(ConfigError, match=r"config key 'sweep.scenarios.IV.geometries'.*geometries=all"):
        compose(["experiment=smoke", "sweep.scenarios.IV.geometries=1"])


def test_the_split_hint_counts_the_imported_livers():
    from liverforce.learn.splits import train_test_split

    with pytest.raises(ValueError) as err:
        train_test_split(np.array(["imp-lab01"] * 6), scenario="IV", test_fraction=0.2, seed=0)
    assert "geometry.procedural.count >= 1 beside the 1 imported liver" in str(err.value)
    with pytest.raises(ValueError, match=r"geometry.procedural.count >= 2, or a second entry"):
        train_test_split(np.array(["proc-0000"] * 6), scenario="IV", test_fraction=0.2, seed=0)


def _dry_run(work: Path, target: list[str], overrides: list[str]) -> subprocess.CompletedProcess:
    cmd = [SNAKEMAKE, "-n", *target, "--snakefile", str(ROOT / "Snakefile"), "--directory", str(work),
           "--cores", "1", "--config", "experiment=smoke", "overrides=" + " ".join(overrides)]
    return subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})


def test_snakemake_refuses_one_liver_before_any_job_and_runs_the_named_target(tmp_path):
    (tmp_path / "liver.stl").write_text("")  # an input of the geometry rule: it must exist, even for -n
    lab = LAB.replace("/lab/liver_lps_m.stl", str(tmp_path / "liver.stl"))
    one = [lab, *ONE_LIVER[1:]]
    proc = _dry_run(tmp_path, [], one)
    text = proc.stdout + proc.stderr
    assert proc.returncode != 0 and "Job stats" not in text
    assert "config key 'sweep.scenarios.IV'" in text and "geometry.procedural.count=1" in text
    # the subset the refusal names: its target runs II alone, on the lab's liver
    proc = _dry_run(tmp_path, ["models"], [*one, "~sweep.scenarios.IV"])
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "scenario=IV" not in proc.stdout and "scenario=II" in proc.stdout


# ------------------------------------- C: Young's modulus in MPa over the preset's Pa

def test_an_override_in_mpa_replaces_the_presets_pa_with_a_note(caplog):
    import logging

    with caplog.at_level(logging.INFO, logger="liverforce"):
        mine = compose(["material=neo_hookean_from_e", "material.E_mpa=0.0149"])  # the audit's: refused before
    explicit = compose(["material=neo_hookean_from_e", "material.E_pa=null", "material.E_mpa=0.0149"])
    assert mine == explicit  # the same config, so the same slices and no re-run between the two spellings
    assert mine["material"]["E_mpa"] == 0.0149 and "E_pa" not in mine["material"]
    assert mine["material"]["params_mpa"] == compose(["material=neo_hookean_from_e"])["material"]["params_mpa"]
    assert ("material.E_mpa=0.0149 given on the command line replaces material.E_pa 14900.0 of the preset "
            "material=neo_hookean_from_e (config/material/neo_hookean_from_e.yaml)") in caplog.text


def test_a_modulus_given_twice_is_refused_naming_where_each_came_from_and_the_fix():
    from liverforce.config import _young_given_once

    with pytest.raises(ConfigError) as err:
        compose(["material=neo_hookean_from_e", "material.E_pa=14900", "material.E_mpa=0.0149"])
    msg = str(err.value)
    assert msg.startswith("config key 'material.E_pa': Young's modulus is given twice")
    assert "both on the command line" in msg
    assert "material.E_pa=14900.0 material.E_mpa=null, or material.E_pa=null material.E_mpa=0.0149" in msg
    # both from config files (an experiment setting E_mpa over the preset's E_pa): each file named
    mat = {"E_pa": 14900.0, "E_mpa": 0.0149}
    with pytest.raises(ConfigError) as err:
        _young_given_once(mat, {"overridden": {}, "choices": {"material": "neo_hookean_from_e",
                                                              "experiment": "lab"}})
    msg = str(err.value)
    assert "E_pa 14900.0 by the preset material=neo_hookean_from_e (config/material/neo_hookean_from_e.yaml)" in msg
    assert "E_mpa 0.0149 by the experiment experiment=lab (config/experiment/lab.yaml)" in msg
