"""Shards are plain Parquet: DuckDB and Polars read them unchanged (DESIGN "Beyond one machine").

Shards written by ``liverforce.dataset.io.write_shard`` (the writer the
simulate stage uses, zstd, schema metadata) with ROI clouds of different
sizes per row, a failed row and several files; DuckDB (``read_parquet`` over
a glob) and Polars (``scan_parquet``) must give the same row count, force
labels and point clouds as pyarrow, value for value. The same check on shards
from a real Snakemake run is in tests/sweep/test_shard_pipeline.py.
"""
from __future__ import annotations

import numpy as np
import pyarrow.dataset as pads
import pytest

from liverforce.dataset import io as dio
from liverforce.dataset.schema import SCHEMA_VERSION

duckdb = pytest.importorskip("duckdb")
pl = pytest.importorskip("polars")

COLUMNS = ["case_id", "force_n", "roi_deformed_mm", "roi_node_ids", "converged", "reason"]


def shard_row(shard: int, i: int, rng) -> dict:
    k = 20 + 7 * i + shard  # ROI sizes differ per row
    und = (rng.normal(size=(k, 3)) * 30).astype(np.float32)
    de = und + rng.normal(size=(k, 3)).astype(np.float32)
    force = rng.uniform(-5, 5, size=3)
    converged = (shard, i) != (1, 1)
    return {
        "case_id": f"II-{shard * 10 + i:06d}", "scenario": "II", "geometry_id": "proc-0000", "shard_index": shard,
        "seed": 1000 + i, "material_model": "yeoh", "material_param_names": ["C10", "C20", "C30"],
        "material_params_mpa": [0.0016, 0.0125, 0.0053], "bulk_modulus_mpa": 0.5, "exertion_id": i,
        "exertion_point_mm": rng.normal(size=3) * 50, "force_n": force, "force_magnitude_n": float(np.linalg.norm(force)),
        "frame_normal": [0, 0, 1.0], "frame_t1": [1.0, 0, 0], "frame_t2": [0, 1.0, 0],
        "liver_centroid_mm": [1.0, 2.0, 3.0], "inertia_mm5": rng.normal(size=9), "tool_thickness_mm": 45.0,
        "probe_compliance_mm_per_n": np.diag([1.0, 1.0, 2.0]).ravel(),
        "roi_fraction": 0.18, "roi_area_fraction": 0.1801, "roi_node_ids": rng.permutation(500)[:k].astype(np.int32),
        "roi_triangles": np.array([[0, j, j + 1] for j in range(1, k - 1)], dtype=np.int32).reshape(-1, 3),
        "roi_undeformed_mm": und, "roi_deformed_mm": de,
        "roi_centroid_undeformed_mm": und.mean(0), "roi_centroid_deformed_mm": de.mean(0),
        "surface_displacement_mm": rng.normal(size=(40, 3)).astype(np.float32), "max_displacement_mm": 3.2,
        "max_principal_stretch": 1.25, "min_principal_stretch": 0.8,
        "converged": converged, "reason": "" if converged else "max_steps=2 load steps reached",
        "load_fraction": 1.0 if converged else 0.5, "load_steps": 4, "newton_iterations": 11,
        "final_residual": 1e-9 if converged else float("nan"), "linear_solver": "cholmod",
        "wall_time_s": float(rng.random()),
    }


@pytest.fixture(scope="module")
def shard_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("shards")
    rng = np.random.default_rng(7)
    for shard in range(3):
        rows = [shard_row(shard, i, rng) for i in range(4 + shard)]
        dio.write_shard(rows, folder / f"shard-{shard:04d}.parquet", compression="zstd",
                        extra_meta={"dataset": {"compression": "zstd", "roi_fraction": 0.18}})
    dio.write_manifest(sorted(folder.glob("shard-*.parquet")), folder / "manifest.json")
    return folder


@pytest.fixture(scope="module")
def reference(shard_folder):
    """pyarrow's reading, sorted by case id, as Python values."""
    files = sorted(shard_folder.glob("shard-*.parquet"))
    table = pads.dataset([str(f) for f in files], format="parquet").to_table()
    return table.sort_by("case_id").select(COLUMNS).to_pylist()


