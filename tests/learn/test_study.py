"""Comparison studies on a tiny synthetic shard set with a known linear force -> dent map.

The "shards" are in memory: cases on an ellipsoid-like sphere surface with
every surface node's displacement stored (as ``dataset.store_full_surface``
does), a Gaussian dent linear in the local force, so the ROI can be re-grown
at any fraction and the physics is clean: noise can only hurt.
"""
from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from liverforce.dataset.roi import extract_roi, local_frame, surface_graph
from liverforce.learn.representation import with_roi_fraction
from liverforce.learn.study import (
    STUDIES,
    enabled_studies,
    hyper_parameters,
    plot_study,
    run_point,
    run_study,
    study_points,
)

MODEL = {
    "encoder": "pca", "code_size": 4, "state_vector": False, "grid_size": 8, "hidden": [64, 64], "dropout": 0.0,
    "occlusion": {"radius_mm": 0.0, "mode": "remove"}, "noise_mm": 0.0, "roi_features": "displacement",
    "grid_half_width_mm": 0.0, "dae_input_noise": 0.1,
}
HP = {"hidden": [64, 64], "dropout": 0.0, "lr": 3e-3, "batch_size": 32}
EPOCHS = 120


def _cases(n: int, seed: int = 0, radius: float = 60.0, base_fraction: float = 0.18):
    """n cases on one sphere 'liver': full-surface Gaussian dents, linear in the local force."""
    s = trimesh.creation.icosphere(subdivisions=4, radius=radius)
    pts, tri = np.asarray(s.vertices), np.asarray(s.faces)
    surf = surface_graph(pts, tri)
    rng = np.random.default_rng(seed)
    upper = np.flatnonzero(surf.points[:, 2] > 0.3 * radius)
    cand = rng.choice(upper, size=12, replace=False)  # 12 candidate exertion points, as a sweep has
    out = {k: [] for k in ("case_id", "geometry_id", "force_n", "exertion_point_mm", "frame_normal", "frame_t1",
                           "frame_t2", "liver_centroid_mm", "inertia_mm5", "tool_thickness_mm", "probe_compliance_mm_per_n",
                           "material_params_mpa",
                           "surface_displacement_mm")}
    inertia = np.eye(3) * 0.4 * radius**2 * (4 / 3 * np.pi * radius**3)
    for i in range(n):
        p = surf.points[cand[i % len(cand)]]
        R = local_frame(surf, p, 5.0)
        mag = rng.uniform(1.0, 5.0)
        tilt, az = np.deg2rad(30) * np.sqrt(rng.uniform()), rng.uniform(0, 2 * np.pi)
        f_loc = mag * np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), -np.cos(tilt)])
        g = np.exp(-np.sum((surf.points - p) ** 2, axis=1) / (2 * 12.0**2))
        d_loc = g[:, None] * (np.array([0.8, 0.8, 1.5]) * f_loc)[None, :]
        out["case_id"].append(f"T-{i:05d}")
        out["geometry_id"].append("sph-0000")
        out["force_n"].append(R.T @ f_loc)
        out["exertion_point_mm"].append(p)
        out["frame_t1"].append(R[0])
        out["frame_t2"].append(R[1])
        out["frame_normal"].append(R[2])
        out["liver_centroid_mm"].append(np.zeros(3))
        out["inertia_mm5"].append(inertia.ravel())
        out["tool_thickness_mm"].append(2.0 * radius)  # a chord through the sphere's centre
        out["probe_compliance_mm_per_n"].append(np.diag([0.8, 0.8, 1.5]).ravel())  # the dent at its centre, per N
        out["material_params_mpa"].append(np.array([0.0016, 0.0125]))
        out["surface_displacement_mm"].append((d_loc @ R).astype(np.float32))
    arrays = {k: (np.array(v, dtype=object) if k in ("case_id", "geometry_id") else
                  v if k == "surface_displacement_mm" else np.asarray(v, dtype=np.float64)) for k, v in out.items()}
    surfaces = {"sph-0000": surf}
    return with_roi_fraction(arrays, base_fraction, surfaces), surfaces


@pytest.fixture(scope="module")
def data():
    return _cases(160)


