"""Is a support's file of points read in the wrong frame (RAS read as LPS, or the reverse)?

Reading a point file in the other of RAS and LPS turns its points by 180 deg about the superior axis
(``x, y -> -x, -y`` in the coordinates they are read in). Far from the surface they are refused already
(:data:`~liverforce.mesh.supports.MAX_SNAP_MM`); on a liver roughly symmetric about that axis through the file's
origin they can still land within it, on the other side of the liver, and the support would hold the wrong
place without a word. Points marked on a segmentation's surface fit it within a fraction of a mm, so the file's
frame shows in how well its points fit the surface as read and mirrored (:func:`check_support_frame`).

The rule: the points look read in the wrong frame when, mirrored, all lie within the snap limit and their
mean distance to the surface is at most :data:`FRAME_FIT_RATIO` of the mean as read and at least
:data:`FRAME_FIT_MARGIN_MM` smaller. Measured on the procedural livers of seeds 0-5, an icosphere (r 60 mm) and
three ellipsoids (125 x 75 x 55 mm) centred 1-4 mm off the origin: 11 800 patches of 3-100 points drawn on the
surface within 5-40 mm of a place (10 000 of them where the place's mirror lands within 3 mm of the surface),
each read as drawn and mirrored:

* read in the right frame, never flagged: 0 of 2 971 exact, 0 of 4 448 moved up to 1 mm (uniform in a ball),
  0 of 2 934 with Gaussian noise of 0.25 or 0.5 mm per axis; with 1 mm per axis (1.7 mm RMS, more than a
  segmentation's surface gives) 1 of 1 447, five points;
* read in the wrong frame and still within 5 mm (5 757): flagged 2 684 of the 2 691 whose mean fits differ by
  1 mm or more, 3 526 of the 3 613 that differ by 0.5 mm or more (with noise up to 1 mm: 2 497 of 2 497 and
  3 293 of 3 296). The 1 759 that differ by less than 0.3 mm (the sphere, a liver symmetric there) cannot be
  told by the fit and are not flagged.

A second signal, the patch on the camera-facing visible area and its mirror not, is not used: a lab's support
may hold the liver's front (the falciform ligament, a clamp), and the visible area is tagged after the supports.

Not checked: vertex ids and a mesh file's groups of nodes (the geometry file's own vertices, read in its frame),
spheres and boxes (a centre or corner need not lie on the surface: no fit to compare).
"""

from __future__ import annotations

import logging

import numpy as np

from liverforce.mesh.supports import (MAX_SNAP_MM, PointFrame, PointReading, Support, SupportError, TriangleSet,
                                      _mirrored)

#: mirrored, the points' mean distance to the surface must be at most this fraction of the mean as read ...
FRAME_FIT_RATIO = 0.5
#: ... and at least this much smaller (mm), for the file to look read in the wrong frame
FRAME_FIT_MARGIN_MM = 0.5

_OTHER = {"RAS": "LPS", "LPS": "RAS"}

log = logging.getLogger(__name__)


