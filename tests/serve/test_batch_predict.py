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


# --------------------------------------------------------------------------- the interval of every predicted row
COMPONENTS = ("t1", "t2", "n")
HALF = [f"half_width_{c}_n" for c in COMPONENTS]
COVERED = [f"covered_{c}" for c in COMPONENTS]


def _with_interval(pred, **changes):
    """``pred``'s model with its interval's fields ``changes`` (nothing else refitted), or without an interval
    (``interval=None``)."""
    import copy
    import dataclasses

    model = copy.copy(pred.model)
    model.meta = copy.deepcopy(pred.model.meta)
    if changes.get("interval", True) is None:
        model.meta.pop("interval")
    else:
        model.meta["interval"] = dataclasses.replace(pred.model.interval, **changes).to_dict()
    return Predictor(model)


#: an interval scaled by the predicted force: sigma_j = 0.05 N + 0.1 |F|, half-width 1.5 sigma_j; its widths
#: move by 1.5 x 0.1 = 0.15 N per N of |F| (times the widening outside the calibration's stiffness range)
BY_FORCE = {"scale": "force", "force_scale": ((0.05, 0.1),) * 3, "half_width_n": (1.5, 1.5, 1.5)}


@pytest.mark.parametrize("scale", ["own", "force"])
def test_every_row_carries_the_models_interval_of_its_force(trained, shards, scale):
    """--shards' half-widths per local component are ForceModel.predict_interval's on the same rows: exactly on the
    reference path; on the compiled path those of its own forces, which an interval scaled by the force reads
    (|F| within 1e-6 N of the reference's, the test above), so within 0.15 N/N x 1e-6 N x the widening."""
    pred = Predictor.load(trained("disp"))
    assert pred.model.interval is not None and pred.model.interval.scale == "stiffness"
    pred = pred if scale == "own" else _with_interval(pred, **BY_FORCE)
    arrays = dio.load_training_arrays(sorted(shards.glob("shard-*.parquet")))
    want = pred.model.predict_interval(arrays)
    widen = float(np.max(pred.model.interval.stiffness_factor(pred.model.forward(arrays).stiffness)))
    for fast in (False, True):
        df = predict_shards(pred, [shards], None, fast=fast)["frame"]
        got = df[HALF].to_numpy()
        assert np.isfinite(got).all() and (got > 0).all()
        if not fast:
            np.testing.assert_allclose(got, want["half_width_local_n"], rtol=1e-12, atol=0)
        else:
            np.testing.assert_allclose(got, want["half_width_local_n"], rtol=0, atol=0.15 * 1e-6 * widen)
    if scale == "force":  # the widths do follow the force
        assert np.ptp(got[:, 0]) > 0.1 * np.ptp(np.linalg.norm(want["force_n"], axis=1))


def test_a_refused_row_has_no_interval(trained, shard_with_refused_rows, tmp_path):
    """The two refused rows' half-widths and coverage are missing (NaN, NA), on both paths; the other rows' are
    predict_interval's of them alone, and the file keeps the missing coverage missing."""
    pred = _with_interval(Predictor.load(trained("disp")), **BY_FORCE)
    folder, bad, clean = shard_with_refused_rows
    arrays = dio.load_training_arrays([clean])
    want = pred.model.predict_interval(arrays)["half_width_local_n"]
    widen = float(np.max(pred.model.interval.stiffness_factor(pred.model.forward(arrays).stiffness)))
    for fast in (False, True):
        out = tmp_path / f"pred-{fast}.parquet"
        predict_shards(pred, [folder], out, fast=fast)
        df = pd.read_parquet(out)
        is_bad = df["case_id"].isin(bad).to_numpy()
        assert is_bad.sum() == 2
        assert np.isnan(df[HALF].to_numpy()[is_bad]).all()
        np.testing.assert_allclose(df[HALF].to_numpy()[~is_bad], want, rtol=1e-12,
                                   atol=0 if not fast else 0.15 * 1e-6 * widen)  # as in the test above
        covered = df[COVERED]
        assert covered[is_bad].isna().all().all() and covered[~is_bad].notna().all().all()


