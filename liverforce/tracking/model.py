"""Force models in MLflow: the pyfunc wrapper, logging a bundle as a model, downloading it for serving.

A logged model is an MLflow pyfunc (reloadable by run id:
``mlflow.pyfunc.load_model(f"runs:/{run_id}/model")``) written as "models from
code" (no cloudpickle) with a signature and an input example, so
``mlflow models serve -m runs:/<id>/model --host 127.0.0.1 --env-manager local``
serves it. Its ``predict`` runs the serving checks of :mod:`liverforce.serve`:
a refused row gets NaN forces and its reason in the ``refused`` column while the
other rows are predicted, as ``liverforce predict --shards`` does (param
``on_refused="row"``, what a model logged since the param exists is served with
unless the request says otherwise; ``"request"``, and for older models: the first
refused row refuses the whole request, HTTP 400). Served over HTTP, those NaN
are ``null`` (:func:`_json_numbers`), so the answer is strict JSON.

For serving, :func:`download_force_model` fetches the bundle of a logged model
(run id, ``runs:/``/``models:/`` URI or registered name) for
:meth:`liverforce.learn.model.ForceModel.load` (nothing unpickled), and
:class:`MlflowPredictor` is the :class:`~liverforce.serve.predictor.Predictor`
that loads such references.

Import direction: this module builds on :mod:`liverforce.serve` (the pyfunc is
the serving predictor behind MLflow's interface); serving never imports
tracking and receives the MLflow download as a ``fetch`` callable.
"""

from __future__ import annotations

import json
import os
import re
import tempfile
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Callable

import mlflow
import mlflow.artifacts
import mlflow.pyfunc
import numpy as np
import pandas as pd
from mlflow.exceptions import MlflowException
from mlflow.models import infer_signature
from mlflow.protos.databricks_pb2 import INVALID_PARAMETER_VALUE
from mlflow.types import ColSpec, Schema

from liverforce.learn.camera import CLOUD_KEY, TIP_KEY
from liverforce.learn.model import ForceModel, subset
from liverforce.learn.representation import ROW_KEY
from liverforce.serve.errors import PredictionInputError
from liverforce.serve.input_frame import InputFrame, is_named
from liverforce.serve.predictor import Predictor, _row_label
from liverforce.tracking.store import with_retry

MODEL_NAME = "model"
#: columns of the pyfunc output frame (source-frame force, N)
OUTPUT_COLUMNS = ("fx_n", "fy_n", "fz_n")
#: further columns for a model with a calibrated interval: the local force (t1, t2, n) and its half-widths, N
INTERVAL_COLUMNS = ("ft1_n", "ft2_n", "fn_n", "ft1_half_n", "ft2_half_n", "fn_half_n")
#: the last column: each row's warnings (Predictor.predict_arrays: the case's geometric state outside the training
#: range, a camera cloud's departures from the training clouds, a force beyond training's), "; "-joined, "" when none
WARNINGS_COLUMN = "warnings"
#: the column before it: why the serving checks refused the row (the words ``Predictor.predict_arrays`` raises,
#: ``"case <id>: ..."``), "" when predicted; the column ``liverforce predict --shards`` writes
REFUSED_COLUMN = "refused"
#: values of the pyfunc param ``on_refused``: a refused row answered with NaN and its reason (the logged default), or
#: the whole request refused with the first refused row's reason (HTTP 400; what a call without the param gets)
ON_REFUSED = ("row", "request")
_ROI_KEYS = ("roi_undeformed_mm", "roi_deformed_mm", "camera_cloud_mm", "unloaded_cloud_mm", "roi_triangles")  # ragged
# (k, 3) point sets and triangles (vertex indices), flattened


# --------------------------------------------------------------------------
# DataFrame <-> input-contract arrays
# --------------------------------------------------------------------------


