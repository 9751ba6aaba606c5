"""Supports and exertion points given by the user, applied to the input surface before meshing.

A support is a selector (which facets), a kind (how they are held) and, for a
foundation, its stiffness. Kinds map onto the region codes of
:data:`~liverforce.mesh.types.REGION_CODES` and the per-region parameters of
:class:`liverforce.fem.problem.BoundaryParams`:

============ =============================== ======================================
kind         region code                     boundary term
============ =============================== ======================================
fixed        1 (ivc)                         all nodes clamped (Dirichlet)
foundation   2 (ligament) or 3 (visceral)    springs ``(k_n, k_t)`` N/mm³ per area
sliding      4 (rib)                         normal penalty, free sliding
============ =============================== ======================================

A foundation picks its slot with ``region: ligament | visceral`` (default
ligament); its stiffness is ``{normal_n_per_mm3, tangential_n_per_mm3}`` or
``{total_n_per_mm, tangential_ratio}`` (the total spread over the region's area,
as the study's). Two foundations in one slot must have the same stiffness.

Selectors, all in the frame of the geometry file (``geometry.imported[].frame``; for
a label volume its header's world in RAS, then that frame), lengths in mm, unless a
selector states its own ``frame`` (``RAS``, ``LPS`` or a 4x4 to the world's RAS: e.g.
LPS points from DICOM or ITK beside a NIfTI or NRRD liver). The world is the mesh's
RAS for a surface or mesh file and the header's world, then the geometry's frame, for
a label volume (:class:`PointFrame`):

* ``sphere: {center_mm: [x, y, z], radius_mm: r}`` and
  ``box: {min_mm: [x, y, z], max_mm: [x, y, z]}`` select a facet when its
  **centroid** lies inside (the mesh then conforms to the border of the
  selected facets). One that selects nothing is refused, saying what it would
  select mirrored in x and y (the other of RAS and LPS) or with its numbers in
  cm or m. A sphere whose centre lies on the surface only mirrored (picked on
  the liver in the other frame) is warned of, refused under ``strict``
  (:func:`check_sphere_frame`);
* ``file: {path: ..., units: ...}`` (``.npy``, ``.csv``, ``.txt``, ``.xyz`` or
  ``.ply``, any case; text read as ``liverforce predict`` reads a point file:
  comma, semicolon, tab or space separated, one optional header line,
  :func:`read_point_file`): one integer column = vertex ids of the file as read
  (before repair), or three columns = coordinates in ``units`` (default: the
  geometry's units). The points mark a **patch** of the surface, however the
  geometry stage refined it (a coarse file is Loop-subdivided, so its vertices are
  no longer the surface's): each point is placed at its closest surface point
  (refused beyond 5 mm, saying when all would land within it read in the other of
  RAS and LPS, or in other units of mm, cm and m, and what to state; distances
  reported as ``snap_mm``), the patch is
  triangulated between neighbouring points (sides at most twice their spacing,
  the median distance of a point to its 6th nearest: ``spacing_mm``, ``link_mm``)
  and a facet is selected when its centroid lies on it, facing the same way (never
  the far side of a thin lobe). Points that are the surface's own vertices select
  the facets between them; gaps in the points narrower than the link are filled; a
  few landmarks select the area they span (:func:`points_patch`). A 3D Slicer markups file
  (``.mrk.json``, ``.fcsv``) gives its control points in the coordinate system
  and units it states (LPS or RAS world, mm), so it takes no ``units`` or ``frame``.
  Points that fit the surface clearly better mirrored in x and y (a file in RAS read as
  LPS, or the reverse, still within 5 mm on a liver near symmetric about the file's
  superior axis) are warned of, naming both fits and the ``frame`` to state, and
  refused under ``mesh.regions_check: strict`` (the frame check below;
  the features JSON's ``frame_check``, shown and flagged in the report's supports table).

* ``group: <name or number>`` or ``group: {array: <cell-data name>, value: <n>}``:
  a Gmsh physical group or a VTU/VTK/XDMF cell-data tag of the geometry file
  (:mod:`liverforce.mesh.groups`). Its faces select the surface facets whose
  nearest boundary triangle of the file is one of them (exactly the tagged
  faces on a mesh imported as given; transferred onto a remeshed surface, the
  largest centroid distance reported as ``transfer_mm``); a group of nodes only
  (vertex or line cells) marks a patch as a file of points. For a liver segmented
  from a label volume, a group is another label value or segment of that file
  (``group: inferior_vena_cava``): the facets where the liver touches it, within
  1.5 voxels of its boundary voxels, each axis in its own spacing (``contact_mm``).

Supports are applied in order (a later one overrides an earlier one) onto zero
regions (``mode: replace``) or onto the auto-tagged ones (``mode: add``). Each
support's report says how it was selected (``selected_by``, :func:`selector_words`,
as the regions picture's legend names it) and counts the facets it finally holds
(``n_facets``; ``n_selected`` and ``taken_by`` when later ones took some); one left with none by a later support
of another kind or region is refused, naming both (:func:`apply_supports`). Under
``mode: add`` the same holds for the auto-tagged regions beneath: a lab support
taking some of one lists them (``took_built_in``), one wholly covered by lab
supports of another kind is refused. The supports must hold the liver: without a
fixed one, a rigid motion that only sliding supports and foundations without
tangential stiffness resist (along their normals) is refused (:func:`check_held`).
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from liverforce.geometry.point_table import TEXT_SUFFIXES, PointTableError, header_unit_clash, read_table
from liverforce.mesh.types import REGION_CODES

log = logging.getLogger(__name__)

KIND_CODES = {"fixed": REGION_CODES["ivc"], "sliding": REGION_CODES["rib"]}
FOUNDATION_SLOTS = ("ligament", "visceral")
SELECTORS = ("sphere", "box", "file", "group")
#: exertion points and support coordinates farther than this from the surface are refused (mm)
MAX_SNAP_MM = 5.0


class SupportError(ValueError):
    """A user support or exertion point cannot be applied."""


@dataclass(frozen=True)
class Support:
    """One user support: ``selector`` = ``(kind, dict)``, ``kind`` fixed | foundation | sliding."""

    name: str
    kind: str
    selector: tuple[str, dict]
    region: str = "ligament"
    stiffness: dict = field(default_factory=dict)
    #: where the lab gave it, for messages (e.g. ``geometry.imported[ct].supports.list[0]``)
    key: str = ""

    @property
    def code(self) -> int:
        return KIND_CODES.get(self.kind, REGION_CODES.get(self.region, 0))


@dataclass(frozen=True)
class PointFrame:
    """How user coordinates map to the surface: ``x_mesh = R @ (scale * x_file) + t`` (mm, RAS).

    ``scale`` converts the geometry file's units to mm; ``matrix`` (4×4) maps
    file mm to mesh mm (identity for procedural livers and the cube). ``world``
    (4×4) maps the world's RAS mm to mesh mm: where points that state their own
    frame, and 3D Slicer markups, are taken from. For a surface or mesh file the
    world is the mesh frame (identity): its ``frame`` (RAS, LPS or a 4x4) maps the
    file's coordinates to RAS mm. For a label volume it is the image header's
    world, then the geometry's ``frame`` (a registration 4x4, identity by default).
    """

    scale: float = 1.0
    matrix: tuple = tuple(map(tuple, np.eye(4)))
    world: tuple = tuple(map(tuple, np.eye(4)))
    #: for messages: the units of the geometry file (what ``scale`` converts) and where coordinates are read
    units: str = "mm"
    frame_label: str = "the geometry file's frame (RAS)"
    #: the frame the coordinates are read in: RAS, LPS or "a 4x4"; for a label volume its world's RAS; None:
    #: not said, told from ``matrix`` (:meth:`read_in`)
    frame_name: str | None = None

    @classmethod
    def from_surface_meta(cls, meta: dict) -> "PointFrame":
        conv = meta.get("conversion") or {}
        matrix = tuple(map(tuple, conv.get("frame_matrix", np.eye(4).tolist())))
        # a label volume: its header's world, then the geometry's frame; any other file: the mesh's RAS
        label = meta.get("label") is not None
        world = matrix if label else tuple(map(tuple, np.eye(4)))
        name = str(conv.get("frame") or meta.get("frame") or "RAS")
        name = "a 4x4" if name == "matrix" else name
        where = (f"the label volume's world (its header's RAS, then the geometry's frame, {name})" if label
                 else f"the geometry file's frame ({name})")
        return cls(float(conv.get("scale_to_mm", 1.0)), matrix, world,
                   str(conv.get("units") or meta.get("units") or "mm"), where,
                   "RAS" if label else name)

    def read_in(self) -> str | None:
        """The frame coordinates are read in, RAS or LPS, for messages; None for a 4x4 (``frame_name``, else
        told from ``matrix``: the identity is RAS, the turn of x and y LPS)."""
        if self.frame_name is not None:
            return self.frame_name if self.frame_name in ("RAS", "LPS") else None
        M = np.asarray(self.matrix, float)
        return next((k for k, d in (("RAS", [1, 1, 1, 1]), ("LPS", [-1, -1, 1, 1])) if np.allclose(M, np.diag(d))),
                    None)

    def read_as(self, units=None) -> str:
        """How coordinates are read, for messages: e.g. ``in m, in the geometry file's frame (LPS)``."""
        return f"in {units if units is not None else self.units}, in {self.frame_label}"

    def to_mesh(self, xyz_mm: np.ndarray) -> np.ndarray:
        M = np.asarray(self.matrix, float)
        return np.asarray(xyz_mm, float) @ M[:3, :3].T + M[:3, 3]

    def to_file(self, xyz_mesh: np.ndarray) -> np.ndarray:
        M = np.linalg.inv(np.asarray(self.matrix, float))
        return np.asarray(xyz_mesh, float) @ M[:3, :3].T + M[:3, 3]

    def stated(self, frame, where: str) -> "PointFrame":
        """This frame, or, when a point spec states its own ``frame`` (RAS, LPS or a 4x4: its coordinates, in
        mm after units, to the world's RAS mm), that one followed by the world's map to the mesh; the file's
        units stay."""
        if frame is None:
            return self
        m = np.asarray(self.world, float) @ points_frame(frame, where)
        name = frame.strip().upper() if isinstance(frame, str) else "a 4x4"
        return PointFrame(self.scale, tuple(map(tuple, m)), self.world, self.units, f"the stated frame {name}", name)

    def from_world(self, xyz_ras_mm: np.ndarray) -> np.ndarray:
        """World RAS mm (e.g. a markups file's points) to mesh mm."""
        W = np.asarray(self.world, float)
        return np.asarray(xyz_ras_mm, float) @ W[:3, :3].T + W[:3, 3]


@dataclass(frozen=True)
class PointReading:
    """How a support's file of points was read, for the checks of its frame and units
    (the frame check below): ``frame`` maps the coordinates it was read in (mm) to the mesh (they are
    mirrored in x and y in those); ``frame_name`` is theirs, RAS or LPS (None: a 4x4, or a markups file stating
    no one system); ``markups``: a 3D Slicer markups file (it states its own frame and units); ``scale_mm``: mm
    per number of the file (its declared units, else the geometry's; 1 for a markups file, read in mm)."""

    support: Support
    frame: PointFrame
    frame_name: str | None
    markups: bool = False
    scale_mm: float = 1.0


@dataclass(frozen=True)
class ExertionReading:
    """How given exertion points were read (:func:`exertion_points_mesh`), for the hints of their refusal beyond
    the snap limit (:func:`_far_points_words`): ``kind`` ``coordinates_mm``, ``file`` (a point file of
    coordinates), ``markups`` (a 3D Slicer markups file: its own frame and units) or ``vertex_ids`` (the geometry
    file's own vertices: no other reading); ``frame`` maps the coordinates they were read in (mm) to the mesh,
    ``frame_name`` is theirs (RAS or LPS; None: a 4x4, or a markups file of no one system); ``scale_mm``: mm per
    number; ``frame_stated``, ``units_stated``: whether the spec states them."""

    kind: str
    frame: PointFrame
    frame_name: str | None
    scale_mm: float = 1.0
    frame_stated: bool = False
    units_stated: bool = False


def points_frame(frame, where: str) -> np.ndarray:
    """The 4x4 (point mm -> RAS mm) of a point spec's ``frame``; :class:`SupportError` naming ``where``."""
    from liverforce.geometry.frames import frame_matrix

    try:
        return frame_matrix(frame)[0]
    except ValueError as exc:  # GeometryError is one
        raise SupportError(f"{where}.frame: {exc}") from None


#: what a ``supports`` entry looks like, for the messages refusing one of another shape
_SUPPORTS_SHAPE = ("{mode: replace, list: [{name: cava, kind: fixed, sphere: {center_mm: [x, y, z], radius_mm: r}}, "
                   "...]}")


