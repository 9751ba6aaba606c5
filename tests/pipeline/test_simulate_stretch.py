"""Simulate stage: the principal-stretch range reached is a shard column, and a case that leaves the
Drucker-checked range (``material.stability_stretch``) is a warning naming the case (issue 18)."""
from __future__ import annotations

import logging

import numpy as np
import pyarrow.parquet as pq
import pytest

from liverforce.config import compose


@pytest.fixture(scope="module")
def liver():
    from liverforce.fem.testing import ellipsoid_liver
    from liverforce.mesh.types import LiverMesh

    return LiverMesh(**ellipsoid_liver(2))  # 129 vertices


def _case(liver, cfg, force_n):
    from liverforce.fem.materials import make_material

    mat = cfg["material"]
    visible = liver.facets[liver.facet_visible]
    top = visible.ravel()[np.argmax(liver.points[visible.ravel(), 2])]  # the highest visible vertex
    return {"case_id": "I-000007", "scenario": "I", "geometry_id": "g", "shard_index": 0, "seed": 0,
            "material_model": mat["model"], "material_param_names": list(mat["params_mpa"]),
            "material_params_mpa": list(mat["params_mpa"].values()),
            "bulk_modulus_mpa": make_material(mat["model"], mat["params_mpa"], nu=mat["nu"]).bulk,
            "exertion_id": 0, "exertion_point_mm": liver.points[top].copy(),
            "force_n": np.asarray(force_n, float), "force_magnitude_n": float(np.linalg.norm(force_n))}


def test_the_stretch_range_is_written_to_the_shard_and_a_case_outside_is_named(liver, tmp_path, caplog):
    from liverforce.dataset import io as dio
    from liverforce.fem.kinematics import principal_stretch_range
    from liverforce.fem.materials import make_material
    from liverforce.fem.problem import LiverModel, ToolLoad
    from liverforce.pipeline.simulate import boundary_params, simulate_cases, solver_options

    cfg = compose(["experiment=smoke"])
    sim = dict(cfg["simulate"])
    case = _case(liver, cfg, [0.0, 0.0, -1.0])
    with caplog.at_level(logging.WARNING, logger="liverforce"):
        rows = simulate_cases([case], {"g": liver}, sim, cfg["boundary"], cfg["dataset"], stretch_range=(0.6, 1.4))
    assert rows[0]["converged"], rows[0]["reason"]
    lo, hi = rows[0]["min_principal_stretch"], rows[0]["max_principal_stretch"]
    assert 0.6 < lo < 1.0 < hi < 1.4
    assert "Drucker-checked" not in caplog.text

    # the same solve outside the product loop: the row holds its range over every quadrature point
    mat = make_material(cfg["material"]["model"], cfg["material"]["params_mpa"], nu=cfg["material"]["nu"])
    fe = LiverModel.from_mesh(liver, mat, boundary_params(liver, cfg["boundary"]), solver_options(sim))
    res = fe.solve(ToolLoad(case["exertion_point_mm"], case["force_n"], sim["tool_radius_mm"]))
    ref = principal_stretch_range(fe.disc, res.state)
    assert (lo, hi) == pytest.approx(ref, abs=1e-6)

    # written and read back as float64 columns with their unit
    path = tmp_path / "shard-0000.parquet"
    dio.write_shard(rows, path)
    t = pq.read_table(path, columns=["max_principal_stretch", "min_principal_stretch"])
    assert str(t.schema.field("max_principal_stretch").type) == "double"
    assert t.column("max_principal_stretch").to_pylist() == [hi]
    assert t.column("min_principal_stretch").to_pylist() == [lo]
    assert "max_principal_stretch" in dio.read_metadata(path)["units"]

    # a range the case leaves: one warning naming the case, its stretches and the range
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="liverforce"):
        simulate_cases([case], {"g": liver}, sim, cfg["boundary"], cfg["dataset"], stretch_range=(0.999, 1.001))
    warnings = [r.getMessage() for r in caplog.records if "Drucker-checked" in r.getMessage()]
    assert len(warnings) == 1
    assert "I-000007" in warnings[0] and f"{lo:.3f}-{hi:.3f}" in warnings[0] and "0.999-1.001" in warnings[0]


def test_a_crashed_case_has_nan_stretches_and_no_warning(liver, caplog, monkeypatch):
    from liverforce.fem.problem import LiverModel
    from liverforce.pipeline.simulate import simulate_cases

    cfg = compose(["experiment=smoke"])

    def crash(*a, **kw):
        raise FloatingPointError("boom")

    monkeypatch.setattr(LiverModel, "solve", crash)
    with caplog.at_level(logging.WARNING, logger="liverforce"):
        rows = simulate_cases([_case(liver, cfg, [0.0, 0.0, -1.0])], {"g": liver}, dict(cfg["simulate"]),
                              cfg["boundary"], cfg["dataset"], stretch_range=(0.6, 1.4))
    assert not rows[0]["converged"]
    assert np.isnan(rows[0]["max_principal_stretch"]) and np.isnan(rows[0]["min_principal_stretch"])
    assert "Drucker-checked" not in caplog.text
