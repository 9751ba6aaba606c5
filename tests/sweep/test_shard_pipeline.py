"""The data factory for real: config -> case table -> Parquet shards -> manifest (issue 5).

Small Snakemake runs of the smoke experiment in temporary directories
(``--directory``), building only scenario I's manifest at a coarse mesh:

- round trip: the shards form one pyarrow dataset with the schema of
  ``liverforce.dataset.schema``, the schema version is in the file metadata,
  the manifest agrees with recomputed counts and hashes, and every case of
  the case table is simulated exactly once;
- determinism: two runs in two directories give equal payload hashes;
- kill and resume: a SIGKILL'ed sweep resumes without redoing finished shards
  and ends with the same payloads as an uninterrupted run;
- a corrupt shard (truncated, one byte flipped) is refused by
  ``verify_manifest`` and by the train rule, naming the file;
- forced non-convergence is recorded, not fatal, counted and logged;
- DuckDB and Polars read the real shards unchanged.

The first run is reused by the later tests (copied with its ``.snakemake``
metadata where a test changes files), so only two runs start from scratch.
"""
from __future__ import annotations

import base64
import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pyarrow.dataset as pads
import pyarrow.parquet as pq
import pytest

from liverforce.dataset import io as dio
from liverforce.dataset.schema import NONDETERMINISTIC_COLUMNS, SCHEMA_VERSION, SHARD_SCHEMA
from test_workflow import SNAKEMAKE, ROOT, job_counts, snakemake

# every test here reads a real smoke sweep (run_a, ~25 s) and several run snakemake again: CI runs them with -m slow
pytestmark = [pytest.mark.workflow, pytest.mark.slow]

EXPERIMENT = "smoke"
N_CASES, PER_SHARD = 6, 2
N_SHARDS = N_CASES // PER_SHARD
OVERRIDES = f"sweep.scenarios.I.n_cases={N_CASES} sweep.cases_per_shard={PER_SHARD} mesh.target_nodes=300"
RESULTS = Path("results") / EXPERIMENT
TARGET = str(RESULTS / "shards" / "I" / "manifest.json")
SHARD_NAMES = [f"shard-{i:04d}.parquet" for i in range(N_SHARDS)]


def sweep_args(work: Path, overrides: str = OVERRIDES, cores: int = 2, target: str = TARGET) -> list[str]:
    return ["--cores", str(cores), "--directory", str(work), "--config", f"experiment={EXPERIMENT}",
            f"overrides={overrides}", "--", target]


def shard_dir(work: Path) -> Path:
    return work / RESULTS / "shards" / "I"


def manifest(work: Path) -> dict:
    return json.loads((shard_dir(work) / "manifest.json").read_text())


def payloads(work: Path) -> dict[str, str]:
    return {e["file"]: e["payload_sha256"] for e in manifest(work)["shards"]}


def incomplete_markers(work: Path) -> set[str]:
    """Shard names Snakemake has marked incomplete (job started, finish not yet recorded)."""
    names = set()
    folder = work / ".snakemake" / "incomplete"
    for p in folder.iterdir() if folder.is_dir() else []:
        try:
            names.add(Path(base64.urlsafe_b64decode(p.name).decode()).name)
        except (ValueError, UnicodeDecodeError):
            names.add(Path(base64.b64decode(p.name).decode(errors="replace")).name)
    return names


def stray_tmp_files(work: Path) -> list[Path]:
    return sorted((work / RESULTS).rglob(".*.tmp*"))


def copy_run(src: Path, dst: Path) -> Path:
    """A copy of a finished run (mtimes and Snakemake metadata kept: nothing is out of date)."""
    shutil.copytree(src, dst, symlinks=True)
    return dst


@pytest.fixture(scope="module")
def run_a(tmp_path_factory) -> Path:
    work = tmp_path_factory.mktemp("sweep_a")
    proc = snakemake(*sweep_args(work))
    counts = job_counts(proc.stdout + proc.stderr)
    assert counts.get("simulate") == N_SHARDS and counts.get("manifest") == 1, counts
    return work


