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


def test_two_imported_livers_of_one_name_are_refused_naming_the_second():
    """Both would be imp-lab01: the plan kept the first's files for both and trained scenario IV on it twice."""
    twice = LAB[:-1] + ",{name:lab01,path:/lab/b.stl,units:mm}]"
    with pytest.raises(ConfigError, match=r"config key 'geometry.imported\[1\].name': 'lab01' is already the name of "
                                          r"geometry.imported\[0\] \(/lab/liver_lps_m.stl\).*its own name"):
        compose(["experiment=smoke", twice])


@pytest.mark.parametrize("units", ["nan", "inf"])
def test_a_units_scale_that_is_no_number_is_refused_by_the_config(units):
    with pytest.raises(ConfigError, match=r"config key 'geometry.imported\[0\].units': scale must be a number > 0"):
        compose(["experiment=smoke", f"geometry.imported=[{{name:lab01,path:/lab/a.stl,units:{units}}}]"])


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


@pytest.mark.slow  # one of the default set's slowest (CI's --durations): run with -m slow
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


def test_a_modulus_given_twice_on_the_command_line_is_refused_naming_it_and_the_fix():
    with pytest.raises(ConfigError) as err:
        compose(["material=neo_hookean_from_e", "material.E_pa=14900", "material.E_mpa=0.0149"])
    msg = str(err.value)
    assert msg.startswith("config key 'material.E_pa': Young's modulus is given twice")
    assert "both on the command line" in msg
    assert "material.E_pa=14900.0 material.E_mpa=null, or material.E_pa=null material.E_mpa=0.0149" in msg


def _lab_experiment(root: Path, name: str, material: str) -> list[str]:
    """A lab's experiment file outside config/ (Hydra's search path, as a lab keeps its own), selecting the
    preset neo_hookean_from_e (E_pa: 14900) and setting ``material``; the overrides that use it."""
    (root / "experiment").mkdir(parents=True, exist_ok=True)
    (root / "experiment" / f"{name}.yaml").write_text(
        "# @package _global_\ndefaults:\n  - override /material: neo_hookean_from_e\n"
        f"experiment: {name}\nmaterial: {material}\n")
    return [f"experiment={name}", f"hydra.searchpath=[file://{root}]"]


def test_an_experiment_files_modulus_replaces_the_presets_as_the_command_lines_does(tmp_path, caplog):
    import logging

    with caplog.at_level(logging.INFO, logger="liverforce"):
        lab = compose(_lab_experiment(tmp_path, "labmat", "{E_mpa: 0.0149}"))  # refused before: 'given twice'
    by_hand = compose(["material=neo_hookean_from_e", "material.E_pa=null", "material.E_mpa=0.0149"])
    assert lab["material"] == by_hand["material"] and "E_pa" not in lab["material"]
    path = tmp_path / "experiment" / "labmat.yaml"
    assert (f"material.E_mpa=0.0149 set by the experiment experiment=labmat ({path}) replaces material.E_pa "
            "14900.0 of the preset material=neo_hookean_from_e (config/material/neo_hookean_from_e.yaml)"
            ) in caplog.text
    # the command line still wins over the experiment's file
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="liverforce"):
        mine = compose([*_lab_experiment(tmp_path, "labmat", "{E_mpa: 0.0149}"), "material.E_pa=20000"])
    assert mine["material"]["E_pa"] == 20000.0 and "E_mpa" not in mine["material"]
    assert (f"material.E_pa=20000.0 given on the command line replaces material.E_mpa 0.0149 of the experiment "
            f"experiment=labmat ({path})") in caplog.text


def test_a_value_the_experiment_changed_is_attributed_to_the_experiment_not_the_preset(tmp_path, caplog):
    import logging

    over = _lab_experiment(tmp_path, "labpa", "{E_pa: 20000.0}")  # the preset sets E_pa 14900: changed here
    with caplog.at_level(logging.INFO, logger="liverforce"):
        cfg = compose([*over, "material.E_mpa=0.0149"])
    assert cfg["material"]["E_mpa"] == 0.0149 and "E_pa" not in cfg["material"]
    path = tmp_path / "experiment" / "labpa.yaml"
    assert (f"material.E_mpa=0.0149 given on the command line replaces material.E_pa 20000.0 of the experiment "
            f"experiment=labpa ({path})") in caplog.text
    assert "of the preset" not in caplog.text


