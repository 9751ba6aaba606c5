"""The frame and units of a user's point inputs, and the force given back in that frame.

Used by ``liverforce predict --frame``, ``Predictor.compile_cloud(frame=...)``, the MLflow pyfunc's
``input_frame``/``units`` params and, on input-contract arrays, :meth:`InputFrame.arrays` (points, the local
frame's axes, the inertia, lengths and the compliance).

A lab's own liver comes in its own frame and units: 3D Slicer and DICOM give LPS,
a registration gives a 4x4, a tracker gives metres. The geometry stage converts
the liver to the model's frame, RAS millimetres (``geometry.imported[].frame`` and
``units``), and records what it did under ``conversion`` in
``results/<exp>/geometry/imp-<name>.json``. The lab's camera clouds, tool tips and
exertion points then come in the liver file's frame, not in RAS mm.
:class:`InputFrame` maps every point input of a prediction to the model's frame,
and gives the force back in the inputs' frame::

    x_model = A (s x) + t        F_inputs = A^T F_model

``s`` is mm per input unit, ``A`` the 3x3 part and ``t`` the translation (mm) of
the frame's 4x4 (:func:`liverforce.geometry.frames.frame_matrix`, the geometry
stage's convention: file mm to RAS mm). ``A`` must be orthogonal (a rotation,
possibly with a reflection): a force has no meaning in a frame that scales or
shears the liver, so such a map is refused. A reflection reverses a surface's
triangle winding back, as the geometry stage does.

A frame is one of: ``RAS`` (the default: nothing changed), ``LPS`` (x and y
negated), a 4x4 matrix (a list of 4 rows, or a ``.npy``/``.json``/``.yaml`` file
holding one, or ``{matrix: [...], units: m}``), or the liver's import record ``results/<exp>/geometry/imp-<name>.json``,
which applies that liver's own units and frame exactly as the geometry stage
did (its units then need not be given again; other units are refused). A record or ``{matrix, units}``
already read (a dict, as the pyfunc's JSON param gives it) is taken too.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from liverforce.serve.errors import PredictionInputError

_HINT = ("use RAS, LPS, a 4x4 matrix (file mm to RAS mm; .npy, .json or .yaml) or the liver's import record "
         "results/<exp>/geometry/imp-<name>.json")


#: input-contract columns (:meth:`InputFrame.arrays`) that are points: one (3,) per case, or (ragged) a set per case
POINT_KEYS = ("exertion_point_mm", "liver_centroid_mm", "roi_centroid_undeformed_mm", "roi_centroid_deformed_mm",
              "tool_tip_mm", "roi_undeformed_mm", "roi_deformed_mm", "camera_cloud_mm", "unloaded_cloud_mm",
              "contact_tip_mm")
RAGGED_POINT_KEYS = ("roi_undeformed_mm", "roi_deformed_mm", "camera_cloud_mm", "unloaded_cloud_mm")
#: the local frame's axes (unit vectors, no translation)
DIRECTION_KEYS = ("frame_normal", "frame_t1", "frame_t2")
#: lengths (mm) and the probe's compliance (mm/N in the local frame, which moves with the liver): scaled only
LENGTH_KEYS = ("tool_thickness_mm", "probe_compliance_mm_per_n")
#: columns with no length or direction in them
PASS_KEYS = ("material_params_mpa", "case_id", "geometry_id")

#: length of one unit in mm
UNITS_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}


def unit_scale(units: str | None) -> float:
    """Millimetres per unit (``mm``, ``cm``, ``m``)."""
    if units is not None and not isinstance(units, str):
        raise PredictionInputError(f"units {units!r}: use one of {sorted(UNITS_MM)} (the model works in mm)")
    u = (units or "mm").strip().lower()
    if u not in UNITS_MM:
        raise PredictionInputError(f"units '{units}': use one of {sorted(UNITS_MM)} (the model works in mm)")
    return UNITS_MM[u]


def is_named(frame) -> bool:
    """True for a frame given by name (``RAS``, ``LPS``, any case), not by a matrix or a file."""
    return isinstance(frame, (str, Path)) and str(frame).strip().upper() in ("RAS", "LPS")


@dataclass(frozen=True)
class InputFrame:
    """How point inputs map to the model's frame (RAS mm): ``x_model = A (scale x) + t`` (module docstring).

    Build with :meth:`resolve`; ``matrix`` is the 4x4 ``[[A, t], [0, 1]]``.
    """

    scale: float = 1.0
    units: str = "mm"
    label: str = "RAS"
    matrix: np.ndarray = field(default_factory=lambda: np.eye(4))
    source: str | None = None
    #: False when neither units nor a frame were said (:meth:`resolve` of None, None): RAS mm by default
    declared: bool = field(default=True, compare=False)
    #: False when no frame was said (units alone, or nothing): read as RAS by default
    frame_declared: bool = field(default=True, compare=False)

    @classmethod
    def resolve(cls, frame=None, units: str | None = None, *, base: Path | None = None) -> "InputFrame":
        """The input frame of ``frame`` (a name, a 4x4, a file of one, an import record or one already read as a
        dict, None: RAS) and ``units``.

        ``base``: the folder a relative file path is taken from (default: the working directory). Raises
        :class:`PredictionInputError` on an unknown name, a malformed, singular or non-rigid matrix, or units that
        contradict an import record's.
        """
        if isinstance(frame, InputFrame):
            if units is not None and unit_scale(units) != frame.scale:
                raise PredictionInputError(f"units '{units}' contradict the input frame's ({frame.units})")
            return frame
        source = None
        scale_units = None
        if isinstance(frame, dict) or (isinstance(frame, (str, Path)) and not is_named(frame)):
            if isinstance(frame, dict):  # a record or {matrix, units} already read (the MLflow pyfunc's JSON param)
                path = "(given inline)"
                frame, rec_units, rec_scale = _frame_of_doc(frame, path)
            else:
                path = Path(frame)
                if not path.is_absolute() and base is not None:
                    path = base / path
                source = str(path)
                frame, rec_units, rec_scale = _read_frame_file(path)
            if rec_units is not None:
                if units is not None and unit_scale(units) != rec_scale and source is None:  # given inline
                    raise PredictionInputError(f"input frame (given inline): its units ({rec_units}) contradict "
                                               f"the units said apart ({units}); give them once")
                if units is not None and unit_scale(units) != rec_scale:
                    raise PredictionInputError(
                        f"{path}: this liver was imported in {rec_units} (x{rec_scale:g} to mm), but the inputs are "
                        f"said to be in {units}: drop the units (the record sets them) or convert the inputs to "
                        f"{rec_units}")
                scale_units = (rec_scale, rec_units)
        from liverforce.geometry.errors import GeometryError
        from liverforce.geometry.frames import frame_matrix

        try:
            m, label = frame_matrix(frame, source)  # the geometry stage's own reading of a frame
        except GeometryError as exc:
            raise PredictionInputError(f"input frame: {exc}") from None
        A = m[:3, :3]
        sv = np.linalg.svd(A, compute_uv=False)
        if not np.allclose(sv, 1.0, atol=1e-6):
            raise PredictionInputError(
                f"input frame{'' if source is None else ' ' + source}: the 3x3 part scales or shears (singular values "
                f"{np.round(sv, 6).tolist()}), so the force has no frame to be given back in; give a rigid map (a "
                "rotation, possibly with a reflection, and a shift) with the inputs' units (mm, cm, m) stated apart, "
                "or convert the inputs to RAS mm yourself")
        declared = frame is not None or units is not None
        if scale_units is None:
            scale = unit_scale(units)  # refuses anything but mm, cm, m
            scale_units = (scale, (units or "mm").strip().lower())
        return cls(scale=scale_units[0], units=scale_units[1], label=label, matrix=m, source=source,
                   declared=declared, frame_declared=frame is not None)

    # -- properties ----------------------------------------------------------

    @property
    def A(self) -> np.ndarray:
        return self.matrix[:3, :3]

    @property
    def t(self) -> np.ndarray:
        return self.matrix[:3, 3]

    @property
    def identity(self) -> bool:
        """True when nothing is converted (mm, RAS, no translation)."""
        return self.scale == 1.0 and bool(np.array_equal(self.matrix, np.eye(4)))

    @property
    def same_axes(self) -> bool:
        """True when the inputs' axes are the model's (RAS; units and a translation may differ)."""
        return bool(np.array_equal(self.A, np.eye(3)))

    @property
    def reflects(self) -> bool:
        return float(np.linalg.det(self.A)) < 0

    # -- inputs to the model's frame -------------------------------------------

    def points(self, xyz) -> np.ndarray:
        """Points ``(n, 3)`` or one ``(3,)`` in the inputs' units and frame -> model frame, mm."""
        try:
            x = np.asarray(xyz, dtype=np.float64) * self.scale
        except (TypeError, ValueError) as exc:
            raise PredictionInputError(f"points: expected numbers x, y, z ({exc})") from None
        if x.ndim not in (1, 2) or x.shape[-1] != 3:
            raise PredictionInputError(f"points: expected one (3,) point or (n, 3) points, got shape {x.shape}")
        return x if self.label == "RAS" and not self.t.any() else x @ self.A.T + self.t

    def surface(self, points, triangles) -> tuple[np.ndarray, np.ndarray]:
        """A surface in the inputs' units and frame -> model frame, its triangles kept outward."""
        tri = np.asarray(triangles, dtype=np.int64)
        return self.points(points), (tri[:, ::-1].copy() if self.reflects else tri)

    def directions(self, v) -> np.ndarray:
        """Unit vectors (rows) in the inputs' frame -> model frame (no units, no translation)."""
        return np.asarray(v, dtype=np.float64) @ self.A.T

    def length(self, value: float) -> float:
        return float(value) * self.scale

    def inertia(self, J) -> np.ndarray:
        """A second moment of volume (3 x 3 or 9 numbers; mm^5 once scaled) -> model frame: ``s^5 A J A^T``."""
        try:
            J = np.asarray(J, dtype=np.float64).reshape(3, 3)
        except (TypeError, ValueError) as exc:
            raise PredictionInputError(f"inertia_mm5: expected a 3 x 3 matrix (or 9 numbers) ({exc})") from None
        return self._turn_inertia(J[None])[0]

    def _turn_inertia(self, J: np.ndarray) -> np.ndarray:
        """Second moments ``(n, 3, 3)`` in the inputs' units and frame -> model frame: ``s^5 A J A^T`` each."""
        return np.einsum("ij,njk,lk->nil", self.A, J, self.A) * self.scale**5

    def arrays(self, arrays: dict) -> dict:
        """Input-contract arrays (one row per case, as the MLflow pyfunc and ``Predictor.predict_arrays`` take them)
        in the inputs' units and frame -> model frame, mm.

        Points (:data:`POINT_KEYS`) are mapped, the local frame's axes (:data:`DIRECTION_KEYS`) rotated, the inertia
        turned and scaled (``s^5 A J A^T``), lengths and the probe's compliance (mm/N, in the local frame) scaled, the
        ROI triangles' winding reversed under a reflection; the material and the ids pass as they are. A column this
        does not know is refused (it cannot say how to convert it), and so is a given local frame under a
        reflection (the axes would turn left-handed). Nothing is copied when nothing is converted.
        """
        if self.identity:
            return arrays
        unknown = sorted(set(arrays) - set(POINT_KEYS) - set(DIRECTION_KEYS) - set(LENGTH_KEYS) - set(PASS_KEYS)
                         - {"inertia_mm5", "roi_triangles"})
        if unknown:
            raise PredictionInputError(f"input frame: cannot say how to convert {', '.join(unknown)} to the model's "
                                       f"frame (RAS mm) from the inputs' ({self.label}, {self.units}): give these "
                                       "columns in RAS mm, or leave them out")
        if self.reflects and set(DIRECTION_KEYS) & set(arrays):
            raise PredictionInputError(
                "input frame: it reflects, which would turn the given local frame (frame_normal, frame_t1, frame_t2) "
                "left-handed; give the inputs in RAS mm, or a frame without a reflection")
        out = {}
        for k, v in arrays.items():
            if k in RAGGED_POINT_KEYS:  # one (k_i, 3) point set per case
                out[k] = [self.points(_numbers(f"{k}[{i}]", a, 2, 3)) for i, a in enumerate(_cases(k, v))]
            elif k in POINT_KEYS:
                out[k] = self.points(_numbers(k, v, 2, 3))
            elif k in DIRECTION_KEYS:
                out[k] = self.directions(_numbers(k, v, 2, 3))
            elif k in LENGTH_KEYS:
                out[k] = _numbers(k, v) * self.scale
            elif k == "inertia_mm5":
                J = _numbers(k, v)
                if J.ndim < 1 or J.size != 9 * len(J):
                    raise PredictionInputError(f"inertia_mm5: expected a 3 x 3 matrix (9 numbers) per case, got shape "
                                               f"{J.shape}")
                out[k] = self._turn_inertia(J.reshape(-1, 3, 3)).reshape(J.shape)
            elif k == "roi_triangles":
                out[k] = [_triangles(f"{k}[{i}]", t)[:, ::-1].copy() if self.reflects else t
                          for i, t in enumerate(_cases(k, v))]
            else:
                out[k] = v
        return out

    # -- results back to the inputs' frame ------------------------------------------

    def points_out(self, x) -> np.ndarray:
        """Points ``(n, 3)`` or one ``(3,)`` in the model's frame (RAS mm) -> the inputs' units and frame (the
        inverse of :meth:`points`; for messages that give a point back as the user entered it)."""
        x = np.asarray(x, dtype=np.float64)
        return np.linalg.solve(self.A, (x - self.t).T).T / self.scale

    def vectors_out(self, v) -> np.ndarray:
        """Vectors (a force in N, or direction rows) in the model frame -> the inputs' frame: ``A^T v``."""
        return np.asarray(v, dtype=np.float64) @ self.A

    def describe(self) -> str:
        """What is converted, in one line (also the output's ``input_frame``)."""
        if self.identity:
            return "inputs in mm, RAS (the model's frame): nothing converted"
        from liverforce.geometry.frames import describe_frame

        fr = describe_frame(self.label, self.matrix, {"determinant": float(np.linalg.det(self.A)),
                                                      "winding_reversed": self.reflects, "rigid": True,
                                                      "singular_values": [1.0, 1.0, 1.0]})
        fr = fr.replace("file mm", "input mm").replace("; winding kept", "")
        src = "" if self.source is None else f" (from {self.source})"
        name = "file units" if self.units.startswith("x") else self.units  # a record's mm per file unit: "x40"
        units = name if self.scale == 1.0 else f"{name} (x{self.scale:g} to mm)"
        back = "" if self.same_axes else "; the force and the interval's axes are given back in the inputs' frame"
        return f"inputs in {units}, {fr}{src}{back}"


