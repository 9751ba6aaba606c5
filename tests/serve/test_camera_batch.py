"""The compiled camera-cloud path (liverforce.serve.compiled_cloud): its features equal the reference
cloud_grid's to rounding, its forces the reference predict_cloud's, and predict_batch gives every cloud exactly
what predict gives it, with refused clouds reported by reason while the rest of the batch is predicted."""
from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest

from liverforce.learn.cloud_features import cloud_grid
from liverforce.learn.model import ForceModel, subset
from liverforce.learn.observation import ObservationConfig, observe
from liverforce.learn.synthetic import synthetic_surface_arrays
from liverforce.learn.train import train_scenario
from liverforce.serve import Predictor, Preop
from liverforce.serve.errors import PredictionInputError

MODEL = {"encoder": "pca", "code_size": 6, "state_vector": True, "grid_size": 8, "hidden": [16, 16],
         "dropout": 0.0, "occlusion": {"radius_mm": 0.0, "mode": "remove"}, "noise_mm": 0.0,
         "roi_features": "cloud", "force_scaling": "stiffness", "probe_force_radius_mm": 5.0,
         "indentation_strain": True,  # as the shipped camera model: the compiled path reads tip_n / h too
         "camera": {"observation": {"n_points": [300, 3000], "noise_sd_mm": 0.3}, "grid": {}, "tip_noise_mm": 0.1}}
TRAIN = {"test_fraction": 0.2, "epochs": 8, "batch_size": 32, "lr": 3e-3, "weight_decay": 0.0, "seed": 0,
         "interval": {"coverage": 0.9, "calibration_fraction": 0.25}}
NO_TUNE = {"enabled": False, "trials": 1, "folds": 2, "sobol_trials": 1, "epochs": 1}


@pytest.fixture(scope="module", params=[("mlp", "stiffness"), ("gp_ensemble", "none"), ("gp", "linear")])
def served(request, tmp_path_factory):
    """The compiled camera path of a small camera model, with each regressor (the MLP, the GP ensemble over
    PCA code sizes, and one GP) and force scaling (the predicted force or the linear force estimate scaled by
    the stiffness, or neither). The GP ensemble has the shipped camera model's settings: no force scaling,
    a grid kernel of 1.5 cells, and an interval scaled by the predicted force and by the members' spread (a
    half-width per cloud)."""
    arrays = synthetic_surface_arrays(80, n_geometries=3, seed=3, material_varies=True)
    regressor, scaling = request.param
    members = [2, 4, 6] if regressor == "gp_ensemble" else None
    camera = MODEL["camera"] if members is None else {**MODEL["camera"], "grid": {"kernel_radius_cells": 1.5}}
    # the shipped interval (scaled by the predicted force) with the shipped camera settings
    train = TRAIN if members is None else {**TRAIN, "interval": {**TRAIN["interval"], "scale": "force",
                                                                  "spread": 4.0}}
    res = train_scenario(arrays, {**MODEL, "regressor": "mlp" if regressor == "mlp" else "gp",
                                  "force_scaling": scaling, "camera": camera,
                                  "gp": {"max_points": 2000, "iterations": 100, "code_members": members}},
                         train, NO_TUNE, "IV", "cloud", out_dir=tmp_path_factory.mktemp("cam-batch"))
    pred = Predictor(ForceModel.load(res["model_path"]))
    assert pred.model.pre.indentation_strain
    assert (type(pred.model.regressor).__name__ == "GPEnsemble") == (members is not None)
    assert pred.model.interval.uses_spread == (members is not None)
    test = np.flatnonzero(np.isin(arrays["geometry_id"], res["split"]["test_geometries"]))
    a = subset(arrays, test)
    ctx = Preop.from_arrays({k: v for k, v in a.items() if k != "roi_deformed_mm"}, 0)
    return pred, a, ctx, pred.compile_cloud(ctx)


def _observe(a: dict, i: int, n_points: int, seed: int):
    V, T = a["surface_meshes"][a["geometry_id"][i]]
    u = np.asarray(a["surface_displacement_mm"][i], dtype=np.float64)
    p = a["exertion_point_mm"][i]
    tip = p + u[int(np.argmin(np.linalg.norm(V - p, axis=1)))]
    cfg = ObservationConfig(n_points=(n_points, n_points), noise_sd_mm=0.3, roi_radius_mm=40.0)
    return observe(V + u, T, tip, a["frame_normal"][i], cfg, seed=seed)[0], tip


def _clouds(a: dict, k: int = 6):
    """Clouds of case 0 (the compiled context): densities 300-5000, one with duplicated points, one with a hole."""
    out = [_observe(a, 0, n, seed) for seed, n in enumerate(np.linspace(300, 5000, k).astype(int))]
    c, tip = out[1]
    dup = np.concatenate([c, c[::3]])[np.random.default_rng(0).permutation(len(c) + len(c[::3]))]
    out.append((dup, tip))
    c, tip = out[2]
    far = np.linalg.norm(c - tip, axis=1) > 8.0  # a hole around the tool: cells filled by the Laplace rule
    out.append((c[far], tip))
    return out


