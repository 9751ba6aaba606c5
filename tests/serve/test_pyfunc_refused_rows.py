"""The MLflow pyfunc refuses a bad row, not the whole request (param ``on_refused``, default ``"row"``), as
``liverforce predict --shards`` does: the row's forces and interval NaN, its reason in the ``refused`` column (the
words ``predict_arrays`` raises for it alone), the other rows as in a request of them alone. ``"request"``: the first
refused row refuses the whole request, as before. Before, one row of thousands lost every other row."""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from liverforce.learn.model import subset
from liverforce.serve import Predictor
from liverforce.serve.errors import PredictionInputError
from liverforce.tracking.model import (INTERVAL_COLUMNS, OUTPUT_COLUMNS, ForceModelPyfunc, PyfuncInputError,
                                       arrays_to_frame)

GOOD = [0, 2, 7]


def _pyfunc(pred: Predictor, df: pd.DataFrame, **params) -> pd.DataFrame:
    pf = ForceModelPyfunc()
    pf.model = pred.model
    return pf.predict(None, df, params=params)


def _refusal(call) -> str:
    with pytest.raises(PredictionInputError) as exc:
        call()
    return str(exc.value)


@pytest.fixture(scope="module")
def request_rows(trained, test_cases):
    """Eight held-out cases as a request, five of them bad in one way each: 1 a NaN point, 3 its exertion point 10
    mm off the surface, 4 a flattened ROI one number short (not 3 k long), 5 its material in Pa, 6 pushed 60x too
    far. Returns the predictor, the arrays (rows 0-7) and the request's DataFrame."""
    pred = Predictor.from_dir(trained("disp"))
    keys = ["case_id", *pred.model.required_inputs(), "roi_triangles"]  # the columns a shard row gives
    cases = subset({k: test_cases[k] for k in keys}, np.arange(8))
    cases = {k: (list(v) if isinstance(v, list) else np.array(v, copy=True)) for k, v in cases.items()}
    deformed = np.array(cases["roi_deformed_mm"][1], dtype=np.float64)
    deformed[3] = np.nan
    cases["roi_deformed_mm"][1] = deformed
    cases["exertion_point_mm"][3] = cases["exertion_point_mm"][3] + 10.0 * np.asarray(cases["frame_normal"][3])
    cases["material_params_mpa"][5] = cases["material_params_mpa"][5] * 1e6
    und, de = (np.asarray(cases[k][6], dtype=np.float64) for k in ("roi_undeformed_mm", "roi_deformed_mm"))
    cases["roi_deformed_mm"][6] = und + 60.0 * (de - und)
    df = arrays_to_frame(cases, keys)
    df.at[4, "roi_undeformed_mm"] = df.at[4, "roi_undeformed_mm"][:-1]
    return pred, cases, df


def test_a_refused_row_is_answered_with_its_reason_and_the_others_are_predicted(request_rows):
    """Each bad row: NaN forces and interval, no warnings, and in ``refused`` the words predict_arrays raises for
    it alone (the unreadable one: what the pyfunc raises for it alone). The good rows: every column as in a
    request of them alone."""
    pred, cases, df = request_rows
    out = _pyfunc(pred, df)
    assert list(out.columns) == [*OUTPUT_COLUMNS, *INTERVAL_COLUMNS, "refused", "warnings"]
    bad = [i for i in range(len(df)) if i not in GOOD]
    want = {i: _refusal(lambda: pred.predict_arrays(subset(cases, [i]))) for i in (1, 3, 5, 6)}
    want[4] = _refusal(lambda: _pyfunc(pred, df.iloc[[4]].reset_index(drop=True), on_refused="request"))
    ids = list(df["case_id"])
    assert want[1].startswith(f"case {ids[1]}: roi_deformed_mm: 1 of ") and "NaN or inf" in want[1]
    assert want[3].startswith(f"case {ids[3]}: the exertion point is ") and "off the undeformed surface" in want[3]
    assert want[4] == (f"case {ids[4]}: roi_undeformed_mm: {len(df.at[4, 'roi_undeformed_mm'])} numbers, not a "
                       "multiple of 3 (x, y, z per point, flattened)")
    assert want[5].startswith(f"case {ids[5]}: material_params_mpa[0]") and "must be in MPa" in want[5]
    assert want[6].startswith(f"case {ids[6]}: the ROI moved by up to")
    assert list(out["refused"]) == [want.get(i, "") for i in range(len(df))]
    assert out.loc[bad, [*OUTPUT_COLUMNS, *INTERVAL_COLUMNS]].isna().all().all()
    assert (out.loc[bad, "warnings"] == "").all()
    alone = _pyfunc(pred, df.iloc[GOOD].reset_index(drop=True))
    assert np.isfinite(alone[[*OUTPUT_COLUMNS, *INTERVAL_COLUMNS]].to_numpy()).all()
    pd.testing.assert_frame_equal(out.iloc[GOOD].reset_index(drop=True), alone)
    np.testing.assert_array_equal(alone[list(OUTPUT_COLUMNS)].to_numpy(), pred.predict_arrays(subset(cases, GOOD)))


def test_on_refused_request_refuses_the_whole_request_as_before(request_rows):
    """``on_refused="request"``: a PyfuncInputError (HTTP 400 from MLflow's server) with the first refused row's
    reason; the unreadable point set is read, and refused, before any check runs."""
    pred, cases, df = request_rows
    with pytest.raises(PyfuncInputError) as exc:
        _pyfunc(pred, df, on_refused="request")
    assert str(exc.value) == _pyfunc(pred, df)["refused"][4]
    readable = df.drop(index=4).reset_index(drop=True)
    with pytest.raises(PyfuncInputError) as exc:
        _pyfunc(pred, readable, on_refused=" Request ")
    assert str(exc.value) == _refusal(lambda: pred.predict_arrays(subset(cases, [0, 1, 2, 3, 5, 6, 7])))
    assert str(exc.value).startswith(f"case {df['case_id'][1]}: ")
    got = _pyfunc(pred, df.iloc[GOOD].reset_index(drop=True), on_refused="request")  # nothing to refuse
    pd.testing.assert_frame_equal(got, _pyfunc(pred, df.iloc[GOOD].reset_index(drop=True)))


def test_a_request_of_refused_rows_only_is_still_answered(request_rows):
    """Every row refused: still answered, every reason given (as --shards still writes its file)."""
    pred, _, df = request_rows
    every = _pyfunc(pred, df)
    bad = [i for i in range(len(df)) if i not in GOOD]
    out = _pyfunc(pred, df.iloc[bad].reset_index(drop=True))
    assert list(out["refused"]) == list(every["refused"][bad]) and all(out["refused"])
    assert out[[*OUTPUT_COLUMNS, *INTERVAL_COLUMNS]].isna().all().all() and (out["warnings"] == "").all()


def test_without_case_ids_a_refused_row_is_named_by_its_place_in_the_request(request_rows):
    """No ``case_id`` column: each reason names the row's index in the whole request, the unreadable row's too."""
    pred, _, df = request_rows
    out = _pyfunc(pred, df.drop(columns="case_id"))
    named = _pyfunc(pred, df)["refused"]
    for i, why in enumerate(out["refused"]):
        assert why == (named[i].replace(f"case {df['case_id'][i]}: ", f"row {i}: ", 1) if named[i] else "")


def test_a_bad_on_refused_refuses_the_request_naming_it(request_rows):
    pred, _, df = request_rows
    with pytest.raises(PyfuncInputError, match=r"on_refused 'rows': give 'row' .* or 'request'"):
        _pyfunc(pred, df.iloc[GOOD].reset_index(drop=True), on_refused="rows")
