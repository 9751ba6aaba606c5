"""Parquet I/O for case tables and shards (the only module that imports pyarrow).

Every file is written atomically: to a dot-prefixed temporary name in the same
folder, flushed and fsynced, then renamed over the final name, so a reader never
sees half a file (a killed job leaves at most a stray ``.<stem>.<random>.tmp<suffix>`` behind, which the
job's next run removes: :func:`liverforce.atomic.remove_stale_temps`).
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np
import pyarrow as pa
import pyarrow.dataset as pads
import pyarrow.parquet as pq

from liverforce.atomic import atomic_path, file_sha256
from liverforce.dataset.schema import (
    CASE_SCHEMA,
    NONDETERMINISTIC_COLUMNS,
    SCHEMA_VERSION,
    SHARD_SCHEMA,
    UNITS,
)


class ShardError(RuntimeError):
    """A shard is missing, truncated, corrupt, or of another schema version."""


# --------------------------------------------------------------------------
# writing
# --------------------------------------------------------------------------


def _metadata(extra: dict[str, Any] | None = None) -> dict[bytes, bytes]:
    meta = {
        b"liverforce.schema_version": SCHEMA_VERSION.encode(),
        b"liverforce.units": json.dumps(UNITS, sort_keys=True).encode(),
    }
    for k, v in (extra or {}).items():
        meta[f"liverforce.{k}".encode()] = json.dumps(v, sort_keys=True).encode()
    return meta


def _atomic_write_table(table: pa.Table, path: Path, compression: str) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            pq.write_table(
                table,
                fh,
                compression=None if compression == "none" else compression,
                use_dictionary=False,
                write_statistics=True,
            )
            fh.flush()
            os.fsync(fh.fileno())


def _column(name: str, values: list, typ: pa.DataType) -> pa.Array:
    if pa.types.is_list(typ) or pa.types.is_fixed_size_list(typ):
        # nested numeric lists: go through numpy for speed where possible
        return pa.array([None if v is None else _to_py(v) for v in values], type=typ)
    return pa.array(values, type=typ)


def _to_py(v):
    if isinstance(v, np.ndarray):
        return v.tolist()
    return v


def rows_to_table(rows: Sequence[dict], schema: pa.Schema) -> pa.Table:
    """Build a table from row dicts, checking that every schema column is given."""
    if rows:
        missing = set(schema.names) - set(rows[0])
        extra = set(rows[0]) - set(schema.names)
        if missing or extra:
            raise ValueError(f"row keys do not match the schema: missing {sorted(missing)}, unexpected {sorted(extra)}")
    cols = [_column(f.name, [r[f.name] for r in rows], f.type) for f in schema]
    return pa.Table.from_arrays(cols, schema=schema)


def write_shard(rows: Sequence[dict], path: str | Path, compression: str = "zstd", extra_meta: dict | None = None) -> dict:
    """Write one shard atomically; return its manifest entry.

    Returns
    -------
    dict
        ``file``, ``rows``, ``failed`` (non-converged rows), ``sha256`` (of
        the file bytes: detects truncation and bit flips) and ``payload_sha256``
        (of the deterministic columns: equal for equal configs).
    """
    table = rows_to_table(rows, SHARD_SCHEMA).replace_schema_metadata(_metadata(extra_meta))
    _atomic_write_table(table, Path(path), compression)
    return manifest_entry(path)


def write_case_table(rows: Sequence[dict], path: str | Path, extra_meta: dict | None = None) -> None:
    """Write the sweep's case table (one row per case) atomically."""
    table = rows_to_table(rows, CASE_SCHEMA).replace_schema_metadata(_metadata(extra_meta))
    _atomic_write_table(table, Path(path), "zstd")


# --------------------------------------------------------------------------
# hashing and manifest
# --------------------------------------------------------------------------


def payload_sha256(table: pa.Table) -> str:
    """Hash of the deterministic columns (values, not file bytes)."""
    h = hashlib.sha256()
    for name in table.column_names:
        if name in NONDETERMINISTIC_COLUMNS:
            continue
        h.update(name.encode())
        col = table.column(name).combine_chunks()
        for buf in col.buffers():
            if buf is not None:
                h.update(memoryview(buf))
    return h.hexdigest()


