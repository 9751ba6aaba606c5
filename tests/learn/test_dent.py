"""The dent round the tool, fitted to a camera cloud (cloud_features.fit_dent, camera.grid.dent_radius_mm).

The tool hides the tip; the visible ring round it holds the dent's profile. A plane (the liver's own motion
there) plus the outer profile of a flat punch of the tool's radius (Sneddon 1946) is fitted to the liver's
points, and its amplitude reaches the regressor as a force (over the probe's normal compliance).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from liverforce.learn import camera
from liverforce.learn.cloud_features import (DENT_MIN_POINTS, CloudGridSpec, ReferenceSurface, cloud_grid,
                                             fit_dent)
from liverforce.learn.observation import ObservationConfig, observe

R_TOOL = 2.5


def spec(**kw):
    base = dict(grid_size=12, half_width_mm=20.0, kernel_radius_cells=1.5, instrument_radius_mm=R_TOOL,
                instrument_point_sd_mm=0.5, instrument_tip_sd_mm=0.5, dent_radius_mm=15.0)
    return CloudGridSpec(**{**base, **kw})


def punch(u, v, depth, centre=(0.0, 0.0)):
    """Sneddon's flat punch of radius R_TOOL pressed ``depth`` into a half-space: the surface outside it."""
    r = np.hypot(u - centre[0], v - centre[1])
    return -depth * (2.0 / math.pi) * np.arcsin(np.minimum(1.0, R_TOOL / np.maximum(r, 1e-12)))


def ring_points(n, rng, r_in=3.5, r_out=20.0, centre=(0.0, 0.0)):
    r = np.sqrt(rng.uniform(r_in**2, r_out**2, n))
    t = rng.uniform(0.0, 2.0 * math.pi, n)
    return centre[0] + r * np.cos(t), centre[1] + r * np.sin(t)


def test_the_fit_reads_a_punchs_depth_and_its_plane_without_bias():
    rng = np.random.default_rng(0)
    amp, off = [], []
    for _ in range(40):
        u, v = ring_points(800, rng, centre=(1.0, -0.5))
        dz = 0.7 + 0.05 * (u - 1.0) - 0.02 * (v + 0.5) + punch(u, v, 4.0, (1.0, -0.5)) + rng.normal(0, 0.5, u.size)
        a, o = fit_dent(u, v, dz, (1.0, -0.5), spec())
        amp.append(a)
        off.append(o)
    # amplitude = -depth (the punch goes in, dz < 0), offset = the plane at the axis
    assert np.mean(amp) == pytest.approx(-4.0, abs=0.05)
    assert np.mean(off) == pytest.approx(0.7, abs=0.05)
    # 0.5 mm point noise over ~450 points within 15 mm: the amplitude to about 0.3 mm (it trades off against the
    # plane's offset, the profile being flat far out), against the plane it sits in, which the tip's 0.5 mm
    # kinematic noise along the normal does not separate from the liver's own motion
    assert 0.1 < np.std(amp) < 0.45, np.std(amp)


def test_the_liver_moving_or_tilting_under_the_dent_leaves_the_amplitude():
    rng = np.random.default_rng(1)
    u, v = ring_points(1500, rng)
    base = punch(u, v, 3.0)
    a0, _ = fit_dent(u, v, base, (0.0, 0.0), spec())
    for shift, su, sv in ((5.0, 0.0, 0.0), (-2.0, 0.3, -0.2), (0.0, -0.4, 0.4)):
        a, o = fit_dent(u, v, base + shift + su * u + sv * v, (0.0, 0.0), spec())
        assert a == pytest.approx(a0, abs=1e-9)
        assert o == pytest.approx(shift, abs=1e-9)
    assert a0 == pytest.approx(-3.0, abs=1e-9)


def test_the_amplitude_is_linear_in_the_dent():
    """Twice the dent, twice the amplitude (the fit is linear least squares): with a linear material the
    amplitude over the compliance is a force."""
    rng = np.random.default_rng(2)
    u, v = ring_points(1000, rng)
    bump = punch(u, v, 1.0) * (1.0 + 0.1 * np.cos(np.arctan2(v, u)))  # not exactly the profile fitted
    a1, _ = fit_dent(u, v, bump, (0.0, 0.0), spec())
    a2, _ = fit_dent(u, v, 2.0 * bump, (0.0, 0.0), spec())
    assert a2 == pytest.approx(2.0 * a1, rel=1e-12)


