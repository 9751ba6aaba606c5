"""Camera-cloud models (roi_features: cloud): trained on observed clouds, served from a cloud and the tool tip.

No test here gives the model node ids: prediction arrays carry the pre-operative context, an
unordered cloud and the tool tip only (``_camera_inputs``).
"""

from __future__ import annotations

from dataclasses import replace as dataclasses_replace

import numpy as np
import pytest

from liverforce.learn import camera
from liverforce.learn.frames import force_to_local, local_rotations
from liverforce.learn.model import ForceModel, eval_seed, fit_force_model, prepare, subset, view_seeds
from liverforce.learn.observation import ObservationConfig, observe
from liverforce.learn.regressor import FitParams
from liverforce.learn.representation import representation_from_config
from liverforce.learn.synthetic import random_rotation, rigid_motion, synthetic_surface_arrays

CAMERA = {"observation": {"n_points": [300, 3000], "noise_sd_mm": 0.3, "tool_radius_mm": 2.5},
          "grid": {}, "tip_noise_mm": 0.1}
MODEL = {"grid_size": 8, "roi_features": "cloud", "camera": CAMERA, "occlusion": {"radius_mm": 0.0},
         "noise_mm": 0.0}
PRE_OP = ("exertion_point_mm", "frame_normal", "frame_t1", "frame_t2", "roi_undeformed_mm",
          "roi_centroid_undeformed_mm", "liver_centroid_mm", "inertia_mm5", "tool_thickness_mm",
          "probe_compliance_mm_per_n", "material_params_mpa", "case_id", "roi_triangles")


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    arrays = synthetic_surface_arrays(260, n_geometries=2, seed=3, material_varies=True)
    tr, te = np.arange(200), np.arange(200, 260)
    a_tr, a_te = subset(arrays, tr), subset(arrays, te)
    rep = representation_from_config(MODEL, a_tr)
    prep = prepare(a_tr, rep, observation_seeds=view_seeds(5, 2))
    model, _ = fit_force_model(prep, rep, encoder="pca", code_size=8, use_state=True, hidden=[64, 64], dropout=0.0,
                               fit=FitParams(epochs=150, lr=2e-3, batch_size=32), seed=1, force_scaling="stiffness",
                               linear_force_radius_mm=5.0)
    path = model.save(tmp_path_factory.mktemp("cam") / "model")
    return ForceModel.load(path), a_te


def _camera_inputs(arrays: dict, clouds, tips) -> dict:
    """What surgery has: pre-operative context, an unordered cloud, the tool tip. No node ids, no displacements."""
    out = {k: arrays[k] for k in PRE_OP}
    out["camera_cloud_mm"] = list(clouds)
    out["tool_tip_mm"] = np.asarray(tips, dtype=np.float64)
    return out


def _new_clouds(arrays: dict, config: ObservationConfig, seed: int, tip_noise: float = 0.1):
    """Each test case's deformed surface observed again: another camera, density and noise, points shuffled."""
    rng = np.random.default_rng(seed)
    clouds, tips = [], []
    for i in range(len(arrays["case_id"])):
        V, T = arrays["surface_meshes"][arrays["geometry_id"][i]]
        u = np.asarray(arrays["surface_displacement_mm"][i], dtype=np.float64)
        p = arrays["exertion_point_mm"][i]
        k = int(np.argmin(np.linalg.norm(V - p, axis=1)))
        tip = p + u[k]  # the exertion point is a surface vertex here
        c, _ = observe(V + u, T, tip, arrays["frame_normal"][i], config, seed=[seed, i])
        clouds.append(c[rng.permutation(len(c))])
        tips.append(tip + rng.normal(0.0, tip_noise, 3))
    return clouds, np.array(tips)


def test_camera_model_learns_the_force_without_node_ids(trained):
    model, a_te = trained
    true = np.asarray(a_te["force_n"])
    pred = model.predict(a_te, observation_seed=eval_seed(5))
    mae = float(np.linalg.norm(pred - true, axis=1).mean())
    mean_force = float(np.linalg.norm(true, axis=1).mean())
    assert mae < 0.12 * mean_force, (mae, mean_force)
    # the features hold no correspondence: a representation of this kind never reads roi_deformed_mm
    no_nodes = {k: v for k, v in a_te.items() if k not in ("roi_deformed_mm", "roi_centroid_deformed_mm")}
    assert np.allclose(model.predict(no_nodes, observation_seed=eval_seed(5)), pred)


