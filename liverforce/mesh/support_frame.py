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

from liverforce.mesh.supports import MAX_SNAP_MM, PointFrame, Support, SupportError, TriangleSet, _mirrored

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
    mix-up) and ``warning`` (None when the frame looks right or cannot be told).

    ``what`` names the support and its file, ``read_as`` how its coordinates were read (units and frame);
    ``markups``: a 3D Slicer markups file (it states its own coordinate system, ``frame_name`` that one).
    ``regions_check`` (``mesh.regions_check``): ``warn`` logs the warning; ``strict`` refuses
    (:class:`~liverforce.mesh.supports.SupportError`); ``off`` checks nothing and returns None."""
    if regions_check == "off":
        return None
    fits = frame_fits(triangles, xyz_mesh, read_in)
    msg = _words(support, what, fits, read_as, frame_name, markups, len(np.atleast_2d(xyz_mesh)))
    read_in_name = frame_name or ("the markups file's own" if markups else "a 4x4")
    record = {"read_in": read_in_name, **fits, "refused_under_strict": fits["likely_mix_up"],
              "warning": msg}
    if msg is None:
        return record
    if regions_check == "strict":
        raise SupportError(msg + "\n(mesh.regions_check=strict refuses a support whose points look read in the "
                                 "wrong frame; set it to warn to go on regardless)")
    log.warning("%s", msg)
    return record


def _words(support: Support, what: str, fits: dict, read_as: str, frame_name: str | None, markups: bool,
           n: int) -> str | None:
    """The warning of a support whose points fit the surface better mirrored, naming both fits and the fix."""
    if not fits["likely_mix_up"]:
        return None
    g, m = fits["as_given_mm"], fits["mirrored_mm"]
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
        fix = (f"The markups file states coordinateSystem {frame_name or 'LPS or RAS'}: if its points are in "
               f"{other or 'the other'}, correct that in the file (export it again from 3D Slicer); if the file "
               f"is right, {liver}")
    elif support.selector[1].get("frame") is not None:
        fix = f"If the file is {in_other}, state {setting}; if {frame_name or 'its 4x4'} is right, {liver}"
    else:
        fix = (f"The file states no frame, so its points are read in the geometry's: if the file is {in_other}, "
               f"state {setting} (changing geometry.imported[].frame would turn the liver and these points alike)")
    return (f"{what} looks read in the wrong frame: its {n} points, read {read_as}, lie {g['mean']:.3g} mm from "
            f"the surface on average (max {g['max']:.3g} mm); mirrored in x and y (a file in RAS read as LPS, or "
            "in LPS read as RAS: half a turn about the superior axis through the file's origin) they would lie "
            f"{m['mean']:.3g} mm (max {m['max']:.3g} mm) from it. Points marked on the liver's surface fit it within "
            f"a fraction of a mm, so the support is likely put on the wrong side of the liver. {fix}. (Flagged "
            f"when, mirrored, the points fit at most {FRAME_FIT_RATIO:g} times as far and {FRAME_FIT_MARGIN_MM:g} "
            "mm closer on average.)")


def _setting(support: Support, value: str) -> str:
    """The setting that states a support file's frame, where the lab gave the support."""
    if support.key:
        return f"{support.key}.file.frame: {value}"
    return f"frame: {value} in the file selector of the support '{support.name}'"
