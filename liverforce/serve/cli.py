"""``liverforce predict``: a force from a point-cloud file, or forces for whole shards.

Examples
--------
liverforce predict -m results/exp/models/II/pca_sv/model cloud.ply --context ctx.yaml
liverforce predict -m runs:/<run_id>/model nodes.npy --mode nodes --context ctx.json --out force.json
liverforce predict -m <run_id> cloud.csv --surface liver.stl --exertion-point 12 -40 88 --material 0.0016 0.0125
liverforce predict -m results/default/models/IV/cloud_sv/model cloud.ply --surface liver.stl --mesh liver.vtu \
    --exertion-point 12 -40 88 --material 0.0016 0.0125 --tool-tip 11.2 -41.0 84.5   # camera-cloud model
liverforce predict -m results/default/models/IV/cloud_sv/model cloud.ply --unloaded before.ply --mesh liver.vtu \
    --exertion-point 12 -40 88 --material 0.0016 0.0125 --tool-tip 11.2 -41.0 84.5   # registration refined first
liverforce predict -m results/default/models/IV/cloud_sv/model frames/ --tool-tips tips.csv --mesh liver.vtu \
    --exertion-point 12 -40 88 --material 0.0016 0.0125 --out forces.csv   # a recorded sequence: a row per cloud
liverforce predict -m my-registered-model --shards results/exp/shards/II --out preds.parquet
liverforce predict -m results/exp/models/II/pca_sv/model --describe
liverforce predict -m results/lab/models/IV/cloud_sv/model cloud_lps_m.ply --frame results/lab/geometry/imp-lab01.json \
    --mesh results/lab/mesh/imp-lab01.vtu --exertion-point -0.031 0.024 0.029 \
    --material 0.0016 0.0125 0.0053 --tool-tip -0.0305 0.0236 0.0262   # a liver imported from LPS metres; the
    # pre-operative surface is the mesh's own (no --surface): the one the training cases were cut from

Modes for the point-cloud file: ``cloud`` (default) an unordered observed
cloud; ``nodes`` the deformed ROI nodes in the context's ROI order; ``surface``
the deformed positions of every vertex of the context's surface file (of a tet
mesh: every node, interior ones too, in the file's order). A sequence of clouds
(several files, a folder, a (T, N, 3) .npy) with ``--tool-tips`` gives one row
per cloud, a refused cloud with its reason (:mod:`liverforce.serve.sequence`); a
file that cannot be read (a damaged frame) is a refused row too, said on stderr,
unless none can be.
Exit codes: 0 done, 2 input refused (the message says why).

``--shards`` and a sequence of clouds: a case the serving checks refuse does
not stop the batch. Its forces are NaN and its reason is in the ``refused``
column (empty when predicted); the summary counts the refused rows, and how
many there were and the first reasons are printed on stderr. The exit code is 0
while at least one row is predicted, and 2 when every row is refused (the file
is still written, with every reason).

Point inputs are in the model's frame (RAS mm) unless ``--units`` and
``--frame`` (or the context's ``units`` and ``input_frame``) say otherwise
(:mod:`liverforce.serve.input_frame`): then they are converted to it, the
output's ``input_frame`` says how, and ``force_n`` and the interval's ``frame``
rows are given back in the inputs' frame (``force_n_model``: the force in RAS).

Wire into the main parser with ``liverforce.serve.cli.register(sub, fetch=...)``:
``fetch(ref, dst_dir, tracking_uri=...)`` downloads a model given by reference into
``dst_dir``, a temporary folder removed once the model is read (the main
CLI, :mod:`liverforce.cli`, passes the MLflow one of :mod:`liverforce.tracking`;
serving never imports tracking). Without it ``-m`` takes directories only.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from contextlib import contextmanager
from functools import partial
from pathlib import Path
from typing import Callable

import numpy as np

from liverforce.serve.errors import PredictionInputError


def register(subparsers, *, fetch: Callable[..., str | Path] | None = None) -> argparse.ArgumentParser:
    """Add the ``predict`` subcommand to an ``argparse`` subparsers object; returns the subparser.

    ``fetch(ref, dst_dir, tracking_uri=...)`` downloads a model reference that is
    not a directory (run id, ``runs:/``/``models:/`` URI, registered name) into the
    folder ``dst_dir`` and returns its bundle directory, or raises
    :class:`PredictionInputError` (see :meth:`Predictor.load`).
    """
    p = subparsers.add_parser(
        "predict", help="predict the tool force from a point cloud (or whole shards) with a trained model",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("-m", "--model", required=True,
                   help="model directory, MLflow run id, runs:/<id>/model, models:/<name>/<version> "
                        "or a registered name")
    p.add_argument("points", nargs="*", help="point-cloud file (.ply, .pcd, .csv, .npy), in --units and --frame. A "
                                             "recorded sequence at one exertion point: several files, a folder "
                                             "(its cloud files in natural name order) or one .npy of shape (T, N, "
                                             "3), with --tool-tips: one row per cloud (liverforce.serve.sequence)")
    p.add_argument("--mode", choices=("cloud", "nodes", "surface"), default="cloud",
                   help="what the point file holds (default: an unordered observed cloud)")
    p.add_argument("--approximate", action="store_true",
                   help="cloud mode for models that need correspondence: normal-only displacement estimate")
    p.add_argument("--context", help="JSON/YAML context: exertion point, material, surface or ROI + frame (+ the ROI "
                                     "patch's roi_triangles)")
    p.add_argument("--surface", help="undeformed liver surface file (overrides the context's; in --units and "
                                     "--frame). Without it (and without a surface or roi_undeformed in --context), "
                                     "--mesh's own surface (RAS mm): the one the training cases were cut from")
    p.add_argument("--mesh", help="the liver's tet mesh (mm, support regions tagged, e.g. results/<exp>/mesh/<id>.vtu):"
                                  " state-vector models compute the pre-operative stiffness probe from it; without "
                                  "--surface its own surface is the pre-operative one")
    p.add_argument("--exertion-point", nargs=3, type=float, metavar=("X", "Y", "Z"),
                   help="tool contact point (--units and --frame apply)")
    p.add_argument("--tool-tip", nargs=3, type=float, metavar=("X", "Y", "Z"),
                   help="the tool tip's position now (robot kinematics; --units and --frame apply): camera-cloud "
                        "models need it")
    p.add_argument("--tool-tips", metavar="FILE",
                   help="a sequence of clouds: the tool tip of each cloud (robot kinematics), one x y z row per cloud "
                        "in the clouds' order (.csv, .npy; --units and --frame apply)")
    p.add_argument("--threads", type=int, default=1, metavar="N",
                   help="a sequence of clouds: grid them in N threads at once (the compiled path; at most the cores; "
                        "default 1)")
    p.add_argument("--unloaded", metavar="FILE",
                   help="camera-cloud models: the camera's cloud (.ply, .pcd, .csv, .npy) of the same region before "
                        "the tool pushed, the tool touching at the exertion point (--units and --frame apply). The "
                        "registration is refined first: the rigid correction that puts this cloud on the "
                        "pre-operative surface moves the cloud and the tool tip, and the liver's smooth change of "
                        "shape since the scan is taken off their height (liverforce.learn.registration); the "
                        "output's 'registration' says by how much")
    p.add_argument("--shape-degree", type=int, choices=range(5), metavar="N",
                   help="with --unloaded: the degree of the change of shape fitted (0-4; default 3; 0: the rigid "
                        "correction only)")
    p.add_argument("--contact-tip", nargs=3, type=float, metavar=("X", "Y", "Z"),
                   help="with --unloaded: the tool tip at contact (robot kinematics; --units and --frame apply): the "
                        "instrument's fit in the unloaded cloud starts from it, and it gives the shift along the "
                        "surface where the instrument is not seen. Without it only the height and tilt are refined "
                        "(a warning says so)")
    p.add_argument("--material", nargs="+", type=float, metavar="MPA", help="material constants, MPa")
    p.add_argument("--units", choices=("mm", "cm", "m"),
                   help="units of every point input, the context's too (default: the context's units or the "
                        "--frame record's, else mm)")
    p.add_argument("--frame", metavar="FRAME",
                   help="frame of every point input (cloud, surface, exertion point, tool tip, context): RAS "
                        "(default), LPS, a 4x4 file (.npy/.json/.yaml, file mm to RAS mm), or the liver's import "
                        "record results/<exp>/geometry/imp-<name>.json (its units and frame, as the geometry stage "
                        "converted them); the force comes back in this frame. Default: the context's input_frame, "
                        "else RAS. --mesh stays the mesh stage's copy (RAS mm)")
    p.add_argument("--shards", nargs="+", metavar="PATH", help="batch: shard files, folders or manifest.json")
    p.add_argument("--observation-seed", type=int, help="batch: draw the evaluation's observation model")
    p.add_argument("--reference", action="store_true", help="batch and sequences: skip the compiled fast path")
    p.add_argument("--out", help="write the result (.json or .csv for one force; .parquet or .csv for shards; "
                                 ".csv, .parquet or .json for a sequence)")
    p.add_argument("--tracking-uri", help="MLflow tracking URI (default: MLFLOW_TRACKING_URI / MLflow's default)")
    p.add_argument("--describe", action="store_true", help="print what the model needs and how it was trained")
    p.set_defaults(func=cmd_predict, fetch_model=fetch)
    # coordinates in metres are small: argparse (3.11) takes "-5e-05" for an option unless it knows the form
    p._negative_number_matcher = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$")
    return p


def _frame_label(frame) -> str:
    """The output's ``frame``: the frame its forces are given in."""
    return ("liver (source) frame of the inputs" if frame.identity
            else f"the inputs' frame ({'a 4x4 matrix' if frame.label == 'matrix' else frame.label})")