def arrays_to_frame(arrays: dict, keys: tuple[str, ...] | list[str]) -> pd.DataFrame:
    """One row per case: vectors as lists of floats, ROI clouds and the ROI patch's triangles flattened to
    ``3 k`` floats, ids as str."""
    cols = {}
    for k in keys:
        v = arrays[k]
        if k in _ROI_KEYS:
            cols[k] = [np.asarray(a, dtype=np.float64).ravel().tolist() for a in v]
        elif k in ("case_id", "geometry_id"):
            cols[k] = [str(x) for x in v]
        else:
            a = np.asarray(v, dtype=np.float64)
            cols[k] = [row.tolist() for row in a.reshape(len(a), -1)]
    return pd.DataFrame(cols)


def frame_to_arrays(df: pd.DataFrame, *, refused: list | None = None) -> dict:
    """Inverse of :func:`arrays_to_frame`.

    A flattened point set (or the ROI patch's triangles) that is not ``3 k`` numbers is refused with a
    :class:`PredictionInputError` naming its row and column (``"case <id>: camera_cloud_mm: ..."``). With
    ``refused`` (one ``""`` per row, as :meth:`~liverforce.serve.Predictor.refine_arrays` takes it) that row gets
    the message there instead, its cell is read as an empty ``(0, 3)`` set, and the other rows are read. The other
    columns are stacked, one ``(n, width)`` array each: a non-number there, or rows of different widths, raise
    ``ValueError`` for the whole frame either way (which of two widths is the wrong one is not for the column to
    say).
    """
    ids = [str(x) for x in df["case_id"]] if "case_id" in df.columns else None
    out: dict = {}
    for k in df.columns:
        col = list(df[k])
        if k in _ROI_KEYS:
            out[k] = [_point_set(k, x, _row_label(ids, i), refused, i) for i, x in enumerate(col)]
        elif k in ("case_id", "geometry_id"):
            out[k] = np.array([str(x) for x in col], dtype=object)
        else:
            out[k] = np.stack([np.asarray(x, dtype=np.float64).ravel() for x in col])
    return out


def _point_set(key: str, x, label: str, refused: list | None, i: int) -> np.ndarray:
    """One flattened cell of a ragged column as ``(k, 3)``: refused (:func:`frame_to_arrays`) unless ``3 k``
    numbers."""
    try:
        a = np.asarray(x, dtype=np.float64).ravel()
        if a.size % 3:
            each = "three vertex indices per triangle" if key == "roi_triangles" else "x, y, z per point"
            raise ValueError(f"{a.size} numbers, not a multiple of 3 ({each}, flattened)")
        return a.reshape(-1, 3)
    except (TypeError, ValueError) as exc:
        why = f"{label}{key}: {exc}"
        if refused is None:
            raise PredictionInputError(why) from None
        refused[i] = why
        return np.zeros((0, 3))


# --------------------------------------------------------------------------
# the pyfunc wrapper
# --------------------------------------------------------------------------


