"""Bad input is refused with a PredictionInputError naming the problem — never a silent wrong force."""
from __future__ import annotations

import json
import re
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from liverforce.serve import PredictionInputError, Predictor, Preop


@pytest.fixture(scope="module")
def pred(trained):
    return Predictor.load(trained("disp"))


@pytest.fixture(scope="module")
def case(test_cases):
    return Preop.from_arrays(test_cases, 0), np.asarray(test_cases["roi_deformed_mm"][0])


def scaled(ctx: Preop, D: np.ndarray, s: float) -> tuple[Preop, np.ndarray]:
    """Every length times ``s`` (a liver in the wrong units); inertia scales with s^5."""
    return (replace(ctx, exertion_point_mm=ctx.exertion_point_mm * s, roi_undeformed_mm=ctx.roi_undeformed_mm * s,
                    liver_centroid_mm=ctx.liver_centroid_mm * s, inertia_mm5=ctx.inertia_mm5 * s**5,
                    tool_thickness_mm=ctx.tool_thickness_mm * s), D * s)


def test_the_good_case_passes(pred, case, test_cases):
    ctx, D = case
    # through the context and every check: the model's force for the case as the shard holds it
    np.testing.assert_array_equal(pred.predict(D, ctx), pred.model.predict({k: v[:1] for k, v in test_cases.items()})[0])


@pytest.mark.parametrize("bad, msg", [
    (lambda D: D[:, :2], r"expected an \(n, 3\) array"),
    (lambda D: D.ravel(), r"expected an \(n, 3\) array"),
    (lambda D: D[:-1], "points but the context's ROI has"),
    (lambda D: np.zeros((0, 3)), "points but the context's ROI has|empty"),
    (lambda D: [["a", "b", "c"]], "not a numeric array"),
])
def test_wrong_shape(pred, case, bad, msg):
    ctx, D = case
    with pytest.raises(PredictionInputError, match=msg):
        pred.predict(bad(D.copy()), ctx)


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_nan_and_inf(pred, case, value):
    ctx, D = case
    D = D.copy()
    D[7, 1] = value
    with pytest.raises(PredictionInputError, match="1 of .* points contain NaN or inf \\(first at row 7\\)"):
        pred.predict(D, ctx)
    with pytest.raises(PredictionInputError, match="exertion_point_mm: contains NaN or inf"):
        Preop(np.array([0.0, value, 0.0]), ctx.frame, ctx.roi_undeformed_mm)


def test_empty_cloud(pred, case):
    ctx, _ = case
    with pytest.raises(PredictionInputError, match="cloud: 0 points.*the cloud is empty"):
        pred.predict_cloud(np.zeros((0, 3)), ctx, approximate=True)


def test_too_few_points_in_the_roi(pred, case):
    ctx, D = case
    small = replace(ctx, roi_undeformed_mm=ctx.roi_undeformed_mm[:6], roi_triangles=None)  # (this model reads none)
    with pytest.raises(PredictionInputError, match="roi_undeformed_mm: 6 points; at least 10 are needed"):
        pred.predict(D[:6], small)
    # enough nodes, but all within 2 mm of the tool: far smaller than the model's grid
    r = np.linalg.norm(ctx.roi_undeformed_mm - ctx.exertion_point_mm, axis=1)
    near = np.argsort(r)[:12]
    tiny = replace(ctx, roi_undeformed_mm=ctx.roi_undeformed_mm[near], roi_triangles=None)
    with pytest.raises(PredictionInputError, match="reaches only .* smaller than the model's grid"):
        pred.predict(D[near], tiny)
    # an unordered cloud with only a handful of points on the ROI
    with pytest.raises(PredictionInputError, match="only 5 of 5 points lie on the ROI footprint"):
        pred.predict_cloud(D[:5], ctx, approximate=True)


@pytest.mark.parametrize("s, msg", [
    (10.0, "times|x the model's grid"),        # cm read as mm... (liver 10x too big)
    (0.1, "smaller than the model's grid"),   # mm read as cm
    (1000.0, "x the model's grid"),           # m <-> mm
    (0.001, "smaller than the model's grid"),
    (0.03, "smaller than the model's grid"),  # a liver 6 mm across
    (30.0, "x the model's grid"),             # a liver 6 m across
])
def test_units_off_by_10_or_1000(pred, case, s, msg):
    ctx, D = case
    c2, D2 = scaled(ctx, D, s)
    with pytest.raises(PredictionInputError, match=msg) as exc:
        pred.predict(D2, c2)
    assert "mm" in str(exc.value)


