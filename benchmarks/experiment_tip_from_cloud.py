"""Experiment: does the camera cloud locate the tool tip along the surface better than the robot's kinematics?

The camera model's largest loss is the tool tip's tangential position (docs/experiments.md, "What a camera sees":
retrained with a tip exact along the surface, IV 88.7 -> 91.6 %, unseen 0.302 -> 0.215 N). This scores estimators of the
tip's tangential displacement (local t1, t2; mm) against the FE tip (the exertion point moved with the surface) on a
finished run's cases, observed as the pipeline observes a training view (the camera variant's camera, visibility, tool,
density, noise and tip noise; the seed of its first view):

- ``kinematic``: the noisy tip the robot reports (``model.camera.tip_noise_mm``);
- ``instrument's axis``: for a variant that fits it (``model.camera.grid.instrument_radius_mm``, the default since
  ea1a819), the tip the model reads: the shaft's axis fitted to the instrument's points in the cloud;
- ridge regressions, 5 folds by liver, from the kinematic tip plus
  - ``grid``: the camera model's grid (height change and coverage, ``2 g^2`` values); ``coverage mask``: the
    coverage alone (the observation cuts the ROI around the FE tip: does the mask's edge give it away?);
  - ``rings``: the grid's height change in rings around the exertion point (mean and first moments along t1, t2);
  - ``rings + parallax``: and per ring the shift ``u`` that best explains the height change as the pre-operative
    surface sliding along itself, ``dz = c - grad h . u`` (least squares over the ring's covered cells,
    :func:`parallax_shift`): the one way a tangential motion shows in heights (the aperture problem elsewhere);
- ``shadow`` (camera position known, ``--shadow-cases`` cases, ~0.5 s each): the tool (tip sphere and shaft along
  the normal, the observation's radius) at candidate positions around the kinematic tip, prior the kinematic
  noise; within ``--window`` mm a visible point whose ray to the camera the tool would block lowers the
  likelihood (Gaussian point noise), and the points, uniform over the part of the window the tool does not
  shadow, favour the larger shadow (no points where the tool hides the surface); the posterior mean
  (:func:`shadow_estimate`).

Along the normal (``--normal``, the tip's normal displacement; the model's tip there is the kinematic one, moved
a little along the fitted axis), ridge regressions from the kinematic tip plus

- ``dent rings``: the median height change of the cloud's points in rings 3-4.5 / 4.5-6 / 6-8 / 8-11 mm round the
  fitted axis (the points lower than the kinematic tip plus 4 mm: not the shaft), and their counts;
- ``shaft's lowest points``: the heights along the normal of the points within ``instrument_search_radius`` of the
  fitted axis (u, v) standing ``instrument_rise_mm`` above the pre-operative surface (the instrument fit's
  candidates, simplified: no widening with height for a tilted shaft, no noise refit) at the quantiles 0 / 0.02 /
  0.05 / 0.1 / 0.2, and their count: where the shaft comes out of the dent;
- ``instrument's own points`` (a ceiling no camera gives): the same quantiles of the points the observation drew
  on the instrument (the cloud's last ``n_instrument_points`` rows), the tip sphere's included.

Measured on the 9ac4790 run's IV shards (1 Dec 2026, 400 cases of 20 livers; docs/experiments.md, "What a camera sees"):
the heights do not locate the tip (no ridge row beats the kinematic tip's own recalibration, 0.509 / 0.475 mm, by
more than 0.006 mm; the kinematic tip as read 0.525 / 0.486 mm), the tool's shadow with the camera's position does
(0.336 / 0.322 mm; along the normal the tip stays the kinematic one). ::

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python benchmarks/experiment_tip_from_cloud.py \\
        --results results/default --shadow-cases 400

Along the normal, on a fresh clone of 764e3ee (2 Dec 2026, the same 400 IV cases; the 345 with every ring, 8 shaft
candidates and 8 of the instrument's own points seen; ``--shadow-cases 0 --normal``): nothing the cloud shows does
better than the kinematic tip, 0.507 mm rms (its ridge recalibration 0.506). With the dent rings 0.598 mm (1.115
alone): the dent's profile varies too much for its rim to place the tip. With the shaft's lowest points 0.502 mm
(2.610 alone): the lowest candidate stands 7.99 +- 2.97 mm above the tip, because the shaft's part inside the dent
is below the pre-operative surface and cannot be told from the liver by height. Only the instrument's own points,
labelled as no camera cloud is, would help: 0.441 mm (0.734 alone; the lowest 1.60 +- 0.89 mm above the tip).
"""