# -- how a refusal names a point input: as the user entered it, with the units and frame declared ----------------

def _frame_name(fr: InputFrame) -> str:
    return fr.label if fr.label in ("RAS", "LPS") else "input frame (a 4x4)"


def as_entered(frame: InputFrame | None, x_model) -> np.ndarray | None:
    """Points ``(n, 3)`` or one ``(3,)`` of the model's frame (RAS mm) as the user entered them: in the units and
    frame declared (``frame``: the inputs' :class:`InputFrame`, which :meth:`InputFrame.points` converted them
    from; None, or one that converts nothing: as they are). None stays None. The one way a refusal takes an input
    back to what the user typed."""
    if x_model is None:
        return None
    x = np.asarray(x_model, dtype=np.float64)
    return x if frame is None or frame.identity else frame.points_out(x)


def as_given(frame: InputFrame | None, xyz_model) -> str:
    """A point of the model's frame written as the user gives it: ``"[0.049058, -0.079043, -0.157016] m LPS"``
    (``frame``: the inputs' :class:`InputFrame`; None: RAS mm)."""
    return written(frame, as_entered(frame, xyz_model))


def written(frame: InputFrame | None, xyz_given) -> str:
    """A point as the user gave it (in the inputs' units and frame), with them: ``"[0.05017, ...] m LPS"``."""
    fr = frame if frame is not None else InputFrame(declared=False)
    v = np.asarray(xyz_given, dtype=np.float64).reshape(-1)
    return "[" + ", ".join(f"{float(x):.6g}" for x in v) + f"] {fr.units} {_frame_name(fr)}"


