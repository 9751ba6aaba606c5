"""The instrument in the camera cloud: observed (observation.instrument_in_cloud), found, fitted and dropped
(cloud_features.fit_instrument), and a camera model trained on such clouds.

A stereo camera sees the tool as well as the liver. Its shaft's points give the tool's axis, so the tip's
position along the surface, which the robot's kinematics give to about 0.5 mm only, comes from the camera.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from liverforce.learn.cloud_features import CloudGridSpec, ReferenceSurface, cloud_grid, fit_instrument
from liverforce.learn.observation import ObservationConfig, Tool, observe

R_TOOL = 2.5


def dent_surface(depth=3.0, width=6.0, half=40.0, n=81):
    """A plate at z = 0 with a Gaussian dent at the origin (the deformed surface), its flat twin (pre-operative)
    and the triangles (outward +z)."""
    x = np.linspace(-half, half, n)
    X, Y = np.meshgrid(x, x)
    Z = -depth * np.exp(-(X**2 + Y**2) / (2 * width**2))
    q = np.arange((n - 1) * n).reshape(n - 1, n)[:, : n - 1].ravel()
    T = np.concatenate([np.column_stack([q, q + 1, q + n + 1]), np.column_stack([q, q + n + 1, q + n])])
    return (np.column_stack([X.ravel(), Y.ravel(), Z.ravel()]),
            np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)]), T)


def obs(**kw):
    base = dict(n_points=(3000, 3000), noise_sd_mm=0.0, roi_radius_mm=30.0, tool_radius_mm=R_TOOL,
                instrument_in_cloud=True)
    return ObservationConfig(**{**base, **kw})


def spec(**kw):
    base = dict(grid_size=12, half_width_mm=20.0, kernel_radius_cells=1.5, instrument_radius_mm=R_TOOL,
                instrument_point_sd_mm=0.5, instrument_tip_sd_mm=0.5)
    return CloudGridSpec(**{**base, **kw})


def test_the_instrument_points_lie_on_the_tools_visible_surface_and_the_livers_points_are_unchanged():
    V, _, T = dent_surface()
    tip = np.array([0.0, 0.0, -3.0])
    cam = np.array([45.0, 20.0, 70.0])
    with_tool, rec = observe(V, T, tip, [0, 0, 1], obs(), seed=5, camera_position_mm=cam)
    alone, rec0 = observe(V, T, tip, [0, 0, 1], obs(instrument_in_cloud=False), seed=5, camera_position_mm=cam)
    k = len(alone)
    assert rec0.n_instrument_points == 0 and rec.n_instrument_points > 50
    assert len(with_tool) == k + rec.n_instrument_points == rec.n_points
    np.testing.assert_array_equal(with_tool[:k], alone)  # the liver's points: the same draw
    inst = with_tool[k:]
    tool = Tool.at_tip(tip, [0, 0, 1], R_TOOL, 150.0)
    dist = np.array([tool.distance(x) for x in inst])
    np.testing.assert_allclose(dist, 0.0, atol=1e-9)  # on the capsule's surface
    axial = inst[:, 2] - tool.centre[2]
    radial = inst[:, :2] / np.linalg.norm(inst[:, :2], axis=1, keepdims=True)
    normals = np.where((axial > 0)[:, None], np.column_stack([radial, np.zeros(len(inst))]),
                       (inst - tool.centre) / R_TOOL)
    assert (np.einsum("ij,ij->i", normals, cam - inst) > 0).all()  # facing the camera
    assert (np.linalg.norm(inst - tip, axis=1) <= 30.0 + 1e-9).all()  # within the ROI ball
    # uniform by area along the shaft: the shaft points' heights are uniform up to the ROI ball's edge
    shaft = axial[axial > 0]
    top = np.sqrt(30.0**2 - R_TOOL**2) - R_TOOL
    assert stats.kstest(shaft / top, "uniform").pvalue > 1e-3
    # at the liver's density: ten times the points, about ten times the instrument's
    _, rec10 = observe(V, T, tip, [0, 0, 1], obs(n_points=(30000, 30000)), seed=5, camera_position_mm=cam)
    assert 8.0 < rec10.n_instrument_points / rec.n_instrument_points < 12.0


def test_the_instrument_behind_the_liver_is_not_seen():
    V, _, T = dent_surface()
    V = V.copy()
    V[:, 2] += 40.0 * (V[:, 0] > 10.0)  # a wall of liver 40 mm high between the tool and a camera on the +x side
    tip = np.array([0.0, 0.0, -3.0])
    cfg = obs(require_tool_visible=False, roi_radius_mm=25.0)
    _, behind = observe(V, T, tip, [0, 0, 1], cfg, seed=2, camera_position_mm=[80.0, 0.0, 20.0])
    _, open_side = observe(V, T, tip, [0, 0, 1], cfg, seed=2, camera_position_mm=[-80.0, 0.0, 20.0])
    assert behind.n_points > 0 and behind.n_instrument_points == 0
    assert open_side.n_instrument_points > 50


def _shaft(centre, n, rng, sd=0.3, facing=0.0):
    """Points on the half of a shaft of radius R_TOOL around ``centre`` (u, v) facing ``facing`` (rad), at
    heights 3-20 mm above the surface, with noise."""
    phi = facing + rng.uniform(-np.pi / 2, np.pi / 2, n)
    uv = np.asarray(centre) + R_TOOL * np.column_stack([np.cos(phi), np.sin(phi)]) + rng.normal(0, sd, (n, 2))
    return uv, rng.uniform(3.0, 20.0, n)


def test_the_fit_finds_the_tools_axis_from_its_points_and_drops_them():
    from liverforce.learn.cloud_features import shaft_fit_radius

    rng = np.random.default_rng(0)
    true = np.array([0.7, -0.4])
    errs, sds = [], []
    for trial in range(20):
        uv, dz = _shaft(true, 60, rng, facing=rng.uniform(0, 2 * np.pi))
        surf = rng.uniform(-15, 15, (400, 2))
        surf = surf[np.hypot(*(surf - true).T) > R_TOOL]
        P = np.concatenate([uv, surf])
        Z = np.concatenate([dz, rng.normal(-0.5, 0.3, len(surf))])
        c, keep, n, sd = fit_instrument(P, Z, [0.0, 0.0], spec(instrument_point_sd_mm=0.3))
        errs.append(c - true)
        sds.append(sd)
        assert n >= 55  # the shaft's points (a few may be trimmed)
        assert not keep[: len(uv)].any()  # every shaft point dropped
        d = np.hypot(*(surf - c).T)
        rf = shaft_fit_radius(R_TOOL, 0.3)  # where the shaft's points stand through their noise
        far = (d >= rf + 1.0) & ((d >= rf + 1.0 + 2 * 0.3) | (Z[len(uv):] <= 0))
        np.testing.assert_array_equal(keep[len(uv):], far)  # the surface's kept beyond the clearance
    rms = np.sqrt(np.mean(np.square(errs), axis=0))
    assert (rms < 0.12).all(), rms  # the kinematic prior alone is 0.81 mm off here
    assert 0.3 / 1.25 < np.median(sds) < 0.3 * 1.25  # the cloud's noise from the shaft's points
    # an exact tracker: the prior wins; too few points: the kinematic tip
    uv, dz = _shaft(true, 60, rng)
    c, _, _, _ = fit_instrument(uv, dz, [0.0, 0.0], spec(instrument_tip_sd_mm=0.0))
    np.testing.assert_allclose(c, 0.0, atol=1e-3)
    c, keep, n, sd = fit_instrument(uv[:5], dz[:5], [0.0, 0.0], spec())
    assert n == 0 and (c == 0.0).all() and np.isnan(sd)
    # points low on the surface are not the instrument's, however near the axis: dropped within the clearance
    # (shaft_fit_radius(2.5, 0.5) = 2.553 + 1 mm), and within another 2 sd of the noise (1 mm) where they stand
    # above the pre-operative surface
    P = np.array([[3.2, 0.0], [4.0, 0.0], [4.0, 0.0], [4.6, 0.0]])
    c, keep, n, _ = fit_instrument(P, np.array([-0.5, -0.5, 0.5, 0.5]), [0.0, 0.0], spec())
    assert n == 0 and keep.tolist() == [False, True, False, True]


def _tilted_shaft(centre, slope, n, rng, sd=0.3):
    """Points (u, v, w) on the visible half of a shaft of radius R_TOOL whose axis passes through ``centre`` at
    height 0 with slope ``slope`` (direction (s_u, s_v, 1)), 3-20 mm up its axis, with noise."""
    a = np.array([slope[0], slope[1], 1.0])
    a /= np.linalg.norm(a)
    e1 = np.cross(a, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    phi = rng.uniform(0, 2 * np.pi) + rng.uniform(-np.pi / 2, np.pi / 2, n)
    t = rng.uniform(3.0, 20.0, n) / a[2]
    P = (np.array([centre[0], centre[1], 0.0]) + t[:, None] * a
         + R_TOOL * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2))
    return P + rng.normal(0.0, sd, P.shape)


def _tilted_scene(rng, tilt_lo_deg: float, tilt_hi_deg: float, n_surface: int):
    """A shaft (80 points) tilted uniformly in ``[tilt_lo_deg, tilt_hi_deg]`` towards a random azimuth, its axis
    through ``true`` (0.5 mm sd about the origin, the kinematic tip), and up to ``n_surface`` liver points on a flat
    surface round it (0.3 mm sd about -0.5 mm). Returns the shaft's points, every point's ``(u, v)`` and height
    (shaft first), ``true`` and the slope."""
    tilt = np.radians(rng.uniform(tilt_lo_deg, tilt_hi_deg))
    az = rng.uniform(0, 2 * np.pi)
    slope = np.tan(tilt) * np.array([np.cos(az), np.sin(az)])
    true = rng.normal(0.0, 0.5, 2)
    S = _tilted_shaft(true, slope, 80, rng)
    surf = rng.uniform(-15, 15, (n_surface, 2))
    surf = surf[np.hypot(*(surf - true).T) > R_TOOL + 1.0]
    return (S, np.concatenate([S[:, :2], surf]), np.concatenate([S[:, 2], rng.normal(-0.5, 0.3, len(surf))]), true,
            slope)


def test_a_tilted_shaft_is_fitted_with_its_slope_and_dropped():
    """instrument_max_tilt_deg: a shaft tilted 0-25 deg from the normal gives its axis (the tip: where the
    kinematic tip projects onto it) and the points' noise, and every one of its points is dropped; on a 20 deg
    shaft the fit that assumes the normal is off by a millimetre or more and leaves some of its points."""
    from liverforce.learn.cloud_features import fit_instrument_tilted

    rng = np.random.default_rng(4)
    sp = spec(instrument_point_sd_mm=0.3, instrument_max_tilt_deg=30.0)
    errs, sds = [], []
    for trial in range(24):
        S, uv, w, true, slope = _tilted_scene(rng, 0.0, 25.0, 800)
        dz = w + 0.0  # a flat pre-operative surface at the tip's height
        tip, keep, n, sd = fit_instrument_tilted(uv, w, dz, [0.0, 0.0, 0.0], sp)
        assert n >= 70 and not keep[: len(S)].any() and keep[len(S):].mean() > 0.97
        # the tip: the kinematic tip (the origin) projected onto the axis, near its projection onto the true one
        t = float(-true @ slope) / (1.0 + float(slope @ slope))
        errs.append(tip - np.array([true[0] + t * slope[0], true[1] + t * slope[1], t]))
        sds.append(sd)
    # the noise estimate (the MAD of about 80 points: about 12 % sd) per shaft, and its median over the shafts
    assert 0.3 / 1.4 < min(sds) and max(sds) < 0.3 * 1.4, sds
    assert 0.3 / 1.1 < np.median(sds) < 0.3 * 1.1, sds
    rms = np.sqrt(np.mean(np.square(errs), axis=0))
    assert (rms < 0.15).all(), rms  # the kinematic prior alone is 0.71 mm off (0.5 mm per coordinate)
    # a 20 deg shaft through the origin: the fit that assumes the normal puts the axis off by a millimetre or
    # more (its points lean away with height) and leaves some on the grid; the tilted fit drops them all
    S = _tilted_shaft([0.0, 0.0], np.tan(np.radians(20.0)) * np.array([1.0, 0.0]), 80, rng)
    c, keep, _, _ = fit_instrument(S[:, :2], S[:, 2], [0.0, 0.0], spec(instrument_point_sd_mm=0.3))
    assert np.hypot(*c) > 1.0 and keep.any()
    tip, keep, _, _ = fit_instrument_tilted(S[:, :2], S[:, 2], S[:, 2], [0.0, 0.0, 0.0], sp)
    assert np.linalg.norm(tip) < 0.3 and not keep.any()


def test_the_tilted_fit_of_a_shaft_along_the_normal_costs_little():
    """A shaft along the normal: the fit with a free slope finds no significant slope (TILT_WALD) and falls back to
    the fit that assumes the normal, whose tip is more precise: as near as it, both far nearer than the kinematic
    tip."""
    from liverforce.learn.cloud_features import fit_instrument_tilted

    rng = np.random.default_rng(8)
    e_normal, e_tilted = [], []
    for trial in range(30):
        true = rng.normal(0.0, 0.5, 2)
        S = _tilted_shaft(true, [0.0, 0.0], 80, rng)
        c, _, _, _ = fit_instrument(S[:, :2], S[:, 2], [0.0, 0.0], spec(instrument_point_sd_mm=0.3))
        tip, _, _, _ = fit_instrument_tilted(S[:, :2], S[:, 2], S[:, 2], [0.0, 0.0, 0.0],
                                             spec(instrument_point_sd_mm=0.3, instrument_max_tilt_deg=30.0))
        e_normal.append(c - true)
        e_tilted.append(tip[:2] - true)
    rms_n, rms_t = np.sqrt(np.mean(np.square(e_normal))), np.sqrt(np.mean(np.square(e_tilted)))
    assert rms_t < 0.15 and rms_t < 1.2 * rms_n, (rms_t, rms_n)


def test_gridding_a_cloud_with_the_instrument_gives_the_instrument_free_heights_and_a_better_tip():
    from liverforce.learn.cloud_features import shaft_fit_radius

    V, U0, T = dent_surface()
    true_tip = np.array([0.0, 0.0, -3.0])
    s_fit, s_off = spec(), spec(instrument_radius_mm=0.0)
    ref = ReferenceSurface.for_case(U0, T, [0, 0, 0], np.eye(3), s_fit)
    rng = np.random.default_rng(1)
    e_fit, e_kin, d_fit, d_off = [], [], [], []
    for seed in range(12):
        cfg = obs(noise_sd_mm=0.5, n_points=(2000, 2000))
        cloud, rec = observe(V, T, true_tip, [0, 0, 1], cfg, seed=seed)
        liver = cloud[: len(cloud) - rec.n_instrument_points]
        kin = true_tip + rng.normal(0.0, 0.5, 3)
        g = cloud_grid(cloud[rng.permutation(len(cloud))], ref, s_fit, kin)
        Ll = ref.to_local(liver)
        dl = np.hypot(Ll[:, 0] - g.tip_local[0], Ll[:, 1] - g.tip_local[1])
        rf = shaft_fit_radius(R_TOOL, 0.5)  # where the shaft's points stand, at the model's noise
        ring = (dl < rf + 1.0) | ((dl < rf + 2.0) & (Ll[:, 2] > ref.height(Ll[:, 0], Ll[:, 1])))
        clean = cloud_grid(liver[~ring], ref, s_off)  # the liver's points alone, beyond the same clearance
        e_fit.append(g.tip_local[:2] - true_tip[:2])
        e_kin.append(kin[:2] - true_tip[:2])
        assert g.tip_local[2] == pytest.approx(kin[2])  # along the normal: the kinematic tip
        assert g.n_instrument > 0.6 * rec.n_instrument_points  # (those 2-25 mm above the surface)
        d_fit.append(np.abs(g.height - clean.height).max())
        d_off.append(np.abs(cloud_grid(cloud[~np.r_[ring, np.zeros(rec.n_instrument_points, bool)]], ref,
                                       s_off).height - clean.height).max())
    rms_fit, rms_kin = np.sqrt(np.mean(np.square(e_fit))), np.sqrt(np.mean(np.square(e_kin)))
    assert rms_fit < 0.4 * rms_kin, (rms_fit, rms_kin)
    # the instrument's points left in would raise the cells round the tool by millimetres; found and dropped,
    # the heights are those of the liver's points alone
    assert np.median(d_off) > 2.0, d_off
    assert max(d_fit) < 0.05, d_fit


def test_an_instrument_fit_needs_the_tip_and_valid_settings():
    V, U0, T = dent_surface()
    ref = ReferenceSurface.for_case(U0, T, [0, 0, 0], np.eye(3), spec())
    with pytest.raises(ValueError, match="tip"):
        cloud_grid(V[:100], ref, spec())
    with pytest.raises(ValueError, match="instrument_radius_mm"):
        spec(instrument_radius_mm=-1.0)
    with pytest.raises(ValueError, match="instrument_min_points"):
        spec(instrument_min_points=2)


# --------------------------------------------------------------------------
# a camera model trained on clouds with the instrument in them
# --------------------------------------------------------------------------

INSTRUMENT = {"observation": {"n_points": [300, 3000], "noise_sd_mm": 0.3, "tool_radius_mm": R_TOOL,
                              "instrument_in_cloud": True},
              "grid": {"instrument_radius_mm": R_TOOL}, "tip_noise_mm": 0.5}


def train_camera_model(out_dir, camera: dict):
    """A camera model with these camera settings, trained on 200 synthetic cases of 4 livers (IV split): the
    training result, the loaded model and the test livers' arrays."""
    from tests.serve.test_camera_serving import MODEL, NO_TUNE, TRAIN

    from liverforce.learn.model import ForceModel, subset
    from liverforce.learn.synthetic import synthetic_surface_arrays
    from liverforce.learn.train import train_scenario

    arrays = synthetic_surface_arrays(200, n_geometries=4, seed=7, material_varies=True)
    res = train_scenario(arrays, {**MODEL, "camera": camera}, TRAIN, NO_TUNE, "IV", "cloud", out_dir=out_dir)
    test = np.flatnonzero(np.isin(arrays["geometry_id"], res["split"]["test_geometries"]))
    return res, ForceModel.load(res["model_path"]), subset(arrays, test)


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    return train_camera_model(tmp_path_factory.mktemp("inst"), INSTRUMENT)