def test_too_few_points_or_points_only_on_a_line_give_no_dent():
    rng = np.random.default_rng(3)
    u, v = ring_points(DENT_MIN_POINTS - 1, rng, r_out=10.0)
    np.testing.assert_array_equal(fit_dent(u, v, punch(u, v, 2.0), (0.0, 0.0), spec()), [0.0, 0.0])
    far_u, far_v = ring_points(500, rng, r_in=16.0, r_out=20.0)  # all beyond dent_radius_mm
    np.testing.assert_array_equal(fit_dent(far_u, far_v, far_u * 0, (0.0, 0.0), spec()), [0.0, 0.0])
    t = np.linspace(4.0, 12.0, 50)  # on one line through the axis: the plane's slope across it is not seen
    line = fit_dent(t, 0 * t, punch(t, 0 * t, 2.0), (0.0, 0.0), spec())
    np.testing.assert_array_equal(line, [0.0, 0.0])


def test_a_dent_fit_needs_the_tools_radius_and_a_radius_beyond_it():
    with pytest.raises(ValueError, match="dent_radius_mm"):
        spec(instrument_radius_mm=0.0)
    with pytest.raises(ValueError, match="dent_radius_mm"):
        spec(dent_radius_mm=2.0)
    with pytest.raises(ValueError, match="dent_radius_mm"):
        spec(dent_radius_mm=-1.0)
    assert spec(dent_radius_mm=0.0, instrument_radius_mm=0.0).dent_radius_mm == 0.0


def plate(depth, half=40.0, n=81):
    """A plate at z = 0 with a punch's dent at the origin (deformed), its flat twin and triangles (+z out)."""
    x = np.linspace(-half, half, n)
    X, Y = np.meshgrid(x, x)
    Z = punch(X, Y, depth)
    q = np.arange((n - 1) * n).reshape(n - 1, n)[:, : n - 1].ravel()
    T = np.concatenate([np.column_stack([q, q + 1, q + n + 1]), np.column_stack([q, q + n + 1, q + n])])
    return (np.column_stack([X.ravel(), Y.ravel(), Z.ravel()]),
            np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)]), T)


def test_a_camera_cloud_with_the_instrument_gives_the_dents_depth_and_a_deeper_dent_a_larger_one():
    """Observed as in training (camera in a cone, the tool hiding its dent, its own points in the cloud, 0.5 mm
    noise): the fit reads the punch's depth from the ring the tool leaves visible, whatever the camera."""
    cfg = ObservationConfig(n_points=(3000, 3000), noise_sd_mm=0.5, roi_radius_mm=30.0, tool_radius_mm=R_TOOL,
                            instrument_in_cloud=True)
    s = spec()
    rng = np.random.default_rng(4)
    found = {}
    for depth in (2.0, 4.0):
        V, U0, T = plate(depth)
        ref = ReferenceSurface.for_case(U0, T, [0, 0, 0], np.eye(3), s)
        tip = np.array([0.0, 0.0, -depth])
        amps = []
        for seed in range(6):
            cloud, rec = observe(V, T, tip, [0, 0, 1], cfg, seed=seed)
            g = cloud_grid(cloud[rng.permutation(len(cloud))], ref, s, tip + rng.normal(0, 0.5, 3))
            assert g.n_instrument > 0 and g.dent is not None
            amps.append(g.dent[0])
        found[depth] = np.array(amps)
    # each camera sees one side of the ring better: about 0.3 mm per cloud, no bias over the cameras
    for depth, amps in found.items():
        assert amps.mean() == pytest.approx(-depth, abs=0.25), amps
        assert np.all(np.abs(amps + depth) < 1.0), amps
    assert found[4.0].mean() / found[2.0].mean() == pytest.approx(2.0, rel=0.15)