def parse_supports(cfg, where: str = "supports") -> tuple[str, list[Support]]:
    """``{mode, list}`` config → ``(mode, [Support])``; ``ValueError`` naming the key on a bad entry.

    Refused (:class:`SupportError` naming the key): a ``supports`` that is no mapping (a bare list of supports
    without ``mode`` and ``list``), a ``list`` that is no list, an entry that is no mapping, two supports of one
    name (each names its facets in the features JSON, the regions picture and the messages), and ``mode:
    replace`` with no support listed (it would replace the built-in supports by nothing: the liver held by
    none, or, as before, the built-in ones kept without a word).
    """
    if cfg is None:
        return "add", []
    if isinstance(cfg, (str, bytes)) or not hasattr(cfg, "keys"):
        hint = " (a list of supports goes under list:)" if isinstance(cfg, (list, tuple)) else ""
        raise SupportError(f"{where}: give a mapping {_SUPPORTS_SHAPE}, got {cfg!r}{hint}")
    cfg = dict(cfg)
    mode = cfg.get("mode", "replace")
    if mode not in ("replace", "add"):
        raise SupportError(f"{where}.mode: '{mode}' must be replace or add")
    extra = set(cfg) - {"mode", "list"}
    if extra:
        raise SupportError(f"{where}: unknown keys {sorted(extra)} (use mode and list)")
    items = cfg.get("list")
    if items is not None and (isinstance(items, (str, bytes)) or hasattr(items, "keys")
                              or not hasattr(items, "__iter__")):
        raise SupportError(f"{where}.list: give a list of supports, each {{name, kind, and one selector of "
                           f"{list(SELECTORS)}}}, got {items!r}")
    items = list(items or [])
    if mode == "replace" and not items:
        raise SupportError(f"{where}.list: no support listed, and mode replace would replace the built-in "
                           "supports (the fixed IVC, the ligaments, the viscera, the ribs) by none: list the "
                           "liver's supports, or leave supports out to keep the built-in ones")
    out, names = [], {}
    for i, s in enumerate(items):
        key = f"{where}.list[{i}]"
        if isinstance(s, (str, bytes)) or not hasattr(s, "keys"):
            raise SupportError(f"{key}: give a support as a mapping {{name, kind: fixed|foundation|sliding, and "
                               f"one selector of {list(SELECTORS)}}}, got {s!r}")
        s = dict(s)
        kind = s.get("kind")
        if kind not in ("fixed", "foundation", "sliding"):
            raise SupportError(f"{key}.kind: '{kind}' must be fixed, foundation or sliding")
        sel = [k for k in SELECTORS if s.get(k) is not None]
        if len(sel) != 1:
            raise SupportError(f"{key}: give exactly one selector of {list(SELECTORS)} (got {sel or 'none'})")
        extra = set(s) - {"name", "kind", "region", "stiffness", *SELECTORS}
        if extra:
            raise SupportError(f"{key}: unknown keys {sorted(extra)}")
        selector = (sel[0], _group_spec(s[sel[0]], f"{key}.group") if sel[0] == "group" else dict(s[sel[0]]))
        _check_selector(selector, f"{key}.{sel[0]}")
        region = s.get("region", "ligament")
        stiffness = dict(s.get("stiffness") or {})
        if kind == "foundation":
            if region not in FOUNDATION_SLOTS:
                raise SupportError(f"{key}.region: '{region}' must be one of {list(FOUNDATION_SLOTS)}")
            _check_stiffness(stiffness, f"{key}.stiffness")
        elif stiffness or "region" in s:
            raise SupportError(f"{key}: stiffness and region are for kind foundation only")
        name = str(s.get("name") or f"support{i}")
        if name in names:
            raise SupportError(f"{key}.name: '{name}' is already the name of {where}.list[{names[name]}]: give "
                               "each support its own name (it names the support's facets in the features JSON, "
                               "the regions picture and the messages)")
        names[name] = i
        out.append(Support(name, kind, selector, region, stiffness, key))
    return mode, out


def _group_spec(value, key: str) -> dict:
    """``group:`` value → ``{name}`` (a string), ``{value}`` (an integer) or ``{array[, value]}``."""
    if isinstance(value, bool):
        raise SupportError(f"{key}: '{value}' must be a group name, a tag number or {{array, value}}")
    if isinstance(value, (int, np.integer)):
        return {"value": int(value)}
    if isinstance(value, str):
        return {"value": int(value)} if value.strip().lstrip("-").isdigit() else {"name": value}
    if isinstance(value, float) and value.is_integer():
        return {"value": int(value)}
    try:
        d = dict(value)
    except (TypeError, ValueError):
        raise SupportError(f"{key}: '{value}' must be a group name, a tag number or {{array, value}}") from None
    if not d or not set(d) <= {"array", "value", "name"} or ("name" in d and len(d) > 1):
        raise SupportError(f"{key}: give a name, a number, or {{array: <cell-data name>, value: <n>}}, got {d}")
    if "value" in d:
        try:
            if float(d["value"]) != int(float(d["value"])):
                raise ValueError
            d["value"] = int(float(d["value"]))
        except (TypeError, ValueError):
            raise SupportError(f"{key}.value: '{d['value']}' must be an integer tag") from None
    return d


def finite_numbers(value, shape: tuple, key: str, what: str) -> np.ndarray:
    """``value`` as a float array of ``shape`` (``-1``: any length) of finite numbers, else :class:`SupportError`
    naming ``key`` and ``what`` was expected (``true``/``false`` and words are no numbers, NaN and inf no place)."""
    try:
        if any(isinstance(x, (bool, np.bool_, str, bytes)) for x in np.asarray(value, dtype=object).ravel()):
            raise TypeError
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise SupportError(f"{key}: must be {what}, got {value!r}") from None
    if a.ndim != len(shape) or any(n != -1 and n != m for n, m in zip(shape, a.shape)):
        raise SupportError(f"{key}: must be {what}, got {value!r} (shape {a.shape})")
    if not np.isfinite(a).all():
        raise SupportError(f"{key}: must be {what}, got {value!r} (a value is not a finite number)")
    return a


def coordinate_list(value, key: str) -> np.ndarray:
    """``value`` as a non-empty ``(k, 3)`` array of finite coordinates, else :class:`SupportError` naming ``key``."""
    a = finite_numbers(value, (-1, 3), key, "a non-empty list of [x, y, z] (numbers, mm)")
    if not len(a):
        raise SupportError(f"{key}: must be a non-empty list of [x, y, z] (numbers, mm), got {value!r}")
    return a


def vertex_id_list(value, key: str) -> np.ndarray:
    """``value`` as a non-empty 1-D array of non-negative integer vertex ids, else :class:`SupportError` naming
    ``key`` (``4690.7`` is refused, not cut to 4690; ``true`` is no vertex id)."""
    a = finite_numbers(value, (-1,), key, "a non-empty list of vertex ids (integers >= 0)")
    bad = np.flatnonzero((a < 0) | (a != np.round(a)))
    if not len(a) or len(bad):
        got = f" (entry {bad[0]} is {a[bad[0]]:g})" if len(bad) else ""
        raise SupportError(f"{key}: must be a non-empty list of vertex ids (integers >= 0){got}")
    return a.astype(np.int64)


def check_point_file_units(units, key: str) -> None:
    """Refuse ``units`` of a point file (a support's or the exertion points') that are no unit, or ``auto`` (a few
    points have no liver size to guess a unit from), with :class:`SupportError` naming ``key``."""
    from liverforce.geometry.units import parse_units

    try:
        scale, _ = parse_units(units)
    except ValueError:
        scale = 0.0
    if not scale:
        raise SupportError(f"{key}: '{units}' is no unit for a point file (auto is for a liver file, guessed from its "
                           "size): give mm, cm, m or a number of mm per file unit (default: the geometry's units)")


def _check_selector(selector, key):
    kind, d = selector
    if kind == "group":
        return
    need = {"sphere": {"center_mm", "radius_mm"}, "box": {"min_mm", "max_mm"}, "file": {"path"}}[kind]
    allowed = need | ({"units"} if kind == "file" else set()) | {"frame"}
    if not need <= set(d) or not set(d) <= allowed:
        raise SupportError(f"{key}: needs keys {sorted(need)} (optional {sorted(allowed - need)}), got {sorted(d)}")
    if kind == "file" and is_markups(d["path"]):
        check_markups_spec(d, key)
    if kind == "file" and d.get("units") is not None:
        check_point_file_units(d["units"], f"{key}.units")
    if d.get("frame") is not None:
        points_frame(d["frame"], key)
    if kind == "sphere":
        finite_numbers(d["center_mm"], (3,), f"{key}.center_mm", "[x, y, z] in mm")
        if not finite_numbers(d["radius_mm"], (), f"{key}.radius_mm", "a radius in mm (a number > 0)") > 0:
            raise SupportError(f"{key}: center_mm must be [x, y, z] and radius_mm > 0")
    if kind == "box":
        lo = finite_numbers(d["min_mm"], (3,), f"{key}.min_mm", "[x, y, z] in mm")
        hi = finite_numbers(d["max_mm"], (3,), f"{key}.max_mm", "[x, y, z] in mm")
        if not (hi > lo).all():
            raise SupportError(f"{key}: min_mm and max_mm must be [x, y, z] with max > min on every axis")


def _check_stiffness(st: dict, key: str):
    per_area = {"normal_n_per_mm3", "tangential_n_per_mm3"}
    total = {"total_n_per_mm", "tangential_ratio"}
    if set(st) == per_area or set(st) == {"normal_n_per_mm3"}:
        vals = [st[k] for k in st]
    elif set(st) in ({"total_n_per_mm"}, total):
        vals = [st[k] for k in st]
    else:
        raise SupportError(f"{key}: give {{normal_n_per_mm3, tangential_n_per_mm3}} (N/mm³) or "
                           f"{{total_n_per_mm, tangential_ratio}} (N/mm over the region), got {sorted(st)}")
    try:
        ok = all(finite_numbers(v, (), key, "") >= 0 for v in vals)
    except SupportError:
        ok = False
    if not ok:
        raise SupportError(f"{key}: stiffness values must be finite numbers >= 0 (got {st})")


#: Point files: the formats ``liverforce predict`` reads a point cloud in (``liverforce.serve.files.read_points``;
#: text files by the same reader, :func:`liverforce.geometry.point_table.read_table`), suffixes in any case; not
#: PCD, a camera's format, which predict reads for clouds only
POINT_FILE_SUFFIXES = (".npy", *TEXT_SUFFIXES, ".ply")


def read_point_file(path, units: str | None = None, scale_mm: float | None = None) -> np.ndarray:
    """Vertex ids ``(k,)`` int or coordinates ``(k, 3)`` float (as in the file: the caller scales them).

    The formats and rules of ``liverforce predict``'s point files
    (``liverforce.serve.files.read_points``): ``.npy``; ``.csv``/``.txt``/
    ``.xyz``, three columns separated by commas, semicolons, tabs or spaces,
    one optional header line, ``#`` comments and blank lines skipped
    (:mod:`liverforce.geometry.point_table`); ``.ply`` (its vertices); suffixes
    in any case. A text or ``.npy`` file of one column holds vertex ids instead
    (non-negative integers; a text file may have a header). ``units`` (as
    declared, e.g. ``"m"``) words the messages only. A refused file is named
    with the line at fault and what was expected; an empty one is said to be.
    ``scale_mm``: mm per unit the coordinates will be read in (declared, or the geometry's); a text file whose
    header names another unit for every column (``x_mm`` read as m) is refused, naming both.
    """
    path = Path(path)
    want = f"3 numbers per row (x, y, z in {units or 'mm'}) or one column of vertex ids"
    if not path.exists():
        raise SupportError(f"{path}: file not found")
    suffix = path.suffix.lower()
    if suffix not in POINT_FILE_SUFFIXES:
        raise SupportError(f"{path}: use {', '.join(POINT_FILE_SUFFIXES)} (any case), or a 3D Slicer markups file "
                           "(.mrk.json, .fcsv)")
    lines = None
    if suffix in TEXT_SUFFIXES:
        try:
            a, lines = read_table(path, columns=(1, 3))
        except PointTableError as exc:
            raise SupportError(f"{exc}; expected {want}") from None
        if a.shape[1] == 1:
            return _vertex_ids(a[:, 0], path, lines)
        clash = None if scale_mm is None else header_unit_clash(path, scale_mm, units or "mm")
        if clash is not None:
            raise SupportError(f"{clash[1]}: declare units: {clash[0]} for this file (or correct its header)")
    elif suffix == ".npy":
        try:
            a = np.load(path, allow_pickle=False)
        except (OSError, ValueError, EOFError) as exc:  # EOFError: numpy's for an empty or cut-short .npy
            raise SupportError(f"{path}: cannot read the array ({type(exc).__name__}: {exc}; expected {want})"
                               ) from None
        if not np.issubdtype(a.dtype, np.number) or a.ndim not in (1, 2) or a.ndim == 2 and a.shape[1] not in (1, 3):
            raise SupportError(f"{path}: an array of shape {a.shape} ({a.dtype}); expected {want}")
        if a.ndim == 1 or a.shape[1] == 1:
            return _vertex_ids(a.reshape(-1).astype(float), path, None)
    else:
        a = _ply_points(path, want)
    if len(a) == 0:
        raise SupportError(f"{path}: the file is empty (no points; expected {want})")
    bad = np.flatnonzero(~np.isfinite(a).all(axis=1))
    if len(bad):
        at = f"line {lines[bad[0]]}" if lines else f"row {bad[0]}"
        raise SupportError(f"{path}, {at}: a coordinate is not a finite number (expected {want})")
    return np.asarray(a, float)


def _ply_points(path: Path, want: str) -> np.ndarray:
    """A PLY file's vertices, read as ``liverforce predict`` reads them (:func:`liverforce.geometry.ply.read_ply`)."""
    from liverforce.geometry.ply import PlyError, read_ply

    try:
        return read_ply(path).points
    except PlyError as exc:
        raise SupportError(f"{exc} (expected {want})") from None