def test_a_cloud_from_another_camera_gives_the_same_force_within_the_models_error(trained):
    model, a_te = trained
    true = np.asarray(a_te["force_n"])
    ref = model.predict(a_te, observation_seed=eval_seed(5))  # the training-time observation model
    cfg = ObservationConfig(n_points=(8000, 8000), noise_sd_mm=0.5, cone_half_angle_deg=30.0, tool_radius_mm=2.5,
                            roi_radius_mm=camera.observation_config(CAMERA, model.representation.half_width_mm,
                                                                    model.representation.grid_size).roi_radius_mm)
    clouds, tips = _new_clouds(a_te, cfg, seed=11)
    got = model.predict(_camera_inputs(a_te, clouds, tips))
    own_error = float(np.linalg.norm(ref - true, axis=1).mean())
    shift = np.linalg.norm(got - ref, axis=1)
    assert float(np.median(shift)) <= own_error, (np.median(shift), own_error)
    assert float(np.linalg.norm(got - true, axis=1).mean()) < 1.5 * own_error


def test_point_order_and_duplicates_do_not_change_the_force(trained):
    model, a_te = trained
    a = subset(a_te, np.arange(5))
    cfg = camera.observation_config(CAMERA, model.representation.half_width_mm, model.representation.grid_size)
    clouds, tips = _new_clouds(a, cfg, seed=2)
    f1 = model.predict(_camera_inputs(a, clouds, tips))
    rng = np.random.default_rng(0)
    shuffled = [np.concatenate([c, c[:50]])[rng.permutation(len(c) + 50)] for c in clouds]
    assert np.allclose(model.predict(_camera_inputs(a, shuffled, tips)), f1, atol=1e-9)


def test_rigid_motion_of_cloud_surface_and_tip_leaves_the_local_force_unchanged(trained):
    model, a_te = trained
    a = subset(a_te, np.arange(8))
    cfg = camera.observation_config(CAMERA, model.representation.half_width_mm, model.representation.grid_size)
    clouds, tips = _new_clouds(a, cfg, seed=4)
    Q, c = random_rotation(np.random.default_rng(9)), np.array([40.0, -25.0, 300.0])
    moved = rigid_motion(a, Q, c)
    f = model.predict(_camera_inputs(a, clouds, tips))
    g = model.predict(_camera_inputs(moved, [x @ Q.T + c for x in clouds], tips @ Q.T + c))
    R = local_rotations(a["frame_normal"], a["frame_t1"], a["frame_t2"])
    Rm = local_rotations(moved["frame_normal"], moved["frame_t1"], moved["frame_t2"])
    assert np.allclose(force_to_local(f, R), force_to_local(g, Rm), atol=1e-6)
    assert np.allclose(g, f @ Q.T, atol=1e-6)


def test_the_tool_tip_drives_the_linear_force_estimate(trained):
    """f_lin = C^-1 (tip displacement): the tip is the one point a camera model knows in correspondence."""
    model, a_te = trained
    assert model.pre.linear_force_tip and model.pre.linear_force_weights is None
    a = subset(a_te, np.arange(3))
    x = model.representation.features_of(a, observation_seed=1)
    from liverforce.learn.state import state_vector

    s = state_vector(model.representation.state_arrays(a))
    f_lin = model.pre.linear_force(x, s)
    C = np.asarray(a["probe_compliance_mm_per_n"]).reshape(-1, 3, 3)
    assert np.allclose(np.einsum("nij,nj->ni", C, f_lin), x[:, -3:])


def test_a_camera_model_refuses_to_predict_without_a_cloud_or_a_seed(trained):
    model, a_te = trained
    a = {k: a_te[k] for k in PRE_OP}
    with pytest.raises(ValueError, match="camera clouds"):
        model.predict(a)
    with pytest.raises(KeyError, match="tool_tip_mm"):
        model.predict({**a, "camera_cloud_mm": [np.zeros((10, 3))] * len(a["case_id"])})