def declared_as(frame: InputFrame | None) -> str:
    """What the user declared of the inputs' units and frame, in words."""
    if frame is None or not frame.declared:
        return "no units or frame were declared, so it was read as mm, RAS"
    src = "" if frame.source is None else f" by {frame.source}"
    if not frame.frame_declared:
        return f"declared in {frame.units}{src}, no frame given, so read as RAS"
    return f"declared in {frame.units}, {_frame_name(frame)}{src}"


def frame_advice(frame: InputFrame | None) -> str:
    """For a point input refused where no reading fits (:func:`reading_hint` None) and no frame was given: how to
    give one (a lab's inputs in LPS or in its scanner's frame read as RAS land off the liver); else ``""``."""
    if frame is not None and frame.frame_declared:
        return ""
    return ("; if the inputs are in another frame than RAS (LPS, or a scanner's), give it with --frame: LPS, a 4x4 "
            "matrix file, or the liver's record results/<exp>/geometry/imp-<name>.json")


def _readings(frame: InputFrame | None):
    """Other readings of the inputs than the declared one: ``(what it looks like, the reading)``: other units in
    the declared frame, then the declared units in RAS or LPS (when another frame was declared), then both."""
    fr = frame if frame is not None else InputFrame(declared=False)
    out = []
    lps = np.diag([-1.0, -1.0, 1.0, 1.0])
    frames = [(None, fr.matrix)] + [(name, m) for name, m in (("RAS", np.eye(4)), ("LPS", lps))
                                     if not np.array_equal(m, fr.matrix)]
    for name, m in frames:
        for units, scale in UNITS_MM.items():
            if name is None and scale == fr.scale:
                continue  # the declared reading
            said = " and ".join(x for x in ((units if scale != fr.scale else None), name) if x)
            out.append((said, InputFrame(scale=scale, units=units, label=name or fr.label, matrix=m)))
    return fr, out