def _vertex_ids(ids: np.ndarray, path: Path, lines: list[int] | None) -> np.ndarray:
    bad = np.flatnonzero(~np.isfinite(ids) | (ids < 0) | (ids != np.round(ids)))
    if len(bad):
        at = f"line {lines[bad[0]]}" if lines else f"row {bad[0]}"
        raise SupportError(f"{path}, {at}: one column must hold non-negative integer vertex ids (got {ids[bad[0]]:g})")
    if not len(ids):
        raise SupportError(f"{path}: the file is empty (no vertex ids)")
    return ids.astype(np.int64)


#: 3D Slicer markups files: control points in the coordinate system and units the file states
MARKUPS_SUFFIXES = (".mrk.json", ".fcsv")


def is_markups(path) -> bool:
    return str(path).lower().endswith(MARKUPS_SUFFIXES)


def check_markups_spec(spec: dict, where: str) -> None:
    """Refuse ``units`` or ``frame`` beside a markups file: it states both itself."""
    extra = sorted(k for k in ("units", "frame") if (spec or {}).get(k) is not None)
    if extra:
        raise SupportError(f"{where}: {Path(str(spec['path'])).name} is a 3D Slicer markups file, which states its "
                           f"own coordinate system and units: leave out {' and '.join(extra)}")


def read_markups(path, spec: dict | None = None, where: str = "points") -> np.ndarray:
    """The control points of a 3D Slicer markups file (``.mrk.json``; legacy ``.fcsv`` read by slicerio) in
    the world's RAS mm (:meth:`PointFrame.from_world` places them): each markup's ``coordinateSystem`` (LPS
    or RAS) and ``coordinateUnits`` (mm) are the file's, so a spec may not state ``units`` or ``frame``
    beside one. A point whose position is not defined (``positionStatus``) is refused by its label."""
    import json

    path = Path(path)
    check_markups_spec({**(spec or {}), "path": str(path)}, where)
    if not path.exists():
        raise SupportError(f"{path}: file not found")
    try:
        if path.name.lower().endswith(".fcsv"):
            from slicerio.markups import read_markups_fcsv

            doc = read_markups_fcsv(str(path))
        else:
            doc = json.loads(path.read_text(encoding="utf-8"))
        markups = list(doc["markups"])
    except Exception as exc:  # malformed JSON or CSV, a missing key
        raise SupportError(f"{path}: not a readable 3D Slicer markups file ({type(exc).__name__}: {exc})") from None
    out = []
    for m in markups:
        system = str(m.get("coordinateSystem", "LPS")).upper()  # the schema's default is LPS
        units = m.get("coordinateUnits", "mm")
        units = str(units.get("CodeValue", "") if isinstance(units, dict) else units).lower()  # or a UCUM code
        if system not in ("LPS", "RAS") or units not in ("mm", "um"):
            raise SupportError(f"{path}: coordinateSystem '{system}' and coordinateUnits '{units}' are not LPS or "
                               "RAS and mm or um")
        for cp in m.get("controlPoints") or []:
            label = cp.get("label") or cp.get("id") or "?"
            if cp.get("positionStatus", "defined") != "defined" or len(cp.get("position") or []) != 3:
                raise SupportError(f"{path}: control point '{label}' has no position "
                                   f"(positionStatus {cp.get('positionStatus', '?')}): place it or delete it")
            xyz = np.asarray(cp["position"], float) * (1e-3 if units == "um" else 1.0)
            out.append(xyz * (np.array([-1.0, -1.0, 1.0]) if system == "LPS" else 1.0))
    if not out:
        raise SupportError(f"{path}: the markups file holds no control point")
    return np.asarray(out)


#: a file of points marks the patch triangulated between neighbouring points no farther apart than
#: ``PATCH_LINK`` times their spacing: the median distance of a point to its ``PATCH_NEIGHBOURS``-th nearest
#: (the ring of neighbours of a vertex of a triangulated surface; all of a few hand-placed landmarks)
PATCH_LINK = 2.0
PATCH_NEIGHBOURS = 6
#: a facet lies on a patch triangle when its centroid projects inside it (or outside by at most this
#: fraction of the facet's mean edge), within half the triangle's longest side of its plane, facing the same
#: way (cosine of the normals above PATCH_COS)
PATCH_TOL = 0.1
PATCH_COS = 0.5


def points_patch(vertices, faces, xyz, what: str, read_as: str, max_mm: float = MAX_SNAP_MM, triangles=None,
                 reading: PointReading | None = None):
    """Facets of the surface ``(vertices, faces)`` (mesh mm) marked by the points ``xyz (k, 3)`` (mesh mm).

    The points mark a surface patch, whatever the surface's resolution (the geometry stage may have refined a
    coarse file by Loop subdivision, so the points are no longer its vertices): each point is placed at its
    closest point on the surface (refused beyond ``max_mm``); the patch is the union of the triangles whose
    corners are neighbouring points, each side at most ``PATCH_LINK`` x the points' spacing (``spacing_mm``:
    the median distance of a point to its ``PATCH_NEIGHBOURS``-th nearest; ``link_mm``), and a facet is
    selected when its centroid lies on one: projects inside it (or outside by at most ``PATCH_TOL`` x the
    facet's mean edge), within half its longest side of its plane, its normal within 60 degrees of the
    patch's (never the far side of a thin lobe). Facets whose three vertices are the nearest vertices of
    points are selected too (points that are the surface's own vertices select the facets between them).
    Gaps in the points narrower than the link are filled; fewer than three points mark nothing.
    Returns ``(mask, info)``, ``info`` with ``snap_mm`` (distances to the surface), ``spacing_mm`` and
    ``link_mm``. ``triangles``: the surface's :class:`TriangleSet` when the caller has one (its search tree is
    built once for the caller's other queries). ``reading``: how a support's file of points was read; the refusal
    of points beyond ``max_mm`` then says which other reading would land them all within it: the other of RAS
    and LPS, or other units (:func:`far_words`). None (the geometry file's own
    vertices or nodes: no other frame or units to read them in): the refusal says to check both.
    """
    from itertools import combinations

    from scipy.spatial import cKDTree

    vertices = np.asarray(vertices, float)
    faces = np.asarray(faces, np.int64)
    xyz = np.atleast_2d(np.asarray(xyz, float))
    tri = vertices[faces]
    triangles = TriangleSet(tri) if triangles is None else triangles
    on, dist, near_facet = triangles.closest(xyz, k=16)
    if (dist > max_mm).any():
        j = int(np.argmax(dist))
        other = ""
        if reading is not None:
            other = far_words(reading, triangles, xyz, max_mm)
        raise SupportError(f"{what}: point {j} {np.round(xyz[j], 3).tolist()} (mm on the mesh; the file's "
                           f"coordinates read {read_as}) is {dist[j]:.3g} mm from the surface (limit {max_mm} mm): "
                           f"check its units and frame{other}")
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
    _, ids = cKDTree(vertices).query(xyz)
    chosen = np.zeros(len(vertices), bool)
    chosen[ids] = True
    mask = chosen[faces].all(axis=1)
    info = {"snap_mm": {"max": float(dist.max()), "mean": float(dist.mean()), "n_points": int(len(dist))}}
    pts = np.unique(np.round(on, 9), axis=0)
    if len(pts) < 3:
        info.update(spacing_mm=None, link_mm=None)
        return mask, info
    ptree = cKDTree(pts)
    spacing = float(np.median(ptree.query(pts, k=min(PATCH_NEIGHBOURS, len(pts) - 1) + 1)[0][:, -1]))
    link = PATCH_LINK * spacing
    pn = fn[near_facet[cKDTree(on).query(pts)[1]]]  # surface normal at each (deduplicated) point
    cent = tri.mean(axis=1)
    edge = np.linalg.norm(tri - tri[:, [1, 2, 0]], axis=2).mean(axis=1)
    k = min(8, len(pts))
    dk, nbr = ptree.query(cent, k=k, distance_upper_bound=link)
    cand = np.flatnonzero(np.isfinite(dk[:, 2]))  # facets with at least three points within the link
    for a, b, c in combinations(range(k), 3):
        f = cand[np.isfinite(dk[cand, c])]
        if not len(f):
            continue
        ia, ib, ic = nbr[f, a], nbr[f, b], nbr[f, c]
        A, B, C = pts[ia], pts[ib], pts[ic]
        e1, e2, e3 = B - A, C - A, C - B
        longest = np.max(np.linalg.norm(np.stack([e1, e2, e3]), axis=2), axis=0)
        n = np.cross(e1, e2)
        area2 = np.linalg.norm(n, axis=1)
        ok = (longest <= link) & (area2 > 1e-6 * longest ** 2)
        n = n / np.maximum(area2, 1e-300)[:, None]
        side = np.sign(np.einsum("ij,ij->i", n, pn[ia] + pn[ib] + pn[ic]))
        n = n * np.where(side == 0, 1.0, side)[:, None]
        ok &= (np.einsum("ij,ij->i", n, pn[ia]) > 0) & (np.einsum("ij,ij->i", n, pn[ib]) > 0) \
            & (np.einsum("ij,ij->i", n, pn[ic]) > 0)  # a triangle across a sharp border spans no patch
        w = cent[f] - A
        h = np.einsum("ij,ij->i", w, n)
        ok &= (np.abs(h) <= 0.5 * longest) & (np.einsum("ij,ij->i", fn[f], n) > PATCH_COS)
        w = w - h[:, None] * n
        d00, d01, d11 = (np.einsum("ij,ij->i", e1, e1), np.einsum("ij,ij->i", e1, e2),
                         np.einsum("ij,ij->i", e2, e2))
        d20, d21 = np.einsum("ij,ij->i", w, e1), np.einsum("ij,ij->i", w, e2)
        den = np.where(ok, d00 * d11 - d01 * d01, 1.0)
        v = (d11 * d20 - d01 * d21) / den  # the barycentric coordinate of B
        u = (d00 * d21 - d01 * d20) / den  # of C
        # times the heights: the distance inside each side (negative outside), within the facet's tolerance
        sides = np.linalg.norm(np.stack([e3, e2, e1]), axis=2) / np.maximum(area2, 1e-300)
        tol = -PATCH_TOL * edge[f]
        ok &= ((1 - u - v) >= tol * sides[0]) & (v >= tol * sides[1]) & (u >= tol * sides[2])
        mask[f[ok]] = True
    info.update(spacing_mm=round(spacing, 4), link_mm=round(link, 4))
    return mask, info


def _no_patch(what: str, n: int, read_as: str, pinfo: dict, frame_check: dict | None = None) -> SupportError:
    """The error of a point file (or group of nodes) that marks no facet, saying how its points were read and,
    from ``frame_check`` (:func:`check_support_frame`; None: not checked, as for
    the geometry file's own nodes), what their fit tells of their frame."""
    if pinfo.get("link_mm") is None:
        why = (f"its {n} point(s) make no patch: a file of points marks the surface patch spanned by "
               "neighbouring points, so give at least three around the area (or use a sphere or box)")
    else:
        why = (f"its {n} points, {pinfo['spacing_mm']:.3g} mm apart (median), make no patch triangle of sides "
               f"at most {pinfo['link_mm']:.3g} mm over the surface (in a line, or scattered): give points "
               "covering the area, or use a sphere or box")
    return SupportError(f"{what}: selects no surface facet: {why} (coordinates read {read_as}; all lie within "
                        f"{pinfo['snap_mm']['max']:.3g} mm of the surface, so the units look right"
                        f"{_frame_fit_words(frame_check)})")


def _frame_fit_words(check: dict | None) -> str:
    """What a point file's fit as read and mirrored tells of its frame, for :func:`_no_patch`."""
    if check is None:
        return ""
    g, m = check["as_given_mm"]["mean"], check["mirrored_mm"]["mean"]
    fits = f"mirrored in x and y (the other of RAS and LPS) they fit it {{}} ({m:.3g} mm on average, {g:.3g} as read)"
    if check["likely_mix_up"]:
        return "; the frame does not: " + fits.format("better") + ", see the warning of the wrong frame"
    if m - g >= FRAME_FIT_MARGIN_MM and g <= FRAME_FIT_RATIO * m:
        return "; " + fits.format("worse") + ", so the frame looks right too"
    return "; " + fits.format("about as well") + ", so the fit cannot tell the frame"


def _markups_systems(path: Path) -> str:
    """The coordinate system(s) a markups file states, for messages."""
    import json

    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        names = sorted({str(m.get("coordinateSystem", "LPS")).upper() for m in doc["markups"]})
        return " and ".join(names) if names else "its own"
    except Exception:  # .fcsv or unreadable (read_markups has refused the latter already)
        return "its own"