def _error(msg: str) -> int:
    print(f"liverforce predict: error: {msg}", file=sys.stderr)
    return 2


#: ``--shards``: the refused rows' reasons printed (all are in the output's ``refused`` column)
REFUSED_SHOWN = 3


def _refused_rows(reasons: list[str], rows: int, out: str | None, shown: str = "give --out to keep them") -> None:
    """Say on stderr how many of the ``rows`` were refused and the first reasons (``shown``: where the reasons are
    without ``--out``)."""
    where = f"in the 'refused' column of {out}" if out else shown
    every = len(reasons) == rows
    first = "; ".join(reasons[:REFUSED_SHOWN])
    more = f" (and {len(reasons) - REFUSED_SHOWN} more)" if len(reasons) > REFUSED_SHOWN else ""
    print(f"liverforce predict: {'error: ' if every else ''}{len(reasons)} of {rows} rows refused, their forces NaN "
          f"({'every row' if every else 'the other rows were predicted'}; each reason {where}). The first: "
          f"{first}{more}", file=sys.stderr)


def cmd_predict(args) -> int:
    """Run ``liverforce predict``; returns the exit code."""
    import torch

    if torch.get_num_threads() != 1:
        torch.set_num_threads(1)
    from liverforce.learn.model import ModelFormatError

    try:
        return _run(args)
    except PredictionInputError as exc:
        return _error(str(exc))
    except ModelFormatError as exc:  # e.g. an interval no path can give (a bundle edited by hand), read on use
        return _error(f"model {args.model}: {exc}")