def reading_hint(frame: InputFrame | None, xyz_given, fits) -> str | None:
    """The hint of a refused point input given as ``xyz_given`` (the inputs' units and frame; (3,) or (n, 3)):
    the first other reading (:func:`_readings`) under which it fits, said against what was declared (``"it looks
    like mm while m was declared: give it in m"``); None if none fits, or if the declared reading fits too.
    ``fits``: called once, with every reading's points in the model's frame stacked, ``(k, 3)`` or ``(k, n, 3)``
    (the declared reading first); returns ``(k,)`` True where they fit (one query for all readings: a surface's
    search tree is built once)."""
    fr, readings = _readings(frame)
    x = np.asarray(xyz_given, dtype=np.float64)
    if not np.isfinite(x).all():
        return None
    ok = np.asarray(fits(np.stack([fr.points(x)] + [alt.points(x) for _, alt in readings])), dtype=bool).reshape(-1)
    if ok[0]:
        return None  # the declared reading is not what is wrong
    for (said, alt), fit in zip(readings, ok[1:]):
        if fit:
            if fr.declared:
                return (f"it looks like {said} while {fr.units}, {_frame_name(fr)} was declared: give it in "
                        f"{fr.units}, {_frame_name(fr)}, as the other inputs")
            opts = " ".join(f"--{k} {v}" for k, v in (("units", alt.units if alt.scale != 1.0 else None),
                                                       ("frame", alt.label if alt.label != "RAS" else None)) if v)
            return (f"it looks like {said}, but no units or frame were declared (read as mm, RAS): declare them "
                    f"({opts}, or units/input_frame in a context file)")
    return None