def test_the_bundle_records_the_camera_settings(trained):
    model, _ = trained
    d = model.representation.to_dict()
    assert d["features"] == "cloud" and d["camera"]["observation"]["n_points"] == [300, 3000]
    assert d["camera"]["tip_noise_mm"] == 0.1
    cam = model.meta["training_scale"]["camera"]
    assert 0 < cam["valid_fraction"][0] <= cam["valid_fraction"][1] <= 1
    assert cam["tip_displacement_max_mm"] > 0


def test_a_camera_bundle_of_format_6_keeps_the_reference_it_was_trained_with(trained, tmp_path):
    """Bundles written before the patch reference read the pre-operative height over the ROI points; loading
    one must not switch it to the triangles (a reader would need inputs it never had and give other forces)."""
    import json
    import shutil

    model, a_te = trained
    assert model.representation.camera_reference == "surface" and "roi_triangles" in model.required_inputs()
    src = tmp_path / "new"
    model.save(src)
    old = tmp_path / "old"
    shutil.copytree(src, old)
    doc = json.loads((old / "model.json").read_text())
    doc["format_version"] = 6
    doc["representation"]["camera"]["grid"].pop("reference", None)
    (old / "model.json").write_text(json.dumps(doc))
    legacy = ForceModel.load(old)
    assert legacy.representation.camera_reference == "points"
    assert "roi_triangles" not in legacy.required_inputs()
    a = subset(a_te, np.arange(4))
    clouds, tips = camera.observe_cases(a, CAMERA, model.representation.half_width_mm,
                                        model.representation.grid_size, 9)
    inputs = _camera_inputs(a, clouds, tips)
    without = {k: v for k, v in inputs.items() if k != "roi_triangles"}
    f_old = legacy.predict(without)
    assert np.isfinite(f_old).all()
    # the points' reference of the same features, computed by hand: what the old reader computed
    from liverforce.learn.cloud_features import ReferenceSurface, cloud_grid
    from liverforce.learn.frames import case_rotations

    spec = camera.grid_spec(model.representation.grid_size, model.representation.half_width_mm,
                            legacy.representation.camera)
    assert spec.reference == "points"
    R = case_rotations(a)
    ref = ReferenceSurface.from_rotation(a["roi_undeformed_mm"][0], a["exertion_point_mm"][0], R[0], spec)
    x = legacy.representation.features_of(without, observation_seed=None)[0]
    assert np.array_equal(x[:-3], cloud_grid(clouds[0], ref, spec).features(include_mask=True))
    # the new model refuses the inputs without the triangles, naming them
    with pytest.raises(KeyError, match="roi_triangles"):
        model.predict(without)


def test_tip_noise_along_the_normal_and_along_the_surface_apart(trained):
    """camera.tip_noise_normal_mm: the tool tip's error splits into its normal and tangential parts, each with its
    own sd, from the same seeded draw; null keeps the isotropic noise bit for bit."""
    model, a_te = trained
    a = subset(a_te, np.arange(40))
    hw, g = model.representation.half_width_mm, model.representation.grid_size
    exact = camera.observe_cases(a, {**CAMERA, "tip_noise_mm": 0.0}, hw, g, 9)[1]
    iso = camera.observe_cases(a, {**CAMERA, "tip_noise_mm": 0.5}, hw, g, 9)[1]
    same = camera.observe_cases(a, {**CAMERA, "tip_noise_mm": 0.5, "tip_noise_normal_mm": None}, hw, g, 9)[1]
    assert np.array_equal(iso, same)
    n = np.asarray(a["frame_normal"], float)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)

    def parts(tips):
        e = tips - exact
        e_n = np.einsum("ij,ij->i", e, n)
        return e_n, np.linalg.norm(e - e_n[:, None] * n, axis=1)

    e_n, e_t = parts(camera.observe_cases(a, {**CAMERA, "tip_noise_mm": 0.0, "tip_noise_normal_mm": 0.5}, hw, g, 9)[1])
    assert np.all(e_t < 1e-9) and 0.3 < np.std(e_n) < 0.7  # only along the normal
    e_n2, e_t2 = parts(camera.observe_cases(a, {**CAMERA, "tip_noise_mm": 0.5, "tip_noise_normal_mm": 0.0}, hw, g, 9)[1])
    assert np.all(np.abs(e_n2) < 1e-9) and 0.3 < np.sqrt(np.mean(e_t2**2) / 2) < 0.7  # only along the surface
    # the same draw: the isotropic error is the sum of the two parts
    iso_n, iso_t = parts(iso)
    np.testing.assert_allclose(iso_n, e_n, atol=1e-12)
    np.testing.assert_allclose(iso_t, e_t2, atol=1e-12)