def test_roi_fraction_changes_the_nodes_used_and_keeps_the_geodesic_rule(data):
    arrays, surfaces = data
    small = with_roi_fraction(arrays, 0.05, surfaces)
    large = with_roi_fraction(arrays, 0.30, surfaces)
    n_small = np.mean([len(x) for x in small["roi_undeformed_mm"]])
    n_large = np.mean([len(x) for x in large["roi_undeformed_mm"]])
    assert 4.0 < n_large / n_small < 8.0  # ~6x the area, ~6x the nodes
    assert np.all(np.abs(small["roi_area_fraction"] - 0.05) < 0.002)
    assert np.all(np.abs(large["roi_area_fraction"] - 0.30) < 0.002)
    # the same rule as the simulation: nodes == extract_roi of the exertion point, in its order
    surf = surfaces["sph-0000"]
    ids, _ = extract_roi(surf, arrays["exertion_point_mm"][3], 0.05)
    assert np.array_equal(small["roi_node_ids"][3], surf.node_ids[ids])
    # re-selecting at the stored fraction reproduces the stored ROI exactly
    again = with_roi_fraction(arrays, 0.18, surfaces)
    assert all(np.array_equal(a, b) for a, b in zip(again["roi_node_ids"], arrays["roi_node_ids"]))
    assert all(np.array_equal(a, b) for a, b in zip(again["roi_deformed_mm"], arrays["roi_deformed_mm"]))
    # centroids follow the new ROI (the state vector uses them)
    assert not np.allclose(small["roi_centroid_undeformed_mm"], large["roi_centroid_undeformed_mm"])
    # the study point reports the nodes it really used (the main model's training split: the test part is dropped)
    from liverforce.learn.splits import train_test_split

    tr, _ = train_test_split(np.asarray(arrays["geometry_id"]).astype(str), scenario="II", test_fraction=0.25, seed=0)
    n_small = np.mean([len(small["roi_undeformed_mm"][i]) for i in tr])
    n_large = np.mean([len(large["roi_undeformed_mm"][i]) for i in tr])
    a = run_point(arrays, MODEL, HP, scenario="II", seed=0, test_fraction=0.25, epochs=5, roi_fraction=0.05,
                  surfaces=surfaces)
    b = run_point(arrays, MODEL, HP, scenario="II", seed=0, test_fraction=0.25, epochs=5, roi_fraction=0.30,
                  surfaces=surfaces)
    assert a["roi_nodes_mean"] == pytest.approx(n_small) and b["roi_nodes_mean"] == pytest.approx(n_large)
    assert a["representation"]["half_width_mm"] < b["representation"]["half_width_mm"]


def test_roi_fraction_needs_the_full_surface(data):
    arrays, surfaces = data
    bare = {k: v for k, v in arrays.items() if k != "surface_displacement_mm"}
    with pytest.raises(KeyError, match="surface_displacement_mm"):
        with_roi_fraction(bare, 0.1, surfaces)
    short = dict(arrays, surface_displacement_mm=[x[:10] for x in arrays["surface_displacement_mm"]])
    with pytest.raises(ValueError, match="store_full_surface"):
        with_roi_fraction(short, 0.1, surfaces)


def test_clean_linear_problem_is_learned_and_heavy_noise_does_not_help(data):
    arrays, _ = data
    clean = run_point(arrays, MODEL, HP, scenario="II", seed=0, test_fraction=0.25, epochs=EPOCHS)
    noisy = run_point(arrays, {**MODEL, "noise_mm": 2.0}, HP, scenario="II", seed=0, test_fraction=0.25,
                      epochs=EPOCHS)
    assert clean["n_val"] == 30 and clean["n_train"] == 90  # 160 cases: test 40 (never read), val 30, fit 90
    assert clean["metrics"]["accuracy_pct"] > 90.0, clean["metrics"]
    # 2 mm noise on a clean, noise-free linear map cannot make the estimate better
    assert noisy["metrics"]["mae_vec"] > clean["metrics"]["mae_vec"]
    assert noisy["metrics"]["accuracy_pct"] < clean["metrics"]["accuracy_pct"]


def test_learning_curve_uses_fewer_training_cases_same_test_split_and_fewer_cases_do_worse(data):
    arrays, _ = data
    full = run_point(arrays, MODEL, HP, scenario="II", seed=0, test_fraction=0.25, epochs=EPOCHS)
    few = run_point(arrays, MODEL, HP, scenario="II", seed=0, test_fraction=0.25, epochs=EPOCHS,
                    train_fraction=0.1)
    assert (few["n_train"], few["n_val"]) == (9, 30) and full["n_train"] == 90
    # 9 cases for a 3-output map through a 4-component code and a 64x64 MLP: clearly worse than 120
    assert few["metrics"]["mae_vec"] > 1.5 * full["metrics"]["mae_vec"], (few["metrics"], full["metrics"])


