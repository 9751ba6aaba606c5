"""The one exception of the geometry stage."""

from __future__ import annotations

from pathlib import Path


class GeometryError(ValueError):
    """A geometry input was refused.

    The message always names the file (when there is one), what is wrong
    with it and what to do about it.
    """


def refuse(path: str | Path | None, problem: str, action: str) -> GeometryError:
    """Build a :class:`GeometryError` with a uniform ``file: problem. action`` message."""
    where = f"{path}: " if path is not None else ""
    return GeometryError(f"{where}{problem}. {action}")