def _instrument_case(arrays: dict, i: int, seed: int, tip_sd: float = 0.5, shuffle: bool = True,
                     noise: float = 0.3):
    """Pre-operative context, a new cloud with the instrument in it (another camera, points shuffled, ``noise``
    mm of point noise: the training clouds'), the true and the kinematic tool tip of case ``i`` (``shuffle``
    false: the instrument's points last)."""
    from liverforce.serve import Preop

    V, T = arrays["surface_meshes"][arrays["geometry_id"][i]]
    u = np.asarray(arrays["surface_displacement_mm"][i], dtype=np.float64)
    p = arrays["exertion_point_mm"][i]
    tip = p + u[int(np.argmin(np.linalg.norm(V - p, axis=1)))]
    cfg = obs(n_points=(2500, 2500), noise_sd_mm=noise, roi_radius_mm=40.0)
    cloud, rec = observe(V + u, T, tip, arrays["frame_normal"][i], cfg, seed=[seed, i])
    rng = np.random.default_rng([seed, i])
    ctx = Preop.from_arrays({k: v for k, v in arrays.items() if k != "roi_deformed_mm"}, i)
    order = rng.permutation(len(cloud)) if shuffle else np.arange(len(cloud))
    return ctx, cloud[order], tip, tip + rng.normal(0.0, tip_sd, 3), rec


