"""Atomic file writes: a temporary name beside the target, then a rename (the only implementation).

A reader never sees a half-written file under the final name: the content goes
to a dot-prefixed temporary file in the same folder (``.<stem>.<random>.tmp<suffix>``,
same file system, so the rename is atomic) and :func:`os.replace` puts it in
place only when writing finished without error; on any error the temporary file
is removed and the error raised. Standard library only, so every layer may use it.

Example
-------
>>> import tempfile, pathlib
>>> d = pathlib.Path(tempfile.mkdtemp())
>>> write_json_atomic(d / "a.json", {"b": 1})
PosixPath('.../a.json')  # doctest: +SKIP
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _temp_affixes(path: Path) -> tuple[str, str]:
    """The prefix and suffix of the temporary names :func:`atomic_path` makes for ``path`` (one place for both)."""
    return f".{path.stem}.", f".tmp{path.suffix}"


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path to write ``path`` through; renamed onto ``path`` if the block ends without error.

    The temporary name keeps the suffix, for writers that infer the format
    from it (matplotlib, meshio). The folder is created if needed.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    prefix, suffix = _temp_affixes(path)
    fd, name = tempfile.mkstemp(prefix=prefix, suffix=suffix, dir=path.parent)
    os.close(fd)
    tmp = Path(name)
    os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600: give the file the permissions open() would
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def remove_stale_temps(path: str | Path) -> list[Path]:
    """Delete the temporary files that killed writers of ``path`` left beside it; returns them.

    Only for ``path``'s owner, before it writes: a job that alone writes ``path`` (a Snakemake job
    and its outputs), since a live writer's temporary file would go too. Matches exactly the names
    :func:`atomic_path` makes for ``path`` (``.<stem>.<8 random>.tmp<suffix>``), not those of another
    file whose stem starts alike (``a.json`` leaves ``a.b.json``'s alone).
    """
    path = Path(path)
    prefix, suffix = _temp_affixes(path)  # between them mkstemp's 8 random characters
    pattern = re.compile(rf"{re.escape(prefix)}[a-z0-9_]{{8}}{re.escape(suffix)}")
    if not path.parent.is_dir():
        return []
    gone = []
    for p in path.parent.iterdir():
        if pattern.fullmatch(p.name) and p.is_file():
            p.unlink(missing_ok=True)
            gone.append(p)
    return gone


def write_bytes_atomic(path: str | Path, data: bytes, *, fsync: bool = False) -> Path:
    """Write ``data`` to ``path`` atomically; ``fsync`` flushes it to the disk before the rename."""
    path = Path(path)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(data)
            if fsync:
                fh.flush()
                os.fsync(fh.fileno())
    return path


def write_text_atomic(path: str | Path, text: str, *, fsync: bool = False) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    return write_bytes_atomic(path, text.encode("utf-8"), fsync=fsync)


def write_json_atomic(path: str | Path, obj: Any, *, fsync: bool = False, indent: int = 2) -> Path:
    """Write ``obj`` as key-sorted JSON to ``path`` atomically (NaN allowed, as Python's json writes it)."""
    return write_text_atomic(path, json.dumps(obj, indent=indent, sort_keys=True, allow_nan=True) + "\n",
                             fsync=fsync)


def file_sha256(path: str | Path) -> str:
    """Hex SHA-256 of a file's bytes: the shard manifests' and the import records' check that a file is the one
    written or read (one helper for both)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()
