"""benchmarks/experiment_tip_from_cloud.py: its estimators of the tool tip's tangential position, checked against
geometry with a known answer (a surface slid along itself, a tool's shadow on a plane), the inputs of its estimators
along the normal (a dent of known profile with a shaft in it), and its folds by liver."""
from __future__ import annotations

import numpy as np

from benchmarks.experiment_tip_from_cloud import (RIM_RINGS_MM, SHAFT_QUANTILES, _by_group_folds, _segment_distances,
                                                  normal_features, parallax_shift, ridge_cv, ring_features,
                                                  score_normal, shadow_estimate)
from liverforce.learn.cloud_features import CloudGridSpec, ReferenceSurface, instrument_search_radius
from liverforce.learn import camera
from liverforce.learn.observation import ObservationConfig, observe
from liverforce.learn.synthetic import synthetic_surface_arrays


def quadratic(U, V):
    return 0.012 * U ** 2 + 0.02 * V ** 2 - 0.008 * U * V + 0.15 * U - 0.05 * V


def test_parallax_recovers_the_slide_of_a_quadratic_surface():
    """A quadratic surface moved along itself by s changes height by -grad h . s plus a constant: every ring's
    least squares gives s (to rounding); a flat surface gives no shift (the slopes do not determine it)."""
    axis = np.linspace(-20.0, 20.0, 12)
    U, V = np.meshgrid(axis, axis, indexing="xy")
    s = np.array([1.3, -0.8])
    H = quadratic(U, V)
    dz = quadratic(U - s[0], V - s[1]) - H
    valid = np.ones_like(H)
    _, par = ring_features(dz, valid, H, axis)
    assert np.allclose(par.reshape(-1, 2), s, atol=1e-9)
    # hidden cells are left out, not read as zero height change
    valid[:4] = 0.0
    dz_hidden = np.where(valid > 0.5, dz, 0.0)
    _, par2 = ring_features(dz_hidden, valid, H, axis)
    assert np.allclose(par2.reshape(-1, 2), s, atol=1e-9)
    assert np.array_equal(parallax_shift(dz, np.zeros_like(H), np.zeros_like(H), np.ones(H.shape, bool)), np.zeros(2))


def test_segment_distances_against_brute_force():
    rng = np.random.default_rng(3)
    p0, p1 = rng.normal(size=(7, 3)), rng.normal(size=(7, 3))
    q0, q1 = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    t = np.linspace(0.0, 1.0, 801)
    for k in range(5):
        for j in range(7):
            a = p0[j] + t[:, None] * (p1[j] - p0[j])
            b = q0[k] + t[:, None] * (q1[k] - q0[k])
            brute = np.sqrt(((a[:, None] - b[None]) ** 2).sum(-1)).min()
            got = _segment_distances(p0[j:j + 1], p1[j:j + 1], q0[k:k + 1], q1[k:k + 1])[0, 0]
            assert got <= brute + 1e-12 and brute - got < 2e-3
    # parallel segments, and a zero-length one (a point)
    p0, p1 = np.array([[0.0, 0.0, 0.0]]), np.array([[1.0, 0.0, 0.0]])
    assert np.isclose(_segment_distances(p0, p1, np.array([[0.5, 2.0, 0.0]]), np.array([[3.0, 2.0, 0.0]]))[0, 0], 2.0)
    assert np.isclose(_segment_distances(p0, p1, np.array([[3.0, 0.0, 4.0]]), np.array([[3.0, 0.0, 4.0]]))[0, 0],
                      np.hypot(2.0, 4.0))


def _plane(half=30.0, n=121):
    """A flat triangulated square in z = 0, outward normal +z."""
    g = np.linspace(-half, half, n)
    X, Y = np.meshgrid(g, g)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    return (np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)]),
            np.concatenate([np.column_stack([a, b, d]), np.column_stack([a, d, c])]))


def test_shadow_estimate_finds_the_tool_in_an_observed_cloud():
    """Clouds of a plane made by the pipeline's own camera model (tool tip and shaft hiding the surface, 5,000
    points, 0.5 mm noise) from two cameras, kinematic tips with 0.5 mm noise: the estimate's rms error is below
    0.3 mm and below 0.7x the kinematic tip's (without the shadow-area term it drifts off, 1.5 mm)."""
    V, T = _plane()
    tool = np.array([0.6, -0.4, 0.0])
    cfg = ObservationConfig(n_points=(5000, 5000), noise_sd_mm=0.5, roi_radius_mm=20.0)
    err, err_kin = [], []
    for c, cam in enumerate((np.array([30.0, 18.0, 80.0]), np.array([-25.0, -30.0, 70.0]))):
        for seed in range(4):
            cloud, _ = observe(V, T, tool, [0.0, 0.0, 1.0], cfg, seed=seed, camera_position_mm=cam)
            kin = tool + np.random.default_rng([c, seed]).normal(0.0, 0.5, 3)
            est = shadow_estimate(cloud, cam, kin, tool_radius_mm=2.5, shaft_mm=150.0, tip_sd_mm=0.5,
                                  noise_sd_mm=0.5)
            err.append(np.sum((est - tool[:2]) ** 2))
            err_kin.append(np.sum((kin[:2] - tool[:2]) ** 2))
    rms, rms_kin = np.sqrt(np.mean(err)), np.sqrt(np.mean(err_kin))
    assert rms < 0.3 and rms < 0.7 * rms_kin, (rms, rms_kin)