@pytest.fixture(scope="module")
def run_b(tmp_path_factory, run_a) -> Path:
    work = tmp_path_factory.mktemp("sweep_b")
    snakemake(*sweep_args(work))
    return work


# ---------------------------------------------------------------- 1. round trip


def test_round_trip_config_to_shards_to_dataset(run_a):
    folder = shard_dir(run_a)
    files = sorted(folder.glob("*.parquet"))
    assert [f.name for f in files] == SHARD_NAMES
    assert not stray_tmp_files(run_a)

    # one dataset, schema inferred from the files themselves, field by field
    ds = pads.dataset([str(f) for f in files], format="parquet")
    schema = ds.schema
    assert schema.names == SHARD_SCHEMA.names
    for field in SHARD_SCHEMA:
        got = schema.field(field.name)
        assert got.type == field.type, (field.name, got.type, field.type)
        assert got.nullable == field.nullable, field.name
    table = ds.to_table()
    assert table.num_rows == N_CASES
    assert dio.open_dataset(files).to_table().num_rows == N_CASES

    # schema version (and units) in every file's Parquet key-value metadata
    for f in files:
        kv = pq.read_metadata(f).metadata
        assert kv[b"liverforce.schema_version"].decode() == SCHEMA_VERSION
        assert json.loads(kv[b"liverforce.units"])["force_n"] == "N"

    # the manifest equals values recomputed from the files
    m = manifest(run_a)
    assert m["schema_version"] == SCHEMA_VERSION
    assert [e["file"] for e in m["shards"]] == SHARD_NAMES
    total_rows = total_failed = 0
    for e in m["shards"]:
        path = folder / e["file"]
        t = pq.read_table(path)
        failed = sum(1 for c in t.column("converged").to_pylist() if not c)
        assert e["rows"] == t.num_rows == pq.ParquetFile(path).metadata.num_rows
        assert e["failed"] == failed
        assert e["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
        assert e["payload_sha256"] == dio.payload_sha256(t)
        # the shard holds exactly its own shard index
        assert set(t.column("shard_index").to_pylist()) == {int(e["file"][6:10])}
        total_rows += t.num_rows
        total_failed += failed
    assert m["rows"] == total_rows == N_CASES
    assert m["failed"] == total_failed
    assert m["failure_rate"] == pytest.approx(total_failed / total_rows)
    assert dio.verify_manifest(folder / "manifest.json") == [folder / n for n in SHARD_NAMES]

    # every case id of the case table exactly once, with its inputs
    cases = pq.read_table(run_a / RESULTS / "sweep" / "I" / "cases.parquet")
    case_ids = cases.column("case_id").to_pylist()
    shard_ids = table.column("case_id").to_pylist()
    assert len(case_ids) == N_CASES
    assert sorted(shard_ids) == sorted(case_ids) and len(set(shard_ids)) == len(shard_ids)
    by_id = {r["case_id"]: r for r in cases.select(["case_id", "force_n", "exertion_point_mm", "shard_index"]).to_pylist()}
    for r in table.select(["case_id", "force_n", "exertion_point_mm", "shard_index"]).to_pylist():
        assert r == by_id[r["case_id"]]
    # converged rows carry a deformed ROI point cloud of the same size as the undeformed one
    for und, de, ok in zip(dio.points_column(table, "roi_undeformed_mm"), dio.points_column(table, "roi_deformed_mm"),
                           table.column("converged").to_pylist()):
        assert und.shape == de.shape and und.shape[0] > 0
        if ok:
            assert (de != und).any()


# ------------------------------------------------------------- 2. determinism


def test_same_config_gives_identical_payloads(run_a, run_b, tmp_path):
    assert payloads(run_a) == payloads(run_b)
    assert manifest(run_a)["data_version"] == manifest(run_b)["data_version"]
    identical = []
    for name in SHARD_NAMES:
        a_bytes = (shard_dir(run_a) / name).read_bytes()
        b_bytes = (shard_dir(run_b) / name).read_bytes()
        ta, tb = pq.read_table(shard_dir(run_a) / name), pq.read_table(shard_dir(run_b) / name)
        # every deterministic column and the file metadata are equal ...
        det = [c for c in ta.column_names if c not in NONDETERMINISTIC_COLUMNS]
        assert ta.select(det).equals(tb.select(det)), name
        assert ta.schema.metadata == tb.schema.metadata, name
        # ... so the bytes differ, if at all, only through the wall-time column: rewriting both
        # with the shard writer and wall_time_s = 0 gives identical bytes (and the rewrite with
        # the original wall times reproduces the original file, so the writer is the same)
        identical.append(a_bytes == b_bytes)
        if a_bytes != b_bytes:
            assert ta.column("wall_time_s") != tb.column("wall_time_s"), name
            rewritten = []
            for tag, t, orig in (("a", ta, a_bytes), ("b", tb, b_bytes)):
                meta = {k: v for k, v in dio.read_metadata(shard_dir(run_a if tag == "a" else run_b) / name).items()
                        if k not in ("schema_version", "units")}
                rows = t.to_pylist()
                same = tmp_path / f"{tag}-same-{name}"
                dio.write_shard(rows, same, compression=meta["dataset"]["compression"], extra_meta=meta)
                assert same.read_bytes() == orig, name
                for r in rows:
                    r["wall_time_s"] = 0.0
                zero = tmp_path / f"{tag}-zero-{name}"
                dio.write_shard(rows, zero, compression=meta["dataset"]["compression"], extra_meta=meta)
                rewritten.append(zero.read_bytes())
            assert rewritten[0] == rewritten[1], name
    print(f"\nshard files byte-identical across the two runs: {dict(zip(SHARD_NAMES, identical))}")


# ---------------------------------------------------------- 3. kill and resume


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    return True


def test_kill_and_resume_redoes_only_missing_shards(run_a, tmp_path):
    work = copy_run(run_a, tmp_path / "killed")
    # keep geometry, mesh and case table; drop every shard (and their progress files)
    shutil.rmtree(shard_dir(work))
    shutil.rmtree(work / RESULTS / "progress", ignore_errors=True)
    folder = shard_dir(work)

    cmd = [SNAKEMAKE, "--snakefile", str(ROOT / "Snakefile"), *sweep_args(work)]
    with open(tmp_path / "killed.out", "w") as out:
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT, start_new_session=True,
                                env={**os.environ, "PYTHONUNBUFFERED": "1"})
        deadline = time.monotonic() + 300
        on_disk: list[str] = []
        registered: list[str] = []
        try:
            # kill once Snakemake has registered at least one shard as finished (file there, its
            # incomplete marker gone) while another shard is still missing
            while time.monotonic() < deadline and proc.poll() is None:
                on_disk = sorted(p.name for p in folder.glob("shard-*.parquet")) if folder.exists() else []
                registered = [n for n in on_disk if n not in incomplete_markers(work)]
                if registered and len(on_disk) < N_SHARDS:
                    os.killpg(proc.pid, signal.SIGKILL)
                    break
                time.sleep(0.05)
        finally:
            if proc.poll() is None and not registered:
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=60)
    assert proc.returncode == -signal.SIGKILL and registered, (
        f"the sweep was not interrupted with some shards missing (return code {proc.returncode}, shards {on_disk}):\n"
        f"{(tmp_path / 'killed.out').read_text()[-3000:]}")
    t0 = time.monotonic()
    while _group_alive(proc.pid) and time.monotonic() - t0 < 30:
        time.sleep(0.1)
    assert not _group_alive(proc.pid), "jobs of the killed sweep are still running"

    on_disk = sorted(p.name for p in folder.glob("shard-*.parquet"))
    flagged = sorted(set(on_disk) & incomplete_markers(work))  # written, but the kill came before Snakemake noted it
    finished = {n: (folder / n).stat() for n in on_disk if n not in flagged}
    assert 1 <= len(finished) and len(on_disk) < N_SHARDS
    assert not (folder / "manifest.json").exists()
    left_after_kill = [str(p.relative_to(work)) for p in stray_tmp_files(work)]

    # resume: the plain command first; add what Snakemake asks for, and say what that was
    needed: list[str] = []
    extra: list[str] = []
    for _ in range(4):
        res = snakemake(*extra, *sweep_args(work), check=False)
        text = res.stdout + res.stderr
        if res.returncode == 0:
            break
        if "LockException" in text and "--unlock" not in needed:
            needed.append("--unlock")
            snakemake("--unlock", *sweep_args(work))
        elif "IncompleteFilesException" in text and "--rerun-incomplete" not in needed:
            needed.append("--rerun-incomplete")
            extra.append("--rerun-incomplete")
        else:
            break
    assert res.returncode == 0, text[-4000:]
    print(f"\nkilled with {sorted(finished)} finished, {flagged} written but flagged incomplete by Snakemake; "
          f".tmp files right after the kill: {left_after_kill}; resume needed: {needed or 'nothing extra'}")
    assert "--unlock" in needed  # a SIGKILL leaves Snakemake's lock behind
    if flagged:
        assert "--rerun-incomplete" in needed

    counts = job_counts(text)
    assert counts.get("simulate") == N_SHARDS - len(finished), counts  # only the missing (and flagged) shards ran
    assert not {"geometry", "mesh", "sweep"} & set(counts), counts
    for name, st in finished.items():  # finished shards untouched: same inode, same mtime
        now = (folder / name).stat()
        assert (now.st_ino, now.st_mtime_ns, now.st_size) == (st.st_ino, st.st_mtime_ns, st.st_size), name
    assert sorted(p.name for p in folder.glob("shard-*.parquet")) == SHARD_NAMES
    assert not stray_tmp_files(work)
    m = manifest(work)
    assert [e["file"] for e in m["shards"]] == SHARD_NAMES
    assert not any(e["file"].startswith(".") or e["file"].endswith(".tmp") for e in m["shards"])
    assert payloads(work) == payloads(run_a)  # same payloads as the uninterrupted run
    dio.verify_manifest(folder / "manifest.json")


