"""Force scaling by the material's stiffness: constants x k move the prediction as hyperelasticity does.

Scaling every constant of a strain energy by k scales the stress at a given
deformation by k; equivalently the same force on a k-times stiffer liver gives
a k-times smaller displacement. The synthetic cases follow exactly that law
(displacement = compliance x force / stiffness), so a model that respects it
holds outside the training range of the constants (here +-30 %).

``stiffness`` scales the predicted force by k (exactly, by construction);
``linear`` (the default) scales the linear force estimate C^-1 u_w by k, so
that input is the same for the same force on any stiffness, and leaves what
does not scale (the supports' springs in FE) to the regressor.
"""

import numpy as np
import pytest

from liverforce.learn.metrics import force_metrics
from liverforce.learn.model import FORMAT_VERSION, ForceModel
from liverforce.learn.synthetic import synthetic_arrays
from liverforce.learn.train import train_scenario

MODEL = {
    "encoder": "pca", "code_size": 3, "state_vector": True, "grid_size": 8, "hidden": [64, 64],
    "dropout": 0.0, "occlusion": {"radius_mm": 0.0, "mode": "remove"}, "noise_mm": 0.0,
}
TRAIN = {"test_fraction": 0.2, "epochs": 150, "batch_size": 32, "lr": 3e-3, "weight_decay": 0.0, "seed": 0}
NO_TUNE = {"enabled": False, "trials": 1, "folds": 2, "sobol_trials": 1, "epochs": 1}


@pytest.fixture(scope="module")
def data():
    return synthetic_arrays(300, seed=5, nodes=(200, 260), dent_width_mm=12.0, material_varies=True)


@pytest.fixture(scope="module")
def models(data, tmp_path_factory):
    out = {}
    for scaling in ("stiffness", "none"):
        res = train_scenario(data, {**MODEL, "force_scaling": scaling}, TRAIN, NO_TUNE, "III", scaling,
                             out_dir=tmp_path_factory.mktemp(scaling))
        out[scaling] = ForceModel.load(res["model_path"])
    for scaling in ("linear", "none"):  # with the linear force estimate C^-1 u_w (the tool's radius)
        res = train_scenario(data, {**MODEL, "force_scaling": scaling, "probe_force_radius_mm": 5.0, "regressor": "gp",
                                    "gp": {"max_points": 2000, "iterations": 200}}, TRAIN, NO_TUNE,
                             "III", f"{scaling}_lin", out_dir=tmp_path_factory.mktemp(f"{scaling}_lin"))
        out[f"{scaling}_lin"] = ForceModel.load(res["model_path"])
    res = train_scenario(data, {**MODEL, "force_scaling": "linear", "probe_force_radius_mm": 5.0, "regressor": "gp",
                                "indentation_strain": True, "gp": {"max_points": 2000, "iterations": 100}},
                         TRAIN, NO_TUNE, "III", "strain", out_dir=tmp_path_factory.mktemp("strain"))
    out["linear_strain"] = ForceModel.load(res["model_path"])
    return out


def stiffer(arrays: dict, k: float) -> dict:
    """The same cases on a liver whose constants are all x k: the same force, displacements / k."""
    out = dict(arrays)
    out["material_params_mpa"] = np.asarray(arrays["material_params_mpa"]) * k
    out["roi_deformed_mm"] = [u + (d - u) / k for u, d in zip(arrays["roi_undeformed_mm"], arrays["roi_deformed_mm"])]
    c_u, c_d = np.asarray(arrays["roi_centroid_undeformed_mm"]), np.asarray(arrays["roi_centroid_deformed_mm"])
    out["roi_centroid_deformed_mm"] = c_u + (c_d - c_u) / k
    return out