def test_ridge_cv_predicts_each_liver_from_the_others_only():
    """Folds by liver: changing one liver's targets leaves that liver's out-of-fold predictions unchanged (with
    the penalty chosen by the inner folds, too) and changes the others'; moving its inputs leaves its fold
    partner's predictions unchanged (the scaling is fitted on the training fold only). A linear target is
    recovered."""
    rng = np.random.default_rng(0)
    groups = np.repeat(np.array([f"liver-{k}" for k in range(10)]), 30)
    F = rng.normal(size=(300, 4))
    y = F @ np.array([[1.0], [-2.0], [0.5], [0.0]]) + 3.0
    assert np.sqrt(np.mean((ridge_cv(F, y, groups, lam=1e-6) - y) ** 2)) < 1e-3
    y_noisy = y + rng.normal(0.0, 0.5, y.shape)
    m = groups == "liver-3"
    y2 = y_noisy.copy()
    y2[m] = 100.0 + 50.0 * rng.normal(size=(m.sum(), 1))
    for lam in (1.0, None):
        a = ridge_cv(F, y_noisy, groups, lam=lam)
        b = ridge_cv(F, y2, groups, lam=lam)
        assert np.allclose(a[m], b[m])
        assert not np.allclose(a[~m], b[~m])  # the other livers' models did see them
    # liver-3's inputs moved: the other liver of its test fold is predicted by a model that never saw them (the
    # scaling included), so its predictions stay; a liver of another fold is predicted by a model that did
    fold = next(te for te in _by_group_folds(groups, 5, 0) if te[m].all())
    partner = fold & ~m
    assert partner.any()
    F3 = F.copy()
    F3[m] = 10.0 * F3[m] + 5.0
    a = ridge_cv(F, y_noisy, groups, lam=1.0)
    c = ridge_cv(F3, y_noisy, groups, lam=1.0)
    assert np.allclose(a[partner], c[partner])
    assert not np.allclose(a[~fold], c[~fold])


def test_observe_cases_returns_the_records_of_its_clouds():
    """records=True adds each cloud's observation record, in the order of ``rows`` over several geometries, and
    changes nothing else: with no tip noise the tip is the record's (the FE tip the camera observed)."""
    a = synthetic_surface_arrays(6, n_geometries=2, seed=1)
    cam = {"observation": {"n_points": [300, 600], "noise_sd_mm": 0.5}, "tip_noise_mm": 0.0}
    rows = np.array([5, 0, 3, 2])
    assert len(set(np.asarray(a["geometry_id"])[rows])) == 2
    clouds, tips = camera.observe_cases(a, cam, 15.0, 8, 4, rows)
    clouds2, tips2, recs = camera.observe_cases(a, cam, 15.0, 8, 4, rows, records=True)
    assert np.array_equal(tips, tips2) and all(np.array_equal(c, c2) for c, c2 in zip(clouds, clouds2))
    assert [r.n_points for r in recs] == [len(c) for c in clouds]
    assert np.array_equal(np.array([r.tool_tip_mm for r in recs]), tips)
    alone = [camera.observe_cases(a, cam, 15.0, 8, 4, np.array([i]), records=True)[2][0] for i in rows]
    assert all(np.array_equal(r.camera_position_mm, r1.camera_position_mm) for r, r1 in zip(recs, alone))


def _dented_plane_with_shaft(depth=8.0, width=10.0, axis=(0.3, -0.2), r=2.5):
    """A flat pre-operative patch (local frame = world), its surface pushed down by a Gaussian dent of ``depth`` and
    ``width`` (mm) round ``axis`` (half a ring 6-8 mm from it raised 3 mm), and the camera-facing half of a shaft
    of radius ``r`` along the normal whose tip sphere's centre is ``r`` above the dent's bottom (the instrument's
    points last). Returns the local cloud, the reference, the spec, the number of instrument points, the dent's
    depth and width and the axis."""
    spec = CloudGridSpec(grid_size=9, half_width_mm=15.0, instrument_radius_mm=r)
    g = np.linspace(-25.0, 25.0, 201)
    U, V = [a.ravel() for a in np.meshgrid(g, g)]
    ref = ReferenceSurface.build(np.column_stack([U, V, np.zeros(U.size)]), [0, 0, 0], [0, 0, 1], [1, 0, 0],
                                 [0, 1, 0], spec)
    rr = np.hypot(U - axis[0], V - axis[1])
    Z = -depth * np.exp(-rr ** 2 / (2 * width ** 2))
    Z[(rr >= 6.0) & (rr < 8.0) & (V > axis[1])] = 3.0  # a raised lip beyond the search radius: neither rim nor shaft
    liver = np.column_stack([U, V, Z])[rr > r]  # under the tool: hidden
    phi, h = np.meshgrid(np.linspace(0.0, np.pi, 25), np.arange(-depth + r, 20.0, 0.25))
    shaft = np.column_stack([axis[0] + r * np.cos(phi.ravel()), axis[1] + r * np.sin(phi.ravel()), h.ravel()])
    return np.vstack([liver, shaft]), ref, spec, len(shaft), depth, width, np.array(axis)