# ----------------------------------------------------------- 4. corrupt shard


def _corrupt(path: Path, how: str) -> None:
    """Truncate or flip one byte, keeping the mtime (silent corruption: Snakemake sees nothing new)."""
    st = path.stat()
    data = bytearray(path.read_bytes())
    if how == "truncate":
        data = data[: len(data) // 2]
    else:
        data[len(data) // 2] ^= 0x01
    path.write_bytes(bytes(data))
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))


@pytest.mark.parametrize("how", ["truncate", "flip"])
def test_corrupt_shard_is_refused_by_verify_and_the_train_rule(run_a, tmp_path, how):
    work = copy_run(run_a, tmp_path / how)
    bad = shard_dir(work) / SHARD_NAMES[1]
    _corrupt(bad, how)

    with pytest.raises(dio.ShardError) as err:
        dio.verify_manifest(shard_dir(work) / "manifest.json")
    assert str(bad) in str(err.value) and "does not match the manifest" in str(err.value)

    model = RESULTS / "models" / "I" / "pca_sv"
    res = snakemake(*sweep_args(work, target=str(model / "metrics.json")), check=False)
    text = res.stdout + res.stderr
    assert res.returncode != 0
    counts = job_counts(text)
    assert counts == {"train": 1}, counts  # the manifest is trusted, not rebuilt over the bad file
    # the refusal names the file; it reaches the Snakemake output (the job's traceback on stderr)
    assert re.search(rf"ShardError: \S*{re.escape(SHARD_NAMES[1])}: content hash \w+ does not match the manifest",
                     text), text[-3000:]
    log = (work / RESULTS / "logs" / "train" / "I-pca_sv.log").read_text()
    assert "converged cases from" not in text + log  # stopped before loading data or training
    assert not (work / model / "metrics.json").exists() and not (work / model / "model").exists()