def normalise(case_id, force, cloud, node_ids, converged, reason):
    return (case_id, [float(x) for x in force], [[float(x) for x in p] for p in cloud], [int(x) for x in node_ids],
            bool(converged), reason)


def expected(reference):
    return [normalise(*(r[c] for c in COLUMNS)) for r in reference]


def test_reference_is_what_was_written(reference, shard_folder):
    assert len(reference) == 4 + 5 + 6
    assert sum(not r["converged"] for r in reference) == 1
    clouds = [len(r["roi_deformed_mm"]) for r in reference]
    assert len(set(clouds)) > 1  # ragged point clouds, not one fixed size
    assert [p.name for p in dio.verify_manifest(shard_folder / "manifest.json")] == [
        f"shard-{i:04d}.parquet" for i in range(3)]


def test_duckdb_reads_the_shards_unchanged(shard_folder, reference):
    glob = str(shard_folder / "*.parquet")
    con = duckdb.connect()
    assert con.sql(f"select count(*) from read_parquet('{glob}')").fetchall()[0][0] == len(reference)
    rows = con.sql(f"select {', '.join(COLUMNS)} from read_parquet('{glob}') order by case_id").fetchall()
    assert [normalise(*r) for r in rows] == expected(reference)
    # types: the force label is a 3-vector of doubles, the cloud a list of float 3-vectors
    types = dict(con.sql(f"select column_name, column_type from (describe select force_n, roi_deformed_mm "
                         f"from read_parquet('{glob}'))").fetchall())
    # (DuckDB 2.0 maps Arrow's fixed_size_list to a LIST: DOUBLE[] rather than DOUBLE[3]; either is fine)
    assert types["force_n"] in ("DOUBLE[3]", "DOUBLE[]"), types
    assert types["roi_deformed_mm"] in ("FLOAT[3][]", "FLOAT[][]"), types
    f_len = con.sql(f"select min(len(force_n)), max(len(force_n)) from read_parquet('{glob}')").fetchall()[0]
    p_len = con.sql(f"select min(len(p)), max(len(p)), count(*) from (select unnest(roi_deformed_mm) as p "
                    f"from read_parquet('{glob}'))").fetchall()[0]
    lengths = (*f_len, *p_len[:2])
    assert p_len[2] == sum(len(r["roi_deformed_mm"]) for r in reference)
    assert lengths == (3, 3, 3, 3)
    # an aggregate straight on the files equals numpy's on pyarrow's values
    mean_fz = con.sql(f"select avg(force_n[3]) from read_parquet('{glob}')").fetchall()[0][0]
    assert mean_fz == pytest.approx(np.mean([r["force_n"][2] for r in reference]), rel=1e-12)
    # the schema version travels in the Parquet key-value metadata, visible to DuckDB too
    kv = con.sql(f"select key, value from parquet_kv_metadata('{shard_folder / 'shard-0000.parquet'}')").fetchall()
    meta = {bytes(k).decode(): bytes(v).decode() for k, v in kv}
    assert meta["liverforce.schema_version"] == SCHEMA_VERSION


def test_polars_reads_the_shards_unchanged(shard_folder, reference):
    glob = str(shard_folder / "*.parquet")
    lf = pl.scan_parquet(glob)
    assert lf.select(pl.len()).collect().item() == len(reference)
    df = lf.select(COLUMNS).sort("case_id").collect()
    assert df.schema["force_n"] == pl.Array(pl.Float64, 3)
    assert df.schema["roi_deformed_mm"] == pl.List(pl.Array(pl.Float32, 3))
    assert [normalise(*(d[c] for c in COLUMNS)) for d in df.iter_rows(named=True)] == expected(reference)
    # lazily filtered on the files: the failed case and its reason
    failed = lf.filter(~pl.col("converged")).select(["case_id", "reason"]).collect()
    assert failed.rows() == [(r["case_id"], r["reason"]) for r in reference if not r["converged"]]
