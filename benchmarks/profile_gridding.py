"""Profile: where the compiled camera path's gridding pass spends its time, stage by stage, and A/B against a revision.

``bench_camera.py --profile`` switches whole fits off in the kernel's parameters. This splits the pass
(:func:`liverforce.serve.compiled_cloud._grid_one`) into its stages: a copy of the kernel, made from its source
when this runs, returns after stage ``k`` when passed ``stop = k``; a batch gridded with ``stop = 1, 2, ...``
in turn, ``--repeats`` times interleaved, gives each stage's time as the difference of two medians (us per
cloud). The copy's cut points are lines of the kernel's source (``_STAGES``): a line no longer there stops the
script with its name, not a wrong table. The shipped kernel's own time and the kernel parameters' switches
(the dent fit, the tilted instrument fit, the drop of gross depth errors, the Laplace fill off) are timed in the
same rounds.

``--against REV`` instead times this tree's gridding pass and GP head against revision ``REV``'s
(``git show REV:liverforce/serve/compiled_cloud.py`` and ``.../learn/gp.py``, imported as modules of their own),
alternating, ``--repeats`` times each, and prints the medians, the ratio new / old and how far the feature rows
(masks exactly) and the head's forces are apart.

The model and clouds: a finished run's camera model (``<results>/models/IV/cloud_sv/model``, a GP over the run's
training rows) and case ``--case`` of its unseen livers (``<results>/shards/V``) as its own pre-operative
context; 20 clouds observed as ``bench_camera.py`` observes them (``--points`` liver points, the instrument's,
0.5 mm noise), jittered into ``--distinct`` copies, a batch of ``--clouds`` cycling them (1 thread).

Usage: ``PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python benchmarks/profile_gridding.py --results results/default
[--against HEAD~1] [--repeats 7]``
"""

from __future__ import annotations

import argparse
import importlib.util
import inspect
import os
import subprocess
import sys
import tempfile
import textwrap
import time

from liverforce.pipeline.job import thread_env

_ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
_ap.add_argument("--results", default="results/default", help="a finished run (default results/default)")
_ap.add_argument("--case", type=int, default=0, help="which case of the unseen livers (default 0)")
_ap.add_argument("--points", type=int, default=5000, help="liver points per cloud (default 5000)")
_ap.add_argument("--distinct", type=int, default=256, help="distinct clouds (jittered copies) in a batch")
_ap.add_argument("--clouds", type=int, default=2048, help="clouds per batch (default 2048)")
_ap.add_argument("--repeats", type=int, default=7, help="timed batches per variant, interleaved (default 7)")
_ap.add_argument("--against", default=None, help="a git revision: A/B this tree's gridding and head against it")
ARGS = _ap.parse_args()
thread_env(1)

import numpy as np  # noqa: E402
from numba import njit  # noqa: E402

from liverforce.learn.observation import ObservationConfig, observe  # noqa: E402
from liverforce.pipeline.shared import run_arrays  # noqa: E402
from liverforce.serve import Predictor, Preop  # noqa: E402
from liverforce.serve import compiled_cloud as cc  # noqa: E402

_STAGES = [  # (name, the kernel's source line(s) the stage ends before)
    ("rotation into the local frame", "    for k in range(n):\n        u = U[k]\n"),
    ("filter: counts, compaction", "    tb = 16\n"),
    ("grid index, sort key, raster cell, hash", "    shaft_r2, ring_r2, shaft_rise, shaft_min = "),
    ("heights over the raster, the shaft's count", "    # 3. counting sort"),
    ("counting sort and gather", "    n_dup = 0\n"),
    ("exact duplicates", "    nf = 0\n"),
    ("the instrument's fits (tilted, normal)", "    if n_dup:  # the duplicates' origin"),
    ("compaction of the duplicates", "    # 4. moments"),
    ("kernel moments", "    n_valid = _cell_planes("),
    ("plane fits", "    n_off = 0\n"),
    ("drop of gross depth errors (+ moments, planes again)", "    if inst[10] > 0.0:"),
    ("dent fit", "    # 5. fill"),
    ("Laplace fill and the row", None),  # the rest
]


