"""A recorded sequence of camera clouds at one exertion point: one force (and interval) per cloud.

``liverforce predict -m MODEL frames/ --tool-tips tips.csv --mesh liver.vtu --exertion-point X Y Z --material ...
--out forces.csv`` reads a folder of clouds (or several files, or one ``.npy`` of shape (T, N, 3)), the tool tip
of each cloud from the robot's kinematics (one x y z row per cloud, in order), and gives one row per cloud: the
force in the inputs' frame, its magnitude, the interval's half-widths per local component, and, for a cloud the
model cannot be trusted on, the reason it was refused (the other clouds are still predicted). Every point input
is in ``--units`` and ``--frame`` as for one cloud, and ``--unloaded`` refines the registration once for the
whole sequence.

A camera model with the PCA encoder (the shipped ``cloud_sv``) runs on the compiled path
(:class:`liverforce.serve.compiled_cloud.CompiledCloud`: the context checked once, every cloud gridded by one
kernel, ``--threads`` threads at once), which equals the reference path (``Predictor.predict_cloud``, one cloud
at a time; ``--reference``) to 1e-6 N and refuses the same clouds with the same reasons.
"""

from __future__ import annotations

import re
import time
from pathlib import Path

import numpy as np

from liverforce.serve.errors import PredictionInputError
from liverforce.serve.files import read_cloud, read_points

CLOUD_SUFFIXES = (".ply", ".pcd", ".csv", ".txt", ".xyz", ".npy")
COMPONENTS = ("t1", "t2", "n")  # the interval's local components


def _natural(name: str) -> tuple:
    """Sort key: runs of ASCII digits as numbers (``frame_2`` before ``frame_10``), then the name (``f01`` before
    ``f1``: a total order, whatever order the folder lists them in)."""
    return [int(p) if i % 2 else p for i, p in enumerate(re.split(r"([0-9]+)", name))], name


def _stack(path: Path) -> np.ndarray | None:
    """The (T, N, 3) array of a ``.npy`` file of stacked clouds (memory-mapped), None for any other file."""
    if path.suffix.lower() != ".npy" or not path.is_file():
        return None
    try:
        arr = np.load(path, allow_pickle=False, mmap_mode="r")
    except (ValueError, OSError) as exc:
        raise PredictionInputError(f"{path}: cannot read the point clouds ({exc})") from None
    return arr if arr.ndim == 3 else None


def is_sequence(paths: list[str | Path]) -> bool:
    """Whether ``paths`` (the command line's point files) are a sequence: several files, a folder, or one ``.npy``
    of stacked clouds (T, N, 3)."""
    return len(paths) > 1 or any(Path(p).is_dir() for p in paths) or _stack(Path(paths[0])) is not None


def read_sequence(paths: list[str | Path], skip=(), frame=None,
                  notes: dict | None = None) -> tuple[list[str], list[np.ndarray]]:
    """The clouds of a sequence as given (the file's units and frame) and a name for each.

    ``paths``: several cloud files (in the order given); one folder (its ``.ply``, ``.pcd``, ``.csv``, ``.txt``,
    ``.xyz`` and ``.npy`` files in natural name order, but the files ``skip``: the tips and the output, if they are
    kept there); or one ``.npy`` file of shape (T, N, 3) (names ``file.npy[k]``). ``frame``: the inputs'
    :class:`~liverforce.serve.input_frame.InputFrame` (None: mm), whose units a text file's header may not
    contradict (:func:`~liverforce.serve.files.check_header_units`). Each file is read as a camera cloud
    (:func:`~liverforce.serve.files.read_cloud`: a PCD's NaN or inf points dropped); ``notes``, a dict given here, gets
    the note of each cloud that had some dropped, by its position (from 0).
    """
    paths = [Path(p) for p in paths]
    if len(paths) == 1 and paths[0].is_dir():
        folder = paths[0]
        skip = {Path(p).resolve() for p in skip if p is not None}
        files = sorted((f for f in paths[0].iterdir() if f.is_file() and f.suffix.lower() in CLOUD_SUFFIXES
                        and f.resolve() not in skip), key=lambda f: _natural(f.name))
        if not files:
            raise PredictionInputError(f"{paths[0]}: no point-cloud files ({', '.join(CLOUD_SUFFIXES)}) in this folder")
        try:
            return [f.name for f in files], [_read(f, k, frame, notes) for k, f in enumerate(files)]
        except PredictionInputError as exc:
            raise PredictionInputError(f"{exc}. A sequence's folder is read as its clouds: repair or remove a "
                                       f"damaged cloud, keep only the clouds in {folder} (the tips and the output "
                                       "may stay), or name the cloud files") from None
    stack = _stack(paths[0]) if len(paths) == 1 else None
    if stack is not None:
        if stack.shape[0] == 0 or stack.shape[2] != 3 or not np.issubdtype(stack.dtype, np.number):
            raise PredictionInputError(f"{paths[0]}: a stack of clouds must have shape (T, N, 3) with T >= 1, got "
                                       f"{stack.shape}")
        return ([f"{paths[0].name}[{k}]" for k in range(stack.shape[0])],
                [np.asarray(c, dtype=np.float64) for c in stack])
    return [p.name for p in paths], [_read(p, k, frame, notes) for k, p in enumerate(paths)]


