"""Experiment: a simulated recording. One unseen-liver case pushed in FE load steps, each step seen by the camera.

``bench_sequence.py`` times a sequence whose frames scale one case's final FE displacement from 0 to 1, a
stand-in for a recording: a hyperelastic liver does not deform in proportion to the force. Here every frame is an
FE equilibrium. A case of an unseen liver (``<results>/sweep/V/cases.parquet``, the first of ``--liver``'s cases
of at least ``--min-force`` N unless ``--case`` names one) is solved again at ``--steps`` fractions of its force
vector (the sweep's solver and supports, from the default config with ``--overrides``; each step warm-started
from the one before, as the sweep does), so the tool presses in along the same direction. Each state is observed
as the validation's camera sees it (``--points`` liver points, 0.5 mm of point noise, the instrument in view, a
new camera draw per frame) with the tool tip as the robot gives it (0.5 mm of kinematics noise), and the frames
go through ``liverforce predict``'s sequence path (``liverforce.serve.sequence.predict_sequence``, compiled)
with the run's camera model (``<results>/models/IV/cloud_sv/model``) and the case's pre-operative context.

Prints per frame the true and predicted force magnitude, the error and whether the 90 % interval covers each
local component; then the path's MAE, the interval's coverage along it, the error's mean (what a smoother
cannot remove) and its frame-to-frame noise (the sd of successive error differences over sqrt 2, per local
component: what a smoother over frames can remove). ``--out DIR`` writes the recording (``DIR/frames/frame_NN.npy``,
``DIR/tips.csv``, ``DIR/truth.csv``, and this run's forces ``DIR/predicted.csv``) and prints the ``liverforce
predict`` command that replays it.

Usage: ``PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python benchmarks/experiment_loading_path.py --results
results/default [--steps 24] [--out /tmp/path]``
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

COMPONENTS = ("t1", "t2", "n")


def step_cases(case: dict, steps: int) -> list[dict]:
    """The case-table row ``case`` at ``steps`` fractions ``k / steps`` (k = 1..steps) of its force vector, in
    that order (the last is the case itself), each with its own case id."""
    if steps < 1:
        raise ValueError(f"steps: need at least 1, got {steps}")
    F = np.asarray(case["force_n"], dtype=np.float64)
    out = []
    for k in range(1, steps + 1):
        f = F * k / steps
        out.append({**case, "case_id": f"{case['case_id']}-s{k:02d}", "force_n": f.tolist(),
                    "force_magnitude_n": float(np.linalg.norm(f))})
    return out


def path_summary(true_n: np.ndarray, pred_n: np.ndarray, half_local_n: np.ndarray, frame: np.ndarray) -> dict:
    """What the path's frames show: ``true_n``, ``pred_n`` (T, 3) N in the liver frame, the interval's local
    half-widths (T, 3) N, the local frame ``frame`` (rows t1, t2, n). Frames with a NaN prediction (refused) are
    left out and counted. Returns the MAE (vector), the coverage per local component, the error's mean per
    component and its frame-to-frame noise (sd of successive differences / sqrt 2; NaN with fewer than 3
    frames), all over the predicted frames."""
    true_n, pred_n, half = (np.asarray(a, dtype=np.float64) for a in (true_n, pred_n, half_local_n))
    ok = np.isfinite(pred_n).all(axis=1)
    e_local = (pred_n[ok] - true_n[ok]) @ np.asarray(frame, dtype=np.float64).T
    d = np.diff(e_local, axis=0)
    noise = d.std(axis=0, ddof=1) / np.sqrt(2.0) if len(d) >= 2 else np.full(3, np.nan)
    return {"frames": int(len(true_n)), "predicted": int(ok.sum()),
            "mae_n": float(np.linalg.norm(pred_n[ok] - true_n[ok], axis=1).mean()) if ok.any() else float("nan"),
            "coverage": (np.abs(e_local) <= half[ok]).mean(axis=0).tolist() if ok.any() else [float("nan")] * 3,
            "mean_error_n": e_local.mean(axis=0).tolist() if ok.any() else [float("nan")] * 3,
            "noise_n": noise.tolist()}


def run_path(res: Path, cfg: dict, case: dict, steps: int, points: int, seed: int, verbose: bool = True):
    """Simulate ``case`` in ``steps`` load steps, observe and predict the frames (module docstring); returns
    ``(path_summary, frames)`` with ``frames`` what ``--out`` writes: clouds, tips, true forces, the model dir, the
    mesh path and the exertion point."""
    from liverforce.dataset import io as dio
    from liverforce.learn.observation import ObservationConfig, observe
    from liverforce.mesh.io import read_mesh
    from liverforce.pipeline.shared import camera_arrays
    from liverforce.pipeline.simulate import make_manifest, probe_reference, simulate_cases
    from liverforce.serve import Predictor, Preop
    from liverforce.serve.input_frame import InputFrame
    from liverforce.serve.sequence import predict_sequence

    gid = case["geometry_id"]
    mesh_path = res / "mesh" / f"{gid}.vtu"
    rows = simulate_cases(step_cases(case, steps), {gid: read_mesh(mesh_path)}, cfg["simulate"], cfg["boundary"],
                          cfg["dataset"], probe=probe_reference(cfg["material"]))
    failed = [r["case_id"] for r in rows if not r["converged"]]
    if failed:
        raise SystemExit(f"load steps that did not converge: {failed}")
    with tempfile.TemporaryDirectory() as tmp:
        shard, manifest = Path(tmp) / "path.parquet", Path(tmp) / "manifest.json"
        dio.write_shard(rows, shard, compression=cfg["dataset"]["compression"])
        make_manifest([str(shard)], manifest)
        a = camera_arrays(manifest, [str(mesh_path)], "loading path")
    V, T = a["surface_meshes"][gid]
    p = np.asarray(a["exertion_point_mm"][0], dtype=np.float64)
    near = int(np.argmin(np.linalg.norm(V - p, axis=1)))
    obs = ObservationConfig(n_points=(points, points), noise_sd_mm=0.5, roi_radius_mm=40.0, instrument_in_cloud=True)
    rng = np.random.default_rng(seed)
    clouds, tips = [], []
    for k in range(steps):
        u = np.asarray(a["surface_displacement_mm"][k], dtype=np.float64)
        tip = p + u[near]
        clouds.append(observe(V + u, T, tip, a["frame_normal"][k], obs, seed=seed * 1000 + k)[0])
        tips.append(tip + rng.normal(0.0, 0.5, 3))
    tips = np.asarray(tips)
    model_dir = res / "models" / "IV" / "cloud_sv" / "model"
    preop = Preop.from_arrays({k: v for k, v in a.items() if k != "roi_deformed_mm"}, 0)  # the case's context
    out, summary = predict_sequence(Predictor.load(model_dir), preop, InputFrame.resolve(None), clouds, tips)
    F = np.asarray(a["force_n"], dtype=np.float64)
    P = np.array([[r["fx_n"], r["fy_n"], r["fz_n"]] for r in out])
    H = np.array([[r[f"half_width_{c}_n"] for c in COMPONENTS] for r in out])
    R = preop.frame
    s = path_summary(F, P, H, R)
    if verbose:
        print(f"{case['case_id']} ({gid}), |F| {np.linalg.norm(case['force_n']):.2f} N, {steps} FE load steps "
              f"(all converged, {sum(r['wall_time_s'] for r in rows):.0f} s), {model_dir}, {summary['path']} path:")
        print("frame |F| true | |F| pred | error N | in the interval t1 t2 n | warnings")
        for k, r in enumerate(out):
            e = (P[k] - F[k]) @ R.T
            inside = " ".join("y" if abs(e[j]) <= H[k, j] else "-" for j in range(3)) if np.isfinite(e).all() else ""
            print(f"{k + 1:5d} | {np.linalg.norm(F[k]):8.3f} | {r['magnitude_n']:8.3f} | "
                  f"{np.linalg.norm(P[k] - F[k]):7.3f} | {inside:>23} | {r['refused'] or r['warnings']}")
    return s, {"clouds": clouds, "tips": tips, "true": F, "predicted": P, "model_dir": model_dir,
               "mesh_path": mesh_path, "point": p}


def _line(s: dict) -> str:
    cov = " / ".join(f"{100 * c:.0f}" for c in s["coverage"])
    return (f"{s['predicted']} of {s['frames']} frames predicted; MAE {s['mae_n']:.3f} N; interval coverage t1 / t2 / "
            f"n {cov} %; error mean {' / '.join(f'{v:+.3f}' for v in s['mean_error_n'])} N, frame-to-frame noise "
            f"{' / '.join(f'{v:.3f}' for v in s['noise_n'])} N (t1 / t2 / n)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results/default", help="a finished default run (default results/default)")
    ap.add_argument("--liver", default=None, help="an unseen liver's id, or 'all': one path per unseen liver, "
                    "then the mean and sd over them (default: the run's first)")
    ap.add_argument("--case", default=None, help="a case id of that liver (default: its first of --min-force N)")
    ap.add_argument("--min-force", type=float, default=3.0, help="the default case's least force, N (default 3)")
    ap.add_argument("--steps", type=int, default=24, help="load steps, one frame each (default 24)")
    ap.add_argument("--points", type=int, default=5000, help="liver points per frame (default 5000)")
    ap.add_argument("--seed", type=int, default=0, help="the camera's and the kinematics' draws (default 0)")
    ap.add_argument("--overrides", nargs="*", default=[], help="Hydra overrides of the run's config (its experiment)")
    ap.add_argument("--out", default=None, help="write the recording here (frames, tips, truth; one liver)")
    args = ap.parse_args()

    from liverforce.pipeline.job import thread_env

    thread_env(1)
    from liverforce.config import compose
    from liverforce.dataset import io as dio

    res = Path(args.results)
    cfg = compose(list(args.overrides))
    table = dio.read_table(res / "sweep" / "V" / "cases.parquet").to_pylist()
    livers = sorted({c["geometry_id"] for c in table})
    which = livers if args.liver == "all" else [args.liver or livers[0]]
    if args.liver == "all" and (args.case or args.out):
        raise SystemExit("--liver all takes each liver's first case of --min-force N; --case and --out need one liver")
    done = []
    for gid in which:
        mine = sorted((c for c in table if c["geometry_id"] == gid), key=lambda c: c["case_id"])
        if args.case is not None:
            chosen = [c for c in mine if c["case_id"] == args.case]
        else:
            chosen = [c for c in mine if c["force_magnitude_n"] >= args.min_force][:1]
        if not chosen:
            raise SystemExit(f"{gid}: no case {args.case or f'of at least {args.min_force} N'}")
        s, frames = run_path(res, cfg, chosen[0], args.steps, args.points, args.seed, verbose=len(which) == 1)
        print(f"{chosen[0]['case_id']} ({gid}, |F| {np.linalg.norm(chosen[0]['force_n']):.2f} N): {_line(s)}")
        done.append(s)
    if len(done) > 1:
        def ms(key, j=None):
            v = np.array([d[key] if j is None else d[key][j] for d in done], dtype=np.float64)
            return f"{v.mean():.3f} +- {v.std(ddof=1):.3f}"
        print(f"over the {len(done)} livers (mean +- sd): MAE {ms('mae_n')} N; coverage t1 / t2 / n "
              f"{' / '.join(ms('coverage', j) for j in range(3))}; frame-to-frame noise "
              f"{' / '.join(ms('noise_n', j) for j in range(3))} N")
    if args.out:
        d = Path(args.out)
        (d / "frames").mkdir(parents=True, exist_ok=True)
        for k, c in enumerate(frames["clouds"]):
            np.save(d / "frames" / f"frame_{k + 1:02d}.npy", c)
        np.savetxt(d / "tips.csv", frames["tips"], delimiter=",", fmt="%.6f")
        np.savetxt(d / "truth.csv", frames["true"], delimiter=",", fmt="%.6f", header="fx_n,fy_n,fz_n", comments="")
        np.savetxt(d / "predicted.csv", frames["predicted"], delimiter=",", fmt="%.6f", header="fx_n,fy_n,fz_n",
                   comments="")  # this run's forces (the case's own shard context)
        mat = " ".join(f"{v:g}" for v in np.asarray(chosen[0]["material_params_mpa"]))
        print(f"replay: liverforce predict -m {frames['model_dir']} {d / 'frames'} --tool-tips {d / 'tips.csv'} "
              f"--mesh {frames['mesh_path']} --exertion-point {' '.join(f'{v:.6f}' for v in frames['point'])} "
              f"--material {mat} --out {d / 'forces.csv'}")


if __name__ == "__main__":
    main()