def frame_fits(triangles: TriangleSet, xyz_mesh: np.ndarray, read_in: PointFrame) -> dict:
    """How the points ``xyz_mesh`` (mesh mm) fit the surface ``triangles`` as read and mirrored in x and y in
    the coordinates ``read_in`` maps to the mesh (``_mirrored``): ``{"as_given_mm": {"mean", "max"},
    "mirrored_mm": {"mean", "max"}, "likely_mix_up": bool}`` (the rule of the module's docstring): two
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


def check_support_frame(support: Support, what: str, triangles: TriangleSet, xyz_mesh: np.ndarray,
                        read_in: PointFrame, read_as: str, frame_name: str | None, markups: bool = False,
                        regions_check: str = "warn") -> dict | None:
    """The frame check of a support given by a file of points (:func:`frame_fits`), as recorded on its report
    (``frame_check``): the fits, ``read_in`` (the frame its coordinates were read in: ``frame_name``, RAS or LPS;
    ``a 4x4``; for a markups file of no one system, ``the markups file's own``), ``refused_under_strict`` (a likely
    mix-up), ``warning`` (None when the frame looks right or cannot be told) and ``advice`` (its last part, what
    to state or correct, for the report; None with it).

    ``what`` names the support and its file, ``read_as`` how its coordinates were read (units and frame);
    ``markups``: a 3D Slicer markups file (it states its own coordinate system, ``frame_name`` that one).
    ``regions_check`` (``mesh.regions_check``): ``warn`` logs the warning; ``strict`` refuses
    (:class:`~liverforce.mesh.supports.SupportError`); ``off`` checks nothing and returns None."""
    if regions_check == "off":
        return None
    fits = frame_fits(triangles, xyz_mesh, read_in)
    fix = _frame_fix(support, frame_name, markups) if fits["likely_mix_up"] else None
    msg = _words(what, fits, read_as, fix, len(np.atleast_2d(xyz_mesh)))
    read_in_name = frame_name or ("the markups file's own" if markups else "a 4x4")
    record = {"read_in": read_in_name, **fits, "refused_under_strict": fits["likely_mix_up"],
              "warning": msg, "advice": fix}
    if msg is None:
        return record
    if regions_check == "strict":
        raise SupportError(msg + "\n(mesh.regions_check=strict refuses a support whose points look read in the "
                                 "wrong frame; set it to warn to go on regardless)")
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


#: what mirroring a point file in x and y stands for, in the messages
_MIRROR_WORDS = ("a file in RAS read as LPS, or in LPS read as RAS: half a turn about the superior axis through the "
                 "file's origin")


def _frame_fix(support: Support, frame_name: str | None, markups: bool) -> str:
    """What to do when a support's file of points looks read in the other of RAS and LPS than ``frame_name`` (None:
    a 4x4): the setting to state where the lab gave the support, or the markups file to correct; or, if the file
    is right, the liver's frame to check."""
    other = _OTHER.get(frame_name or "")
    liver = ("the liver may be the one read in the wrong frame: check geometry.imported[].frame (and any warning "
             "of implausible regions)")
    # a 4x4 (other is None): the file in the other of RAS and LPS than the coordinates the 4x4 takes
    in_other = f"in {other}" if other else "in the other of RAS and LPS than the coordinates its 4x4 takes"
    if other:
        setting = _setting(support, other)
    else:
        setting = (_setting(support, "that 4x4 with its first two columns negated")
                   + " (or RAS or LPS, for a file in those world coordinates)")
    if markups:
        return (f"The markups file states coordinateSystem {frame_name or 'LPS or RAS'}: if its points are in "
                f"{other or 'the other'}, correct that in the file (export it again from 3D Slicer); if the file "
                f"is right, {liver}")
    if support.selector[1].get("frame") is not None:
        return f"If the file is {in_other}, state {setting}; if {frame_name or 'its 4x4'} is right, {liver}"
    return (f"The file states no frame, so its points are read in the geometry's: if the file is {in_other}, "
            f"state {setting} (changing geometry.imported[].frame would turn the liver and these points alike)")


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
    fr = reading.frame
    names = [None]  # None: mirrored; else the unit the numbers would be in
    stacked = [_mirrored(q, fr)]
    if not reading.markups:
        in_file = fr.to_file(q)  # the file's numbers times the mm per number they were read with
        for unit, mm in UNIT_TO_MM.items():
            if not np.isclose(mm, reading.scale_mm, rtol=1e-9):
                names.append(unit)
                stacked.append(fr.to_mesh(in_file * (mm / reading.scale_mm)))
    dist = triangles.closest(np.concatenate(stacked))[1].reshape(len(stacked), len(q))
    said, n = [], len(q)
    for unit, d in zip(names, dist):
        if float(d.max()) > max_mm:
            continue
        fit = (f"all {n} points would lie within {max_mm:g} mm of the surface ({d.mean():.3g} mm on average, "
               f"max {d.max():.3g} mm)")
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
    """The setting that states a support file's ``frame`` (or ``units``), where the lab gave the support."""
    if support.key:
        return f"{support.key}.file.{key}: {value}"
    return f"{key}: {value} in the file selector of the support '{support.name}'"