def _read(path: Path, k: int, frame, notes: dict | None) -> np.ndarray:
    """One cloud of a sequence (:func:`~liverforce.serve.files.read_cloud`), its note kept in ``notes[k]``."""
    cloud, note = read_cloud(path, frame=frame, empty=True)  # a frame without a point is refused as its row
    if note is not None and notes is not None:
        notes[k] = note
    return cloud


def read_tips(path: str | Path, n: int, frame=None) -> np.ndarray:
    """The tool tip of each of ``n`` clouds: ``n`` rows of x, y, z (``.csv``/``.txt``/``.npy``, as given; a text
    file's header may not name another unit than ``frame``'s, as :func:`read_sequence`)."""
    if not Path(path).is_file():
        raise PredictionInputError(f"--tool-tips {path}: no such file of tool tips")
    try:
        tips = read_points(path, frame=frame)
    except PredictionInputError as exc:
        raise PredictionInputError(f"--tool-tips: {str(exc).replace('point cloud', 'tool tips')}") from None
    if len(tips) != n:
        raise PredictionInputError(f"--tool-tips {path}: {len(tips)} tips for {n} clouds; give one x y z row per "
                                   "cloud, in the clouds' order")
    return tips


def predict_sequence(predictor, preop, frame, clouds: list[np.ndarray], tips: np.ndarray, *, registration=None,
                     threads: int = 1, reference: bool = False) -> tuple[list[dict], dict]:
    """One row per cloud (``clouds`` and ``tips`` in the inputs' frame ``frame``, converted here) and a summary.

    Rows: ``fx_n, fy_n, fz_n`` (the inputs' frame), ``magnitude_n``, ``half_width_{t1,t2,n}_n`` (the interval's
    local half-widths; NaN without an interval), ``refused`` (the reason, or empty) and ``warnings`` (joined by
    ``"; "``). A refused cloud gets NaN forces. The summary: clouds, predicted, refused, the path taken, threads,
    seconds and clouds per second."""
    from liverforce.learn.encoders import PCAEncoder

    model = predictor.model
    if not model.representation.is_camera:
        raise PredictionInputError(f"a sequence of clouds needs a camera-cloud model (roi_features: cloud); this "
                                   f"model reads {model.representation.features} node displacements")
    P = [frame.points(c) for c in clouds]
    T = frame.points(np.asarray(tips, dtype=np.float64).reshape(-1, 3))
    compiled = not reference and isinstance(model.pre.encoder, PCAEncoder)
    t0 = time.perf_counter()
    if compiled:
        fast = predictor.compile_cloud(preop, registration=registration, declared=frame)
        t0 = time.perf_counter()  # the compilation is once per exertion point, not per cloud
        res = fast.predict_batch(P, T, threads=threads)
        force, half, refused, warns = res.force, res.half_width, res.refused, res.warnings
    else:
        force = np.full((len(P), 3), np.nan)
        half = None
        refused, warns = [None] * len(P), [[] for _ in P]
        for k, (c, tip) in enumerate(zip(P, T)):
            try:
                force[k], info = predictor.predict_cloud(c, preop, tool_tip_mm=tip, return_info=True,
                                                         registration=registration, input_frame=frame)
            except PredictionInputError as exc:
                refused[k] = str(exc)
                continue
            warns[k] = info.get("warnings", [])
            iv = info.get("interval")
            if iv is not None:
                half = np.full((len(P), 3), np.nan) if half is None else half
                half[k] = iv["half_width_local_n"]
    seconds = time.perf_counter() - t0
    out = frame.vectors_out(force)
    mag = np.linalg.norm(force, axis=1)
    hw = np.full((len(P), 3), np.nan) if half is None else np.asarray(half, dtype=np.float64)
    rows = [{"fx_n": float(out[k, 0]), "fy_n": float(out[k, 1]), "fz_n": float(out[k, 2]),
             "magnitude_n": float(mag[k]),
             **{f"half_width_{c}_n": float(hw[k, j]) for j, c in enumerate(COMPONENTS)},
             "refused": refused[k] or "", "warnings": "; ".join(warns[k] or [])} for k in range(len(P))]
    n_ok = sum(r is None for r in refused)
    summary = {"clouds": len(P), "predicted": n_ok, "refused": len(P) - n_ok,
               "path": "compiled" if compiled else "reference", "threads": threads if compiled else 1,
               "seconds": seconds, "clouds_per_s": len(P) / seconds if seconds > 0 else float("inf")}
    return rows, summary