def test_units_of_the_liver_features_and_material(pred, case):
    ctx, D = case
    with pytest.raises(PredictionInputError, match=r"size \(tr\(I\)/2\)\^\(1/5\).*in mm \(mm\^5\)"):
        pred.predict(D, replace(ctx, inertia_mm5=ctx.inertia_mm5 * 1e5))  # inertia of a liver in cm, as mm
    with pytest.raises(PredictionInputError, match="from the liver centroid"):
        pred.predict(D, replace(ctx, liver_centroid_mm=ctx.liver_centroid_mm * 1000 + 1e4))
    for factor in (1e3, 1e6, 1e-3):  # kPa, Pa, GPa read as MPa
        with pytest.raises(PredictionInputError, match="material_params_mpa\\[0\\].*must be in MPa"):
            pred.predict(D, ctx.with_material(ctx.material_params_mpa * factor))
    with pytest.raises(PredictionInputError, match="trained with 2 material constants"):
        pred.predict(D, ctx.with_material([0.0016, 0.0125, 0.005]))


def test_deformed_cloud_in_other_units_than_the_context(pred, case):
    ctx, D = case
    # deformed points in cm (x0.1) against an undeformed ROI in mm: huge apparent displacement
    with pytest.raises(PredictionInputError, match="moved by up to .* same units"):
        pred.predict(D * 0.1, ctx)


def test_exertion_point_off_the_surface(pred, case, test_cases):
    ctx, D = case
    n = ctx.frame[2]
    ok = replace(ctx, exertion_point_mm=ctx.exertion_point_mm + 0.5 * n)
    shifted = {k: np.asarray(v[:1]) if not isinstance(v, list) else v[:1] for k, v in test_cases.items()}
    shifted["exertion_point_mm"] = shifted["exertion_point_mm"] + 0.5 * n
    np.testing.assert_array_equal(pred.predict(D, ok), pred.model.predict(shifted)[0])  # within the 2 mm tolerance
    for off in (10.0, -6.0):
        bad = replace(ctx, exertion_point_mm=ctx.exertion_point_mm + off * n)
        with pytest.raises(PredictionInputError, match="mm off the undeformed surface") as exc:
            pred.predict(D, bad)
        # measured to the ROI's triangles (the context has them): the curved ROI lies a little nearer than along n
        d = float(re.search(r"is ([\d.]+) mm off", str(exc.value)).group(1))
        assert 0.9 * abs(off) <= d <= abs(off) + 0.5
    side = replace(ctx, exertion_point_mm=ctx.exertion_point_mm + 80.0 * ctx.frame[0])
    with pytest.raises(PredictionInputError, match="not inside its ROI|x the model's grid"):
        pred.predict(D, side)


def test_frame_not_orthonormal(pred, case):
    ctx, D = case
    bad = replace(ctx, frame=ctx.frame * np.array([[1.0], [1.3], [1.0]]))
    with pytest.raises(PredictionInputError, match="not orthonormal"):
        pred.predict(D, bad)


def test_model_of_another_format_version(trained, tmp_path):
    path = Path(shutil.copytree(trained("disp"), tmp_path / "m"))
    doc = json.loads((path / "model.json").read_text())
    doc["format_version"] = 999
    (path / "model.json").write_text(json.dumps(doc))
    with pytest.raises(PredictionInputError, match="format version 999 is not supported"):
        Predictor.load(path)


class _Evil:
    def __reduce__(self):  # would create a file if unpickled
        return (Path.touch, (Path(_Evil.marker),))


def test_model_weights_never_unpickle_code(trained, tmp_path):
    path = Path(shutil.copytree(trained("disp"), tmp_path / "m"))
    _Evil.marker = str(tmp_path / "PWNED")
    torch.save({"0.weight": _Evil()}, path / "regressor.pt")
    with pytest.raises(PredictionInputError, match="unreadable bundle.*UnpicklingError"):
        Predictor.load(path)
    assert not (tmp_path / "PWNED").exists()


def test_shard_of_another_schema_version(tmp_path, pred):
    import pandas as pd

    from liverforce.serve.batch import predict_shards

    p = tmp_path / "shard-0000.parquet"
    pd.DataFrame({"case_id": ["x"], "converged": [True]}).to_parquet(p)  # no liverforce schema metadata
    with pytest.raises(PredictionInputError, match="schema version"):
        predict_shards(pred, [p])


