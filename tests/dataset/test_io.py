"""Shard I/O: schema round trip, atomic writes, manifest hashes, corruption detection."""
from __future__ import annotations

import json

import numpy as np
import pyarrow.parquet as pq
import pytest

from liverforce.dataset import io as dio
from liverforce.dataset.schema import SCHEMA_VERSION, SHARD_SCHEMA

from fake_rows import fake_row


@pytest.fixture
def rows():
    rng = np.random.default_rng(0)
    return [fake_row(i, rng, converged=(i != 2)) for i in range(4)]


def test_round_trip_keeps_schema_values_and_metadata(tmp_path, rows):
    p = tmp_path / "shard-0000.parquet"
    entry = dio.write_shard(rows, p)
    assert entry["rows"] == 4 and entry["failed"] == 1
    t = dio.read_table(p)
    assert t.schema.remove_metadata().equals(SHARD_SCHEMA)
    assert dio.read_metadata(p)["schema_version"] == SCHEMA_VERSION
    clouds = dio.points_column(t, "roi_deformed_mm")
    for r, c in zip(rows, clouds):
        np.testing.assert_array_equal(c, r["roi_deformed_mm"])
        assert c.dtype == np.float32
    arrays = dio.load_training_arrays([p])
    assert len(arrays["case_id"]) == 3  # the failed case is dropped for training ...
    assert "I-000002" not in set(arrays["case_id"])
    assert t.num_rows == 4  # ... but stays in the shard with its reason
    assert t.column("reason").to_pylist()[2] == "diverged"
    np.testing.assert_allclose(arrays["force_n"][1], rows[1]["force_n"])
    # the ROI patch's triangles come back as (m, 3) int64 per case, in the row's node order
    by_id = {r["case_id"]: r for r in rows}
    for cid, T in zip(arrays["case_id"], arrays["roi_triangles"]):
        assert T.dtype == np.int64 and T.shape[1] == 3
        np.testing.assert_array_equal(T, by_id[cid]["roi_triangles"])


def test_payload_hash_ignores_wall_time_only(tmp_path, rows):
    a = dio.write_shard(rows, tmp_path / "a.parquet")
    for r in rows:
        r["wall_time_s"] += 1.0
    b = dio.write_shard(rows, tmp_path / "b.parquet")
    assert a["payload_sha256"] == b["payload_sha256"]
    rows[0]["force_n"] = [9.0, 9.0, 9.0]
    c = dio.write_shard(rows, tmp_path / "c.parquet")
    assert c["payload_sha256"] != a["payload_sha256"]


def test_same_rows_give_byte_identical_files(tmp_path, rows):
    dio.write_shard(rows, tmp_path / "a.parquet")
    dio.write_shard(rows, tmp_path / "b.parquet")
    assert (tmp_path / "a.parquet").read_bytes() == (tmp_path / "b.parquet").read_bytes()


def test_failed_write_leaves_nothing(tmp_path, rows, monkeypatch):
    p = tmp_path / "shard-0000.parquet"

    def broken(table, where, **kw):
        where.write(b"PAR1 half a file")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(pq, "write_table", broken)
    with pytest.raises(OSError):
        dio.write_shard(rows, p)
    assert list(tmp_path.iterdir()) == []


def test_manifest_detects_truncation_and_bit_flips(tmp_path, rows):
    paths = []
    for i in range(2):
        p = tmp_path / f"shard-{i:04d}.parquet"
        dio.write_shard(rows, p)
        paths.append(p)
    m = dio.write_manifest(paths, tmp_path / "manifest.json")
    assert m["rows"] == 8 and m["failed"] == 2
    assert dio.verify_manifest(tmp_path / "manifest.json") == paths
    data = bytearray(paths[1].read_bytes())
    data[len(data) // 2] ^= 0x01
    paths[1].write_bytes(bytes(data))
    with pytest.raises(dio.ShardError, match="shard-0001.*does not match"):
        dio.verify_manifest(tmp_path / "manifest.json")
    paths[1].write_bytes(bytes(data[:100]))
    with pytest.raises(dio.ShardError, match="truncated or corrupt"):
        dio.verify_manifest(tmp_path / "manifest.json")
    with pytest.raises(dio.ShardError, match="not a readable Parquet"):
        dio.read_table(paths[1])
    paths[1].unlink()
    with pytest.raises(dio.ShardError, match="missing"):
        dio.verify_manifest(tmp_path / "manifest.json")


def test_other_schema_version_is_refused(tmp_path, rows):
    p = tmp_path / "s.parquet"
    dio.write_shard(rows, p)
    man = dio.write_manifest([p], tmp_path / "manifest.json")
    man["schema_version"] = "0.1"
    (tmp_path / "manifest.json").write_text(json.dumps(man))
    with pytest.raises(dio.ShardError, match="schema version"):
        dio.verify_manifest(tmp_path / "manifest.json")
    t = pq.read_table(p).replace_schema_metadata({b"liverforce.schema_version": b"0.1"})
    pq.write_table(t, p)
    with pytest.raises(dio.ShardError, match="schema version 0.1"):
        dio.read_table(p)


def test_empty_shard_is_valid(tmp_path):
    e = dio.write_shard([], tmp_path / "empty.parquet")
    assert e["rows"] == 0 and e["failed"] == 0


def test_dataset_reads_all_shards(tmp_path, rows):
    paths = []
    for i in range(3):
        p = tmp_path / f"shard-{i:04d}.parquet"
        dio.write_shard(rows, p)
        paths.append(p)
    ds = dio.open_dataset(paths)
    assert ds.count_rows() == 12
    assert ds.to_table(columns=["force_magnitude_n"]).num_rows == 12


def test_the_train_and_validate_steps_verify_every_shard_before_reading_any(tmp_path, rows):
    """A shard modified after its manifest was written stops the train step (node and camera variants) and the
    validation's camera arrays with the shard named, before any model is fitted (the slow shard-pipeline tests
    run the same through snakemake)."""
    from liverforce.pipeline.shared import camera_arrays, load_study_arrays
    from liverforce.pipeline.train import train_model

    paths = [tmp_path / f"shard-{i:04d}.parquet" for i in range(2)]
    for p in paths:
        dio.write_shard(rows, p)
    manifest = tmp_path / "manifest.json"
    dio.write_manifest(paths, manifest)
    assert len(load_study_arrays(manifest)["case_id"]) == 6
    data = bytearray(paths[1].read_bytes())
    data[len(data) // 2] ^= 0x01
    paths[1].write_bytes(bytes(data))
    for cfg in ({}, {"roi_features": "cloud"}):
        with pytest.raises(dio.ShardError, match="shard-0001.*does not match"):
            train_model(manifest, "I", "v", cfg, {}, {}, f"sqlite:///{tmp_path / 'mlflow.db'}", "e", "e", 0, 1,
                        tmp_path / "metrics.json", tmp_path / "model")
    with pytest.raises(dio.ShardError, match="shard-0001.*does not match"):
        camera_arrays(manifest, [str(tmp_path / "liver.vtu")], "validation")  # not read: the shards first
    assert not (tmp_path / "metrics.json").exists() and not (tmp_path / "model").exists()
