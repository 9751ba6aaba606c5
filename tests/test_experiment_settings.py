"""benchmarks/experiment_settings.py reads its ``--settings`` into model overrides, and refuses a key the model lacks."""
from __future__ import annotations

import pytest

from benchmarks.experiment_settings import parse_setting
from liverforce.config import compose, merge_mapping, variant_model


def cloud_variant() -> dict:
    cfg = compose([])
    return variant_model(cfg["model"], next(v for v in cfg["train"]["variants"] if v["name"] == "cloud_sv"))


def test_nested_keys_and_yaml_values():
    v = cloud_variant()
    over = parse_setting("force_scaling=none,camera.grid.kernel_radius_cells=1.5,camera.observation.n_points=[500, 900]", v)
    assert over == {"force_scaling": "none",
                    "camera": {"grid": {"kernel_radius_cells": 1.5}, "observation": {"n_points": [500, 900]}}}
    merged = merge_mapping(v, over)
    assert merged["camera"]["grid"]["kernel_radius_cells"] == 1.5
    assert merged["camera"]["grid"]["fill"] == v["camera"]["grid"]["fill"]  # the rest of the group is kept
    assert parse_setting("default", v) == {}


@pytest.mark.parametrize("text", ["force_scalin=none", "camera.grid.radius=2", "force_scaling.x=1", "encoder",
                                  "camera.grid={radius: 2}", "camera=1", "camera.grid=1", "camera.grid.kernel_radius_cells=8",
                                  "force_scaling=nonee"])
def test_unknown_or_malformed_settings_are_refused(text):
    with pytest.raises(SystemExit, match="--settings"):
        parse_setting(text, cloud_variant())
