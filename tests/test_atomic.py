"""liverforce.atomic: all-or-nothing writes with ordinary file permissions."""
import json
import os

import pytest

from liverforce.atomic import atomic_path, remove_stale_temps, write_json_atomic, write_text_atomic


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


_DEAD: list = []  # the killed writers' blocks, kept from garbage collection (which would run their clean-up)


def _killed_writer(path):
    """The temporary file a writer of ``path`` killed mid-write leaves (atomic_path's own name for it)."""
    cm = atomic_path(path)
    tmp = cm.__enter__()  # never exits: as if the process died inside the block
    tmp.write_bytes(b"half")
    _DEAD.append(cm)
    return tmp


def test_an_owner_removes_what_killed_writers_of_its_file_left_and_nothing_else(tmp_path):
    shard = tmp_path / "shard-0003.parquet"
    strays = [_killed_writer(shard), _killed_writer(shard)]
    others = [_killed_writer(tmp_path / "shard-0003.x.parquet"),  # a stem that starts alike
              _killed_writer(tmp_path / "shard-0004.parquet"), _killed_writer(tmp_path / "shard-0003.json")]
    keep = [write_text_atomic(tmp_path / "shard-0003.parquet.txt", "x"), write_text_atomic(shard, "done")]
    (tmp_path / ".shard-0003.notmine.tmp.parquet").write_text("another tool's")  # not atomic_path's name
    assert sorted(remove_stale_temps(shard)) == sorted(strays)
    assert not any(p.exists() for p in strays)
    assert all(p.exists() for p in others + keep) and shard.read_text() == "done"
    assert (tmp_path / ".shard-0003.notmine.tmp.parquet").exists()
    assert remove_stale_temps(tmp_path / "missing" / "a.json") == []  # no folder: nothing to do


def test_a_job_clears_its_outputs_strays_at_set_up(tmp_path, monkeypatch):
    import logging
    import sys

    from liverforce.pipeline import job

    monkeypatch.setattr(job, "limit_threads", lambda n: None)  # this process's thread pools stay as they are
    monkeypatch.setattr(sys, "excepthook", sys.excepthook)  # restored after the test
    logger = logging.getLogger("liverforce")
    monkeypatch.setattr(logger, "level", logger.level)
    out = tmp_path / "shards" / "I" / "shard-0000.parquet"
    stray = _killed_writer(out)
    neighbour = _killed_writer(out.with_name("shard-0001.parquet"))  # another job's: left alone
    log = tmp_path / "job.log"
    before = list(logger.handlers)
    try:
        job.setup_job(log, 1, outputs=[str(out)])
    finally:
        for h in logger.handlers:
            h.close()
        logger.handlers[:] = before
    assert not stray.exists() and neighbour.exists()
    assert f"removed {stray}, left by a killed earlier run of this job" in log.read_text()