class ForceModelPyfunc(mlflow.pyfunc.PythonModel):
    """MLflow pyfunc around a :class:`liverforce.learn.model.ForceModel` bundle (artifact ``force_model``).

    Input: a DataFrame, one row per case, columns as :func:`arrays_to_frame`
    writes them. Output: a DataFrame ``fx_n, fy_n, fz_n`` (N; the liver's frame, or the inputs' frame below),
    and for a model with a calibrated interval also the local force
    ``ft1_n, ft2_n, fn_n`` and its interval half-widths ``ft1_half_n, ft2_half_n,
    fn_half_n`` (nominal coverage in the bundle's ``meta["interval"]``), ``refused`` (why the serving checks
    refused the row, ``"case <id>: ..."`` or ``"row <i>: ..."``; ``""`` when predicted) and ``warnings``
    (the case's geometric state outside the training range, a camera cloud's departures from the training
    clouds, a predicted force beyond the training forces: those of ``Predictor.predict_cloud``; ``"; "``-joined,
    ``""`` when none, and for a refused row).

    Param ``on_refused``: ``"row"`` answers a request whose rows the serving checks refuse (a NaN or inf point, a
    cloud too sparse or off the grid, a tip beyond it, an exertion point off the surface, units off the training
    scale, too few ROI nodes beyond the tool for a model that leaves out those it hides, a flattened point set not
    ``3 k`` long, a failed registration) as ``liverforce predict --shards`` does: such a row's forces and interval
    columns are NaN (over HTTP ``null``: see below) and its reason is in ``refused``, and the other rows are predicted
    as in a request of them alone (a stochastic observation model draws each row by its ``case_id``, without one
    by its place in the request, so the same whatever rows are refused). A row every check passes but the model
    cannot take (its ``ValueError``) is refused so too, with the model's reason. A request whose every row is
    refused is still answered, every reason given, as ``--shards`` still writes its file. ``"request"``: the first
    refused row refuses the whole request (:class:`PyfuncInputError`, HTTP 400 from MLflow's scoring server, its
    reason the message), as before the param existed. Which applies: a model logged since the param exists has
    ``"row"`` as its signature's default, which MLflow fills in when the request does not say (so over HTTP and
    through ``mlflow.pyfunc.load_model`` the default is ``"row"``); a model logged before has no such param,
    MLflow drops it from the request and this method, not given the key, answers ``"request"``, as such a model
    did when logged. A direct call of this method without the key is taken for such an older model's: pass
    ``on_refused="row"`` for per-row answers (a blank value is the signature's default, ``"row"``). Either way
    the request as a whole is refused when it is not the input contract: a bad ``input_frame``, ``units`` or
    ``on_refused``, a required column missing, a column MLflow's schema refuses, a fixed-width column (exertion
    point, frame, material, tool tip ...) whose rows differ in width.

    A camera-cloud model also takes the optional columns ``unloaded_cloud_mm`` (per row the camera's cloud
    before the tool pushed, flattened; empty: none) and ``contact_tip_mm`` (the tool tip at contact): the
    row's registration is refined from them first (:meth:`~liverforce.serve.Predictor.refine_arrays`).

    Served by MLflow (its scoring server, as in the serve command above; ``mlflow models predict``:
    :func:`_in_mlflow_serving`) the number columns hold None where the frame above has NaN or inf (a refused
    row's, an unbounded interval's half-width), so the JSON answer has ``null`` there: MLflow's scoring server
    writes a float NaN as the bare token ``NaN``, which a strict JSON parser (JavaScript's ``JSON.parse``, Go's
    ``encoding/json``) refuses. A Python caller (``mlflow.pyfunc.load_model(...).predict``) gets the float
    columns with NaN, as the output schema says.

    Param ``observation_seed`` (int, -1 = none) draws the stochastic observation model as in evaluation.
    Params ``input_frame`` and ``units`` (:func:`pyfunc_input_frame`; default ``""``: RAS, and mm unless the
    frame's record or JSON says) give the inputs' frame and units: every column is converted to the model's
    (RAS mm) as :meth:`~liverforce.serve.input_frame.InputFrame.arrays` does, and ``fx_n, fy_n, fz_n`` come back
    in the inputs' frame (the local columns have no global axes). Models logged before these params existed
    ignore them (MLflow drops params outside the signature with a warning): give such a model RAS mm.
    """

    def load_context(self, context) -> None:
        self.model = ForceModel.load(context.artifacts["force_model"])

    def predict(self, context, model_input: pd.DataFrame, params: dict | None = None) -> pd.DataFrame:
        params = params or {}
        seed = int(params.get("observation_seed", -1))
        # the serving checks (shape, NaN/inf, units against the training scale, exertion point on the
        # surface) refuse bad rows with a PredictionInputError naming the row; then the reference path
        predictor = Predictor(self.model)
        try:
            per_row = pyfunc_on_refused(params.get("on_refused"))  # absent: a model logged before the param
            frame = pyfunc_input_frame(params.get("input_frame"), params.get("units"))
            df = pd.DataFrame(model_input)
            refused = [""] * len(df) if per_row else None  # each row's reason so far, "" while it goes on
            try:
                arrays = frame_to_arrays(df, refused=refused)
            except PredictionInputError:
                raise  # a flattened point set not 3 k long, its row named
            except (TypeError, ValueError) as exc:  # a non-number, rows of different widths
                raise PredictionInputError(f"input columns: {exc}") from None
            arrays = frame.arrays(arrays)
            if "case_id" not in arrays:  # each row's place in the request keys its draw, whatever rows are refused
                arrays = {**arrays, ROW_KEY: np.arange(len(df))}
            entered = ((arrays[CLOUD_KEY], arrays[TIP_KEY])  # a refusal gives them back before the registration
                       if CLOUD_KEY in arrays and TIP_KEY in arrays else None)
            # registration refined from unloaded clouds, if given
            arrays, fixes = predictor.refine_arrays(arrays, refused=refused)
            got = predictor.predict_arrays(_held_back(arrays, refused), observation_seed=None if seed < 0 else seed,
                                           return_warnings=True, registrations=fixes, input_frame=frame,
                                           entered=entered, return_refused=per_row)
        except ValueError as exc:  # a refusal (PredictionInputError), or a ValueError the model raised for a row it
            # cannot take ("row": one predict_arrays could not pin on single rows): HTTP 400 with it, not a bare 500
            raise PyfuncInputError(str(exc)) from exc
        force, warnings = got[:2]
        if per_row:  # a row refused before predict_arrays keeps that reason (predict_arrays' is of its NaN point)
            refused = [r or why for r, why in zip(refused, got[2])]
        out = _output_frame(self.model, arrays, force, None if seed < 0 else seed, predictor, warnings, refused)
        if not frame.same_axes:  # the force back in the inputs' frame; the local columns have no global axes
            out[list(OUTPUT_COLUMNS)] = frame.vectors_out(out[list(OUTPUT_COLUMNS)].to_numpy(dtype=np.float64))
        return _json_numbers(out) if _in_mlflow_serving() else out