def select_facets(vertices, faces, support: Support, frame: PointFrame = PointFrame(),
                  file_vertices=None, base_dir=None, file_groups=None,
                  regions_check: str = "warn") -> tuple[np.ndarray, dict]:
    """Facets of the surface ``(vertices, faces)`` (mesh frame, mm) selected by ``support``.

    ``file_vertices`` : callable returning the geometry file's vertices as read
    (file units and frame), for selectors of vertex ids. ``file_groups`` : callable
    returning the file's :class:`~liverforce.mesh.groups.FileGroups`, for ``group``
    selectors. Returns ``(mask, info)``, ``info`` with the count and, for files,
    the distances of the points to the surface (mm) and the patch they mark (:func:`points_patch`).
    A file of coordinates (or a 3D Slicer markups file) is checked for a frame mix-up, its points fitting the
    surface better mirrored in x and y (RAS read as LPS, or the reverse): ``info["frame_check"]``
    (:func:`check_support_frame`), warned, or refused under ``regions_check``
    (``mesh.regions_check``) ``strict``; None under ``off``. So is a sphere whose centre lies on the surface
    only mirrored (:func:`check_sphere_frame`). A sphere or box that selects nothing is refused naming what it
    would select mirrored or in cm or m (:func:`_shape_readings`).
    """
    vertices = np.asarray(vertices, float)
    faces = np.asarray(faces, np.int64)
    kind, d = support.selector
    info: dict = {"name": support.name, "kind": support.kind, "selector": kind, "selected_by": selector_words(support)}
    if kind == "group":
        if file_groups is None:
            raise SupportError(f"support '{support.name}': a group selector needs the geometry's mesh file "
                               "(an imported Gmsh MSH, VTU, VTK or XDMF file with tags)")
        mask, ginfo = _select_group(vertices, faces, support, frame, file_groups())
        info.update(ginfo)
    elif kind in ("sphere", "box"):
        frame = frame.stated(d.get("frame"), f"support '{support.name}' {kind}")
        cent = frame.to_file(vertices[faces].mean(axis=1))  # file frame (or the stated one), mm
        mask = _inside(kind, d, cent)
        if not mask.any():
            if kind == "sphere":
                r = np.linalg.norm(cent - np.asarray(d["center_mm"], float), axis=1)
                miss = f"the nearest facet centroid is {r.min():.3g} mm from its centre"
            else:
                lo, hi = np.asarray(d["min_mm"], float), np.asarray(d["max_mm"], float)
                miss = (f"the nearest facet centroid is "
                        f"{np.linalg.norm(cent - np.clip(cent, lo, hi), axis=1).min():.3g} mm outside it")
            raise SupportError(f"support '{support.name}': its {kind} selector {d} selects no surface facet "
                               f"({miss}; coordinates read {frame.read_as('mm')}): enlarge it or check the frame"
                               + _shape_readings(support, cent, frame))
        if kind == "sphere":
            info["frame_check"] = check_sphere_frame(support, frame, TriangleSet(vertices[faces]),
                                                     frame.read_as("mm"), regions_check)
    else:
        path = Path(d["path"])
        if not path.is_absolute() and base_dir is not None:
            path = Path(base_dir) / path
        scale = frame.scale if d.get("units") is None else _units_scale(d["units"])
        a = None if is_markups(path) else read_point_file(path, _units_words(d.get("units"), frame), scale)
        if a is not None and a.ndim == 1 and d.get("frame") is not None:
            raise SupportError(f"support '{support.name}' file.frame: vertex ids have no frame (they index the "
                               "file's vertices)")
        reading = None  # how the points were read, for the checks of their frame (and units)
        if a is None:  # a Slicer markups file: world RAS mm
            where = f"support '{support.name}' file"
            xyz = frame.from_world(read_markups(path, d, where))
            systems = _markups_systems(path)
            read_as = f"in mm, in the markups file's own coordinate system ({systems})"
            reading = PointReading(support, PointFrame(matrix=frame.world),
                                   systems if systems in ("RAS", "LPS") else None, markups=True)
        elif a.ndim == 1:  # the geometry file's own vertices, in its frame: nothing to mirror
            if file_vertices is None:
                raise SupportError(f"support '{support.name}': vertex ids need the geometry file's vertices "
                                   "(an imported geometry)")
            fv = np.asarray(file_vertices(), float)
            if a.max() >= len(fv):
                raise SupportError(f"support '{support.name}': vertex id {int(a.max())} out of range "
                                   f"(the file has {len(fv)} vertices)")
            xyz = frame.to_mesh(fv[a] * frame.scale)
            read_as = f"as vertex ids of the geometry file, its vertices {frame.read_as()}"
        else:
            stated = frame.stated(d.get("frame"), f"support '{support.name}' file")
            xyz = stated.to_mesh(a * scale)
            read_as = stated.read_as(d.get("units"))
            reading = PointReading(support, stated, stated.read_in(), scale_mm=scale)
        what = f"support '{support.name}' ({path})"
        triangles = TriangleSet(vertices[faces])
        mask, pinfo = points_patch(vertices, faces, xyz, what, read_as, triangles=triangles, reading=reading)
        info.update(pinfo)
        checked = None
        if reading is not None:
            checked = check_support_frame(reading, what, triangles, xyz, read_as, regions_check)
            info["frame_check"] = checked
        if not mask.any():
            raise _no_patch(what, len(xyz), read_as, pinfo, checked)
    if not mask.any():  # a group of faces transferred onto no facet
        raise SupportError(f"support '{support.name}': its {kind} selector {d} selects no surface facet")
    info["n_facets"] = int(mask.sum())
    return mask, info


def _inside(kind: str, d: dict, cent: np.ndarray, mm_per_number: float = 1.0) -> np.ndarray:
    """The facets whose centroids ``cent`` (mm, in the coordinates the selector is read in) lie inside a sphere
    or box selector ``d`` whose numbers are taken as ``mm_per_number`` mm each (1: as given, in mm)."""
    if kind == "sphere":
        centre = np.asarray(d["center_mm"], float) * mm_per_number
        return np.linalg.norm(cent - centre, axis=1) <= float(d["radius_mm"]) * mm_per_number
    lo, hi = (np.asarray(d[k], float) * mm_per_number for k in ("min_mm", "max_mm"))
    return ((cent >= lo) & (cent <= hi)).all(axis=1)


def selector_words(support: Support) -> str:
    """A support's selector in a few words, as the lab gave it: ``group vena_cava``, ``group tag=3``,
    ``sphere r 20 mm``, ``box``, ``file cava.csv`` (the legend of the regions picture, the support's report)."""
    kind, d = support.selector
    if kind == "group":
        if "name" in d:
            return f"group {d['name']}"
        if "array" in d:
            return f"group {d['array']}={d['value']}" if "value" in d else f"group {d['array']}"
        return f"group {d['value']}"
    if kind == "sphere":
        return f"sphere r {float(d['radius_mm']):g} mm"
    if kind == "file":
        return f"file {Path(str(d['path'])).name}"
    return kind


def _select_group(vertices, faces, support: Support, frame: PointFrame, groups) -> tuple[np.ndarray, dict]:
    """Facets selected by a file group (see :mod:`liverforce.mesh.groups`)."""
    from liverforce.mesh.groups import GroupError

    where = f"support '{support.name}' group {support.selector[1]}"
    if hasattr(groups, "contact"):  # a label volume's other segment: where the liver touches it
        return _select_contact(vertices, faces, frame, groups, support.selector[1], where)
    try:
        gfaces, gnodes = groups.select(support.selector[1], where)
    except GroupError as exc:
        raise SupportError(str(exc)) from None
    P = frame.to_mesh(groups.points * frame.scale)
    info: dict = {"file": groups.path}
    if len(gfaces):
        B, n = groups.boundary, len(groups.points)
        key = lambda t: np.sort(t, axis=1) @ np.array([n * n, n, 1], dtype=np.int64)  # noqa: E731
        in_group = np.isin(key(B), key(gfaces))
        if not in_group.any():
            raise SupportError(f"{where}: its {len(gfaces)} faces in {groups.path} are none on the boundary "
                               "of the mesh; a support must be a part of the outer surface")
        _, d, facet = closest_on_triangles(P[B], vertices[faces].mean(axis=1), k=8)
        mask = in_group[facet]
        info["group_faces"] = int(in_group.sum())
        info["transfer_mm"] = float(d[mask].max()) if mask.any() else 0.0
    else:  # a group of nodes only (vertex or line cells): the patch they mark, as a file of points
        read_as = f"as nodes of {groups.path}, {frame.read_as()}"
        mask, pinfo = points_patch(vertices, faces, P[gnodes], where, read_as)
        info.update(pinfo)
        info["group_nodes"] = int(len(gnodes))
        if not mask.any():
            raise _no_patch(where, len(gnodes), read_as, pinfo)
    return mask, info


def _select_contact(vertices, faces, frame: PointFrame, groups, spec: dict, where: str) -> tuple[np.ndarray, dict]:
    """Facets whose centroid lies within ``groups.REACH_VOXELS`` voxels (in voxel indices) of a segment's
    boundary voxels (:class:`~liverforce.mesh.groups.VolumeGroups`)."""
    from scipy.spatial import cKDTree

    from liverforce.mesh.groups import GroupError

    try:
        ijk, affine, what = groups.contact(spec, where)
    except GroupError as exc:
        raise SupportError(str(exc)) from None
    world = frame.to_file(vertices[faces].mean(axis=1)) / frame.scale  # the image's world, its units
    inv = np.linalg.inv(affine)
    d, _ = cKDTree(ijk).query(world @ inv[:3, :3].T + inv[:3, 3])  # in voxels
    reach = groups.REACH_VOXELS
    mask = d <= reach
    spacing_mm = np.linalg.norm(affine[:3, :3], axis=0) * frame.scale
    if not mask.any():
        raise SupportError(f"{where}: {what} of {groups.path} does not touch the liver (its nearest surface "
                           f"facet is {d.min():.3g} voxels away, beyond {reach:g}): choose the segment the liver "
                           "rests on, or select the support by sphere, box or file")
    return mask, {"file": groups.path, "segment": what, "contact_voxels": reach,
                  "contact_mm": [round(float(reach * v), 4) for v in spacing_mm], "boundary_voxels": int(len(ijk))}


def _units_words(units, frame: PointFrame) -> str:
    """The units of a point file's numbers, for messages: as declared, else the geometry's."""
    if units is not None:
        return str(units)
    if {"mm": 1.0, "cm": 10.0, "m": 1000.0}.get(str(frame.units).lower()) == frame.scale:
        return f"{frame.units} (the geometry's units)"
    return f"the geometry's units ({frame.scale:g} mm each)"


def _units_scale(units) -> float:
    from liverforce.geometry.units import parse_units

    scale, _ = parse_units(units)
    if scale is None:
        raise SupportError(f"units '{units}' cannot be guessed for a point file: give mm, cm, m or a number")
    return float(scale)


def apply_supports(vertices, faces, auto_region: np.ndarray, mode: str, supports: list[Support],
                   frame: PointFrame = PointFrame(), file_vertices=None, base_dir=None,
                   file_groups=None, regions_check: str = "warn") -> tuple[np.ndarray, list]:
    """Region codes of the input surface's facets after the user supports (in order; later override).

    Each report's ``n_facets`` counts the facets the support finally holds; ``n_selected`` the facets its
    selector selected and, when later supports took some, ``taken_by`` ``{name: facets}``. A support left
    with no facet by later ones of another kind or region is refused (:class:`SupportError` naming them):
    a fixed support or a foundation vanishing silently would change the physics. One wholly inside later
    supports of its own kind and region (the same boundary term) is only logged. A file of points (or a sphere)
    read in the wrong frame (RAS as LPS, or the reverse) is warned, or refused under ``regions_check``
    ``strict`` (:func:`select_facets`).
    """
    region, report, _ = assign_supports(vertices, faces, auto_region, mode, supports, frame, file_vertices,
                                        base_dir, file_groups, regions_check)
    return region, report


def assign_supports(vertices, faces, auto_region: np.ndarray, mode: str, supports: list[Support],
                    frame: PointFrame = PointFrame(), file_vertices=None, base_dir=None,
                    file_groups=None, regions_check: str = "warn") -> tuple[np.ndarray, list, np.ndarray]:
    """:func:`apply_supports`, and which support holds each facet: ``(region, report, owner)``, ``owner[i]``
    the index in ``supports`` of the one holding facet ``i``, -1 where none does (an auto-tagged region under
    ``mode: add``, or a free facet); what :func:`snap_exertion_points` names a refused point's support by."""
    region = np.asarray(auto_region, np.int8).copy() if mode == "add" else np.zeros(len(faces), np.int8)
    owner = np.full(len(faces), -1, np.int64)
    report, masks = [], []
    for i, s in enumerate(supports):
        mask, info = select_facets(vertices, faces, s, frame, file_vertices, base_dir, file_groups, regions_check)
        region[mask] = s.code
        owner[mask] = i
        info["region_code"] = int(s.code)
        report.append(info)
        masks.append(mask)
    for i, (s, mask, info) in enumerate(zip(supports, masks, report)):
        held = int((owner == i).sum())
        info["n_selected"] = int(mask.sum())
        info["n_facets"] = held
        if held == info["n_selected"]:
            continue
        lost = np.bincount(owner[mask], minlength=len(supports))
        takers = [j for j in range(i + 1, len(supports)) if lost[j]]
        info["taken_by"] = {supports[j].name: int(lost[j]) for j in takers}
        names = ", ".join(f"'{supports[j].name}' ({supports[j].kind}{_slot(supports[j])}, "
                          f"{supports[j].selector[0]}: {int(lost[j])} facets)" for j in takers)
        if held == 0 and any(supports[j].code != s.code for j in takers):
            raise SupportError(
                f"support '{s.name}' ({s.kind}{_slot(s)}, {s.selector[0]}) selects {info['n_selected']} facets "
                f"but holds none: the later support(s) {names} took them all. Supports apply in order, each overriding "
                f"the earlier ones (mode {mode} only decides what lies beneath them: add the auto-tagged regions, "
                f"replace none). Put '{s.name}' after them in the list, shrink them so they leave it its facets, "
                "or remove it if they are meant to replace it")
        log.log(logging.WARNING if held == 0 else logging.INFO,
                "support %s (%s): %d of its %d facets taken by later support(s) %s; it holds %d",
                s.name, s.kind, info["n_selected"] - held, info["n_selected"], names, held)
    if mode == "add":
        _check_built_in_left(np.asarray(auto_region), owner, supports, report)
    return region, report, owner


#: what each auto-tagged region is as a support (its kind, and a foundation's slot)
_BUILT_IN_KIND = {"ivc": "fixed", "ligament": "foundation ligament", "visceral": "foundation visceral",
                  "rib": "sliding"}