def test_the_dent_columns_sit_between_the_mask_and_the_tip():
    assert camera.n_features(12, dent=True) == 2 * 144 + camera.N_DENT + 3
    groups = camera.channel_groups(12, dent=True)
    assert list(groups[288:288 + camera.N_DENT]) == [3] * camera.N_DENT and list(groups[-3:]) == [2, 2, 2]
    assert camera.n_features(12) == 2 * 144 + 3


def _compiled_row(cloud, ref, sp, kin):
    """One cloud through the compiled gridding pass (serve.compiled_cloud._grid_clouds): its feature row."""
    from liverforce.serve.compiled_cloud import _FILL_CODES, _grid_clouds, instrument_params

    g = sp.grid_size
    X = np.empty((1, camera.n_features(g, sp.dent_radius_mm > 0)))
    n_used, n_bad, n_tool = np.zeros(1, np.int64), np.zeros(1, np.int64), np.zeros((1, 5))
    _grid_clouds(cloud, np.zeros(1, np.int64), np.array([len(cloud)]), kin[None], ref.origin, ref.R,
                 np.ascontiguousarray(ref.raster), ref.lo, ref.step, g, sp.half_width_mm, sp.spacing_mm,
                 sp.kernel_radius_cells, sp.max_abs_height_mm, sp.min_points, sp.max_leverage, True,
                 _FILL_CODES["laplace"], sp.half_width_mm * (1 + 2 / (g - 1)), np.zeros(4), instrument_params(sp),
                 X, n_used, n_bad, n_tool)
    return X[0]


@pytest.mark.parametrize("centre,noise,tilt", [((0.0, 0.0), 0.5, 0.0), ((-12.0, 5.0), 0.5, 0.0),
                                               ((0.0, 0.0), 1.5, 0.0), ((0.0, 0.0), 0.5, 30.0)])
@pytest.mark.slow  # one of the default set's slowest (CI's --durations): run with -m slow
def test_the_compiled_kernel_fits_the_dent_as_the_reference(centre, noise, tilt):
    """The numba pass's dent fit (over the sorted, distinct points, the instrument's moved off the grid) against
    cloud_grid's, on camera clouds of the punch with the tool in view, shuffled, a kinematic tip up to 1.5 mm off:
    mid-grid and near the grid's edge, at the model's noise and three times it, with the tilted shaft fit."""
    V, U0, T = plate(3.0)
    sp = spec(instrument_max_tilt_deg=tilt)
    p = np.array([-centre[0], -centre[1], 0.0])
    ref = ReferenceSurface.for_case(U0, T, p, np.eye(3), sp)
    cfg = ObservationConfig(noise_sd_mm=noise, roi_radius_mm=30.0, tool_radius_mm=R_TOOL, instrument_in_cloud=True)
    rng = np.random.default_rng(8)
    true_tip = np.array([0.0, 0.0, -3.0])
    g2 = 2 * sp.grid_size**2
    for seed in range(5):
        n = 400 + 1500 * seed
        cloud, _ = observe(V, T, true_tip, [0, 0, 1], ObservationConfig(**{**cfg.__dict__, "n_points": (n, n)}),
                           seed=seed)
        cloud = np.ascontiguousarray(cloud[rng.permutation(len(cloud))])
        kin = true_tip + rng.uniform(-1.5, 1.5, 3)
        want = cloud_grid(cloud, ref, sp, kin)
        x = _compiled_row(cloud, ref, sp, kin)
        assert want.dent[0] < -1.0  # a dent was found
        np.testing.assert_allclose(x[g2:g2 + camera.N_DENT], want.dent, atol=1e-9)
        np.testing.assert_allclose(x[:g2], want.features(include_mask=True), atol=1e-9)
        np.testing.assert_allclose(x[-3:], want.tip_local, atol=1e-9)
    few = np.ascontiguousarray(cloud[:30])  # a few points: no dent in either
    np.testing.assert_allclose(_compiled_row(few, ref, sp, kin)[g2:g2 + 2], cloud_grid(few, ref, sp, kin).dent,
                               atol=1e-9)


DENT_CAMERA = {"observation": {"n_points": [300, 3000], "noise_sd_mm": 0.3, "tool_radius_mm": R_TOOL,
                               "instrument_in_cloud": True},
               "grid": {"instrument_radius_mm": R_TOOL, "dent_radius_mm": 10.0}, "tip_noise_mm": 0.5}


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    from tests.learn.test_instrument import train_camera_model

    return train_camera_model(tmp_path_factory.mktemp("dent"), DENT_CAMERA)