#: the variable MLflow sets to ``"true"`` where its scoring server answers (``scoring_server.init``, which
#: the serve command runs in each worker), and while ``mlflow models predict`` and the check of a logged
#: model's serving input example run (MLflow 3.x). MLflow's own name, internal to it: read here as text, not
#: imported, so that a release without it leaves the answer as a Python caller gets it (NaN), not an ImportError
MLFLOW_SERVING_ENV = "_MLFLOW_IS_IN_SERVING_ENVIRONMENT"


def _in_mlflow_serving() -> bool:
    """Whether the pyfunc's answer goes to MLflow's scoring server, which writes it as JSON with
    ``json.dump(..., cls=NumpyEncoder)``: a float NaN or inf as the bare tokens ``NaN``/``Infinity``."""
    return os.environ.get(MLFLOW_SERVING_ENV, "").strip().lower() in ("true", "1")


def _json_numbers(out: pd.DataFrame) -> pd.DataFrame:
    """``out`` with each float column that has a NaN or inf (a refused row's forces and interval, an unbounded
    interval's half-width) as an object column of floats and None there: MLflow's scoring server writes None as
    ``null``, where it writes a float NaN as the token ``NaN`` that strict JSON parsers refuse."""
    out = out.copy()
    for c in out.columns:
        if pd.api.types.is_float_dtype(out[c]):
            v = out[c].to_numpy(dtype=np.float64)
            finite = np.isfinite(v)
            if not finite.all():
                out[c] = pd.Series(np.where(finite, v.astype(object), None), index=out.index, dtype=object)
    return out


def pyfunc_on_refused(on_refused: str | None) -> bool:
    """Whether the pyfunc's param ``on_refused`` (:data:`ON_REFUSED`) answers refused rows one by one (``"row"``:
    True) or refuses the whole request (``"request"``: False). None (the key absent: a model logged before the
    param, whose signature MLflow fills in no default from) is ``"request"``; a blank value is the signature's
    default, ``"row"``."""
    if on_refused is None:
        return False
    said = str(on_refused).strip().lower() or ON_REFUSED[0]
    if said not in ON_REFUSED:
        raise PredictionInputError(
            f"on_refused {str(on_refused)[:80]!r}: give 'row' (a refused row's forces NaN and its reason in the "
            "'refused' column, the other rows predicted) or 'request' (the first refused row refuses the whole "
            "request)")
    return said == "row"