def test_a_modulus_given_twice_in_the_experiment_file_is_refused_naming_the_file_and_the_fix(tmp_path):
    over = _lab_experiment(tmp_path, "labboth", "{E_pa: 20000.0, E_mpa: 0.0149}")
    with pytest.raises(ConfigError) as err:
        compose(over)
    msg = str(err.value)
    path = tmp_path / "experiment" / "labboth.yaml"
    assert msg.startswith("config key 'material.E_pa': Young's modulus is given twice, E_pa 20000.0 (Pa) and "
                          "E_mpa 0.0149 (MPa)")
    assert f"both by the experiment experiment=labboth ({path})" in msg and "preset" not in msg
    assert (f"give it once in {path}: under material:, E_pa: null (to keep E_mpa 0.0149) or E_mpa: null "
            "(to keep E_pa 20000.0)") in msg
    # the fix it names composes (the file's E_pa: null; or the command line's unit over the file's)
    assert compose(_lab_experiment(tmp_path, "labboth", "{E_pa: null, E_mpa: 0.0149}"))["material"]["E_mpa"] == 0.0149


# ------------------------- D: what only a run needs is checked by the run, not by every compose

def test_a_one_liver_config_composes_without_the_run_check_and_check_run_refuses_it():
    from liverforce.config import check_run

    cfg = compose(["experiment=smoke", "geometry.procedural.count=1"], run=False)  # refused by every compose before
    assert cfg["geometry"]["procedural"]["count"] == 1 and "IV" in cfg["sweep"]["scenarios"]
    with pytest.raises(ConfigError, match=r"config key 'sweep.scenarios.IV'.*geometry.procedural.count=2"):
        check_run(cfg)
    with pytest.raises(ConfigError, match=r"config key 'sweep.scenarios.IV'"):
        compose(["experiment=smoke", "geometry.procedural.count=1"])  # run=True: the default, the Snakefile's
    lab = compose(["experiment=smoke", LAB, "geometry.procedural.count=0"], run=False)  # IV in train and studies
    assert lab["geometry"]["imported"][0]["name"] == "lab01"


def test_liverforce_config_prints_a_one_liver_config_with_a_note_and_run_refuses_it(monkeypatch, capsys):
    import yaml

    from liverforce import cli

    assert cli.main(["config", "-e", "smoke", "geometry.procedural.count=1"]) == 0
    out, err = capsys.readouterr()
    assert yaml.safe_load(out)["geometry"]["procedural"]["count"] == 1
    assert "note: `liverforce run` (and snakemake) would refuse this config before any job" in err
    assert "config key 'sweep.scenarios.IV'" in err
    assert cli.main(["config", "-e", "smoke"]) == 0 and "note:" not in capsys.readouterr().err

    def no_snakemake(*a, **k):
        raise AssertionError("snakemake started on a config the run refuses")

    monkeypatch.setattr(cli.subprocess, "call", no_snakemake)
    assert cli.main(["run", "-e", "smoke", "-n", "geometry.procedural.count=1"]) == 2
    assert "configuration error: config key 'sweep.scenarios.IV'" in capsys.readouterr().err


def test_bench_mesh_meshes_one_liver(monkeypatch):
    """benchmarks/bench_mesh.py --livers 1 only meshes: the run-level check does not refuse it (meshing stubbed)."""
    import importlib.util

    import liverforce.pipeline.geometry as geometry
    import liverforce.pipeline.mesh as mesh

    spec = importlib.util.spec_from_file_location("bench_mesh", ROOT / "benchmarks" / "bench_mesh.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    meshed = []

    def fake_mesh(surface, mesh_cfg, seed, *paths, **kw):
        meshed.append(Path(surface).name)
        attempt = {"edge_length_mm": 5.0, "n_nodes": 10}
        return {"meshing_time_s": 0.0, "n_nodes": 10, "quality": {"radius_ratio_min": 0.3},
                "provenance": {"meshing": {"attempts": [attempt], "route": "stub", "edge_length_mm": 5.0}}}

    monkeypatch.setattr(geometry, "make_geometry", lambda *a, **k: None)
    monkeypatch.setattr(mesh, "make_mesh", fake_mesh)
    rows = bench.pipeline_meshing("default", 1)
    assert [r["gid"] for r in rows] == ["proc-0000"] and len(meshed) == 1
