"""Length units of input geometries and the plausibility of a liver's size."""

from __future__ import annotations

import numpy as np

from liverforce.geometry.errors import refuse

#: Millimetres per unit.
UNIT_TO_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
#: Largest bounding-box extent (mm) a human liver plausibly has; used by
#: ``units="auto"`` to pick a unit and to refuse wrong units.
LIVER_EXTENT_MM = (100.0, 450.0)
#: mm per inch. ``units="auto"`` never picks inches (a SOFA liver, of arbitrary units about 6 across, would pass
#: as one); it names them when they too would make the liver liver-sized, and a file in inches states
#: ``units: 25.4``.
INCH_MM = 25.4


def parse_units(units, path=None) -> tuple[float | None, str]:
    """Turn ``units`` into ``(mm per file unit, label)``; ``(None, "auto")`` for auto.

    Parameters
    ----------
    units : {"mm", "cm", "m", "auto"} or float
        A unit name, ``"auto"`` or a positive number of mm per file unit
        (e.g. ``40`` for the SOFA livers, whose units are arbitrary).
    """
    if isinstance(units, bool):
        raise refuse(path, f"invalid units {units!r}", "Use 'mm', 'cm', 'm', 'auto' or a positive number")
    if isinstance(units, (int, float, np.integer, np.floating)):
        if not np.isfinite(units) or units <= 0:
            raise refuse(path, f"invalid units scale {units!r}", "Give a positive number of mm per file unit")
        return float(units), f"x{float(units):g}"
    if isinstance(units, str):
        key = units.strip().lower()
        if key == "auto":
            return None, "auto"
        if key in UNIT_TO_MM:
            return UNIT_TO_MM[key], key
        try:
            return parse_units(float(key), path)
        except ValueError:
            pass
    raise refuse(path, f"invalid units {units!r}", "Use 'mm', 'cm', 'm', 'auto' or a positive number")


def guess_units(extent: float, path=None) -> tuple[float, str]:
    """Pick mm, cm or m so that the largest extent looks like a liver.

    Parameters
    ----------
    extent : float
        Largest bounding-box edge in file units.

    Raises
    ------
    GeometryError
        If no unit puts the extent in :data:`LIVER_EXTENT_MM`.
    """
    lo, hi = LIVER_EXTENT_MM
    for name, scale in UNIT_TO_MM.items():
        if lo <= extent * scale <= hi:
            return scale, name
    options = ", ".join(f"{extent * s:.3g} mm if {n}" for n, s in UNIT_TO_MM.items())
    fits = (f"; in inches it would be {extent * INCH_MM:.3g} mm: if the file is in inches, state units: "
            f"{INCH_MM:g}" if inches_fit(extent) else "")
    raise refuse(
        path,
        f"cannot guess the units: the largest extent is {extent:.4g} file units ({options}); "
        f"none is liver-sized ({lo:g}-{hi:g} mm){fits}",
        "State the units explicitly: 'mm', 'cm', 'm' or a number of mm per file unit "
        f"(e.g. units={INCH_MM:g} for inches, units=40 for the SOFA livers, about 6 units across)",
    )


def guessed_words(extent: float, scale: float, label: str) -> str:
    """What ``units="auto"`` chose (:func:`guess_units`), for the conversion's messages: the unit and the
    extent in mm, and, when inches would make the liver liver-sized too (a file 10-17.7 units across, taken as
    cm), that they would and what to state if so."""
    text = f"units guessed as '{label}' (largest extent {extent:.4g} file units -> {extent * scale:.4g} mm)"
    if inches_fit(extent):
        text += (f"; in inches it would be {extent * INCH_MM:.4g} mm across, liver-sized too: if the file is in "
                 f"inches, state units: {INCH_MM:g}")
    return text


def inches_fit(extent: float) -> bool:
    """Whether a largest extent of ``extent`` file units would be liver-sized in inches (the guess of
    :func:`guess_units` is then doubtful, and logged as a warning)."""
    lo, hi = LIVER_EXTENT_MM
    return bool(lo <= extent * INCH_MM <= hi)


def check_liver_size(extent_mm: float, scale: float, label: str, path=None, size_range_mm=LIVER_EXTENT_MM) -> None:
    """Refuse a surface whose largest extent (mm) is outside ``size_range_mm``."""
    if size_range_mm is None:
        return
    lo, hi = size_range_mm
    if not lo <= extent_mm <= hi:
        raise refuse(
            path,
            f"with units {label} (x{scale:g} to mm) the surface is {extent_mm:.4g} mm across "
            f"(largest extent), outside the {lo:g}-{hi:g} mm expected of a liver: the units are "
            "probably wrong",
            "Give the right units (geometry.imported[].units: 'mm', 'cm', 'm', 'auto' or a number of mm per file "
            f"unit; {_likely(extent_mm / scale, lo, hi)}). The workflow takes human-liver-sized surfaces only (its "
            "supports and checks assume one); from Python, load_surface(..., size_range_mm=None) reads a phantom "
            "of any size",
        )


def _likely(extent: float, lo: float, hi: float) -> str:
    """The units that would make ``extent`` (file units) liver-sized, as a phrase."""
    fits = [f"'{n}' gives {extent * s:.4g} mm" for n, s in UNIT_TO_MM.items() if lo <= extent * s <= hi]
    return fits[0] if fits else f"none of mm, cm, m makes {extent:.4g} file units {lo:g}-{hi:g} mm"
