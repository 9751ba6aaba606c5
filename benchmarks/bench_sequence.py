"""Benchmark: a finished run's own camera model on a sequence of clouds of an unseen liver, 1 and N threads.

``bench_camera.py`` times the compiled path on a synthetic model of the shipped settings. This one takes the
run's own camera model (``<results>/models/IV/cloud_sv/model``, a GP over the run's training rows) and one case
of the unseen livers (``<results>/shards/V``, its mesh from ``<results>/mesh``): ``--distinct`` clouds of it
are observed as the evaluation's camera sees them (``--points`` liver points, 0.5 mm noise, the instrument in
the cloud), the FE displacement scaled from 0 to 1 and back (the tool pressing in and out, a stand-in for a
recording), each tip with 0.5 mm of kinematic noise; the batch repeats them to ``--clouds`` clouds. The
pre-operative context is the case's own (its shard row: ROI, frame, state), as the validation reads it. It times
``CompiledCloud.predict_batch`` on 1 and ``--threads`` threads, interleaved, ``--repeats`` times, and prints
the medians per cloud and in clouds/s, and whether the forces are the same bits.

Usage: ``PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_sequence.py --results results/default``
"""

from __future__ import annotations

import argparse
import time

from liverforce.pipeline.job import thread_env

_ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
_ap.add_argument("--results", default="results/default", help="a finished run (default results/default)")
_ap.add_argument("--case", type=int, default=0, help="which converged case of the unseen livers (default 0)")
_ap.add_argument("--distinct", type=int, default=200, help="distinct clouds observed (default 200)")
_ap.add_argument("--clouds", type=int, default=1000, help="clouds per batch (default 1000)")
_ap.add_argument("--points", type=int, default=5000, help="liver points per cloud (default 5000)")
_ap.add_argument("--threads", type=int, default=2, help="threads besides 1 (default 2)")
_ap.add_argument("--repeats", type=int, default=9, help="timed batches per thread count (default 9)")
ARGS = _ap.parse_args()
thread_env(1)

import numpy as np  # noqa: E402

from liverforce.learn.observation import ObservationConfig, observe  # noqa: E402
from liverforce.pipeline.shared import run_arrays  # noqa: E402
from liverforce.serve import Predictor, Preop  # noqa: E402


def main() -> None:
    a = run_arrays(ARGS.results, "V", True, "bench_sequence")
    i = ARGS.case
    geo = str(a["geometry_id"][i])
    V, T = a["surface_meshes"][geo]
    u = np.asarray(a["surface_displacement_mm"][i], dtype=np.float64)
    p = np.asarray(a["exertion_point_mm"][i], dtype=np.float64)
    tip = p + u[int(np.argmin(np.linalg.norm(V - p, axis=1)))]
    cfg = ObservationConfig(n_points=(ARGS.points, ARGS.points), noise_sd_mm=0.5, roi_radius_mm=40.0,
                            instrument_in_cloud=True)
    rng = np.random.default_rng(0)
    clouds, tips = [], []
    for k in range(ARGS.distinct):
        s = np.sin(np.pi * k / max(ARGS.distinct - 1, 1))
        clouds.append(observe(V + s * u, T, p + s * (tip - p), a["frame_normal"][i], cfg, seed=k)[0])
        tips.append(p + s * (tip - p) + rng.normal(0.0, 0.5, 3))
    clouds = [clouds[k % len(clouds)] for k in range(ARGS.clouds)]
    tips = np.array([tips[k % len(tips)] for k in range(ARGS.clouds)])
    model_dir = f"{ARGS.results}/models/IV/cloud_sv/model"
    pred = Predictor.load(model_dir)
    preop = Preop.from_arrays({k: v for k, v in a.items() if k != "roi_deformed_mm"}, i)  # the case's own context
    fast = pred.compile_cloud(preop)
    counts = (1, ARGS.threads)
    first = {n: fast.predict_batch(clouds, tips, threads=n) for n in counts}  # also the warm-up
    same = np.array_equal(first[1].force, first[ARGS.threads].force, equal_nan=True)
    times: dict = {n: [] for n in counts}
    for _ in range(ARGS.repeats):
        for n in counts:
            t0 = time.perf_counter()
            fast.predict_batch(clouds, tips, threads=n)
            times[n].append(time.perf_counter() - t0)
    print(f"{model_dir} on {ARGS.clouds} clouds ({ARGS.distinct} distinct, {np.mean([len(c) for c in clouds]):.0f} "
          f"points) of {a['case_id'][i]} ({geo}); {int(first[1].ok.sum())} predicted; medians of {ARGS.repeats}, "
          "interleaved:")
    for n in counts:
        m = float(np.median(times[n])) / ARGS.clouds
        print(f"  {n} thread(s): {1e6 * m:.1f} us per cloud, {1 / m:,.0f} clouds/s")
    r = np.median(times[1]) / np.median(times[ARGS.threads])
    print(f"  {ARGS.threads} threads: {r:.2f}x one; forces {'the same bits' if same else 'DIFFERENT'}")


if __name__ == "__main__":
    main()
