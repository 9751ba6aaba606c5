"""Bad config values are refused before any work, naming the key.

Negative force range, ROI fraction 0 or > 1, unknown material, unstable
material constants, zero cases. Range errors are refused when the config is
composed; Drucker-unstable constants are refused by the workflow's start-up
check (``workflow/rules/common.smk``) before any job — the sweep would refuse
them only after geometry and meshing.
"""
from __future__ import annotations

import pytest

from liverforce.config import ConfigError, compose
from test_workflow import snakemake

BAD = [
    ("sweep.force.min_n=-1", "sweep.force.min_n"),
    ("sweep.force.max_n=-2", "sweep.force.max_n"),
    ("dataset.roi_fraction=0", "dataset.roi_fraction"),
    ("dataset.roi_fraction=1.01", "dataset.roi_fraction"),
    ("dataset.roi_fraction=-0.2", "dataset.roi_fraction"),
    ("material.model=rubber", "material.model"),
    ("sweep.scenarios.II.n_cases=0", "sweep.scenarios.II.n_cases"),
    ("validate.n_cases=0", "validate.n_cases"),
]

UNSTABLE = [
    ("material=mooney_rivlin_study", "material.params_mpa"),  # the study's printed MR5 constants
    ("material.params_mpa.C10=-0.01", "material.params_mpa"),  # negative initial shear modulus
]


@pytest.mark.parametrize("override, key", BAD)
def test_bad_value_is_refused_when_composed(override, key, fault_ledger):
    with fault_ledger.check(f"bad config {override}"):
        with pytest.raises(ConfigError) as err:
            compose(["experiment=smoke", override])
        assert f"'{key}'" in str(err.value)


@pytest.mark.workflow
@pytest.mark.parametrize("override, key", [*UNSTABLE, BAD[0], BAD[6]])
def test_workflow_refuses_before_any_job(override, key, tmp_path, fault_ledger):
    with fault_ledger.check(f"bad config {override} (workflow)"):
        proc = snakemake("-n", "--directory", str(tmp_path), "--config", "experiment=smoke",
                         f"overrides={override}", check=False)
        text = proc.stdout + proc.stderr
        assert proc.returncode != 0
        assert f"config key '{key}'" in text, text[-2000:]
        assert "Job stats" not in text and "rule geometry" not in text  # no job was planned
        assert not (tmp_path / "results").exists()


def test_stable_defaults_still_pass_the_start_up_check(tmp_path):
    proc = snakemake("-n", "--directory", str(tmp_path), "--config", "experiment=smoke")
    assert "Job stats" in proc.stdout