def test_labelled_shards_say_which_rows_the_interval_covers(trained, shards, tmp_path):
    """``covered_*``: the true local component within its interval, row by row, and the summary's coverage per
    component over the rows; a narrow interval (the median residual of each component) covers some rows and
    misses others, so a wrong frame or sign would show."""
    from liverforce.learn.frames import force_to_local

    pred = Predictor.load(trained("disp"))
    arrays = dio.load_training_arrays(sorted(shards.glob("shard-*.parquet")))
    got = pred.model.predict_interval(arrays)
    true_local = force_to_local(np.asarray(arrays["force_n"], float), got["frame"])
    median = tuple(float(v) for v in np.median(np.abs(true_local - got["force_local_n"]), axis=0))
    pred = _with_interval(pred, scale="none", half_width_n=median, stiffness_range=None)
    want = np.abs(true_local - got["force_local_n"]) <= np.asarray(median)[None, :]
    assert 0.2 < want.mean() < 0.8
    for fast in (False, True):
        summary = predict_shards(pred, [shards], tmp_path / "pred.csv", fast=fast)
        df = summary["frame"]
        np.testing.assert_array_equal(df[COVERED].to_numpy(dtype=bool), want)
        cov = summary["interval_coverage"]
        assert cov["nominal"] == pred.model.interval.coverage and cov["rows"] == len(df)
        assert [cov[c] for c in COMPONENTS] == pytest.approx(list(want.mean(axis=0)), abs=1e-12)
        back = pd.read_csv(tmp_path / "pred.csv")
        np.testing.assert_array_equal(back[COVERED].to_numpy(dtype=bool), want)


def test_a_model_without_an_interval_gives_no_width(trained, shards):
    """The half-widths are NaN in every row (a sequence's rows too), no coverage is claimed, the forces are
    unchanged."""
    pred = Predictor.load(trained("disp"))
    bare = _with_interval(pred, interval=None)
    assert bare.model.interval is None
    with_ci = predict_shards(pred, [shards], None)["frame"]
    summary = predict_shards(bare, [shards], None)
    df = summary["frame"]
    assert np.isnan(df[HALF].to_numpy()).all() and not set(COVERED) & set(df.columns)
    assert summary["interval_coverage"] is None and len(df) == len(with_ci)
    np.testing.assert_array_equal(df[["fx_n", "fy_n", "fz_n"]].to_numpy(), with_ci[["fx_n", "fy_n", "fz_n"]].to_numpy())


@pytest.fixture(scope="module")
def ensemble(data, configs, tmp_path_factory):
    """The ``disp`` model's settings with a GP ensemble over two code sizes and an interval scaled by the members'
    spread (train.interval.spread), as the shipped models'."""
    from liverforce.learn.train import train_scenario

    base, train, no_tune = configs
    res = train_scenario(data, {**base, "regressor": "gp",
                                "gp": {"max_points": 2000, "iterations": 30, "code_members": [2, 4]}},
                         {**train, "interval": {**train["interval"], "scale": "force_bins", "bins": 2,
                                                "spread": 4.0}},
                         no_tune, "III", "ens", out_dir=tmp_path_factory.mktemp("serve-ens"))
    pred = Predictor.load(res["model_path"])
    assert pred.model.member_spread and pred.model.interval.uses_spread
    return pred


def test_the_interval_of_a_gp_ensemble_reads_its_members_spread(ensemble, shards):
    """Each row's width is predict_interval's, which reads the members' spread of that row (it raises without it).
    The widths are constant within each of the 2 bins of |F|, and no row's |F| is within 1e-5 N of the edge
    (checked), so the compiled path's forces (within 1e-6 N of the reference's) give the same widths too."""
    arrays = dio.load_training_arrays(sorted(shards.glob("shard-*.parquet")))
    want = ensemble.model.predict_interval(arrays)
    edge = np.asarray(ensemble.model.interval.bin_edges_n)
    assert len(edge) == 1 and np.min(np.abs(np.linalg.norm(want["force_n"], axis=1) - edge[0])) > 1e-5
    for fast in (False, True):
        got = predict_shards(ensemble, [shards], None, fast=fast)["frame"][HALF].to_numpy()
        np.testing.assert_allclose(got, want["half_width_local_n"], rtol=1e-12, atol=0)
    assert np.ptp(got[:, 2]) > 0  # the spread makes the widths differ per row


def test_an_interval_no_path_can_give_is_refused_in_words(trained, shards):
    """A bundle edited by hand: an interval scaled by the GP ensemble members' spread on an MLP. --shards says what
    is wrong with the model (a PredictionInputError, which the command prints) instead of a traceback."""
    pred = _with_interval(Predictor.load(trained("disp")), spread_beta=4.0, spread_median_n=(0.1, 0.1, 0.1))
    with pytest.raises(PredictionInputError, match=r"^model: the model's interval .* its regressor is an MLP, which "
                                                   r"has no members' spread"):
        predict_shards(pred, [shards], None)