@pytest.mark.slow
def test_a_model_trained_with_the_instrument_in_view_predicts_from_such_clouds(served):
    """New clouds with the instrument, of livers the model never saw: the force within the model's own test
    error, the tip along the surface from the instrument's axis (nearer the truth than the kinematic tip), a
    warning when the instrument was masked out, one when the camera is three times noisier than the training
    clouds, and the compiled path equal to the reference."""
    from liverforce.serve import Predictor

    res, model, a = served
    pred = Predictor.from_dir(res["model_path"])
    err, e_fit, e_kin = [], [], []
    for i in range(len(a["case_id"])):
        ctx, cloud, tip, kin, rec = _instrument_case(a, i, seed=50)
        assert rec.n_instrument_points > 0
        force, info = pred.predict_cloud(cloud, ctx, tool_tip_mm=kin, return_info=True)
        err.append(np.linalg.norm(force - a["force_n"][i]))
        # the cloud is like the training clouds: no warning of its own (a force beyond the training forces' may be)
        assert info["warnings"] == pred.context_warnings(ctx) + pred.force_warnings(force)[0]
        x = model.representation.features_of(
            {**ctx.to_arrays(ctx.roi_undeformed_mm), "camera_cloud_mm": [cloud], "tool_tip_mm": kin[None]},
            R=ctx.rotation[None])[0]
        true_local = ctx.rotation @ (tip - ctx.exertion_point_mm)
        e_fit.append(x[-3:-1] - true_local[:2])
        e_kin.append((ctx.rotation @ (kin - ctx.exertion_point_mm))[:2] - true_local[:2])
    # 50 cases of 1 or 2 livers: within a quarter of the model's own test MAE (its test clouds, other seeds)
    assert np.mean(err) < 1.25 * res["metrics"]["mae_vec"], (np.mean(err), res["metrics"]["mae_vec"])
    rms_fit, rms_kin = np.sqrt(np.mean(np.square(e_fit), 0)), np.sqrt(np.mean(np.square(e_kin), 0))
    assert (rms_fit < 0.3 * rms_kin).all(), (rms_fit, rms_kin)
    # the instrument masked out: predicted from the kinematic tip, with a warning that says so
    ctx, cloud, tip, kin, rec = _instrument_case(a, 0, seed=51, shuffle=False)
    masked = cloud[: len(cloud) - rec.n_instrument_points]
    _, info = pred.predict_cloud(masked, ctx, tool_tip_mm=kin, return_info=True)
    assert any("tool's shaft" in w and "kinematic" in w for w in info["warnings"])
    # a camera three times noisier than the training clouds': fitted with its own noise, and said so
    ctx, noisy, _, kin_noisy, _ = _instrument_case(a, 0, seed=52, noise=0.9)
    _, info = pred.predict_cloud(noisy, ctx, tool_tip_mm=kin_noisy, return_info=True)
    said = [w for w in info["warnings"] if "noisier camera" in w]
    assert len(said) == 1 and "0.3 mm noise of the model's training clouds" in said[0], info["warnings"]
    assert 0.9 / 1.3 < float(said[0].split("scatter ")[1].split(" mm")[0]) < 0.9 * 1.3  # the estimate
    # the compiled path fits the instrument too: the reference's features, forces, intervals and warnings
    fast = pred.compile_cloud(ctx)
    clouds, tips = [cloud, masked, noisy], [kin, kin, kin_noisy]
    for seed in range(3):
        _, c, _, k, _ = _instrument_case(a, 0, seed=60 + seed)
        clouds.append(c[: 300 + 2000 * seed])  # sparser clouds, fewer of the instrument's points
        tips.append(k)
    batch = fast.predict_batch(clouds, np.array(tips))
    for c, k, f, h, w in zip(clouds, tips, batch.force, batch.half_width, batch.warnings):
        want, info = pred.predict_cloud(c, ctx, tool_tip_mm=k, return_info=True)
        ref_x = model.representation.features_of(
            {**ctx.to_arrays(ctx.roi_undeformed_mm), "camera_cloud_mm": [c], "tool_tip_mm": k[None]},
            R=ctx.rotation[None])[0]
        np.testing.assert_allclose(fast.features(c, k), ref_x, atol=1e-9)
        np.testing.assert_allclose(f, want, atol=1e-6)
        np.testing.assert_allclose(h, info["interval"]["half_width_local_n"], rtol=1e-9)
        assert w == info["warnings"]