def _held_back(arrays: dict, refused: list | None) -> dict:
    """``arrays`` with a NaN exertion point in each row ``refused`` already (an unreadable point set, a failed
    registration): ``Predictor.predict_arrays`` checks every row first and refuses these, before either path or
    any later check reads their placeholder cells."""
    if not refused or not any(refused) or "exertion_point_mm" not in arrays:
        return arrays
    p = np.array(arrays["exertion_point_mm"], dtype=np.float64)
    p[[i for i, r in enumerate(refused) if r]] = np.nan
    return {**arrays, "exertion_point_mm": p}


def pyfunc_input_frame(input_frame: str | None, units: str | None) -> InputFrame:
    """The :class:`~liverforce.serve.input_frame.InputFrame` of the pyfunc's params ``input_frame`` and ``units``.

    ``input_frame``: ``""``/``RAS`` (the model's frame), ``LPS``, or JSON: a 4x4 matrix (``[[...], ...]``, file mm
    to RAS mm), ``{"matrix": [...], "units": "m"}``, or the text of a geometry import record
    ``results/<exp>/geometry/imp-<name>.json`` (its units and frame). A file path is refused: the served model
    reads no file a request names. ``units``: ``""``/``mm``, ``cm``, ``m``.
    """
    frame = str(input_frame or "").strip() or None
    units = str(units or "").strip() or None
    if frame is None or is_named(frame):
        return InputFrame.resolve(frame, units)
    if frame[0] not in "[{":
        raise PredictionInputError(
            f"input_frame {frame[:80]!r}: give RAS, LPS, or as JSON a 4x4 matrix (file mm to RAS mm), "
            '{"matrix": ..., "units": ...} or the text of the import record results/<exp>/geometry/imp-<name>.json; '
            "the served model reads no file a request names")
    try:
        doc = json.loads(frame)
    except (ValueError, RecursionError) as exc:
        raise PredictionInputError(f"input_frame: not valid JSON ({exc}); give RAS, LPS or a 4x4 matrix, "
                                   "{matrix, units} or an import record as JSON") from None
    return InputFrame.resolve(doc, units)


def _output_frame(model: ForceModel, arrays: dict, force: np.ndarray, seed: int | None,
                  predictor: Predictor | None = None, warnings: list | None = None,
                  refused: list | None = None) -> pd.DataFrame:
    """The output columns: ``force`` (already computed), the interval columns when the model has one,
    ``refused`` (each row's reason, ``""`` when predicted; None: every row predicted) and ``warnings`` (each
    row's, from :meth:`Predictor.predict_arrays`; without them the context's and the force's, from
    ``predictor``'s training scale, else a new one's). A refused row's forces and interval are NaN, its warnings
    empty: the interval is computed for the other rows only."""
    n = len(force)
    refused = list(refused) if refused is not None else [""] * n
    bad = np.array([bool(r) for r in refused], dtype=bool)
    rows = np.flatnonzero(~bad)
    out = pd.DataFrame(np.where(bad[:, None], np.nan, force), columns=list(OUTPUT_COLUMNS))
    if model.interval is not None:
        local = np.full((n, len(INTERVAL_COLUMNS)), np.nan)
        if len(rows):
            got = model.predict_interval(arrays if len(rows) == n else subset(arrays, rows), observation_seed=seed)
            local[rows] = np.hstack([got["force_local_n"], got["half_width_local_n"]])
        for j, c in enumerate(INTERVAL_COLUMNS):
            out[c] = local[:, j]
    if warnings is None:
        p = predictor or Predictor(model)
        warnings = [w + f for w, f in zip(p.arrays_warnings(arrays), p.force_warnings(force))]
    out[REFUSED_COLUMN] = refused
    out[WARNINGS_COLUMN] = ["" if r else "; ".join(w) for r, w in zip(refused, warnings)]
    return out