def test_the_tip_noise_sensitivity_is_isotropic_whatever_the_model_was_trained_with(trained, tmp_path):
    """validate's camera sensitivity sweeps tip_noise_mm as the same sd in every direction: a model trained with
    tip_noise_normal_mm gives the same rows as one without it (at 0 mm: an exact tip, not its normal noise)."""
    import json

    from liverforce.pipeline.validate import camera_sensitivity

    model, a_te = trained
    a = subset(a_te, np.arange(12))
    plain = model.save(tmp_path / "plain")
    aniso = model.save(tmp_path / "aniso")
    doc = json.loads((aniso / "model.json").read_text())
    doc["representation"]["camera"]["tip_noise_normal_mm"] = 0.7
    (aniso / "model.json").write_text(json.dumps(doc))
    grid = {"tip_noise_mm": [0.0, 0.5]}
    got, want = camera_sensitivity(aniso, a, grid), camera_sensitivity(plain, a, grid)
    assert got["model_settings"]["tip_noise_normal_mm"] == 0.7
    assert got["tip_noise_mm"] == want["tip_noise_mm"]
    # a tilted tool: a row per angle; a range is not a setting's value
    tilt = camera_sensitivity(plain, a, {"tool_tilt_deg": [0.0, 20.0]})["tool_tilt_deg"]
    assert [r["value"] for r in tilt] == [0.0, 20.0] and all(np.isfinite(r["mae_vec"]) for r in tilt)
    with pytest.raises(ValueError, match="tool_tilt_deg: each value is one number"):
        camera_sensitivity(plain, a, {"tool_tilt_deg": [[0.0, 30.0]]})
    # gross depth errors: the row at 0 is the model's own camera; 20 % of the points off costs more than none
    gross = camera_sensitivity(plain, a, {"outlier_fraction": [0.0, 0.2]})["outlier_fraction"]
    own = camera_sensitivity(plain, a, {"tip_noise_mm": [model.representation.camera["tip_noise_mm"]]})
    assert gross[0]["mae_vec"] == own["tip_noise_mm"][0]["mae_vec"]
    assert gross[1]["mae_vec"] > gross[0]["mae_vec"]


def test_the_registration_rows_score_the_model_off_and_refined(trained, tmp_path):
    """validate's registration rows: with the camera side moved off the pre-operative surface the model's error
    grows; refined from the unloaded view it is the well-registered error again; a correction beyond a
    refinement is refused and counted, not scored."""
    from liverforce.pipeline.validate import registration_sensitivity

    model, a_te = trained
    a = subset(a_te, np.arange(16))
    path = model.save(tmp_path / "m")
    rows = registration_sensitivity(path, a, [[0.0, 0.0], [2.0, 2.0], [30.0, 0.0]])["rows"]
    base, off, far = rows
    assert base["refined"]["n_refused"] == 0 and off["refined"]["n_refused"] == 0
    assert base["refined"]["anchors"] == {"contact tip": 16}  # this model fits no instrument
    assert off["as_registered"]["mae_vec"] > 3 * base["as_registered"]["mae_vec"]
    assert abs(off["refined"]["mae_vec"] - base["as_registered"]["mae_vec"]) < 0.25 * base["as_registered"]["mae_vec"]
    assert abs(base["refined"]["mae_vec"] - base["as_registered"]["mae_vec"]) < 0.25 * base["as_registered"]["mae_vec"]
    assert far["refined"] == {"n_refused": 16, "anchors": {}}  # 30 mm: beyond a refinement, every case refused
    assert registration_sensitivity(path, a, []) is None


