"""Experiment: do features without the ROI's rigid-body motion help scenario IV, the unseen livers and the physics study?

The physics study (issue #18) showed that changing the liver's supports barely
changes the indentation under the tool but moves the whole ROI (near rigid-body
motion on the supports), and the models read that motion as force. This script
retrains the scenario-IV model of one variant with its tuned hyper-parameters
(``models/IV/<variant>/metrics.json``) and the config's epochs on the same seeded
splits as ``train.repeats`` (split 0: ``train.seed``; split r: ``derive(seed,
"split.repeat", r)``, over all IV cases ordered by case id), several ways:

displacement models (``pca_sv``, ``ae_sv``, ``pca_nosv``)
    ``keep``          the current features;
    ``rigid far``     ``model.rigid_motion: remove`` (:mod:`liverforce.learn.representation`): the rigid transform (rotation + translation, Kabsch) that best
                      maps the undeformed ROI nodes farther than ``--far-radius`` mm
                      (tangent distance from the exertion point) onto their deformed
                      positions is undone on every deformed ROI node, and the deformed
                      ROI centroid of the state vector is that of the corrected nodes;
                      the grid, ``u_w`` and the linear force estimate then read only the
                      deformation relative to the far ROI;
    ``transl far``    the same with a translation only (the mean displacement of the far
                      nodes is subtracted).

camera models (``cloud_sv``)
    ``keep``          the current features;
    ``plane far``     a plane ``a + b u + c v`` is fitted to the height change dz over the
                      covered grid cells farther than ``--far-radius`` mm and subtracted from
                      every cell; the tool tip's normal displacement is taken relative to
                      the plane (``tip_n - a``). Its tangential part is left (the camera
                      cannot see tangential motion of the surface).

It prints, per row: IV test accuracy and MAE (mean +- sd over the splits); the
unseen livers' (scenario V) MAE, each liver's MAE averaged over the splits' models,
then mean +- sd over the livers; and each physics-study file's MAE (the baseline
00 and 01-06 with one support choice changed; mean over the splits' models).

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python benchmarks/experiment_rigid_motion.py \\
        --results /tmp/fresh-final/results/default --physics /tmp/s4/phys/shards --variant pca_sv --splits 5

Measured on that run (1 core; pca_sv ~15 s per row, cloud_sv ~70 s per row with 3 splits):

- pca_sv, 5 splits: keep 88.9 +- 1.0 % / unseen 0.280 +- 0.075 N; rigid far 15 88.3 +- 0.9 % / 0.271 +- 0.068 N
  (paired: -0.6 +- 0.4 pp, -0.009 +- 0.011 N, 6/8 livers better); physics MAE keep -> rigid: baseline 0.196 ->
  0.190, foundations x0.25 0.658 -> 0.505, x4 0.238 -> 0.233, kt/kn 0.1 0.341 -> 0.288, rib unilateral 0.376 ->
  0.382, rib off 0.403 -> 0.391, gravity supine 0.213 -> 0.193 N. Far radius 10 / 25 mm: the same within noise;
  translation only: less (foundations x0.25 0.543, unseen -0.003 N).
- cloud_sv, 3 splits: keep 81.6 +- 1.0 % / unseen 0.486 +- 0.091 N; plane far 15 78.0 +- 1.2 % / 0.574 +- 0.149 N
  (physics: baseline 0.421 -> 0.482, foundations x0.25 0.872 -> 0.746, rib off 0.594 -> 0.543 N): worse.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

PHYSICS_NAMES = ("baseline", "found x0.25", "found x4", "kt/kn 0.1", "rib unilat", "rib off", "grav supine")


# --------------------------------------------------------------------------
# rigid-motion-free inputs (applied to the arrays, so grid, state vector and u_w all see them)
# --------------------------------------------------------------------------


def rigid_fit(A: np.ndarray, B: np.ndarray, rotation: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """``(Q, t)`` minimising ``sum |Q a_j + t - b_j|^2`` (Kabsch; ``Q = I`` without ``rotation``)."""
    ca, cb = A.mean(axis=0), B.mean(axis=0)
    if not rotation:
        return np.eye(3), cb - ca
    H = (A - ca).T @ (B - cb)
    Uh, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ Uh.T)) or 1.0
    Q = Vt.T @ np.diag([1.0, 1.0, d]) @ Uh.T
    return Q, cb - Q @ ca


def without_rigid_motion(arrays: dict, far_radius_mm: float, rotation: bool = True) -> dict:
    """The arrays with every case's deformed ROI moved back by the far ROI nodes' best rigid motion (with
    ``rotation``, what ``model.rigid_motion: remove`` does; without, a translation only)."""
    from liverforce.learn.frames import case_rotations

    R = case_rotations(arrays)
    P = np.asarray(arrays["exertion_point_mm"], dtype=np.float64)
    dfm, cen = [], []
    for i in range(len(P)):
        U = np.asarray(arrays["roi_undeformed_mm"][i], dtype=np.float64).reshape(-1, 3)
        D = np.asarray(arrays["roi_deformed_mm"][i], dtype=np.float64).reshape(-1, 3)
        r = np.hypot(*((U - P[i]) @ R[i][:2].T).T)
        far = r >= far_radius_mm
        if far.sum() < 10:  # a small ROI: its outer half
            far = r >= np.median(r)
        Q, t = rigid_fit(U[far], D[far], rotation)
        Dc = (D - t) @ Q  # Q^T (d - t) per row
        dfm.append(Dc.astype(np.float32))
        cen.append(Dc.mean(axis=0))
    out = dict(arrays)
    out["roi_deformed_mm"] = dfm
    out["roi_centroid_deformed_mm"] = np.asarray(cen)
    return out


def plane_free_camera(x: np.ndarray, grid_size: int, half_width_mm: float, far_radius_mm: float) -> np.ndarray:
    """Camera features with the far covered cells' best plane removed from dz and from the tip's normal part."""
    g2 = grid_size**2
    s = np.linspace(-half_width_mm, half_width_mm, grid_size)
    uu, vv = np.meshgrid(s, s)
    u, v = uu.ravel(), vv.ravel()
    far = np.hypot(u, v) >= far_radius_mm
    A = np.column_stack([np.ones(g2), u, v])
    out = np.array(x, dtype=np.float64, copy=True)
    for k in range(len(out)):
        ok = far & (out[k, g2:2 * g2] > 0.5)
        if ok.sum() < 6:
            ok = out[k, g2:2 * g2] > 0.5
        if ok.sum() < 3:
            continue
        coef = np.linalg.lstsq(A[ok], out[k, :g2][ok], rcond=None)[0]
        out[k, :g2] -= A @ coef
        out[k, -1] -= coef[0]
    return out


# --------------------------------------------------------------------------


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results/default")
    ap.add_argument("--physics", default=None, help="folder with the physics study's 0K.manifest.json (optional)")
    ap.add_argument("--variant", default="pca_sv")
    ap.add_argument("--splits", type=int, default=5, help="seeded splits (<= train.repeats)")
    ap.add_argument("--far-radius", type=float, default=15.0, help="tangent distance (mm) of the far ROI nodes "
                                                                     "(default 15 = 3 tool radii)")
    ap.add_argument("--overrides", nargs="*", default=[], help="config overrides (as for snakemake --config)")
    ap.add_argument("--only", nargs="*", help="run only these rows (by name)")
    ap.add_argument("--json", help="also write the results here")
    args = ap.parse_args()
    results = Path(args.results)

    import liverforce.learn.camera as camera_mod
    from liverforce.config import compose, variant_model
    from liverforce.pipeline.shared import run_arrays
    from liverforce.learn.metrics import force_metrics
    from liverforce.learn.model import (eval_seed, fit_force_model, state_options,
                                        n_views_for, prepare, subset, view_seeds)
    from liverforce.learn.regressor import fit_params
    from liverforce.learn.representation import representation_from_config
    from liverforce.learn.splits import train_test_split
    from liverforce.learn.torchutil import configure_torch
    from liverforce.seeds import derive

    configure_torch(1)
    cfg = compose(list(args.overrides))
    v = {x["name"]: x for x in cfg["train"]["variants"]}[args.variant]
    model_cfg = variant_model(cfg["model"], v)
    train = cfg["train"]
    best = json.loads((results / "models/IV" / args.variant / "metrics.json").read_text())["best_params"]
    hidden = [int(best["width"])] * int(best["n_layers"]) if "width" in best else []
    fit = fit_params(model_cfg, lr=float(best.get("lr", train["lr"])), batch_size=int(best.get("batch_size", train["batch_size"])),
                     epochs=int(train["epochs"]), weight_decay=float(train.get("weight_decay", 0.0)))
    camera = str(model_cfg.get("roi_features", "displacement")) == "cloud"

    arrays = run_arrays(results, "IV", camera, "rigid-motion experiment")
    arrays = subset(arrays, np.argsort(np.asarray(arrays["case_id"]).astype(str), kind="stable"))
    unseen = run_arrays(results, "V", camera, "rigid-motion experiment")
    physics = []
    if args.physics:
        for k in range(len(PHYSICS_NAMES)):
            m = Path(args.physics) / f"{k:02d}.manifest.json"
            if m.exists():
                physics.append((PHYSICS_NAMES[k], run_arrays(results, None, camera, "rigid-motion experiment", manifest=m)))
    geo = np.asarray(arrays["geometry_id"]).astype(str)
    seed = int(train.get("seed", 0))
    split_seeds = [seed] + [derive(seed, "split.repeat", r) for r in range(1, args.splits)]

    far = float(args.far_radius)
    if camera:
        orig_features = camera_mod.camera_features
        state = {"on": False}

        def patched(arrs, cam, grid_size, half_width_mm, observation_seed, R=None):
            x = orig_features(arrs, cam, grid_size, half_width_mm, observation_seed, R=R)
            return plane_free_camera(x, grid_size, half_width_mm, far) if state["on"] else x

        camera_mod.camera_features = patched

        def switch(on):
            def f(a):
                state["on"] = on
                return a
            return f

        rows = (("keep", switch(False), {}), (f"plane far {far:g}", switch(True), {}))
    else:
        rows = (("keep", lambda a: a, {}),  # the option model.rigid_motion: remove (the library's path)
                (f"rigid far {far:g}", lambda a: a, {"rigid_motion": "remove", "rigid_motion_radius_mm": far}),
                (f"transl far {far:g}", lambda a: without_rigid_motion(a, far, False), {}))
    if args.only:
        rows = tuple(r for r in rows if r[0].split()[0] in args.only)

    report = []
    for name, data, over in rows:
        mcfg = {**model_cfg, **over}
        t0 = time.perf_counter()
        d_all, d_unseen = data(arrays), data(unseen)
        d_phys = [(n, data(a)) for n, a in physics]
        test_m, per_liver, phys_mae = [], [], []
        gu = np.asarray(unseen["geometry_id"]).astype(str)
        livers = sorted(set(gu))
        for s in split_seeds:
            tr, te = train_test_split(geo, scenario="IV", test_fraction=float(train["test_fraction"]), seed=s)
            a_tr, a_te = subset(d_all, tr), subset(d_all, te)
            rep = representation_from_config(mcfg, a_tr)
            prep = prepare(a_tr, rep, observation_seeds=view_seeds(s, n_views_for(rep)))
            model, _ = fit_force_model(prep, rep, encoder=str(model_cfg["encoder"]),
                                       code_size=int(model_cfg["code_size"]),
                                       use_state=bool(model_cfg["state_vector"]), hidden=hidden,
                                       dropout=float(best.get("dropout", 0.0)), fit=fit, seed=s,
                                       dae_input_noise=float(model_cfg.get("dae_input_noise", 0.1)),
                                       **state_options(model_cfg))
            es = eval_seed(s)
            test_m.append(force_metrics(np.asarray(a_te["force_n"], float), model.predict(a_te, observation_seed=es)))
            pu = model.predict(d_unseen, observation_seed=es)
            err = np.linalg.norm(pu - np.asarray(unseen["force_n"], float), axis=1)
            per_liver.append([float(err[gu == g].mean()) for g in livers])
            phys_mae.append([force_metrics(np.asarray(a["force_n"], float),
                                           model.predict(a, observation_seed=es))["mae_vec"] for _, a in d_phys])
            print(f"  {name}: split {s} test acc {test_m[-1]['accuracy_pct']:.1f} % MAE {test_m[-1]['mae_vec']:.3f}"
                  f" N; unseen {np.mean(per_liver[-1]):.3f} N; physics "
                  + " ".join(f"{x:.3f}" for x in phys_mae[-1]) + f" ({time.perf_counter() - t0:.0f} s)", flush=True)
        acc = np.array([m["accuracy_pct"] for m in test_m])
        mae = np.array([m["mae_vec"] for m in test_m])
        liver = np.asarray(per_liver).mean(axis=0)
        split_unseen = np.asarray(per_liver).mean(axis=1)
        ph = np.asarray(phys_mae).mean(axis=0) if physics else np.empty(0)
        entry = {"row": name, "splits": len(split_seeds), "test_accuracy_pct": [acc.mean(), acc.std(ddof=1) if len(acc) > 1 else 0.0],
                 "test_mae_n": [mae.mean(), mae.std(ddof=1) if len(mae) > 1 else 0.0],
                 "unseen_mae_n": [liver.mean(), liver.std(ddof=1)], "unseen_mae_split_sd": float(split_unseen.std(ddof=1)) if len(split_unseen) > 1 else 0.0,
                 "unseen_per_liver": dict(zip(livers, liver.tolist())),
                 "physics_mae_n": dict(zip([n for n, _ in physics], ph.tolist())),
                 "split_accuracy_pct": acc.tolist(), "seconds": time.perf_counter() - t0}
        report.append(entry)
        paired = ""
        if len(report) > 1:  # paired differences to the first row (same splits, same livers)
            da = acc - np.asarray(report[0]["split_accuracy_pct"])
            dl = liver - np.asarray(list(report[0]["unseen_per_liver"].values()))
            paired = (f"\n{'':16s} vs {report[0]['row']}: IV test acc {da.mean():+.1f} +- {da.std(ddof=1) if len(da) > 1 else 0:.1f} pp "
                      f"(paired over splits), unseen MAE {dl.mean():+.3f} +- {dl.std(ddof=1):.3f} N (paired over livers, "
                      f"{int((dl < 0).sum())}/{len(dl)} livers better)")
        print(f"{name:16s} IV test acc {acc.mean():.1f} +- {entry['test_accuracy_pct'][1]:.1f} %, MAE {mae.mean():.3f} +- "
              f"{entry['test_mae_n'][1]:.3f} N ({len(acc)} splits); unseen MAE {liver.mean():.3f} +- {liver.std(ddof=1):.3f} N "
              f"over {len(livers)} livers (split sd {entry['unseen_mae_split_sd']:.3f}); physics MAE "
              + " ".join(f"{n}={x:.3f}" for (n, _), x in zip(physics, ph))
              + (f"; max/baseline {ph[1:6].max() / ph[0]:.2f}" if len(ph) >= 6 else "")
              + f" ({entry['seconds']:.0f} s)" + paired, flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1, default=float))


if __name__ == "__main__":
    main()
