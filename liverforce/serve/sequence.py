"""A recorded sequence of camera clouds at one exertion point: one force (and interval) per cloud.

``liverforce predict -m MODEL frames/ --tool-tips tips.csv --mesh liver.vtu --exertion-point X Y Z --material ...
--out forces.csv`` reads a folder of clouds (or several files, or one ``.npy`` of shape (T, N, 3)), the tool tip
of each cloud from the robot's kinematics (one x y z row per cloud, in order), and gives one row per cloud: the
force in the inputs' frame, its magnitude, the interval's half-widths per local component, and, for a cloud the
model cannot be trusted on, the reason it was refused (the other clouds are still predicted). A file that cannot
be read at all (a frame the camera's driver cut short, a CSV with a broken line, a file that is not a cloud) is
its own refused row too, in its place, naming the file and what is wrong with it; its tool tip keeps its row of
the tips file (one per file), and a sequence none of whose files can be read is refused. Every point input is in
``--units`` and ``--frame`` as for one cloud, and ``--unloaded`` refines the registration once for the whole
sequence.

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
UNREADABLE_NAMED = 3  # the files that could not be read named in a refusal of the tool tips' count
#: a sequence's file that was there when the folder was listed (or the names checked) and is not when it is read
GONE = ("{}: this file was listed with the sequence's files but was gone when it was read: moved or deleted "
        "meanwhile; is the recording still being written or copied?")


def _natural(name: str) -> tuple:
    """Sort key: runs of ASCII digits as numbers (``frame_2`` before ``frame_10``), then the name (``f01`` before
    ``f1``: a total order, whatever order the folder lists them in)."""
    return [int(p) if i % 2 else p for i, p in enumerate(re.split(r"([0-9]+)", name))], name


def _stack(path: Path) -> np.ndarray | None:
    """The (T, N, 3) array of a ``.npy`` file of stacked clouds (memory-mapped), None for any other file."""
    if path.suffix.lower() != ".npy" or not path.is_file():
        return None
    try:
        try:
            arr = np.load(path, allow_pickle=False, mmap_mode="r")
        except ValueError:  # numpy's map of a file cut short says 'mmap length is greater than file size': its
            arr = np.load(path, allow_pickle=False)  # reading says how many values it could not read
    except (ValueError, OSError, EOFError) as exc:  # EOFError: numpy's for an empty or cut-short .npy
        raise PredictionInputError(f"{path}: cannot read the point clouds ({type(exc).__name__}: {exc})") from None
    return arr if arr.ndim == 3 else None


def is_sequence(paths: list[str | Path]) -> bool:
    """Whether ``paths`` (the command line's point files) are a sequence: several files, a folder, or one ``.npy``
    of stacked clouds (T, N, 3)."""
    return len(paths) > 1 or any(Path(p).is_dir() for p in paths) or _stack(Path(paths[0])) is not None


def read_sequence(paths: list[str | Path], skip=(), frame=None, notes: dict | None = None,
                  errors: dict | None = None) -> tuple[list[str], list[np.ndarray | None]]:
    """The clouds of a sequence as given (the file's units and frame) and a name for each.

    ``paths``: several cloud files (in the order given); one folder (its ``.ply``, ``.pcd``, ``.csv``, ``.txt``,
    ``.xyz`` and ``.npy`` files in natural name order, but the files ``skip``: the tips and the output, if they are
    kept there); or one ``.npy`` file of shape (T, N, 3) (names ``file.npy[k]``). ``frame``: the inputs'
    :class:`~liverforce.serve.input_frame.InputFrame` (None: mm), whose units a text file's header may not
    contradict (:func:`~liverforce.serve.files.check_header_units`). Each file is read as a camera cloud
    (:func:`~liverforce.serve.files.read_cloud`: a PCD's NaN or inf points dropped); ``notes``, a dict given here, gets
    the note of each cloud that had some dropped, by its position (from 0).

    ``errors``: None (default), the first file that cannot be read (a truncated PCD or PLY, a CSV with a broken
    line, a file that is not a cloud) refuses the whole sequence. A dict given here takes each such file as its
    frame's refusal instead: its cloud is None and ``errors`` gets, by its position, the reason (``read_cloud``'s,
    which names the file, or :data:`GONE` for a file moved or deleted since it was listed, and what to do), the
    other files read on; still refused are a file named that does not exist and a sequence none of whose files can
    be read (naming the first file's problem and the count). A stack ``.npy`` is one file: read whole or refused.
    """
    paths = [Path(p) for p in paths]
    if len(paths) == 1 and paths[0].is_dir():
        folder = paths[0]
        skip = {Path(p).resolve() for p in skip if p is not None}
        files = sorted((f for f in paths[0].iterdir() if f.is_file() and f.suffix.lower() in CLOUD_SUFFIXES
                        and f.resolve() not in skip), key=lambda f: _natural(f.name))
        if not files:
            raise PredictionInputError(f"{paths[0]}: no point-cloud files ({', '.join(CLOUD_SUFFIXES)}) in this folder")
        advice = (f"A sequence's folder is read as its clouds: repair or remove a damaged cloud, keep only the clouds "
                  f"in {folder} (the tips and the output may stay), or name the cloud files")
        try:
            return [f.name for f in files], _read_all(files, frame, notes, errors)
        except PredictionInputError as exc:
            raise PredictionInputError(f"{exc}. {advice}") from None
    stack = _stack(paths[0]) if len(paths) == 1 else None
    if stack is not None:
        if stack.shape[0] == 0 or stack.shape[2] != 3 or not np.issubdtype(stack.dtype, np.number):
            raise PredictionInputError(f"{paths[0]}: a stack of clouds must have shape (T, N, 3) with T >= 1, got "
                                       f"{stack.shape}")
        return ([f"{paths[0].name}[{k}]" for k in range(stack.shape[0])],
                [np.asarray(c, dtype=np.float64) for c in stack])
    missing = next((p for p in paths if not p.is_file()), None)
    if missing is not None:  # a file named that is not there: a mistyped name, not a damaged frame
        raise PredictionInputError(f"{missing}: no such point-cloud file")
    try:
        return [p.name for p in paths], _read_all(paths, frame, notes, errors)
    except PredictionInputError as exc:
        if errors is None or len(paths) == 1:
            raise
        raise PredictionInputError(f"{exc}. Repair or export the clouds again, or name only the cloud files"
                                   ) from None


def _read_all(files: list[Path], frame, notes: dict | None, errors: dict | None) -> list:
    """The clouds of ``files`` (:func:`_read`); with ``errors`` (a dict), a file that cannot be read is None there
    and its reason in ``errors`` (:func:`read_sequence`), unless none can be read."""
    if errors is None:
        return [_read(f, k, frame, notes) for k, f in enumerate(files)]
    clouds, failed = [], {}
    for k, f in enumerate(files):
        try:
            clouds.append(_read(f, k, frame, notes))
        except PredictionInputError as exc:
            clouds.append(None)
            failed[k] = str(exc) if f.exists() else GONE.format(f)
    if len(failed) == len(files):
        first = failed[0]
        raise PredictionInputError(first if len(files) == 1 else
                                   f"none of the {len(files)} files of the sequence could be read as a point cloud; "
                                   f"the first: {first}")
    errors.update({k: f"{why} (this file could not be read as a cloud: its row has no force, the other files are "
                      "read on; repair or export it again, or remove it and its row of tool tips)"
                   for k, why in failed.items()})
    return clouds


def _read(path: Path, k: int, frame, notes: dict | None) -> np.ndarray:
    """One cloud of a sequence (:func:`~liverforce.serve.files.read_cloud`), its note kept in ``notes[k]``."""
    cloud, note = read_cloud(path, frame=frame, empty=True)  # a frame without a point is refused as its row
    if note is not None and notes is not None:
        notes[k] = note
    return cloud


def read_tips(path: str | Path, n: int, frame=None, unreadable=()) -> np.ndarray:
    """The tool tip of each of ``n`` clouds: ``n`` rows of x, y, z (``.csv``/``.txt``/``.npy``, as given; a text
    file's header may not name another unit than ``frame``'s, as :func:`read_sequence`).

    ``n`` counts the files that could not be read as clouds too (a damaged frame keeps its tip); ``unreadable``,
    their names, are named when the count differs: a file in the folder that is not a frame is the likely cause.
    """
    if not Path(path).is_file():
        raise PredictionInputError(f"--tool-tips {path}: no such file of tool tips")
    try:
        tips = read_points(path, frame=frame)
    except PredictionInputError as exc:
        raise PredictionInputError(f"--tool-tips: {str(exc).replace('point cloud', 'tool tips')}") from None
    if len(tips) != n:
        unreadable = list(unreadable)
        named = ", ".join(unreadable[:UNREADABLE_NAMED]) + (f" and {len(unreadable) - UNREADABLE_NAMED} more"
                                                             if len(unreadable) > UNREADABLE_NAMED else "")
        stray = (f". {len(unreadable)} of the {n} files could not be read as clouds ({named}), each counted as a "
                 "frame: if one is not a frame of the recording, move it out of the clouds' folder or name the "
                 "cloud files; a damaged frame keeps its row of tips" if unreadable else "")
        raise PredictionInputError(f"--tool-tips {path}: {len(tips)} tips for {n} clouds; give one x y z row per "
                                   f"cloud, in the clouds' order{stray}")
    return tips


def predict_sequence(predictor, preop, frame, clouds: list[np.ndarray | None], tips: np.ndarray, *,
                     registration=None, threads: int = 1, reference: bool = False,
                     unreadable: dict[int, str] | None = None) -> tuple[list[dict], dict]:
    """One row per cloud (``clouds`` and ``tips`` in the inputs' frame ``frame``, converted here) and a summary.

    Rows: ``fx_n, fy_n, fz_n`` (the inputs' frame), ``magnitude_n``, ``half_width_{t1,t2,n}_n`` (the interval's
    local half-widths; NaN without an interval), ``refused`` (the reason, or empty) and ``warnings`` (joined by
    ``"; "``). A refused cloud gets NaN forces. ``unreadable``: the files that could not be read, by position
    (:func:`read_sequence`'s ``errors``; their clouds None, their tips kept): each is refused with its reason,
    the others predicted. The summary: clouds, predicted, refused (the unreadable ones too), unreadable, the path
    taken, threads, seconds and clouds per second (of the clouds read)."""
    from liverforce.learn.encoders import PCAEncoder

    model = predictor.model
    if not model.representation.is_camera:
        raise PredictionInputError(f"a sequence of clouds needs a camera-cloud model (roi_features: cloud); this "
                                   f"model reads {model.representation.features} node displacements")
    n = len(clouds)  # a row for every file: the clouds read, in their places, and the unreadable ones
    unreadable = dict(unreadable or {})
    outside = sorted(k for k in unreadable if not 0 <= k < n)
    if outside:
        raise ValueError(f"unreadable: positions {outside} are not among the {n} clouds (from 0)")
    blank = [k for k, c in enumerate(clouds) if c is None and k not in unreadable]
    if blank:
        raise ValueError(f"clouds: {blank} are None without their reason in unreadable (read_sequence's errors)")
    tips = np.asarray(tips, dtype=np.float64).reshape(-1, 3)
    if len(tips) != n:
        raise PredictionInputError(f"tips: need one x, y, z tip per cloud ({n}, the unreadable ones too), got "
                                   f"{len(tips)}")
    if n and len(unreadable) == n:
        raise PredictionInputError(f"none of the {n} clouds of the sequence could be read; the first: "
                                   f"{unreadable[min(unreadable)]}")
    read = [k for k in range(n) if k not in unreadable]  # predicted; the others' rows give their reasons
    P = [frame.points(clouds[k]) for k in read]
    T = frame.points(tips)[read]
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
    full = np.full((n, 3), np.nan)
    full[read] = force
    force = full
    hw = np.full((n, 3), np.nan)
    if half is not None:
        hw[read] = np.asarray(half, dtype=np.float64)
    reasons, said = [None] * n, [[] for _ in range(n)]
    for j, k in enumerate(read):
        reasons[k], said[k] = refused[j], warns[j]
    for k, why in unreadable.items():
        reasons[k] = why
    out = frame.vectors_out(force)
    mag = np.linalg.norm(force, axis=1)
    rows = [{"fx_n": float(out[k, 0]), "fy_n": float(out[k, 1]), "fz_n": float(out[k, 2]),
             "magnitude_n": float(mag[k]),
             **{f"half_width_{c}_n": float(hw[k, j]) for j, c in enumerate(COMPONENTS)},
             "refused": reasons[k] or "", "warnings": "; ".join(said[k] or [])} for k in range(n)]
    n_ok = sum(r is None for r in reasons)
    summary = {"clouds": n, "predicted": n_ok, "refused": n - n_ok, "unreadable": len(unreadable),
               "path": "compiled" if compiled else "reference", "threads": threads if compiled else 1,
               "seconds": seconds, "clouds_per_s": len(P) / seconds if seconds > 0 else float("inf")}
    return rows, summary