def manifest_entry(path: str | Path) -> dict:
    path = Path(path)
    table = read_table(path)
    conv = table.column("converged").to_numpy(zero_copy_only=False)
    return {
        "file": path.name,
        "rows": table.num_rows,
        "failed": int((~conv).sum()),
        "sha256": file_sha256(path),
        "payload_sha256": payload_sha256(table),
    }


def write_manifest(shard_paths: Iterable[str | Path], path: str | Path, extra: dict | None = None) -> dict:
    """Write ``manifest.json`` listing every shard with rows, failures and hashes."""
    entries = [manifest_entry(p) for p in shard_paths]
    rows = sum(e["rows"] for e in entries)
    failed = sum(e["failed"] for e in entries)
    manifest = {
        "schema_version": SCHEMA_VERSION,
        "shards": entries,
        "rows": rows,
        "failed": failed,
        "failure_rate": failed / rows if rows else 0.0,
        "data_version": hashlib.sha256("".join(e["payload_sha256"] for e in entries).encode()).hexdigest()[:16],
        **(extra or {}),
    }
    _write_manifest_json(manifest, path)
    return manifest


def _write_manifest_json(obj: Any, path: str | Path) -> None:
    """The manifest through this module's ``open`` (so disk faults can be injected here), fsynced, atomically."""
    with atomic_path(path) as tmp:
        with open(tmp, "w") as fh:
            json.dump(obj, fh, indent=2, sort_keys=True)
            fh.flush()
            os.fsync(fh.fileno())


def verify_manifest(manifest_path: str | Path) -> list[Path]:
    """Check every shard listed in a manifest against its hash.

    Returns
    -------
    list of Path
        The shard paths, in manifest order.

    Raises
    ------
    ShardError
        Naming the first missing, truncated or modified shard and what to do.
    """
    manifest_path = Path(manifest_path)
    with open(manifest_path) as fh:
        manifest = json.load(fh)
    if manifest.get("schema_version") != SCHEMA_VERSION:
        raise ShardError(
            f"{manifest_path}: schema version {manifest.get('schema_version')} != {SCHEMA_VERSION} of this liverforce; "
            "re-run the sweep (delete the shards folder) or use the matching liverforce version"
        )
    out = []
    for e in manifest["shards"]:
        p = manifest_path.parent / e["file"]
        if not p.exists():
            raise ShardError(f"{p}: listed in {manifest_path.name} but missing; re-run `snakemake` to rebuild it")
        digest = file_sha256(p)
        if digest != e["sha256"]:
            raise ShardError(
                f"{p}: content hash {digest[:12]} does not match the manifest ({e['sha256'][:12]}): the file is "
                "truncated or corrupt. Delete it and re-run `snakemake` to rebuild it."
            )
        out.append(p)
    return out


# --------------------------------------------------------------------------
# reading
# --------------------------------------------------------------------------


def read_table(path: str | Path, columns: list[str] | None = None) -> pa.Table:
    """Read one Parquet file, refusing a corrupt file or another schema version."""
    path = Path(path)
    try:
        pf = pq.ParquetFile(path)
        meta = pf.schema_arrow.metadata or {}
        table = pf.read(columns=columns)
    except (pa.ArrowInvalid, OSError) as exc:
        raise ShardError(f"{path}: not a readable Parquet file ({exc}); delete it and re-run `snakemake`") from exc
    version = meta.get(b"liverforce.schema_version", b"?").decode()
    if version != SCHEMA_VERSION:
        raise ShardError(f"{path}: schema version {version}, this liverforce reads {SCHEMA_VERSION} (1.4 added the "
                         "ROI patch's triangles); re-run the sweep (`snakemake` re-simulates) or use the liverforce "
                         "that wrote the shards")
    return table