def test_normal_features_read_the_dent_and_the_shaft_where_they_are():
    """On a dent of known profile: each ring's median height change is the median of the profile over the ring's
    points below the kinematic tip plus 4 mm; the shaft's candidates are the points standing ``instrument_rise_mm``
    above the pre-operative surface (the shaft inside the dent is not among them); the instrument's own points
    start at the tip sphere's centre. Too few points seen: NaN, not a number."""
    cloud, ref, spec, n_inst, depth, width, axis = _dented_plane_with_shaft()
    kin_n = -depth + 0.3
    F = normal_features(cloud, ref, axis, kin_n, spec, n_inst, instrument_search_radius(spec))
    liver = cloud[:-n_inst]
    d = np.hypot(liver[:, 0] - axis[0], liver[:, 1] - axis[1])
    prof = liver[:, 2]
    low = prof < kin_n + 4.0  # the rings leave out what stands 4 mm above the kinematic tip (the shaft's height)
    lip = (d >= 6.0) & (d < 8.0) & (prof > 0.0)
    assert lip.any() and not low[lip].any()
    for j, (lo, hi) in enumerate(RIM_RINGS_MM):
        m = (d >= lo) & (d < hi) & low
        assert F[2 * j + 1] == m.sum() > 3
        assert abs(F[2 * j] - np.median(-depth * np.exp(-d[m] ** 2 / (2 * width ** 2)))) < 1e-9
    assert F[5] == ((d >= 6.0) & (d < 8.0)).sum() - lip.sum()  # the lip is not in its ring
    o = 2 * len(RIM_RINGS_MM)
    nq = len(SHAFT_QUANTILES)
    shaft = cloud[-n_inst:]
    raised = shaft[shaft[:, 2] > spec.instrument_rise_mm]
    assert F[o + nq] == len(raised)  # the raised lip is beyond the search radius
    assert F[o] == raised[:, 2].min() > spec.instrument_rise_mm
    assert np.allclose(F[o:o + nq], np.quantile(raised[:, 2], SHAFT_QUANTILES))
    assert F[o + nq + 1] == -depth + spec.instrument_radius_mm  # the shaft's own lowest point
    assert np.all(np.diff(F[o + nq + 1:]) >= 0)
    # nothing of the instrument in the cloud, and a search that finds nothing: NaN for both
    G = normal_features(cloud[:-n_inst], ref, axis, kin_n, spec, 0, instrument_search_radius(spec))
    assert np.isnan(G[o:o + nq]).all() and G[o + nq] == 0 and np.isnan(G[o + nq + 1:]).all()
    assert np.array_equal(G[:o], F[:o])


def test_score_normal_recovers_a_tip_its_inputs_determine(capsys):
    """Rows whose instrument quantiles are the tip plus a constant: that estimator's error is ~0 mm, the
    kinematic tip's is its noise; a row with a NaN input is left out."""
    rng = np.random.default_rng(5)
    n = 200
    groups = np.repeat(np.array([f"liver-{k}" for k in range(10)]), n // 10)
    t = rng.normal(-6.0, 2.0, n)
    kin = t + rng.normal(0.0, 0.5, n)
    nr, nq = 2 * len(RIM_RINGS_MM), len(SHAFT_QUANTILES)
    F = rng.normal(size=(n, nr + 2 * nq + 1))
    F[:, nr + nq + 1:] = t[:, None] + 2.5 + np.arange(nq)
    F[0, 0] = np.nan
    score_normal(F, kin, kin, t, groups)
    out = capsys.readouterr().out
    assert f"{n - 1} of {n} cases" in out
    lines = {ln.rsplit(" n ", 1)[0].strip(): float(ln.rsplit(" n ", 1)[1].split()[0]) for ln in out.splitlines()[1:]}
    assert lines["instrument's own points alone"] < 0.01
    assert lines["ridge: + instrument's own points"] < 0.01  # the kinematic column is not what it reads
    assert lines["shaft's lowest points alone"] > 1.0  # noise columns: about the tip's own spread
    assert abs(lines["kinematic"] - np.sqrt(np.mean((kin[1:] - t[1:]) ** 2))) < 1e-3
    assert 0.4 < lines["kinematic"] < 0.6 and abs(lines["ridge: kinematic"] - lines["kinematic"]) < 0.05
    assert "the instrument's own 2.50 +- 0.00 mm" in out  # its lowest quantile read, the tip plus 2.5
