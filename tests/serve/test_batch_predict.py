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


@pytest.fixture(scope="module")
def shard_with_refused_rows(test_cases, tmp_path_factory, make_shard_rows):
    """A shard of the held-out cases, two of them pushed at two more force levels (shared contexts: the compiled
    path), and two rows the serving checks refuse: case 1 pushed 60x too far (in a compiled group) and case 4's
    exertion point 10 mm off its surface. Returns the folder, the refused case ids and the shard without them."""
    n = len(test_cases["case_id"])
    rows = make_shard_rows(test_cases, range(n))
    for s in (0.5, 0.8):
        rows += make_shard_rows(test_cases, [1, 2], scale=s, suffix=f"-x{s}")
    rows += make_shard_rows(test_cases, [1], scale=60.0, suffix="-x60")
    off = rows[4]
    off["exertion_point_mm"] = np.asarray(off["exertion_point_mm"]) + 10.0 * np.asarray(off["frame_normal"])
    d = tmp_path_factory.mktemp("refused")
    dio.write_shard(rows, d / "shard-0000.parquet")
    bad = [rows[4]["case_id"], rows[-1]["case_id"]]
    dio.write_shard([r for r in rows if r["case_id"] not in bad], d.parent / "clean.parquet")
    return d, bad, d.parent / "clean.parquet"


def test_a_refused_case_does_not_stop_the_batch(trained, shard_with_refused_rows, tmp_path):
    """Two refused rows among the held-out cases: NaN forces and their reason in `refused` (the words
    predict_arrays raises for that row alone), the others predicted as without them, on the compiled and the
    reference path alike; the summary counts them and the metrics are the predicted rows'."""
    from liverforce.learn.metrics import force_metrics
    from liverforce.learn.model import subset

    pred = Predictor.load(trained("disp"))
    folder, bad, clean = shard_with_refused_rows
    arrays = dio.load_training_arrays([folder / "shard-0000.parquet"])
    ids = [str(c) for c in arrays["case_id"]]
    want = {}
    for c in bad:
        with pytest.raises(PredictionInputError) as exc:
            pred.predict_arrays(subset(arrays, [ids.index(c)]))
        want[c] = str(exc.value)
    assert want[bad[0]].startswith(f"case {bad[0]}: the exertion point is 10")
    assert want[bad[1]].startswith(f"case {bad[1]}: the ROI moved by up to")
    with pytest.raises(PredictionInputError) as first:  # predict_arrays still raises by default: the first refused
        pred.predict_arrays(arrays)
    assert str(first.value) == want[min(bad, key=ids.index)]
    frames = {}
    for fast in (True, False):
        out = tmp_path / f"pred-{fast}.parquet"
        summary = predict_shards(pred, [folder], out, fast=fast)
        df = pd.read_parquet(out)
        frames[fast] = df
        assert summary["rows"] == len(df) == len(ids) and summary["refused"] == 2
        assert summary["predicted"] == len(ids) - 2
        refused = df.set_index("case_id")["refused"]
        assert refused[bad[0]] == want[bad[0]] and refused[bad[1]] == want[bad[1]]
        assert (refused.drop(bad) == "").all()
        is_bad = df["case_id"].isin(bad).to_numpy()
        F = df[["fx_n", "fy_n", "fz_n"]].to_numpy()
        assert np.isnan(F[is_bad]).all() and np.isfinite(F[~is_bad]).all()
        assert np.isnan(df["error_n"].to_numpy()[is_bad]).all() and (df["warnings"][is_bad] == "").all()
        ok = predict_shards(pred, [clean], None, fast=fast)["frame"]
        assert list(ok["case_id"]) == list(df["case_id"][~is_bad])
        np.testing.assert_allclose(F[~is_bad], ok[["fx_n", "fy_n", "fz_n"]].to_numpy(), atol=1e-12)
        assert list(df["warnings"][~is_bad]) == list(ok["warnings"])
        true = df[["fx_true_n", "fy_true_n", "fz_true_n"]].to_numpy()
        assert summary["metrics"] == pytest.approx(force_metrics(true[~is_bad], F[~is_bad]))
    # the compiled and the reference path: the same rows refused in the same words, the same forces
    assert list(frames[True]["refused"]) == list(frames[False]["refused"])
    np.testing.assert_allclose(frames[True][["fx_n", "fy_n", "fz_n"]].to_numpy(),
                               frames[False][["fx_n", "fy_n", "fz_n"]].to_numpy(), atol=1e-6)


def test_predict_arrays_opts_in_to_refused_rows(trained, shard_with_refused_rows):
    """``return_refused``: the reasons come last, after the warnings; a batch of refused rows only is all NaN."""
    from liverforce.learn.model import subset

    pred = Predictor.load(trained("disp"))
    folder, bad, _ = shard_with_refused_rows
    arrays = dio.load_training_arrays([folder / "shard-0000.parquet"])
    force, refused = pred.predict_arrays(arrays, return_refused=True)
    force_w, warned, refused_w = pred.predict_arrays(arrays, return_warnings=True, return_refused=True)
    assert refused == refused_w and sum(bool(r) for r in refused) == 2 and len(warned) == len(refused)
    np.testing.assert_array_equal(force, force_w)
    rows = [i for i, c in enumerate(arrays["case_id"]) if str(c) in bad]
    got, why = pred.predict_arrays(subset(arrays, rows), return_refused=True, fast=True)
    assert np.isnan(got).all() and why == [refused[i] for i in rows]
