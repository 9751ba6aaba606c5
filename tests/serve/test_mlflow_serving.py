"""Models logged to MLflow: load by run id / URI / registered name, the pyfunc, and ``mlflow models serve``."""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import yaml

from liverforce.pipeline.job import thread_env
from liverforce.learn.model import subset
from liverforce.learn.train import train_scenario
from liverforce.serve import PredictionInputError
from liverforce.tracking import MlflowPredictor as Predictor
from liverforce.tracking import Tracker, download_force_model, load_pyfunc, predict_pyfunc

from tests.serve.test_input_frame import to_input_arrays


@pytest.fixture(scope="module")
def logged(data, tmp_path_factory, configs):
    BASE, TRAIN, NO_TUNE = configs
    root = tmp_path_factory.mktemp("mlflow")
    uri = f"sqlite:///{root / 'mlflow.db'}"
    tracker = Tracker(uri, "serve-test")
    res = train_scenario(subset(data, np.arange(60)), BASE, {**TRAIN, "epochs": 10}, NO_TUNE, "III", "pca",
                         tracker=tracker, out_dir=root / "out")
    return {"uri": uri, "tracker": tracker, "root": root, **res}


def test_the_logged_model_has_a_signature_an_example_and_no_pickle(logged, tmp_path):
    bundle = download_force_model(logged["run_id"], tmp_path, tracking_uri=logged["uri"])
    model_dir = bundle.parent.parent
    mlmodel = yaml.safe_load((model_dir / "MLmodel").read_text())
    inputs = {c["name"] for c in json.loads(mlmodel["signature"]["inputs"])}
    assert {"roi_undeformed_mm", "roi_deformed_mm", "exertion_point_mm", "material_params_mpa"} <= inputs
    assert [c["name"] for c in json.loads(mlmodel["signature"]["outputs"])] == [
        "fx_n", "fy_n", "fz_n", "ft1_n", "ft2_n", "fn_n", "ft1_half_n", "ft2_half_n", "fn_half_n",  # + the interval
        "refused",  # why a row was refused ("" when predicted)
        "warnings"]  # the context outside the training range
    required = {c["name"]: c.get("required", True) for c in json.loads(mlmodel["signature"]["outputs"])}
    assert required.pop("refused") and required.pop("warnings")  # always there
    assert not any(required.values()), required  # a refused row's numbers are NaN (null served): optional
    params = {p["name"]: p for p in json.loads(mlmodel["signature"]["params"])}
    assert set(params) == {"observation_seed", "input_frame", "units", "on_refused"}
    assert params["on_refused"]["default"] == "row" and params["on_refused"]["type"] == "string"
    assert (model_dir / "serving_input_example.json").is_file()
    assert not list(model_dir.rglob("*.pkl"))  # models from code: nothing to unpickle
    assert (bundle / "model.json").is_file()


def test_load_by_run_id_uri_and_registered_name(logged, data):
    uri = logged["uri"]
    local = Predictor.from_dir(logged["model_path"])
    cases = subset(data, np.arange(60, 70))
    ref = local.predict_arrays(cases)
    for ref_str in (logged["run_id"], f"runs:/{logged['run_id']}/model"):
        np.testing.assert_array_equal(Predictor.load(ref_str, tracking_uri=uri).predict_arrays(cases), ref)
    version = logged["tracker"].register_force_model(logged["model_uri"], "liverforce-serve-test")
    assert version == "1"
    for ref_str in ("models:/liverforce-serve-test/1", "liverforce-serve-test"):
        pred = Predictor.load(ref_str, tracking_uri=uri)
        assert pred.source == ref_str
        np.testing.assert_array_equal(pred.predict_arrays(cases), ref)
    with pytest.raises(PredictionInputError, match="cannot fetch it from MLflow"):
        Predictor.load("0123456789abcdef0123456789abcdef", tracking_uri=uri)