def test_the_compiled_fit_is_the_reference_fit(monkeypatch):
    """The numba kernel's pieces of the fit (serve.compiled_cloud: _fit_axis_points on the candidates, _point_sd,
    _instrument_point for the points dropped) against fit_instrument's: the same axis to rounding, the same
    noise estimate, the same points fitted and dropped, in any point order. The refit with the cloud's own noise
    is switched off here (it is the same pieces again with another sd; the gridding test below covers it)."""
    from liverforce.learn import cloud_features
    from liverforce.learn.cloud_features import instrument_point_sd, shaft_fit_radius
    from liverforce.serve.compiled_cloud import _fit_axis_points, _instrument_point, _point_sd, instrument_params

    monkeypatch.setattr(cloud_features, "NOISE_REFIT_RATIO", np.inf)
    rng = np.random.default_rng(3)
    sp = spec(instrument_point_sd_mm=0.4, instrument_tip_sd_mm=0.6)
    inst = instrument_params(sp)
    fitted = 0
    for trial in range(60):
        true = rng.normal(0.0, 0.6, 2)
        n_shaft = int(rng.integers(0, 40))  # none, too few or enough of the shaft
        uv, dz = _shaft(true, n_shaft, rng, sd=0.4, facing=rng.uniform(0, 2 * np.pi))
        surf = rng.uniform(-10, 10, (300, 2))
        P = np.concatenate([uv, surf, [[true[0] + 9.0, true[1]]]])  # and one point far out, well above
        Z = np.concatenate([dz, rng.normal(-0.5, 0.6, len(surf)), [5.0]])
        c, keep, n, _ = fit_instrument(P, Z, [0.0, 0.0], sp)
        order = rng.permutation(len(P))  # the kernel's points in another order (sorted by bin)
        cand = order[(Z[order] > inst[2]) & (np.hypot(*P[order].T) < inst[1])].astype(np.int32)
        U, V, orig = P[:, 0].copy(), P[:, 1].copy(), np.arange(len(P), dtype=np.int32)
        if len(cand):
            assert _point_sd(U, V, orig, cand, len(cand), c[0], c[1], R_TOOL) == pytest.approx(
                instrument_point_sd(P[cand], c, R_TOOL), rel=1e-12)
        cu, cv, nf = _fit_axis_points(U, V, orig, cand, len(cand), 0.0, 0.0, inst)
        np.testing.assert_allclose([cu, cv], c, atol=1e-12)
        assert nf == n
        rf = shaft_fit_radius(R_TOOL, sp.instrument_point_sd_mm)
        drop = np.array([_instrument_point(P[i, 0], P[i, 1], Z[i], cu, cv, 0.0, 0.0, inst, rf) for i in range(len(P))])
        np.testing.assert_array_equal(drop, ~keep)
        fitted += n > 0
    assert 10 < fitted < 60  # both outcomes were exercised


def test_a_cloud_noisier_than_the_models_is_fitted_with_its_own_noise(monkeypatch):
    """A camera with 1.5 mm of point noise where the model was trained at 0.5 mm: the candidates' scatter about
    the fitted cylinder estimates the noise (within 25 %), and the fit done again with it leaves fewer of the
    shaft's points on the grid and finds the axis at least as well as the fit with the model's sd."""
    from liverforce.learn import cloud_features

    def run(refit: bool):
        monkeypatch.setattr(cloud_features, "NOISE_REFIT_RATIO", 1.25 if refit else np.inf)
        rng = np.random.default_rng(11)
        err, left, sds = [], 0, []
        for trial in range(30):
            true = rng.normal(0.0, 0.5, 2)
            uv, dz = _shaft(true, 80, rng, sd=1.5, facing=rng.uniform(0, 2 * np.pi))
            surf = rng.uniform(-15, 15, (1500, 2))
            surf = surf[np.hypot(*(surf - true).T) > R_TOOL + 1.0]
            P = np.concatenate([uv, surf])
            Z = np.concatenate([dz, rng.normal(-0.3, 1.5, len(surf))])
            c, keep, n, sd = fit_instrument(P, Z, [0.0, 0.0], spec())
            assert n >= 8
            err.append(np.hypot(*(c - true)))
            left += int(keep[: len(uv)].sum())  # the shaft's points left on the grid
            sds.append(sd)  # the fit's estimate, from its candidates (the liver's points among them too)
        return np.sqrt(np.mean(np.square(err))), left, np.median(sds)

    rms_own, left_own, sd_est = run(True)
    rms_model, left_model, _ = run(False)
    assert 1.5 / 1.25 < sd_est < 1.5 * 1.25
    assert left_own < 0.5 * left_model
    assert rms_own <= 1.05 * rms_model


def test_a_cloud_as_noisy_as_the_models_is_rarely_fitted_again(monkeypatch):
    """At the model's own noise the estimate stays below the refit's threshold but for a few sparse shafts (the
    median's spread): at most 3 of 40 shafts of 30-90 points are fitted a second time."""
    from liverforce.learn import cloud_features

    calls = []
    real = cloud_features._fit_candidates
    monkeypatch.setattr(cloud_features, "_fit_candidates", lambda *a: calls.append(1) or real(*a))
    rng = np.random.default_rng(5)
    for trial in range(40):
        uv, dz = _shaft(np.zeros(2), int(rng.integers(30, 90)), rng, sd=0.5, facing=rng.uniform(0, 2 * np.pi))
        fit_instrument(uv, dz, [0.0, 0.0], spec())
    assert 40 <= len(calls) <= 43


def test_the_shaft_fit_radius_is_what_a_noisy_arc_of_the_shaft_fits_without_bias():
    """cloud_features.shaft_fit_radius against its closed form written with scipy's Bessel functions, against
    the radius a least-squares fit has no first-order bias with, from Monte Carlo points on an arc of the tool's
    circle with Gaussian noise (``E[p . e] / E[(p / |p|) . e]``: the same for a half and a third of the circle),
    and against the small-noise limit r + sd^2 / (2 r)."""
    from scipy.special import i0e, i1e

    from liverforce.learn.cloud_features import shaft_fit_radius

    rng = np.random.default_rng(2)
    assert shaft_fit_radius(R_TOOL, 0.0) == R_TOOL
    assert shaft_fit_radius(R_TOOL, 1e-200) == R_TOOL  # no overflow for a vanishing sd
    assert shaft_fit_radius(R_TOOL, 1e-4) == pytest.approx(R_TOOL + 1e-8 / (2 * R_TOOL), rel=1e-12)
    assert shaft_fit_radius(R_TOOL, 0.05) == pytest.approx(R_TOOL + 0.05**2 / (2 * R_TOOL), rel=1e-6)
    for sd in (1e-3, 0.05, 0.3, 0.5, 1.0, 1.5, 2.0, 5.0):
        rho = R_TOOL / sd
        want = R_TOOL / (np.sqrt(np.pi / 8) * rho * (i0e(rho**2 / 4) + i1e(rho**2 / 4)))
        assert shaft_fit_radius(R_TOOL, sd) == pytest.approx(want, rel=1e-6)
        if sd < 0.3 or sd > 1.5:
            continue
        for arc in (np.pi, 2 * np.pi / 3):
            phi = rng.uniform(-arc / 2, arc / 2, 400_000)
            px = R_TOOL * np.cos(phi) + rng.normal(0, sd, phi.size)
            d = np.hypot(px, R_TOOL * np.sin(phi) + rng.normal(0, sd, phi.size))
            assert px.mean() / (px / d).mean() == pytest.approx(shaft_fit_radius(R_TOOL, sd), abs=5e-3)
    assert shaft_fit_radius(R_TOOL, 1.0) - R_TOOL > 0.25  # what a fit with the plain radius is off by, about


