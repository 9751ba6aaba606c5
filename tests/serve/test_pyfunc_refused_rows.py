"""The MLflow pyfunc refuses a bad row, not the whole request (param ``on_refused="row"``, the logged signature's
default, which MLflow fills in), as ``liverforce predict --shards`` does: the row's forces and interval NaN, its
reason in the ``refused`` column (the words ``predict_arrays`` raises for it alone), the other rows as in a request of
them alone. ``"request"``, and a call without the key (a model logged before the param): the first refused row
refuses the whole request, as before. Before, one row of thousands lost every other row."""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from liverforce.learn.model import subset
from liverforce.serve import Predictor
from liverforce.serve.errors import PredictionInputError
from liverforce.tracking.model import (INTERVAL_COLUMNS, OUTPUT_COLUMNS, ForceModelPyfunc, PyfuncInputError,
                                       arrays_to_frame, predict_pyfunc)

GOOD = [0, 2, 7]


def _pyfunc(pred: Predictor, df: pd.DataFrame, **params) -> pd.DataFrame:
    """The pyfunc's answer as MLflow calls a model logged with ``on_refused`` (its default ``"row"`` filled in)."""
    pf = ForceModelPyfunc()
    pf.model = pred.model
    return pf.predict(None, df, params={"on_refused": "row", **params})


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


# --------------------------------------------------------------------------
# a row the model cannot take, the draws of a request without case_id, older models, labels, predict_pyfunc
# --------------------------------------------------------------------------


def _hidden_by_the_tool(pred: Predictor, cases: dict, rows) -> dict:
    """``cases`` with each row of ``rows`` made of 12 ROI nodes, all but two within 1 mm of the exertion point
    (inside the ``disp`` model's 3 mm occlusion radius, which removes them) and two at the grid's edge, at rest:
    every other serving check passes (the ROI reaches the grid, the point lies on it, nothing moved)."""
    out = {k: (list(v) if isinstance(v, list) else np.array(v, copy=True)) for k, v in cases.items()}
    h = pred.model.representation.half_width_mm
    ang = np.linspace(0.0, 2.0 * np.pi, 9, endpoint=False)
    local = np.vstack([np.column_stack([np.cos(ang), np.sin(ang), np.zeros(9)]), [[0.0, 0.0, 0.0]],
                       [[h, 0.0, 0.0]], [[-h, 0.0, 0.0]]])
    for i in rows:
        R = np.stack([out["frame_t1"][i], out["frame_t2"][i], out["frame_normal"][i]]).astype(np.float64)
        U = np.asarray(out["exertion_point_mm"][i], dtype=np.float64) + local @ R
        out["roi_undeformed_mm"][i], out["roi_deformed_mm"][i] = U, U.copy()
        out["roi_triangles"][i] = np.zeros((0, 3), dtype=np.int64)
    return out


@pytest.fixture(scope="module")
def hidden_rows(trained, test_cases):
    """Six held-out cases, rows 1 and 4 with too few ROI nodes beyond the tool (:func:`_hidden_by_the_tool`)."""
    pred = Predictor.from_dir(trained("disp"))
    keys = ["case_id", *pred.model.required_inputs(), "roi_triangles"]
    cases = subset({k: test_cases[k] for k in keys}, np.arange(6))
    assert pred.model.representation.occlusion_mode == "remove" and pred.model.representation.occlusion_radius_mm == 3
    return pred, _hidden_by_the_tool(pred, cases, [1, 4]), keys


def test_too_few_roi_nodes_beyond_the_tool_is_a_serving_refusal_of_that_row(hidden_rows):
    """The model leaves out the nodes the tool hides and resamples no fewer than 3: a row with 2 beyond the
    radius is refused by the checks, naming it (predict_arrays raises, the pyfunc answers the row with it, or the
    whole request with "request"); the other rows as in a request of them alone. Before, the model raised a plain
    ValueError and the whole request was lost (HTTP 500)."""
    pred, cases, keys = hidden_rows
    ids = list(cases["case_id"])
    why = _refusal(lambda: pred.predict_arrays(subset(cases, [1])))
    assert why == (f"case {ids[1]}: only 2 of the 12 ROI nodes lie 3 mm or more from the exertion point (in the "
                   "tangent plane): the model leaves out the nodes the tool hides (its occlusion radius, 3 mm) and "
                   "needs 3 or more to resample; give the ROI round the exertion point beyond the tool, not only "
                   "the nodes under it")
    force, refused = pred.predict_arrays(cases, return_refused=True)
    assert refused == ["", why, "", "", refused[4], ""] and refused[4].startswith(f"case {ids[4]}: only 2 of the 12")
    np.testing.assert_array_equal(force[[0, 2, 3, 5]], pred.predict_arrays(subset(cases, [0, 2, 3, 5])))
    df = arrays_to_frame(cases, keys)
    out = _pyfunc(pred, df)
    assert list(out["refused"]) == refused
    pd.testing.assert_frame_equal(out.iloc[[0, 2, 3, 5]].reset_index(drop=True),
                                  _pyfunc(pred, df.iloc[[0, 2, 3, 5]].reset_index(drop=True)))
    with pytest.raises(PyfuncInputError) as exc:
        _pyfunc(pred, df, on_refused="request")
    assert str(exc.value) == why