def test_loading_by_reference_leaves_no_download_behind(logged, tmp_path, monkeypatch, capsys):
    """A model fetched by reference is read whole, then its download folder is removed (Python and CLI); a
    ``dst_dir`` the user names is kept."""
    import argparse
    import tempfile

    from liverforce.cli import register_predict

    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))  # where TemporaryDirectory and mkdtemp create folders
    ref = f"runs:/{logged['run_id']}/model"
    pred = Predictor.load(ref, tracking_uri=logged["uri"])
    assert pred.model.meta and list(scratch.iterdir()) == []
    parser = argparse.ArgumentParser()
    register_predict(parser.add_subparsers(dest="cmd"))
    args = parser.parse_args(["predict", "-m", ref, "--describe", "--tracking-uri", logged["uri"]])
    assert args.func(args) == 0
    assert json.loads(capsys.readouterr().out)["source"] == ref
    assert list(scratch.iterdir()) == []
    kept = tmp_path / "kept"
    Predictor.load(ref, tracking_uri=logged["uri"], dst_dir=kept)
    assert list(kept.rglob("model.json")) and list(scratch.iterdir()) == []


def test_pyfunc_predicts_like_the_predictor_and_refuses_bad_rows(logged, data, tmp_path, monkeypatch):
    """The pyfunc is loaded whole: its download folder is gone before it predicts (MLflow alone would leave
    one folder per load in the temporary directory)."""
    import tempfile

    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    pf = load_pyfunc(f"runs:/{logged['run_id']}/model", logged["uri"])
    assert list(scratch.iterdir()) == []
    cases = subset(data, np.arange(60, 66))
    local = Predictor.from_dir(logged["model_path"])
    np.testing.assert_array_equal(predict_pyfunc(pf, cases), local.predict_arrays(cases))
    bad = dict(cases)
    bad["material_params_mpa"] = cases["material_params_mpa"] * 1e6  # Pa, not MPa
    from liverforce.tracking import PyfuncInputError, arrays_to_frame

    with pytest.raises(PyfuncInputError, match=r"^case S-000060: material_params_mpa\[0\].*must be in MPa"):
        predict_pyfunc(pf, bad)  # what the server answers with HTTP 400
    # through MLflow's params schema: one row in Pa among good ones is answered with its reason, the others
    # predicted (MLflow fills in the signature's default "row"); asked to, the whole request is refused

    mixed = {k: (np.array(v, copy=True) if isinstance(v, np.ndarray) else v) for k, v in cases.items()}
    mixed["material_params_mpa"][2] = bad["material_params_mpa"][2]
    frame = arrays_to_frame(mixed, ["case_id", *local.model.required_inputs()])
    out = pf.predict(frame)
    why = out["refused"][2]
    assert why.startswith("case S-000062: material_params_mpa[0]") and "must be in MPa" in why
    assert list(out["refused"].drop(index=2)) == [""] * 5
    force = out[["fx_n", "fy_n", "fz_n"]].to_numpy()
    assert np.isnan(force[2]).all()
    np.testing.assert_array_equal(np.delete(force, 2, axis=0), local.predict_arrays(subset(cases, [0, 1, 3, 4, 5])))
    with pytest.raises(PyfuncInputError, match=r"^case S-000062: material_params_mpa\[0\]"):
        pf.predict(frame, params={"on_refused": "request"})