class PyfuncInputError(PredictionInputError, MlflowException):
    """A refused input inside the pyfunc: a :class:`PredictionInputError` that MLflow's scoring
    server answers with HTTP 400 and this message (other exceptions become a generic error)."""

    def __init__(self, message: str):
        MlflowException.__init__(self, message, error_code=INVALID_PARAMETER_VALUE)


#: MLflow "models from code" entry: logged instead of a cloudpickled object, so that loading or
#: serving the pyfunc model runs this file (an import of liverforce) and unpickles nothing.
#: Models logged before the tracking package was split import ``liverforce.tracking.ForceModelPyfunc``:
#: the package keeps that name.
_PYFUNC_CODE = '''"""MLflow pyfunc entry of a liverforce force model (models from code; no pickle)."""
import mlflow

from liverforce.tracking.model import ForceModelPyfunc

mlflow.models.set_model(ForceModelPyfunc())
'''


# --------------------------------------------------------------------------
# logging
# --------------------------------------------------------------------------


def log_force_model(uri: str, run_id: str, model_dir: str | Path, example_arrays: dict, *,
                    call: Callable = with_retry) -> str:
    """Log the bundle ``model_dir`` as the MLflow pyfunc model of run ``run_id`` (signature + input example).

    Parameters
    ----------
    uri : str
        Tracking URI of the run.
    run_id : str
        Resumed for the logging; leaving it marks the run ``FINISHED``
        (``FAILED`` on error): call this last, then set the final status.
    model_dir : path
        A bundle written by :meth:`ForceModel.save`.
    example_arrays : dict
        Input-contract arrays of at least one case (the input example; ``case_id`` optional).
    call : callable
        How to call the store, ``call(fn)`` (default :func:`~liverforce.tracking.store.with_retry`).

    Returns
    -------
    str
        The model URI ``runs:/<run_id>/model``.
    """
    model = ForceModel.load(model_dir)
    keys = list(model.required_inputs())
    if model.representation.is_camera:  # a camera-cloud model is served from a cloud and the tool tip
        keys += ["camera_cloud_mm", "tool_tip_mm"]
        if "camera_cloud_mm" not in example_arrays:  # simulated cases: observe them as in evaluation
            from liverforce.learn.camera import observe_cases

            rep = model.representation
            clouds, tips = observe_cases(example_arrays, rep.camera, rep.half_width_mm, rep.grid_size,
                                         int(model.meta.get("eval_observation_seed", 0)))
            example_arrays = {**example_arrays, "camera_cloud_mm": clouds, "tool_tip_mm": tips}
    if "case_id" in example_arrays:
        keys.insert(0, "case_id")
    example = arrays_to_frame(example_arrays, keys)
    ex = frame_to_arrays(example)
    output = _output_frame(model, ex, model.predict(ex), None)
    signature = infer_signature(example, output, params={"observation_seed": -1, "input_frame": "", "units": "",
                                                         "on_refused": ON_REFUSED[0]})
    # case_id only seeds the per-case observation noise: optional
    cols = [ColSpec(c.type, c.name, required=c.name != "case_id") for c in signature.inputs.inputs]
    if model.representation.is_camera:  # optional: the camera's registration refined from its unloaded view
        kind = {c.name: c.type for c in signature.inputs.inputs}
        cols += [ColSpec(kind["camera_cloud_mm"], "unloaded_cloud_mm", required=False),
                 ColSpec(kind["tool_tip_mm"], "contact_tip_mm", required=False)]
    signature.inputs = Schema(cols)
    # a refused row's forces and interval are NaN (null when served): only its reason and warnings are always there
    signature.outputs = Schema([ColSpec(c.type, c.name, required=c.name in (REFUSED_COLUMN, WARNINGS_COLUMN))
                                for c in signature.outputs.inputs])

    def _log():
        mlflow.set_tracking_uri(uri)
        with tempfile.TemporaryDirectory(prefix="liverforce-pyfunc-") as tmp:
            code = Path(tmp) / "liverforce_force_model.py"
            code.write_text(_PYFUNC_CODE)
            with mlflow.start_run(run_id=run_id):
                mlflow.pyfunc.log_model(
                    name=MODEL_NAME,
                    python_model=str(code),
                    artifacts={"force_model": str(model_dir)},
                    signature=signature,
                    input_example=example,
                    pip_requirements=_requirements(),
                )

    call(_log)
    return f"runs:/{run_id}/{MODEL_NAME}"