# ------------------------------------------------------ 5. forced non-convergence


def test_non_convergence_is_recorded_counted_and_logged(run_a, tmp_path):
    work = copy_run(run_a, tmp_path / "fail")
    res = snakemake(*sweep_args(work, overrides=f"{OVERRIDES} simulate.max_iter=1 simulate.max_steps=2"))
    counts = job_counts(res.stdout + res.stderr)
    assert counts == {"simulate": N_SHARDS, "manifest": 1}, counts  # params changed: only simulate re-runs

    failed = 0
    for name in SHARD_NAMES:
        t = pq.read_table(shard_dir(work) / name)
        assert t.num_rows == PER_SHARD  # failed cases are rows, never dropped
        for r in t.select(["converged", "reason", "load_fraction", "roi_deformed_mm"]).to_pylist():
            if r["converged"]:
                assert r["reason"] == ""
            else:
                failed += 1
                assert "max_steps=2" in r["reason"], r["reason"]
                assert r["load_fraction"] < 1.0 and len(r["roi_deformed_mm"]) > 0
    assert failed == N_CASES  # two load steps from 0.25 cannot reach the full load
    m = manifest(work)
    assert m["rows"] == N_CASES and m["failed"] == failed and m["failure_rate"] == pytest.approx(failed / N_CASES)
    log = (work / RESULTS / "logs" / "manifest" / "I.log").read_text()
    rate = re.search(r"(\d+) failed \(failure rate ([\d.]+) %\)", log)
    assert rate and int(rate.group(1)) == failed and float(rate.group(2)) == pytest.approx(100 * failed / N_CASES)
    sim_log = (work / RESULTS / "logs" / "simulate" / "I-0000.log").read_text()
    assert "FAILED (max_steps=2" in sim_log