def staged_kernel():
    """``_grid_one`` with a last argument ``stop``: returns after stage ``stop`` (1-based; 0 or more than the
    stages: the whole pass), and a batch runner ``run(clouds, tips, params..., X, stop)``."""
    src = textwrap.dedent(inspect.getsource(cc._grid_one))
    src = src[src.index("def _grid_one("):]  # without the decorator
    src = src.replace("shaft, inst, ws, x):", "shaft, inst, ws, x, stop):", 1)
    for k, (name, line) in enumerate(_STAGES[:-1], start=1):
        at = src.find("\n" + line)
        if at < 0 or src.count("\n" + line) != 1:
            sys.exit(f"profile_gridding: the stage {name!r} ends before {line!r}, which is not once in "
                     "compiled_cloud._grid_one any more: update _STAGES")
        src = src[:at + 1] + f"    if stop == {k}:\n        return 0, 0, 0, 0, np.nan, 0, 0\n" + src[at + 1:]
    scope = dict(vars(cc))
    exec(compile(src, "<staged _grid_one>", "exec"), scope)
    one = njit(fastmath={"contract"})(scope["_grid_one"])

    @njit
    def run(clouds, tips, origin, R, raster, lo, rstep, g, h, gstep, kr, max_abs, min_points, max_leverage,
            linear, fill, reach_count, shaft, inst, X, stop):
        nmax = 1
        for b in range(len(clouds)):
            nmax = max(nmax, clouds[b].shape[0])
        ws = cc._workspace(nmax, g, kr)
        for b in range(len(clouds)):
            P = clouds[b]
            one(P, 0, P.shape[0], tips[b], origin, R, raster, lo, rstep, g, h, gstep, kr, max_abs, min_points,
                max_leverage, linear, fill, reach_count, shaft, inst, ws, X[b], stop)

    return run


def setup():
    """The compiled model, its predictor, the preop, the batch (a typed list) and the tips."""
    a = run_arrays(ARGS.results, "V", True, "profile_gridding")
    i = ARGS.case
    V, T = a["surface_meshes"][str(a["geometry_id"][i])]
    u = np.asarray(a["surface_displacement_mm"][i], dtype=np.float64)
    p = np.asarray(a["exertion_point_mm"][i], dtype=np.float64)
    tip = p + u[int(np.argmin(np.linalg.norm(V - p, axis=1)))]
    cfg = ObservationConfig(n_points=(ARGS.points, ARGS.points), noise_sd_mm=0.5, roi_radius_mm=40.0,
                            instrument_in_cloud=True)
    clouds = [observe(V + u, T, tip, a["frame_normal"][i], cfg, seed=s)[0] for s in range(20)]
    rng = np.random.default_rng(0)
    pool = [clouds[k % 20] + rng.normal(0.0, 0.01, clouds[k % 20].shape) for k in range(ARGS.distinct)]
    batch = [pool[k % len(pool)] for k in range(ARGS.clouds)]
    pred = Predictor.load(f"{ARGS.results}/models/IV/cloud_sv/model")
    preop = Preop.from_arrays({k: v for k, v in a.items() if k != "roi_deformed_mm"}, i)
    return pred, preop, batch, np.tile(tip, (len(batch), 1))


def per_cloud(fn, n: int) -> float:
    t = time.perf_counter()
    fn()
    return (time.perf_counter() - t) / n * 1e6


def profile(fast, batch, tips) -> None:
    run = staged_kernel()
    sp = fast.spec
    clouds = cc.List.empty_list(cc._CLOUD_TYPE)
    for c in batch:
        clouds.append(c)
    X = np.empty((len(batch), fast.n_features))

    def params(inst=None, fill=None):
        return (fast._kp, fast._kR, fast._raster, fast.ref.lo, fast.ref.step, fast.g, sp.half_width_mm,
                sp.spacing_mm, sp.kernel_radius_cells, sp.max_abs_height_mm, sp.min_points, sp.max_leverage,
                sp.estimator == "linear", cc._FILL_CODES[sp.fill] if fill is None else fill, fast.reach,
                fast._shaft, fast._inst if inst is None else inst)

    def switched(*off):
        inst = fast._inst.copy()
        inst[list(off)] = 0.0
        return inst

    variants = {f"stop {k}": (params(), k) for k in range(1, len(_STAGES))}
    variants["whole pass (copy)"] = (params(), 0)
    switches = {"without the dent fit": (params(switched(10)), 0),
                "without the tilted fit (the fit along the normal)": (params(switched(8)), 0),
                "without the instrument's fits (nor the dent)": (params(switched(0, 8, 10)), 0),
                "without the drop of gross depth errors": (params(switched(14)), 0),
                "without the Laplace fill (zeros)": (params(fill=0), 0)}
    variants.update(switches)
    n = len(batch)
    for prm, stop in variants.values():  # compile and warm up
        run(clouds, tips, *prm, X, stop)
    times: dict = {k: [] for k in variants}
    shipped = []
    for _ in range(ARGS.repeats):
        shipped.append(per_cloud(lambda: fast._grid(batch, None, None, tips), n))
        for name, (prm, stop) in variants.items():
            times[name].append(per_cloud(lambda: run(clouds, tips, *prm, X, stop), n))
    med = {k: float(np.median(v)) for k, v in times.items()}
    print(f"gridding pass, {n} clouds ({ARGS.distinct} distinct, {np.mean([len(c) for c in batch]):.0f} points), "
          f"grid {fast.g}^2, us per cloud, medians of {ARGS.repeats} interleaved rounds (1 thread):")
    print(f"  CompiledCloud._grid as shipped: {np.median(shipped):.1f}; the staged copy, whole: "
          f"{med['whole pass (copy)']:.1f}")
    prev = 0.0
    for k, (name, _) in enumerate(_STAGES, start=1):
        upto = med[f"stop {k}"] if k < len(_STAGES) else med["whole pass (copy)"]
        print(f"  {k:2d}. {name:55s} {upto - prev:7.1f}   (cumulative {upto:6.1f})")
        prev = upto
    for name in switches:
        print(f"  {name:59s} {med[name]:7.1f}   ({med[name] - med['whole pass (copy)']:+.1f})")