def test_a_model_logged_before_on_refused_still_refuses_the_whole_request(logged, data, tmp_path):
    """A model whose signature has no ``on_refused`` (logged before it existed): MLflow drops the param from a
    request and fills in no default, so the pyfunc is not given the key and refuses a request with a bad row as the
    model did when logged (PyfuncInputError: HTTP 400), not a 200 with rows its clients never had to read;
    predict_pyfunc likewise. Its good requests are answered as before."""
    import mlflow

    from liverforce.tracking import PyfuncInputError, arrays_to_frame

    model_dir = download_force_model(logged["run_id"], tmp_path, tracking_uri=logged["uri"]).parent.parent
    mlmodel = yaml.safe_load((model_dir / "MLmodel").read_text())
    sig = mlmodel["signature"]
    sig["params"] = json.dumps([p for p in json.loads(sig["params"]) if p["name"] != "on_refused"])
    (model_dir / "MLmodel").write_text(yaml.safe_dump(mlmodel))
    pf = mlflow.pyfunc.load_model(str(model_dir))
    assert [p.name for p in pf.metadata.get_params_schema().params] == ["observation_seed", "input_frame", "units"]
    cases = subset(data, np.arange(60, 63))
    local = Predictor.from_dir(logged["model_path"])
    np.testing.assert_array_equal(predict_pyfunc(pf, cases), local.predict_arrays(cases))
    mixed = {k: (np.array(v, copy=True) if isinstance(v, np.ndarray) else v) for k, v in cases.items()}
    mixed["material_params_mpa"][1] = mixed["material_params_mpa"][1] * 1e6  # Pa, not MPa
    frame = arrays_to_frame(mixed, ["case_id", *local.model.required_inputs()])
    for params in (None, {"on_refused": "row"}):  # asked for per-row answers, which it does not take
        with pytest.raises(PyfuncInputError, match=r"^case S-000061: material_params_mpa\[0\].*must be in MPa"):
            pf.predict(frame, params=params)
    with pytest.raises(PyfuncInputError, match=r"^case S-000061: material_params_mpa\[0\]"):
        predict_pyfunc(pf, mixed)


def _strict_json(body: bytes):
    """``body`` read as strict JSON: a bare ``NaN``/``Infinity`` token refused, as JavaScript's ``JSON.parse``
    refuses it."""
    def refuse(token):
        raise ValueError(f"{token} is not JSON")

    return json.loads(body, parse_constant=refuse)


def _asgi_post(app, doc: dict) -> tuple[int, bytes]:
    """POST ``doc`` to ``/invocations`` of MLflow's scoring-server app (ASGI), in this process: the server's
    route, parsing, prediction and JSON writing, without a port (no HTTP client library needed)."""
    import asyncio

    body = json.dumps(doc).encode()
    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "POST", "scheme": "http",
             "path": "/invocations", "raw_path": b"/invocations", "query_string": b"", "root_path": "",
             "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())],
             "client": ("127.0.0.1", 1), "server": ("127.0.0.1", 80)}
    sent: list[dict] = []

    async def run():
        done = asyncio.Event()
        given = []

        async def receive():
            if not given:
                given.append(True)
                return {"type": "http.request", "body": body, "more_body": False}
            await done.wait()  # the client stays until the answer is sent
            return {"type": "http.disconnect"}

        async def send(message):
            sent.append(message)
            if message["type"] == "http.response.body" and not message.get("more_body", False):
                done.set()

        await app(scope, receive, send)

    asyncio.run(run())
    status = next(m["status"] for m in sent if m["type"] == "http.response.start")
    return status, b"".join(m.get("body", b"") for m in sent if m["type"] == "http.response.body")


@pytest.fixture()
def served(logged, tmp_path, monkeypatch):
    """The logged model loaded as ``mlflow models serve`` loads it, and MLflow's scoring-server app for it
    (``scoring_server.init``, which marks this process as serving: undone after the test)."""
    import mlflow
    from mlflow.pyfunc import scoring_server

    from liverforce.tracking.model import MLFLOW_SERVING_ENV

    monkeypatch.setenv(MLFLOW_SERVING_ENV, "false")  # unset before: unset again after the test (init sets it)
    model_dir = download_force_model(logged["run_id"], tmp_path, tracking_uri=logged["uri"]).parent.parent
    pf = mlflow.pyfunc.load_model(str(model_dir))
    return pf, scoring_server.init(pf)


NUMBER_COLUMNS = ("fx_n", "fy_n", "fz_n", "ft1_n", "ft2_n", "fn_n", "ft1_half_n", "ft2_half_n", "fn_half_n")


