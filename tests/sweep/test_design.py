"""Design of experiments: force cone, ranges, determinism, stability refusal."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from liverforce.sweep.design import ExertionSet, SweepError, build_cases, force_vectors, n_shards, sample_exertion_points

MATERIAL = {"model": "yeoh", "params_mpa": {"C10": 0.00161, "C20": 0.0125, "C30": 0.00531}, "nu": 0.49,
            "vary_rel": 0.3, "on_unstable": "refuse"}
FORCE = {"min_n": 0.0, "max_n": 5.0, "cone_deg": 30.0}


def always_stable(model, params):
    return True, "stable"


def bulk(model, params, nu):
    return 1.0


def frames_for(normals):
    out = []
    for n in normals:
        a = np.eye(3)[np.argmin(np.abs(n))]
        t1 = a - a.dot(n) * n
        t1 /= np.linalg.norm(t1)
        out.append(np.stack([t1, np.cross(n, t1), n]))
    return np.asarray(out)


@pytest.fixture
def exertion():
    rng = np.random.default_rng(1)
    n = rng.normal(size=(5, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return {"g0": ExertionSet(points=rng.normal(size=(5, 3)) * 50, normals=n, frames=frames_for(n)),
            "g1": ExertionSet(points=rng.normal(size=(5, 3)) * 50, normals=n[::-1].copy(), frames=frames_for(n[::-1]))}


def run(exertion, spec, material=MATERIAL, check=always_stable, seed=0, gids=("g0",)):
    return build_cases("II", spec, list(gids), exertion, material, FORCE, "sobol", seed, 10, check, bulk)


def test_forces_push_inward_within_the_cone_and_range(exertion):
    res = run(exertion, {"n_cases": 200, "exertion": "varies", "material": "fixed"})
    assert len(res.rows) == 200
    for r in res.rows:
        f = np.asarray(r["force_n"])
        n = np.asarray(r["exertion_normal"])
        mag = np.linalg.norm(f)
        assert 0.0 <= mag <= 5.0 + 1e-12
        if mag > 1e-9:
            angle = np.degrees(np.arccos(np.clip(-f.dot(n) / mag, -1, 1)))
            assert angle <= 30.0 + 1e-9
    mags = np.array([r["force_magnitude_n"] for r in res.rows])
    assert mags.min() < 0.2 and mags.max() > 4.8  # space filling covers the range


def test_cap_sampling_is_uniform_in_cos_theta():
    rng = np.random.default_rng(0)
    n = 20000
    fr = np.tile(np.eye(3), (n, 1, 1))
    f = force_vectors(np.ones(n), rng.random(n), rng.random(n), fr, 0.0, 1.0, 60.0)
    cos_t = -f[:, 2]
    # cos theta uniform on [0.5, 1]: mean 0.75, and the azimuth is isotropic
    assert cos_t.mean() == pytest.approx(0.75, abs=0.005)
    assert abs(f[:, 0].mean()) < 0.01 and abs(f[:, 1].mean()) < 0.01


def test_same_seed_same_table_other_seed_other_table(exertion):
    spec = {"n_cases": 50, "exertion": "varies", "material": "varies"}
    a, b, c = run(exertion, spec), run(exertion, spec), run(exertion, spec, seed=1)
    assert a.rows == b.rows
    assert [r["force_n"] for r in a.rows] != [r["force_n"] for r in c.rows]


def test_fixed_exertion_and_material(exertion):
    res = run(exertion, {"n_cases": 40, "exertion": "fixed", "material": "fixed"})
    assert {r["exertion_id"] for r in res.rows} == {0}
    assert {tuple(r["material_params_mpa"]) for r in res.rows} == {(0.00161, 0.0125, 0.00531)}


def test_varied_material_in_relative_range(exertion):
    res = run(exertion, {"n_cases": 64, "exertion": "varies", "material": "varies"})
    p = np.array([r["material_params_mpa"] for r in res.rows])
    base = np.array([0.00161, 0.0125, 0.00531])  # names sorted: C10, C20, C30
    assert np.all(p >= base * 0.7 - 1e-15) and np.all(p <= base * 1.3 + 1e-15)
    assert len({r["exertion_id"] for r in res.rows}) == 5


def test_shards_and_warm_start_order(exertion):
    res = run(exertion, {"n_cases": 35, "exertion": "varies", "material": "fixed"}, gids=("g0", "g1"))
    shards = [r["shard_index"] for r in res.rows]
    assert shards == sorted(shards) and max(shards) == n_shards(35, 10) - 1
    keys = [(r["geometry_id"], r["exertion_id"]) for r in res.rows]
    assert keys == sorted(keys)
    # within a (geometry, point) group: a nearest-neighbour chain of forces from the smallest one
    for key in set(keys):
        g = [r for r in res.rows if (r["geometry_id"], r["exertion_id"]) == key]
        f = np.array([r["force_n"] for r in g])
        assert np.linalg.norm(f[0]) == pytest.approx(np.linalg.norm(f, axis=1).min())
        for k in range(len(g) - 2):
            assert np.linalg.norm(f[k + 1] - f[k]) <= np.linalg.norm(f[k + 2:] - f[k], axis=1).min() + 1e-12
    assert {r["geometry_id"] for r in res.rows} == {"g0", "g1"}
    assert len({r["case_id"] for r in res.rows}) == 35


def test_unstable_base_material_refused_before_anything(exertion):
    def unstable(model, params):
        return False, "uniaxial stable only for stretch 0.87-1.10"

    with pytest.raises(SweepError, match="not Drucker-stable.*0.87"):
        run(exertion, {"n_cases": 10, "exertion": "varies", "material": "fixed"}, check=unstable)


def test_unstable_samples_refused_or_clipped(exertion):
    calls = {"n": 0}

    def sometimes(model, params):
        calls["n"] += 1
        return (params["C10"] <= 0.00161, "C10 too high (test rule)")

    spec = {"n_cases": 40, "exertion": "varies", "material": "varies"}
    with pytest.raises(SweepError, match="material.on_unstable=clip"):
        run(exertion, spec, check=sometimes)
    res = run(exertion, spec, material={**MATERIAL, "on_unstable": "clip", "params_mpa": {**MATERIAL["params_mpa"], "C10": 0.0016}},
              check=sometimes)
    assert 0 < len(res.rows) < 40 and len(res.rows) + len(res.dropped_unstable) == 40
    assert all(r["material_params_mpa"][0] <= 0.00161 for r in res.rows)


def test_exertion_points_on_visible_surface_with_spacing():
    s = trimesh.creation.icosphere(subdivisions=3, radius=60.0)
    pts, tri = np.asarray(s.vertices), np.asarray(s.faces)
    visible = pts[tri].mean(axis=1)[:, 2] > 20.0
    p = sample_exertion_points(pts, tri, visible, 6, 15.0, seed=3)
    assert p.shape == (6, 3)
    d = np.linalg.norm(p[:, None] - p[None], axis=2) + np.eye(6) * 1e9
    assert d.min() >= 15.0
    assert np.all(p[:, 2] > 15.0)
    np.testing.assert_array_equal(p, sample_exertion_points(pts, tri, visible, 6, 15.0, seed=3))
    with pytest.raises(SweepError, match="min_spacing_mm"):
        sample_exertion_points(pts, tri, visible, 50, 40.0, seed=3)