def test_bundles_without_a_training_scale_fall_back_to_the_scalers(trained, case, tmp_path, test_cases):
    path = Path(shutil.copytree(trained("disp"), tmp_path / "old"))
    doc = json.loads((path / "model.json").read_text())
    del doc["meta"]["training_scale"]
    (path / "model.json").write_text(json.dumps(doc))
    pred = Predictor.load(path)
    assert pred.scale.source.startswith("approximate")
    ctx, D = case
    np.testing.assert_array_equal(pred.predict(D, ctx), pred.model.predict({k: v[:1] for k, v in test_cases.items()})[0])
    for s in (10.0, 0.001):
        with pytest.raises(PredictionInputError, match="mm"):
            pred.predict(*scaled(ctx, D, s)[::-1])
    with pytest.raises(PredictionInputError, match="must be in MPa"):
        pred.predict(D, ctx.with_material(ctx.material_params_mpa * 1e3))
    with pytest.raises(PredictionInputError, match=r"in mm \(mm\^5\)"):
        pred.predict(D, replace(ctx, inertia_mm5=ctx.inertia_mm5 * 1e5))
    # the scalers' rough ranges refuse units, but do not claim what "every training case" was: no warnings
    assert pred.context_warnings(replace(ctx, tool_thickness_mm=0.1 * ctx.tool_thickness_mm)) == []
    assert pred.context_warnings(replace(ctx, inertia_mm5=ctx.inertia_mm5 * 2.0)) == []


def test_tissue_thickness_in_the_wrong_units_or_missing_is_refused(pred, case):
    ctx, D = case
    with pytest.raises(PredictionInputError, match="tool_thickness_mm .* is far outside the training range"):
        pred.predict(D, replace(ctx, tool_thickness_mm=ctx.tool_thickness_mm * 1000))  # 1000x too thick: micrometres given as mm
    with pytest.raises(PredictionInputError, match="tool_thickness_mm"):
        pred.predict(D, replace(ctx, tool_thickness_mm=None))
    np.testing.assert_array_equal(pred.predict(D, ctx), pred.predict(D, replace(ctx)))  # the good one passes


def test_a_state_outside_the_training_range_is_named_row_by_row():
    """outside_training flags each geometric input below or above its training range (bounds inclusive), with
    the value, the range and the direction in words; rows inside every range get no warning."""
    from liverforce.serve.checks import TrainingScale, outside_training

    scale = TrainingScale(half_width_mm=20.0, inertia_length_mm=(80.0, 100.0), centroid_distance_mm=(40.0, 140.0),
                          material_lo=None, material_hi=None, feature_abs_max=None, n_material=None,
                          source="bundle meta training_scale",
                          thickness_mm=(13.0, 170.0), compliance_trace=(11.0, 27.0))

    def rows(thick, trace, length, dist):
        n = len(thick)
        inertia = np.zeros((n, 9))
        inertia[:, [0, 4, 8]] = (2.0 * np.asarray(length) ** 5 / 3.0)[:, None]  # (tr I / 2)^(1/5) = length
        comp = np.zeros((n, 9))
        comp[:, [0, 4, 8]] = (np.asarray(trace) / 3.0)[:, None]
        p = np.zeros((n, 3))
        return {"exertion_point_mm": p, "tool_thickness_mm": np.asarray(thick, float), "probe_compliance_mm_per_n": comp,
                "inertia_mm5": inertia, "liver_centroid_mm": p + np.asarray(dist, float)[:, None] * [0.0, 0.6, 0.8]}

    a = rows([13.0, 10.4, 170.0, 50.0, 60.0], [11.0, 20.0, 30.0, 20.0, 20.0], [80.0, 90.0, 90.0, 101.0, 90.0],
             [140.0, 60.0, 60.0, 60.0, 30.0])
    masks, warn = outside_training(a, scale)
    assert masks["tool_thickness_mm"].tolist() == [False, True, False, False, False]
    assert masks["probe_compliance_mm_per_n"].tolist() == [False, False, True, False, False]
    assert masks["liver_size_mm"].tolist() == [False, False, False, True, False]
    assert masks["centroid_distance_mm"].tolist() == [False, False, False, False, True]
    assert warn[0] == []  # every value on a bound of its range
    assert len(warn[1]) == 1 and "10.4 mm, thinner than in every training case (13..170 mm)" in warn[1][0]
    assert len(warn[2]) == 1 and "30 mm/N, softer" in warn[2][0]
    assert len(warn[3]) == 1 and "liver's size" in warn[3][0] and "larger" in warn[3][0]
    assert len(warn[4]) == 1 and "30 mm, nearer" in warn[4][0]
    # an unknown range (an old bundle) is not checked
    masks, warn = outside_training(a, replace(scale, thickness_mm=None))
    assert "tool_thickness_mm" not in masks and warn[1] == []
    # rough ranges from the fitted scalers (a bundle without training_scale) flag nothing
    assert outside_training(a, replace(scale, source="approximate: fitted scalers")) == ({}, [[]] * 5)