def test_a_row_the_model_cannot_take_after_every_check_is_refused_alone(hidden_rows, monkeypatch):
    """A row every serving check passes that the model still cannot take (here: the occlusion check above taken
    out, so the model's own ValueError comes through): with ``return_refused`` (``--shards``) and the pyfunc's
    "row" it is refused with the model's reason, named by its case or its place in the request, and the other rows
    are predicted as in a call of them alone; with "request" the pyfunc refuses the request with the model's
    words (a PyfuncInputError: HTTP 400, not a 500)."""
    from liverforce.serve import checks

    pred, cases, keys = hidden_rows
    monkeypatch.setattr(checks, "check_occlusion", lambda *a, **k: None)
    ids = list(cases["case_id"])
    with pytest.raises(ValueError) as raised:  # the model's, as --shards without return_refused meets it
        pred.predict_arrays(subset(cases, [1]))
    model_says = str(raised.value)
    assert not isinstance(raised.value, PredictionInputError)
    assert model_says.startswith(f"case {ids[1]}: only 2 ROI nodes remain outside the occlusion radius 3.0 mm")
    force, warnings, refused = pred.predict_arrays(cases, return_refused=True, return_warnings=True)
    reason = model_says[len(f"case {ids[1]}: "):]
    assert refused == ["", f"case {ids[1]}: {reason}", "", "", f"case {ids[4]}: {reason}", ""]
    assert np.isnan(force[[1, 4]]).all() and warnings[1] == warnings[4] == []
    good = [0, 2, 3, 5]
    np.testing.assert_array_equal(force[good], pred.predict_arrays(subset(cases, good)))
    df = arrays_to_frame(cases, keys)
    out = _pyfunc(pred, df)
    assert list(out["refused"]) == refused
    pd.testing.assert_frame_equal(out.iloc[good].reset_index(drop=True),
                                  _pyfunc(pred, df.iloc[good].reset_index(drop=True)))
    nameless = _pyfunc(pred, df.drop(columns="case_id"))  # named by the row's place in the request
    assert list(nameless["refused"]) == ["", f"row 1: {reason}", "", "", f"row 4: {reason}", ""]
    with pytest.raises(PyfuncInputError) as exc:
        _pyfunc(pred, df, on_refused="request")
    assert str(exc.value) == model_says


def test_without_case_id_a_row_draws_the_same_whatever_rows_before_it_are_refused(trained, test_cases):
    """A stochastic observation model (point noise), seeded, no ``case_id``: a row's draw is keyed by its place in
    the request, so rows 2 and 3 get the same forces and interval whether row 1 is good, unreadable or refused by
    a check (pyfunc and predict_arrays alike). Before, the draw was keyed by the row's index among the rows not
    refused, so refusing row 1 changed rows 2 and 3 by hundredths of a newton."""
    import copy
    import dataclasses

    pred = Predictor.from_dir(trained("disp"))
    model = copy.copy(pred.model)
    model.representation = dataclasses.replace(model.representation, noise_mm=0.5)
    noisy = Predictor(model)
    keys = [*model.required_inputs(), "roi_triangles"]  # no case_id
    cases = subset({k: test_cases[k] for k in keys}, np.arange(4))
    df = arrays_to_frame(cases, keys)
    cols = [*OUTPUT_COLUMNS, *INTERVAL_COLUMNS]
    good = _pyfunc(noisy, df, observation_seed=7)
    unreadable = df.copy()
    unreadable.at[1, "roi_undeformed_mm"] = unreadable.at[1, "roi_undeformed_mm"][:-1]
    mixed = _pyfunc(noisy, unreadable, observation_seed=7)
    assert mixed["refused"][1].startswith("row 1: roi_undeformed_mm: ")
    assert list(mixed["refused"][[0, 2, 3]]) == [""] * 3
    clean = _pyfunc(noisy, df)  # no seed: no draw
    drawn = np.abs(good.loc[[2, 3], cols].to_numpy() - clean.loc[[2, 3], cols].to_numpy()).max()
    assert drawn > 1e-3  # the draw moves the answer, so a different draw would show
    # the same draw; the batch of 3 rows instead of 4 moves float32 sums by ~1e-7 N
    np.testing.assert_allclose(mixed.loc[[0, 2, 3], cols].to_numpy(), good.loc[[0, 2, 3], cols].to_numpy(),
                               rtol=0, atol=1e-5)
    nan_point = {k: (list(v) if isinstance(v, list) else np.array(v, copy=True)) for k, v in cases.items()}
    nan_point["exertion_point_mm"][1] = np.nan
    force, refused = noisy.predict_arrays(nan_point, observation_seed=7, return_refused=True)
    assert refused[1].startswith("row 1: exertion_point_mm") and refused[2:] == ["", ""]
    np.testing.assert_allclose(force[[0, 2, 3]], noisy.predict_arrays(cases, observation_seed=7)[[0, 2, 3]],
                               rtol=0, atol=1e-5)
    np.testing.assert_allclose(force[[0, 2, 3]], good.loc[[0, 2, 3], list(OUTPUT_COLUMNS)].to_numpy(), rtol=0,
                               atol=1e-5)