def _bad_rows(data, pred):
    """Four new cases as a request, rows 1 (material in Pa) and 3 (the ROI moved far off) refused."""
    from liverforce.tracking import arrays_to_frame

    cases = subset(data, np.arange(60, 64))
    mixed = {k: (np.array(v, copy=True) if isinstance(v, np.ndarray) else list(v)) for k, v in cases.items()}
    mixed["material_params_mpa"][1] = mixed["material_params_mpa"][1] * 1e6
    mixed["roi_deformed_mm"][3] = 0.1 * np.asarray(mixed["roi_deformed_mm"][3], dtype=np.float64)
    return arrays_to_frame(mixed, ["case_id", *pred.model.required_inputs()])


def test_a_served_refused_row_is_null_in_strict_json_and_nan_for_python(served, logged, data, monkeypatch):
    """Over HTTP (MLflow's scoring server, in this process) a refused row's forces and interval are ``null``,
    so the answer is strict JSON, with its reason in ``refused``; the good rows are the numbers of a request of
    them alone. A Python caller (``mlflow.pyfunc.load_model(...).predict``) still gets float columns with NaN
    there. Before, the server wrote the bare token ``NaN``, which strict JSON parsers refuse."""
    from liverforce.tracking.model import MLFLOW_SERVING_ENV

    pf, app = served
    pred = Predictor.from_dir(logged["model_path"])
    frame = _bad_rows(data, pred)
    monkeypatch.setenv(MLFLOW_SERVING_ENV, "false")  # init marked the process as serving: a Python caller here
    out = pf.predict(frame)
    assert all(out[c].dtype == np.float64 for c in NUMBER_COLUMNS)
    assert out.loc[[1, 3], list(NUMBER_COLUMNS)].isna().all().all()
    assert np.isfinite(out.loc[[0, 2], list(NUMBER_COLUMNS)].to_numpy()).all()
    assert out["refused"][1].startswith("case S-000061: material_params_mpa[0]")
    assert out["refused"][3].startswith("case S-000063: the ROI moved by up to")
    monkeypatch.setenv(MLFLOW_SERVING_ENV, "true")  # as init set it: the server's process

    status, body = _asgi_post(app, {"dataframe_split": frame.to_dict(orient="split")})
    assert status == 200, body
    rows = _strict_json(body)["predictions"]
    assert [r["refused"] for r in rows] == list(out["refused"])
    for i in (1, 3):
        assert all(rows[i][c] is None for c in NUMBER_COLUMNS), rows[i]
        assert rows[i]["warnings"] == ""
    status, alone = _asgi_post(app, {"dataframe_split": frame.iloc[[0, 2]].reset_index(drop=True)
                                     .to_dict(orient="split")})
    assert status == 200, alone
    assert [rows[0], rows[2]] == _strict_json(alone)["predictions"]
    for i in (0, 2):  # the numbers a Python caller gets
        assert [rows[i][c] for c in NUMBER_COLUMNS] == list(out.loc[i, list(NUMBER_COLUMNS)])
    # with "request" the first refused row still refuses the whole request (HTTP 400, its reason)
    status, refused = _asgi_post(app, {"dataframe_split": frame.to_dict(orient="split"),
                                       "params": {"on_refused": "request"}})
    assert status == 400 and out["refused"][1] in _strict_json(refused)["message"]