@pytest.mark.parametrize("tilted", [False, True])
def test_a_noisy_half_shaft_is_fitted_on_its_axis_not_away_from_the_camera(tilted):
    """The camera sees half the shaft. With 1 mm of point noise (the model's own sd here: no refit) the points
    stand further from the axis than the tool's 2.5 mm: a shaft fitted with 2.5 mm sits about 0.37 mm too near the
    camera. Fitted with shaft_fit_radius it does not: the mean offset of the fitted axis towards the camera over 60
    shafts of 150 points each is within 0.1 mm of 0 (-0.02 and 0.01 mm here, standard errors 0.02-0.03 mm; along
    the normal, and with the slope fitted), where the same points fitted with the plain radius are more than
    0.25 mm off."""
    from liverforce.learn import cloud_features
    from liverforce.learn.cloud_features import fit_instrument_tilted

    rng = np.random.default_rng(21)
    sp = spec(instrument_point_sd_mm=1.0, instrument_max_tilt_deg=30.0 if tilted else 0.0)
    offsets, plain = [], []
    for trial in range(60):
        facing = rng.uniform(0, 2 * np.pi)
        towards = np.array([np.cos(facing), np.sin(facing)])
        true = rng.normal(0.0, 0.5, 2)
        if tilted:  # a shaft tilted 20 deg; the kinematic tip on its axis; the camera on the side its points face
            slope = np.tan(np.radians(20.0)) * towards
            P = _tilted_shaft(true, slope, 150, rng, sd=1.0)
            side = (P[:, :2] - true - P[:, 2:] * slope).mean(axis=0)  # the seen half's offset from the axis
            towards = side / np.linalg.norm(side)
            tip, _, n, _ = fit_instrument_tilted(P[:, :2], P[:, 2], P[:, 2] + 3.0, [true[0], true[1], 0.0], sp)
            c = tip[:2]
            assert n >= 140
        else:
            uv, dz = _shaft(true, 150, rng, sd=1.0, facing=facing)
            c, _, n, _ = fit_instrument(uv, dz, true, sp)
            assert n >= 140
            plain.append((cloud_features._fit_axis(uv, true, true, R_TOOL, 1.0, 1 / 0.5**2) - true) @ towards)
        offsets.append((c - true) @ towards)
    assert abs(np.mean(offsets)) < 0.1, np.mean(offsets)
    if plain:
        assert np.mean(plain) > 0.25, np.mean(plain)


def test_only_models_trained_without_the_instrument_check_for_it():
    """The serving check refuses the instrument for a model whose training clouds never showed it; a model
    trained on clouds with it (fitting its axis or not) sees it as in training, and a model whose height
    reference is the old points interpolant (another sheet of a thin lobe under the grid) is not checked."""
    from types import SimpleNamespace

    from liverforce.serve.cloud import instrument_check_radius

    def radius(observation: dict, grid: dict) -> float:
        cam = {"observation": {"tool_radius_mm": 2.5, **observation}, "grid": grid, "tip_noise_mm": 0.5}
        rep = SimpleNamespace(camera=cam, half_width_mm=20.0, grid_size=12)
        from liverforce.learn.camera import grid_spec

        return instrument_check_radius(rep, grid_spec(12, 20.0, cam))

    assert radius({}, {}) == 2.5
    assert radius({"instrument_in_cloud": True}, {}) == 0.0
    assert radius({"instrument_in_cloud": True}, {"instrument_radius_mm": 2.5}) == 0.0
    assert radius({}, {"reference": "points"}) == 0.0
    assert radius({"tool_radius_mm": 0.0}, {}) == 0.0


def _compiled_grid(cloud, ref, sp, kin, inst):
    """One cloud through the compiled gridding pass (serve.compiled_cloud._grid_clouds) with the instrument
    settings ``inst``: its feature row (2 g^2 + 3) and its tool counts (shaft points, instrument points fitted,
    noise estimate)."""
    from liverforce.serve.compiled_cloud import _FILL_CODES, _grid_clouds

    g = sp.grid_size
    X = np.empty((1, 2 * g * g + 3))
    n_used, n_bad, n_tool = np.zeros(1, np.int64), np.zeros(1, np.int64), np.zeros((1, 5))
    _grid_clouds(cloud, np.zeros(1, np.int64), np.array([len(cloud)]), kin[None], ref.origin, ref.R,
                 np.ascontiguousarray(ref.raster), ref.lo, ref.step, g, sp.half_width_mm, sp.spacing_mm,
                 sp.kernel_radius_cells, sp.max_abs_height_mm, sp.min_points, sp.max_leverage, True,
                 _FILL_CODES["laplace"], sp.half_width_mm * (1 + 2 / (g - 1)), np.zeros(4), inst, X, n_used, n_bad,
                 n_tool)
    return X[0], n_tool[0]


@pytest.mark.parametrize("centre,noise,tilt,fit_tilt", [
    ((0.0, 0.0), 0.5, 0.0, 0.0), ((-15.0, 6.0), 0.5, 0.0, 0.0), ((0.0, 0.0), 1.5, 0.0, 0.0),
    ((0.0, 0.0), 0.5, 0.0, 30.0), ((0.0, 0.0), 0.5, 20.0, 30.0), ((-15.0, 6.0), 0.5, 20.0, 30.0),
    ((0.0, 0.0), 1.5, 20.0, 30.0)])
def test_the_compiled_kernel_grids_a_cloud_with_the_instrument_as_the_reference(centre, noise, tilt, fit_tilt,
                                                                                monkeypatch):
    """The numba gridding pass with the instrument (its bin scan, the points moved off the grid) against
    cloud_grid, on clouds of the dent with the tool in view, a kinematic tip up to 1.5 mm off, points shuffled:
    the tool mid-grid and 15 mm off (near the grid's edge) at the model's noise, and mid-grid at three times it
    (the fit done again with the cloud's own noise, in both); with the fit that finds the shaft's slope, the tool
    along the normal (the slope not significant: the normal fit) and tilted 20 deg."""
    from liverforce.learn import cloud_features
    from liverforce.learn.cloud_features import NOISE_REFIT_RATIO
    from liverforce.serve.compiled_cloud import instrument_params

    estimates, tilted = [], []
    real_sd, real_tilted = cloud_features.instrument_point_sd, cloud_features._tilted_point_sd
    monkeypatch.setattr(cloud_features, "instrument_point_sd", lambda *a: estimates.append(real_sd(*a)) or
                        estimates[-1])
    def record_tilted(uv, H, dz, x, sp_, sdp):  # about a fitted axis (not the fit along the normal's, slope 0, that
        got = real_tilted(uv, H, dz, x, sp_, sdp)  # the TILT_SD_RATIO gate measures alike)
        if x[2] != 0.0 or x[3] != 0.0:
            tilted.append(got)
        return got

    monkeypatch.setattr(cloud_features, "_tilted_point_sd", record_tilted)

    V, U0, T = dent_surface()
    sp = spec(instrument_max_tilt_deg=fit_tilt)
    p = np.array([-centre[0], -centre[1], 0.0])  # the exertion point's frame: the dent lies at -p from it
    ref = ReferenceSurface.for_case(U0, T, p, np.eye(3), sp)
    inst = instrument_params(sp)
    rng = np.random.default_rng(7)
    true_tip = np.array([0.0, 0.0, -3.0])
    for seed in range(6):
        cloud, rec = observe(V, T, true_tip, [0, 0, 1], obs(noise_sd_mm=noise, n_points=(400 + 1500 * seed,) * 2,
                                                             tool_tilt_deg=tilt),
                             seed=seed)
        cloud = np.ascontiguousarray(cloud[rng.permutation(len(cloud))])
        kin = true_tip + rng.uniform(-1.5, 1.5, 3)
        want = cloud_grid(cloud, ref, sp, kin)
        X, n_tool = _compiled_grid(cloud, ref, sp, kin, inst)
        assert rec.n_instrument_points > 0 and want.n_instrument > 0
        assert n_tool[1] == want.n_instrument
        assert n_tool[2] == pytest.approx(want.instrument_sd_mm, rel=1e-9)  # the noise estimate
        np.testing.assert_allclose(X[:-3], want.features(include_mask=True), atol=1e-9)
        np.testing.assert_allclose(X[-3:], want.tip_local, atol=1e-9)
    if tilt:  # the tilted fit's noise estimate: a refit at the higher noise only
        refit = np.array(tilted) > NOISE_REFIT_RATIO * sp.instrument_point_sd_mm
        assert len(refit) >= 6 and (refit.any() if noise > 1.0 else not refit.any())
    if not fit_tilt:  # the shaft along the normal: the refit, and only at the higher noise
        refit = np.array(estimates) > NOISE_REFIT_RATIO * sp.instrument_point_sd_mm
        assert len(refit) >= 6 and (refit.all() if noise > 1.0 else not refit.any())


def test_the_noisy_cloud_warning_names_the_estimate_and_the_training_noise():
    """serve.cloud.noisy_cloud: nothing at or below 1.75 x the training clouds' noise or when nothing was fitted
    (NaN); above it, a warning with both figures."""
    from liverforce.serve.cloud import NOISY_CLOUD_RATIO, noisy_cloud

    sp = spec(instrument_point_sd_mm=0.5)
    assert noisy_cloud(np.nan, sp) is None
    assert noisy_cloud(0.5, sp) is None and noisy_cloud(NOISY_CLOUD_RATIO * 0.5, sp) is None
    said = noisy_cloud(1.1, sp)
    assert "scatter 1.1 mm" in said and "2.2 times the 0.5 mm noise" in said