def test_without_the_param_the_pyfunc_refuses_the_whole_request_as_an_older_model_did(request_rows):
    """The key ``on_refused`` absent: MLflow fills in the signature's default ``"row"`` for a model logged with
    the param, so only a model logged before it (MLflow drops the param) gets here; such a model refused the
    whole request (HTTP 400) and still does, rather than answer a 200 with refused rows its clients never had to
    read. A blank value is the signature's default, ``"row"``."""
    pred, _, df = request_rows
    pf = ForceModelPyfunc()
    pf.model = pred.model
    with pytest.raises(PyfuncInputError) as exc:
        pf.predict(None, df, params={})
    assert str(exc.value) == _pyfunc(pred, df)["refused"][4]
    with pytest.raises(PyfuncInputError):
        pf.predict(None, df, params=None)
    pd.testing.assert_frame_equal(pf.predict(None, df, params={"on_refused": ""}), _pyfunc(pred, df))


def test_a_single_row_without_case_id_is_named_row_0_by_every_refusal(request_rows):
    """One row, no ``case_id``: its reason reads ``row 0: ...`` whichever check refuses it (the checks of the
    case too, which named no row when it was alone), and ``case <id>: ...`` with the column."""
    pred, cases, df = request_rows
    for i, start in ((3, "the exertion point is "), (1, "roi_deformed_mm: 1 of "), (4, "roi_undeformed_mm: "),
                     (5, "material_params_mpa[0]")):
        one = df.iloc[[i]].reset_index(drop=True)
        named = _pyfunc(pred, one)["refused"][0]
        assert named.startswith(f"case {df['case_id'][i]}: {start}"), named
        nameless = _pyfunc(pred, one.drop(columns="case_id"))["refused"][0]
        assert nameless == named.replace(f"case {df['case_id'][i]}: ", "row 0: ", 1)
    alone = {k: v for k, v in subset(cases, [3]).items() if k != "case_id"}
    with pytest.raises(PredictionInputError, match=r"^row 0: the exertion point is "):
        pred.predict_arrays(alone)


class _Served:
    """A loaded pyfunc as :func:`predict_pyfunc` sees one: its input names, the params its signature takes and
    MLflow's call, which drops the others and fills in ``defaults`` (those the signature takes; the others stand
    for how the model behaves unasked); ``sent``: the params it was given."""

    def __init__(self, pred: Predictor, defaults: dict, takes: tuple[str, ...]):
        from types import SimpleNamespace

        self.pyfunc = ForceModelPyfunc()
        self.pyfunc.model = pred.model
        self.defaults, self.takes, self.sent = defaults, takes, []
        names = ["case_id", *pred.model.required_inputs(), "roi_triangles"]
        self.metadata = SimpleNamespace(
            get_input_schema=lambda: SimpleNamespace(input_names=lambda: names),
            get_params_schema=lambda: SimpleNamespace(params=[SimpleNamespace(name=k) for k in takes]))

    def predict(self, df, params):
        self.sent.append(dict(params))
        return self.pyfunc.predict(None, df, params={**self.defaults,
                                                     **{k: v for k, v in params.items() if k in self.takes}})


def test_predict_pyfunc_refuses_as_the_server_does(request_rows):
    """predict_pyfunc sends ``on_refused="request"`` to a model that takes it, so the first refused row refuses
    the call with the PyfuncInputError the server answers 400 with; an older model's per-row answer (a model that
    answers per row without the param) raises the same error with its first reason. Before, a plain
    PredictionInputError was raised from the per-row answer, after predicting every row."""
    pred, cases, df = request_rows
    arrays = dict(cases)
    with pytest.raises(PyfuncInputError) as exc:
        _pyfunc(pred, df.drop(index=4).reset_index(drop=True), on_refused="request")
    first = str(exc.value)  # predict_pyfunc sends the arrays, whose row 4 is readable
    new = _Served(pred, {"observation_seed": -1, "on_refused": "row"}, ("observation_seed", "on_refused"))
    with pytest.raises(PyfuncInputError) as exc:
        predict_pyfunc(new, arrays)
    assert str(exc.value) == first and new.sent[0]["on_refused"] == "request"
    old = _Served(pred, {"observation_seed": -1, "on_refused": "row"}, ("observation_seed",))  # answers per row
    with pytest.raises(PyfuncInputError) as exc:
        predict_pyfunc(old, arrays)
    assert str(exc.value) == first and "on_refused" not in old.sent[0]
    np.testing.assert_array_equal(predict_pyfunc(new, subset(cases, GOOD)), pred.predict_arrays(subset(cases, GOOD)))