from __future__ import annotations

import argparse

import numpy as np

RINGS_MM = ((0.0, 7.0), (7.0, 12.0), (12.0, 18.0), (18.0, 30.0))
LAMBDAS = tuple(10.0 ** k for k in range(-2, 6))  # ridge penalties the inner cross-validation chooses from


def parallax_shift(dz: np.ndarray, hu: np.ndarray, hv: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The tangential shift ``u`` (2,) and offset ``c`` with ``dz ~ c - hu u_1 - hv u_2`` over ``mask`` (least
    squares; a surface ``h`` moved along itself by ``u`` changes height by ``-grad h . u`` to first order, exactly
    up to a constant for a quadratic ``h``); zeros where the slopes do not determine it."""
    m = mask.ravel()
    if m.sum() < 4:
        return np.zeros(2)
    A = np.column_stack([np.ones(m.sum()), -hu.ravel()[m], -hv.ravel()[m]])
    sol, _, rank, _ = np.linalg.lstsq(A, dz.ravel()[m], rcond=1e-9)
    return sol[1:] if rank == 3 else np.zeros(2)


def ring_features(dz: np.ndarray, valid: np.ndarray, H: np.ndarray, axis_mm: np.ndarray,
                  rings=RINGS_MM) -> tuple[np.ndarray, np.ndarray]:
    """Per ring of the ``g x g`` grid (``axis_mm``: the grid's coordinates along t1 and t2, cell ``[i, j]`` at
    ``(axis[j], axis[i])``): the covered cells' mean height change and its first moments along t1, t2
    (``(3 len(rings),)``), and :func:`parallax_shift` with the pre-operative heights ``H`` (``(2 len(rings),)``)."""
    U, V = np.meshgrid(axis_mm, axis_mm, indexing="xy")
    step = float(axis_mm[1] - axis_mm[0])
    hv, hu = np.gradient(H, step, edge_order=2)
    r = np.hypot(U, V)
    moments, par = [], []
    for lo, hi in rings:
        m = (r >= lo) & (r < hi) & (valid > 0.5)
        w = max(int(m.sum()), 1)
        moments += [float((dz * m).sum()) / w, float((dz * U * m).sum()) / w, float((dz * V * m).sum()) / w]
        par += list(parallax_shift(dz, hu, hv, m))
    return np.array(moments), np.array(par)


def _ridge_fit(F: np.ndarray, target: np.ndarray, lam: float, free: int = 0):
    mu, sd = F.mean(0), F.std(0)
    sd[sd == 0] = 1.0
    A = np.column_stack([np.ones(len(F)), (F - mu) / sd])
    reg = lam * np.eye(A.shape[1])
    reg[:1 + free, :1 + free] = 0.0
    w = np.linalg.solve(A.T @ A + reg, A.T @ target)
    return lambda G: np.column_stack([np.ones(len(G)), (G - mu) / sd]) @ w


def _by_group_folds(groups: np.ndarray, folds: int, seed: int) -> list[np.ndarray]:
    names = np.unique(groups)
    np.random.default_rng(seed).shuffle(names)
    return [np.isin(groups, part) for part in np.array_split(names, min(folds, len(names)))]


def ridge_cv(F: np.ndarray, target: np.ndarray, groups: np.ndarray, *, folds: int = 5, lam: float | None = None,
             free: int = 0, seed: int = 0) -> np.ndarray:
    """Out-of-fold predictions of a ridge regression (inputs standardised on the training fold; the intercept and
    the first ``free`` columns not penalised, e.g. the kinematic tip), folds by group. ``lam`` None: the penalty
    of :data:`LAMBDAS` with the lowest error of an inner cross-validation by group on each training fold (so many
    inputs against few rows do not just interpolate; a large one leaves the free columns' fit)."""
    pred = np.empty_like(target, dtype=np.float64)
    for te in _by_group_folds(groups, folds, seed):
        tr = ~te
        best = lam
        if best is None:
            inner = [np.mean((ridge_cv(F[tr], target[tr], groups[tr], folds=folds, lam=l_, free=free,
                                       seed=seed + 1) - target[tr]) ** 2) for l_ in LAMBDAS]
            best = LAMBDAS[int(np.argmin(inner))]
        pred[te] = _ridge_fit(F[tr], target[tr], best, free)(F[te])
    return pred


def _segment_distances(p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    """Distances ``(K, m)`` between the segments ``p0[j] p1[j]`` (``(m, 3)``) and ``q0[k] q1[k]`` (``(K, 3)``)."""
    d1 = p1 - p0
    d2 = q1 - q0
    r = p0[None] - q0[:, None]
    a = (d1 * d1).sum(-1)[None]
    e = (d2 * d2).sum(-1)[:, None]
    b = (d1[None] * d2[:, None]).sum(-1)
    c = (d1[None] * r).sum(-1)
    f = (d2[:, None] * r).sum(-1)
    a = np.maximum(a, 1e-300)  # a zero-length segment is its point (s, t = 0 from the clamps below)
    e = np.maximum(e, 1e-300)
    den = a * e - b * b
    ok = den > 1e-12 * a * e
    s = np.clip(np.where(ok, (b * f - c * e) / np.where(ok, den, 1.0), 0.0), 0.0, 1.0)
    t = np.clip((b * s + f) / e, 0.0, 1.0)
    s = np.clip((b * t - c) / a, 0.0, 1.0)
    return np.linalg.norm(p0[None] + s[..., None] * d1[None] - q0[:, None] - t[..., None] * d2[:, None], axis=-1)


def shadow_estimate(points: np.ndarray, camera: np.ndarray, tip: np.ndarray, *, tool_radius_mm: float,
                    shaft_mm: float, tip_sd_mm: float, noise_sd_mm: float, window_mm: float = 12.0,
                    reach_sd: float = 3.0, step_mm: float = 0.1, plane_step_mm: float = 0.5) -> np.ndarray:
    """Posterior mean of the tool's tangential position (2,) from the visible cloud, local frame (normal = +z).

    ``points`` (k, 3) and ``camera`` (3,) in the local frame; ``tip`` (3,) the kinematic tip (prior mean of the
    tangential position, sd ``tip_sd_mm``; its normal coordinate is used as is). The tool: a capsule of radius
    ``r`` from ``tip + r z`` along ``+z`` for ``shaft_mm``. Candidates on a grid of ``step_mm`` within ``reach_sd``
    prior sd's. Within ``window_mm`` of the kinematic tip (tangentially), given the number ``n`` of points there
    (each uniform over the window's part the tool does not shadow): ``sum log Phi(D_i / noise_sd)`` over the points
    (``D_i``: how far the point's ray to the camera clears the tool) minus ``n log(A - S)``, ``A`` the window's
    area and ``S`` the tool's shadow on the plane through the tip within it (both counted on a grid of
    ``plane_step_mm``). Approximations: that plane (the dented surface lies lower near the tool), ``S`` on a grid
    (its steps add jitter where thousands of points weigh it), the kinematic tip's normal coordinate taken as
    exact, the window's hidden parts (self-occlusion) counted as visible. Assumed known exactly: the tool's axis
    (+z), radius and shaft, the camera's position, the noise sd's."""
    from scipy.special import log_ndtr

    r = float(tool_radius_mm)
    c0 = np.asarray(tip, dtype=np.float64)
    off = np.arange(-reach_sd * tip_sd_mm, reach_sd * tip_sd_mm + step_mm / 2, step_mm)
    cu, cv = (a.ravel() for a in np.meshgrid(off, off, indexing="ij"))
    centres = np.column_stack([c0[0] + cu, c0[1] + cv, np.full(cu.size, c0[2] + r)])
    ends = centres + np.array([0.0, 0.0, float(shaft_mm)])
    rho = np.hypot(points[:, 0] - c0[0], points[:, 1] - c0[1])
    near = points[rho < window_mm]
    log_post = -(cu ** 2 + cv ** 2) / (2.0 * tip_sd_mm ** 2)
    if len(near):
        D = _segment_distances(near, np.broadcast_to(camera, near.shape), centres, ends) - r
        log_post = log_post + log_ndtr(D / noise_sd_mm).sum(1)
    g = np.arange(-window_mm, window_mm + plane_step_mm / 2, plane_step_mm)
    gu, gv = (a.ravel() for a in np.meshgrid(g, g, indexing="ij"))
    inside = gu ** 2 + gv ** 2 < window_mm ** 2
    plane = np.column_stack([c0[0] + gu[inside], c0[1] + gv[inside], np.full(inside.sum(), c0[2])])
    shade = (_segment_distances(plane, np.broadcast_to(camera, plane.shape), centres, ends) < r).sum(1)
    area = inside.sum() * plane_step_mm ** 2  # the window, measured as its shadow is
    shadow = np.minimum(shade * plane_step_mm ** 2, 0.99 * area)
    log_post = log_post - len(near) * np.log(area - shadow)  # each point uniform over the unshadowed window
    w = np.exp(log_post - log_post.max())
    w /= w.sum()
    return c0[:2] + np.array([w @ cu, w @ cv])


RIM_RINGS_MM = ((3.0, 4.5), (4.5, 6.0), (6.0, 8.0), (8.0, 11.0))
SHAFT_QUANTILES = (0.0, 0.02, 0.05, 0.1, 0.2)
_MIN_SEEN = 8  # points for a quantile row (as the fit's instrument_min_points)


def normal_features(loc: np.ndarray, ref, axis_uv: np.ndarray, kin_n: float, spec, n_instrument: int,
                    search_mm: float) -> np.ndarray:
    """One case's inputs of the normal-tip estimators (module docstring), NaN where too few points were seen:
    the dent rings' median height change and counts (``2 x 4``), the candidates' height quantiles and count
    (``5 + 1``), the instrument's own points' quantiles (``5``). ``loc``: the cloud in the local frame."""
    dz = loc[:, 2] - ref.height(loc[:, 0], loc[:, 1])
    rr = np.hypot(loc[:, 0] - axis_uv[0], loc[:, 1] - axis_uv[1])
    out = np.full(2 * len(RIM_RINGS_MM) + 2 * len(SHAFT_QUANTILES) + 1, np.nan)
    low = loc[:, 2] < kin_n + 4.0  # not the shaft: it stands above the tip
    for j, (lo, hi) in enumerate(RIM_RINGS_MM):
        m = (rr >= lo) & (rr < hi) & low
        out[2 * j + 1] = m.sum()
        if m.sum() >= 3:
            out[2 * j] = np.median(dz[m])
    o = 2 * len(RIM_RINGS_MM)
    cand = (rr < search_mm) & (dz > spec.instrument_rise_mm)
    out[o + len(SHAFT_QUANTILES)] = cand.sum()
    if cand.sum() >= _MIN_SEEN:
        out[o:o + len(SHAFT_QUANTILES)] = np.quantile(loc[cand, 2], SHAFT_QUANTILES)
    if n_instrument >= _MIN_SEEN:
        out[o + len(SHAFT_QUANTILES) + 1:] = np.quantile(loc[-n_instrument:, 2], SHAFT_QUANTILES)
    return out


def score_normal(F: np.ndarray, kin_n: np.ndarray, model_n: np.ndarray, target_n: np.ndarray,
                 groups: np.ndarray) -> None:
    """Print the normal-tip estimators' rms error (mm) on the cases where every input was seen."""
    nr, nq = 2 * len(RIM_RINGS_MM), len(SHAFT_QUANTILES)
    ok = np.isfinite(F).all(axis=1)
    if not ok.any():
        raise SystemExit(f"--normal: no case had every ring, {_MIN_SEEN} shaft candidates and {_MIN_SEEN} of the "
                         "instrument's own points seen (a variant with model.camera.observation.instrument_in_cloud?)")
    k, t, g = kin_n[ok, None], target_n[ok, None], groups[ok]
    rings, cand, own = F[ok, :nr], F[ok, nr:nr + nq + 1], F[ok, nr + nq + 1:]

    def rms(est) -> str:
        return f"{np.sqrt(np.mean((np.ravel(est) - t[:, 0]) ** 2)):.3f} mm"

    print(f"along the normal: {ok.sum()} of {len(F)} cases with every ring, >= {_MIN_SEEN} shaft candidates and "
          f">= {_MIN_SEEN} of the instrument's own points seen; "
          f"the tip's normal displacement rms {np.sqrt(np.mean(t ** 2)):.2f} mm; shaft's lowest point "
          f"{np.mean(cand[:, 0] - t[:, 0]):.2f} +- {np.std(cand[:, 0] - t[:, 0]):.2f} mm above the tip, the "
          f"instrument's own {np.mean(own[:, 0] - t[:, 0]):.2f} +- {np.std(own[:, 0] - t[:, 0]):.2f} mm", flush=True)
    print(f"{'kinematic':34s} n {rms(k)}", flush=True)
    label = "the model's tip"
    print(f"{label:34s} n {rms(model_n[ok])}", flush=True)
    for label, Z, free in (("ridge: kinematic", k, 1),
                           ("ridge: + dent rings", np.column_stack([k, rings]), 1),
                           ("ridge: + shaft's lowest points", np.column_stack([k, cand]), 1),
                           ("ridge: + instrument's own points", np.column_stack([k, own]), 1),
                           ("dent rings alone", rings, 0),
                           ("shaft's lowest points alone", cand, 0),
                           ("instrument's own points alone", own, 0)):
        print(f"{label:34s} n {rms(ridge_cv(Z, t, g, free=free))}", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results/default")
    ap.add_argument("--scenario", default="IV")
    ap.add_argument("--variant", default="cloud_sv")
    ap.add_argument("--cases", type=int, default=400, help="cases drawn (seeded) from the scenario")
    ap.add_argument("--shadow-cases", type=int, default=60, help="the first of those the shadow estimate runs on")
    ap.add_argument("--window", type=float, default=12.0, help="shadow estimate's window around the tip, mm")
    ap.add_argument("--normal", action="store_true", help="also score the tip along the normal (module docstring)")
    args = ap.parse_args()

    from liverforce.learn import camera as C
    from liverforce.learn.cloud_features import ReferenceSurface, instrument_search_radius
    from liverforce.learn.frames import case_rotations
    from liverforce.learn.model import view_seeds

    from benchmarks.experiment import PipelineTraining

    run = PipelineTraining(args.results, "tip experiment")
    mc = run.variants[args.variant]
    if mc.get("roi_features") != "cloud":
        raise SystemExit(f"--variant {args.variant}: not a camera-cloud variant (model.roi_features: cloud)")
    cam, g, hw = mc["camera"], int(mc["grid_size"]), float(mc["grid_half_width_mm"])
    if hw <= 0:
        raise SystemExit("a grid half-width fitted to the ROI (0) is not supported here; give one in mm")
    a = run.arrays(args.scenario, True)
    n = len(a["exertion_point_mm"])
    rows = np.random.default_rng(0).permutation(n)[:min(n, args.cases)]  # in drawn order: any prefix (the shadow
    # cases) spans the livers (the shards are ordered by liver)
    seed = view_seeds(run.seed, 1)[0]
    clouds, tips, recs = C.observe_cases(a, cam, hw, g, seed, rows, records=True)
    spec = C.grid_spec(g, hw, cam)
    R = case_rotations(a)
    X = C.features_from_clouds(clouds, tips, a, spec, rows, R)
    P = np.asarray(a["exertion_point_mm"], dtype=np.float64)
    geo = np.asarray(a["geometry_id"]).astype(str)
    fe_tip = np.array([r.tool_tip_mm for r in recs])  # the FE tip each cloud was observed with
    target = np.einsum("nij,nj->ni", R[rows], fe_tip - P[rows])[:, :2]
    kin = np.einsum("nij,nj->ni", R[rows], tips - P[rows])  # the kinematic tip (local), as the robot reports it
    fitted = X[:, -3:] if spec.instrument_radius_mm > 0 else None  # the instrument's axis, where the model fits it
    axis = np.linspace(-hw, hw, g)
    moments, par = [], []
    normal_rows = []
    for k, i in enumerate(rows):
        ref = ReferenceSurface.for_case(a["roi_undeformed_mm"][i], a.get("roi_triangles", [None] * n)[i], P[i],
                                        R[i], spec)
        if args.normal:
            axis_uv = X[k, -3:-1] if spec.instrument_radius_mm > 0 else kin[k, :2]
            normal_rows.append(normal_features(ref.to_local(clouds[k]), ref, axis_uv, kin[k, 2], spec,
                                               recs[k].n_instrument_points, instrument_search_radius(spec)))
        h_, p_ = ring_features(X[k, :g * g].reshape(g, g), X[k, g * g:2 * g * g].reshape(g, g), ref.grid_height,
                               axis)
        moments.append(h_)
        par.append(p_)
    moments, par = np.array(moments), np.array(par)
    groups = geo[rows]
    n_pts = np.array([len(c) for c in clouds])
    thirds = np.quantile(n_pts, [1 / 3, 2 / 3])
    bins = [n_pts <= thirds[0], (n_pts > thirds[0]) & (n_pts <= thirds[1]), n_pts > thirds[1]]

    def line(label: str, est: np.ndarray, sel=slice(None)) -> str:
        e = est[sel] - target[sel]
        rms = np.sqrt(np.mean(e ** 2, axis=0))
        by = [np.sqrt(np.mean(e[b[sel]] ** 2)) if b[sel].any() else float("nan") for b in bins]
        return (f"{label:28s} t1 {rms[0]:.3f}  t2 {rms[1]:.3f} mm  (both, by density third: "
                f"{' / '.join(f'{x:.3f}' for x in by)}; {len(e)} cases)")

    print(f"{args.scenario}: {len(rows)} cases of {len(set(groups))} livers; points per cloud {n_pts.min()}-"
          f"{n_pts.max()} (thirds at {thirds[0]:.0f}, {thirds[1]:.0f}); tangential tip displacement rms "
          f"{np.sqrt(np.mean(target ** 2)):.2f} mm; kinematic noise {cam.get('tip_noise_mm')} mm", flush=True)
    gg = g * g
    ridge_inputs = [("ridge: kinematic", kin),
                    ("ridge: + grid", np.column_stack([kin, X[:, :2 * gg]])),
                    ("ridge: + coverage mask", np.column_stack([kin, X[:, gg:2 * gg]])),
                    ("ridge: + rings", np.column_stack([kin, moments])),
                    ("ridge: + rings + parallax", np.column_stack([kin, moments, par]))]
    print(line("kinematic", kin[:, :2]), flush=True)
    if fitted is not None:
        print(line("instrument's axis (the model's)", fitted[:, :2]), flush=True)
    for label, F in ridge_inputs:  # the kinematic tip's 3 columns unpenalised
        print(line(label, ridge_cv(F, target, groups, free=3)), flush=True)
    print(line("parallax alone (no tip)", ridge_cv(par, target, groups)), flush=True)
    if args.normal:
        score_normal(np.array(normal_rows), kin[:, 2], X[:, -1] if fitted is not None else kin[:, 2],
                     np.einsum("nij,nj->ni", R[rows], fe_tip - P[rows])[:, 2], groups)
    ns = min(args.shadow_cases, len(rows))
    if ns:
        obs = C.observation_config(cam, hw, g)
        sd_t = float(cam.get("tip_noise_mm") or 0.0)
        if sd_t <= 0:
            raise SystemExit("the shadow estimate needs a kinematic tip noise > 0 (its prior)")
        est = np.empty((ns, 2))
        for k in range(ns):
            i = rows[k]
            pts = (clouds[k] - P[i]) @ R[i].T
            cam_l = R[i] @ (recs[k].camera_position_mm - P[i])
            est[k] = shadow_estimate(pts, cam_l, kin[k], tool_radius_mm=obs.tool_radius_mm,
                                     shaft_mm=obs.tool_shaft_length_mm, tip_sd_mm=sd_t,
                                     noise_sd_mm=max(recs[k].noise_sd_mm, 0.05),  # > 0: a noise-free cloud's
                                     window_mm=args.window)  # edge as a near-hard limit
        print(line("kinematic (shadow cases)", kin[:ns, :2], slice(0, ns)), flush=True)
        print(line("shadow, camera pose known", est, slice(0, ns)), flush=True)


if __name__ == "__main__":
    main()