def _check_built_in_left(auto_region: np.ndarray, owner: np.ndarray, supports: list[Support], report: list) -> None:
    """``mode: add``: the auto-tagged regions lie beneath the lab's supports. One wholly covered by lab supports of
    another kind or slot would vanish from the physics (the liver's fixed IVC turned into a sliding bed) without a
    word: refused, naming it and the supports. Facets taken from the built-in regions are listed on each lab
    support (``took_built_in``: region -> facets) and logged."""
    for code, name in ((c, n) for n, c in REGION_CODES.items() if c):
        auto = auto_region == code
        if not auto.any():
            continue
        takers = np.bincount(owner[auto & (owner >= 0)], minlength=len(supports))
        other = [j for j in np.flatnonzero(takers) if supports[j].code != code]
        if not other:
            continue
        for j in other:
            report[j].setdefault("took_built_in", {})[name] = int(takers[j])
        left = int((auto & ~np.isin(owner, other)).sum())
        names = ", ".join(f"'{supports[j].name}' ({supports[j].kind}{_slot(supports[j])}: {int(takers[j])} facets)"
                          for j in other)
        if left == 0:
            raise SupportError(
                f"the built-in {name} region ({_BUILT_IN_KIND[name]}, {int(auto.sum())} facets auto-tagged) is wholly "
                f"covered by the lab's support(s) {names}: with mode add the auto-tagged regions lie beneath the "
                f"lab's supports, so the liver would lose its {_BUILT_IN_KIND[name]} support without a word. Shrink "
                f"them so they leave it facets, or use mode: replace and list every support the liver has")
        log.info("built-in %s region (%s): %d of its %d facets taken by the lab's support(s) %s; it keeps %d",
                 name, _BUILT_IN_KIND[name], int(auto.sum()) - left, int(auto.sum()), names, left)


def _slot(s: Support) -> str:
    return f" {s.region}" if s.kind == "foundation" else ""


def support_stiffness(supports: list[Support], region_area_mm2: dict[int, float]) -> dict[str, float]:
    """Foundation parameters for :class:`~liverforce.fem.problem.BoundaryParams` (``ligament_kn`` ...).

    ``{total_n_per_mm}`` is spread over the final area of the slot's region.
    """
    out: dict[str, float] = {}
    for s in supports:
        if s.kind != "foundation":
            continue
        st = s.stiffness
        if "total_n_per_mm" in st:
            area = region_area_mm2.get(REGION_CODES[s.region], 0.0)
            if not area > 0:
                raise SupportError(f"support '{s.name}': its region '{s.region}' has no area on the mesh")
            kn = float(st["total_n_per_mm"]) / area
            kt = float(st.get("tangential_ratio", 1.0)) * kn
        else:
            kn = float(st["normal_n_per_mm3"])
            kt = float(st.get("tangential_n_per_mm3", kn))
        prev = (out.get(f"{s.region}_kn"), out.get(f"{s.region}_kt"))
        if prev[0] is not None and not np.allclose(prev, (kn, kt)):
            raise SupportError(f"support '{s.name}': two foundations in region '{s.region}' with different "
                               "stiffness; put the other one in the other slot (ligament / visceral)")
        out[f"{s.region}_kn"], out[f"{s.region}_kt"] = kn, kt
    return out



def no_tool_area(supports: list[Support], report: list[dict] | None) -> SupportError:
    """The refusal of a lab's supports that leave no free facet facing the camera, where the sweep samples the
    tool's positions (the visible area: free facets within ``mesh.regions.visible_cone_deg`` of the view, away
    from the supports by ``visible_margin_mm``); ``report`` (:func:`assign_supports`) gives their facet counts."""
    held = {r["name"]: r.get("n_facets") for r in report or []}
    names = ", ".join(f"'{s.name}' ({s.kind}{_slot(s)}, {selector_words(s)}"
                      + (f", {held[s.name]} facets" if held.get(s.name) is not None else "") + ")" for s in supports)
    return SupportError(
        f"the lab's supports {names} leave no free surface facing the camera: the tool's positions are sampled "
        "there (the visible area: free facets facing the view direction, mesh.regions.visible_cone_deg, at least "
        "mesh.regions.visible_margin_mm from a support), and none is left. Shrink the supports so free surface "
        "faces the camera, or give the tool's positions (geometry.imported[].exertion_points)")


#: the weakest rigid motion of the liver its supports must resist, as a fraction of what the supports' area would
#: resist pressing straight against it (:func:`check_held`); a liver on a sliding patch of its posterior surface
#: (1e-3) failed every FE case after 30 s, one wrapped in sliding supports over its whole posterior half (1.2e-2)
#: solved in 2 s
HOLD_MIN = 5e-3


def check_held(points, facets, facet_region, support_boundary: dict | None, supports: list[Support],
               where: str = "supports") -> dict:
    """Refuse supports that leave the liver free to move as a rigid body.

    A fixed facet (region ``ivc``) holds it. Else every rigid motion, three translations and three rotations
    about the supported facets' centroid (scaled by their RMS distance from it, so a rotation moves them as far
    as a translation), is resisted only by the springs: a foundation along the facet normal (``kn > 0``) and
    across it (``kt > 0``), a sliding support along the normal only. With unit weights the 6 x 6 matrix
    ``sum(area * (wn (phi . n)^2 + wt |phi_t|^2)) / area`` has eigenvalue 1 for a motion every support resists
    with its full area; its smallest eigenvalue below :data:`HOLD_MIN` (a sliding patch lets the liver slide
    along it, a foundation of zero stiffness holds nothing) is refused with :class:`SupportError`, naming the
    supports and the motion; the solver would fail every case of the sweep, or swing the liver instead of
    deforming it.

    ``support_boundary`` : the lab's foundation stiffness (:func:`support_stiffness`, N/mm³); a foundation slot
    it does not give is the built-in one (springs both ways). Returns ``{"held_by": "fixed" | "springs",
    "weakest": eigenvalue or None}``.
    """
    points = np.asarray(points, float)
    facets = np.asarray(facets, np.int64)
    region = np.asarray(facet_region)
    if (region == REGION_CODES["ivc"]).any():
        return {"held_by": "fixed", "weakest": None}
    sb = support_boundary or {}
    wn = np.zeros(len(facets))
    wt = np.zeros(len(facets))
    for slot in FOUNDATION_SLOTS:
        on = region == REGION_CODES[slot]
        wn[on] = float(sb.get(f"{slot}_kn", 1.0) > 0)
        wt[on] = float(sb.get(f"{slot}_kt", 1.0) > 0)
    wn[region == REGION_CODES["rib"]] = 1.0
    tri = points[facets]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    n = cross / np.maximum(2.0 * area, 1e-300)[:, None]
    held = area * ((wn + wt) > 0)
    weakest, problem = 0.0, "no support is fixed and none has any stiffness: nothing resists any motion"
    if held.sum() > 0:
        centre = tri.mean(axis=1)
        c = (centre * held[:, None]).sum(axis=0) / held.sum()
        L = max(float(np.sqrt((held * ((centre - c) ** 2).sum(axis=1)).sum() / held.sum())), 1e-9)
        eye = np.eye(3)
        phi = np.stack([np.broadcast_to(e, centre.shape) for e in eye]
                       + [np.cross(e, centre - c) / L for e in eye], axis=1)  # (k, 6, 3)
        pn = np.einsum("kmd,kd->km", phi, n)
        pt = phi - pn[:, :, None] * n[:, None, :]
        K = (np.einsum("k,km,kl->ml", area * wn, pn, pn) + np.einsum("k,kmd,kld->ml", area * wt, pt, pt)) / held.sum()
        ev, vec = np.linalg.eigh(K)
        weakest, free = max(float(ev[0]), 0.0), int((ev < HOLD_MIN).sum())
        problem = (f"no support is fixed, and {_rigid_motion_words(vec[:, 0], c, L)} is resisted at "
                   f"{100 * weakest:.2g} % of the supports' area (below {100 * HOLD_MIN:g} %"
                   + (f"; {free} independent rigid motions are as free" if free > 1 else "") + ")")
    if weakest >= HOLD_MIN:
        return {"held_by": "springs", "weakest": weakest}
    names = ", ".join(f"'{s.name}' ({_hold_words(s, sb)})" for s in supports) or "none"
    raise SupportError(
        f"{where}: the supports do not hold the liver: {problem}; the supports: {names}. "
        "Sliding supports and foundations without tangential stiffness resist motion along their normals only, "
        "a foundation of zero stiffness none: the FE cases would fail, or move the liver as a whole instead of "
        "deforming it. Add a fixed support (kind: fixed, e.g. at the vena cava), a foundation with tangential "
        "stiffness, or use mode: add to keep the built-in supports (the fixed IVC) beneath yours")


def require_held_by(vertices, faces, region, supports: list[Support], where: str) -> dict:
    """:func:`check_held` on a surface whose facets carry the region codes ``region`` after ``supports``
    (:func:`assign_supports`), their foundation stiffness spread over its own areas (:func:`support_stiffness`)."""
    from liverforce.fem.boundary import region_areas

    sb = support_stiffness(supports, region_areas(np.asarray(vertices, float), np.asarray(faces), region))
    return check_held(vertices, faces, region, sb, supports, where)


def _rigid_motion_words(v: np.ndarray, c: np.ndarray, L: float) -> str:
    """A rigid motion ``u(x) = t + w x (x - c)`` (``t = v[:3]``, ``w = v[3:] / L``) in words, RAS mm."""
    t, w = v[:3], v[3:] / L
    if float(v[3:] @ v[3:]) < 0.5:
        return f"a translation along {np.round(t / np.linalg.norm(t), 2).tolist()} (RAS)"
    p = c + np.cross(w, t) / float(w @ w)
    return (f"a rotation about the axis {np.round(w / np.linalg.norm(w), 2).tolist()} through "
            f"{np.round(p, 1).tolist()} mm (RAS)")


def _hold_words(s: Support, sb: dict) -> str:
    """How a support holds its facets, for :func:`check_held`'s message."""
    if s.kind != "foundation":
        return s.kind
    kn, kt = sb.get(f"{s.region}_kn", 1.0), sb.get(f"{s.region}_kt", 1.0)
    how = "no stiffness" if not kn > 0 and not kt > 0 else "no tangential stiffness" if not kt > 0 else (
        "no normal stiffness" if not kn > 0 else "springs both ways")
    return f"foundation {s.region}, {how}"


class TriangleSet:
    """Triangles ``tri (m, 3, 3)`` and the search tree over their centroids, built on the first query and kept:
    several queries on one surface (a refused point and each other reading of it) build it once."""

    def __init__(self, tri: np.ndarray):
        self.tri = np.asarray(tri, dtype=np.float64)

    @functools.cached_property
    def tree(self):
        from scipy.spatial import cKDTree

        return cKDTree(self.tri.mean(axis=1))

    def closest(self, q: np.ndarray, k: int = 16):
        """:func:`closest_on_triangles` of the queries ``q (n, 3)`` on these triangles."""
        return closest_on_triangles(self.tri, q, k, tree=self.tree)


def closest_on_triangles(tri: np.ndarray, q: np.ndarray, k: int = 16, tree=None):
    """Closest point on a triangle set ``tri (m, 3, 3)`` to each query ``q (n, 3)``.

    Searches the ``k`` triangles with the nearest centroids (``tree``: a search tree over them,
    :attr:`TriangleSet.tree`; None: one is built). Returns ``(points (n, 3), distances (n,), triangle index (n,))``.
    """
    from scipy.spatial import cKDTree
    from trimesh.triangles import closest_point

    k = min(int(k), len(tri))
    _, near = (cKDTree(tri.mean(axis=1)) if tree is None else tree).query(q, k=k)
    near = near.reshape(len(q), k)
    cp = closest_point(tri[near.ravel()], np.repeat(q, k, axis=0)).reshape(len(q), k, 3)
    dist = np.linalg.norm(cp - q[:, None], axis=2)
    best = np.argmin(dist, axis=1)
    rows = np.arange(len(q))
    return cp[rows, best], dist[rows, best], near[rows, best]

def _given(a: np.ndarray) -> list:
    return [float(f"{x:.6g}") for x in np.asarray(a, float)]