def _module_at(rev: str, path: str, name: str, tmp: str):
    """The file ``path`` of git revision ``rev`` imported as a module ``name`` (its numba cache in ``tmp``)."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    src = subprocess.run(["git", "-C", root, "show", f"{rev}:{path}"], capture_output=True, text=True)
    if src.returncode:
        sys.exit(f"profile_gridding: --against {rev}: git show failed: {src.stderr.strip()}")
    file = os.path.join(tmp, f"{name}.py")
    with open(file, "w") as f:
        f.write(src.stdout)
    spec = importlib.util.spec_from_file_location(name, file)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def against(pred, preop, fast, batch, tips) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        old_cc = _module_at(ARGS.against, "liverforce/serve/compiled_cloud.py", "old_compiled_cloud", tmp)
        old_gp = _module_at(ARGS.against, "liverforce/learn/gp.py", "old_gp", tmp)
        old = old_cc.CompiledCloud(pred.model, preop, limits=fast.limits)
        reg = pred.model.regressor
        nz = fast.A.shape[0]
        fixed = {nz + k: float(v) for k, v in enumerate(fast.s_base.astype(np.float32))} or None
        if fast.gp is not None:
            from liverforce.learn.gp import GPEnsemble

            cls = old_gp.GPEnsemble if isinstance(reg, GPEnsemble) else old_gp.GPRegressor
            spread = {"members": True} if getattr(old, "_spread", False) else {}  # a revision with the spread
            if getattr(old, "_far", None) is not None:  # a revision with the input-distance flag
                spread["distance"] = True
            old.gp = cls.from_state_dict(reg.state_dict()).numpy_head(fixed, **spread)
        n = len(batch)
        Xn = fast._grid(batch, None, None, tips)[0]
        Xo = old._grid(batch, None, None, tips)[0]
        g2 = fast.g * fast.g
        same_mask = np.array_equal(Xn[:, g2:2 * g2], Xo[:, g2:2 * g2])
        dx = float(np.nanmax(np.abs(Xn - Xo)))
        Fn, Fo = (h[0] if isinstance(h, tuple) else h for h in (fast._head(Xn), old._head(Xn)))  # (F, sd) since 17
        dF = float(np.abs(Fn - Fo).max())
        rows = slice(0, (n // cc._HEAD_ROWS) * cc._HEAD_ROWS or n)

        def head(obj):
            def f():
                for a in range(0, rows.stop, cc._HEAD_ROWS):
                    obj._head(Xn[a:a + cc._HEAD_ROWS])
            return f

        t = {"grid new": [], "grid old": [], "head new": [], "head old": []}
        for r in range(ARGS.repeats):  # alternating which goes first
            pairs = [("new", fast), ("old", old)] if r % 2 == 0 else [("old", old), ("new", fast)]
            for tag, obj in pairs:
                t[f"grid {tag}"].append(per_cloud(lambda: obj._grid(batch, None, None, tips), n))
            for tag, obj in pairs:
                t[f"head {tag}"].append(per_cloud(head(obj), rows.stop))
        med = {k: float(np.median(v)) for k, v in t.items()}
        print(f"this tree against {ARGS.against}, {n} clouds, us per cloud, medians of {ARGS.repeats} alternating "
              "rounds (1 thread):")
        for what in ("grid", "head"):
            ratios = np.array(t[f"{what} new"]) / np.array(t[f"{what} old"])
            print(f"  {what}: new {med[what + ' new']:.1f}, old {med[what + ' old']:.1f}, new / old "
                  f"{med[what + ' new'] / med[what + ' old']:.3f}; per round median {np.median(ratios):.3f}, "
                  f"quartiles {np.percentile(ratios, 25):.3f} - {np.percentile(ratios, 75):.3f}")
        print(f"  feature rows: max |diff| {dx:.1e}, masks {'identical' if same_mask else 'DIFFERENT'}; head "
              f"forces max |diff| {dF:.1e} N")


def main() -> None:
    pred, preop, batch, tips = setup()
    fast = pred.compile_cloud(preop)
    if ARGS.against:
        against(pred, preop, fast, batch, tips)
    else:
        profile(fast, batch, tips)


if __name__ == "__main__":
    main()
