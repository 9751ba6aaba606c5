"""The learning arrays do not depend on how the sweep ordered and sharded the cases."""
import numpy as np
from fake_rows import fake_row

from liverforce.dataset import io as dio


def test_training_arrays_come_in_case_id_order_whatever_the_shard_order(tmp_path):
    rng = np.random.default_rng(0)
    rows = [fake_row(i, rng) for i in (5, 2, 9, 0, 7, 3)]
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    a = [tmp_path / "a" / "s0.parquet", tmp_path / "a" / "s1.parquet"]
    dio.write_shard(rows[:3], a[0])
    dio.write_shard(rows[3:], a[1])
    rev = rows[::-1]
    b = [tmp_path / "b" / "s0.parquet", tmp_path / "b" / "s1.parquet"]
    dio.write_shard(rev[:2], b[0])
    dio.write_shard(rev[2:], b[1])
    x, y = dio.load_training_arrays(a), dio.load_training_arrays(b)
    assert list(x["case_id"]) == sorted(r["case_id"] for r in rows)
    assert list(x["case_id"]) == list(y["case_id"])
    for k in ("force_n", "roi_deformed_mm"):
        assert all(np.array_equal(np.asarray(p), np.asarray(q)) for p, q in zip(x[k], y[k]))
    # each row keeps its own data
    assert [float(f[2]) for f in x["force_n"]] == [-1.0 * i for i in (0, 2, 3, 5, 7, 9)]