def test_a_study_point_never_reads_the_test_split(data):
    """The main model's test cases can be anything (NaN forces, garbage ROIs): a study point gives exactly the
    same result, because it fits and scores on the training split only."""
    from liverforce.learn.splits import train_test_split

    arrays, _ = data
    _, te = train_test_split(np.asarray(arrays["geometry_id"]).astype(str), scenario="II", test_fraction=0.25, seed=0)
    spoiled = dict(arrays)
    spoiled["force_n"] = np.array(arrays["force_n"], dtype=float)
    spoiled["force_n"][te] = np.nan
    spoiled["roi_deformed_mm"] = [np.full_like(d, np.nan) if i in set(te) else d
                                  for i, d in enumerate(arrays["roi_deformed_mm"])]
    a = run_point(arrays, MODEL, HP, scenario="II", seed=0, test_fraction=0.25, epochs=5)
    b = run_point(spoiled, MODEL, HP, scenario="II", seed=0, test_fraction=0.25, epochs=5)
    assert a["metrics"] == b["metrics"] and np.isfinite(b["metrics"]["mae_vec"])
    assert a["evaluated_on"] == "validation"


def test_training_subsample_is_per_geometry_seeded_and_inside_the_split():
    from liverforce.learn.study import subsample_per_geometry

    geo = np.array(["a"] * 40 + ["b"] * 20)
    idx = np.arange(0, 60, 2)  # 20 of a, 10 of b
    sub = subsample_per_geometry(idx, geo, 0.5, seed=3)
    assert set(sub) <= set(idx)
    assert (geo[sub] == "a").sum() == 10 and (geo[sub] == "b").sum() == 5
    assert np.array_equal(sub, subsample_per_geometry(idx, geo, 0.5, seed=3))
    assert not np.array_equal(sub, subsample_per_geometry(idx, geo, 0.5, seed=4))
    with pytest.raises(ValueError, match="train fraction"):
        subsample_per_geometry(idx, geo, 0.0, seed=3)


def test_study_points_expand_the_config():
    cfg = {
        "enabled": True, "epochs": 3, "hyper_parameters": "main",
        "roi_fraction": {"enabled": True, "scenarios": ["II"], "values": [0.05, 0.3]},
        "encoder": {"enabled": True, "scenarios": ["I", "IV"], "values": ["pca", "ae", "dae"]},
        "state_vector": {"enabled": True, "scenarios": ["II"], "values": [False, True], "encoder": "pca"},
        "occlusion": {"enabled": True, "scenarios": ["IV"], "radii_mm": [0, 5, 10], "encoders": ["dae", "pca"],
                      "modes": ["noise", "remove"]},
        "noise": {"enabled": False, "scenarios": ["II"], "values": [0, 1]},
        "train_size": {"enabled": True, "scenarios": ["II", "IV"], "values": [0.25, 1.0]},
        "train_livers": {"enabled": True, "scenarios": ["IV"], "values": [2, 8]},
    }
    assert enabled_studies(cfg) == ["roi_fraction", "encoder", "state_vector", "occlusion", "train_size",
                                    "train_livers"]
    tl = study_points("train_livers", cfg)
    assert [(p.scenario, p.train_livers, p.label) for p in tl] == [("IV", 2, "2 livers"), ("IV", 8, "8 livers")]
    ts = study_points("train_size", cfg)
    assert [(p.scenario, p.train_fraction) for p in ts] == [("II", 0.25), ("II", 1.0), ("IV", 0.25), ("IV", 1.0)]
    assert len(study_points("encoder", cfg)) == 6
    occ = study_points("occlusion", cfg)
    assert len(occ) == 12
    assert occ[-1].model_overrides == {"encoder": "pca", "occlusion": {"radius_mm": 10.0, "mode": "remove"}}
    sv = study_points("state_vector", cfg)
    assert [p.model_overrides["state_vector"] for p in sv] == [False, True]
    assert enabled_studies({**cfg, "enabled": False}) == []
    assert set(STUDIES) == {"roi_fraction", "encoder", "state_vector", "occlusion", "noise", "train_size",
                            "train_livers"}