def _numbers(key: str, v, ndim: int | None = None, cols: int | None = None) -> np.ndarray:
    """Column ``key`` as float64, refused by name when it is not numbers of ``ndim`` dimensions, ``cols`` wide."""
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise PredictionInputError(f"{key}: expected numbers ({exc})") from None
    if a.shape == (0,) and cols is not None:  # an empty point set: the checks downstream refuse it by their rules
        a = a.reshape(0, cols)
    if (ndim is not None and a.ndim != ndim) or (cols is not None and a.shape[-1:] != (cols,)):
        raise PredictionInputError(f"{key}: expected rows of {cols} numbers, got shape {a.shape}")
    return a


def _cases(key: str, v) -> list:
    """A ragged column: one entry per case."""
    if isinstance(v, (str, bytes)) or not hasattr(v, "__len__"):
        raise PredictionInputError(f"{key}: expected one entry per case, got {type(v).__name__}")
    return list(v)


def _triangles(key: str, t) -> np.ndarray:
    """Triangles as int64 (k, 3) vertex indices, refused by name unless whole numbers."""
    a = _numbers(key, t)
    if a.size % 3 or not np.isfinite(a).all() or (a != np.round(a)).any():
        raise PredictionInputError(f"{key}: expected whole vertex indices, three per triangle (got shape {a.shape})")
    return a.astype(np.int64).reshape(-1, 3)