def test_a_model_trained_on_a_range_of_point_noise_fits_with_the_least_and_warns_above_the_most():
    """observation.noise_sd_mm: [lo, hi]: the instrument fit's prior sd is lo (a noisier cloud is refitted with
    its own), the grid spec records hi, and serving warns only about clouds noisier than 1.75 x hi. A single value
    records no range, as before ranges existed."""
    from liverforce.learn.camera import grid_spec
    from liverforce.serve.cloud import NOISY_CLOUD_RATIO, noisy_cloud

    cam = {"observation": {"noise_sd_mm": [0.5, 1.0]}, "tip_noise_mm": 0.5, "grid": {"instrument_radius_mm": 2.5}}
    sp = grid_spec(16, 20.0, cam)
    assert (sp.instrument_point_sd_mm, sp.instrument_point_sd_max_mm) == (0.5, 1.0)
    assert noisy_cloud(NOISY_CLOUD_RATIO * 1.0, sp) is None  # 1.75 mm: the noisiest training clouds' ratio
    assert "1.9 times the 1 mm noise" in noisy_cloud(1.9, sp)
    one = grid_spec(16, 20.0, {**cam, "observation": {"noise_sd_mm": 0.5}})
    assert (one.instrument_point_sd_mm, one.instrument_point_sd_max_mm) == (0.5, None)
    assert grid_spec(16, 20.0, {**cam, "observation": {}}).instrument_point_sd_max_mm is None
    assert noisy_cloud(1.0, one) is not None  # 2 x the single training noise
    with pytest.raises(ValueError, match="instrument_point_sd_max_mm"):
        spec(instrument_point_sd_mm=0.5, instrument_point_sd_max_mm=0.4)


def test_a_trained_model_keeps_its_noise_range_when_saved_and_when_re_observed():
    """The representation records both ends of the training noise in its grid (and back from its dict); a model
    re-observed with another camera (the validation's sensitivity, --observe) keeps its own, whether it was
    trained on a range or on one value and re-observed with a range below it; a config that sets the fit's point
    sd itself records no range."""
    from dataclasses import replace

    from liverforce.learn.camera import grid_spec
    from liverforce.learn.representation import Representation, representation_from_config
    from liverforce.learn.synthetic import synthetic_surface_arrays

    arrays = synthetic_surface_arrays(6, n_geometries=1, seed=0)
    cam = {"observation": {"noise_sd_mm": [0.5, 1.0], "tool_radius_mm": 2.5}, "tip_noise_mm": 0.5,
           "grid": {"instrument_radius_mm": 2.5}}
    model = {"grid_size": 8, "roi_features": "cloud", "camera": cam, "occlusion": {"radius_mm": 0.0},
             "noise_mm": 0.0, "grid_half_width_mm": 20.0}

    def sds(rep):
        sp = grid_spec(rep.grid_size, rep.half_width_mm, rep.camera)
        return sp.instrument_point_sd_mm, sp.instrument_point_sd_max_mm

    rep = Representation.from_dict(representation_from_config(model, arrays).to_dict())
    assert sds(rep) == (0.5, 1.0)
    for noise in (0.2, 2.0, [0.1, 0.3]):  # re-observed: the grid's own sds stay
        assert sds(replace(rep, camera={**rep.camera, "observation": {**cam["observation"], "noise_sd_mm": noise}})) \
            == (0.5, 1.0)
    one = representation_from_config({**model, "camera": {**cam, "observation": {"noise_sd_mm": 0.8}}}, arrays)
    assert sds(one) == (0.8, None)
    assert sds(replace(one, camera={**one.camera, "observation": {"noise_sd_mm": [0.3, 0.6]}})) == (0.8, None)
    own = {**cam, "grid": {**cam["grid"], "instrument_point_sd_mm": 1.5}}
    assert sds(representation_from_config({**model, "camera": own}, arrays)) == (1.5, None)


def test_the_compiled_tilted_pass_is_the_reference_on_few_points():
    """The numba search-and-fit pass of the tilted fit (serve.compiled_cloud._tilted_pass, on the list of the
    points standing above the surface, one of them a duplicate the kernel has struck out) against
    cloud_features._tilted_pass on shafts of 7-14 points with liver bumps among the candidates: the same axis,
    points fitted and Wald statistic, also when a trim would leave fewer than the fewest points (every candidate
    must stay in the fit then)."""
    from liverforce.learn import cloud_features as cf
    from liverforce.serve import compiled_cloud as cc

    sp = spec(instrument_max_tilt_deg=30.0)
    inst = cc.instrument_params(sp)
    rng = np.random.default_rng(12)
    early = 0
    for trial in range(60):
        slope = np.tan(np.radians(rng.uniform(0, 25))) * np.array([1.0, 0.0])
        S = _tilted_shaft(rng.normal(0, 0.3, 2), slope, int(rng.integers(7, 15)), rng, sd=0.2)
        n_out = int(rng.integers(0, 4))  # liver bumps standing above the surface near the tool, listed first
        ang = rng.uniform(0, 2 * np.pi, n_out)
        out = np.column_stack([5.8 * np.cos(ang), 5.8 * np.sin(ang), rng.uniform(2.2, 3.0, n_out)])
        P = np.concatenate([out, S])
        uv, H = P[:, :2].copy(), P[:, 2].copy()
        want = cf._tilted_pass(uv, H, H, np.zeros(2), sp, sp.instrument_point_sd_mm)
        n = len(P)
        # the kernel's list of the points standing above the surface, with a struck-out duplicate (orig -1) of a shaft
        # point in it: it must be skipped
        U, V, Hk = (np.append(a, a[-1]) for a in (uv[:, 0], uv[:, 1], H))
        orig = np.append(np.arange(n, dtype=np.int32), np.int32(-1))
        raised = np.flatnonzero(Hk > inst[2])
        assert raised[-1] == n
        got = cc._tilted_pass(U, V, Hk, orig, raised, len(raised), 0.0, 0.0, inst[1], sp.instrument_point_sd_mm, inst,
                              np.zeros(n + 1, dtype=np.int32))
        np.testing.assert_allclose(got[0], want[0], atol=1e-9)
        assert got[1] == want[1]
        assert got[2] == pytest.approx(want[2], rel=1e-9, abs=1e-9)
        res = cf._tilt_residuals(uv, H, cf._fit_tilted(uv[H > 2.0], H[H > 2.0], np.zeros(4), np.zeros(4), R_TOOL,
                                                       4.0, 4.0, 3.0), R_TOOL)[0]
        early += int(0 < (np.abs(res) <= 1.8).sum() < 8)
    assert early > 0  # a trim that would leave too few points happened


def _undamped_fit_tilted(Q, H, x0, prior, r, wp, wk, ws):
    """The tilted fit's Gauss-Newton before the damping: every full step taken."""
    from liverforce.learn import cloud_features as cf

    x = np.array(x0, dtype=np.float64)
    W = np.array([wk, wk, ws, ws])
    for _ in range(cf._FIT_ITERATIONS):
        res, J = cf._tilt_residuals(Q, H, x, r)
        step = np.linalg.solve(wp * (J.T @ J) + np.diag(W), wp * (J.T @ res) + W * (x - prior))
        x = x - step
        if float(step @ step) < 1e-16:
            break
    return x


def _tilt_objective(Q, H, x, prior, r, wp, wk, ws) -> float:
    from liverforce.learn import cloud_features as cf

    res, _ = cf._tilt_residuals(Q, H, x, r)
    return wp * float(res @ res) + float(np.array([wk, wk, ws, ws]) @ (x - prior) ** 2)


def test_the_damped_tilted_fit_takes_the_undamped_steps_where_they_lower_the_objective(monkeypatch):
    """On tilted shafts with liver points round them every full Gauss-Newton step lowers the objective: the damped
    fit's tip, points and noise equal those of the undamped one, bit for bit."""
    from liverforce.learn import cloud_features as cf

    rng = np.random.default_rng(12)
    sp = spec(instrument_point_sd_mm=0.3, instrument_max_tilt_deg=30.0)
    cases = []
    for trial in range(12):
        _, uv, w, _, _ = _tilted_scene(rng, 5.0, 30.0, 600)
        cases.append((uv, w))
    damped = [cf.fit_instrument_tilted(uv, w, w, [0.0, 0.0, 0.0], sp) for uv, w in cases]
    monkeypatch.setattr(cf, "_fit_tilted", _undamped_fit_tilted)
    for (uv, w), got in zip(cases, damped):
        want = cf.fit_instrument_tilted(uv, w, w, [0.0, 0.0, 0.0], sp)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])
        assert got[2:] == want[2:]
        assert np.hypot(*got[0][:2]) < 2.0 and got[0][2] != 0.0  # tilted fits (a fallback keeps the tip's height)


