"""The fixed-topology fast path equals the reference path to 1e-6 N."""
from __future__ import annotations

import numpy as np
import pytest

from liverforce.serve import PredictionInputError, Predictor, Preop

TOL = 1e-6  # N; the reference runs the network in float32, so ~1e-7 N rounding is expected


def frames_of(test_cases, i, n, seed=0):
    """``n`` deformed ROIs of case ``i``: its own plus scaled / perturbed versions (a haptic stream)."""
    rng = np.random.default_rng(seed)
    U = np.asarray(test_cases["roi_undeformed_mm"][i])
    D = np.asarray(test_cases["roi_deformed_mm"][i])
    out = [D]
    for _ in range(n - 1):
        out.append(U + (D - U) * rng.uniform(0.3, 1.2) + rng.normal(scale=0.05, size=U.shape))
    return np.stack(out)


@pytest.mark.parametrize("variant", ["disp", "dae", "gp", "top"])
def test_compiled_equals_reference(trained, test_cases, variant):
    pred = Predictor.load(trained(variant))
    for i in range(0, len(test_cases["case_id"]), 4):
        ctx = Preop.from_arrays(test_cases, i)
        comp = pred.compile(ctx)
        Ds = frames_of(test_cases, i, 5, seed=i)
        ref = np.array([pred.model.predict(ctx.to_arrays(D))[0] for D in Ds])
        single = np.array([comp.predict(D) for D in Ds])
        np.testing.assert_allclose(single, ref, rtol=0, atol=TOL)
        np.testing.assert_allclose(comp.predict_batch(Ds), ref, rtol=0, atol=TOL)
        assert np.abs(ref).max() > 0.5  # not trivially small forces


def test_material_can_change_per_call(trained, test_cases):
    pred = Predictor.load(trained("disp"))
    ctx = Preop.from_arrays(test_cases, 2)
    comp = pred.compile(ctx)
    D = np.asarray(test_cases["roi_deformed_mm"][2])
    mats = np.array([[0.0013, 0.011], [0.0019, 0.014]])
    ref = np.array([pred.model.predict(ctx.with_material(m).to_arrays(D))[0] for m in mats])
    got = comp.predict_batch(np.stack([D, D]), material_params_mpa=mats)
    np.testing.assert_allclose(got, ref, atol=TOL)
    assert np.abs(ref[0] - ref[1]).max() > 100 * TOL  # the material reaches the output
    np.testing.assert_allclose(comp.with_material(mats[1]).predict(D), ref[1], atol=TOL)


def test_predict_arrays_fast_groups_shared_contexts(trained, test_cases):
    pred = Predictor.load(trained("disp"))
    # a shard-like batch: 3 contexts x 4 deformed states, plus singletons that take the reference path
    rows = {k: [] for k in test_cases}
    for i in (0, 1, 2):
        Ds = frames_of(test_cases, i, 4, seed=10 + i)
        for D in Ds:
            for k, v in test_cases.items():
                val = {"roi_deformed_mm": D, "roi_centroid_deformed_mm": D.mean(0)}.get(k, v[i])
                rows[k].append(val)
    for i in (5, 6):
        for k, v in test_cases.items():
            rows[k].append(v[i])
    arrays = {k: (v if k.startswith("roi_") and k.endswith("formed_mm") or k == "roi_triangles" else np.asarray(v))
              for k, v in rows.items()}
    ref = pred.model.predict(arrays)
    np.testing.assert_allclose(pred.predict_arrays(arrays, fast=True), ref, atol=TOL)


def test_fast_path_refuses_bad_input(trained, test_cases):
    pred = Predictor.load(trained("disp"))
    ctx = Preop.from_arrays(test_cases, 0)
    comp = pred.compile(ctx)
    D = np.asarray(test_cases["roi_deformed_mm"][0], dtype=np.float64)
    with pytest.raises(PredictionInputError, match=r"expected shape \(\d+, 3\)"):
        comp.predict(D[:-1])
    bad = D.copy()
    bad[3, 2] = np.nan
    with pytest.raises(PredictionInputError, match="first at row 3"):
        comp.predict(bad)
    with pytest.raises(PredictionInputError, match="row 1: .*first at row 3"):
        comp.predict_batch(np.stack([D, bad]))
    with pytest.raises(PredictionInputError, match="moved by up to"):
        comp.predict(D * 0.1)  # cm read as mm
    with pytest.raises(PredictionInputError, match="must be in MPa"):
        comp.predict_batch(np.stack([D, D]), material_params_mpa=np.array([[1.6, 12.5], [0.0016, 0.0125]]))
    with pytest.raises(PredictionInputError, match="must be in MPa"):
        comp.with_material([1600.0, 12500.0])
    with pytest.raises(PredictionInputError, match="roi_features: displacement"):
        Predictor.load(trained("deformed")).compile(ctx)
    # the refusals left the compiled context as it was: it still gives the reference force
    np.testing.assert_allclose(comp.predict(D), pred.model.predict(
        {k: v[:1] for k, v in test_cases.items()})[0], atol=TOL)


def test_the_fast_path_does_not_share_a_context_between_rows_that_differ_in_the_state(trained, test_cases):
    """Rows with the same ROI, point and liver but another tissue thickness or probe compliance are other
    contexts: each group of the fast path compiles its own, so it equals the reference."""
    pred = Predictor.load(trained("disp"))
    i = 1
    changes = [{}, {"tool_thickness_mm": 1.3}, {"probe_compliance_mm_per_n": 1.2}]
    rows = {k: [] for k in test_cases}
    for change in changes:
        for _ in range(3):  # 3 rows each: enough for a compiled group
            for k, v in test_cases.items():
                val = v[i]
                if k in change:
                    val = np.asarray(val) * change[k]
                rows[k].append(val)
    arrays = {k: (v if k.startswith("roi_") and k.endswith("formed_mm") or k == "roi_triangles" else np.asarray(v))
              for k, v in rows.items()}
    ref = pred.model.predict(arrays)
    assert all(np.abs(ref[3 * j] - ref[0]).max() > 1e-4 for j in (1, 2))  # each change moves the prediction
    np.testing.assert_allclose(pred.predict_arrays(arrays, fast=True, min_group=2), ref, rtol=0, atol=TOL)