def test_the_shape_rows_score_the_model_on_livers_changed_since_the_scan(trained, tmp_path):
    """validate's shape rows: each liver's surface changed by a smooth field since its scan, the model scored as
    the camera sees it, refined rigidly and refined with the change of shape; with no change the rows are the
    registration rows' well-registered ones."""
    from liverforce.pipeline.validate import registration_sensitivity, shape_sensitivity

    model, a_te = trained
    a = subset(a_te, np.arange(16))
    path = model.save(tmp_path / "m")
    base, bent = shape_sensitivity(path, a, [[0.0, 150.0], [4.0, 150.0]])["rows"]
    reg = registration_sensitivity(path, a, [[0.0, 0.0]])["rows"][0]
    assert base["as_registered"] == reg["as_registered"] and base["refined"]["n_refused"] == 0
    assert base["refined"] == reg["refined"]  # the same refinement as the registration rows'
    assert base["rigid"]["n_refused"] == 0  # with no change, the change of shape fitted to noise costs little:
    assert abs(base["refined"]["mae_vec"] - base["rigid"]["mae_vec"]) < 0.15 * base["rigid"]["mae_vec"]  # 0.189, 0.175
    assert (base["amplitude_mm"], bent["wavelength_mm"]) == (0.0, 150.0)
    assert bent["as_registered"]["mae_vec"] > 2 * base["as_registered"]["mae_vec"]  # the change was there
    for k in ("rigid", "refined"):
        assert bent[k]["n_refused"] < 16 and bent[k]["mae_vec"] < bent["as_registered"]["mae_vec"]
    assert bent["refined"]["mae_vec"] < bent["rigid"]["mae_vec"]  # 0.173 against 0.199 N here (2.07 as seen)
    assert shape_sensitivity(path, a, []) is None


def test_exact_tip_scores_the_same_clouds_with_the_true_tool_tip(trained):
    """train's exact-tip accuracy: the fitted model and the clouds unchanged, the tool tip without its kinematics
    noise in any direction (exact_tip also drops a split of the noise along the normal)."""
    from liverforce.learn.metrics import force_metrics
    from liverforce.learn.train import exact_tip_metrics

    model, a_te = trained
    a = subset(a_te, np.arange(30))
    hw, g = model.representation.half_width_mm, model.representation.grid_size
    seed = eval_seed(5)
    noisy = {**CAMERA, "tip_noise_mm": 0.5, "tip_noise_normal_mm": 0.2}
    exact = camera.exact_tip(noisy)
    assert exact["tip_noise_mm"] == 0.0 and exact["tip_noise_normal_mm"] is None
    assert exact["observation"] == noisy["observation"] and noisy["tip_noise_mm"] == 0.5  # a copy
    c_noisy, t_noisy = camera.observe_cases(a, noisy, hw, g, seed)
    c_exact, t_exact = camera.observe_cases(a, exact, hw, g, seed)
    assert all(np.array_equal(x, y) for x, y in zip(c_noisy, c_exact))  # the same clouds
    assert np.abs(t_noisy - t_exact).max() > 0.1
    # the true tip: the exertion point moved with the surface (a surface vertex in these cases)
    for i in range(len(t_exact)):
        V = a["surface_meshes"][a["geometry_id"][i]][0]
        k = int(np.argmin(np.linalg.norm(V - a["exertion_point_mm"][i], axis=1)))
        np.testing.assert_allclose(t_exact[i], a["exertion_point_mm"][i] + a["surface_displacement_mm"][i][k],
                                   atol=1e-9)
    # exact_tip_metrics = the model's metrics from those clouds and the true tips, given as camera inputs
    got = exact_tip_metrics(model, a, 5)["exact_tip"]
    want = force_metrics(np.asarray(a["force_n"], float),
                         model.predict(_camera_inputs(a, *camera.observe_cases(a, camera.exact_tip(CAMERA), hw, g,
                                                                               seed))))
    assert got == pytest.approx(want, rel=1e-9)
    assert got["mae_vec"] != pytest.approx(force_metrics(np.asarray(a["force_n"], float),
                                                         model.predict(a, observation_seed=seed))["mae_vec"])
    with pytest.raises(ValueError, match="not a camera-cloud model"):
        ForceModel(dataclasses_replace(model.representation, features="displacement", camera=None), model.pre,
                   model.regressor_spec, model.regressor).observed_with(CAMERA)