def test_compiled_features_equal_the_reference_cloud_grid(served):
    pred, a, ctx, fast = served
    filled = 0
    for cloud, tip in _clouds(a):
        ref = cloud_grid(cloud, fast.ref, fast.spec).features(include_mask=True)
        x = fast.features(cloud, tip)
        g2 = fast.g ** 2
        np.testing.assert_array_equal(x[g2:2 * g2], ref[g2:])  # the same valid cells
        np.testing.assert_allclose(x[:-3], ref, rtol=0, atol=1e-9)
        np.testing.assert_allclose(x[-3:], fast.R @ (tip - fast.p), rtol=0, atol=1e-12)
        filled += int((ref[g2:] == 0).sum())
    assert filled > 0  # the Laplace fill was exercised


@pytest.mark.parametrize("kr", [0.7, 1.25, 1.5, 1.6, 2.0])
def test_compiled_features_with_another_kernel_radius(served, kr):
    """Kernel radii other than one cell (more or fewer bin rows per grid point; sort bins a quarter (1.25) or half
    (0.7, 1.5, 1.6) grid step wide), and points present three times."""
    pred, a, ctx, fast = served
    other = copy.copy(fast)
    other.spec = dataclasses.replace(fast.spec, kernel_radius_cells=kr)
    (c, tip), (c2, tip2) = _clouds(a, 2)[:2]
    triple = np.concatenate([c2, c2[::4], c2[::4]])[np.random.default_rng(2).permutation(len(c2) + 2 * len(c2[::4]))]
    g2 = fast.g ** 2
    for cloud, t in ((c, tip), (triple, tip2)):
        ref = cloud_grid(cloud, other.ref, other.spec).features(include_mask=True)
        x = other.features(cloud, t)
        np.testing.assert_array_equal(x[g2:2 * g2], ref[g2:])
        np.testing.assert_allclose(x[:-3], ref, rtol=0, atol=1e-9)