def test_first_geometries_are_nested_seeded_subsets_of_the_training_livers():
    from liverforce.learn.study import first_geometries

    geo = np.repeat([f"g{i}" for i in range(10)], 3)
    idx = np.flatnonzero(~np.isin(geo, ["g0", "g5"]))  # the training split: 8 livers
    subsets = {k: set(geo[first_geometries(idx, geo, k, seed=4)]) for k in (1, 2, 4, 8, 30)}
    assert [len(subsets[k]) for k in (1, 2, 4, 8, 30)] == [1, 2, 4, 8, 8]
    assert subsets[1] < subsets[2] < subsets[4] < subsets[8] == subsets[30]
    assert not subsets[8] & {"g0", "g5"}  # never a test liver
    assert all(len(first_geometries(idx, geo, 2, seed=4)) == 6 for _ in range(2))  # every case of those livers
    assert subsets[4] != set(geo[first_geometries(idx, geo, 4, seed=5)])  # another seed, another order
    with pytest.raises(ValueError):
        first_geometries(idx, geo, 0, seed=4)


def test_hyper_parameters_come_from_the_tuned_main_model():
    model, train = {"hidden": [8], "dropout": 0.1}, {"lr": 1e-3, "batch_size": 64}
    ax = {"run_id": "abc", "best_params": {"n_layers": 3, "width": 32, "dropout": 0.2, "lr": 0.004, "batch_size": 16}}
    hp = hyper_parameters(ax, model, train, "main")
    assert hp["hidden"] == [32, 32, 32] and hp["lr"] == 0.004 and hp["batch_size"] == 16 and "abc" in hp["source"]
    fixed = {"best_params": {"hidden": [16, 16], "dropout": 0.0, "lr": 0.01, "batch_size": 8}}
    assert hyper_parameters(fixed, model, train, "main")["hidden"] == [16, 16]
    cfg = hyper_parameters(ax, model, train, "config")
    assert cfg["hidden"] == [8] and cfg["lr"] == 1e-3 and cfg["source"] == "config"


class FakeTracker:
    experiment_name = "liverforce-test-studies"

    def __init__(self):
        self.runs = {}

    def start_run(self, name, params=None, tags=None, parent_run_id=None):
        rid = f"run{len(self.runs)}"
        self.runs[rid] = {"name": name, "params": params, "tags": tags, "metrics": {}}
        return rid

    def log_metrics(self, run_id, metrics, step=0):
        self.runs[run_id]["metrics"].update(metrics)

    def end_run(self, run_id, status="FINISHED"):
        self.runs[run_id]["status"] = status


def test_run_study_logs_one_run_per_point_and_records_failures(data, tmp_path):
    arrays, surfaces = data
    cfg = {
        "enabled": True, "epochs": 5, "hyper_parameters": "config",
        "occlusion": {"enabled": True, "scenarios": ["II"], "radii_mm": [0.0, 500.0], "encoders": ["pca"],
                      "modes": ["noise", "remove"]},
    }
    tracker = FakeTracker()
    doc = run_study("occlusion", cfg, {"II": arrays}, MODEL, {"II": None},
                    {"lr": 3e-3, "batch_size": 32, "test_fraction": 0.25, "seed": 0}, seed=0, tracker=tracker)
    ok, noise500, same, failed = doc["points"]
    assert ok["status"] == "ok" and noise500["status"] == "ok" and failed["status"] == "failed"
    assert "occlusion" in failed["reason"]  # a 500 mm radius hides the whole ROI: recorded, not fatal
    # radius 0 is the same model in both modes: trained once, reported (and logged) under both labels
    assert same["same_as"] == "pca/noise/0mm" and same["label"] == "pca/remove/0mm"
    assert same["metrics"] == ok["metrics"] and "same_as" not in ok
    # hiding the whole ROI behind noise leaves nothing to learn from: worse than seeing it
    assert noise500["metrics"]["mae_vec"] > ok["metrics"]["mae_vec"]
    assert len(tracker.runs) == 4
    run = tracker.runs[ok["run_id"]]
    assert run["tags"]["study"] == "occlusion" and run["tags"]["value"] == "0.0" and run["tags"]["scenario"] == "II"
    assert run["metrics"]["accuracy_pct"] == ok["metrics"]["accuracy_pct"]
    assert tracker.runs[failed["run_id"]]["status"] == "FAILED"
    png = plot_study(doc, tmp_path / "occlusion.png")
    assert png.stat().st_size > 5000
    json.dumps(doc)  # the study document is JSON-serialisable as written