@pytest.mark.parametrize("k", [0.5, 0.8, 1.25, 2.0])
def test_constants_times_k_scale_the_prediction_by_k_at_the_same_deformation(models, data, k):
    model = models["stiffness"]
    base = model.predict(data)
    scaled = dict(data, material_params_mpa=np.asarray(data["material_params_mpa"]) * k)
    np.testing.assert_allclose(model.predict(scaled), k * base, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("k", [0.5, 2.0])
def test_stiffness_scaled_model_holds_outside_the_training_range(models, data, k):
    """Constants x0.5 / x2 (the training range is x0.7..x1.3): the scaled model keeps its accuracy."""
    shifted = stiffer(data, k)
    true = np.asarray(data["force_n"], dtype=float)
    acc = {s: force_metrics(true, m.predict(shifted))["accuracy_pct"] for s, m in models.items()}
    inside = force_metrics(true, models["stiffness"].predict(data))["accuracy_pct"]
    assert acc["stiffness"] > 90.0, (acc, inside)
    assert acc["none"] < acc["stiffness"] - 10.0, acc  # without it the model extrapolates badly


def test_compiled_fast_path_applies_the_same_scaling(models, data):
    from liverforce.serve.compiled import CompiledROI
    from liverforce.serve.preop import Preop

    model = models["stiffness"]
    i = 0
    case = {k: v[i:i + 1] for k, v in data.items()}
    comp = CompiledROI(model, Preop.from_arrays(data, i))
    D = np.asarray(data["roi_deformed_mm"][i], dtype=float)
    ref = model.predict(case)[0]
    np.testing.assert_allclose(comp.predict(D), ref, atol=1e-5)
    mat = np.asarray(data["material_params_mpa"][i]) * 1.7
    comp.with_material(mat)
    ref2 = model.predict(dict(case, material_params_mpa=mat[None]))[0]
    np.testing.assert_allclose(ref2, 1.7 * ref, rtol=1e-9)
    np.testing.assert_allclose(comp.predict(D), ref2, atol=1e-5)


@pytest.mark.parametrize("k", [0.5, 1.25, 2.0])
def test_linear_scaling_scales_the_linear_force_estimate_by_k_and_keeps_the_constants(models, data, k):
    """force_scaling: linear: constants x k multiply f_lin = C^-1 u_w by k exactly, enter the state as they are
    (MPa, not ratios) and leave the target unscaled."""
    pre = models["linear_lin"].pre
    assert pre.stiffness_ref is None and pre.linear_force_ref is not None
    rep = models["linear_lin"].representation
    from liverforce.learn.model import prepare
    from liverforce.learn.state import MATERIAL_START as M

    prep = prepare(data, rep, observation_seeds=[0])
    x, st = prep.x_obs[0], prep.state
    st_k = st.copy()
    st_k[:, M:] *= k  # the constants
    base, scaled = pre.state_features(st, x), pre.state_features(st_k, x)
    np.testing.assert_allclose(scaled[:, -3:], k * base[:, -3:], rtol=1e-12)
    np.testing.assert_allclose(scaled[:, M:-3], k * base[:, M:-3], rtol=1e-12)  # raw constants, not ratios
    np.testing.assert_allclose(pre.stiffness(st_k, len(st_k)), 1.0)
    np.testing.assert_allclose(pre.material_factor(st_k, len(st_k)), k * pre.material_factor(st, len(st)), rtol=1e-12)


@pytest.mark.parametrize("k", [0.5, 2.0])
def test_linear_scaled_model_holds_outside_the_training_range(models, data, k):
    """Constants x0.5 / x2 with the same forces: the f_lin input is unchanged (u / k times k), so the linear
    model stays accurate where the same model without the scaling does not."""
    shifted = stiffer(data, k)
    true = np.asarray(data["force_n"], dtype=float)
    acc = {s: force_metrics(true, models[s].predict(shifted))["accuracy_pct"] for s in ("linear_lin", "none_lin")}
    assert acc["linear_lin"] > 90.0, acc
    assert acc["none_lin"] < acc["linear_lin"] - 10.0, acc


def test_compiled_fast_path_applies_the_linear_scaling(models, data):
    """The compiled ROI path gives the reference prediction of a linear-scaled model, also after with_material
    and with a material per row."""
    from liverforce.serve.compiled import CompiledROI
    from liverforce.serve.preop import Preop

    model = models["linear_lin"]
    i = 3
    case = {key: v[i:i + 1] for key, v in data.items()}
    comp = CompiledROI(model, Preop.from_arrays(data, i))
    D = np.asarray(data["roi_deformed_mm"][i], dtype=float)
    np.testing.assert_allclose(comp.predict(D), model.predict(case)[0], atol=1e-5)
    mat = np.asarray(data["material_params_mpa"][i]) * 1.2
    ref2 = model.predict(dict(case, material_params_mpa=mat[None]))[0]
    assert not np.allclose(ref2, model.predict(case)[0], atol=1e-3)  # the material moves the prediction
    np.testing.assert_allclose(comp.with_material(mat).predict(D), ref2, atol=1e-5)
    mats = np.stack([mat, mat / 1.2 * 0.8])
    rows = comp.predict_batch(np.stack([D, D]), material_params_mpa=mats)
    for r, m in zip(rows, mats):
        np.testing.assert_allclose(r, model.predict(dict(case, material_params_mpa=m[None]))[0], atol=1e-5)


def test_the_indentation_strain_is_the_normal_displacement_under_the_tool_over_the_thickness(models, data, tmp_path):
    """model.indentation_strain: the state features end with u_w,n / h (after f_lin), the same for every material,
    and the flag survives save/load (a bundle of format 5)."""
    import json

    from liverforce.learn.model import prepare
    from liverforce.learn.state import MATERIAL_START as M
    from liverforce.learn.state import THICKNESS_COLUMN

    model = models["linear_strain"]
    pre = model.pre
    assert pre.indentation_strain and pre.n_displacement_features == 4
    assert pre.n_material == np.asarray(data["material_params_mpa"]).shape[1]
    prep = prepare(data, model.representation, observation_seeds=[0])
    x, st = prep.x_obs[0], prep.state
    feats = pre.state_features(st, x)
    w = pre.linear_force_weights
    g2 = w.size
    u_n = x[:, 2 * g2:3 * g2] @ w  # the normal channel under the tool, by hand
    np.testing.assert_allclose(feats[:, -1], u_n / st[:, THICKNESS_COLUMN], rtol=1e-12)
    assert np.all(feats[:, -1] < 0)  # the tool pushes into the liver
    np.testing.assert_allclose(feats[:, -4:-1], pre.linear_force(x, st), rtol=1e-12)
    st_k = st.copy()
    st_k[:, M:] *= 1.7
    np.testing.assert_allclose(pre.state_features(st_k, x)[:, -1], feats[:, -1], rtol=1e-12)
    thin = st.copy()
    thin[:, THICKNESS_COLUMN] /= 2
    np.testing.assert_allclose(pre.state_features(thin, x)[:, -1], 2 * feats[:, -1], rtol=1e-12)
    saved = model.save(tmp_path / "m")
    assert json.loads((saved / "model.json").read_text())["format_version"] == FORMAT_VERSION
    again = ForceModel.load(saved)
    assert again.pre.indentation_strain
    np.testing.assert_array_equal(again.predict(data), model.predict(data))


def test_compiled_fast_path_reads_the_indentation_strain(models, data):
    """The compiled ROI path gives the reference prediction of a model with the indentation strain, also with a
    material per row (the strain does not move with it, f_lin does)."""
    from liverforce.serve.compiled import CompiledROI
    from liverforce.serve.preop import Preop

    model = models["linear_strain"]
    for i in (1, 4):
        case = {key: v[i:i + 1] for key, v in data.items()}
        comp = CompiledROI(model, Preop.from_arrays(data, i))
        U = np.asarray(data["roi_undeformed_mm"][i], dtype=float)
        D = np.asarray(data["roi_deformed_mm"][i], dtype=float)
        deeper = U + 1.5 * (D - U)
        for Di in (D, deeper):
            np.testing.assert_allclose(comp.predict(Di), model.predict(dict(case, roi_deformed_mm=[Di],
                                                                            roi_centroid_deformed_mm=Di.mean(0)[None]))[0],
                                       atol=1e-5)
        mat = np.asarray(data["material_params_mpa"][i])
        mats = np.stack([mat * 1.2, mat * 0.8])
        rows = comp.predict_batch(np.stack([D, D]), material_params_mpa=mats)
        for r, m in zip(rows, mats):
            np.testing.assert_allclose(r, model.predict(dict(case, material_params_mpa=m[None]))[0], atol=1e-5)
        np.testing.assert_allclose(comp.with_material(mats[0]).predict(D), rows[0], atol=1e-5)


def test_a_version_4_bundle_with_the_linear_force_estimate_still_loads(models, data, tmp_path):
    """A bundle written before the indentation strain (format 4: no such key, the state features end with f_lin)
    loads with the same number of material constants and predicts exactly as before."""
    import json

    model = models["linear_lin"]
    assert not model.pre.indentation_strain and model.pre.n_linear_force == 3
    path = model.save(tmp_path / "m")
    doc = json.loads((path / "model.json").read_text())
    del doc["scalers"]["indentation_strain"]
    doc["format_version"] = 4
    (path / "model.json").write_text(json.dumps(doc))
    old = ForceModel.load(path)
    assert not old.pre.indentation_strain and old.pre.n_displacement_features == 3
    assert old.pre.n_material == model.pre.n_material == np.asarray(data["material_params_mpa"]).shape[1]
    np.testing.assert_array_equal(old.predict(data), model.predict(data))


def test_the_stiffness_factor_of_the_interval_does_not_depend_on_the_force_scaling(models, data, tmp_path):
    """The interval widens outside its calibration's stiffness range by k = C10 / C10_ref: a model with
    force_scaling none has that k too (format 9; the camera variant uses none), equal to the scaled models' k, and
    it survives the bundle. A format-8 bundle of such a model had no reference: it keeps k = 1, as it was written."""
    import json

    from liverforce.learn.model import prepare
    from liverforce.learn.state import MATERIAL_START as M

    none, lin = models["none_lin"], models["linear_lin"]
    assert none.pre.stiffness_ref is None and none.pre.linear_force_ref is None
    assert none.pre.material_ref == pytest.approx(lin.pre.linear_force_ref, rel=1e-12)
    st = prepare(data, none.representation, observation_seeds=[0]).state
    k = none.pre.material_factor(st, len(st))
    np.testing.assert_allclose(k, lin.pre.material_factor(st, len(st)), rtol=1e-12)
    np.testing.assert_allclose(k[:, 0] * none.pre.material_ref, st[:, M], rtol=1e-12)  # C10 / its training mean
    assert k.min() < 0.9 and k.max() > 1.1  # the constants vary, so does k
    path = none.save(tmp_path / "none")
    np.testing.assert_array_equal(ForceModel.load(path).pre.material_factor(st, len(st)), k)
    doc = json.loads((path / "model.json").read_text())
    doc["format_version"] = 8
    del doc["scalers"]["material_ref"]
    (path / "model.json").write_text(json.dumps(doc))
    np.testing.assert_array_equal(ForceModel.load(path).pre.material_factor(st, len(st)), np.ones((len(st), 1)))
