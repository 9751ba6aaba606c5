"""Batch prediction of whole shards / datasets to Parquet or CSV (atomic), equal to the reference path."""
from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from liverforce.dataset import io as dio
from liverforce.serve import PredictionInputError, Predictor
from liverforce.serve.batch import predict_shards


@pytest.fixture(scope="module")
def shards(test_cases, tmp_path_factory, make_shard_rows):
    shard_rows = make_shard_rows
    d = tmp_path_factory.mktemp("shards")
    n = len(test_cases["case_id"])
    a = shard_rows(test_cases, range(n // 2)) + shard_rows(test_cases, [0], converged=False, suffix="-failed")
    # shard 2: three cases pushed with 3 force levels each (shared contexts -> the compiled path)
    b = shard_rows(test_cases, range(n // 2, n))
    for s in (0.5, 0.8):
        b += shard_rows(test_cases, range(n // 2, n // 2 + 3), scale=s, suffix=f"-x{s}")
    paths = [d / "shard-0000.parquet", d / "shard-0001.parquet"]
    dio.write_shard(a, paths[0])
    dio.write_shard(b, paths[1])
    dio.write_manifest(paths, d / "manifest.json")
    return d


@pytest.mark.parametrize("fmt", ["parquet", "csv"])
def test_predict_a_dataset_to_parquet_or_csv(trained, shards, tmp_path, fmt):
    pred = Predictor.load(trained("disp"))
    out = tmp_path / "out" / f"pred.{fmt}"
    summary = predict_shards(pred, [shards / "manifest.json"], out)
    arrays = dio.load_training_arrays(sorted(shards.glob("shard-*.parquet")))
    ref = pred.model.predict(arrays)
    df = pd.read_parquet(out) if fmt == "parquet" else pd.read_csv(out)
    assert summary["rows"] == len(df) == len(ref) and summary["skipped_failed"] == 1
    assert list(df["case_id"]) == [str(c) for c in arrays["case_id"]]
    np.testing.assert_allclose(df[["fx_n", "fy_n", "fz_n"]].to_numpy(), ref, atol=1e-6)
    np.testing.assert_allclose(df[["fx_true_n", "fy_true_n", "fz_true_n"]].to_numpy(), arrays["force_n"], atol=1e-6)
    assert summary["metrics"]["mae_vec"] == pytest.approx(df["error_n"].mean(), rel=1e-6)
    assert [p.name for p in out.parent.iterdir()] == [out.name]  # no temporary files left behind
    # the reference path (no grouping) gives the same numbers
    ref_summary = predict_shards(pred, [shards], None, fast=False)
    np.testing.assert_allclose(ref_summary["frame"][["fx_n", "fy_n", "fz_n"]].to_numpy(), ref, atol=1e-12)


def test_cases_outside_the_training_range_carry_their_warning(trained, test_cases, tmp_path, make_shard_rows):
    """A shard whose tissue under the tool is thinner than in every training case: each row's warnings name it;
    with the thickness in the middle of the training range, none mentions it."""
    pred = Predictor.load(trained("disp"))
    n = len(test_cases["case_id"])
    thin = {**test_cases, "tool_thickness_mm": np.full(n, 0.7 * pred.scale.thickness_mm[0])}
    dio.write_shard(make_shard_rows(thin, range(n)), tmp_path / "thin.parquet")
    df = predict_shards(pred, [tmp_path / "thin.parquet"])["frame"]
    assert len(df) == n and all("thinner than in every training case" in w for w in df["warnings"])
    mid = {**test_cases, "tool_thickness_mm": np.full(n, np.mean(pred.scale.thickness_mm))}
    dio.write_shard(make_shard_rows(mid, range(n)), tmp_path / "mid.parquet")
    df = predict_shards(pred, [tmp_path / "mid.parquet"])["frame"]
    assert not any("tissue under the tool" in w for w in df["warnings"])


def test_forces_beyond_the_training_forces_carry_their_warning(trained, shards):
    """--shards' rows (the compiled node path and the reference alike): a predicted |F| above the model's largest
    training force is warned about, by both magnitudes; at or below it, not."""
    import copy

    pred = Predictor.load(trained("disp"))
    model = copy.copy(pred.model)
    model.meta = copy.deepcopy(pred.model.meta)
    for fast in (True, False):
        df = predict_shards(pred, [shards], None, fast=fast)["frame"]
        mag = np.linalg.norm(df[["fx_n", "fy_n", "fz_n"]].to_numpy(), axis=1)
        cap = float(np.median(mag))
        model.meta["training_scale"]["force_magnitude_n"][1] = cap
        capped = predict_shards(Predictor(model), [shards], None, fast=fast)["frame"]
        warned = np.array(["the predicted force" in w for w in capped["warnings"]])
        assert warned.any() and not warned.all()
        np.testing.assert_array_equal(warned, mag > cap)
        assert not any("the predicted force" in w for w in df["warnings"][mag <= pred.scale.force_max_n])
        k = int(np.flatnonzero(warned)[0])
        assert f"({mag[k]:.4g} N) exceeds every training case's (at most {cap:.4g} N)" in capped["warnings"][k]
        assert "the ROI nodes" in capped["warnings"][k] and "tool tip" not in capped["warnings"][k]


def test_bad_shards_are_refused(trained, shards, tmp_path):
    pred = Predictor.load(trained("disp"))
    with pytest.raises(PredictionInputError, match="no such shard"):
        predict_shards(pred, [tmp_path / "missing.parquet"])
    with pytest.raises(PredictionInputError, match="no Parquet shards"):
        predict_shards(pred, [tmp_path])
    bad = tmp_path / "m"
    bad.mkdir()
    man = json.loads((shards / "manifest.json").read_text())
    man["shards"][0]["sha256"] = "0" * 64
    (shards / "manifest-bad.json").write_text(json.dumps(man))
    with pytest.raises(PredictionInputError, match="does not match the manifest"):
        predict_shards(pred, [shards / "manifest-bad.json"])
    with pytest.raises(PredictionInputError, match=r"\.parquet or \.csv"):
        predict_shards(pred, [shards / "shard-0000.parquet"], tmp_path / "x.xlsx")