def snap_exertion_points(vertices, faces, region, xyz_mesh: np.ndarray, max_mm: float = MAX_SNAP_MM,
                         labels: list[str] | None = None, owner: np.ndarray | None = None,
                         supports: list[Support] | None = None, visible: np.ndarray | None = None,
                         regions_check: str = "warn", params=None, not_visible: list | None = None,
                         frame: PointFrame | None = None, reading: ExertionReading | None = None):
    """Closest point on the surface to each given exertion point, refusing far points and fixed supports.

    ``labels`` (from :func:`exertion_points_mesh`) name each point as the user gave it (the file and row, the
    value in the file's units and frame), for the messages; without them a point is named by its index.
    ``owner`` and ``supports`` (from :func:`assign_supports`) name the fixed support a refused point lies on:
    the lab's support holding its facet, else the built-in IVC region (as without them: ``region`` is then
    the auto-tagged one). ``visible`` (the facets' visible mask, what built-in sampling draws the tool's
    positions from; :func:`~liverforce.mesh.regions.visible_facets` with ``params``): a point snapped off it is
    reported by :func:`check_exertion_facing` (a warning; refused under ``regions_check: strict`` if it faces
    away from the camera or looks like a frame mix-up, judged with ``frame`` and ``max_mm``), its record
    appended to ``not_visible``; without ``visible``, or with ``regions_check: off``, that check is not made and
    ``not_visible`` is left as it is. ``reading`` (from :func:`exertion_points_mesh`): how the points were read;
    a point beyond ``max_mm`` is then refused saying when all would lie within it read otherwise
    (:func:`_far_points_words`). Returns ``(points (k, 3), distances (k,))`` in mm (mesh frame).
    """
    q = np.atleast_2d(np.asarray(xyz_mesh, float))
    bad = np.flatnonzero(~np.isfinite(q).all(axis=1))
    if len(bad):
        raise SupportError(f"{_who(int(bad[0]), q, labels)}: a coordinate is not a finite number; give x, y, z")
    triangles = TriangleSet(np.asarray(vertices, float)[np.asarray(faces)])
    pts, d, facet = triangles.closest(q)
    for j in range(len(q)):
        who = _who(j, q, labels)
        if d[j] > max_mm:
            raise SupportError(f"{who} is {d[j]:.3g} mm from the surface (limit {max_mm} mm): check its units and "
                               "frame (points are read in the geometry file's frame, a label volume's being its "
                               "header's world in RAS then the geometry's frame, unless they state frame: LPS, "
                               "RAS or a 4x4; a 3D Slicer markups file states its own), or move it onto the liver"
                               + _far_points_words(triangles, q, reading, max_mm))
        if region is not None and int(region[facet[j]]) == REGION_CODES["ivc"]:
            i = -1 if owner is None else int(owner[facet[j]])
            raise SupportError(f"{who} lies on {_fixed_support_words(supports[i] if i >= 0 else None)}")
    _refuse_repeated_points(pts, q, labels)
    if visible is not None and regions_check != "off":
        found = check_exertion_facing(vertices, faces, visible, q, labels=labels, regions_check=regions_check,
                                      params=params, snapped=(pts, facet), region=region, frame=frame,
                                      max_mm=max_mm)
        if not_visible is not None:
            not_visible.extend(found)
    return pts, d


def _fitting_readings(triangles: TriangleSet, q: np.ndarray, frame: PointFrame, scale_mm: float, own_units: bool,
                      max_mm: float) -> list:
    """The other readings of the points ``q`` (mesh mm, read in the coordinates ``frame`` maps to the mesh, at
    ``scale_mm`` mm per number) under which all of them lie within ``max_mm`` of the surface: ``(unit, fit)``
    pairs, ``unit`` None for mirrored in x and y in those coordinates (:func:`_mirrored`), else the other of mm,
    cm and m their numbers would be in (scaled about that frame's origin; none with ``own_units``, a markups
    file's), ``fit`` the words of how they would lie. One query of all the readings on the surface's search tree
    (:func:`far_words`, :func:`_far_points_words`)."""
    from liverforce.geometry.units import UNIT_TO_MM

    units = [] if own_units else [u for u, mm in UNIT_TO_MM.items() if not np.isclose(mm, scale_mm, rtol=1e-9)]
    in_file = frame.to_file(q)  # the numbers times the mm per number they were read with
    stacked = [_mirrored(q, frame)] + [frame.to_mesh(in_file * (UNIT_TO_MM[u] / scale_mm)) for u in units]
    dist = triangles.closest(np.concatenate(stacked))[1].reshape(len(stacked), len(q))
    return [(unit, f"all {len(q)} {{}} would lie within {max_mm:g} mm of the surface ({d.mean():.3g} mm on "
                   f"average, max {d.max():.3g} mm)")
            for unit, d in zip([None, *units], dist) if float(d.max()) <= max_mm]


def _far_points_words(triangles: TriangleSet, q: np.ndarray, reading: ExertionReading | None,
                      max_mm: float) -> str:
    """For the refusal of given exertion points some of which lie beyond ``max_mm``: the other readings under which
    all of them would lie within it, and what to state for each, or ``""`` (no ``reading``, or vertex ids: the
    geometry file's own vertices). The readings, as :func:`far_words`' for a support's file: mirrored in x and y
    in the coordinates they were read in (the other of RAS and LPS), and, but for a markups file (its own units),
    their numbers in each other of mm, cm and m (about the origin of those coordinates)."""
    from liverforce.geometry.units import UNIT_TO_MM

    if reading is None or reading.kind == "vertex_ids":
        return ""
    said = []
    for unit, fit in _fitting_readings(triangles, q, reading.frame, reading.scale_mm, reading.kind == "markups",
                                       max_mm):
        fit = fit.format("given point" + "s" * (len(q) != 1))
        if unit is None:
            other = _OTHER.get(reading.frame_name or "", "the other of RAS and LPS")
            said.append(f"mirrored in x and y ({_MIRROR_WORDS}) {fit}, so they are likely in {other}: "
                        f"{_exertion_frame_fix(reading, other)}")
        else:
            fix = ("coordinates_mm are mm: give them in mm" if reading.kind == "coordinates_mm"
                   else f"state exertion_points.units: {unit}" if reading.units_stated
                   else f"the file states no units, so its numbers are read in the geometry's: state "
                        f"exertion_points.units: {unit}")
            said.append(f"scaled by {UNIT_TO_MM[unit] / reading.scale_mm:g} (their numbers in {unit}, read "
                        f"{_units_read(reading)}) {fit}, so they are likely in {unit}: {fix}")
    return "".join(f". {x[0].upper()}{x[1:]}" for x in said)


def _exertion_frame_fix(reading: ExertionReading, other: str) -> str:
    """What to do when given exertion points look read in the other of RAS and LPS (:func:`_far_points_words`)."""
    liver = ("the liver may be the one read in the wrong frame: check geometry.imported[].frame (and any warning "
             "of implausible regions)")
    if reading.kind == "markups":
        return (f"the markups file states coordinateSystem {reading.frame_name or 'LPS or RAS'}: if its points are "
                f"in {other}, correct that in the file (export it again from 3D Slicer); if the file is right, "
                f"{liver}")
    setting = (f"exertion_points.frame: {other}" if reading.frame_name else "exertion_points.frame: that 4x4 with "
               "its first two columns negated (or RAS or LPS, for coordinates in those world coordinates)")
    if reading.frame_stated:
        return (f"if they are {'in ' + other if reading.frame_name else 'so'}, state {setting}; if "
                f"{reading.frame_name or 'its 4x4'} is right, {liver}")
    return (f"they state no frame, so they are read in the geometry's: state {setting} (changing "
            "geometry.imported[].frame would turn the liver and the points alike)")


#: two given exertion points snapped closer than this (mm) are one tool position given twice
SAME_POINT_MM = 1.0


def _refuse_repeated_points(snapped: np.ndarray, q: np.ndarray, labels: list[str] | None) -> None:
    """Refuse two given exertion points that snap to one place (closer than :data:`SAME_POINT_MM`): each would
    get its own ``exertion_id`` and its own cases, so a fold of ``train.heldout_points`` would hold one out while
    training on the other, the same position, and score a seen point as unseen."""
    from scipy.spatial import cKDTree

    pairs = sorted(cKDTree(snapped).query_pairs(SAME_POINT_MM))
    if pairs:
        i, j = pairs[0]
        gap = float(np.linalg.norm(snapped[i] - snapped[j]))
        raise SupportError(f"{_who(j, q, labels)} is the tool position of {_who(i, q, labels)} again ({gap:.3g} mm "
                           f"apart on the surface, under {SAME_POINT_MM:g} mm; {len(pairs)} such pair"
                           f"{'s' * (len(pairs) != 1)}): the sweep would press there as two positions, and a "
                           "held-out position (train.heldout_points) would be trained on under the other's id. "
                           "List each tool position once")


def _who(j: int, q: np.ndarray, labels: list[str] | None) -> str:
    """Exertion point ``j`` as the messages name it: as given (``labels``) and where it lies as meshed."""
    if labels and j < len(labels):
        return f"exertion point {j} ({labels[j]}; {np.round(q[j], 3).tolist()} RAS mm as meshed)"
    return f"exertion point {j} {np.round(q[j], 3).tolist()} (mesh frame, mm)"


#: x and y mirrored: a point file in RAS read as LPS, or in LPS read as RAS
_LPS_RAS = np.array([-1.0, -1.0, 1.0])


def check_exertion_facing(vertices, faces, visible, xyz_mesh: np.ndarray, labels: list[str] | None = None,
                          regions_check: str = "warn", params=None, snapped=None, region=None,
                          frame: PointFrame | None = None, max_mm: float = MAX_SNAP_MM) -> list[dict] | None:
    """Given exertion points that do not lie on the ``visible`` facets (the camera-facing area built-in sampling
    draws the tool's positions from), each logged as a warning with one record: ``point`` (its index),
    ``as_given`` (its label, or None), ``snapped_mm`` (mesh frame), ``normal_ras`` and ``angle_to_view_deg``
    (the facet's normal and its angle to the view direction exactly as the visible area was classified with:
    :func:`~liverforce.mesh.regions.classified_normals`, :func:`~liverforce.mesh.regions.view_direction`),
    ``facing`` (``"away"``: beyond 90 deg, the normal points away from the view direction; ``"oblique"``:
    between ``visible_cone_deg`` and 90 deg, facing the camera from the side; ``"camera"``: within the cone but
    on a tagged region, near one, or in a speck of visible area), ``frame_mix_up`` (the point mirrored in x and
    y, as an RAS point file read as LPS or the reverse, snaps within ``max_mm`` onto a visible facet: then
    ``{"mirrored_mm": [x, y, z] mesh frame, "distance_mm": d}``, else None), ``refused_under_strict`` (facing
    away or a frame mix-up) and ``warning`` (the message).

    The simulated camera looks along the outward normal at the point: a point facing away would train the camera
    model on views from behind the liver, an oblique one on views from the side. ``regions_check``: ``warn``
    logs and returns the records; ``strict`` refuses (:class:`SupportError` naming them) the points facing away
    and the frame mix-ups, and warns of the others; ``off`` checks nothing and returns None (as the features
    JSON's ``exertion_not_visible`` is null when the check is not made; a list, empty when all are visible,
    when it is). ``params`` (:class:`RegionParams`, defaults if None): those the ``visible`` mask was computed
    with. ``snapped``: ``(points, facet)`` as :func:`closest_on_triangles` snapped ``xyz_mesh``, else snapped
    here; ``region`` (the facets' region codes, optional) names the region a point off the visible area lies on.
    ``frame`` (:class:`PointFrame`, the geometry file's frame the points were read in): the mirror is taken in
    its coordinates (without it, in the mesh frame, the same for RAS and LPS files)."""
    if regions_check == "off":
        return None
    from liverforce.mesh.regions import RegionParams, classified_normals, view_cosines, view_direction

    p = params or RegionParams()
    V = np.asarray(vertices, float)
    F = np.asarray(faces, np.int64)
    visible = np.asarray(visible, bool)
    q = np.atleast_2d(np.asarray(xyz_mesh, float))
    tri = V[F]
    pts, facet = snapped if snapped is not None else closest_on_triangles(tri, q, k=16)[::2]
    off = [j for j in range(len(q)) if not visible[facet[j]]]
    if off and visible.any():  # on an edge or corner of a visible facet: on the visible area
        on_edge = closest_on_triangles(tri[visible], pts[off], k=16)[1] <= 1e-6 * max(1.0, float(np.ptp(V)))
        off = [j for j, edge in zip(off, on_edge) if not edge]
    if not off:
        return []
    normals = classified_normals(V, F, p)[[facet[j] for j in off]]  # as the visible area was classified
    cosines = view_cosines(normals, p)
    view = view_direction(p)
    mirrored = _mirrored(q[off], frame)
    m_pts, m_d, m_facet = closest_on_triangles(tri, mirrored, k=16)
    found, refused, warned = [], [], []
    for i, j in enumerate(off):
        n, c = normals[i], float(cosines[i])
        angle = float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))
        facing = "away" if c < 0 else "oblique" if c < np.cos(np.deg2rad(p.visible_cone_deg)) else "camera"
        mix = ({"mirrored_mm": _given(m_pts[i]), "distance_mm": round(float(m_d[i]), 3)}
               if m_d[i] <= max_mm and visible[m_facet[i]] else None)
        code = 0 if region is None else int(region[facet[j]])
        msg = _facing_words(_who(j, q, labels), n, angle, view, p, facing, mix, code)
        strict = facing == "away" or mix is not None
        found.append({"point": j, "as_given": labels[j] if labels and j < len(labels) else None,
                      "snapped_mm": _given(pts[j]), "normal_ras": [round(float(x), 3) for x in n],
                      "angle_to_view_deg": round(angle, 1), "facing": facing, "frame_mix_up": mix,
                      "refused_under_strict": strict, "warning": msg})
        (refused if strict else warned).append(msg)
    if regions_check == "strict" and refused:
        raise SupportError("\n".join(refused) + "\n(mesh.regions_check=strict refuses exertion points facing away "
                           "from the camera or read in the wrong frame; set it to warn to go on regardless)")
    for msg in (warned if regions_check == "strict" else refused + warned):
        log.warning("%s", msg)
    return found


def _mirrored(q: np.ndarray, frame: PointFrame | None) -> np.ndarray:
    """Points (mesh frame) as they would be had their file been read in the other of RAS and LPS: x and y
    mirrored in the coordinates they were read in (``frame``'s, else the mesh frame's)."""
    if frame is None:
        return q * _LPS_RAS
    return frame.to_mesh(frame.to_file(q) * _LPS_RAS)


