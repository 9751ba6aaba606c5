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


def test_local_test_mae_splits_the_error_by_each_case_s_own_frame(tmp_path):
    """An error along one case's normal counts as n, along another case's first tangent as t1, whatever the
    source-frame axes; the cases are found by id, in any order."""
    import numpy as np
    import pandas as pd

    from benchmarks.experiment import local_test_mae

    c, s = np.cos(0.7), np.sin(0.7)
    arrays = {"case_id": np.array(["a", "b"]),
              "frame_normal": np.array([[0.0, 0.0, 1.0], [c, s, 0.0]]),
              "frame_t1": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
              "frame_t2": np.array([[0.0, 1.0, 0.0], [s, -c, 0.0]])}
    true = np.array([[0.3, -0.2, 1.0], [1.0, 2.0, -0.5]])
    err = np.array([0.4 * arrays["frame_normal"][0], 0.1 * arrays["frame_t1"][1]])  # n of a, t1 of b
    rows = pd.DataFrame({"case_id": ["b", "a"]})  # not in the arrays' order
    for k, ax in enumerate("xyz"):
        rows[f"f{ax}_true_n"] = true[[1, 0], k]
        rows[f"f{ax}_pred_n"] = (true + err)[[1, 0], k]
    rows.to_csv(tmp_path / "test_predictions.csv", index=False)
    mae = local_test_mae(tmp_path / "test_predictions.csv", arrays)
    assert np.allclose(mae, [0.05, 0.0, 0.2], atol=1e-12)
    rows.assign(case_id=["b", "z"]).to_csv(tmp_path / "other.csv", index=False)
    with pytest.raises(ValueError, match="not in the arrays"):
        local_test_mae(tmp_path / "other.csv", arrays)


def test_observation_settings_for_the_unseen_livers_are_read_and_checked():
    """--observe: the unseen livers re-observed with these observation settings; values as YAML, checked by
    ObservationConfig before any training."""
    from benchmarks.experiment_settings import parse_observation

    assert parse_observation("noise_sd_mm=1.0") == {"noise_sd_mm": 1.0}
    assert parse_observation("noise_sd_mm=[0.5, 1.0],n_points=[5000, 5000]") == {"noise_sd_mm": [0.5, 1.0],
                                                                                  "n_points": [5000, 5000]}
    for bad in ("noise_sd_mm", "noise=1.0", "noise_sd_mm=-1", "noise_sd_mm=[1.0, 0.5]"):
        with pytest.raises(SystemExit, match="--observe"):
            parse_observation(bad)
