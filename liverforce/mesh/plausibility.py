"""Is the auto-tagged anatomy plausible for the frame the liver was given in?

:func:`~liverforce.mesh.regions.tag_regions` places the supports from the
anatomical directions of the stated frame (RAS unless ``RegionParams`` says
otherwise).  A liver whose file frame was stated wrongly (e.g. an LPS export
from 3D Slicer imported as RAS) is still tagged, only in the wrong places.
These checks measure the result against anatomy; each gives a value, its
threshold and a pass/fail:

=====================  ==================================================  ==========
check                  value                                               passes if
=====================  ==================================================  ==========
``right_lobe``         position of the liver's volume centroid along        > 0.5
                       the right axis, as a fraction of the left→right
                       extent (the right lobe holds most of the volume:
                       procedural livers 0.58–0.62; mirrored 0.38–0.42)
``ivc_posterior``      IVC patch centroid minus liver centroid along the    < 0 mm
                       anterior axis (mm)
``visible_anterior``   area-weighted mean unit normal of the visible       > 0
                       region · (anterior + superior)/√2
``<region>_area``      area of each region (ivc, ligament, visceral, rib)   ≥ 0.5 %
                       and of the visible region, % of the boundary area
=====================  ==================================================  ==========

``right_lobe`` is the check that catches a left–right mirror or a 180°
rotation about the superior axis (LPS read as RAS): the tagging rules follow
the stated frame, so the IVC and visible checks pass by construction in that
case and catch instead a tagging that went wrong on an unusual shape (and
axis swaps that leave the IVC off the posterior face).  The checks do not
prove a frame right; they flag the common mistakes.

Under ``mode: add`` the lab's supports lie over the built-in regions: those
checks then run on the regions as auto-tagged, beneath the lab's supports, and
are skipped on the final ones (listed with the reason).

A lab's own supports (``geometry.imported[...].supports`` with ``mode:
replace``) take the place of the built-in IVC, ligament, visceral and rib
regions, so the checks that measure those (:data:`BUILT_IN_SUPPORT_CHECKS`)
are skipped for it (:func:`skipped_checks`), and the report lists them under
``skipped`` with the reason.  ``right_lobe`` depends on the geometry and the
stated frame only, and the visible region is tagged from the frame on the free
surface whatever the supports: those still run (and refuse under ``strict``).
``visible_area`` is skipped too when the lab also gives its own exertion
points (the visible region then serves no purpose).
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass

import numpy as np

from liverforce.mesh.regions import RegionParams
from liverforce.mesh.types import REGION_CODES

log = logging.getLogger(__name__)

MODES = ("warn", "strict", "off")

#: Checks that measure the built-in (auto-tagged) supports: meaningless when a lab's own supports replace them
BUILT_IN_SUPPORT_CHECKS = ("ivc_posterior", "ivc_area", "ligament_area", "visceral_area", "rib_area")


class ImplausibleRegionsError(ValueError):
    """Tagged regions fail an anatomical plausibility check under ``mesh.regions_check: strict``."""


@dataclass(frozen=True)
class PlausibilityThresholds:
    """Thresholds of :func:`check_regions` (see the module table).

    Parameters
    ----------
    min_right_fraction : float
        The volume centroid must lie right of this fraction of the
        left→right extent (default 0.5, the middle).
    max_ivc_anterior_mm : float
        The IVC centroid must lie at most this far anterior of the liver
        centroid (default 0 mm: posterior of it).
    min_visible_facing : float
        Minimum of the visible region's mean normal · (A + S)/√2 (default 0).
    min_area_percent : float
        Minimum area of each region and of the visible region, % of the
        boundary area (default 0.5 %).
    """

    min_right_fraction: float = 0.5
    max_ivc_anterior_mm: float = 0.0
    min_visible_facing: float = 0.0
    min_area_percent: float = 0.5


def closed_surface_centroid(points: np.ndarray, facets: np.ndarray) -> np.ndarray:
    """Centroid (mm) of the solid enclosed by a closed, outward-oriented triangle surface.

    Notes
    -----
    Cone decomposition about a reference point ``o``: each triangle
    ``(a, b, c)`` spans a tetrahedron of signed volume ``(a−o)·((b−o)×(c−o))/6``
    and centroid ``(o + a + b + c)/4``; the solid's centroid is their
    volume-weighted mean (exact for the polyhedron).
    """
    o = points.mean(axis=0)
    a, b, c = (points[facets[:, i]] - o for i in range(3))
    vol = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0
    return o + (vol[:, None] * (a + b + c) / 4.0).sum(axis=0) / vol.sum()


def check_regions(points: np.ndarray, facets: np.ndarray, facet_region: np.ndarray, facet_visible: np.ndarray,
                  params: RegionParams | None = None,
                  thresholds: PlausibilityThresholds | None = None) -> list[dict]:
    """Measure the tagged regions against anatomy (see the module table).

    Parameters
    ----------
    points : numpy.ndarray
        ``(n, 3)`` coordinates, mm.
    facets : numpy.ndarray
        ``(k, 3)`` closed, outward-oriented boundary triangles.
    facet_region, facet_visible : numpy.ndarray
        ``(k,)`` region codes and visible mask (as
        :func:`~liverforce.mesh.regions.tag_regions` returns them).
    params : RegionParams, optional
        Gives the anatomical directions (default RAS).
    thresholds : PlausibilityThresholds, optional

    Returns
    -------
    list of dict
        One per check: ``check``, ``value``, ``threshold``, ``unit``,
        ``passed`` and ``what`` (a phrase saying what was measured).
    """
    p = params or RegionParams()
    t = thresholds or PlausibilityThresholds()
    points = np.asarray(points, dtype=np.float64)
    facets = np.asarray(facets, dtype=np.int64)
    region = np.asarray(facet_region)
    visible = np.asarray(facet_visible, dtype=bool)
    right, anterior, superior = p.frame()
    tri = points[facets]
    raw = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = 2 × area
    area = 0.5 * np.linalg.norm(raw, axis=1)
    total = float(area.sum())
    centre = tri.mean(axis=1)
    centroid = closed_surface_centroid(points, facets)
    out = []

    along = points @ right
    frac = float((centroid @ right - along.min()) / max(np.ptp(along), 1e-12))
    out.append({"check": "right_lobe", "value": frac, "threshold": t.min_right_fraction, "unit": "",
                "passed": frac > t.min_right_fraction,
                "what": "volume centroid along the left->right extent (expected right of the middle: "
                        "the right lobe is the larger)"})

    ivc = region == REGION_CODES["ivc"]
    if ivc.any():
        c_ivc = (area[ivc, None] * centre[ivc]).sum(axis=0) / area[ivc].sum()
        d = float((c_ivc - centroid) @ anterior)
        out.append({"check": "ivc_posterior", "value": d, "threshold": t.max_ivc_anterior_mm, "unit": "mm",
                    "passed": d < t.max_ivc_anterior_mm,
                    "what": "IVC patch centroid minus liver centroid along anterior (expected negative: posterior)"})

    if visible.any():
        n_mean = (raw[visible] / 2.0).sum(axis=0) / area[visible].sum()
        facing = float(n_mean @ (anterior + superior) / np.sqrt(2.0))
        out.append({"check": "visible_anterior", "value": facing, "threshold": t.min_visible_facing, "unit": "",
                    "passed": facing > t.min_visible_facing,
                    "what": "visible region's mean normal . (anterior + superior)/sqrt(2) "
                            "(expected positive: facing anterior-superior)"})

    masks = {name: region == code for name, code in REGION_CODES.items() if code}
    masks["visible"] = visible
    for name, mask in masks.items():
        pct = 100.0 * float(area[mask].sum()) / total
        out.append({"check": f"{name}_area", "value": pct, "threshold": t.min_area_percent, "unit": "%",
                    "passed": pct >= t.min_area_percent,
                    "what": f"{name} region area, % of the boundary (expected >= {t.min_area_percent:g} %, "
                            "empty or tiny otherwise)"})
    return out


def skipped_checks(supports_mode: str | None, exertion_given: bool = False) -> dict[str, str]:
    """The checks that do not apply to an imported liver's own scene, each with the reason.

    Parameters
    ----------
    supports_mode : {"replace", "add"} or None
        The mode of the lab's own supports (``geometry.imported[...].supports``),
        ``None`` when it gives none. Under ``replace`` the checks of
        :data:`BUILT_IN_SUPPORT_CHECKS` are skipped; ``right_lobe`` (the frame)
        and the visible region's checks are kept. Under ``add`` those checks are
        skipped on the final regions (the lab's supports lie over the built-in
        ones: a lab's clamp on the anterior face is no IVC in the wrong place)
        and run instead on the auto-tagged regions beneath
        (:func:`built_in_only`; the mesh stage records them under
        ``regions_check.built_in``).
    exertion_given : bool
        The lab gives its own exertion points: with ``replace`` supports,
        ``visible_area`` is skipped too (no candidate is sampled there).
    """
    if supports_mode == "add":
        why = ("the lab's own supports (geometry.imported[...].supports, mode: add) lie over the built-in regions "
               "this check measures: it ran on the regions as auto-tagged, before them (regions_check.built_in)")
        return {name: why for name in BUILT_IN_SUPPORT_CHECKS}
    if supports_mode != "replace":
        return {}
    why = ("the lab's own supports (geometry.imported[...].supports, mode: replace) replace the built-in "
           "regions this check measures")
    skip = {name: why for name in BUILT_IN_SUPPORT_CHECKS}
    if exertion_given:
        skip["visible_area"] = ("the lab gives its own exertion points (geometry.imported[...].exertion_points) "
                                "and supports: the visible region is not sampled")
    return skip


def built_in_only(reason: str = "checked on the final regions (regions_check.checks)") -> dict[str, str]:
    """A ``skip`` that leaves only :data:`BUILT_IN_SUPPORT_CHECKS` to run (the other checks run elsewhere)."""
    return {name: reason for name in ("right_lobe", "visible_anterior", "visible_area")}


def regions_check(points, facets, facet_region, facet_visible, *, mode: str = "warn",
                  params: RegionParams | None = None, thresholds: PlausibilityThresholds | None = None,
                  frame: str | None = None, where: str = "", skip: dict[str, str] | None = None) -> dict:
    """Run :func:`check_regions`, log a warning per failed check, refuse under ``strict``.

    Parameters
    ----------
    mode : {"warn", "strict", "off"}
        ``warn``: failures are logged (WARNING) and returned; ``strict``:
        the first report with failures raises; ``off``: nothing is checked.
    frame : str, optional
        The frame the liver was given in (``"RAS"``, ``"LPS"``, ``"matrix"``),
        to word the advice.
    where : str
        Names the liver (geometry id or file) in the messages.
    skip : dict, optional
        Check name -> why it does not apply (:func:`skipped_checks`): such
        checks are left out of ``checks`` and of the verdict, and listed under
        ``skipped``; the others run in ``mode``.

    Returns
    -------
    dict
        JSON-serialisable: ``mode``, ``passed`` (bool or ``None`` when off),
        ``checks`` (as :func:`check_regions`), ``warnings`` (messages),
        ``thresholds``, ``frame``, ``skipped`` (``[{check, why}]``).

    Raises
    ------
    ImplausibleRegionsError
        Under ``strict`` when any check fails; the message names each failed
        check, its value and threshold, and what to do.
    """
    if mode not in MODES:
        raise ValueError(f"regions_check mode must be one of {MODES}, got {mode!r}")
    t = thresholds or PlausibilityThresholds()
    frame = _frame_label(frame)
    skip = dict(skip or {})
    report = {"mode": mode, "passed": None, "checks": [], "warnings": [], "thresholds": asdict(t), "frame": frame,
              "skipped": []}
    if mode == "off":
        return report
    checks = check_regions(points, facets, facet_region, facet_visible, params, t)
    report["skipped"] = [{"check": c["check"], "why": skip[c["check"]]} for c in checks if c["check"] in skip]
    checks = [c for c in checks if c["check"] not in skip]
    if report["skipped"]:
        log.info("%sregions checks skipped: %s", where + ": " if where else "",
                 "; ".join(f"{c['check']} ({c['why']})" for c in report["skipped"]))
    failed = [c for c in checks if not c["passed"]]
    report.update(checks=checks, passed=not failed)
    if not failed:
        return report
    advice = _advice(frame, failed)
    for c in failed:
        report["warnings"].append(
            f"{where + ': ' if where else ''}implausible regions for the stated frame ({frame}): "
            f"{c['check']} = {c['value']:.3g}{(' ' + c['unit']) if c['unit'] else ''} "
            f"(threshold {c['threshold']:g}; {c['what']}). {advice}")
    if mode == "strict":
        raise ImplausibleRegionsError(
            "\n".join(report["warnings"]) + "\n(mesh.regions_check=strict; set it to warn to go on regardless)")
    for w in report["warnings"]:
        log.warning("%s", w)
    return report


def _frame_label(frame) -> str:
    """``RAS`` (also for None and procedural livers' "RAS: +x patient right, ..."), ``LPS`` or ``matrix``."""
    text = "RAS" if frame is None else str(frame).strip()
    return "RAS" if text.upper().startswith("RAS") else ("LPS" if text.upper() == "LPS" else text)


def _advice(frame: str, failed: list[dict]) -> str:
    names = {c["check"] for c in failed}
    if names & {"right_lobe", "ivc_posterior", "visible_anterior"}:
        if frame == "RAS":
            tip = ("The liver may be mirrored or rotated: if the file comes from 3D Slicer or DICOM it is "
                   "probably LPS, state frame: LPS for it (geometry.imported[...].frame), or give the 4x4 "
                   "transform from its frame to RAS")
        elif frame == "LPS":
            tip = ("The file may not be LPS: try frame: RAS, or give the 4x4 transform from its frame to RAS "
                   "(geometry.imported[...].frame)")
        else:
            tip = "Check the 4x4 transform in geometry.imported[...].frame: it should map the file to RAS"
    else:
        tip = ("A region is empty or tiny: check the frame (geometry.imported[...].frame) and the region "
               "parameters (mesh.regions, liverforce.mesh.regions.RegionParams)")
    return tip