def _facing_words(who: str, n: np.ndarray, angle: float, view: np.ndarray, p, facing: str, mix: dict | None,
                  code: int = 0) -> str:
    """Why a given exertion point off the visible area matters, and what to do."""
    normal = f"its outward normal there is {np.round(n, 2).tolist()} (RAS, averaged over {p.normal_smoothing_mm:g} mm)"
    cone = (f"{angle:.0f} deg from the view direction {np.round(view, 2).tolist()} (RAS: mesh.regions.anterior tilted "
            f"visible_tilt_deg={p.visible_tilt_deg:g} toward superior; the visible area takes normals within "
            f"visible_cone_deg={p.visible_cone_deg:g})")
    name = next((k for k, c in REGION_CODES.items() if c == code), None) if code else None
    on_region = (f" It also lies on the {name} region ({_BUILT_IN_KIND.get(name, name)} support, the lab's or "
                 "auto-tagged)." if name else "")
    if mix is not None:
        frames = (f" Likely a frame mix-up: mirrored in x and y (the point file in RAS read as LPS, or in LPS read "
                  f"as RAS) it lands {mix['distance_mm']:.3g} mm from the visible area, at "
                  f"{np.round(mix['mirrored_mm'], 3).tolist()} RAS mm as meshed; state exertion_points.frame: LPS "
                  "or RAS, or fix the geometry's frame.")
    elif facing == "away":
        frames = (" Mirrored in x and y on its own (its point file in RAS read as LPS, or the reverse) it would not "
                  "land on the visible area either, so reading the point file in the other frame would not help. "
                  "If the liver itself was given in the wrong frame (see any warning of implausible regions for the "
                  "stated frame), the whole liver is mirrored and its front faces away: fix the geometry's frame "
                  "(geometry.imported[].frame), not the points'.")
    else:
        frames = ""
    if facing == "away":
        return (f"{who} lies on the surface facing away from the camera, off the visible area where built-in "
                f"sampling places the tool: {normal}, {cone}, more than 90 deg. The camera model is trained on "
                "views along the outward normal at the exertion point, and a laparoscope sees the liver from the "
                f"front: here it would learn views from behind the liver.{on_region}{frames} If the point is meant, "
                "widen the visible area (mesh.regions.visible_cone_deg, visible_tilt_deg, anterior, superior); "
                "otherwise move it onto the liver's front")
    if facing == "oblique":
        return (f"{who} lies on an oblique part of the surface, off the visible area where built-in sampling places "
                f"the tool: {normal}, {cone}, so it faces the camera, but from the side: outside "
                "mesh.regions.visible_cone_deg, under 90 deg. The camera model is trained on views along the outward "
                f"normal at the exertion point, which here would come from the side of the liver.{on_region}{frames}"
                f" If the point is meant, widen mesh.regions.visible_cone_deg (to at least {int(np.ceil(angle))})")
    if code:
        return (f"{who} lies off the visible area where built-in sampling places the tool: {normal}, {cone}, so it "
                f"faces the camera, but it lies on the {name} region ({_BUILT_IN_KIND.get(name, name)} support, "
                "the lab's or auto-tagged). The camera model is trained on views along the outward normal at the "
                f"exertion point, on free surface the tool can push.{frames} Move the point off that support, or "
                "shrink it")
    return (f"{who} lies off the visible area where built-in sampling places the tool: {normal}, {cone}, so it faces "
            f"the camera, but the facet is within mesh.regions.visible_margin_mm={p.visible_margin_mm:g} mm of a "
            f"support or tagged region, or in a visible patch smaller than min_patch_fraction="
            f"{p.min_patch_fraction:g} of the visible area. The camera model is trained on views along the outward "
            f"normal at the exertion point.{frames} Move the point away from the support, or, if it is meant, "
            "lower mesh.regions.visible_margin_mm")


def _fixed_support_words(s: Support | None) -> str:
    """The fixed support a refused exertion point lies on, as the lab's config or the auto-tagging names it,
    and what to do."""
    if s is None:
        return ("a fixed support, the built-in IVC region (auto-tagged on the posterior face by "
                "mesh.regions.ivc_position and ivc_radius_mm; with supports mode: add it lies beneath the lab's "
                "supports): the tool cannot push a clamped surface; move the point, or shrink or move that region "
                "(mesh.regions.ivc_radius_mm, ivc_position), or list the liver's own supports with mode: replace")
    where = f"{s.key}, " if s.key else ""
    return (f"a fixed support, the lab's '{s.name}' ({where}selected by {s.selector[0]}): the tool cannot push a "
            f"clamped surface; move the point, or shrink or move the support '{s.name}'")


def exertion_points_mesh(spec, frame: PointFrame = PointFrame(), file_vertices=None, base_dir=None,
                         labels: list | None = None, reading: list | None = None) -> np.ndarray:
    """Given exertion points → mesh-frame mm: ``{coordinates_mm: [[x,y,z],..]}``,
    ``{vertex_ids: [..]}`` or ``{path: ..., units: ...}`` (a point file, as support files).

    A ``labels`` list is filled with one phrase per point naming it as given (``coordinates_mm[1] [x, y, z]``,
    ``vertex_ids[0] = 245``, ``row 2 of pts.csv: [x, y, z] m``), for :func:`snap_exertion_points`' messages; a
    ``reading`` list with how they were read (one :class:`ExertionReading`), for the hints of its refusals.
    ``units`` beside ``coordinates_mm`` or ``vertex_ids`` is refused: it applies to a point file only (it was
    ignored)."""
    spec = dict(spec)
    labels = labels if labels is not None else []
    reading = reading if reading is not None else []
    keys = set(spec) - {"units", "frame"}
    if spec.get("frame") is not None and keys == {"vertex_ids"}:
        raise SupportError("exertion_points.frame: vertex ids have no frame (they index the file's vertices)")
    if spec.get("units") is not None and keys in ({"coordinates_mm"}, {"vertex_ids"}):
        raise SupportError(f"exertion_points.units: {next(iter(keys))} take no units (coordinates_mm are mm; vertex "
                           "ids index the file's vertices); units applies to a point file (path)")
    stated = spec.get("frame") is not None
    frame = frame.stated(spec.get("frame"), "exertion_points")
    if keys == {"coordinates_mm"}:
        a = coordinate_list(spec["coordinates_mm"], "exertion_points.coordinates_mm")
        labels[:] = [f"exertion_points.coordinates_mm[{j}] {_given(x)} mm" for j, x in enumerate(a)]
        reading[:] = [ExertionReading("coordinates_mm", frame, frame.read_in(), 1.0, stated)]
        return frame.to_mesh(a)
    if keys == {"vertex_ids"}:
        a = vertex_id_list(spec["vertex_ids"], "exertion_points.vertex_ids")
        labels[:] = [f"exertion_points.vertex_ids[{j}] = {int(i)}" for j, i in enumerate(a)]
    elif keys == {"path"}:
        p = Path(spec["path"])
        p = p if p.is_absolute() or base_dir is None else Path(base_dir) / p
        if is_markups(p):  # a Slicer markups file: world RAS mm
            a = read_markups(p, spec, "exertion_points")
            labels[:] = [f"control point {j + 1} of {p}: {_given(x)} RAS mm" for j, x in enumerate(a)]
            systems = _markups_systems(p)
            reading[:] = [ExertionReading("markups", PointFrame(matrix=frame.world),
                                          systems if systems in ("RAS", "LPS") else None)]
            return frame.from_world(a)
        units = _units_words(spec.get("units"), frame)
        scale = frame.scale if spec.get("units") is None else _units_scale(spec["units"])
        a = read_point_file(p, units, scale)
        if a.ndim == 1 and spec.get("frame") is not None:
            raise SupportError("exertion_points.frame: vertex ids have no frame (they index the file's vertices)")
        if a.ndim == 2:
            labels[:] = [f"point {j + 1} of {p}: {_given(x)} in {units}" for j, x in enumerate(a)]
            reading[:] = [ExertionReading("file", frame, frame.read_in(), scale, stated,
                                          spec.get("units") is not None)]
            return frame.to_mesh(a * scale)
        labels[:] = [f"vertex id {int(i)} (point {j + 1} of {p})" for j, i in enumerate(a)]
    else:
        raise SupportError("exertion_points: give one of coordinates_mm, vertex_ids or path "
                           f"(with optional units and frame), got {sorted(spec)}")
    reading[:] = [ExertionReading("vertex_ids", frame, None)]
    if file_vertices is None:
        raise SupportError("exertion_points.vertex_ids need the geometry file's vertices (an imported geometry)")
    fv = np.asarray(file_vertices(), float)
    if len(a) == 0 or a.min() < 0 or a.max() >= len(fv):
        raise SupportError(f"exertion_points.vertex_ids must be in [0, {len(fv)}) (the file's vertices)")
    return frame.to_mesh(fv[a] * frame.scale)

# --------------------------------------------------------------------------
# A support's file of points read in the wrong frame (RAS read as LPS, or the reverse)
# --------------------------------------------------------------------------
#
# Reading a point file in the other of RAS and LPS turns its points by 180 deg about the superior axis
# (``x, y -> -x, -y`` in the coordinates they are read in). Far from the surface they are refused already
# (:data:`~liverforce.mesh.supports.MAX_SNAP_MM`); on a liver roughly symmetric about that axis through the file's
# origin they can still land within it, on the other side of the liver, and the support would hold the wrong
# place without a word. Points marked on a segmentation's surface fit it within a fraction of a mm, so the file's
# frame shows in how well its points fit the surface as read and mirrored (:func:`check_support_frame`).
#
# The rule: the points look read in the wrong frame when, mirrored, all lie within the snap limit and their
# mean distance to the surface is at most :data:`FRAME_FIT_RATIO` of the mean as read and at least
# :data:`FRAME_FIT_MARGIN_MM` smaller. Measured on the procedural livers of seeds 0-5, an icosphere (r 60 mm) and
# three ellipsoids (125 x 75 x 55 mm) centred 1-4 mm off the origin: 11 800 patches of 3-100 points drawn on the
# surface within 5-40 mm of a place (10 000 of them where the place's mirror lands within 3 mm of the surface),
# each read as drawn and mirrored:
#
# * read in the right frame, never flagged: 0 of 2 971 exact, 0 of 4 448 moved up to 1 mm (uniform in a ball),
#   0 of 2 934 with Gaussian noise of 0.25 or 0.5 mm per axis; with 1 mm per axis (1.7 mm RMS, more than a
#   segmentation's surface gives) 1 of 1 447, five points;
# * read in the wrong frame and still within 5 mm (5 757): flagged 2 684 of the 2 691 whose mean fits differ by
#   1 mm or more, 3 526 of the 3 613 that differ by 0.5 mm or more (with noise up to 1 mm: 2 497 of 2 497 and
#   3 293 of 3 296). The 1 759 that differ by less than 0.3 mm (the sphere, a liver symmetric there) cannot be
#   told by the fit and are not flagged.
#
# A second signal, the patch on the camera-facing visible area and its mirror not, is not used: a lab's support
# may hold the liver's front (the falciform ligament, a clamp), and the visible area is tagged after the supports.
#
# Not checked: vertex ids and a mesh file's groups of nodes (the geometry file's own vertices, read in its frame),
# and boxes (their corners need not lie on the surface: no fit to compare). A sphere has one point to compare, its
# centre, which need not lie on the surface either; it is checked by a rule of its own (:func:`check_sphere_frame`).
# A sphere or box that selects nothing is refused saying what it would select mirrored or in cm or m
# (:func:`_shape_readings`).

#: mirrored, the points' mean distance to the surface must be at most this fraction of the mean as read ...
FRAME_FIT_RATIO = 0.5
#: ... and at least this much smaller (mm), for the file to look read in the wrong frame
FRAME_FIT_MARGIN_MM = 0.5

_OTHER = {"RAS": "LPS", "LPS": "RAS"}


def frame_fits(triangles: TriangleSet, xyz_mesh: np.ndarray, read_in: PointFrame) -> dict:
    """How the points ``xyz_mesh`` (mesh mm) fit the surface ``triangles`` as read and mirrored in x and y in
    the coordinates ``read_in`` maps to the mesh (``_mirrored``): ``{"as_given_mm": {"mean", "max"},
    "mirrored_mm": {"mean", "max"}, "likely_mix_up": bool}`` (the rule of the comment above): two
    queries of the points on the surface's search tree, no loop over its facets."""
    q = np.atleast_2d(np.asarray(xyz_mesh, float))
    given = triangles.closest(q)[1]
    mirrored = triangles.closest(_mirrored(q, read_in))[1]
    g, m = float(given.mean()), float(mirrored.mean())
    likely = (float(mirrored.max()) <= MAX_SNAP_MM and m <= FRAME_FIT_RATIO * g
              and g - m >= FRAME_FIT_MARGIN_MM)
    return {"as_given_mm": {"mean": round(g, 4), "max": round(float(given.max()), 4)},
            "mirrored_mm": {"mean": round(m, 4), "max": round(float(mirrored.max()), 4)},
            "likely_mix_up": bool(likely)}