def _requirements() -> list[str]:
    reqs = []
    for pkg in ("torch", "numpy", "scipy", "pandas", "liverforce"):
        try:
            reqs.append(f"{pkg}=={version(pkg).split('+')[0]}")
        except PackageNotFoundError:
            continue
    return reqs


# --------------------------------------------------------------------------
# loading, downloading, serving
# --------------------------------------------------------------------------


def load_pyfunc(model_uri: str, tracking_uri: str | None = None):
    """``mlflow.pyfunc.load_model`` (e.g. ``runs:/<run_id>/model``), leaving no download behind.

    Without ``dst_path`` MLflow downloads the model into a new temporary folder
    that it never removes (one per load). Here the download goes to a
    temporary folder that is removed once the model is loaded: loading reads
    the bundle into memory (:meth:`ForceModel.load` reads every file eagerly)
    and the pyfunc reads nothing from disk afterwards.
    """
    if tracking_uri:
        mlflow.set_tracking_uri(tracking_uri)
    with tempfile.TemporaryDirectory(prefix="liverforce-pyfunc-load-") as dst:
        return mlflow.pyfunc.load_model(model_uri, dst_path=dst)


def resolve_model_uri(ref: str) -> str:
    """Run id (32 hex) -> ``runs:/<id>/model``; a name without scheme -> ``models:/<name>/latest``; URIs as given."""
    if re.fullmatch(r"[0-9a-f]{32}", ref):
        return f"runs:/{ref}/{MODEL_NAME}"
    if ":/" in ref:
        return ref
    return f"models:/{ref}/latest"


def download_force_model(model_ref: str, dst_dir: str | Path | None = None, tracking_uri: str | None = None) -> Path:
    """Download a logged force model and return its liverforce bundle directory.

    Parameters
    ----------
    model_ref : str
        ``runs:/<run_id>/model``, a bare run id, ``models:/<name>/<version>``,
        ``models:/<name>@<alias>`` or a registered model name (latest version).
    dst_dir : path, optional
        Where to download (default: a new temporary folder, which the caller
        removes; :meth:`MlflowPredictor.load` removes its own).
    tracking_uri : str, optional
        Tracking (and registry) store; default: MLflow's current one.

    Returns
    -------
    Path
        The bundle (``model.json`` + weights) inside the downloaded pyfunc
        model; load it with :meth:`liverforce.learn.model.ForceModel.load`,
        which never unpickles (the pyfunc's own code is not executed).
    """
    uri = resolve_model_uri(model_ref)
    if tracking_uri:
        mlflow.set_tracking_uri(tracking_uri)
        mlflow.set_registry_uri(tracking_uri)
    dst = Path(dst_dir) if dst_dir is not None else Path(tempfile.mkdtemp(prefix="liverforce-model-"))
    dst.mkdir(parents=True, exist_ok=True)
    local = Path(with_retry(mlflow.artifacts.download_artifacts, artifact_uri=uri, dst_path=str(dst)))
    hits = sorted(local.glob("artifacts/*/model.json")) or sorted(local.glob("**/model.json"))
    if not hits:
        raise FileNotFoundError(f"{uri}: the logged model holds no liverforce bundle (artifacts/*/model.json)")
    return hits[0].parent


def fetch_force_model(model_ref: str, *, tracking_uri: str | None = None, dst_dir: str | Path | None = None) -> Path:
    """:func:`download_force_model` for serving: a failure is a :class:`PredictionInputError` naming the reference.

    This is the ``fetch`` that :meth:`liverforce.serve.predictor.Predictor.load`
    and ``liverforce predict`` receive for references that are not directories.
    """
    try:
        return download_force_model(model_ref, dst_dir=dst_dir, tracking_uri=tracking_uri)
    except (MlflowException, FileNotFoundError, OSError) as exc:
        raise PredictionInputError(f"model {model_ref}: cannot fetch it from MLflow ({exc})") from exc