def _run(args) -> int:
    from liverforce.atomic import write_text_atomic
    from liverforce.serve.files import read_cloud, read_context, read_points
    from liverforce.serve.input_frame import is_named
    from liverforce.serve.predictor import Predictor

    fetch_model = getattr(args, "fetch_model", None)
    fetch = partial(fetch_model, tracking_uri=args.tracking_uri) if fetch_model is not None else None
    predictor = Predictor.load(args.model, fetch=fetch)
    if args.describe:
        print(json.dumps(predictor.describe(), indent=2, default=str))
        return 0
    if args.shards:
        from liverforce.serve.batch import predict_shards

        if args.points:
            return _error("give either a point-cloud file or --shards, not both")
        if args.frame or args.units:
            return _error("--frame and --units apply to point inputs; shards are in the model's frame (RAS mm) "
                          "already")
        summary = predict_shards(predictor, args.shards, args.out, observation_seed=args.observation_seed,
                                 fast=not args.reference)
        reasons = [r for r in summary.pop("frame")["refused"] if r]
        print(json.dumps(summary, indent=2, default=float))
        if reasons:
            _refused_rows(reasons, summary["rows"], args.out)
        return 2 if reasons and not summary["predicted"] else 0
    if not args.points:
        return _error("give a point-cloud file (or --shards for batch prediction)")
    from liverforce.serve.sequence import is_sequence

    sequence = args.tool_tips is not None or is_sequence(args.points)
    if sequence and args.mode != "cloud":
        return _error("a sequence of files is predicted in --mode cloud (camera clouds) only; give one file for "
                      "--mode nodes or surface")
    if sequence and args.approximate:
        return _error("--approximate reads one cloud for a correspondence model; a sequence needs a camera-cloud "
                      "model")
    if sequence and not predictor.model.representation.is_camera:
        return _error(f"a sequence of clouds needs a camera-cloud model (roi_features: cloud); this model reads "
                      f"{predictor.model.representation.features} node displacements: give it one file at a time")
    if args.tool_tips is not None and args.tool_tip is not None:
        return _error("give --tool-tips (one tip per cloud) or --tool-tip (one for every cloud), not both")
    if args.threads < 1:
        return _error(f"--threads: need a whole number >= 1, got {args.threads}")
    if args.threads != 1 and not sequence:
        return _error("--threads grids a sequence of clouds at once; one cloud is predicted on one thread")
    overrides = {"exertion_point_mm": args.exertion_point, "material_params_mpa": args.material, "units": args.units}
    # file paths given here are relative to the working directory (a context file's own are relative to it)
    if args.frame:
        overrides["input_frame"] = args.frame if is_named(args.frame) else str(Path(args.frame).absolute())
    if args.surface:
        overrides["surface"] = str(Path(args.surface).absolute())
    if args.mesh:
        overrides["mesh"] = str(Path(args.mesh).absolute())
    preop, frame = read_context(args.context, predictor, overrides=overrides)
    notes = []  # what reading the camera clouds did (a PCD's NaN or inf points dropped): the output's warnings
    pts = None
    if not sequence:
        if args.mode == "cloud":
            pts, note = read_cloud(args.points[0], frame=frame)
            notes += [note] if note else []
        else:  # ordered nodes or surface vertices: none may be dropped (a NaN is refused by the checks)
            pts = read_points(args.points[0], frame=frame)
        pts = frame.points(pts)
    info: dict = {"mode": args.mode}
    if (args.unloaded or args.contact_tip) and args.mode != "cloud":
        return _error("--unloaded and --contact-tip refine a camera cloud's registration: --mode cloud only")
    if args.shape_degree is not None and not args.unloaded:
        return _error("--shape-degree goes with --unloaded (the change of shape is fitted to that cloud)")
    if args.contact_tip and not args.unloaded:
        return _error("--contact-tip goes with --unloaded (the camera's cloud before the tool pushed)")
    fix = None
    if args.unloaded:
        unloaded, note = read_cloud(args.unloaded, frame=frame)
        notes += [note] if note else []
        with _saying(notes):
            fix = predictor.refine_registration(frame.points(unloaded), preop,
                                                None if args.contact_tip is None else frame.points(args.contact_tip),
                                                shape_degree=args.shape_degree)
    if sequence:
        return _sequence(args, predictor, preop, frame, fix, notes)
    if args.mode == "cloud":
        tip = None if args.tool_tip is None else frame.points(args.tool_tip)
        with _saying(notes):
            force, extra = predictor.predict_cloud(pts, preop, approximate=args.approximate, tool_tip_mm=tip,
                                                   return_info=True, registration=fix, input_frame=frame)
        info.update(extra)
        info["warnings"] = notes + info["warnings"]
    else:
        nodes = preop.roi_of_surface(pts) if args.mode == "surface" else pts
        iv = predictor.interval(nodes, preop)  # the force and its interval in one pass (None: no interval)
        force = predictor.predict(nodes, preop) if iv is None else np.asarray(iv.pop("force_n"))
        if iv is not None:
            info["interval"] = iv
        far = predictor.distance_warnings(None if iv is None else [iv.get("input_distance")])
        info["warnings"] = predictor.context_warnings(preop) + predictor.force_warnings(force)[0] + (far or [[]])[0]
    force_in = frame.vectors_out(force)
    doc = {"force_n": [float(v) for v in force_in], "magnitude_n": float(np.linalg.norm(force)),
           "frame": _frame_label(frame),
           "input_frame": frame.describe(), "model": predictor.source}
    if not frame.same_axes:
        doc["force_n_model"] = [float(v) for v in force]  # RAS, the frame the liver was meshed in
        if "interval" in info:  # local components are frame-free; their axes go back to the inputs' frame
            iv = info["interval"]
            iv["frame"] = frame.vectors_out(iv["frame"]).tolist()
            if "force_n" in iv:
                iv["force_n"] = frame.vectors_out(iv["force_n"]).tolist()
    doc.update(info)
    if args.out and args.out.lower().endswith(".csv"):
        write_text_atomic(args.out, "fx_n,fy_n,fz_n\n" + ",".join(repr(float(v)) for v in force_in) + "\n")
    elif args.out:
        write_text_atomic(args.out, json.dumps(doc, indent=2) + "\n")
    print(json.dumps(doc))
    return 0


