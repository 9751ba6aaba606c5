"""The one reader of text point files (``.csv``, ``.txt``, ``.xyz``), for every stage.

``liverforce predict`` reads its point clouds with it (:func:`liverforce.serve.files.read_points`) and the
geometry and mesh stages their exertion-point and support files (:func:`liverforce.mesh.supports.read_point_file`):
``geometry`` is the lowest layer both may import, so the rules live here once.

The rules:

- one row per line, its values separated by commas, semicolons, tabs or spaces (any run of them);
- blank lines and lines starting with ``#`` are skipped;
- one optional header line: a first line that is not all numbers. A first line of three values of which two or
  more are numbers is refused as garbled instead (``1,2,abc``: a point with a typo, which taken as a header would
  be dropped without a word);
- every row as wide as the first, all numbers (``nan`` and ``inf`` are numbers here: the callers judge them);
- an empty file (no rows, or a header alone) is refused.

A refused file raises :class:`PointTableError` naming the file and, when a line is at fault, its number (from 1)
and its text.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

#: suffixes of text point files (compared in lower case)
TEXT_SUFFIXES = (".csv", ".txt", ".xyz")
_SEPARATORS = re.compile(r"[,;\t ]+")


class PointTableError(ValueError):
    """A text point file was refused: ``path``, ``line`` (from 1, or None for the whole file) and ``problem``.

    The message is ``"<path>, line <n>: <problem>"`` (or ``"<path>: <problem>"``); callers add what they expected.
    """

    def __init__(self, path, problem: str, line: int | None = None):
        self.path, self.problem, self.line = Path(path), problem, line
        where = f"{path}, line {line}" if line is not None else f"{path}"
        super().__init__(f"{where}: {problem}")


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _quote(text: str) -> str:
    return f"'{text[:80]}'"


#: a header column's unit: ``x_mm``, ``x mm``, ``x(m)``, ``X [mm]``, ``r_um``
_UNIT_SUFFIX = re.compile(r"(?:^|[_\s(\[])(mm|cm|m|um|µm)[)\]]?$", re.IGNORECASE)
#: mm per unit a header may name
HEADER_UNIT_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "um": 1e-3, "µm": 1e-3}


def header_units(path) -> tuple[str, str] | None:
    """The unit a text point file's header names for every one of its columns (``x_mm,y_mm,z_mm``,
    ``X [m], Y [m], Z [m]``): ``(unit, the header line)``; None when the file has no header, a column names no
    unit, or the columns name different ones. An unreadable file: None (:func:`read_table` refuses it)."""
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError):
        return None
    first = next((ln.strip() for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")), None)
    if first is None:
        return None
    tokens = [t for t in re.split(r"\s*[,;\t]\s*", first) if t] if re.search(r"[,;\t]", first) \
        else _SEPARATORS.split(first)
    if not tokens or all(_is_number(t) for t in tokens):
        return None
    units = {m.group(1).lower() if m else None for m in (_UNIT_SUFFIX.search(t.strip()) for t in tokens)}
    if len(units) != 1 or None in units:
        return None
    return units.pop(), first


def header_unit_clash(path, scale_mm: float, read_in: str) -> tuple[str, str] | None:
    """``(the unit the header names, the words)`` when a text point file's header names a unit for every column
    (:func:`header_units`) other than the one its coordinates are read in: ``scale_mm`` mm per unit, ``read_in``
    those units in words (``"m"``); None when the header agrees or names no unit.

    The words, ``"<path>: its header '<line>' says the coordinates are in <unit>, but they are read in <read_in>
    (<scale_mm> mm each)"``, are every stage's (the mesh stage's point files, ``liverforce predict``'s clouds and
    tool tips); the caller adds what to declare there.
    """
    said = header_units(path)
    if said is None or np.isclose(HEADER_UNIT_MM[said[0]], scale_mm, rtol=1e-9):
        return None
    return said[0], (f"{path}: its header {said[1]!r} says the coordinates are in {said[0]}, but they are read in "
                     f"{read_in} ({scale_mm:g} mm each)")


def read_table(path, columns: tuple[int, ...] | None = None) -> tuple[np.ndarray, list[int]]:
    """``(rows (k, c) float, line numbers (k,) from 1)`` of a text point file (module docstring); ``k >= 1``.

    ``columns``: the row widths accepted (e.g. ``(3,)``); a first row of another width is refused naming its
    line. Raises :class:`PointTableError`.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise PointTableError(path, f"cannot read the file as text ({exc})") from None
    numbered = [(i, ln.strip()) for i, ln in enumerate(text.splitlines(), 1)
                if ln.strip() and not ln.lstrip().startswith("#")]
    if not numbered:
        raise PointTableError(path, "the file is empty (no points)")
    rows = [_SEPARATORS.split(ln) for _, ln in numbered]
    numbers = [sum(_is_number(x) for x in r) for r in rows]
    if numbers[0] < len(rows[0]):  # one header line
        if len(rows[0]) == 3 and numbers[0] >= 2:
            raise PointTableError(path, f"{_quote(numbered[0][1])} is neither a header nor a row of numbers "
                                        "(a value that is not a number?)", numbered[0][0])
        numbered, rows, numbers = numbered[1:], rows[1:], numbers[1:]
        if not rows:
            raise PointTableError(path, "the file is empty (a header line, no points)")
    width = len(rows[0])
    allowed = columns is None or width in columns
    for (i, ln), r, n in zip(numbered, rows, numbers):
        if len(r) != width or n < len(r) or not allowed:
            what = f"{len(r)} value{'s' * (len(r) != 1)}" + ("" if n == len(r) else ", not all numbers")
            if len(r) != width and allowed:
                what += f", the rows above {width}"
            raise PointTableError(path, f"{_quote(ln)} ({what})", i)
    return np.asarray(rows, dtype=np.float64).reshape(len(rows), width), [i for i, _ in numbered]