def _read_frame_file(path: Path) -> tuple[object, str | None, float | None]:
    """The frame (name or 4x4), units and mm per unit (None, None if not stated) of a 4x4 file or an import
    record."""
    if not path.is_file():
        raise PredictionInputError(f"input frame {path}: no such file; {_HINT}")
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            return np.load(path, allow_pickle=False), None, None
        text = path.read_text()
        if suffix in (".yaml", ".yml"):
            import yaml

            doc = yaml.safe_load(text)
        else:
            doc = json.loads(text)
    except Exception as exc:  # noqa: BLE001 - numpy, JSON and YAML errors, re-raised with the file named
        raise PredictionInputError(f"input frame {path}: cannot read it ({type(exc).__name__}: {exc}); "
                                   f"{_HINT}") from None
    return _frame_of_doc(doc, path)


def _frame_of_doc(doc, path) -> tuple[object, str | None, float | None]:
    """Frame, units and mm per unit (None, None if not stated) of a read document: an import record, a procedural
    liver's record, ``{matrix, units}``, a 4x4 list or a name (``path``: where it came from, for messages)."""
    if isinstance(doc, dict) and "conversion" in doc:  # an import record of the geometry stage
        return _record_frame(doc, path)
    if isinstance(doc, dict) and "frame" in doc and "spec" in doc:  # a procedural liver's record: RAS mm
        return "RAS", "mm", 1.0
    if isinstance(doc, dict) and "matrix" in doc:
        if doc["matrix"] is None:
            raise PredictionInputError(f"input frame {path}: 'matrix' is empty; give a 4x4 (file mm to RAS mm)")
        u = doc.get("units")
        return doc["matrix"], (None if u is None else str(u)), (None if u is None else unit_scale(u))
    if isinstance(doc, (list, str)):
        return doc, None, None
    raise PredictionInputError(f"input frame {path}: neither a 4x4 matrix nor an import record; {_HINT}")


def _record_frame(doc: dict, path: Path) -> tuple[object, str, float]:
    """Frame, units and mm per unit of the geometry stage's record ``geometry/imp-<name>.json``."""
    conv = doc["conversion"]
    redo = "run the geometry stage again to rewrite it, or give --frame RAS/LPS or a 4x4 with --units"
    if not isinstance(conv, dict) or not {"frame_matrix", "units", "scale_to_mm"} <= set(conv):
        raise PredictionInputError(f"input frame {path}: the record's conversion lacks frame_matrix, units or "
                                   f"scale_to_mm; {redo}")
    if doc.get("label") is not None:  # the label of a label volume the surface was extracted from
        try:
            moved = not np.allclose(np.asarray(conv["frame_matrix"], dtype=np.float64), np.eye(4))
        except (TypeError, ValueError):
            moved = True
        raise PredictionInputError(
            f"input frame {path}: this liver came from a label volume, whose image header set its frame on reading "
            "(NRRD and DICOM world coordinates are LPS, NIfTI's RAS); the record cannot say which your points are "
            "in: give --frame LPS or --frame RAS (and --units) for them" + (
                "; this liver was also moved by its import frame (a 4x4, the record's conversion.frame_matrix): give "
                "--frame a 4x4 file, that matrix times diag(-1, -1, 1, 1) for LPS points, the matrix itself for RAS "
                "ones" if moved else ""))
    try:
        m = np.asarray(conv["frame_matrix"], dtype=np.float64)
        scale = float(conv["scale_to_mm"])
    except (TypeError, ValueError) as exc:
        raise PredictionInputError(f"input frame {path}: the record's conversion is malformed ({exc}); "
                                   f"{redo}") from None
    if m.shape != (4, 4) or not np.isfinite(scale) or scale <= 0:
        raise PredictionInputError(f"input frame {path}: the record's frame_matrix has shape {m.shape} and its "
                                   f"scale_to_mm is {scale!r}; {redo}")
    name = str(conv.get("frame", ""))
    if is_named(name):
        from liverforce.geometry.frames import frame_matrix

        if np.array_equal(m, frame_matrix(name)[0]):
            return name.upper(), str(conv["units"]), scale  # stated by name: said by name
    return m.tolist(), str(conv["units"]), scale