def test_a_tilted_fit_is_damped_and_one_that_runs_off_is_not_believed(monkeypatch):
    """The candidates of a real camera cloud (tests/learn/data/runaway_shaft.csv: an unseen liver, the tool tilted
    30 deg; the shaft's points and liver points to its side standing above the surface) sent the undamped
    Gauss-Newton, with the tool's radius as the fit then used, off to a near-horizontal axis whose tip lay tens of
    mm from the kinematic tip, with a large Wald statistic (with shaft_fit_radius the undamped steps still run off
    to a near-horizontal axis, but its tip lands near the kinematic one). Damped (a step that raises the objective
    halved), the fit finds a shaft tilted about 30 deg through the kinematic tip, at a lower objective, and the
    compiled kernel finds the same. That recorded runaway axis is still refused by ``tilt_credible`` (the tip on it
    beyond the search radius of the kinematic tip), numpy and kernel, and a cloud of these points is gridded alike
    by both."""
    from pathlib import Path

    from liverforce.learn import cloud_features as cf
    from liverforce.learn.cloud_features import fit_instrument_tilted, instrument_search_radius, tilt_credible
    from liverforce.serve import compiled_cloud as cc

    P = np.loadtxt(Path(__file__).parent / "data" / "runaway_shaft.csv", delimiter=",")
    sp = spec(instrument_max_tilt_deg=30.0)
    S = instrument_search_radius(sp)
    uv, H = P[:, :2].copy(), P[:, 2].copy()

    def tip_off(x):  # the tip the fit gives (the kinematic tip, the origin, projected onto its axis), from it
        t = float(-x[:2] @ x[2:]) / (1.0 + float(x[2:] @ x[2:]))
        return np.hypot(x[0] + t * x[2], x[1] + t * x[3])

    x, n, wald = cf._tilted_pass(uv, H, H, np.zeros(2), sp, sp.instrument_point_sd_mm)
    tilt = np.degrees(np.arctan(np.hypot(*x[2:])))
    assert wald > cf.TILT_WALD and 25.0 < tilt < 35.0 and tip_off(x) < 1.0, (x, n, wald)
    assert tilt_credible(x, np.zeros(2), S)
    with monkeypatch.context() as m:  # the undamped fit as it ran then: with the tool's radius
        m.setattr(cf, "_fit_tilted", _undamped_fit_tilted)
        m.setattr(cf, "shaft_fit_radius", lambda r, sd: r)
        x_u, n_u, wald_u = cf._tilted_pass(uv, H, H, np.zeros(2), sp, sp.instrument_point_sd_mm)
        assert n_u == len(P) and wald_u > cf.TILT_WALD and tip_off(x_u) > 20.0, (x_u, n_u, wald_u)
        assert not tilt_credible(x_u, np.zeros(2), S)
        tip_u, keep_u, n_fit_u, sd_u = fit_instrument_tilted(uv, H, H, [0.0, 0.0, 0.0], sp)
        c, keep_n, n_n, sd_n = fit_instrument(uv, H, np.zeros(2), sp)  # refused: the fit along the normal
        np.testing.assert_array_equal(tip_u, [c[0], c[1], 0.0])
        np.testing.assert_array_equal(keep_u, keep_n)
        assert (n_fit_u, sd_u) == (n_n, sd_n)
    # from the same start on every candidate, damping ends lower than the undamped steps
    wp, wk = 1.0 / sp.instrument_point_sd_mm ** 2, 1.0 / sp.instrument_tip_sd_mm ** 2
    ws = 1.0 / np.tan(np.radians(30.0)) ** 2
    x0 = np.array([0.0, 0.0, *np.linalg.lstsq(np.column_stack([np.ones(len(H)), H]), uv, rcond=None)[0][1]])
    obj = [_tilt_objective(uv, H, f(uv, H, x0, np.zeros(4), R_TOOL, wp, wk, ws), np.zeros(4), R_TOOL, wp, wk, ws)
           for f in (cf._fit_tilted, _undamped_fit_tilted)]
    assert obj[0] < obj[1] and obj[0] < _tilt_objective(uv, H, x0, np.zeros(4), R_TOOL, wp, wk, ws), obj
    # on every budget of iterations the damped fit ends no higher than with one fewer (a last step that raised the
    # objective is not kept), the kernel's alike; the undamped steps do end higher
    ends, ends_u = [], []
    Qk = np.ascontiguousarray(np.vstack([uv.T, H, np.zeros(len(H))]))
    Wv = np.array([wk, wk, ws, ws])
    for it in range(1, cf._FIT_ITERATIONS + 1):
        xd = cf._fit_tilted(uv, H, x0, np.zeros(4), R_TOOL, wp, wk, ws, iterations=it)
        xk = cc._tilt_steps(Qk, len(H), x0.copy(), np.zeros(4), R_TOOL, wp, Wv, it)
        np.testing.assert_allclose(xk, xd, atol=1e-9)
        ends.append(_tilt_objective(uv, H, xd, np.zeros(4), R_TOOL, wp, wk, ws))
        cf_it = cf._FIT_ITERATIONS
        try:
            cf._FIT_ITERATIONS = it
            ends_u.append(_tilt_objective(uv, H, _undamped_fit_tilted(uv, H, x0, np.zeros(4), R_TOOL, wp, wk, ws),
                                          np.zeros(4), R_TOOL, wp, wk, ws))
        finally:
            cf._FIT_ITERATIONS = cf_it
    assert all(b <= a * (1.0 + 1e-9) for a, b in zip(ends, ends[1:])), ends
    assert any(b > a * 1.01 for a, b in zip(ends_u, ends_u[1:])), ends_u
    # the tilted tip is returned: the kinematic tip projected onto the damped axis
    tip, keep, n_fit, sd = fit_instrument_tilted(uv, H, H, [0.0, 0.0, 0.0], sp)
    t = float(-x[:2] @ x[2:]) / (1.0 + float(x[2:] @ x[2:]))
    np.testing.assert_allclose(tip, [x[0] + t * x[2], x[1] + t * x[3], t], atol=1e-12)
    assert n_fit == n
    # the kernel's pass on the same candidates: the same damped axis, and its check agrees on both axes
    inst = cc.instrument_params(sp)
    raised = np.arange(len(P))
    got = cc._tilted_pass(uv[:, 0].copy(), uv[:, 1].copy(), H, np.arange(len(P), dtype=np.int32), raised, len(P),
                          0.0, 0.0, S, sp.instrument_point_sd_mm, inst, np.zeros(len(P), dtype=np.int32))
    np.testing.assert_allclose(got[0], x, atol=1e-9)
    assert got[1] == n and np.isclose(got[2], wald, rtol=1e-6)
    assert cc._tilt_credible(got[0], 0.0, 0.0, S) and not cc._tilt_credible(x_u, 0.0, 0.0, S)
    assert cc._tilt_credible(np.array([0.3, -0.4, 0.2, -0.5]), 0.0, 0.0, S)  # a shaft tilted 28 deg near the tip
    # a whole cloud: a flat pre-operative surface, the kinematic tip 7.2 mm below it (the dent), these points
    # standing on it, liver points round them; cloud_grid and the compiled kernel grid it alike
    _, U0, T = dent_surface()
    ref = ReferenceSurface.for_case(U0, T, np.zeros(3), np.eye(3), sp)
    rng = np.random.default_rng(3)
    flat = rng.uniform(-25.0, 25.0, (3000, 2))
    flat = flat[np.hypot(*flat.T) > R_TOOL + 1.0]
    tw = -7.2
    cloud = np.concatenate([np.column_stack([flat, rng.normal(0.0, 0.3, len(flat))]),
                            np.column_stack([uv, H + tw])])
    cloud = np.ascontiguousarray(cloud[rng.permutation(len(cloud))])
    kin = np.array([0.0, 0.0, tw])
    want = cloud_grid(cloud, ref, sp, kin)
    assert want.n_instrument > 0 and np.hypot(*want.tip_local[:2]) < S
    X, n_tool = _compiled_grid(cloud, ref, sp, kin, inst)
    assert n_tool[1] == want.n_instrument
    np.testing.assert_allclose(X[:-3], want.features(include_mask=True), atol=1e-9)
    np.testing.assert_allclose(X[-3:], want.tip_local, atol=1e-9)