@pytest.mark.parametrize("g", [8, 40])
@pytest.mark.parametrize("kr", [1.0, 1.25, 1.5, 1.75, 2.0, 2.5, 0.7, 4 / 3, 1.5000000000000002])
def test_sort_bins_and_padded_runs_change_no_sum(g, kr):
    """The counting sort's bins, their groups of rows and the runs read on past a grid point's last bin
    (compiled_cloud._bins, _bin_key, _cell_moments) change no grid point's sums: on a lattice with points on
    bin edges and exactly on the kernel's edge (|du| = kr, du^2 + dv^2 = kr^2 for kr = 1.25, the float just
    inside), and on a sparse strip of it along the grid's left edge, for whole-step,
    half-step and quarter-step bins with exact edges and for radii without exact edges (0.7, 4/3, 1.5 + 1 ulp),
    each grid point counts exactly the points with the reference's test du^2 + dv^2 < kr^2 (cloud_features:
    d2 / kr^2 < 1), and its weighted sums agree with a sum over every point to rounding."""
    from liverforce.serve import compiled_cloud as cc

    sb, pad, nc, exact = cc._bins(g, kr)
    assert exact == (kr in ((1.0, 1.25, 1.5, 1.75, 2.0, 2.5) if g == 8 else (1.0, 2.0)))  # <= 64 bins over the grid
    inner = np.nextafter(kr, 0.0)
    offs = np.concatenate([np.arange(-24, 25) / 8.0, [kr, -kr, inner, -inner]])
    anchors = np.unique([0, 1, g // 2, g - 2, g - 1])
    ou, ov = np.meshgrid(offs, offs)
    au, av = np.meshgrid(anchors, anchors)  # every offset around every pair of anchor grid points
    GU = np.add.outer(au.ravel(), ou.ravel()).ravel()
    GV = np.add.outer(av.ravel(), ov.ravel()).ravel()
    rng = np.random.default_rng(0)
    GU = np.concatenate([GU, rng.uniform(-kr, g - 1 + kr, 3000)])
    GV = np.concatenate([GV, rng.uniform(-kr, g - 1 + kr, 3000)])
    kept = (GU > -kr) & (GU < g - 1 + kr) & (GV > -kr) & (GV < g - 1 + kr)  # _grid_one keeps no other point
    GU, GV = GU[kept], GV[kept]
    count, on_edge = _check_moments(GU, GV, rng.normal(0.0, 2.0, len(GU)), g, kr, sb, pad, nc, exact)
    assert (count > 0).sum() > 0.5 * g * g
    assert on_edge > 0 or kr not in (1.0, 1.25, 1.5, 1.75, 2.0, 2.5)  # the edge was exercised
    # a sparse cloud, points only near the grid's left edge: a run read on to a multiple of 8 points reaches
    # the end of its group of bin rows, where it must stop (the next group's points are within the kernel)
    strip = (GU < 0.5) & (rng.random(len(GU)) < 0.3)
    count, _ = _check_moments(GU[strip], GV[strip], rng.normal(0.0, 2.0, int(strip.sum())), g, kr, sb, pad, nc,
                              exact)
    assert count[:g].sum() > 0  # grid points along the strip saw points


def _check_moments(GU, GV, Z, g, kr, sb, pad, nc, exact):
    """compiled_cloud._cell_moments of the points sorted as _grid_one sorts them (int32 keys and starts)
    against a sum over every (point, grid point) pair: counts exactly, sums to rounding. Returns each grid
    point's count and the pairs exactly on a kernel's edge."""
    from liverforce.serve import compiled_cloud as cc

    key = np.array([cc._bin_key(u, v, sb, pad, nc) for u, v in zip(GU, GV)])
    fl_u, fl_v = np.floor(GU * sb).astype(int) + pad, np.floor(GV * sb).astype(int) + pad
    assert (fl_u >= 0).all() and (fl_u < nc).all() and (fl_v >= 0).all() and (fl_v < nc).all()
    assert nc % sb == 0 and (not exact or (pad - kr * sb) % sb == 0)  # whole groups; a window starts a group
    # no kept point is clamped; groups of sb bin rows, column by column within a group
    np.testing.assert_array_equal(key, (fl_v // sb) * nc * sb + fl_u * sb + fl_v % sb)
    order = np.argsort(key, kind="stable")
    first = np.zeros(nc * nc + 1, dtype=np.int32)  # as the kernel's workspace
    first[1:] = np.cumsum(np.bincount(key, minlength=nc * nc))
    M = np.zeros((g * g, 10))
    cc._cell_moments(GU[order], GV[order], Z[order], first, g, kr, sb, pad, nc, exact, M)
    # every (point, grid point within ceil(kr) + 1 of its nearest) pair, as cloud_features.cloud_grid pairs them
    c = int(np.ceil(kr)) + 1
    o = np.arange(-c, c + 1)
    I = np.rint(GV).astype(int)[None, :] + np.repeat(o, o.size)[:, None]
    J = np.rint(GU).astype(int)[None, :] + np.tile(o, o.size)[:, None]
    du, dv = GU[None, :] - J, GV[None, :] - I
    d2 = du * du + dv * dv
    on_grid = (I >= 0) & (I < g) & (J >= 0) & (J < g)
    on_edge = int((on_grid & (d2 == kr * kr)).sum())  # points exactly on a grid point's kernel edge: not counted
    inside = (d2 < kr * kr) & on_grid
    cell = (I * g + J)[inside]
    w = (1.0 - d2[inside] / (kr * kr)) ** 2
    z = np.broadcast_to(Z, d2.shape)[inside]
    du, dv = du[inside], dv[inside]
    want = np.column_stack([np.bincount(cell, weights=x, minlength=g * g) for x in
                            (w, np.ones_like(w), w * z, w * du, w * dv, w * du * du, w * dv * dv, w * du * dv,
                             w * du * z, w * dv * z)])
    np.testing.assert_array_equal(M[:, 1], want[:, 1])  # the same points, exactly
    np.testing.assert_allclose(M, want, rtol=1e-12, atol=1e-9)
    return want[:, 1], on_edge


def test_every_kernel_names_its_fast_math_flags():
    """Every numba kernel of the compiled camera path (compiled_cloud's, and the GP head's gp._rq_power_mean)
    names its fast-math flags and error model: numba gives a function that names none its caller's, and the
    first caller to compile a signature fixes its machine code for every caller (on disk too, cache=True), so
    the pass's bits would depend on which test or caller compiled a kernel first. On an input where the pass's
    fused multiply-adds change the last bits of _spd4_solve (the dent fit's and the tilted fit's 4 x 4 solve),
    a copy of it with its own options, compiled through a caller without fast-math and through one with every
    flag, gives the bits it has in the pass (compiled with "contract") both times."""
    from numba import njit
    from numba.core.registry import CPUDispatcher

    from liverforce.learn import gp
    from liverforce.serve import compiled_cloud as cc

    kernels = {name: f for name, f in vars(cc).items()
               if isinstance(f, CPUDispatcher) and f.py_func.__module__ == cc.__name__}
    kernels["gp._rq_power_mean"] = gp._rq_power_mean
    assert len(kernels) > 30 and "_grid_one" in kernels and "_spd4_solve" in kernels
    unnamed = sorted(name for name, f in kernels.items() if not {"fastmath", "error_model"} <= f.targetoptions.keys())
    assert not unnamed, f"kernels that inherit their caller's fast-math flags or error model: {unnamed}"
    rng = np.random.default_rng(0)
    M = rng.normal(size=(4, 4))
    args = (*(M @ M.T + np.eye(4))[np.triu_indices(4)], *rng.normal(size=4))  # upper triangle, then b
    solve = cc._spd4_solve.py_func
    fused = njit(fastmath={"contract"}, error_model="python")(solve)(*args)
    assert fused != njit(fastmath=False, error_model="python")(solve)(*args)  # the flag changes these bits
    opts = {k: v for k, v in cc._spd4_solve.targetoptions.items() if k not in ("cache", "nopython")}
    for caller_flags in (False, True):
        callee = njit(**opts)(solve)  # a fresh copy: compiled by its first caller, below
        assert njit(fastmath=caller_flags)(lambda *a: callee(*a))(*args) == fused, caller_flags


def test_compiled_predict_equals_the_reference_path(served):
    pred, a, ctx, fast = served
    for cloud, tip in _clouds(a):
        want, info = pred.predict_cloud(cloud, ctx, tool_tip_mm=tip, return_info=True)
        got, half, warnings = fast.predict(cloud, tip)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)
        np.testing.assert_allclose(half, info["interval"]["half_width_local_n"], rtol=1e-12)
        assert warnings == info["warnings"]


def test_batch_equals_per_cloud_predictions(served):
    pred, a, ctx, fast = served
    items = _clouds(a)
    clouds = [c for c, _ in items]
    tips = np.stack([t for _, t in items]) + np.random.default_rng(1).normal(0, 0.2, (len(items), 3))
    single = np.stack([fast.predict(c, t)[0] for c, t in zip(clouds, tips)])
    res = fast.predict_batch(clouds, tips)
    assert res.force.shape == (len(clouds), 3) and res.ok.all() and res.refused == [None] * len(clouds)
    np.testing.assert_allclose(res.force, single, rtol=0, atol=1e-9)
    half = np.stack([fast.predict(c, t)[1] for c, t in zip(clouds, tips)])
    np.testing.assert_allclose(res.half_width, half, rtol=1e-12)
    def compiled_with(interval: dict | None):
        model = copy.copy(pred.model)
        model.meta = {**model.meta, "interval": interval}
        return Predictor(model).compile_cloud(ctx)

    # each cloud's own width from its force, whatever scale the fixture's model was calibrated with (the scales
    # without the members' spread: the widths then read the force alone)
    m = np.linalg.norm(res.force, axis=1)
    assert np.ptp(m) > 0
    k_rows = np.full((len(m), 1), fast.k_material)
    sloped = compiled_with({**fast.interval.to_dict(), "scale": "force", "force_scale": [[0.1, 0.05]] * 3,
                            "spread_beta": None})
    h2 = sloped.predict_batch(clouds, tips).half_width  # with a positive slope, wider for a larger force
    assert (h2[np.argmax(m)] > h2[np.argmin(m)]).all()
    np.testing.assert_allclose(h2, sloped.interval.half_widths(k_rows, res.force), rtol=1e-12)
    edge = float(np.median(m))  # force_bins: one width below the median |F|, three times it above
    binned = compiled_with({**fast.interval.to_dict(), "scale": "force_bins", "bin_edges_n": [edge],
                            "bin_half_width_n": [[0.1, 0.1, 0.2], [0.3, 0.3, 0.6]], "spread_beta": None})
    h3 = binned.predict_batch(clouds, tips).half_width
    np.testing.assert_allclose(h3, binned.interval.half_widths(k_rows, res.force), rtol=1e-12)
    kf = binned.interval.stiffness_factor(np.array([[fast.k_material]]))[0, 0]
    np.testing.assert_allclose(h3, kf * np.where((m >= edge)[:, None], [[0.3, 0.3, 0.6]], [[0.1, 0.1, 0.2]]),
                               rtol=1e-12)
    np.testing.assert_allclose(binned.predict(clouds[0], tips[0])[1], h3[0], rtol=1e-12)
    # widen: fitted, the context's liver stiffer than every calibration case: a factor per component
    k = fast.k_material
    fitted = compiled_with({**binned.interval.to_dict(), "stiffness_range": [0.5 * k, 0.8 * k], "widen": "fitted",
                            "stiffness_exponent": [0.5, -0.3, 1.0]})
    h4 = fitted.predict_batch(clouds, tips).half_width
    np.testing.assert_allclose(h4, fitted.interval.half_widths(k_rows, res.force), rtol=1e-12)
    np.testing.assert_allclose(h4 / h3, np.tile([[1.25 ** 0.5, 1.0, 1.25]], (len(m), 1)) / kf, rtol=1e-12)
    np.testing.assert_allclose(fitted.predict(clouds[0], tips[0])[1], h4[0], rtol=1e-12)
    # a model without an interval: the force alone, and None for the widths
    bare = compiled_with(None)
    f0, h0, _ = bare.predict(clouds[0], tips[0])
    np.testing.assert_array_equal(f0, single[0])
    assert h0 is None and bare.predict_batch(clouds, tips).half_width is None
    # one padded array with counts; float32 clouds (as parquet stores them) too
    N = max(len(c) for c in clouds)
    pad = np.full((len(clouds), N, 3), np.nan)
    for k, c in enumerate(clouds):
        pad[k, :len(c)] = c
    res2 = fast.predict_batch(pad, tips, counts=[len(c) for c in clouds])
    np.testing.assert_allclose(res2.force, single, rtol=0, atol=1e-9)
    np.testing.assert_allclose(res2.half_width, half, rtol=1e-9)  # and the widths (the spread's too)
    c32 = [c.astype(np.float32) for c in clouds]
    single32 = np.stack([fast.predict(c, t)[0] for c, t in zip(c32, tips)])
    np.testing.assert_allclose(fast.predict_batch(c32, tips).force, single32, rtol=0, atol=1e-9)
    # a padded float32 array is read as it is; one in another layout is converted a chunk at a time
    n = [len(c) for c in clouds]
    np.testing.assert_allclose(fast.predict_batch(pad.astype(np.float32), tips, counts=n).force, single32, rtol=0,
                               atol=1e-9)
    np.testing.assert_allclose(fast.predict_batch(np.asfortranarray(pad), tips, counts=n).force, single, rtol=0,
                               atol=1e-9)
    # read-only clouds (as Arrow buffers give them) beside writable ones
    ro = [c.copy() for c in clouds]
    for c in ro[::2]:
        c.flags.writeable = False
    np.testing.assert_allclose(fast.predict_batch(ro, tips).force, single, rtol=0, atol=1e-9)


def test_a_refused_cloud_does_not_poison_the_batch(served):
    pred, a, ctx, fast = served
    (cloud, tip), (other, tip2) = _clouds(a, 2)[:2]
    nan = cloud.copy()
    nan[7, 1] = np.nan
    R, h = ctx.frame, fast.half_width_mm
    loc = (cloud - ctx.exertion_point_mm) @ R.T
    corner = cloud[(loc[:, 0] > 0.6 * h) & (loc[:, 1] > 0.6 * h)]
    bad = {1: (cloud[:5], tip), 2: (cloud / 1000.0, tip), 3: (nan, tip),
           4: (cloud, ctx.exertion_point_mm + 3 * h), 6: (corner, tip), 7: (np.zeros((0, 3)), tip),
           8: (np.ones((4, 2)), tip), 9: (np.ones((4, 2)), np.array([np.nan, 0.0, 0.0])),
           10: (nan, np.array([np.nan, 0.0, 0.0]))}
    items = [(cloud, tip), *[None] * 4, (other, tip2), *[None] * 5]
    for k, v in bad.items():
        items[k] = v
    res = fast.predict_batch([c for c, _ in items], np.stack([t for _, t in items]))
    assert list(np.flatnonzero(res.ok)) == [0, 5]
    np.testing.assert_allclose(res.force[0], fast.predict(cloud, tip)[0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(res.force[5], fast.predict(other, tip2)[0], rtol=0, atol=1e-9)
    assert np.isnan(res.force[list(bad)]).all() and np.isnan(res.half_width[list(bad)]).all()
    np.testing.assert_allclose(res.half_width[0], fast.predict(cloud, tip)[1], rtol=1e-12)
    for k, (c, t) in bad.items():  # the reference path refuses each with the same reason
        with pytest.raises(PredictionInputError) as exc:
            pred.predict_cloud(c, ctx, tool_tip_mm=t)
        assert res.refused[k] == str(exc.value), k
        with pytest.raises(PredictionInputError):
            fast.predict(c, t)
    # a mild departure is predicted with the reference's warning
    top = pred.model.meta["training_scale"]["camera"]["tip_displacement_max_mm"]
    push = ctx.exertion_point_mm - 1.3 * top * R[2]
    res = fast.predict_batch([cloud, cloud], np.stack([tip, push]))
    _, info = pred.predict_cloud(cloud, ctx, tool_tip_mm=push, return_info=True)
    assert res.ok.all() and res.warnings[0] == fast.context_warnings  # the context's (if any), nothing of the cloud's
    assert res.warnings[1] == info["warnings"] and len(_inputs(info["warnings"])) == len(fast.context_warnings) + 1


def _inputs(warnings: list) -> list:
    """The warnings about the inputs: without a force beyond training's (a deep push may also give one)."""
    return [w for w in warnings if not w.startswith("the predicted force")]


def test_a_batch_gridded_in_threads_gives_the_same_bits(served, monkeypatch):
    """predict_batch(threads=N) cuts the batch into N contiguous parts gridded at once (the kernels release the
    GIL), and runs the head's blocks in the threads too; every cloud's force, width, warnings and refusal are the
    same bits as on one thread, for a list (refused clouds among them) and a padded array, an uneven cut, more
    threads than clouds and a batch of several head blocks."""
    from liverforce.serve import compiled_cloud

    pred, a, ctx, fast = served
    items = _clouds(a)
    clouds = [c for c, _ in items] + [items[0][0][:5], np.ones((4, 2))]  # two refused: too few points, not (n, 3)
    tips = np.stack([t for _, t in items] + [items[0][1]] * 2)
    parts, blocks = [], []
    real = compiled_cloud.ThreadPoolExecutor

    class Counting(real):
        def submit(self, fn, *args):
            (parts if fn.__name__ == "part" else blocks).append(args)  # the gridding's parts, the head's blocks
            return super().submit(fn, *args)

    monkeypatch.setattr(compiled_cloud, "ThreadPoolExecutor", Counting)
    one = fast.predict_batch(clouds, tips)
    assert not parts and one.ok.sum() == len(items) and one.refused[-2] and one.refused[-1]
    for threads in (2, 3, 40):
        many = fast.predict_batch(clouds, tips, threads=threads)
        np.testing.assert_array_equal(many.force, one.force)
        np.testing.assert_array_equal(many.half_width, one.half_width)
        assert many.refused == one.refused and many.warnings == one.warnings
    # as many parts as threads, at most the cores (and clouds): each a contiguous run, together every gridded
    # cloud once (the one that is not (n, 3) never reaches the kernel; the 5 points are refused after it)
    n_grid = len(clouds) - 1
    sizes = [min(t, compiled_cloud.cores(), n_grid) for t in (2, 3, 40)]
    cuts, at = [], 0
    for k in sizes:
        cuts.append(parts[at:at + k])
        at += k
    assert at == len(parts) and not blocks  # one block of the head: run where it is
    for cut in (c for c in cuts if len(c) > 1):
        assert [s for s, _ in cut] == [0] + [e for _, e in cut[:-1]] and cut[-1][1] == n_grid
        assert max(e - s for s, e in cut) - min(e - s for s, e in cut) <= 1
    N = max(len(c) for c in clouds[:len(items)])
    pad = np.full((len(items), N, 3), np.nan)
    for k, c in enumerate(clouds[:len(items)]):
        pad[k, :len(c)] = c
    n = [len(c) for c in clouds[:len(items)]]
    np.testing.assert_array_equal(fast.predict_batch(pad, tips[:len(items)], counts=n, threads=2).force,
                                  fast.predict_batch(pad, tips[:len(items)], counts=n).force)
    # a padded array in another layout: converted a chunk (_CHUNK clouds) at a time, each chunk in threads
    fort = np.asfortranarray(np.concatenate([pad] * (compiled_cloud._CHUNK // len(items) + 2)))
    n_f, tips_f = n * (len(fort) // len(items)), np.resize(tips[:len(items)], (len(fort), 3))
    np.testing.assert_array_equal(fast.predict_batch(fort, tips_f, counts=n_f, threads=2).force,
                                  fast.predict_batch(fort, tips_f, counts=n_f).force)
    assert compiled_cloud._grid_list.targetoptions["nogil"] and compiled_cloud._grid_clouds.targetoptions["nogil"]
    # a batch of more than one block of the head (_HEAD_ROWS): the blocks in threads too, the same bits
    big = (clouds * (2 * compiled_cloud._HEAD_ROWS // len(clouds) + 1))[:2 * compiled_cloud._HEAD_ROWS + 5]
    tips_big = np.resize(tips, (len(big), 3))
    one = fast.predict_batch(big, tips_big)
    blocks.clear()
    for threads in (2, 3):
        many = fast.predict_batch(big, tips_big, threads=threads)
        np.testing.assert_array_equal(many.force, one.force)
        np.testing.assert_array_equal(many.half_width, one.half_width)
        assert many.refused == one.refused
    if compiled_cloud.cores() > 1:  # the head's blocks of the predicted clouds, each run in the pool
        assert len(blocks) == 2 * -(-int(one.ok.sum()) // compiled_cloud._HEAD_ROWS) >= 4
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(PredictionInputError, match="threads"):
            fast.predict_batch(clouds, tips, threads=bad)


def test_empty_batch(served):
    pred, a, ctx, fast = served
    res = fast.predict_batch([], np.zeros((0, 3)))
    assert res.force.shape == (0, 3) and res.warnings == [] and res.refused == [] and res.ok.shape == (0,)
    res = fast.predict_batch(np.zeros((0, 100, 3)), np.zeros((0, 3)))
    assert res.force.shape == (0, 3) and res.refused == []
    with pytest.raises(PredictionInputError, match="one"):
        fast.predict_batch([np.zeros((30, 3))], np.zeros((2, 3)))


def test_a_cloud_beyond_the_32_bit_indices_is_refused_by_name(served, monkeypatch):
    """The kernel's sort keys and indices are 32-bit: a larger cloud is refused, never wrapped around (the
    limit, 2^31 - 1 points, is lowered here to try it)."""
    from liverforce.serve import compiled_cloud as cc

    pred, a, ctx, fast = served
    cloud, tip = _clouds(a, 3)[2]
    monkeypatch.setattr(cc, "_MAX_POINTS", len(cloud) - 1)
    with pytest.raises(PredictionInputError, match=f"cloud: {len(cloud)} points; the compiled path takes at most"):
        fast.predict(cloud, tip)
    res = fast.predict_batch([cloud[:-1], cloud], np.stack([tip, tip]))
    assert list(res.ok) == [True, False] and "the compiled path takes at most" in res.refused[1]
    with pytest.raises(PredictionInputError, match="points per cloud; the compiled path takes at most"):
        fast.predict_batch(cloud[None], tip[None])


@pytest.mark.parametrize("served", [("gp", "linear")], indirect=True)
def test_gp_head_equals_the_regressors_posterior_mean(served):
    """The compiled path's GP head (GPRegressor.numpy_head, distances and linear term folded, the context's
    state held in it) gives the torch module's posterior mean on rows with that state, also near the training
    inputs, where the squared distances cancel most."""
    import torch

    pred, a, ctx, fast = served
    gp = pred.model.regressor
    assert fast.gp is not None and fast.uses_state
    X = gp.X.numpy()
    nz, ns = fast.A.shape[0], fast.s_base.size
    free = np.r_[0:nz, nz + ns:X.shape[1]]  # the code and f_lin columns: what the head reads per cloud
    rng = np.random.default_rng(4)
    near = X[rng.integers(0, len(X), 40)] + rng.normal(0, 0.05, (40, X.shape[1]))
    for Z in (near, X[:40], rng.normal(0, 1, (40, X.shape[1]))):
        Z = Z.astype(np.float32)  # as the compiled path feeds it
        Z[:, nz:nz + ns] = fast.s_base.astype(np.float32)  # the context's state
        with torch.no_grad():
            want = gp(torch.from_numpy(Z.astype(np.float64))).numpy()
        got = fast.gp(Z[:, free])
        if fast._spread:  # the ensemble's head also gives its members' sd (the interval's spread)
            got, sd = got
            with torch.no_grad():
                each = gp.forward_members(torch.from_numpy(Z.astype(np.float64))).numpy()
            assert sd.shape == want.shape and (sd > 0).all()
            np.testing.assert_allclose(sd, each.std(axis=0, ddof=1), rtol=1e-6, atol=1e-9 * np.abs(want).max())
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9 * np.abs(want).max())
    with pytest.raises(ValueError, match=f"rows of {free.size} inputs"):  # the full row is not what it takes
        fast.gp(Z)


def _capped(pred, cap_n: float) -> Predictor:
    """The same model, its recorded training forces' largest magnitude set to ``cap_n``."""
    model = copy.copy(pred.model)
    model.meta = copy.deepcopy(pred.model.meta)
    model.meta["training_scale"]["force_magnitude_n"][1] = cap_n
    return Predictor(model)


def test_a_force_beyond_the_training_forces_is_warned_on_every_path(served):
    """A predicted |F| above every training case's comes with a warning naming both, after the inputs' warnings,
    on the reference path, the compiled path (one cloud and a batch) and predict_arrays (the MLflow pyfunc's and
    --shards' path), which also gives a camera cloud's own warnings as predict_cloud does. The model is the
    served one with its recorded largest training force lowered below the clouds' forces; the served model
    itself warns about none of the three clouds of the case as simulated."""
    pred, a, ctx, fast = served
    items = _clouds(a, 3)[:3]
    top = pred.model.meta["training_scale"]["camera"]["tip_displacement_max_mm"]
    items.append((items[0][0], ctx.exertion_point_mm - 1.3 * top * ctx.frame[2]))  # a cloud warning as well
    clouds, tips = [c for c, _ in items], np.stack([t for _, t in items])
    plain = [pred.predict_cloud(c, ctx, tool_tip_mm=t, return_info=True) for c, t in items]
    mags = np.array([np.linalg.norm(f) for f, _ in plain])
    assert all(_inputs(info["warnings"]) == info["warnings"] for _, info in plain[:3])
    capped = _capped(pred, 0.5 * mags.min())
    cfast = capped.compile_cloud(ctx)
    batch = cfast.predict_batch(clouds, tips)
    n = len(items)
    rows = {k: np.repeat(v, n, axis=0) if isinstance(v, np.ndarray) else [v[0]] * n
            for k, v in ctx.to_arrays(ctx.roi_undeformed_mm).items()}
    rows.update({"camera_cloud_mm": clouds, "tool_tip_mm": tips})
    force, warned = capped.predict_arrays(rows, return_warnings=True)
    for k, ((c, t), (f0, info0)) in enumerate(zip(items, plain)):
        f, info = capped.predict_cloud(c, ctx, tool_tip_mm=t, return_info=True)
        assert info["warnings"][:-1] == _inputs(info0["warnings"])  # the inputs' warnings first, unchanged
        assert info["warnings"][-1].startswith(f"the predicted force ({mags[k]:.4g} N) exceeds every training "
                                               f"case's (at most {0.5 * mags.min():.4g} N)")
        assert cfast.predict(c, t)[2] == info["warnings"] and batch.warnings[k] == info["warnings"]
        assert warned[k] == info["warnings"]
        np.testing.assert_allclose(force[k], f, rtol=0, atol=1e-6)
    assert len(_inputs(plain[3][1]["warnings"])) > len(plain[0][1]["warnings"])  # the deep push's tip warning is kept
    refused = cfast.predict_batch([clouds[0][:5]], tips[:1])  # a refused cloud: its reason, no force warning
    assert refused.refused[0] is not None and refused.warnings == [[]]


def test_a_cloud_in_metres_is_refused_as_one_on_every_path(served):
    """A cloud given in metres (read as mm it spans a fraction of a millimetre) is refused, naming metres and
    --units m, by the reference path, the compiled path and predict_arrays alike: off the grid, and also lying
    over it (a frame whose origin is near the exertion point), where the grid's coverage would refuse it first.
    A cloud in mm that misses the grid, and twenty identical points, are not called metres."""
    pred, a, ctx, fast = served
    cloud, tip = _clouds(a, 2)[0]
    p = ctx.exertion_point_mm
    over = p + (cloud - p) / 1000.0  # metres about the exertion point: every point over the grid
    same = np.repeat(cloud[:1] + 10 * fast.half_width_mm * ctx.frame[0], 20, axis=0)
    n = 1
    row = {k: np.repeat(v, n, axis=0) if isinstance(v, np.ndarray) else [v[0]] * n
           for k, v in ctx.to_arrays(ctx.roi_undeformed_mm).items()}
    for c, metres in ((cloud / 1000.0, True), (over, True), (cloud + 10 * fast.half_width_mm * ctx.frame[0], False),
                      (same, False)):
        with pytest.raises(PredictionInputError) as exc:
            pred.predict_cloud(c, ctx, tool_tip_mm=tip)
        assert ("looks like metres read as mm; give --units m" in str(exc.value)) == metres
        assert fast.predict_batch([c], tip[None]).refused == [str(exc.value)]
        with pytest.raises(PredictionInputError) as exc2:
            fast.predict(c, tip)
        assert str(exc2.value) == str(exc.value)
        with pytest.raises(PredictionInputError) as exc3:
            pred.predict_arrays({**row, "camera_cloud_mm": [c], "tool_tip_mm": tip[None]})
        assert ("looks like metres read as mm" in str(exc3.value)) == metres


def test_gross_depth_errors_are_dropped_and_warned_about_alike_on_every_path(served):
    """With ``camera.grid.outlier_mm`` (set here on the served model, trained without it) a cloud with 20 % of
    its points up to 10 mm off along their lines of sight: the reference path, the compiled path (one cloud and a
    batch) and predict_arrays (the MLflow pyfunc's and --shards' path) drop the same points, give the same force
    and the same warning, which names the share; its force lies nearer the clean cloud's than without the
    filter, and the clean cloud gets no such warning."""
    import copy
    import dataclasses

    pred, a, ctx, fast = served
    model = copy.copy(pred.model)
    cam = copy.deepcopy(model.representation.camera)
    cam.setdefault("grid", {})["outlier_mm"] = 2.5
    model.representation = dataclasses.replace(model.representation, camera=cam)
    robust = Predictor(model)
    rfast = robust.compile_cloud(ctx)
    V, T = a["surface_meshes"][a["geometry_id"][0]]
    u = np.asarray(a["surface_displacement_mm"][0], dtype=np.float64)
    p = a["exertion_point_mm"][0]
    tip = p + u[int(np.argmin(np.linalg.norm(V - p, axis=1)))]
    base = dict(n_points=(3000, 3000), noise_sd_mm=0.3, roi_radius_mm=40.0)
    clean = observe(V + u, T, tip, a["frame_normal"][0], ObservationConfig(**base), seed=11)[0]
    dirty = observe(V + u, T, tip, a["frame_normal"][0], ObservationConfig(**base, outlier_fraction=0.2),
                    seed=11)[0]
    f_clean, info_clean = robust.predict_cloud(clean, ctx, tool_tip_mm=tip, return_info=True)
    assert not any("gross depth errors" in w for w in info_clean["warnings"])
    f, info = robust.predict_cloud(dirty, ctx, tool_tip_mm=tip, return_info=True)
    gross = [w for w in info["warnings"] if "gross depth errors" in w]
    assert len(gross) == 1 and "more than 2.5 mm off the surface" in gross[0], info["warnings"]
    share = float(gross[0].split(" %")[0])
    assert 10 < share <= 20
    got, _, warnings = rfast.predict(dirty, tip)
    np.testing.assert_allclose(got, f, rtol=0, atol=1e-6)
    assert warnings == info["warnings"]
    batch = rfast.predict_batch([clean, dirty], np.stack([tip, tip]))
    np.testing.assert_allclose(batch.force, [f_clean, f], rtol=0, atol=1e-6)
    assert batch.warnings == [info_clean["warnings"], info["warnings"]]
    n = 2
    rows = {k: np.repeat(v, n, axis=0) if isinstance(v, np.ndarray) else [v[0]] * n
            for k, v in ctx.to_arrays(ctx.roi_undeformed_mm).items()}
    rows.update({"camera_cloud_mm": [clean, dirty], "tool_tip_mm": np.stack([tip, tip])})
    force, warned = robust.predict_arrays(rows, return_warnings=True)
    np.testing.assert_allclose(force, [f_clean, f], rtol=0, atol=1e-6)
    assert warned == [info_clean["warnings"], info["warnings"]]
    plain_gap = np.linalg.norm(pred.predict_cloud(dirty, ctx, tool_tip_mm=tip)
                               - pred.predict_cloud(clean, ctx, tool_tip_mm=tip))
    assert np.linalg.norm(f - f_clean) < plain_gap


def test_the_forward_paths_spread_is_the_members_sd_of_the_local_force(served):
    """ForceModel.forward's spread_local (what the interval with ``spread`` reads) is the standard deviation over
    the GP ensemble's members of each member's own local force, each member run alone as the whole model; the
    mean of those forces is the model's force."""
    pred, a, ctx, fast = served
    model = pred.model
    fw = model.forward(a, observation_seed=0)
    reg = model.regressor
    if type(reg).__name__ != "GPEnsemble":
        assert fw.spread_local is None
        return
    from liverforce.learn.gp import GPEnsemble

    each = []
    for i, member in enumerate(reg.members):
        model.regressor = GPEnsemble([member], [reg.columns(i)])  # this member alone as the model's GP
        try:
            each.append(model.forward(a, observation_seed=0).force_local)
        finally:
            model.regressor = reg
    each = np.stack(each)
    np.testing.assert_allclose(each.mean(axis=0), fw.force_local, rtol=0, atol=1e-12)
    np.testing.assert_allclose(fw.spread_local, each.std(axis=0, ddof=1), rtol=1e-9, atol=1e-12)
    assert (fw.spread_local > 0).all()
    got = model.predict_interval(a, observation_seed=0)["half_width_local_n"]
    want = model.interval.half_widths(fw.stiffness, fw.force_local, each.std(axis=0, ddof=1))
    np.testing.assert_allclose(got, want, rtol=1e-9)


def test_an_interval_scaled_by_the_spread_on_a_regressor_without_members_is_refused_alike_on_both_paths(served):
    """A bundle whose interval reads the GP ensemble members' spread on a regressor without it (an ensemble of
    one member, one GP, an MLP): the compiled camera path refused one GP or an MLP in other words than the
    reference path, and gave an ensemble of one member a width as if its spread were 0; both now refuse it in
    the same words, and the force alone is still predicted."""
    from liverforce.learn.gp import GPEnsemble
    from liverforce.learn.model import ModelFormatError

    pred, a, ctx, fast = served
    cloud, tip = _observe(a, 0, 1000, 0)
    model = copy.copy(pred.model)
    reg = model.regressor
    if isinstance(reg, GPEnsemble):  # its interval reads the spread: keep one member
        assert model.interval.uses_spread
        model.regressor = GPEnsemble([reg.members[-1]], [reg.columns(len(reg.members) - 1)])
        what = "a GP ensemble of one member"
    else:
        assert not model.interval.uses_spread
        model.meta = {**model.meta, "interval": {**model.meta["interval"], "spread_beta": 4.0,
                                                 "spread_median_n": [0.1, 0.1, 0.2]}}
        what = "one GP" if type(reg).__name__ == "GPRegressor" else "an MLP"
    p = Predictor(model)
    with pytest.raises(ModelFormatError, match=f"its regressor is {what}, which has no members' spread") as compiled:
        p.compile_cloud(ctx)
    with pytest.raises(ModelFormatError) as reference:
        p.predict_cloud(cloud, ctx, tool_tip_mm=tip, return_info=True)
    assert str(compiled.value) == str(reference.value)
    assert np.isfinite(p.predict_cloud(cloud, ctx, tool_tip_mm=tip)).all()