@pytest.mark.slow  # one of the default set's slowest (CI's --durations): run with -m slow
def test_a_model_with_the_dent_reads_it_as_a_force_and_serves_it_on_both_paths(served):
    """The bundle keeps the dent columns; the regressor reads k amplitude / C_nn and the offset after f_lin and
    the strain; the compiled path gives the reference's features, forces, intervals and warnings."""
    from liverforce.learn.state import compliance_matrices
    from liverforce.serve import Predictor, Preop

    res, model, a = served
    pre = model.pre
    assert pre.dent_force and model.representation.dent
    assert pre.n_displacement_features == 3 + 1 + camera.N_DENT  # f_lin, the strain, the dent
    pred = Predictor.from_dir(res["model_path"])
    rng = np.random.default_rng(9)
    cfg = ObservationConfig(n_points=(2500, 2500), noise_sd_mm=0.3, roi_radius_mm=40.0, tool_radius_mm=R_TOOL,
                            instrument_in_cloud=True)
    for i in range(3):
        V, T = a["surface_meshes"][a["geometry_id"][i]]
        u = np.asarray(a["surface_displacement_mm"][i], dtype=np.float64)
        p = a["exertion_point_mm"][i]
        tip = p + u[int(np.argmin(np.linalg.norm(V - p, axis=1)))]
        cloud, _ = observe(V + u, T, tip, a["frame_normal"][i], cfg, seed=[20, i])
        cloud = cloud[rng.permutation(len(cloud))]
        kin = tip + rng.normal(0.0, 0.5, 3)
        ctx = Preop.from_arrays({k: v for k, v in a.items() if k != "roi_deformed_mm"}, i)
        arrays = {**ctx.to_arrays(ctx.roi_undeformed_mm), "camera_cloud_mm": [cloud], "tool_tip_mm": kin[None]}
        x = model.representation.features_of(arrays, R=ctx.rotation[None])
        s = model.representation.state_arrays(arrays)
        from liverforce.learn.state import state_vector

        sv = state_vector(s, R=ctx.rotation[None])
        feats = pre.state_features(sv, x)[0]
        k = pre.material_factor(sv, 1)[0, 0]
        np.testing.assert_allclose(feats[-2:], [k * x[0, -5] / compliance_matrices(sv)[0, 2, 2], x[0, -4]],
                                   rtol=1e-12)
        fast = pred.compile_cloud(ctx)
        want, info = pred.predict_cloud(cloud, ctx, tool_tip_mm=kin, return_info=True)
        got, half, warnings = fast.predict(cloud, kin)
        np.testing.assert_allclose(fast.features(cloud, kin), x[0], atol=1e-9)
        np.testing.assert_allclose(got, want, atol=1e-6)
        np.testing.assert_allclose(half, info["interval"]["half_width_local_n"], rtol=1e-9)
        assert warnings == info["warnings"]


def test_the_compiled_fit_gives_no_dent_where_the_reference_gives_none():
    """serve.compiled_cloud._dent_fit on the singular cases of the reference: points on one line through the axis
    (no slope across it), on one circle round it (the profile is a constant there), too few; and a regular ring."""
    from liverforce.serve.compiled_cloud import _dent_fit

    sp = spec()
    h, step = sp.half_width_mm, sp.spacing_mm

    def both(u, v, z):
        got = _dent_fit((u + h) / step, (v + h) / step, z, len(u), h, step, 0.0, 0.0, R_TOOL, sp.dent_radius_mm,
                        float(DENT_MIN_POINTS), 1e-10)  # a float, as the pass passes it: the pass's compiled code
        return np.array(got), fit_dent(u, v, z, (0.0, 0.0), sp)

    t = np.linspace(4.0, 12.0, 50)
    circle = np.linspace(0.0, 2.0 * math.pi, 60, endpoint=False)
    rng = np.random.default_rng(11)
    ru, rv = ring_points(600, rng)
    for u, v in ((t, 0 * t), (8.0 * np.cos(circle), 8.0 * np.sin(circle)), (t[:DENT_MIN_POINTS - 1], 0 * t[:11])):
        got, want = both(u, v, punch(u, v, 2.0) + 0.3 * u)
        np.testing.assert_array_equal(want, [0.0, 0.0])
        np.testing.assert_array_equal(got, [0.0, 0.0])
    got, want = both(ru, rv, punch(ru, rv, 2.0) + 0.3 * ru + rng.normal(0, 0.5, ru.size))
    np.testing.assert_allclose(got, want, atol=1e-9)
    assert want[0] == pytest.approx(-2.0, abs=0.5)