def test_a_tilted_axis_its_points_scatter_about_far_more_than_the_normals_is_not_taken(monkeypatch):
    """fit_instrument_tilted: when the tilted fit ends in a minimum that is not the tool's (here forced: an axis
    3 mm off with a slope, its Wald statistic high), its points scatter about it far more than about the fit
    along the normal, and that fit is returned (its tip, points and noise estimate); with the gate off
    (TILT_SD_RATIO infinite) the wrong axis would have given a tip millimetres off."""
    from liverforce.learn import cloud_features as cf
    from liverforce.learn.cloud_features import fit_instrument_tilted

    rng = np.random.default_rng(21)
    sp = spec(instrument_point_sd_mm=0.3, instrument_max_tilt_deg=30.0)
    true = rng.normal(0.0, 0.3, 2)
    S = _tilted_shaft(true, [0.0, 0.0], 80, rng)  # a shaft along the normal
    real = cf._tilted_pass

    def wrong(uv, H, dz, c0, spec_, sdp):
        _, n, _ = real(uv, H, dz, c0, spec_, sdp)
        return np.array([true[0] + 3.0, true[1], 0.2, 0.0]), n, 100.0

    monkeypatch.setattr(cf, "_tilted_pass", wrong)
    tip, keep, n, sd = fit_instrument_tilted(S[:, :2], S[:, 2], S[:, 2], [0.0, 0.0, 0.0], sp)
    c, keep_n, n_n, sd_n = cf.fit_instrument(S[:, :2], S[:, 2], [0.0, 0.0], sp)
    np.testing.assert_array_equal(tip, [c[0], c[1], 0.0])
    assert np.hypot(*(tip[:2] - true)) < 0.2 and n == n_n and sd == sd_n and (keep == keep_n).all()
    monkeypatch.setattr(cf, "TILT_SD_RATIO", np.inf)
    tip_off, _, _, sd_off = fit_instrument_tilted(S[:, :2], S[:, 2], S[:, 2], [0.0, 0.0, 0.0], sp)
    about_normal = cf._tilted_point_sd(S[:, :2], S[:, 2], S[:, 2], np.array([c[0], c[1], 0.0, 0.0]), sp, 0.3)
    assert np.hypot(*(tip_off[:2] - true)) > 2.0 and sd_off > 1.5 * about_normal  # what the default ratio refused


def test_a_noisy_cloud_of_a_tilted_tool_keeps_its_tilted_fit(monkeypatch):
    """The gate compares the scatters alike (the same points near each axis, at every height): the fit along the
    normal reads only its vertical cylinder of candidates, which a tilted shaft leaves as it rises, so its own
    estimate is too small for a tilted tool. On these clouds (tilted 20-30 deg, 1-1.5 mm of point noise; a review
    found them) compared with that estimate the gate took the normal's fit, its tip 2-2.7 mm off; now the tilted
    fit stays: the tip is the one with the gate off."""
    from liverforce.learn import cloud_features as cf

    V, U0, T = dent_surface()
    sp = spec(instrument_max_tilt_deg=30.0)
    ref = ReferenceSurface.for_case(U0, T, [0.0, 0.0, 0.0], np.eye(3), sp)
    tip0 = np.array([0.0, 0.0, -3.0])
    rng = np.random.default_rng(4)
    own_estimate_fires = 0
    for tilt, noise, seed in ((20.0, 1.5, 320), (20.0, 1.5, 355), (30.0, 1.0, 328), (30.0, 1.5, 321),
                              (30.0, 1.5, 342)):
        cloud, _ = observe(V, T, tip0, [0, 0, 1], obs(noise_sd_mm=noise, n_points=(5000, 5000), tool_tilt_deg=tilt),
                           seed=seed)
        kin = tip0 + rng.uniform(-0.5, 0.5, 3)
        g = cloud_grid(cloud, ref, sp, kin)
        monkeypatch.setattr(cf, "TILT_SD_RATIO", np.inf)
        np.testing.assert_array_equal(g.tip_local, cloud_grid(cloud, ref, sp, kin).tip_local)
        monkeypatch.setattr(cf, "TILT_SD_RATIO", 1.5)
        assert g.tip_local[2] != kin[2]  # the tilted fit's tip (it moves the height), not the normal's
        # the tilted fit's scatter against the normal fit's own estimate: the comparison that misfired
        L = ref.to_local(cloud)
        L = cf._canonical(L[(np.abs(L[:, 0]) < 24.0) & (np.abs(L[:, 1]) < 24.0)])
        dz = L[:, 2] - ref.height(L[:, 0], L[:, 1])
        ok = np.abs(dz) <= sp.max_abs_height_mm
        uv, H, dz = L[ok, :2], L[ok, 2] - kin[2], dz[ok]
        sdp = sp.instrument_point_sd_mm
        x, n, _ = cf._tilted_pass(uv, H, dz, kin[:2], sp, sdp)
        sd = cf._tilted_point_sd(uv, H, dz, x, sp, sdp)
        if sd > cf.NOISE_REFIT_RATIO * sdp:
            x, n, _ = cf._tilted_pass(uv, H, dz, kin[:2], sp, sd)
            sd = cf._tilted_point_sd(uv, H, dz, x, sp, sd)
        own_estimate_fires += n > 0 and sd > cf.TILT_SD_RATIO * cf.fit_instrument(uv, dz, kin[:2], sp)[3]
    assert own_estimate_fires >= 1  # these clouds do tell the two comparisons apart


@pytest.mark.parametrize("tilt", [0.0, 20.0])
def test_the_compiled_kernel_takes_the_normals_fit_where_the_reference_does(tilt, monkeypatch):
    """The compiled kernel's TILT_SD_RATIO gate against cloud_grid's: with the ratio lowered so far that every
    tilted fit is judged worse than the fit along the normal, both take the normal's (the same features, tip and
    noise estimate) on clouds of the dent with the tool along the normal or tilted 20 deg; the tilted tool's tip
    then stays the kinematic one's height, where at the default ratio its tilted fit moves it."""
    from liverforce.learn import cloud_features
    from liverforce.serve.compiled_cloud import instrument_params

    V, U0, T = dent_surface()
    sp = spec(instrument_max_tilt_deg=30.0)
    ref = ReferenceSurface.for_case(U0, T, [0.0, 0.0, 0.0], np.eye(3), sp)
    rng = np.random.default_rng(8)
    true_tip = np.array([0.0, 0.0, -3.0])
    moved = []
    for seed in range(4):
        cloud, _ = observe(V, T, true_tip, [0, 0, 1], obs(noise_sd_mm=0.5, n_points=(3000, 3000), tool_tilt_deg=tilt),
                           seed=seed)
        cloud = np.ascontiguousarray(cloud[rng.permutation(len(cloud))])
        kin = true_tip + rng.uniform(-1.0, 1.0, 3)
        default = cloud_grid(cloud, ref, sp, kin)
        monkeypatch.setattr(cloud_features, "TILT_SD_RATIO", 1e-6)
        want = cloud_grid(cloud, ref, sp, kin)
        X, n_tool = _compiled_grid(cloud, ref, sp, kin, instrument_params(sp))
        monkeypatch.setattr(cloud_features, "TILT_SD_RATIO", 1.5)
        assert want.tip_local[2] == pytest.approx(kin[2])  # the fit along the normal keeps the kinematic height
        assert n_tool[1] == want.n_instrument and n_tool[2] == pytest.approx(want.instrument_sd_mm, rel=1e-9)
        np.testing.assert_allclose(X[:-3], want.features(include_mask=True), atol=1e-9)
        np.testing.assert_allclose(X[-3:], want.tip_local, atol=1e-9)
        moved.append(abs(default.tip_local[2] - kin[2]))
    assert (max(moved) > 0.05) == (tilt > 0)  # at the default ratio only the tilted tool's fit is the tilted one