class MlflowPredictor(Predictor):
    """A :class:`~liverforce.serve.predictor.Predictor` whose :meth:`load` also takes logged models.

    >>> pred = MlflowPredictor.load("runs:/<run_id>/model", tracking_uri="sqlite:///results/mlflow.db")  # doctest: +SKIP
    """

    @classmethod
    def load(cls, ref: str | Path, *, tracking_uri: str | None = None, dst_dir: str | Path | None = None,
             **kw) -> "MlflowPredictor":
        """A bundle directory if ``ref`` is one, else an MLflow run id, ``runs:/`` or ``models:/`` URI or
        registered name, downloaded from ``tracking_uri`` into ``dst_dir`` (kept) or, by default, into a
        temporary folder that is removed once the bundle is read."""
        def fetch(model_ref: str, tmp: Path) -> Path:
            return fetch_force_model(model_ref, tracking_uri=tracking_uri, dst_dir=tmp if dst_dir is None else dst_dir)

        return super().load(ref, fetch=fetch, **kw)


def predict_pyfunc(pyfunc_model, arrays: dict, observation_seed: int | None = None, *,
                   input_frame: str = "", units: str = "") -> np.ndarray:
    """Run a loaded pyfunc model on input-contract ``arrays`` (in ``units`` and ``input_frame``: the pyfunc's
    params, :func:`pyfunc_input_frame`; a 4x4 or a record may be given as a list, array or dict); returns
    ``(n, 3)`` N in the inputs' frame. A refused row refuses the call, as the model refuses a request with
    ``on_refused="request"`` (sent where the model's params take it): :class:`PyfuncInputError` (a
    :class:`PredictionInputError`) with the first refused row's reason. An older model's per-row answer (its
    ``refused`` column) raises the same, with the first reason there."""
    inputs = _pyfunc_inputs(pyfunc_model)
    dropped = sorted({"unloaded_cloud_mm", "contact_tip_mm"} & set(arrays) - inputs)
    if dropped:  # MLflow would drop them and the clouds would be predicted as registered, unrefined
        raise PredictionInputError(f"this model was logged before it took {', '.join(dropped)}: log it again, or "
                                   "refine the registration first (Predictor.refine_arrays)")
    keys = [k for k in arrays if k in inputs]
    df = arrays_to_frame(arrays, keys)
    params = {"observation_seed": -1 if observation_seed is None else observation_seed}
    schema = pyfunc_model.metadata.get_params_schema()
    taken = {p.name for p in schema.params} if schema is not None else set()
    if "on_refused" in taken:  # the first refused row refuses the call, as the server would refuse the request
        params["on_refused"] = "request"
    if input_frame is not None and not isinstance(input_frame, str):  # a 4x4 or a record: the param is JSON text
        input_frame = json.dumps(input_frame, default=lambda a: np.asarray(a).tolist())
    said = {k: v for k, v in (("input_frame", input_frame), ("units", units)) if v}
    if said:
        missing = sorted(set(said) - taken)
        if missing:  # MLflow would drop them with a warning and the model would read the inputs as RAS mm
            raise PredictionInputError(
                f"this model was logged before it took {' and '.join(missing)}: convert the inputs to RAS mm "
                "(liverforce.serve.input_frame.InputFrame.arrays) or log the model again")
        params.update(said)
    out = pd.DataFrame(pyfunc_model.predict(df, params=params))
    why = [r for r in out.get(REFUSED_COLUMN, []) if isinstance(r, str) and r]
    if why:  # a model that answered per row all the same: the first refused row's reason, as the server's 400
        raise PyfuncInputError(why[0])
    return np.asarray(out[list(OUTPUT_COLUMNS)], dtype=np.float64)


def _pyfunc_inputs(pyfunc_model) -> set[str]:
    schema = pyfunc_model.metadata.get_input_schema()
    return set(schema.input_names()) if schema is not None else set()