def test_the_compiled_asin_is_the_c_librarys_to_one_ulp():
    """serve.compiled_cloud._asin01 (fdlibm's approximations, branch-free, for the dent fit's SIMD loop) against
    math.asin over [0, 1]: within 1 ulp everywhere, exact at the ends of its ranges (0, 0.5, 0.975, 1) and at
    the points next to them, and in each of its three ranges."""
    from liverforce.serve.compiled_cloud import _asin01

    rng = np.random.default_rng(3)
    ends = [0.0, 0.5, 0.975, 1.0]
    x = np.concatenate([rng.uniform(0.0, 1.0, 20000), rng.uniform(0.5, 0.975, 20000), rng.uniform(0.975, 1.0, 5000),
                        ends, [np.nextafter(e, 0.5) for e in ends], [1e-300, 1e-8, np.nextafter(1.0, 0.0)]])
    got = np.array([_asin01(float(t)) for t in x])
    want = np.array([math.asin(float(t)) for t in x])
    ulp = np.spacing(np.maximum(np.abs(want), 1e-300))
    assert (np.abs(got - want) <= ulp).all(), x[np.abs(got - want) > ulp][:5]
    assert got[-10:-7].tolist() == [math.asin(e) for e in ends[1:]] and got[-11] == 0.0


def test_the_compiled_dent_fit_reads_every_point_within_its_radius_from_the_sort_bins():
    """serve.compiled_cloud._dent_fit_bins (the bins within the dent radius of the axis, as _grid_one sorts the
    points) against _dent_fit over every point: the same fit to rounding, for axes in the middle, near and off
    the grid's edge, and on points placed just inside and just outside the dent radius on the bins' edges."""
    from liverforce.serve import compiled_cloud as cc

    sp = spec()
    g, h, step, kr = sp.grid_size, sp.half_width_mm, sp.spacing_mm, sp.kernel_radius_cells
    sb, pad, nc, _ = cc._bins(g, kr)
    rng = np.random.default_rng(5)
    reach = h + kr * step
    for tu, tv in ((0.0, 0.0), (3.3, -7.1), (-18.0, 16.5), (reach - 1.0, 0.0)):
        u, v = rng.uniform(-reach, reach, 6000), rng.uniform(-reach, reach, 6000)
        t = rng.uniform(0.0, 2.0 * math.pi, 400)
        rim = np.concatenate([np.full(200, np.nextafter(sp.dent_radius_mm, 0.0)), np.full(200, sp.dent_radius_mm)])
        u = np.concatenate([u, tu + rim * np.cos(t)])
        v = np.concatenate([v, tv + rim * np.sin(t)])
        keep = (np.abs(u) < reach) & (np.abs(v) < reach)
        u, v = u[keep], v[keep]
        GU, GV = (u + h) / step, (v + h) / step
        z = punch(u, v, 2.0, (tu, tv)) + 0.3 * u + rng.normal(0.0, 0.3, u.size)
        key = np.array([cc._bin_key(a, b, sb, pad, nc) for a, b in zip(GU, GV)])
        order = np.argsort(key, kind="stable")
        first = np.zeros(nc * nc + 1, dtype=np.int32)
        first[1:] = np.cumsum(np.bincount(key, minlength=nc * nc))
        args = (h, step, tu, tv, R_TOOL, sp.dent_radius_mm, DENT_MIN_POINTS, 1e-10)
        want = cc._dent_fit(GU, GV, z, len(GU), *args)
        got = cc._dent_fit_bins(GU[order], GV[order], z[order], first, sb, pad, nc, *args)
        assert want[0] < -1.0
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