# ---------------------------------------------------------- 7. external readers


def test_real_shards_read_unchanged_by_duckdb_and_polars(run_a):
    duckdb = pytest.importorskip("duckdb")
    pl = pytest.importorskip("polars")
    glob = str(shard_dir(run_a) / "*.parquet")
    ref = pads.dataset(sorted(shard_dir(run_a).glob("*.parquet")), format="parquet").to_table()
    ref = ref.sort_by("case_id").select(["case_id", "force_n", "roi_deformed_mm", "converged"]).to_pylist()

    con = duckdb.connect()
    assert con.sql(f"select count(*) from read_parquet('{glob}')").fetchall()[0][0] == len(ref)
    got = con.sql(f"select case_id, force_n, roi_deformed_mm, converged from read_parquet('{glob}') order by case_id")
    for (cid, f, cloud, ok), r in zip(got.fetchall(), ref, strict=True):
        assert (cid, list(f), [list(p) for p in cloud], ok) == (r["case_id"], r["force_n"], r["roi_deformed_mm"],
                                                                r["converged"])

    lf = pl.scan_parquet(glob)
    assert lf.select(pl.len()).collect().item() == len(ref)
    df = lf.select(["case_id", "force_n", "roi_deformed_mm", "converged"]).sort("case_id").collect()
    for d, r in zip(df.iter_rows(named=True), ref, strict=True):
        assert (d["case_id"], list(d["force_n"]), [list(p) for p in d["roi_deformed_mm"]], d["converged"]) == (
            r["case_id"], r["force_n"], r["roi_deformed_mm"], r["converged"])
