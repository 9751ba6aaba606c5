"""liverforce.atomic: all-or-nothing writes with ordinary file permissions."""
import json
import os

import pytest

from liverforce.atomic import atomic_path, write_json_atomic, write_text_atomic


def test_written_whole_with_the_permissions_open_would_give(tmp_path):
    mask = os.umask(0o022)
    try:
        p = write_json_atomic(tmp_path / "sub" / "a.json", {"b": [1, 2], "a": float("nan")})
    finally:
        os.umask(mask)
    assert json.loads(p.read_text().replace("NaN", "null")) == {"a": None, "b": [1, 2]}
    assert p.stat().st_mode & 0o777 == 0o644  # readable by the group and others, as a report must be
    assert sorted(x.name for x in p.parent.iterdir()) == ["a.json"]


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    p = write_text_atomic(tmp_path / "r.html", "old")
    with pytest.raises(RuntimeError):
        with atomic_path(p) as tmp:
            tmp.write_text("half of the new")
            raise RuntimeError("killed mid-write")
    assert p.read_text() == "old" and [x.name for x in tmp_path.iterdir()] == ["r.html"]
    with atomic_path(tmp_path / "fig.png") as tmp:  # the suffix is kept for writers that infer the format
        assert tmp.suffix == ".png" and tmp.name.startswith(".fig.")
        tmp.write_bytes(b"png")
    assert (tmp_path / "fig.png").read_bytes() == b"png"