def check_support_frame(reading: PointReading, what: str, triangles: TriangleSet, xyz_mesh: np.ndarray,
                        read_as: str, regions_check: str = "warn") -> dict | None:
    """The frame check of a support given by a file of points (:func:`frame_fits`), as recorded on its report
    (``frame_check``): the fits, ``read_in`` (the frame its coordinates were read in: ``reading.frame_name``, RAS
    or LPS; ``a 4x4``; for a markups file of no one system, ``the markups file's own``), ``refused_under_strict``
    (a likely mix-up), ``warning`` (None when the frame looks right or cannot be told) and ``advice`` (its last
    part, what to state or correct, for the report; None with it).

    ``reading``: how the file was read (:class:`PointReading`: the support, the frame its coordinates map to the
    mesh with, that frame's name, a 3D Slicer markups file?); ``what`` names the support and its file, ``read_as``
    how its coordinates were read (units and frame). ``regions_check`` (``mesh.regions_check``): ``warn``
    logs the warning; ``strict`` refuses (:class:`~liverforce.mesh.supports.SupportError`); ``off`` checks
    nothing and returns None."""
    if regions_check == "off":
        return None
    fits = frame_fits(triangles, xyz_mesh, reading.frame)
    fix = _frame_fix(reading.support, reading.frame_name, reading.markups) if fits["likely_mix_up"] else None
    msg = _words(what, fits, read_as, fix, len(np.atleast_2d(xyz_mesh)))
    read_in_name = reading.frame_name or ("the markups file's own" if reading.markups else "a 4x4")
    record = {"read_in": read_in_name, **fits, "refused_under_strict": fits["likely_mix_up"],
              "warning": msg, "advice": fix}
    return _frame_flagged(record, regions_check)


def _frame_flagged(record: dict, regions_check: str) -> dict:
    """A frame check's ``record``, its warning (if any) logged, or refused when ``refused_under_strict`` under
    ``regions_check: strict``."""
    msg = record["warning"]
    if msg is None:
        return record
    if regions_check == "strict" and record["refused_under_strict"]:
        raise SupportError(msg + "\n(mesh.regions_check=strict refuses a support that looks read in the wrong "
                                 "frame; set it to warn to go on regardless)")
    log.warning("%s", msg)
    return record


def _words(what: str, fits: dict, read_as: str, fix: str | None, n: int) -> str | None:
    """The warning of a support whose points fit the surface better mirrored, naming both fits and the ``fix``
    (:func:`_frame_fix`; None: not flagged, no warning)."""
    if fix is None:
        return None
    g, m = fits["as_given_mm"], fits["mirrored_mm"]
    return (f"{what} looks read in the wrong frame: its {n} points, read {read_as}, lie {g['mean']:.3g} mm from "
            f"the surface on average (max {g['max']:.3g} mm); mirrored in x and y ({_MIRROR_WORDS}) they would lie "
            f"{m['mean']:.3g} mm (max {m['max']:.3g} mm) from it. Points marked on the liver's surface fit it within "
            f"a fraction of a mm, so the support is likely put on the wrong side of the liver. {fix}. (Flagged "
            f"when, mirrored, the points fit at most {FRAME_FIT_RATIO:g} times as far and {FRAME_FIT_MARGIN_MM:g} "
            "mm closer on average.)")


#: what mirroring coordinates in x and y stands for, in the messages
_MIRROR_WORDS = ("coordinates in RAS read as LPS, or in LPS read as RAS: half a turn about the superior axis "
                 "through the origin of the coordinates as read")


def _frame_fix(support: Support, frame_name: str | None, markups: bool) -> str:
    """What to do when a support's file of points (or sphere, or box) looks read in the other of RAS and LPS than
    ``frame_name`` (None: a 4x4): the setting to state where the lab gave the support, or the markups file to
    correct; or, if the file is right, the liver's frame to check."""
    other = _OTHER.get(frame_name or "")
    liver = ("the liver may be the one read in the wrong frame: check geometry.imported[].frame (and any warning "
             "of implausible regions)")
    # a 4x4 (other is None): the file in the other of RAS and LPS than the coordinates the 4x4 takes
    in_other = f"in {other}" if other else "in the other of RAS and LPS than the coordinates its 4x4 takes"
    if other:
        setting = _setting(support, other)
    else:
        setting = (_setting(support, "that 4x4 with its first two columns negated")
                   + f" (or RAS or LPS, for {'a file' if support.selector[0] == 'file' else 'coordinates'} in those "
                   "world coordinates)")
    if markups:
        return (f"The markups file states coordinateSystem {frame_name or 'LPS or RAS'}: if its points are in "
                f"{other or 'the other'}, correct that in the file (export it again from 3D Slicer); if the file "
                f"is right, {liver}")
    kind = support.selector[0]
    if kind == "file":
        it_is, its, both = "the file is", "its points", "these points"
    else:
        it_is, its, both = f"the {kind}'s coordinates are", "its coordinates", f"the {kind}"
    if support.selector[1].get("frame") is not None:
        return f"If {it_is} {in_other}, state {setting}; if {frame_name or 'its 4x4'} is right, {liver}"
    return (f"The {kind} states no frame, so {its} are read in the geometry's: if {it_is} {in_other}, "
            f"state {setting} (changing geometry.imported[].frame would turn the liver and {both} alike)")


def far_words(reading: PointReading, triangles: TriangleSet, xyz_mesh: np.ndarray, max_mm: float) -> str:
    """For the refusal of a support's file of points some of which lie beyond ``max_mm`` of the surface
    (:func:`~liverforce.mesh.supports.points_patch`): the other readings of the file under which all of them
    would lie within it, and what to state for each, or ``""`` when none would.

    The readings: mirrored in x and y in the coordinates the file was read in (the other of RAS and LPS, as
    :func:`frame_fits`), and, but for a 3D Slicer markups file (it states its units, mm or um), the file's
    numbers in each other of mm, cm and m than they were read in (scaled about the file's origin by 10, 1000,
    0.1, 0.001, or 100 and 0.01 between cm and m). One query of all the readings' points on the surface's
    search tree."""
    from liverforce.geometry.units import UNIT_TO_MM

    q = np.atleast_2d(np.asarray(xyz_mesh, float))
    said = []
    for unit, fit in _fitting_readings(triangles, q, reading.frame, reading.scale_mm, reading.markups, max_mm):
        fit = fit.format("points")
        if unit is None:
            other = _OTHER.get(reading.frame_name or "", "the other of RAS and LPS")
            said.append(f"mirrored in x and y ({_MIRROR_WORDS}) {fit}, so the file is likely in {other}. "
                        f"{_frame_fix(reading.support, reading.frame_name, reading.markups)}")
        else:
            said.append(f"scaled by {UNIT_TO_MM[unit] / reading.scale_mm:g} (its numbers in {unit}, read "
                        f"{_units_read(reading)}) {fit}, so the file is likely in {unit}: "
                        f"{_units_fix(reading.support, unit)}")
    return "".join(f". {s[0].upper()}{s[1:]}" for s in said)


def _units_read(reading: PointReading) -> str:
    """The units a support's file of points was read in, for messages: ``in mm`` or ``as 40 mm each``."""
    from liverforce.geometry.units import UNIT_TO_MM

    unit = next((u for u, mm in UNIT_TO_MM.items() if np.isclose(mm, reading.scale_mm, rtol=1e-9)), None)
    return f"in {unit}" if unit else f"as {reading.scale_mm:g} mm each"


def _units_fix(support: Support, unit: str) -> str:
    """The setting that states a support file's units, and what the file is read in without it."""
    if support.selector[1].get("units") is not None:
        return f"state {_setting(support, unit, 'units')}"
    return (f"the file states no units, so its numbers are read in the geometry's: state "
            f"{_setting(support, unit, 'units')}")


def _setting(support: Support, value: str, key: str = "frame") -> str:
    """The setting that states a support selector's ``frame`` (or a file's ``units``), where the lab gave the
    support."""
    kind = support.selector[0]
    if support.key:
        return f"{support.key}.{kind}.{key}: {value}"
    return f"{key}: {value} in the {kind} selector of the support '{support.name}'"


# A sphere's frame. Its centre need not lie on the surface (the middle of the vena cava, beside the liver), so
# its distance to it tells nothing alone. A centre picked on the surface (a click on the liver in 3D Slicer) lies
# on it, and, read in the other of RAS and LPS, lies off it; so the sphere looks read in the wrong frame when its
# centre, mirrored in x and y, lies within SPHERE_ON_SURFACE_MM of the surface while as read it lies
# SPHERE_OFF_SURFACE_MM or more off it. Measured (benchmarks/experiment_sphere_frame.py) on the procedural livers
# of seeds 0-5 and three ellipsoids (125 x 75 x 55 mm) centred 1-4 mm off the origin, 13,500 centres each:
# * read in the right frame, never flagged: 0 of 13,500 centres on the surface, 0 of 13,500 moved off it by
#   Gaussian noise of 0.5 mm; 1.7 % of 13,500 centres 0-15 mm off the surface along its normal (inside or
#   outside; their mirror lands on the surface by chance);
# * read in the wrong frame, with the sphere (radius 10-40 mm) still selecting facets, so that nothing else
#   would say so: flagged 45 % of the centres picked on the surface (43 % with 0.5 mm of noise). The others lie
#   within 5 mm of the surface as read too (the liver near symmetric there) and cannot be told by the distance.
#   A centre off the surface read in the wrong frame is flagged 3 % of the time.

#: mirrored, a sphere's centre must lie this close to the surface (mm) ...
SPHERE_ON_SURFACE_MM = 1.0
#: ... and as read at least this far from it, for the sphere to look read in the wrong frame
SPHERE_OFF_SURFACE_MM = 5.0


def check_sphere_frame(support: Support, frame: PointFrame, triangles: TriangleSet, read_as: str,
                       regions_check: str = "warn") -> dict | None:
    """The frame check of a sphere selector that selects facets, as recorded on its support's report
    (``frame_check``, the keys of :func:`check_support_frame`'s with the centre's distance to the surface as both
    ``mean`` and ``max``, and ``of: centre``): flagged by the rule above. ``frame`` maps the coordinates the sphere
    is read in (mm) to the mesh; ``read_as`` says how, for the warning. ``regions_check``: ``warn`` logs it,
    ``strict`` refuses it unless the sphere states its ``frame`` (the lab's word for it: a centre off the surface
    whose mirror lands on it by chance, 1.7 % of such centres, is then only warned), ``off`` checks nothing (None)."""
    if regions_check == "off":
        return None
    centre = frame.to_mesh(np.asarray(support.selector[1]["center_mm"], float)[None])
    read, mirrored = (float(x) for x in triangles.closest(np.concatenate([centre, _mirrored(centre, frame)]))[1])
    likely = mirrored <= SPHERE_ON_SURFACE_MM and read >= SPHERE_OFF_SURFACE_MM
    stated = support.selector[1].get("frame") is not None
    fix = msg = None
    if likely:
        fix = _frame_fix(support, frame.read_in(), False)
        if not stated:
            fix += (f"; if the centre is right (a point off the surface whose mirror lands on it by chance), state "
                    f"{_setting(support, frame.read_in() or 'its 4x4')} to say so")
        msg = (f"support '{support.name}' ({selector_words(support)}) looks read in the wrong frame: its centre, "
               f"read {read_as}, lies {read:.3g} mm from the surface; mirrored in x and y ({_MIRROR_WORDS}) it "
               f"would lie {mirrored:.3g} mm from it, as a point picked on the liver's surface does, so the sphere "
               f"likely holds the wrong side of the liver. {fix}. (Flagged when, mirrored, the centre lies within "
               f"{SPHERE_ON_SURFACE_MM:g} mm of the surface and, as read, {SPHERE_OFF_SURFACE_MM:g} mm or more off "
               "it; a sphere that states its frame is not refused for it under mesh.regions_check: strict.)")
    record = {"of": "centre", "read_in": frame.read_in() or "a 4x4",
              "as_given_mm": {"mean": round(read, 4), "max": round(read, 4)},
              "mirrored_mm": {"mean": round(mirrored, 4), "max": round(mirrored, 4)},
              "likely_mix_up": bool(likely), "refused_under_strict": bool(likely and not stated), "warning": msg,
              "advice": fix}
    return _frame_flagged(record, regions_check)


#: a reading of a sphere's or box's numbers in cm or m is named only when it selects at most this fraction of the
#: facets: scaled by 10 or 1000 about the origin, a small shape left there would swallow the liver
SHAPE_READING_MAX_FRACTION = 0.5


def _shape_readings(support: Support, cent: np.ndarray, frame: PointFrame) -> str:
    """For the refusal of a sphere or box that selects no facet: the other readings of its numbers under which it
    would select some, and what to do for each, or ``""`` when none would. The readings: mirrored in x and y in
    the coordinates it is read in (the other of RAS and LPS), and its numbers in cm or m rather than mm (when
    they select at most :data:`SHAPE_READING_MAX_FRACTION` of the facets). ``cent``: the facets' centroids in
    those coordinates (mm)."""
    from liverforce.geometry.units import UNIT_TO_MM

    kind, d = support.selector
    said = []
    n = int(_inside(kind, d, cent * _LPS_RAS).sum())
    if n:
        other = _OTHER.get(frame.read_in() or "", "the other of RAS and LPS")
        said.append(f"mirrored in x and y ({_MIRROR_WORDS}) it would select {n} facets, so its coordinates are "
                    f"likely in {other}. {_frame_fix(support, frame.read_in(), False)}")
    keys = "center_mm, radius_mm" if kind == "sphere" else "min_mm, max_mm"
    for unit, mm in UNIT_TO_MM.items():
        n = int(_inside(kind, d, cent, mm).sum()) if mm != 1.0 else 0
        if 0 < n <= SHAPE_READING_MAX_FRACTION * len(cent):  # scaled up about the origin, a small shape there
            said.append(f"its numbers taken in {unit} (x{mm:g}) would select {n} facets, so they are likely in "
                        f"{unit}: a {kind}'s numbers ({keys}) are mm, so give them in mm")
    return "".join(f". {x[0].upper()}{x[1:]}" for x in said)