def read_metadata(path: str | Path) -> dict[str, Any]:
    """The ``liverforce.*`` file metadata, JSON-decoded."""
    meta = pq.ParquetFile(path).schema_arrow.metadata or {}
    out = {}
    for k, v in meta.items():
        k = k.decode()
        if k == "liverforce.schema_version":
            out["schema_version"] = v.decode()
        elif k.startswith("liverforce."):
            try:
                out[k[len("liverforce."):]] = json.loads(v)
            except json.JSONDecodeError:
                out[k[len("liverforce."):]] = v.decode()
    return out


def open_dataset(paths: Sequence[str | Path]) -> pads.Dataset:
    """All shards as one pyarrow dataset (DuckDB and Polars read the same files)."""
    return pads.dataset([str(p) for p in paths], format="parquet", schema=SHARD_SCHEMA)


def points_column(table: pa.Table, name: str) -> list[np.ndarray]:
    """A ``list<fixed_size_list<float32,3>>`` (or ``int32``) column as a list of (k_i, 3) arrays (no copy of
    values)."""
    col = table.column(name).combine_chunks()
    offsets = col.offsets.to_numpy()
    flat = col.values.values.to_numpy(zero_copy_only=False).reshape(-1, 3)
    return [flat[offsets[i]: offsets[i + 1]] for i in range(len(col))]


def vector_column(table: pa.Table, name: str) -> np.ndarray:
    """A fixed-size-list (or equal-length list) column as an (n, d) float array."""
    col = table.column(name).combine_chunks()
    if len(col) == 0:
        return np.zeros((0, 0))
    flat = col.flatten().to_numpy(zero_copy_only=False)
    return flat.reshape(len(col), -1)


def load_training_arrays(paths: Sequence[str | Path], converged_only: bool = True,
                         full_surface: bool = False) -> dict[str, Any]:
    """The arrays the learning stage consumes (see ``liverforce.learn``).

    Failed cases are dropped when ``converged_only`` (their rows stay in the
    shards with their reason). Rows come in case-id order, whatever order the
    sweep simulated and sharded them in, so that a seeded split depends only
    on the cases and the seed. ``full_surface`` adds ``surface_displacement_mm``
    (empty arrays when the shards were written without it).
    """
    tables = [read_table(p) for p in paths]
    table = pa.concat_tables(tables) if tables else SHARD_SCHEMA.empty_table()
    if converged_only:
        table = table.filter(table.column("converged"))
    table = table.sort_by([("case_id", "ascending")])
    out: dict[str, Any] = {
        "case_id": np.asarray(table.column("case_id").to_pylist(), dtype=object),
        "geometry_id": np.asarray(table.column("geometry_id").to_pylist(), dtype=object),
        "scenario": np.asarray(table.column("scenario").to_pylist(), dtype=object),
        "exertion_id": table.column("exertion_id").to_numpy(),
        "roi_undeformed_mm": points_column(table, "roi_undeformed_mm"),
        "roi_deformed_mm": points_column(table, "roi_deformed_mm"),
        "roi_node_ids": [np.asarray(x, dtype=np.int64) for x in table.column("roi_node_ids").to_pylist()],
        "roi_triangles": [t.astype(np.int64) for t in points_column(table, "roi_triangles")],
    }
    for name in (
        "force_n",
        "exertion_point_mm",
        "frame_normal",
        "frame_t1",
        "frame_t2",
        "liver_centroid_mm",
        "inertia_mm5",
        "material_params_mpa",
        "roi_centroid_undeformed_mm",
        "roi_centroid_deformed_mm",
    ):
        out[name] = vector_column(table, name).astype(np.float64)
    out["force_magnitude_n"] = table.column("force_magnitude_n").to_numpy()
    out["tool_thickness_mm"] = table.column("tool_thickness_mm").to_numpy().astype(np.float64)
    out["probe_compliance_mm_per_n"] = vector_column(table, "probe_compliance_mm_per_n").astype(np.float64)
    if full_surface:
        out["surface_displacement_mm"] = points_column(table, "surface_displacement_mm")
    return out
