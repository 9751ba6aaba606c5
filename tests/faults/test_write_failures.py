"""The disk filling up or a write failing mid-shard: no partial file is ever taken as complete.

Faults injected for real:

- the file handle raises ``ENOSPC`` after a byte budget, in the middle of the
  Parquet bytes (first shard write, and a rewrite over an older complete shard);
- ``fsync`` fails (the kernel reports the lost write late);
- the final rename fails;
- a real full disk: a 16 KiB tmpfs mounted inside the test (root only).

After each: no file under the shard's name (or the older complete one, byte for
byte), no temporary file left, the manifest cannot be written over the missing
shard (and an older manifest is untouched), and a rerun without the fault
writes the same payload as a clean write.
"""
from __future__ import annotations

import errno
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from liverforce.dataset import io as dio

from fake_rows import fake_row


def make_rows(n: int, seed: int = 0, k: int = 8) -> list[dict]:
    rng = np.random.default_rng(seed)
    return [fake_row(i, rng, k=k) for i in range(n)]


class FullDisk:
    """A binary file object that raises ENOSPC once ``budget`` bytes have been written."""

    def __init__(self, fh, budget: int):
        self._fh, self.budget, self.written = fh, budget, 0

    def write(self, data) -> int:
        if self.written + len(data) > self.budget:
            part = self.budget - self.written
            if part > 0:
                self._fh.write(bytes(data[:part]))
                self.written += part
            raise OSError(errno.ENOSPC, "No space left on device")
        self.written += len(data)
        return self._fh.write(data)

    def __getattr__(self, name):
        return getattr(self._fh, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self._fh.close()
        return False


def leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


def check_rerun(folder: Path, rows: list[dict], reference: dict) -> None:
    """Without the fault: the shard is written, listed, verified, and has the clean payload."""
    entry = dio.write_shard(rows, folder / "shard-0000.parquet")
    assert entry["payload_sha256"] == reference["payload_sha256"]
    dio.write_manifest([folder / "shard-0000.parquet"], folder / "manifest.json")
    assert [p.name for p in dio.verify_manifest(folder / "manifest.json")] == ["shard-0000.parquet"]
    assert pq.read_table(folder / "shard-0000.parquet").num_rows == len(rows)
    assert leftovers(folder) == []


@pytest.fixture
def rows():
    return make_rows(20)


@pytest.fixture
def clean(tmp_path, rows) -> dict:
    d = tmp_path / "clean"
    return dio.write_shard(rows, d / "shard-0000.parquet")


@pytest.mark.parametrize("budget", [0, 4, 2000])
def test_disk_full_mid_shard_leaves_no_shard(tmp_path, rows, clean, monkeypatch, budget, fault_ledger):
    folder = tmp_path / "shards"
    folder.mkdir()
    real_open = open

    def full_open(path, mode="r", *a, **kw):
        fh = real_open(path, mode, *a, **kw)
        return FullDisk(fh, budget) if "w" in mode and Path(path).name.startswith(".shard-") else fh

    monkeypatch.setattr(dio, "open", full_open, raising=False)
    with fault_ledger.check(f"ENOSPC after {budget} bytes of a shard", rows_expected=len(rows)) as seen:
        with pytest.raises(OSError) as err:
            dio.write_shard(rows, folder / "shard-0000.parquet")
        assert err.value.errno == errno.ENOSPC
        assert list(folder.iterdir()) == []  # neither the shard nor its temporary file
        with pytest.raises((FileNotFoundError, dio.ShardError), match="shard-0000"):  # cannot list what is not there
            dio.write_manifest([folder / "shard-0000.parquet"], folder / "manifest.json")
        assert not (folder / "manifest.json").exists()
        monkeypatch.undo()
        check_rerun(folder, rows, clean)
        seen.rows_found = pq.read_table(folder / "shard-0000.parquet").num_rows


def test_failed_rewrite_keeps_the_older_complete_shard_and_manifest(tmp_path, rows, clean, monkeypatch, fault_ledger):
    folder = tmp_path / "shards"
    old_rows = make_rows(20, seed=7)
    dio.write_shard(old_rows, folder / "shard-0000.parquet")
    dio.write_manifest([folder / "shard-0000.parquet"], folder / "manifest.json")
    old_bytes = (folder / "shard-0000.parquet").read_bytes()
    old_manifest = (folder / "manifest.json").read_bytes()
    real_open = open

    def full_open(path, mode="r", *a, **kw):  # room for 3000 bytes of a shard, 50 of a manifest
        fh = real_open(path, mode, *a, **kw)
        return FullDisk(fh, 3000 if ".shard-" in str(path) else 50) if "w" in mode else fh

    monkeypatch.setattr(dio, "open", full_open, raising=False)
    with fault_ledger.check("ENOSPC while rewriting a shard and its manifest", rows_expected=len(rows)) as seen:
        with pytest.raises(OSError):
            dio.write_shard(rows, folder / "shard-0000.parquet")
        with pytest.raises(OSError):  # the manifest rewrite fails too: the old one stays whole
            dio.write_manifest([folder / "shard-0000.parquet"], folder / "manifest.json")
        assert (folder / "shard-0000.parquet").read_bytes() == old_bytes
        assert (folder / "manifest.json").read_bytes() == old_manifest
        assert leftovers(folder) == []
        dio.verify_manifest(folder / "manifest.json")  # still consistent: old shard, old manifest
        monkeypatch.undo()
        check_rerun(folder, rows, clean)
        seen.rows_found = pq.read_table(folder / "shard-0000.parquet").num_rows


@pytest.mark.parametrize("step", ["fsync", "replace"])
def test_late_write_errors_leave_no_shard(tmp_path, rows, clean, monkeypatch, step, fault_ledger):
    folder = tmp_path / "shards"
    folder.mkdir()

    def boom(*a, **kw):
        raise OSError(errno.ENOSPC if step == "fsync" else errno.EIO, f"{step} failed")

    monkeypatch.setattr(dio.os, step, boom)
    with fault_ledger.check(f"{step} failing after a shard's bytes were written", rows_expected=len(rows)) as seen:
        with pytest.raises(OSError):
            dio.write_shard(rows, folder / "shard-0000.parquet")
        monkeypatch.undo()
        assert list(folder.iterdir()) == []
        check_rerun(folder, rows, clean)
        seen.rows_found = pq.read_table(folder / "shard-0000.parquet").num_rows


def test_real_full_tmpfs(tmp_path, fault_ledger):
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("mounting a tmpfs needs root (the ENOSPC tests above inject the same fault without it)")
    mnt = tmp_path / "tiny"
    mnt.mkdir()
    rows = make_rows(20, k=200)  # ~100 KB of point clouds: cannot fit 16 KiB
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=16k", "tmpfs", str(mnt)], capture_output=True, text=True)
    if proc.returncode != 0:
        pytest.skip(f"mount -t tmpfs refused here: {proc.stderr.strip()}")
    try:
        folder = mnt / "shards"
        with fault_ledger.check("real full disk (16 KiB tmpfs)", rows_expected=len(rows)) as seen:
            with pytest.raises(OSError) as err:
                dio.write_shard(rows, folder / "shard-0000.parquet")
            assert err.value.errno == errno.ENOSPC
            assert list(folder.iterdir()) == []  # the partial temporary file was removed
            assert not (folder / "manifest.json").exists()
            # more room, then the rerun completes
            subprocess.run(["mount", "-o", "remount,size=4m", str(mnt)], check=True)
            clean = dio.write_shard(rows, tmp_path / "clean" / "shard-0000.parquet")
            check_rerun(folder, rows, clean)
            seen.rows_found = pq.read_table(folder / "shard-0000.parquet").num_rows
    finally:
        subprocess.run(["umount", str(mnt)], check=False)