@contextmanager
def _saying(notes: list[str]):
    """A refusal raised inside says what reading the clouds did (a PCD's points dropped), after its own reason:
    a cloud refused for too few points may be a depth camera's frame that was mostly pixels without depth."""
    try:
        yield
    except PredictionInputError as exc:
        if not notes:
            raise
        raise PredictionInputError(f"{exc} (reading the clouds: {'; '.join(notes)})") from None


def _sequence(args, predictor, preop, frame, fix, notes: list[str]) -> int:
    """``liverforce predict`` of a recorded sequence of clouds (:mod:`liverforce.serve.sequence`): one row per
    cloud to ``--out`` (.csv, .parquet or .json), a summary (and the rows, without ``--out``) on stdout. ``notes``:
    what reading ``--unloaded`` did (the summary's ``warnings``); a cloud's own (a PCD's NaN or inf points dropped)
    lead its row's warnings. A file that cannot be read is its row's refusal (counted in the summary's
    ``unreadable``, said on stderr); its tool tip keeps its row of ``--tool-tips``."""
    from liverforce.atomic import write_text_atomic
    from liverforce.serve.files import write_frame
    from liverforce.serve.sequence import predict_sequence, read_sequence, read_tips

    if args.out and Path(args.out).suffix.lower() not in (".csv", ".parquet", ".json"):
        return _error(f"--out {args.out}: a sequence's rows are written as .csv, .parquet or .json")
    read: dict[int, str] = {}
    unreadable: dict[int, str] = {}  # the files that could not be read: each its own refused row
    names, clouds = read_sequence(args.points, skip=(args.tool_tips, args.out), frame=frame,  # skip: if kept there
                                  notes=read, errors=unreadable)
    if args.tool_tips is not None:  # one tip per file, a damaged frame's too
        tips = read_tips(args.tool_tips, len(clouds), frame, unreadable=[names[k] for k in sorted(unreadable)])
    elif args.tool_tip is not None:
        tips = np.tile(np.asarray(args.tool_tip, dtype=np.float64), (len(clouds), 1))
    else:
        return _error("a camera-cloud model needs the tool tip of each cloud: --tool-tips FILE (one x y z row per "
                      "cloud, robot kinematics), or --tool-tip X Y Z if the tool stood still")
    rows, summary = predict_sequence(predictor, preop, frame, clouds, tips, registration=fix, threads=args.threads,
                                     reference=args.reference, unreadable=unreadable)
    rows = [{"cloud": name, **row} for name, row in zip(names, rows)]
    for k, note in read.items():
        rows[k]["warnings"] = "; ".join([note] + ([rows[k]["warnings"]] if rows[k]["warnings"] else []))
    plain = [{k: None if isinstance(v, float) and v != v else v for k, v in r.items()} for r in rows]  # JSON: null
    summary.update({"frame": _frame_label(frame),
                    "input_frame": frame.describe(), "model": predictor.source,
                    "context_warnings": predictor.context_warnings(preop)})
    if fix is not None:
        summary["registration"] = {**fix.to_dict(), "description": fix.describe()}
    if notes:
        summary["warnings"] = notes
    if args.out:
        if args.out.lower().endswith(".json"):
            write_text_atomic(args.out, json.dumps({**summary, "rows": plain}, indent=2) + "\n")
        else:
            import pandas as pd

            write_frame(pd.DataFrame(rows), args.out)
        summary["out"] = str(args.out)
    else:
        summary["rows"] = plain
    print(json.dumps(summary))
    if unreadable:
        _unreadable_files([unreadable[k] for k in sorted(unreadable)], len(rows), summary["predicted"], args.out)
    elif summary["refused"]:  # as --shards: how many the model's checks refused, and the first reasons
        _refused_rows([r["refused"] for r in rows if r["refused"]], len(rows), args.out, "in its row's 'refused'")
    return 2 if summary["refused"] and not summary["predicted"] else 0


def _unreadable_files(reasons: list[str], clouds: int, predicted: int, out: str | None) -> None:
    """Say on stderr how many of a sequence's ``clouds`` files could not be read, how many of the others were
    ``predicted`` (the rest refused by the model's checks), and the first reasons."""
    where = f"in the 'refused' column of {out}" if out else "in its row's 'refused'"
    first = "; ".join(reasons[:REFUSED_SHOWN])
    more = f" (and {len(reasons) - REFUSED_SHOWN} more)" if len(reasons) > REFUSED_SHOWN else ""
    read = clouds - len(reasons)
    others = (f"the other {read} predicted" if predicted == read else
              f"of the other {read}, {predicted} predicted and {read - predicted} refused by the model's checks")
    print(f"liverforce predict: {len(reasons)} of {clouds} files could not be read as clouds, their rows refused "
          f"with NaN forces ({others}; each reason {where}). The first: {first}{more}", file=sys.stderr)