def test_a_force_beyond_the_training_forces_is_warned_only_where_recorded():
    """force_warnings: a warning on each row whose |F| exceeds the recorded largest training force (at it, below
    it and a refused row's NaN: none); none at all for a bundle that recorded no training forces, or whose ranges
    come from the scalers; the advice names a camera model's inputs or a node model's."""
    from liverforce.serve.checks import TrainingScale, force_warnings

    scale = TrainingScale(half_width_mm=20.0, inertia_length_mm=None, centroid_distance_mm=None, material_lo=None,
                          material_hi=None, feature_abs_max=None, n_material=None,
                          source="bundle meta training_scale", force_max_n=5.0)
    F = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 5.2], [np.nan] * 3, [4.0, 0.0, 0.0], [0.0, 6.0, 8.0]])
    got = force_warnings(F, scale)
    assert [bool(w) for w in got] == [False, True, False, False, True]
    assert got[1][0].startswith("the predicted force (5.2 N) exceeds every training case's (at most 5 N)")
    assert "(10 N)" in got[4][0] and "the tool tip and the registration" in got[4][0]
    assert "the ROI nodes" in force_warnings(F, scale, camera=False)[1][0]
    assert force_warnings(F, replace(scale, force_max_n=None)) == [[]] * 5
    assert force_warnings(F, replace(scale, source="approximate: fitted scalers")) == [[]] * 5


def test_a_context_inside_every_training_range_gets_no_warning(pred, test_cases, mid_range):
    """Every held-out case moved into the middle of every training range is served without a context warning
    (no false alarm); moved onto a bound (bounds inclusive) too."""
    rec = pred.model.meta["training_scale"]
    for i in range(len(test_cases["case_id"])):
        assert pred.context_warnings(mid_range(Preop.from_arrays(test_cases, i), rec)) == []
    ctx = mid_range(Preop.from_arrays(test_cases, 0), rec)
    for t in rec["tool_thickness_mm"]:
        assert pred.context_warnings(replace(ctx, tool_thickness_mm=t)) == []


def test_the_context_warns_when_the_tissue_is_thinner_than_in_training(pred, case):
    """Thinner than every training case but within the refusal factor: predicted, with the warning (the
    correspondence model's context, as `liverforce predict` prints it)."""
    ctx, D = case
    lo, hi = pred.scale.thickness_mm
    inside = [w for w in pred.context_warnings(replace(ctx, tool_thickness_mm=0.5 * (lo + hi)))
              if "tissue under the tool" in w]
    assert inside == []
    thin = replace(ctx, tool_thickness_mm=0.8 * lo)
    warn = [w for w in pred.context_warnings(thin) if "tissue under the tool" in w]
    assert len(warn) == 1 and "thinner than in every training case" in warn[0]
    assert np.isfinite(pred.predict(D, thin)).all()  # a warning, not a refusal


def test_a_camera_models_roi_patch_is_checked_before_its_height_is_read():
    """A camera model reads the pre-operative height from the ROI patch's triangles. Missing triangles, triangles
    that cover none of the grid, and triangles whose top sheet does not pass through the exertion point (saved
    against another point order: here they index a lid 10 mm above the patch) are refused, named."""
    from types import SimpleNamespace

    from liverforce.learn.representation import Representation
    from liverforce.serve.checks import Limits, check_patch

    model = SimpleNamespace(representation=Representation(8, 20.0, features="cloud", camera={"grid": {}}))
    s = np.linspace(-40, 40, 21)
    X, Y = np.meshgrid(s, s)
    plate = np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])
    a = (np.arange(20)[:, None] * 21 + np.arange(20)[None, :]).ravel()
    T = np.concatenate([np.column_stack([a, a + 21, a + 22]), np.column_stack([a, a + 22, a + 1])])
    lid = plate + [0.0, 0.0, 10.0]
    U = np.vstack([plate, lid])
    check_patch({"roi_triangles": [T]}, 0, U, model, Limits(), "case A: ")  # the plate: through the point
    with pytest.raises(PredictionInputError, match=r"case A: roi_triangles: the patch's top sheet passes 10 mm"):
        check_patch({"roi_triangles": [T + len(plate)]}, 0, U, model, Limits(), "case A: ")
    with pytest.raises(PredictionInputError, match="give roi_triangles"):
        check_patch({}, 0, U, model, Limits(), "")
    far = np.vstack([plate, plate + [500.0, 0.0, 0.0]])
    with pytest.raises(PredictionInputError, match="covers no point"):
        check_patch({"roi_triangles": [T + len(plate)]}, 0, far, model, Limits(), "")
    with pytest.raises(PredictionInputError, match="index points"):
        check_patch({"roi_triangles": [T + 2 * len(plate)]}, 0, U, model, Limits(), "")