def test_an_unbounded_half_width_is_served_as_null(served, logged, data, monkeypatch):
    """An interval too few calibration cases left unbounded (an infinite half-width) is ``null`` over HTTP
    too, not the token ``Infinity``; its force and the other numbers as given; a Python caller gets inf."""
    from liverforce.tracking.model import MLFLOW_SERVING_ENV

    pf, app = served
    meta = pf.unwrap_python_model().model.meta
    half = meta["interval"]["half_width_n"]  # the normal's as model.json writes an unbounded one: null
    monkeypatch.setitem(meta, "interval", {**meta["interval"], "half_width_n": [*half[:2], None]})
    pred = Predictor.from_dir(logged["model_path"])
    frame = _bad_rows(data, pred).iloc[[0, 2]].reset_index(drop=True)
    monkeypatch.setenv(MLFLOW_SERVING_ENV, "false")
    out = pf.predict(frame)
    assert np.isinf(out["fn_half_n"]).all() and np.isfinite(out[list(NUMBER_COLUMNS[:-1])].to_numpy()).all()
    monkeypatch.setenv(MLFLOW_SERVING_ENV, "true")
    status, body = _asgi_post(app, {"dataframe_split": frame.to_dict(orient="split")})
    assert status == 200, body
    rows = _strict_json(body)["predictions"]
    assert [r["fn_half_n"] for r in rows] == [None, None]
    for i, r in enumerate(rows):
        assert [r[c] for c in NUMBER_COLUMNS[:-1]] == list(out.loc[i, list(NUMBER_COLUMNS[:-1])])


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _post(url: str, doc: dict, timeout: float = 30.0) -> tuple[int, dict]:
    req = urllib.request.Request(url, data=json.dumps(doc).encode(), headers={"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            return r.status, _strict_json(r.read())
    except urllib.error.HTTPError as e:
        return e.code, _strict_json(e.read() or b"{}")


@pytest.mark.slow  # one of the default set's slowest (CI's --durations): run with -m slow
def test_mlflow_models_serve_answers_over_http(logged, data, tmp_path):
    port = _free_port()
    # `mlflow models serve` runs `uvicorn` through the shell: the venv's bin must be on PATH
    venv_bin = Path(sys.executable).parent
    env = thread_env(1, {**os.environ, "MLFLOW_TRACKING_URI": logged["uri"],
                         "PATH": f"{venv_bin}:{os.environ['PATH']}"})
    cmd = [sys.executable, "-m", "mlflow", "models", "serve", "-m", f"runs:/{logged['run_id']}/model",
           "--host", "127.0.0.1", "--port", str(port), "--env-manager", "local"]
    log = open(tmp_path / "serve.log", "w")
    proc = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 120.0
        while True:
            if proc.poll() is not None:
                log_text = (tmp_path / "serve.log").read_text()
                pytest.fail(f"mlflow models serve exited with {proc.returncode}:\n{log_text}")
            try:
                with urllib.request.urlopen(f"{base}/ping", timeout=2.0) as r:
                    if r.status == 200:
                        break
            except (urllib.error.URLError, ConnectionError, TimeoutError):
                pass
            if time.monotonic() > deadline:
                pytest.fail(f"server not ready after 120 s:\n{(tmp_path / 'serve.log').read_text()}")
            time.sleep(0.5)
        bundle = download_force_model(logged["run_id"], tmp_path / "dl", tracking_uri=logged["uri"])
        example = json.loads((bundle.parent.parent / "serving_input_example.json").read_text())
        status, body = _post(f"{base}/invocations", example)
        assert status == 200, body
        assert set(body["predictions"][0]) == {"fx_n", "fy_n", "fz_n", "ft1_n", "ft2_n", "fn_n", "ft1_half_n",
                                               "ft2_half_n", "fn_half_n", "refused", "warnings"}
        # a request built from new cases equals the local predictor
        from liverforce.tracking import arrays_to_frame

        cases = subset(data, np.arange(60, 63))
        pred = Predictor.from_dir(logged["model_path"])
        frame = arrays_to_frame(cases, list(pred.model.required_inputs()))
        status, body = _post(f"{base}/invocations", {"dataframe_split": frame.to_dict(orient="split")})
        assert status == 200, body
        got = np.array([[p["fx_n"], p["fy_n"], p["fz_n"]] for p in body["predictions"]])
        np.testing.assert_allclose(got, pred.predict_arrays(cases), atol=1e-9)
        # tissue thinner than in every training case: the force comes back with the warning naming it
        thin = {**cases, "tool_thickness_mm": np.full(3, 0.7 * pred.scale.thickness_mm[0])}
        frame = arrays_to_frame(thin, list(pred.model.required_inputs()))
        status, body_thin = _post(f"{base}/invocations", {"dataframe_split": frame.to_dict(orient="split")})
        assert status == 200, body_thin
        assert all("thinner than in every training case" in p["warnings"] for p in body_thin["predictions"])
        iv = pred.model.predict_interval(cases)  # the served interval is the model's
        got = np.array([[p["ft1_half_n"], p["ft2_half_n"], p["fn_half_n"]] for p in body["predictions"]])
        np.testing.assert_allclose(got, iv["half_width_local_n"], rtol=1e-9)
        # a lab's columns in LPS metres, said in the request's params: the force in LPS, the local columns as in RAS
        lps = to_input_arrays(np.diag([-1.0, -1.0, 1.0, 1.0]), 1000.0, cases)
        frame = arrays_to_frame(lps, list(pred.model.required_inputs()))
        status, body_lps = _post(f"{base}/invocations", {"dataframe_split": frame.to_dict(orient="split"),
                                                         "params": {"input_frame": "LPS", "units": "m"}})
        assert status == 200, body_lps
        got = np.array([[p["fx_n"], p["fy_n"], p["fz_n"]] for p in body_lps["predictions"]])
        np.testing.assert_allclose(got, pred.predict_arrays(cases) * [-1.0, -1.0, 1.0], atol=1e-6)
        local = [[p[c] for c in ("ft1_n", "ft2_n", "fn_n", "ft1_half_n")] for p in body_lps["predictions"]]
        np.testing.assert_allclose(local, [[p[c] for c in ("ft1_n", "ft2_n", "fn_n", "ft1_half_n")]
                                           for p in body["predictions"]], atol=1e-6)
        # bad input: a clear refusal, not a force. One bad row among good ones: that row null (strict JSON) with its
        # reason, the others predicted; with on_refused "request" the whole request refused (HTTP 400)
        want = pred.predict_arrays(cases)
        cases["roi_deformed_mm"] = [d * (0.1 if i == 1 else 1.0) for i, d in enumerate(cases["roi_deformed_mm"])]
        frame = arrays_to_frame(cases, list(pred.model.required_inputs()))
        status, body = _post(f"{base}/invocations", {"dataframe_split": frame.to_dict(orient="split")})
        assert status == 200, body
        rows = body["predictions"]
        assert rows[1]["refused"].startswith("row 1: ") and "moved by up to" in rows[1]["refused"], rows[1]
        assert [rows[0]["refused"], rows[2]["refused"]] == ["", ""]
        assert all(rows[1][c] is None for c in rows[1] if c not in ("refused", "warnings"))
        got = np.array([[p["fx_n"], p["fy_n"], p["fz_n"]] for p in (rows[0], rows[2])])
        np.testing.assert_allclose(got, want[[0, 2]], atol=1e-9)
        status, body = _post(f"{base}/invocations", {"dataframe_split": frame.to_dict(orient="split"),
                                                     "params": {"on_refused": "request"}})
        said = body.get("message", "")
        assert status == 400 and "row 1: the ROI moved by up to" in said, body  # after MLflow's "Failed to predict"
        status, body = _post(f"{base}/invocations", {"dataframe_split": frame.to_dict(orient="split"),
                                                     "params": {"on_refused": "never"}})
        assert status == 400 and "on_refused 'never'" in body.get("message", ""), body
        # not the input contract: the whole request refused (HTTP 400) in "row" mode too, a missing column named
        status, body = _post(f"{base}/invocations",
                             {"dataframe_split": frame.drop(columns="material_params_mpa").to_dict(orient="split")})
        assert status == 400 and "material_params_mpa" in body.get("message", ""), body
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10)
        log.close()
