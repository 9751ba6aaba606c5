"""Fast path of a camera-cloud model at one exertion point: raw clouds and tool tips -> forces and intervals.

In the operating room the tool rests at one exertion point while the camera
streams clouds. Everything that depends only on the pre-operative context is
done once, when compiling (:class:`CompiledCloud`):

- the pre-operative height raster of :class:`~liverforce.learn.cloud_features.ReferenceSurface`;
- the state vector (scaled), the compliance's inverse ``C^-1`` (for ``f_lin``),
  the stiffness factor of the material (``C10 / C10_ref``: the force scaling's, and
  the interval's widening outside its calibration's stiffness range) and so the
  interval's half-widths (with ``train.interval.scale: force`` those before the
  force's scale ``a + b |F|``, a few multiplications per cloud);
- the scalers and PCA folded into one affine map; the MLP as NumPy arrays
  (float32, as the torch reference; :func:`liverforce.serve.compiled.numpy_layers`)
  or the Gaussian process's posterior mean
  (:meth:`liverforce.learn.gp.GPRegressor.numpy_head`: the training rows scaled, ``alpha`` and the
  linear term folded).

A call (:meth:`CompiledCloud.predict`, one cloud) or a batch
(:meth:`CompiledCloud.predict_batch`, many clouds, one kernel call: a list is
read in place, not concatenated) then runs, per cloud, one compiled (numba)
pass that does what :func:`~liverforce.learn.cloud_features.cloud_grid` does,
in a few loops over the points instead of NumPy temporaries:

1. every point: rotate into the local frame, count the points over the grid
   and the non-finite ones (the refusal checks of the reference path), keep
   the points within the kernel's reach (compacted without branches);
2. the kept points: grid-index coordinates, sort bin (half a grid step wide
   for the shipped 1.5-step kernel, so that a grid point's bins hold no point
   beyond the kernel along u or v; ordered by groups of bin rows one grid step
   tall, column by column within a group), the height change over the
   pre-operative raster (same bilinear read);
3. a stable counting sort by bin; exact duplicate points (equal local
   coordinates) count once, as in the reference's canonical order: a bit
   table of hashed coordinates flags the few candidates, each checked
   exactly against the earlier points of its bin;
4. the biweight-kernel moments of every grid point from one contiguous run
   of points per group of bin rows (two for a one-step kernel, three for the
   shipped 1.5), the per-cell weighted plane fit, the validity test (same
   formulas);
5. the Laplace fill of the invalid cells as a banded Cholesky solve (the
   4-neighbour system of the unknowns has bandwidth ``<= g`` in flat cell
   order), instead of the reference's dense LU; ``nearest`` fill goes back to
   the reference's function.

A batch can be gridded in several threads (``predict_batch(threads=N)``): the
batch is cut into ``N`` contiguous parts, each gridded by the kernel (which
releases the GIL) with its own scratch arrays, and the head's blocks of
``_HEAD_ROWS`` rows run in the threads too. Each cloud is gridded as it would
be alone and the blocks are the same, so the results are the same bits.

Indices into the arrays are unsigned where numba cannot see they are >= 0
(it would otherwise emit the negative-index wrap, which stops LLVM from
loading runs contiguously: the moments took 2.4x longer), and the pass lets
LLVM fuse multiply-adds (``R (x - p)`` then matches NumPy/BLAS's bits more
often, 80 % of coordinates against 68 %; with an input frame folded into ``R`` and
``p``, the local coordinates agree with the converted cloud's to rounding only).
Every kernel names its own fast-math flags and error model, so that its machine
code does not depend on which caller compiled it first (numba passes a caller's
on to a function that names none).

The features agree with ``cloud_grid`` to rounding (sums in another order:
about 1e-14 mm; tests check 1e-9 mm and identical masks). The
out-of-distribution checks are those of
:func:`liverforce.serve.cloud.camera_checks` (called for every cloud near or
past a limit; the others pass them by construction). For an MLP the affine
map and the MLP run row by row in a fixed order (float64 affine, float32 MLP,
as the reference), so a cloud gives bit-identical forces alone or inside a
batch of any size. For a GP the affine map and the head
(``GPRegressor.numpy_head`` with the context's state held in it; equal to the
module to ~1e-14) multiply with BLAS, so there a cloud alone and in a batch
agree to rounding, not bit for bit: ~1e-15 relative, and where a code's
float32 rounding (the inputs the reference feeds the GP) falls the other way,
rarely, one float32 step of that code. The reference path
(:meth:`liverforce.serve.Predictor.predict_cloud`) stays the oracle: a test
checks both agree to 1e-6 N, and that both refuse the same inputs with the
same reasons (tool tip missing or off the grid, NaN points, too few points
over the grid, too little of the grid seen, heights or tip displacements far
outside training).

Measured with ``benchmarks/bench_camera.py`` (5,000-point clouds, 12 x 12
grid, 1 thread, a loaded 2-core VM): see the commit that last changed this
module.
"""

from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numpy as np
from numba import njit, types
from numba.typed import List

from liverforce.learn import camera, cloud_features
from liverforce.learn.cloud_features import (_COST_RTOL, _FIT_ITERATIONS, _MAD_SD, _MIN_POINT_SD, _MIN_TIP_SD,
                                             ReferenceSurface, _fill, instrument_search_radius, shaft_fit_radius)
from liverforce.learn.encoders import PCAEncoder
from liverforce.learn.state import THICKNESS_COLUMN, compliance_matrices, state_vector
from liverforce.serve.checks import Limits, TrainingScale, distance_warnings, force_warnings, outside_training
from liverforce.serve.cloud import (MASKED_INSTRUMENT, SHAFT_MARGIN_MM, SHAFT_POINTS, SHAFT_RING_MM, SHAFT_RISE_MM,
                                    camera_checks, check_camera_cloud, instrument_check_radius, instrument_refusal,
                                    metres_cloud, noisy_cloud, noisy_threshold_mm, outlier_cloud, registration_warnings,
                                    tip_off_grid, tool_tip_of)
from liverforce.serve.compiled import numpy_layers, regressor_head
from liverforce.serve.errors import PredictionInputError
from liverforce.serve.input_frame import InputFrame, as_entered
from liverforce.serve.preop import Preop, _points

_FILL_CODES = {"zero": 0, "laplace": 1, "nearest": 2}
_CHUNK = 64  # clouds per conversion of a padded array that is not float32 / float64 C-contiguous (bounds the copy)
_RUN = 8  # _cell_moments reads a run on to a multiple of this many points (fewer scalar loop remainders)
_MAX_POINTS = 2**31 - 1  # points per cloud: the kernel's sort keys and indices are 32-bit
_HEAD_ROWS = 128  # feature rows per call of the head (the GP's kernel matrix: rows x 2,000 training rows). On an
# AVX-512 host, 5 members of 38-94 inputs, us per row at 64 / 128 / 256 rows: 45 / 44 / 47 (1 thread, medians of 9);
# with the fused pass (gp._rq_power_mean, session 42), one 62-input member at 32 / 64 / 128 / 256 rows: 9.0 / 7.8
# / 7.4 / 7.2 us (benchmarks/bench_gp_head.py --block, medians of 7)
_CLOUD_TYPE = types.Array(types.float64, 2, "C", readonly=True)  # items of the typed list of clouds: one signature
# for writable and read-only (e.g. Arrow-backed) clouds alike


# --------------------------------------------------------------------------
# compiled kernels (numba; serial and deterministic; the batch entries release the GIL for predict_batch threads).
# Each names its fast-math flags and error model: numba gives a function that names none its caller's, and the
# first caller to compile a signature fixes its machine code for all (on disk too), so a test that called
# _dent_fit before the pass was compiled moved the pass's dent columns by ~1e-14 (_spd4_solve without FMAs).
# The flags are those each kernel had when compiled from _grid_one: "contract" for the pass and what it calls
# (the sums' loops, the entry points and the MLP's rows their own; _dent_solve none); error model "python" (the
# dent's sums "numpy").
# --------------------------------------------------------------------------


@njit(cache=True, fastmath={"reassoc", "nsz", "contract", "arcp"}, error_model="python")
def _cell_moments(GU, GV, Z, first, g, kr, sb, pad, nc, exact, M):
    """Biweight moments of every grid point ``(I, J)`` from the points sorted by bin (:func:`_bins`).

    ``GU, GV``: grid-index coordinates, ``Z``: height change; the points in bin ``(floor(gv sb), floor(gu sb))``
    are ``first[key]:first[key + 1]`` with ``key`` from :func:`_bin_key`: groups of ``sb`` bin rows (one grid
    step), column by column within a group, so the points within ``kr`` of a grid point are one run per group
    (three runs, each of six half-step bin columns of two bin rows, for the shipped ``kr = 1.5``, ``sb = 2``:
    a grid point's first bin row starts a group; with ``exact`` false one bin more on each side, and whole
    groups). Each run ends in a horizontal sum of the vector accumulators, so fewer, longer runs cost less
    (about 4.5 us per 5,000-point cloud less than one run per bin row). ``M[I * g + J]`` gets: sum of w, of 1 (points
    within the support), of w z, w du, w dv, w du^2, w dv^2, w du dv, w du z, w dv z (``w = (1 - q)^2``,
    ``q = d2 / kr^2``, ``d2 = du^2 + dv^2 < kr^2``: the reference's test ``d2 / kr^2 < 1``), the sums of
    ``cloud_features.cloud_grid``. Points outside the support add exact zeros (so do those of a group's rows
    beyond it), and the points after a run's last bin column in its group lie ``>= kr`` to the right
    (``d2 >= kr^2`` in floating point too: with ``exact`` the bin edges are the support's edges exactly), so a
    run is read on to a multiple of ``_RUN`` points within its group: LLVM's vector loop then less often ends
    in its scalar remainder. The fast-math flags let LLVM vectorise
    the sums: their order depends only on the points' order, never on the batch, so a cloud gives the same bits
    alone or in a batch (and the reference's sums to rounding). The count of points within the support is summed
    as an integer (the same whole number): with ten float sums in AVX2's sixteen vector registers one of them was
    kept on the stack, a store and a load per step of the loop (the pass took 1.2x the time).
    """
    kr2 = kr * kr
    inv_kr2 = 1.0 / kr2
    row = nc * sb  # keys per group of sb bin rows
    m = 0 if exact else 1  # inexact edges: a whole bin of margin on each side
    for I in range(g):
        i_lo = int(math.floor((I - kr) * sb)) - m + pad
        i_hi = int(math.ceil((I + kr) * sb)) - 1 + m + pad  # bin rows floor(gv sb) of the points with |gv - I| < kr
        for J in range(g):
            j_lo = int(math.floor((J - kr) * sb)) - m + pad
            j_hi = int(math.ceil((J + kr) * sb)) - 1 + m + pad
            s0 = s2 = s3 = s4 = s5 = s6 = s7 = s8 = s9 = 0.0
            s1 = 0  # a whole count: integer lanes, one vector register fewer for the float sums (no spill)
            for p in range(i_lo // sb, i_hi // sb + 1):  # groups of sb bin rows
                base = p * row
                a0 = first[base + j_lo * sb]
                e0 = min(a0 + (first[base + (j_hi + 1) * sb] - a0 + _RUN - 1) // _RUN * _RUN, first[base + row])
                # unsigned bounds: numba then knows t >= 0 (no negative-index wrap), and LLVM loads contiguously
                for t in range(np.uint64(a0), np.uint64(e0)):
                    du = GU[t] - J
                    dv = GV[t] - I
                    d2 = du * du + dv * dv
                    q = d2 * inv_kr2
                    inside = d2 < kr2
                    wt = (1.0 - q) * (1.0 - q) if inside else 0.0
                    z = Z[t]
                    s0 += wt
                    s1 += inside
                    s2 += wt * z
                    s3 += wt * du
                    s4 += wt * dv
                    s5 += wt * (du * du)
                    s6 += wt * (dv * dv)
                    s7 += wt * (du * dv)
                    s8 += wt * (du * z)
                    s9 += wt * (dv * z)
            cell = I * g + J
            M[cell, 0] = s0
            M[cell, 1] = s1
            M[cell, 2] = s2
            M[cell, 3] = s3
            M[cell, 4] = s4
            M[cell, 5] = s5
            M[cell, 6] = s6
            M[cell, 7] = s7
            M[cell, 8] = s8
            M[cell, 9] = s9


@njit(cache=True, fastmath=False, error_model="python")
def _bins(g, kr):
    """Sort bins of :func:`_grid_one`: bins per grid step ``sb``, padding ``pad``, bins per row ``nc``, ``exact``.

    ``exact``: ``sb`` (1, 2 or 4, at most 64 bins over the grid, ``kr sb <= 8``) makes ``kr sb`` whole, so the
    bin edges ``(I +- kr) sb`` are the kernel support's edges exactly (``I +- kr`` and the products are exact in
    floating point; 1 for ``kr = 1``, 2 for the shipped 1.5). Else half-step bins (whole steps for ``kr > 2`` or
    a grid over 32 points) and :func:`_cell_moments` reads one bin more on each side. ``pad`` bins beyond the
    grid on each side hold the kept points off it (``|gu|, |gv|`` within ``kr`` of the grid) and that margin;
    with ``exact``, ``pad = kr sb + sb``, so that a grid point's first bin row ``(I - kr) sb + pad`` starts a
    group of ``sb`` rows (:func:`_bin_key`). ``nc``: bins per row and rows, a multiple of ``sb``.
    """
    for c in (1, 2, 4):
        if kr * c == math.floor(kr * c) and g * c <= 64 and kr * c <= 8.0:
            pad = int(kr * c) + c  # > kr c, and = kr c mod c: a grid point's first bin row starts a group
            return c, pad, (g * c + 2 * pad + c - 1) // c * c, True
    sb = 1 if kr > 2.0 or g > 32 else 2
    pad = int(math.ceil(kr * sb)) + 2
    return sb, pad, g * sb + 2 * pad, False


@njit(cache=True, fastmath={"contract"}, error_model="python")
def _bin_key(gu, gv, sb, pad, nc):
    """Bin of grid-index coordinates ``(gu, gv)`` (clamped to the bins; a kept point never is): bin row ``r``,
    column ``c``; key ``(r // sb, c, r % sb)`` row-major (groups of ``sb`` rows, column by column within one).
    32-bit conversions (a kept point's ``gu sb``, ``gv sb`` are within the bins): AVX2 has no vector conversion
    of a double to a 64-bit integer, and :func:`_grid_one`'s pass over the kept points vectorises with these."""
    r = min(max(np.int32(math.floor(gv * sb)) + pad, 0), nc - 1)
    c = min(max(np.int32(math.floor(gu * sb)) + pad, 0), nc - 1)
    return _key(r, c, sb, nc)


@njit(cache=True, fastmath={"contract"}, error_model="python")
def _key(r, c, sb, nc):
    """Sort key of bin row ``r``, column ``c`` (:func:`_bin_key`)."""
    return (r >> (sb >> 1)) * (nc * sb) + c * sb + (r & (sb - 1))  # sb is 1, 2 or 4: shifts, not divisions


@njit(cache=True, fastmath=False, error_model="python")
def _workspace(nmax, g, kr):
    """Scratch arrays of :func:`_grid_one` for clouds of up to ``nmax`` points (allocated once per call)."""
    gg = g * g
    nc = _bins(g, kr)[2]  # bin rows / columns, with those beyond the grid a kept point can lie in
    nmax = max(nmax, 1)
    tb = 16  # duplicate filter: a bit table of >= 16 bits per point
    while (1 << tb) < 16 * nmax:
        tb += 1
    return (np.empty(nmax), np.empty(nmax), np.empty(nmax),  # U, V, W: local frame (every point, then the kept)
            np.empty(nmax), np.empty(nmax), np.empty(nmax), np.empty(nmax, dtype=np.int32),  # GU, GV, Z, key
            np.empty(nmax), np.empty(nmax), np.empty(nmax, dtype=np.uint64),  # raster cell offsets, index (A: then
            np.empty(nmax, dtype=np.int64),  # the tilted fit's scratch); duplicate filter's hash (then its raised list)
            np.empty(nmax), np.empty(nmax), np.empty(nmax), np.empty(nmax, dtype=np.int32),  # sorted; origin
            np.empty(nc * nc + 1, dtype=np.int32), np.empty(nc * nc, dtype=np.int32),  # first, fill_at
            np.zeros(1 << (tb - 5), dtype=np.int64), np.empty(nmax, dtype=np.int32),  # bit table, candidates
            np.zeros((gg, 10)), np.zeros(gg), np.zeros(gg, dtype=np.bool_),  # M, Hc, valid
            np.empty(gg, dtype=np.int64), np.empty(gg, dtype=np.int64), np.zeros((gg, g + 1)),  # idx, unk, Lb
            np.zeros(gg), np.zeros(gg), np.zeros(gg), np.zeros(gg))  # rhs, y; the planes' slopes


@njit(cache=True, fastmath={"reassoc", "nsz", "contract", "arcp"}, error_model="python")  # sums in SIMD lanes
def _axis_system(P, k, cu, cv, r):
    """The Gauss-Newton sums of ``cloud_features._fit_axis`` at ``(cu, cv)`` on the points ``P[:, :k]`` (rows
    ``u, v``, contiguous, so the loop runs in SIMD lanes): ``J^T J`` (upper triangle) and ``J^T res``."""
    hxx = hxy = hyy = gx = gy = 0.0
    for j in range(k):
        dx = P[0, j] - cu
        dy = P[1, j] - cv
        n = max(math.sqrt(dx * dx + dy * dy), 1e-9)
        inv = 1.0 / n
        res = n - r
        jx = -dx * inv
        jy = -dy * inv
        hxx += jx * jx
        hxy += jx * jy
        hyy += jy * jy
        gx += jx * res
        gy += jy * res
    return hxx, hxy, hyy, gx, gy


@njit(cache=True, fastmath={"contract"}, error_model="python")
def _axis_steps(P, k, cu, cv, c0u, c0v, r, wp, wk):
    """Gauss-Newton steps of the instrument's axis on the points ``P[:, :k]`` (rows: local ``u, v``), from
    ``(cu, cv)``, the kinematic tip ``(c0u, c0v)`` the prior: ``cloud_features._fit_axis``."""
    for _ in range(_FIT_ITERATIONS):
        hxx, hxy, hyy, gx, gy = _axis_system(P, k, cu, cv, r)
        a = wp * hxx + wk
        b = wp * hxy
        d = wp * hyy + wk
        ex = wp * gx + wk * (cu - c0u)
        ey = wp * gy + wk * (cv - c0v)
        det = a * d - b * b
        sx = (d * ex - b * ey) / det
        sy = (a * ey - b * ex) / det
        cu -= sx
        cv -= sy
        if sx * sx + sy * sy < 1e-16:
            break
    return cu, cv


@njit(cache=True, fastmath={"contract"}, error_model="python")
def _fit_axis_points(U, V, orig, idx, k, c0u, c0v, inst):
    """The instrument's axis fitted to the candidate points ``orig[idx[:k]]`` (local ``U, V``; the sorted indices
    ``idx[:k]`` are reordered, the outliers behind the others), the kinematic tip ``(c0u, c0v)`` the prior, as
    :func:`liverforce.learn.cloud_features.fit_instrument`: Gauss-Newton, then once more without the outliers.
    ``inst``: radius, search radius, rise, clearance, point sd, tip sd, fewest points; the distances are compared
    with ``shaft_fit_radius`` of the radius and point sd. Returns ``(cu, cv, n_fitted)`` (the prior and 0 with
    fewer than the fewest points)."""
    sdp, sdk, n_min = inst[4], inst[5], inst[6]
    r = shaft_fit_radius(inst[0], sdp)
    if k < n_min:
        return c0u, c0v, 0
    wp = 1.0 / max(sdp, _MIN_POINT_SD) ** 2
    wk = 1.0 / max(sdk, _MIN_TIP_SD) ** 2
    P = np.empty((2, k))  # the candidates' u, v, contiguous
    for j in range(k):
        t = orig[idx[j]]
        P[0, j] = U[t]
        P[1, j] = V[t]
    cu, cv = _axis_steps(P, k, c0u, c0v, c0u, c0v, r, wp, wk)
    thr = 3.0 * sdp + 0.3
    k2 = 0
    for j in range(k):  # the outliers to the end, in place (the others in their order; idx[:k] keeps every one)
        dx = P[0, j] - cu
        dy = P[1, j] - cv
        if abs(math.sqrt(dx * dx + dy * dy) - r) <= thr:
            keep = idx[j]
            idx[j] = idx[k2]
            idx[k2] = keep
            P[0, k2] = P[0, j]  # and their coordinates in the order of idx[:k2]
            P[1, k2] = P[1, j]
            k2 += 1
    if n_min <= k2 < k:
        cu, cv = _axis_steps(P, k2, cu, cv, c0u, c0v, r, wp, wk)
        return cu, cv, k2
    return cu, cv, k


@njit(cache=True, fastmath={"contract"}, error_model="python")
def _instrument_point(u, v, z, cu, cv, c0u, c0v, inst, rf):
    """Is the point ``(u, v)`` (local, mm; height change ``z``) the instrument's, to be dropped: a candidate
    (within the search radius of the kinematic tip ``(c0u, c0v)``, ``rise`` above the surface), within the
    clearance of the fitted axis ``(cu, cv)`` beyond ``rf`` (``shaft_fit_radius`` of the fit's point sd), or
    within another 2 point sds of it above the surface (``fit_instrument``'s ``keep``, negated)."""
    search, rise, clear, sdp = inst[1], inst[2], inst[3], inst[4]
    dx = u - cu
    dy = v - cv
    d2 = dx * dx + dy * dy
    ex = u - c0u
    ey = v - c0v
    return (d2 < (rf + clear) ** 2 or (d2 < (rf + clear + 2.0 * sdp) ** 2 and z > 0.0)
            or (z > rise and ex * ex + ey * ey < search * search))


@njit(cache=True, fastmath={"contract"}, error_model="python")
def _bin_box(u, v, reach, h, gstep, sb, pad, nc):
    """Sort-bin rows and columns ``(r_lo, r_hi, c_lo, c_hi)`` (clamped) holding every point within ``reach`` grid
    units of the local point ``(u, v)`` mm (:func:`_bin_key`'s rows ``floor(gv sb) + pad``)."""
    gu = (u + h) / gstep
    gv = (v + h) / gstep
    r_lo = min(max(int(math.floor((gv - reach) * sb)) + pad, 0), nc - 1)
    r_hi = min(max(int(math.floor((gv + reach) * sb)) + pad, 0), nc - 1)
    c_lo = min(max(int(math.floor((gu - reach) * sb)) + pad, 0), nc - 1)
    c_hi = min(max(int(math.floor((gu + reach) * sb)) + pad, 0), nc - 1)
    return r_lo, r_hi, c_lo, c_hi


@njit(cache=True, fastmath={"contract"}, error_model="python")
def _collect_candidates(U, V, Zs, orig, first, sb, pad, nc, h, gstep, c0u, c0v, search, rise, idx):
    """The instrument's candidates' sorted positions into ``idx``, in the bins' order; returns how many: the points
    ``rise`` above the surface within ``search`` mm of the kinematic tip's axis ``(c0u, c0v)``."""
    margin = 1.0 / sb  # grid units: a bin of margin for rounding
    r_lo, r_hi, c_lo, c_hi = _bin_box(c0u, c0v, search / gstep + margin, h, gstep, sb, pad, nc)
    k = 0
    for rr in range(r_lo, r_hi + 1):
        for cc in range(c_lo, c_hi + 1):
            kk = _key(rr, cc, sb, nc)
            for s in range(first[kk], first[kk + 1]):
                t = orig[s]
                if t >= 0 and Zs[s] > rise:
                    dx = U[t] - c0u
                    dy = V[t] - c0v
                    if dx * dx + dy * dy < search * search:
                        idx[k] = s
                        k += 1
    return k


@njit(cache=True, fastmath={"contract"}, error_model="python")
def _point_sd(U, V, orig, idx, k, cu, cv, r):
    """``cloud_features.instrument_point_sd`` of the candidates ``orig[idx[:k]]`` about the axis ``(cu, cv)``."""
    a = np.empty(k)
    for j in range(k):
        t = orig[idx[j]]
        dx = U[t] - cu
        dy = V[t] - cv
        a[j] = abs(math.sqrt(dx * dx + dy * dy) - r)
    return _MAD_SD * np.median(a)


@njit(cache=True, fastmath={"contract"}, error_model="python")
def _normal_axis(U, V, Zs, orig, first, sb, pad, nc, h, gstep, c0u, c0v, inst, idx):
    """The axis along the normal of :func:`_fit_instrument`, nothing dropped: ``(cu, cv, n_fit, sd, inst)`` (the
    ``inst`` the last pass used: a noisy cloud's own point sd and search radius)."""
    r, search, rise, sdp = inst[0], inst[1], inst[2], inst[4]
    k = _collect_candidates(U, V, Zs, orig, first, sb, pad, nc, h, gstep, c0u, c0v, search, rise, idx)
    cu, cv, n_fit = _fit_axis_points(U, V, orig, idx, k, c0u, c0v, inst)
    rf = shaft_fit_radius(r, sdp)  # where the shaft's points stand, at this pass's point sd
    sd = np.nan
    if n_fit > 0:
        sd = _point_sd(U, V, orig, idx, k, cu, cv, rf)
        if sd > inst[7] * max(sdp, _MIN_POINT_SD):  # the cloud's own noise: search and fit again
            inst = inst.copy()
            inst[4] = sd
            search = r + 3.0 * inst[5] + 2.0 * sd + 0.5  # cloud_features.instrument_search_radius
            inst[1] = search
            rf = shaft_fit_radius(r, sd)
            k = _collect_candidates(U, V, Zs, orig, first, sb, pad, nc, h, gstep, c0u, c0v, search, rise, idx)
            cu, cv, n_fit = _fit_axis_points(U, V, orig, idx, k, c0u, c0v, inst)
            sd = _point_sd(U, V, orig, idx, k, cu, cv, rf)  # from the wider search: less cut off
    return cu, cv, n_fit, sd, inst


@njit(cache=True, fastmath={"contract"}, error_model="python")
def _drop_normal(U, V, GUs, GVs, Zs, orig, first, sb, pad, nc, h, gstep, c0u, c0v, cu, cv, inst):
    """The instrument's points of the axis ``(cu, cv)`` along the normal (``inst`` as :func:`_normal_axis` returns
    it) moved far off the grid; returns how many."""
    r, search, clear, sdp = inst[0], inst[1], inst[3], inst[4]
    rf = shaft_fit_radius(r, sdp)
    # dropped: the candidates (within the search radius of the kinematic tip) and the points near the fitted axis
    margin = 1.0 / sb
    r_lo, r_hi, c_lo, c_hi = _bin_box(c0u, c0v, search / gstep + margin, h, gstep, sb, pad, nc)
    a_lo, a_hi, b_lo, b_hi = _bin_box(cu, cv, (rf + clear + 2.0 * sdp) / gstep + margin, h, gstep, sb, pad, nc)
    r_lo, r_hi, c_lo, c_hi = min(r_lo, a_lo), max(r_hi, a_hi), min(c_lo, b_lo), max(c_hi, b_hi)
    n_drop = 0
    for rr in range(r_lo, r_hi + 1):
        for cc in range(c_lo, c_hi + 1):
            kk = _key(rr, cc, sb, nc)
            for s in range(first[kk], first[kk + 1]):
                t = orig[s]
                if t >= 0 and _instrument_point(U[t], V[t], Zs[s], cu, cv, c0u, c0v, inst, rf):
                    GUs[s] = _FAR
                    GVs[s] = _FAR
                    n_drop += 1
    return n_drop


@njit(cache=True, fastmath={"contract"}, error_model="python")
def _fit_instrument(U, V, GUs, GVs, Zs, orig, first, sb, pad, nc, h, gstep, c0u, c0v, inst, idx):
    """The instrument's axis from the sorted, distinct points (``orig[s] >= 0``; local ``U[orig[s]], V[orig[s]]``,
    height change ``Zs[s]``; bins as :func:`_grid_one` sorts them), as
    :func:`liverforce.learn.cloud_features.fit_instrument`, a cloud clearly noisier than the model's point sd
    fitted again with its own (:func:`_normal_axis`). Only the bins that can hold its points are read (the search
    radius round the kinematic tip ``(c0u, c0v)``, the clearance round the fitted axis); the instrument's points
    are moved far off the grid (``GUs, GVs``; :func:`_drop_normal`), so they add exact zeros to every cell's
    moments. ``inst``: radius, search radius, rise, clearance, point sd, tip sd, fewest points, refit ratio
    (``NOISE_REFIT_RATIO``, passed in: a module constant would be frozen into the cached kernel). Returns the axis
    ``(cu, cv)``, the points fitted, the points dropped and the cloud's point noise estimated from every candidate
    of the last pass (NaN when nothing was fitted)."""
    cu, cv, n_fit, sd, used = _normal_axis(U, V, Zs, orig, first, sb, pad, nc, h, gstep, c0u, c0v, inst, idx)
    n_drop = _drop_normal(U, V, GUs, GVs, Zs, orig, first, sb, pad, nc, h, gstep, c0u, c0v, cu, cv, used)
    return cu, cv, n_fit, n_drop, sd


@njit(cache=True, fastmath={"contract"}, error_model="python")
def _tilt_terms(u, v, hh, x, r):
    """``cloud_features._tilt_residuals`` of one point: its distance minus ``r`` from the axis ``x`` and the
    Jacobian's row."""
    su = x[2]
    sv = x[3]
    du = u - x[0] - hh * su
    dv = v - x[1] - hh * sv
    kap = 1.0 / (1.0 + (su * su + sv * sv))
    p = du * su + dv * sv
    d = math.sqrt(max((du * du + dv * dv) - kap * p * p, 1e-18))
    gx = du - kap * p * su
    gy = dv - kap * p * sv
    kp = kap * kap * p * p
    return (d - r, -gx / d, -gy / d, (-hh * gx - kap * p * du + kp * su) / d,
            (-hh * gy - kap * p * dv + kp * sv) / d)


@njit(cache=True, fastmath={"contract"}, error_model="python")
def _spd4_solve(a00, a01, a02, a03, a11, a12, a13, a22, a23, a33, b0, b1, b2, b3):
    """``x = A^-1 b`` for a symmetric positive definite 4 x 4 ``A`` (upper triangle ``aij``), by its Cholesky factor
    ``L`` (no allocation: the tilted fit solves one per Gauss-Newton step). Returns ``(x0, x1, x2, x3, l22, l32,
    l33)``: the lower-right block ``L_ss`` of ``L`` is the Cholesky factor of the Schur complement ``A_ss - A_sc
    A_cc^-1 A_cs = ((A^-1)_ss)^-1``, so ``s^T ((A^-1)_ss)^-1 s = |L_ss^T s|^2`` (the slope's Wald statistic,
    ``cloud_features._slope_wald``)."""
    l00 = math.sqrt(a00)
    l10 = a01 / l00
    l20 = a02 / l00
    l30 = a03 / l00
    l11 = math.sqrt(a11 - l10 * l10)
    l21 = (a12 - l20 * l10) / l11
    l31 = (a13 - l30 * l10) / l11
    l22 = math.sqrt(a22 - l20 * l20 - l21 * l21)
    l32 = (a23 - l30 * l20 - l31 * l21) / l22
    l33 = math.sqrt(a33 - l30 * l30 - l31 * l31 - l32 * l32)
    y0 = b0 / l00
    y1 = (b1 - l10 * y0) / l11
    y2 = (b2 - l20 * y0 - l21 * y1) / l22
    y3 = (b3 - l30 * y0 - l31 * y1 - l32 * y2) / l33
    x3 = y3 / l33
    x2 = (y2 - l32 * x3) / l22
    x1 = (y1 - l21 * x2 - l31 * x3) / l11
    x0 = (y0 - l10 * x1 - l20 * x2 - l30 * x3) / l00
    return x0, x1, x2, x3, l22, l32, l33


@njit(cache=True, fastmath={"reassoc", "nsz", "contract", "arcp"}, error_model="python")  # sums in SIMD lanes
def _tilt_normal(Q, k, x, prior, r, wp, W):
    """The Gauss-Newton system of ``cloud_features._fit_tilted`` at ``x`` on the points ``Q[:, :k]`` (rows: local
    ``u, v``, height): ``wp J^T J + diag(W)`` (its upper triangle) and ``wp J^T res + W (x - prior)``, in scalars
    (:func:`_tilt_terms` inlined by hand; the points contiguous, so the loop runs in SIMD lanes), then the
    objective ``wp sum res^2 + sum W (x - prior)^2``."""
    cu = x[0]
    cv = x[1]
    su = x[2]
    sv = x[3]
    kap = 1.0 / (1.0 + (su * su + sv * sv))
    a00 = a01 = a02 = a03 = a11 = a12 = a13 = a22 = a23 = a33 = 0.0
    b0 = b1 = b2 = b3 = 0.0
    c = 0.0
    for j in range(k):
        hh = Q[2, j]
        du = Q[0, j] - cu - hh * su
        dv = Q[1, j] - cv - hh * sv
        p = du * su + dv * sv
        d = math.sqrt(max((du * du + dv * dv) - kap * p * p, 1e-18))
        gx = du - kap * p * su
        gy = dv - kap * p * sv
        kp = kap * kap * p * p
        inv = 1.0 / d
        res = d - r
        j0 = -gx * inv
        j1 = -gy * inv
        j2 = (-hh * gx - kap * p * du + kp * su) * inv
        j3 = (-hh * gy - kap * p * dv + kp * sv) * inv
        a00 += j0 * j0
        a01 += j0 * j1
        a02 += j0 * j2
        a03 += j0 * j3
        a11 += j1 * j1
        a12 += j1 * j2
        a13 += j1 * j3
        a22 += j2 * j2
        a23 += j2 * j3
        a33 += j3 * j3
        b0 += j0 * res
        b1 += j1 * res
        b2 += j2 * res
        b3 += j3 * res
        c += res * res
    e0 = x[0] - prior[0]
    e1 = x[1] - prior[1]
    e2 = x[2] - prior[2]
    e3 = x[3] - prior[3]
    return (wp * a00 + W[0], wp * a01, wp * a02, wp * a03, wp * a11 + W[1], wp * a12, wp * a13, wp * a22 + W[2],
            wp * a23, wp * a33 + W[3], wp * b0 + W[0] * e0, wp * b1 + W[1] * e1, wp * b2 + W[2] * e2,
            wp * b3 + W[3] * e3, wp * c + (W[0] * e0 * e0 + W[1] * e1 * e1 + W[2] * e2 * e2 + W[3] * e3 * e3))


@njit(cache=True, fastmath={"nsz", "contract", "arcp"}, error_model="python")
def _tilt_near(Q, k, x, r, thr):
    """How many of the points ``Q[:, :k]`` are within ``thr`` of the cylinder of radius ``r`` about the axis ``x``
    (:func:`_tilt_terms`'s residual); ``Q[3, j]`` set to 1 for those, else 0."""
    cu = x[0]
    cv = x[1]
    su = x[2]
    sv = x[3]
    kap = 1.0 / (1.0 + (su * su + sv * sv))
    n = 0
    for j in range(k):
        hh = Q[2, j]
        du = Q[0, j] - cu - hh * su
        dv = Q[1, j] - cv - hh * sv
        p = du * su + dv * sv
        near = abs(math.sqrt(max((du * du + dv * dv) - kap * p * p, 1e-18)) - r) <= thr
        Q[3, j] = 1.0 if near else 0.0
        n += near
    return n


@njit(cache=True, fastmath={"contract"}, error_model="python")
def _tilt_steps(Q, k, x, prior, r, wp, W, iterations=_FIT_ITERATIONS):
    """``cloud_features._fit_tilted`` on the points ``Q[:, :k]`` (:func:`_tilt_normal`), from ``x`` (updated in
    place, and returned): damped, a step that raises the objective halved, as there. (The objective's sum, in the
    same vectorised loop as the system's, reorders those sums' rounding: the kernel moved by ~1e-16 with it.)"""
    f_prev = math.inf
    p0 = p1 = p2 = p3 = 0.0  # the point before the last step, and that step
    s0 = s1 = s2 = s3 = 0.0
    lam = 1.0
    done = False
    for _ in range(iterations):
        a00, a01, a02, a03, a11, a12, a13, a22, a23, a33, b0, b1, b2, b3, f = _tilt_normal(Q, k, x, prior, r, wp, W)
        if f > f_prev * (1.0 + _COST_RTOL):  # the last step raised the objective: half of it instead
            lam *= 0.5
            x[0] = p0 - lam * s0
            x[1] = p1 - lam * s1
            x[2] = p2 - lam * s2
            x[3] = p3 - lam * s3
            continue
        s0, s1, s2, s3, _, _, _ = _spd4_solve(a00, a01, a02, a03, a11, a12, a13, a22, a23, a33, b0, b1, b2, b3)
        p0, p1, p2, p3 = x[0], x[1], x[2], x[3]
        f_prev = f
        lam = 1.0
        x[0] -= s0
        x[1] -= s1
        x[2] -= s2
        x[3] -= s3
        if s0 * s0 + s1 * s1 + s2 * s2 + s3 * s3 < 1e-16:
            done = True
            break
    if not done:  # the budget spent: the last step not yet checked
        f = _tilt_normal(Q, k, x, prior, r, wp, W)[14]
        if f > f_prev * (1.0 + _COST_RTOL):
            x[0] = p0
            x[1] = p1
            x[2] = p2
            x[3] = p3
    return x


@njit(cache=True, fastmath={"contract"}, error_model="python")
def _tilted_pass(U, V, Hs, orig, raised, n_raised, c0u, c0v, S, sdp, inst, idx):
    """``cloud_features._tilted_pass``: the candidates within ``S + tan(max tilt) x height`` of the kinematic tip's
    axis among the points standing ``rise`` above the surface (sorted positions ``raised[:n_raised]``), the slope's
    start, the fit and its two trims with point sd ``sdp``. Returns the axis ``(cu, cv, su, sv)``, the points fitted
    and the slope's Wald statistic. The distances are compared with ``shaft_fit_radius`` of the radius and ``sdp``."""
    r, t_max = shaft_fit_radius(inst[0], sdp), inst[8]
    k = 0
    for j in range(n_raised):
        t = orig[raised[j]]
        if t >= 0:
            dx = U[t] - c0u
            dy = V[t] - c0v
            lim = S + t_max * max(Hs[t], 0.0)
            if dx * dx + dy * dy < lim * lim:
                idx[k] = t
                k += 1
    x = np.array([c0u, c0v, 0.0, 0.0])
    if k < inst[6]:
        return x, 0, 0.0
    prior = x.copy()
    wp = 1.0 / max(sdp, _MIN_POINT_SD) ** 2
    wk = 1.0 / max(inst[5], _MIN_TIP_SD) ** 2
    ws = 1.0 / max(t_max, 1e-3) ** 2
    W = np.array([wk, wk, ws, ws])
    Q = np.empty((4, k))  # the candidates' u, v, height and scratch, contiguous (the trims compact them stably)
    lo = np.inf
    hi = -np.inf
    sh = shh = su = sv = shu = shv = 0.0
    for j in range(k):
        t = idx[j]
        hh = Hs[t]
        Q[0, j] = U[t]
        Q[1, j] = V[t]
        Q[2, j] = hh
        lo = min(lo, hh)
        hi = max(hi, hh)
        sh += hh
        shh += hh * hh
        su += U[t]
        sv += V[t]
        shu += hh * U[t]
        shv += hh * V[t]
    if hi - lo > 1.0:  # the slope first (least squares of u, v on the height)
        den = k * shh - sh * sh
        slu = (k * shu - sh * su) / den
        slv = (k * shv - sh * sv) / den
        if math.sqrt(slu * slu + slv * slv) <= 1.5 * t_max + 0.05:
            x[2] = slu
            x[3] = slv
    thr = 3.0 * sdp + 0.3
    for _ in range(2):
        x = _tilt_steps(Q, k, x, prior, r, wp, W)
        k2 = _tilt_near(Q, k, x, r, thr)  # the points near the fitted axis (Q[3]: 1 or 0)
        if k2 < inst[6]:  # too few: every candidate stays
            break
        k2 = 0
        for j in range(k):  # kept in their order
            if Q[3, j] > 0.0:
                Q[0, k2] = Q[0, j]
                Q[1, k2] = Q[1, j]
                Q[2, k2] = Q[2, j]
                k2 += 1
        k = k2
    x = _tilt_steps(Q, k, x, prior, r, wp, W)
    # the slope's Wald statistic (cloud_features._slope_wald): s^T Cov(s)^-1 s, Cov(s)^-1 = the Schur complement
    a00, a01, a02, a03, a11, a12, a13, a22, a23, a33, b0, b1, b2, b3, _ = _tilt_normal(Q, k, x, prior, r, wp, W)
    _, _, _, _, l22, l32, l33 = _spd4_solve(a00, a01, a02, a03, a11, a12, a13, a22, a23, a33, b0, b1, b2, b3)
    e2 = l22 * x[2] + l32 * x[3]  # L_ss^T s
    e3 = l33 * x[3]
    return x, k, e2 * e2 + e3 * e3


@njit(cache=True, fastmath={"contract"}, error_model="python")
def _tilt_credible(x, c0u, c0v, S):
    """``cloud_features.tilt_credible``: the kinematic tip ``(c0u, c0v)`` projected onto the fitted axis ``x``
    within ``S`` of it along the surface."""
    su = x[2]
    sv = x[3]
    t = ((c0u - x[0]) * su + (c0v - x[1]) * sv) / (1.0 + (su * su + sv * sv))
    du = x[0] + t * su - c0u
    dv = x[1] + t * sv - c0v
    return du * du + dv * dv <= S * S


@njit(cache=True, fastmath={"contract"}, error_model="python")
def _axis_box(x, h_lo, h_hi, reach, h, gstep, sb, pad, nc):
    """Sort-bin rows and columns holding every point within ``reach`` grid units of the axis ``x`` at heights
    ``h_lo`` to ``h_hi`` (the box of the segment's two ends)."""
    a_lo, a_hi, b_lo, b_hi = _bin_box(x[0] + x[2] * h_lo, x[1] + x[3] * h_lo, reach, h, gstep, sb, pad, nc)
    e_lo, e_hi, f_lo, f_hi = _bin_box(x[0] + x[2] * h_hi, x[1] + x[3] * h_hi, reach, h, gstep, sb, pad, nc)
    return min(a_lo, e_lo), max(a_hi, e_hi), min(b_lo, f_lo), max(b_hi, f_hi)


@njit(cache=True, fastmath={"contract"}, error_model="python")
def _tilted_sd(U, V, Hs, orig, raised, n_raised, x, S, r, a):
    """``cloud_features._tilted_point_sd``: ``1.4826`` times the median ``|d - r|`` of the points standing ``rise``
    above the surface (sorted positions ``raised[:n_raised]``) within ``S`` of the axis ``x`` (NaN without one);
    ``a``: scratch, as long as the cloud."""
    k = 0
    for j in range(n_raised):
        t = orig[raised[j]]
        if t >= 0:
            d = _tilt_terms(U[t], V[t], Hs[t], x, 0.0)[0]
            if d < S:
                a[k] = abs(d - r)
                k += 1
    return _MAD_SD * np.median(a[:k]) if k else np.nan


@njit(cache=True, fastmath={"contract"}, error_model="python")
def _fit_instrument_tilted(U, V, Wl, GUs, GVs, Zs, orig, first, sb, pad, nc, h, gstep, c0u, c0v, tw, inst, idx,
                           Hs, scr, raised):
    """:func:`liverforce.learn.cloud_features.fit_instrument_tilted` on the sorted, distinct points (as
    :func:`_fit_instrument`): the shaft's axis with its slope (``inst[8]``: the tangent of the largest tilt), a
    cloud clearly noisier than the model's point sd fitted again with its own, the instrument's points moved off
    the grid; a tilted axis its points scatter about far more than about the fit along the normal's gives way to it
    (``inst[13]``: ``TILT_SD_RATIO``; :func:`_normal_axis` reuses ``idx``, and the comparison ``scr``, after the tilted
    pass has done with them). ``tw``: the kinematic tip's height; ``Hs``: scratch, the raised points' heights above
    it; ``scr`` and
    ``raised``: scratch as long (the noise estimate's distances; the sorted positions of the points standing
    ``rise`` above the surface, the only ones the search and the noise estimate read). Returns the tip ``(tu,
    tv)``, its height change along the normal, the points fitted and the noise estimate."""
    r, rise, clear, sdp, sdk = inst[0], inst[2], inst[3], inst[4], inst[5]
    n_all = first[nc * nc]
    n_raised = 0
    for s in range(n_all):  # the points standing rise above the surface, the only candidates (branch-free)
        raised[n_raised] = s
        n_raised += Zs[s] > rise
    for j in range(n_raised):  # their heights above the kinematic tip (duplicates struck out: orig -1)
        t = orig[raised[j]]
        if t >= 0:
            Hs[t] = Wl[t] - tw
    S = inst[1]
    x, n_fit, wald = _tilted_pass(U, V, Hs, orig, raised, n_raised, c0u, c0v, S, sdp, inst, idx)
    rf = shaft_fit_radius(r, sdp)  # where the shaft's points stand, at this pass's point sd
    sd = np.nan
    if n_fit > 0:
        sd = _tilted_sd(U, V, Hs, orig, raised, n_raised, x, S, rf, scr)
        if sd > inst[7] * max(sdp, _MIN_POINT_SD):  # the cloud's own noise: search and fit again
            sdp = sd
            rf = shaft_fit_radius(r, sdp)
            S = r + 3.0 * sdk + 2.0 * sd + 0.5  # cloud_features.instrument_search_radius
            x, n_fit, wald = _tilted_pass(U, V, Hs, orig, raised, n_raised, c0u, c0v, S, sdp, inst, idx)
            sd = _tilted_sd(U, V, Hs, orig, raised, n_raised, x, S, rf, scr)
    cu, cv, n_nf, sd_n, used = c0u, c0v, 0, np.nan, inst
    if n_fit > 0:  # the fit along the normal, to judge the tilted one by (TILT_SD_RATIO)
        cu, cv, n_nf, sd_n, used = _normal_axis(U, V, Zs, orig, first, sb, pad, nc, h, gstep, c0u, c0v, inst, idx)
    if (wald < inst[9] or not _tilt_credible(x, c0u, c0v, S) or (n_fit > 0 and sd > inst[13] * _tilted_sd(
            U, V, Hs, orig, raised, n_raised, np.array([cu, cv, 0.0, 0.0]), S, rf, scr))):
        # no tilt the points can tell from the normal (TILT_WALD), an axis they cannot support, or one they scatter
        # about far more than about the normal's, measured alike (TILT_SD_RATIO): the fit along it
        if n_fit == 0:
            cu, cv, n_nf, sd_n, used = _normal_axis(U, V, Zs, orig, first, sb, pad, nc, h, gstep, c0u, c0v, inst,
                                                    idx)
        _drop_normal(U, V, GUs, GVs, Zs, orig, first, sb, pad, nc, h, gstep, c0u, c0v, cu, cv, used)
        return cu, cv, 0.0, n_nf, sd_n
    # dropped: the points near the fitted axis at their height (between the lowest and the highest point's)
    h_lo = 0.0
    h_hi = 0.0
    for s in range(n_all):
        t = orig[s]
        if t >= 0:
            h_lo = min(h_lo, Wl[t] - tw)
            h_hi = max(h_hi, Wl[t] - tw)
    sec = math.sqrt(1.0 + (x[2] * x[2] + x[3] * x[3]))  # within d of the axis: within d sec sideways
    far = max(S, rf + clear + 2.0 * sdp) * sec / gstep + 1.0 / sb
    r_lo, r_hi, c_lo, c_hi = _axis_box(x, h_lo, h_hi, far, h, gstep, sb, pad, nc)
    for rr in range(r_lo, r_hi + 1):
        for cc in range(c_lo, c_hi + 1):
            kk = _key(rr, cc, sb, nc)
            for s in range(first[kk], first[kk + 1]):
                t = orig[s]
                if t >= 0:
                    d = _tilt_terms(U[t], V[t], Wl[t] - tw, x, 0.0)[0]
                    z = Zs[s]
                    if (d < rf + clear or (d < rf + clear + 2.0 * sdp and z > 0.0)) or (z > rise and d < S):
                        GUs[s] = _FAR
                        GVs[s] = _FAR
    su = x[2]
    sv = x[3]
    tt = ((c0u - x[0]) * su + (c0v - x[1]) * sv) / (1.0 + (su * su + sv * sv))
    return x[0] + tt * su, x[1] + tt * sv, tt, n_fit, sd


_FAR = 1e9  # grid-index coordinate of a dropped point: beyond every kernel support (weight and count exact zeros)
_H1 = 2654435761  # odd multipliers of the duplicate filter's hash (products stay far below 2^63)
_H2 = 2246822519


_TINY = 1e-280  # added to the dent fit's last two diagonal entries: a zero pivot becomes 1e-140, not a 0 division


# asin by fdlibm's rational approximations (e_asin.c; within 1 ulp of the C library's): branch-free, so the dent
# fit's loop runs in SIMD lanes (numba's wheels have no vector asin: a libm call per point took 16 ns)
_PIO2_HI = 1.57079632679489655800e+00
_PIO2_LO = 6.12323399573676603587e-17
_PIO4_HI = 7.85398163397448278999e-01
_PS0, _PS1, _PS2 = 1.66666666666666657415e-01, -3.25565818622400915405e-01, 2.01212532134862925881e-01
_PS3, _PS4, _PS5 = -4.00555345006794114027e-02, 7.91534994289814532176e-04, 3.47933107596021167570e-05
_QS1, _QS2 = -2.40339491173441421878e+00, 2.02094576023350569471e+00
_QS3, _QS4 = -6.88283971605453293030e-01, 7.70381505559019352791e-02


@njit(cache=True, error_model="numpy", fastmath=False)  # not a caller's fast-math (numba passes it on to a
# function that sets none): the split of s below needs exact IEEE steps
def _asin01(x):
    """``asin(x)`` for ``0 <= x <= 1``, as fdlibm's ``__ieee754_asin`` computes it (its three ranges, each
    evaluated and one selected: no branch), within 1 ulp of ``math.asin``. In ``[0.5, 0.975)`` fdlibm splits
    ``s = sqrt(t)`` by clearing its low word; here by Veltkamp's split (``w`` its high 26 bits: ``w * w`` exact)."""
    big = x >= 0.5
    t = (1.0 - x) * 0.5 if big else x * x
    p = t * (_PS0 + t * (_PS1 + t * (_PS2 + t * (_PS3 + t * (_PS4 + t * _PS5)))))
    q = 1.0 + t * (_QS1 + t * (_QS2 + t * (_QS3 + t * _QS4)))
    r = p / q
    s = math.sqrt(t)
    sh = s * 134217729.0  # 2^27 + 1
    w = sh - (sh - s)
    c = (t - w * w) / (s + w)  # (0 / 0 at x = 1: NaN, not selected)
    mid = _PIO4_HI - ((2.0 * s * r - (_PIO2_LO - 2.0 * c)) - (_PIO4_HI - 2.0 * w))
    top = _PIO2_HI - (2.0 * (s + s * r) - _PIO2_LO)
    return (top if x >= 0.975 else mid) if big else x + x * r


@njit(cache=True, fastmath={"reassoc", "nsz"}, error_model="numpy")  # reassociated sums: vectorised
def _dent_sums(GUs, GVs, Zs, a0, e0, h, gstep, tu, tv, a, rd, S):
    """Add to ``S`` (14) the normal equations' sums of :func:`_dent_fit` over the points ``[a0, e0)``, branch-free
    (a point beyond ``rd`` of the axis adds exact zeros; :func:`_asin01`); returns the points within ``rd``."""
    rd2 = rd * rd
    inv = 1.0 / rd
    c = 2.0 / math.pi
    a00 = a01 = a02 = a03 = a11 = a12 = a13 = a22 = a23 = a33 = 0.0
    b0 = b1 = b2 = b3 = 0.0
    k = 0
    for s in range(np.uint64(a0), np.uint64(e0)):
        du = GUs[s] * gstep - h - tu
        dv = GVs[s] * gstep - h - tv
        r2 = du * du + dv * dv
        inside = r2 < rd2
        gq = c * _asin01(min(1.0, a / max(math.sqrt(r2), 1e-12)))
        p1 = du * inv if inside else 0.0
        p2 = dv * inv if inside else 0.0
        gq = gq if inside else 0.0
        z = Zs[s] if inside else 0.0
        a00 += 1.0 if inside else 0.0
        a01 += p1
        a02 += p2
        a03 += gq
        a11 += p1 * p1
        a12 += p1 * p2
        a13 += p1 * gq
        a22 += p2 * p2
        a23 += p2 * gq
        a33 += gq * gq
        b0 += z
        b1 += p1 * z
        b2 += p2 * z
        b3 += gq * z
        k += inside
    S[0] += a00
    S[1] += a01
    S[2] += a02
    S[3] += a03
    S[4] += a11
    S[5] += a12
    S[6] += a13
    S[7] += a22
    S[8] += a23
    S[9] += a33
    S[10] += b0
    S[11] += b1
    S[12] += b2
    S[13] += b3
    return k


@njit(cache=True, fastmath=False, error_model="python")  # not the pass's "contract": l22 * l22 - _TINY fused keeps
# the exact square of sqrt(_TINY), which can exceed _TINY (a singular system, e.g. every point on one line through
# the axis, taken as solvable: amplitude -2 where the reference gives 0); the solution's bits are _spd4_solve's
def _dent_solve(S, k, min_points, cloud_tol):
    """``(amplitude, offset)`` from the sums ``S`` of :func:`_dent_sums` over ``k`` points (:func:`_dent_fit`)."""
    if k < min_points:
        return 0.0, 0.0
    a00, a01, a02, a03, a11, a12, a13, a22, a23, a33 = S[0], S[1], S[2], S[3], S[4], S[5], S[6], S[7], S[8], S[9]
    # a pivot of the normal matrix's Cholesky factor at most cloud_tol of its diagonal entry: singular (e.g. the
    # points on one line through the axis, or on one circle round it), as cloud_features.fit_dent decides. The
    # last two pivots come from the solve, on a matrix nudged by _TINY so that a zero pivot divides nothing
    if not a11 - a01 * a01 / a00 > cloud_tol * a11:
        return 0.0, 0.0
    x0, _, _, x3, l22, _, l33 = _spd4_solve(a00, a01, a02, a03, a11, a12, a13, a22 + _TINY, a23, a33 + _TINY, S[10],
                                            S[11], S[12], S[13])
    if not (l22 * l22 - _TINY > cloud_tol * a22 and l33 * l33 - _TINY > cloud_tol * a33
            and math.isfinite(x0) and math.isfinite(x3)):
        return 0.0, 0.0
    return x3, x0


@njit(cache=True, fastmath={"contract"}, error_model="python")
def _dent_fit(GUs, GVs, Zs, n, h, gstep, tu, tv, a, rd, min_points, cloud_tol):
    """``(amplitude, offset)`` of :func:`liverforce.learn.cloud_features.fit_dent` from the points ``[0, n)``
    (grid-index coordinates ``GUs, GVs``, the instrument's moved far off the grid; height change ``Zs``), round
    the axis ``(tu, tv)``: the same least squares, by its normal equations in the same scaled columns and the same
    pivot test (``cloud_tol``: ``DENT_PIVOT_TOL``), the sums in SIMD lanes (:func:`_dent_sums`; the reference's
    to rounding). Fewer than ``min_points`` points or a singular system: zeros."""
    S = np.zeros(14)
    return _dent_solve(S, _dent_sums(GUs, GVs, Zs, 0, n, h, gstep, tu, tv, a, rd, S), min_points, cloud_tol)


@njit(cache=True, fastmath={"contract"}, error_model="python")
def _dent_fit_bins(GUs, GVs, Zs, first, sb, pad, nc, h, gstep, tu, tv, a, rd, min_points, cloud_tol):
    """:func:`_dent_fit` of the sorted points (bins as :func:`_grid_one` sorts them), reading only the bins within
    ``rd`` of the axis (and a bin of margin): one run per group of ``sb`` bin rows."""
    S = np.zeros(14)
    r_lo, r_hi, c_lo, c_hi = _bin_box(tu, tv, rd / gstep + 1.0 / sb, h, gstep, sb, pad, nc)
    row = nc * sb
    k = 0
    for p in range(r_lo // sb, r_hi // sb + 1):
        k += _dent_sums(GUs, GVs, Zs, first[p * row + c_lo * sb], first[p * row + (c_hi + 1) * sb], h, gstep, tu,
                        tv, a, rd, S)
    return _dent_solve(S, k, min_points, cloud_tol)


@njit(cache=True, fastmath={"contract"}, error_model="python")
def _cell_planes(M, g, kr, linear, min_points, max_leverage, Hc, valid, Bu, Bv):
    """Per grid point from its moments ``M`` (:func:`_cell_moments`): the estimate ``Hc`` (0 where not valid), the
    validity and the plane's slopes ``Bu, Bv`` per grid spacing (0 where no plane was fitted), as
    ``cloud_features._cell_fit``; returns the valid cells."""
    kr2 = kr * kr
    n_valid = 0
    for cell in range(g * g):
        mom = M[cell]
        W = mom[0]
        Wp = W if W > 0 else 1.0
        zbar = mom[2] / Wp
        ub = mom[3] / Wp
        vb = mom[4] / Wp
        cuu = mom[5] / Wp - ub * ub
        cvv = mom[6] / Wp - vb * vb
        cuv = mom[7] / Wp - ub * vb
        det = cuu * cvv - cuv * cuv
        spread = det > 1e-6 * kr2 * kr2
        dp = det if spread else 1.0
        lev = (cvv * ub * ub - 2.0 * cuv * ub * vb + cuu * vb * vb) / dp if spread else np.inf
        est = zbar
        bs = 0.0
        cs = 0.0
        if linear and spread:
            cuz = mom[8] / Wp - ub * zbar
            cvz = mom[9] / Wp - vb * zbar
            bs = (cvv * cuz - cuv * cvz) / dp
            cs = (cuu * cvz - cuv * cuz) / dp
            est = zbar - bs * ub - cs * vb
        ok = mom[1] >= min_points and W > 0 and lev <= max_leverage
        valid[cell] = ok
        Hc[cell] = est if ok else 0.0
        Bu[cell] = bs
        Bv[cell] = cs
        if ok:
            n_valid += 1
    return n_valid


@njit(cache=True, fastmath={"contract"}, error_model="python")
def _drop_off_plane(GUs, GVs, Zs, first, nc, g, kr, tol, Hc, valid, Bu, Bv, flag):
    """Drop, in place, the sorted points whose height change lies more than ``tol`` from the plane of a valid grid
    point within ``kr`` of them: their nearest grid point (``np.rint``, clamped to the grid) where it is valid and
    within ``kr``, else the nearest valid one within ``kr`` (the first of equal distances, rows then columns;
    ``cloud_features._off_plane``), keeping the bins' order (:func:`_compact`); ``flag``: scratch of the points'
    length (-1 for a point dropped). Returns the points dropped and the points tested (those within ``kr`` of a
    valid grid point)."""
    n = first[nc * nc]
    kr2 = kr * kr
    g1 = g - 1.0
    c = int(math.ceil(kr))
    n_off = 0
    n_test = 0
    for s in range(n):
        gu = GUs[s]
        gv = GVs[s]
        J = min(max(np.rint(gu), 0.0), g1)
        I = min(max(np.rint(gv), 0.0), g1)
        du = gu - J
        dv = gv - I
        off = 0
        cell = int(I) * g + int(J)
        tested = du * du + dv * dv < kr2 and valid[cell]
        if not tested:  # the nearest valid grid point within the support (at the edge of what the camera sees)
            best = kr2
            I0 = np.rint(gv)
            J0 = np.rint(gu)
            for di in range(-c, c + 1):
                Ii = I0 + di
                if Ii < 0.0 or Ii > g1:
                    continue
                for dj in range(-c, c + 1):
                    Jj = J0 + dj
                    if Jj < 0.0 or Jj > g1:
                        continue
                    ddu = gu - Jj
                    ddv = gv - Ii
                    d2 = ddu * ddu + ddv * ddv
                    k = int(Ii) * g + int(Jj)
                    if d2 < best and valid[k]:
                        best = d2
                        cell = k
                        du = ddu
                        dv = ddv
                        tested = True
        if tested:
            n_test += 1
            if abs(Zs[s] - (Hc[cell] + Bu[cell] * du + Bv[cell] * dv)) > tol:
                off = -1
                n_off += 1
        flag[s] = off
    if n_off:
        _compact(GUs, GVs, Zs, first, nc, flag)
    return n_off, n_test


@njit(cache=True, fastmath={"contract"}, error_model="python")
def _compact(GUs, GVs, Zs, first, nc, mark):
    """Keep, in place and in the bins' order, the sorted points ``t`` with ``mark[t] >= 0`` (``first``: the bins'
    starts, updated)."""
    w = 0
    for kk in range(nc * nc):
        a0 = first[kk]
        e0 = first[kk + 1]
        first[kk] = w
        for t in range(a0, e0):
            if mark[t] >= 0:
                GUs[w] = GUs[t]
                GVs[w] = GVs[t]
                Zs[w] = Zs[t]
                w += 1
    first[nc * nc] = w


@njit(cache=True, fastmath={"contract"}, error_model="python")  # FMAs: u, v, w as BLAS computes R (x - p) more often
def _grid_one(P, s0, n, tip, origin, R, raster, lo, rstep, g, h, gstep, kr, max_abs, min_points, max_leverage,
              linear, fill, reach_count, shaft, inst, ws, x):
    """Feature row ``x = [height (g^2), mask (g^2), (dent (2),) R (tip - p) (3)]`` of the cloud ``P[s0:s0 + n]``.

    Mirrors :func:`liverforce.learn.cloud_features.cloud_grid` (module docstring); ``ws``: :func:`_workspace`.
    Returns the points over the grid (``|u|, |v| <= reach_count``), the points whose local coordinates are
    not finite (every point with a NaN or inf coordinate; :meth:`CompiledCloud._refusal` counts exactly) and the
    points on the tool's shaft (``shaft``: squared inner and outer radius of the ring, rise, fewest points;
    :func:`liverforce.serve.cloud.shaft_points`; an inner radius 0: not counted) and the instrument points its
    axis was fitted to, and the point noise estimated from the candidates (NaN when none were fitted): with
    ``inst[0] > 0`` the instrument's axis is fitted to its points, which are dropped, and gives the tip's
    tangential part (:func:`_fit_instrument`); with a slope as well (``inst[8] > 0``,
    :func:`_fit_instrument_tilted`) the tip is the kinematic one projected onto the axis, its height too (the fit
    along the normal where the slope is not significant or that tip is not credible, :func:`_tilt_credible`).
    With ``inst[10] > 0`` the dent round that axis is fitted to the liver's points (:func:`_dent_fit`). Last, the
    points dropped as off their grid point's plane (``inst[14] > 0``: :func:`_drop_off_plane`) and the points
    tested.
    """
    U, V, Wl, GU, GV, Z, key, A, C, Q, HB, GUs, GVs, Zs, orig, first, fill_at, bits, cand = ws[:19]
    M, Hc, valid, idx, unk, Lb, rhs, y, Bu, Bv = ws[19:]
    gg = g * g
    RF = raster.ravel()  # C-contiguous: a view
    rs = np.uint64(raster.shape[1])
    one = np.uint64(1)
    r_last = raster.shape[0] - 1.000001
    inv_rstep = 1.0 / rstep
    inv_gstep = 1.0 / gstep
    reach = h + kr * gstep
    sb, pad, nc, exact = _bins(g, kr)
    o0, o1, o2 = origin[0], origin[1], origin[2]
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2], R[2, 0], R[2, 1], R[2, 2]
    tp0, tp1, tp2 = tip[0] - o0, tip[1] - o1, tip[2] - o2
    tu = tp0 * r00 + tp1 * r01 + tp2 * r02  # the tip's tangential position: the axis of the shaft check
    tv = tp0 * r10 + tp1 * r11 + tp2 * r12
    # 1. every point: local frame (a pass of its own, which LLVM vectorises); not finite (a NaN or inf
    #    coordinate makes u NaN or inf) and over the grid (the refusal checks); the points within the kernel's
    #    reach compacted in their order, in place (branch-free: a branch mispredicts on a camera's point order).
    #    The two passes take 19 us against 23 us in one for 5,300 points (the benchmark's distinct clouds, AVX2).
    #    Unsigned indices here and below: numba then skips the negative-index wrap and LLVM can vectorise.
    m = np.uint64(0)
    nu = 0
    nb = 0
    base = np.uint64(s0)
    for k in range(n):
        row = base + np.uint64(k)
        d0 = P[row, 0] - o0
        d1 = P[row, 1] - o1
        d2 = P[row, 2] - o2
        U[k] = d0 * r00 + d1 * r01 + d2 * r02
        V[k] = d0 * r10 + d1 * r11 + d2 * r12
        Wl[k] = d0 * r20 + d1 * r21 + d2 * r22
    for k in range(n):
        u = U[k]
        v = V[k]
        w = Wl[k]
        nb += (u - u) != 0.0
        e = max(abs(u), abs(v))  # not finite (u and v both are) for a point with a NaN or inf: never counted
        nu += e <= reach_count
        U[m] = u  # m <= k: read before it is overwritten
        V[m] = v
        Wl[m] = w
        m += np.uint64(e < reach)
    tb = 16
    while (1 << tb) < 16 * m:
        tb += 1
    mask = (1 << tb) - 1
    # 2. the kept points: grid-index coordinates and sort bin; the height change over the pre-operative raster
    #    (ReferenceSurface.height: bilinear, clamped), its cell and offsets first (no gathers: vectorised)
    for t in range(m):
        u = U[t]
        v = V[t]
        fu = min(max((u - lo) * inv_rstep, 0.0), r_last)
        fv = min(max((v - lo) * inv_rstep, 0.0), r_last)
        j0 = np.int32(fu)  # 32-bit conversions: AVX2 has no vector conversion of a double to a 64-bit integer
        i0 = np.int32(fv)
        A[t] = fu - j0
        C[t] = fv - i0
        Q[t] = np.uint64(i0) * rs + np.uint64(j0)
        gu = (u + h) * inv_gstep  # a kept point's |gu|, |gv| stay within the grid's reach: 32 bits hold gu 4096
        gv = (v + h) * inv_gstep
        GU[t] = gu
        GV[t] = gv
        key[t] = _bin_key(gu, gv, sb, pad, nc)
        HB[t] = (np.int64(np.int32(gu * 4096.0)) * _H1  # duplicate filter: equal points, equal bits
                 + np.int64(np.int32(gv * 4096.0)) * _H2) & mask
    shaft_r2, ring_r2, shaft_rise, shaft_min = shaft[0], shaft[1], shaft[2], shaft[3]
    n_near = 0
    n_ring = 0
    ring_sum = 0.0
    for t in range(m):
        q = Q[t]
        a = A[t]
        c = C[t]
        z = Wl[t] - ((1 - a) * (1 - c) * RF[q] + a * (1 - c) * RF[q + one]
                     + (1 - a) * c * RF[q + rs] + a * c * RF[q + rs + one])
        Z[t] = z
        du = U[t] - tu
        dv = V[t] - tv
        d2t = du * du + dv * dv
        if d2t < ring_r2:
            if d2t < shaft_r2:
                n_near += 1
            elif abs(z) <= max_abs:
                ring_sum += z
                n_ring += 1
    ns = 0
    if n_near >= shaft_min:  # the points on the shaft: shaft_rise above the ring's mean height change
        top = (ring_sum / n_ring if n_ring else 0.0) + shaft_rise
        for t in range(m):
            du = U[t] - tu
            dv = V[t] - tv
            if du * du + dv * dv < shaft_r2 and Z[t] >= top:
                ns += 1
    # 3. counting sort by bin (stable); exact duplicates (equal local coordinates) are found with a bit table of
    #    hashed (u, v): a point whose bit is already set is a candidate, checked against its bin's earlier points
    nw = 1 << (tb - 5)
    bits[:nw] = 0
    first[:nc * nc + 1] = 0
    n_cand = 0
    for t in range(m):
        if abs(Z[t]) <= max_abs:  # else dropped (key -1)
            kk = key[t]
            first[kk + 1] += 1
            hb = HB[t]
            word = hb >> 5
            bit = 1 << (hb & 31)
            if bits[word] & bit:
                cand[n_cand] = t
                n_cand += 1
            bits[word] |= bit
        else:
            key[t] = -1
    for kk in range(nc * nc):
        first[kk + 1] += first[kk]
        fill_at[kk] = first[kk]
    for t in range(m):  # the permutation only, then a sequential gather (faster than scattering every array)
        kk = key[t]
        if kk >= 0:
            s = fill_at[kk]
            orig[s] = t
            fill_at[kk] = s + 1
    for s in range(np.uint64(first[nc * nc])):
        t = np.uint64(orig[s])
        GUs[s] = GU[t]
        GVs[s] = GV[t]
        Zs[s] = Z[t]
    n_dup = 0
    for r in range(n_cand):
        t = cand[r]
        kk = key[t]
        s = first[kk]
        while orig[s] != t:
            s += 1
        for s2 in range(first[kk], s):
            q2 = orig[s2]
            if q2 >= 0 and U[q2] == U[t] and V[q2] == V[t] and Wl[q2] == Wl[t]:
                orig[s] = -1  # the first of equal points stays (the same values either way)
                n_dup += 1
                break
    nf = 0
    sd = np.nan
    dw = 0.0
    if inst[0] > 0.0 and inst[8] > 0.0:  # the instrument, its shaft perhaps tilted: the tip from its axis
        tw = R[2, 0] * tp0 + R[2, 1] * tp1 + R[2, 2] * tp2
        tu, tv, dw, nf, sd = _fit_instrument_tilted(U, V, Wl, GUs, GVs, Zs, orig, first, sb, pad, nc, h, gstep, tu,
                                                    tv, tw, inst, cand, GU, A, HB)
    elif inst[0] > 0.0:  # the instrument's points: fitted (the tip's tangential part), then moved off the grid
        tu, tv, nf, _, sd = _fit_instrument(U, V, GUs, GVs, Zs, orig, first, sb, pad, nc, h, gstep, tu, tv, inst, cand)
    if n_dup:  # the duplicates' origin is -1
        _compact(GUs, GVs, Zs, first, nc, orig)
    # 4. moments, per-cell weighted plane fit and validity test (cloud_grid's formulas); with inst[14] > 0 the
    #    points off their nearest grid point's plane by more than it are dropped and the planes fitted again
    _cell_moments(GUs, GVs, Zs, first, g, kr, sb, pad, nc, exact, M)
    n_valid = _cell_planes(M, g, kr, linear, min_points, max_leverage, Hc, valid, Bu, Bv)
    n_off = 0
    n_test = 0
    if inst[14] > 0.0 and n_valid > 0:
        n_off, n_test = _drop_off_plane(GUs, GVs, Zs, first, nc, g, kr, inst[14], Hc, valid, Bu, Bv, key)
        if n_off:
            _cell_moments(GUs, GVs, Zs, first, g, kr, sb, pad, nc, exact, M)
            n_valid = _cell_planes(M, g, kr, linear, min_points, max_leverage, Hc, valid, Bu, Bv)
    if inst[10] > 0.0:  # the dent round the tool's axis, from the liver's distinct points
        x[2 * gg], x[2 * gg + 1] = _dent_fit_bins(GUs, GVs, Zs, first, sb, pad, nc, h, gstep, tu, tv, inst[0],
                                                  inst[10], inst[11], inst[12])
    # 5. fill of the cells the camera does not see
    if fill == 1 and 0 < n_valid < gg:
        _laplace_fill(Hc, valid, g, idx, unk, Lb, rhs, y)
    for cell in range(gg):
        x[cell] = Hc[cell]
        x[gg + cell] = 1.0 if valid[cell] else 0.0
    nx = x.shape[0]  # the tip last, after the dent's columns if any
    x[nx - 3] = tu
    x[nx - 2] = tv
    x[nx - 1] = R[2, 0] * tp0 + R[2, 1] * tp1 + R[2, 2] * tp2 + dw
    return nu, nb, ns, nf, sd, n_off, n_test


@njit(cache=True, nogil=True, fastmath=False, error_model="python")  # threads: predict_batch(threads=)
def _grid_clouds(P, starts, counts, tips, origin, R, raster, lo, rstep, g, h, gstep, kr, max_abs, min_points,
                 max_leverage, linear, fill, reach_count, shaft, inst, X, n_used, n_bad, n_tool):
    """Feature rows ``X[b]`` of the clouds ``P[starts[b]:starts[b] + counts[b]]`` (float64 or float32 points),
    their points over the grid, their points with a NaN or inf coordinate and on the tool's shaft
    (:func:`_grid_one`)."""
    nmax = 1
    for b in range(starts.shape[0]):
        nmax = max(nmax, counts[b])
    ws = _workspace(nmax, g, kr)
    for b in range(starts.shape[0]):
        n_used[b], n_bad[b], n_tool[b, 0], n_tool[b, 1], n_tool[b, 2], n_tool[b, 3], n_tool[b, 4] = _grid_one(
            P, starts[b], counts[b], tips[b], origin, R, raster, lo, rstep, g, h, gstep, kr, max_abs, min_points,
            max_leverage, linear, fill, reach_count, shaft, inst, ws, X[b])


@njit(cache=True, nogil=True, fastmath=False, error_model="python")  # threads: predict_batch(threads=)
def _grid_list(clouds, tips, origin, R, raster, lo, rstep, g, h, gstep, kr, max_abs, min_points, max_leverage,
               linear, fill, reach_count, shaft, inst, X, n_used, n_bad, n_tool):
    """:func:`_grid_clouds` of a typed list of (n_b, 3) float64 clouds, read in place (no concatenation)."""
    nmax = 1
    for b in range(len(clouds)):
        nmax = max(nmax, clouds[b].shape[0])
    ws = _workspace(nmax, g, kr)
    for b in range(len(clouds)):
        P = clouds[b]
        n_used[b], n_bad[b], n_tool[b, 0], n_tool[b, 1], n_tool[b, 2], n_tool[b, 3], n_tool[b, 4] = _grid_one(
            P, 0, P.shape[0], tips[b], origin, R, raster, lo, rstep, g, h, gstep, kr, max_abs, min_points,
            max_leverage, linear, fill, reach_count, shaft, inst, ws, X[b])


@njit(cache=True, fastmath={"contract"}, error_model="python")
def _laplace_fill(H, valid, g, idx, unk, Lb, rhs, y):
    """Harmonic fill of the invalid cells (the system of ``cloud_features._fill``), banded Cholesky, in place."""
    gg = g * g
    m = 0
    for cell in range(gg):
        if valid[cell]:
            idx[cell] = -1
        else:
            idx[cell] = m
            unk[m] = cell
            m += 1
    bw = min(g, m - 1)
    Lb[:m, :bw + 1] = 0.0
    for r in range(m):
        cell = unk[r]
        i = cell // g
        j = cell - i * g
        rhs[r] = 0.0
        deg = 0.0
        for t in range(4):
            ni = i - 1 if t == 0 else (i + 1 if t == 1 else i)
            nj = j - 1 if t == 2 else (j + 1 if t == 3 else j)
            if ni < 0 or ni >= g or nj < 0 or nj >= g:
                continue
            deg += 1.0
            nbc = ni * g + nj
            q = idx[nbc]
            if q < 0:
                rhs[r] += H[nbc]
            elif q < r:
                Lb[r, r - q] -= 1.0
        Lb[r, 0] += deg
    for jj in range(m):  # Cholesky, lower band: Lb[i, i - k] = L[i, k]
        s = Lb[jj, 0]
        for k in range(max(0, jj - bw), jj):
            s -= Lb[jj, jj - k] * Lb[jj, jj - k]
        d = math.sqrt(s)
        Lb[jj, 0] = d
        for ii in range(jj + 1, min(m, jj + bw + 1)):
            s = Lb[ii, ii - jj]
            for k in range(max(0, ii - bw), jj):
                s -= Lb[ii, ii - k] * Lb[jj, jj - k]
            Lb[ii, ii - jj] = s / d
    for ii in range(m):
        s = rhs[ii]
        for k in range(max(0, ii - bw), ii):
            s -= Lb[ii, ii - k] * y[k]
        y[ii] = s / Lb[ii, 0]
    for ii in range(m - 1, -1, -1):
        s = y[ii]
        for k in range(ii + 1, min(m, ii + bw + 1)):
            s -= Lb[k, k - ii] * rhs[k]
        rhs[ii] = s / Lb[ii, 0]
        H[unk[ii]] = rhs[ii]


@njit(cache=True, nogil=True, fastmath=False, error_model="python")
def _affine_rows(X, AT, b, out):
    """``out[r, :n] = A X[r] + b`` (``AT = A^T``, n = its columns), row by row in a fixed order (independent of
    the batch size)."""
    n_in, n_out = AT.shape
    for r in range(X.shape[0]):
        for i in range(n_out):
            out[r, i] = 0.0
        for k in range(n_in):
            xk = X[r, k]
            for i in range(n_out):
                out[r, i] += xk * AT[k, i]
        for i in range(n_out):
            out[r, i] += b[i]


@njit(cache=True, nogil=True, fastmath=False, error_model="python")
def _dense_rows(Hin, WT, b, slope, act):
    """float32 ``act(Hin W^T + b)`` row by row in a fixed order; ``act``: 0 none, 1 ReLU, 2 LeakyReLU(slope)."""
    n, k_in = Hin.shape
    k_out = WT.shape[1]
    out = np.zeros((n, k_out), dtype=np.float32)
    for r in range(n):
        for k in range(k_in):
            hk = Hin[r, k]
            for j in range(k_out):
                out[r, j] += hk * WT[k, j]
        for j in range(k_out):
            val = out[r, j] + b[j]
            if act == 1:
                val = max(val, np.float32(0.0))
            elif act == 2 and not val > 0:
                val = slope * val
            out[r, j] = val
    return out


# --------------------------------------------------------------------------
# the compiled model
# --------------------------------------------------------------------------


def _with_force(warnings: list, force: np.ndarray, scale: TrainingScale, distance: np.ndarray | None = None,
                record: dict | None = None) -> list:
    """Each cloud's warnings, a force beyond the training forces' appended (a refused cloud's NaN gets none), then
    an input distance beyond the model's training-side quantile (``distance`` (B,), NaN for a refused cloud;
    ``record``: ``ForceModel.distance_flag``; None: none)."""
    far = distance_warnings(distance, record) or [[] for _ in warnings]
    return [w + f + d for w, f, d in zip(warnings, force_warnings(force, scale, camera=True), far)]


def instrument_params(sp) -> np.ndarray:
    """The kernels' ``inst`` vector of a grid spec: the tool's radius, the search radius, the rise, the clearance,
    the point sd, the tip sd, the fewest points, ``NOISE_REFIT_RATIO``, ``tan(instrument_max_tilt_deg)``,
    ``TILT_WALD``, ``dent_radius_mm``, ``DENT_MIN_POINTS``, ``DENT_PIVOT_TOL``, ``TILT_SD_RATIO`` (the module
    constants passed in, read when called: inside a cached kernel they would be frozen into it) and
    ``outlier_mm``."""
    return np.array([sp.instrument_radius_mm, instrument_search_radius(sp), sp.instrument_rise_mm,
                     sp.instrument_clearance_mm, sp.instrument_point_sd_mm, sp.instrument_tip_sd_mm,
                     sp.instrument_min_points, cloud_features.NOISE_REFIT_RATIO,
                     math.tan(math.radians(sp.instrument_max_tilt_deg)), cloud_features.TILT_WALD,
                     sp.dent_radius_mm, cloud_features.DENT_MIN_POINTS, cloud_features.DENT_PIVOT_TOL,
                     cloud_features.TILT_SD_RATIO, sp.outlier_mm],
                    dtype=np.float64)


def cores() -> int:
    """The cores this process may run on (its CPU affinity where the platform tells it, else the CPU count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - macOS, Windows
        return max(1, os.cpu_count() or 1)


def _in_threads(fn, calls: list, threads: int) -> None:
    """``fn(*args)`` for each ``args`` of ``calls``, at most ``threads`` at once in a pool (the compiled passes and
    BLAS release the GIL; each call writes its own rows), or here, in order, when one thread suffices."""
    if threads <= 1 or len(calls) <= 1:
        for args in calls:
            fn(*args)
        return
    with ThreadPoolExecutor(min(threads, len(calls))) as pool:
        for _ in pool.map(fn, *zip(*calls)):  # raises a call's exception here
            pass


def _check_size(n: int, what: str) -> None:
    """Refuse ``n`` points per cloud beyond the kernel's 32-bit sort keys and indices (``_MAX_POINTS``);
    ``what`` leads the message (e.g. ``"cloud: 12 points"``)."""
    if n > _MAX_POINTS:
        raise PredictionInputError(f"{what}; the compiled path takes at most {_MAX_POINTS} (subsample, or use "
                                   "Predictor.predict_cloud)")


class CloudBatch(NamedTuple):
    """What :meth:`CompiledCloud.predict_batch` returns (one entry per cloud).

    force : (B, 3) N, liver frame (the inputs' frame when compiled with one); NaN for a refused cloud
    half_width : (B, 3) N in the local frame (the interval of each force; NaN for a refused cloud) or None
    warnings : list of lists of str (milder departures from training, as ``info["warnings"]``)
    refused : list of str or None: the reason a cloud was refused (the reference path's error message)
    """

    force: np.ndarray
    half_width: np.ndarray | None
    warnings: list
    refused: list

    @property
    def ok(self) -> np.ndarray:
        """(B,) True where a force was predicted."""
        return np.array([r is None for r in self.refused], dtype=bool)


class CompiledCloud:
    """A camera-cloud model (PCA encoder) specialised to one :class:`Preop` (module docstring).

    ``predict(cloud, tool_tip)`` returns ``(force (3,) N liver frame (or the input frame), half-widths (3,) N
    local or None, warnings)`` and raises :class:`PredictionInputError` where the reference path refuses;
    ``predict_batch(clouds, tool_tips)`` returns a :class:`CloudBatch`. Build it with
    :meth:`liverforce.serve.Predictor.compile_cloud` (the context is checked there).

    ``frame`` (an :class:`~liverforce.serve.input_frame.InputFrame`; default: RAS mm): the frame and units of the
    clouds and tips of a lab's own liver. They are read in the model's frame (RAS mm) as ``liverforce predict
    --frame`` converts them, the map folded into the kernel's rotation (no copy of a cloud), and the forces are
    given back in the inputs' frame (the half-widths are local: they have no global axes). The ``preop`` is in
    the model's frame (:func:`~liverforce.serve.files.read_context` returns both).

    ``registration`` (a :class:`~liverforce.learn.registration.Refinement`,
    :meth:`~liverforce.serve.Predictor.refine_registration`): the camera's registration refined from its unloaded
    view (its matrix in the model's frame), applied to every cloud and tip after the input frame (folded into the
    kernel's rotation too); the forces go back through the input frame only, as without it. A refinement with a
    change of shape (not :attr:`~liverforce.learn.registration.Refinement.rigid`) is not a rigid map: the clouds
    are then converted to the model's frame and reshaped before the kernel (one pass over the points, ~10 us per
    1,000), as the reference path does.
    """

    def __init__(self, model, preop: Preop, *, limits: Limits | None = None, frame: InputFrame | None = None,
                 registration=None, declared: InputFrame | None = None):
        rep = model.representation
        # the units and frame the user declared, for the refusals (they give the inputs back as entered): the
        # input frame, or (``declared``) the one the caller converted the clouds and tips from already, which a
        # refusal converts them back from (``_converted_from``; None: they come as entered)
        self._said = frame if frame is not None else declared
        self._converted_from = declared if frame is None else None
        # clouds and tips in another frame or unit (a lab's own liver): read as given (the map is folded into the
        # kernel's rotation below), forces given back in that frame
        self.frame = None if frame is None or frame.identity else frame
        self.registration = registration
        # how the points are read: the input frame, then the registration's refinement (the forces go back through
        # the input frame only)
        self._points_frame = self.frame
        if registration is not None:
            fr = self.frame or InputFrame()
            self._points_frame = InputFrame(scale=fr.scale, units=fr.units, label="matrix",
                                            matrix=np.asarray(registration.matrix, dtype=np.float64) @ fr.matrix,
                                            source=fr.source)
        if not rep.is_camera or not isinstance(model.pre.encoder, PCAEncoder):
            raise PredictionInputError("the compiled cloud path needs a camera-cloud model (roi_features: cloud) with "
                                       "the PCA encoder; use Predictor.predict_cloud")
        self.model, self.limits = model, limits or Limits()
        self.p = np.asarray(preop.exertion_point_mm, dtype=np.float64)
        self.R = np.ascontiguousarray(preop.rotation, dtype=np.float64)
        self.spec = camera.grid_spec(rep.grid_size, rep.half_width_mm, rep.camera)
        try:
            self.ref = ReferenceSurface.for_case(preop.roi_undeformed_mm, preop.roi_triangles, self.p, self.R,
                                                 self.spec, label="pre-operative context")
        except ValueError as exc:
            raise PredictionInputError(str(exc)) from None
        self.half_width_mm = float(rep.half_width_mm)
        self.reach = rep.half_width_mm * (1.0 + 2.0 / (rep.grid_size - 1))
        self.g = int(self.spec.grid_size)
        self.n_features = int(rep.n_features)  # 2 g^2 (+ the dent's columns) + 3
        pre = model.pre
        fs, enc, cs = pre.feature_scaler, pre.encoder, pre.code_scaler
        # code = ((x - mu_f) / s_f - mu_pca) C^T, scaled: one affine map A x + b
        A = (enc.components / fs.scale[None, :]) / cs.scale[:, None]
        self.A = np.ascontiguousarray(A, dtype=np.float64)
        self.AT = np.ascontiguousarray(self.A.T)
        self.b = -(enc.components @ (fs.mean / fs.scale + enc.mean) + cs.mean) / cs.scale
        self.uses_state = model.uses_state
        self.k = 1.0
        self.k_material = 1.0
        self.s_base = np.zeros(0)
        self.lin = False
        self.strain = False
        self.dent = False
        self.n_disp = 0
        if self.uses_state:
            arrays = rep.state_arrays(preop.to_arrays(preop.roi_undeformed_mm))
            s = state_vector(arrays, R=self.R[None])
            self.k = float(pre.stiffness(s, 1)[0, 0])
            self.k_material = float(pre.material_factor(s, 1)[0, 0])
            ss = pre.state_scaler
            base = pre.base_state_features(s)[0]
            n_base = base.size
            self.s_base = (base - ss.mean[:n_base]) / ss.scale[:n_base]
            self.lin = pre.n_linear_force == 3
            if self.lin:  # f_lin = k_lin C^-1 tip (k_lin: force_scaling linear, else 1), then tip_n / h if used
                self.Cinv = pre.linear_factor(s, 1)[0, 0] * np.linalg.inv(compliance_matrices(s)[0])
                self.lin_mean, self.lin_scale = ss.mean[n_base:], ss.scale[n_base:]
                self.n_disp = pre.n_displacement_features
                self.strain = bool(pre.indentation_strain)
                if self.strain:  # the indentation strain tip_n / h (Preop refuses a thickness <= 0)
                    self.inv_h = 1.0 / float(s[0, THICKNESS_COLUMN])
                self.dent = bool(pre.dent_force)  # (k amplitude / C_nn, offset): Preprocessor.dent_features
                if self.dent:
                    self.dent_k = float(pre.material_factor(s, 1)[0, 0]) / float(compliance_matrices(s)[0][2, 2])
        self.context_warnings = []  # the context's state outside the training range (Predictor.context_warnings)
        self.scale = TrainingScale.of(model)  # and the training forces (force_warnings)
        if self.uses_state:
            self.context_warnings = outside_training(preop.to_arrays(preop.roi_undeformed_mm), self.scale)[1][0]
        self.layers = []
        nz = self.A.shape[0]
        # the GP takes the (float32-rounded, as the reference feeds it) state once: its share of every training
        # row's distance and of the linear term is computed here, and the head reads the code and f_lin only
        iv = model.interval
        self._spread = iv is not None and iv.uses_spread  # the head also gives the members' sd (the interval's)
        self._far = model.distance_flag  # the input-distance flag (a GP's; None: none, no warning)
        # the head gives each cloud's input distance for the flag's warning and for an interval's far widths
        self._dist = self._far is not None or (iv is not None and iv.uses_distance)
        self.gp = regressor_head(model.regressor, {nz + k: float(v) for k, v in
                                                   enumerate(self.s_base.astype(np.float32))} or None,
                                 members=self._spread, distance=self._dist)
        self._state_cols = self.s_base.size if self.gp is None else 0  # state columns _head writes into Z
        for W, b, sl in ([] if self.gp is not None else numpy_layers(model.regressor)):
            act, slope = (0, 0.0) if sl is None else ((1, 0.0) if sl == 0.0 else (2, float(sl)))
            self.layers.append((np.ascontiguousarray(W.astype(np.float32).T), b.astype(np.float32),
                                np.float32(slope), act))
        self.tmean, self.tscale = pre.target_scaler.mean, pre.target_scaler.scale
        self.interval = model.interval  # its half-widths: the context's stiffness factor, and per cloud its force
        if self.interval is not None:  # the context's stiffness factor, once; the widths of |F| per cloud
            # (1, 1), or (1, 3) per component with widen: fitted
            self._kf = self.interval.stiffness_factor(np.array([[self.k_material]]))
        self._rec = ((model.meta or {}).get("training_scale") or {}).get("camera")
        self._raster = np.ascontiguousarray(self.ref.raster, dtype=np.float64)
        # the instrument's points in a cloud (a model trained without them refuses it: serve.cloud.shaft_points)
        self._shaft_tool_mm = instrument_check_radius(rep, self.spec)  # 0: no check (serve.cloud.shaft_points)
        inner = self._shaft_tool_mm + SHAFT_MARGIN_MM if self._shaft_tool_mm > 0 else 0.0
        self._shaft = np.array([inner**2, (inner + SHAFT_RING_MM) ** 2 if inner > 0 else 0.0, SHAFT_RISE_MM,
                                SHAFT_POINTS], dtype=np.float64)
        sp = self.spec  # the instrument's axis fitted to its points in the cloud (cloud_features.fit_instrument)
        self.fits_instrument = sp.instrument_radius_mm > 0
        self._inst = instrument_params(sp)
        # the kernel reads clouds and tips as given: R (A s x + t - p) = (s R A) (x - A^-1 (p - t) / s), so an input
        # frame costs nothing per point (the checks and messages below convert the few points they read)
        # a change of shape: the points are converted and reshaped before the kernel (_grid), which reads them as is
        self._reshape = None if registration is None or registration.rigid else registration.reshaped
        if self._points_frame is None or self._reshape is not None:
            self._kp, self._kR = self.p, self.R
        else:
            fr = self._points_frame
            # A^-1, not A^T: a registration's matrix printed to 6 decimals is orthogonal only to ~1e-6, and with a
            # shift of hundreds of mm A^T would move every local point by ~1e-3 mm
            self._kp = np.ascontiguousarray(np.linalg.solve(fr.A, self.p - fr.t) / fr.scale)
            self._kR = np.ascontiguousarray(fr.scale * self.R @ fr.A)
        # load (or compile) the kernels now, not on the first cloud in the operating room
        for dtype in (np.float64, np.float32):  # a cloud, a padded batch of either precision
            self._grid(np.zeros((1, 3), dtype), np.zeros(1, np.int64), np.ones(1, np.int64), self._kp[None].copy())
        self._grid([np.zeros((1, 3))], None, None, self._kp[None].copy())  # a list of clouds
        self._head(np.zeros((1, self.A.shape[1])))

    # -- per-cloud pieces ------------------------------------------------------

    def _grid(self, P, starts, counts, tips: np.ndarray, threads: int = 1):
        """Feature rows, points over the grid, non-finite points of the clouds ``P[starts[b]:starts[b] + counts[b]]``
        (``P``: (n, 3) float64 or float32, C-contiguous), or of a list ``P`` of (n_b, 3) C-contiguous float64
        clouds (``starts`` and ``counts`` None: read in place, no concatenation). Clouds and ``tips`` as given (in
        the input frame, if any). ``threads`` > 1: the batch cut into that many contiguous parts, gridded at once in
        as many threads (the kernel releases the GIL; every cloud gets the same bits as alone)."""
        B = len(P) if starts is None else len(starts)
        sp = self.spec
        X = np.empty((B, self.n_features))
        n_used = np.zeros(B, dtype=np.int64)
        n_bad = np.zeros(B, dtype=np.int64)
        n_tool = np.zeros((B, 5))  # points on the shaft, instrument points fitted, the point noise from them (mm),
        # points dropped as gross depth errors and points tested for them
        if B:
            params = (self._kp, self._kR, self._raster, self.ref.lo, self.ref.step, self.g, sp.half_width_mm,
                      sp.spacing_mm, sp.kernel_radius_cells, sp.max_abs_height_mm, sp.min_points, sp.max_leverage,
                      sp.estimator == "linear", _FILL_CODES[sp.fill], self.reach, self._shaft, self._inst)

            def part(a: int, e: int) -> None:  # clouds [a, e): their own rows of the outputs (views, no copy)
                out = (X[a:e], n_used[a:e], n_bad[a:e], n_tool[a:e])
                shaped = self._reshape is not None  # not a rigid map: the points in the model's frame, reshaped
                t = np.ascontiguousarray(self._model(tips[a:e])) if shaped else tips[a:e]
                if starts is None:
                    clouds = List.empty_list(_CLOUD_TYPE)
                    for c in P[a:e]:
                        clouds.append(np.ascontiguousarray(self._model(c)) if shaped else c)
                    _grid_list(clouds, t, *params, *out)
                elif shaped:  # the part's rows only, converted in this thread
                    s0, s1 = int(starts[a:e].min()), int((starts[a:e] + counts[a:e]).max())
                    _grid_clouds(self._model(P[s0:s1]), starts[a:e] - s0, counts[a:e], t, *params, *out)
                else:
                    _grid_clouds(P, starts[a:e], counts[a:e], t, *params, *out)

            cuts = np.linspace(0, B, min(threads, B) + 1).round().astype(int)  # one contiguous part per thread
            _in_threads(part, list(zip(cuts[:-1], cuts[1:])), threads)
            if sp.fill == "nearest":
                g, gg = self.g, self.g * self.g
                for r in range(B):
                    X[r, :gg] = _fill(X[r, :gg].reshape(g, g), X[r, gg:2 * gg].reshape(g, g) > 0.5, "nearest").ravel()
        return X, n_used, n_bad, n_tool

    def _head(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """Forces (n, 3) N in the liver frame of feature rows ``X`` (affine map, state, MLP or GP, scaling), for an
        interval scaled by the spread the GP ensemble members' sd of the local force (n, 3) N (else None), and for a
        model with the input-distance flag or an interval with far widths each row's input distance (n,) (else None), as
        :meth:`liverforce.learn.model.ForceModel.forward` gives them."""
        n = len(X)
        nz = self.A.shape[0]
        ns = self._state_cols  # 0 for the GP: its head holds the state (__init__)
        Z = np.empty((n, nz + ns + self.n_disp))  # n_disp: 0 without f_lin
        if self.gp is None:  # row by row: the MLP gives a cloud the same bits alone and in a batch
            _affine_rows(X, self.AT, self.b, Z)
        else:  # BLAS: the GP head's products agree alone and in a batch to rounding only anyway
            np.matmul(X, self.AT, out=Z[:, :nz])
            Z[:, :nz] += self.b
        if self.uses_state:
            if ns:
                Z[:, nz:nz + ns] = self.s_base
            if self.lin:
                t = X[:, -3:]
                lin = (t[:, 0:1] * self.Cinv[:, 0] + t[:, 1:2] * self.Cinv[:, 1]) + t[:, 2:3] * self.Cinv[:, 2]
                o = nz + ns
                Z[:, o:o + 3] = (lin - self.lin_mean[:3]) / self.lin_scale[:3]
                if self.strain:  # the indentation strain tip_n / h
                    Z[:, o + 3] = (t[:, 2] * self.inv_h - self.lin_mean[3]) / self.lin_scale[3]
                if self.dent:  # the dent's amplitude as a force and the plane's offset, the last columns
                    j = self.n_disp - camera.N_DENT
                    d = X[:, -3 - camera.N_DENT:-3]
                    Z[:, o + j] = (d[:, 0] * self.dent_k - self.lin_mean[j]) / self.lin_scale[j]
                    Z[:, o + j + 1] = (d[:, 1] - self.lin_mean[j + 1]) / self.lin_scale[j + 1]
        h = Z.astype(np.float32)
        sd = near = None
        if self.gp is not None:
            h = self.gp(h)
            if self._dist:
                *h, near = h
                h = h[0] if len(h) == 1 else tuple(h)
            if self._spread:
                h, sd = h
                sd = sd * np.abs(self.tscale * self.k)  # the sd of (h tscale + tmean) k over the members
        for WT, b, slope, act in self.layers:
            h = _dense_rows(h, WT, b, slope, act)
        f = (h.astype(np.float64) * self.tscale + self.tmean) * self.k  # local frame
        R = self.R
        return (f[:, 0:1] * R[0] + f[:, 1:2] * R[1]) + f[:, 2:3] * R[2], sd, near  # R^T f, row by row

    def _reasons(self, cloud_of, counts, tips, X, n_used, n_bad, n_tool) -> tuple[list, list]:
        """Per cloud: the refusal reason (None if predicted) and the warnings, in the reference path's order.

        ``cloud_of(r)``: the points of cloud ``r`` (only called for a cloud near or past a refusal)."""
        B = len(counts)
        refused: list = [None] * B
        warnings: list = [[] for _ in range(B)]
        lim = self.limits
        for r in np.flatnonzero(self._flagged(counts, tips, n_used, n_bad, n_tool)):
            refused[r] = self._refusal(cloud_of(r), tips[r], int(n_used[r]), int(n_tool[r, 0]))
        if self._rec:
            g2 = self.g * self.g
            mask = X[:, g2:2 * g2]
            seen = mask.mean(axis=1)
            height = np.max(np.where(mask > 0.5, np.abs(X[:, :g2]), 0.0), axis=1)
            tip = np.sqrt(np.sum(X[:, -3:] ** 2, axis=1))
            rec, eps = self._rec, 1e-9  # gate with a margin: camera_checks decides for every cloud near a limit
            near = ((seen < float(rec["valid_fraction"][0]) + eps)
                    | (height > float(rec["height_abs_max_mm"]) * (1 - eps))
                    | (tip > float(rec["tip_displacement_max_mm"]) * (1 - eps)))
            for r in np.flatnonzero(near):
                if refused[r] is None:
                    try:
                        warnings[r] = camera_checks(self.model, X[r], lim)
                    except PredictionInputError as exc:  # a cloud in metres is named first, as the reference does
                        refused[r] = metres_cloud(self._model(cloud_of(r)), self.half_width_mm,
                                                  lim.min_cloud_points, self._said) or str(exc)
        if self.spec.outlier_mm > 0:  # gross depth errors dropped (outlier_cloud decides), before the feature checks
            for r in np.flatnonzero(n_tool[:, 3] > 0):
                gross = outlier_cloud(n_tool[r, 3], n_tool[r, 4], self.spec) if refused[r] is None else None
                if gross:
                    warnings[r] = [gross] + warnings[r]
        if self.fits_instrument:  # predict_cloud's order: too little of the instrument to fit (the kinematic tip),
            # noisier than the training clouds (noisy_cloud decides), the gross depth errors, the feature checks
            for r in np.flatnonzero(n_tool[:, 2] > noisy_threshold_mm(self.spec)):
                if refused[r] is None:
                    noisy = noisy_cloud(n_tool[r, 2], self.spec)
                    warnings[r] = [noisy] + warnings[r] if noisy else warnings[r]
            for r in np.flatnonzero(n_tool[:, 1] == 0):
                if refused[r] is None:
                    warnings[r] = [MASKED_INSTRUMENT] + warnings[r]
        if self.context_warnings:
            warnings = [w if why is not None else self.context_warnings + w for w, why in zip(warnings, refused)]
        reg = registration_warnings(self.registration)  # predict_cloud's: after the cloud's own
        if reg:
            warnings = [w if why is not None else w + reg for w, why in zip(warnings, refused)]
        return refused, warnings

    def _model(self, x: np.ndarray) -> np.ndarray:
        """Points as given -> the model's frame (RAS mm), the registration's change of shape taken off if any."""
        x = x if self._points_frame is None else self._points_frame.points(x)
        return x if self._reshape is None else self._reshape(x)

    def _flagged(self, counts, tips, n_used, n_bad, n_tool) -> np.ndarray:
        """(B,) True for a cloud that may be refused before its features are read (:meth:`_refusal` decides;
        the others pass its checks by construction). ``tips`` as given."""
        tips = self._model(tips)
        tip_ok = np.isfinite(tips).all(axis=1)
        off = tip_off_grid(np.where(tip_ok[:, None], tips, self.p), self.p, self.R, self.half_width_mm)[0]
        return ((counts == 0) | (n_bad > 0) | (n_used < self.limits.min_cloud_points) | ~tip_ok
                | off | (n_tool[:, 0] >= SHAFT_POINTS))

    @staticmethod
    def _tip_refusal(tip: np.ndarray) -> str | None:
        if not np.isfinite(tip).all():
            return f"tool_tip_mm: need 3 finite coordinates (mm), got {tip!r}"
        return None

    def _refusal(self, O: np.ndarray, tip: np.ndarray, n_used: int, n_shaft: int) -> str | None:
        """The reference path's message, from its own checks in its order (``preop._points``,
        :func:`~liverforce.serve.cloud.check_camera_cloud`, then the instrument); the cloud ``O`` and ``tip`` as
        given, ``n_used`` the kernel's count of points over the grid."""
        why = self._tip_refusal(tip)
        if why:
            return why
        try:
            O_model = _points("cloud", self._model(O), min_points=1)  # empty; NaN / inf in the model's frame
            check_camera_cloud(self.model.representation, O_model, self._model(tip), self.p, self.R,
                               self.limits, self._said, n_used=n_used,
                               entered=lambda: (as_entered(self._converted_from, O),
                                                as_entered(self._converted_from, tip)))
        except PredictionInputError as exc:
            return str(exc)
        if n_shaft >= SHAFT_POINTS:  # (counted for models trained without the instrument only)
            return instrument_refusal(n_shaft, self._shaft_tool_mm)
        return None

    def _forces(self, X: np.ndarray, ok: np.ndarray,
                threads: int = 1) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """Forces (B, 3) N of the feature rows ``X[ok]`` (NaN elsewhere), the head in blocks of ``_HEAD_ROWS``
        (``threads`` > 1: the blocks in that many threads; the same blocks, so the same bits), the members'
        sd (B, 3) N for an interval scaled by the spread (NaN elsewhere; None without) and the input distances
        (B,) for a model with the flag or far widths (NaN elsewhere; None without)."""
        F = np.full((len(X), 3), np.nan)
        S = np.full((len(X), 3), np.nan) if self._spread else None
        D = np.full(len(X), np.nan) if self._dist else None
        rows = np.flatnonzero(ok)
        every = len(rows) == len(X)  # then blocks of rows are views, not copies
        blocks = [(slice(a, a + _HEAD_ROWS) if every else rows[a:a + _HEAD_ROWS],)
                  for a in range(0, len(rows), _HEAD_ROWS)]

        def block(r) -> None:  # its own rows of F (and S, D)
            F[r], sd, near = self._head(X[r])
            if S is not None:
                S[r] = sd
            if D is not None:
                D[r] = near

        _in_threads(block, blocks, threads)
        return F, S, D

    def _half(self, F: np.ndarray, S: np.ndarray | None = None, D: np.ndarray | None = None) -> np.ndarray | None:
        """Half-widths ``(B, 3)`` (local frame) of forces ``(B, 3)`` (any frame: the scale reads ``|F|``) and the
        members' sd ``S`` ``(B, 3)`` (an interval scaled by the spread) and the input distances ``D`` ``(B,)`` (an
        interval with far widths), as :meth:`ConformalInterval.half_widths` gives them; NaN for a refused cloud
        whatever the scale; None without an interval."""
        if self.interval is None:
            return None
        half = self._kf * self.interval.force_widths(F, S, D)  # the same widths per cloud for a scale without them
        half[~np.isfinite(F).all(axis=1)] = np.nan  # a refused cloud: no force, no interval
        return half

    # -- public ------------------------------------------------------------------

    @staticmethod
    def _cloud(cloud_mm) -> np.ndarray:
        """The cloud as a C-contiguous float64 (n, 3) array, refused here only when not one (the reference
        path's message); an empty cloud or NaN / inf points are refused after the gridding pass counted them."""
        try:
            x = np.asarray(cloud_mm, dtype=np.float64)
        except (TypeError, ValueError):
            x = None
        if x is None or x.ndim != 2 or x.shape[1] != 3:
            return np.ascontiguousarray(_points("cloud", cloud_mm, min_points=1))  # raises the reference's message
        _check_size(len(x), f"cloud: {len(x)} points")
        return x if x.flags.c_contiguous else np.ascontiguousarray(x)

    @staticmethod
    def _tip(tool_tip_mm) -> np.ndarray:
        return tool_tip_of(tool_tip_mm)

    def _out(self, F: np.ndarray) -> np.ndarray:
        """Forces (model frame) -> the inputs' frame."""
        return F if self.frame is None or self.frame.same_axes else self.frame.vectors_out(F)

    def _one(self, cloud_mm, tool_tip_mm):
        """Feature row, refusal reason and warnings of one cloud (the tip is checked first, as the reference does)."""
        tip = self._tip(tool_tip_mm)
        O = self._cloud(cloud_mm)
        X, n_used, n_bad, n_tool = self._grid(O, np.zeros(1, np.int64), np.array([len(O)], np.int64), tip[None])
        refused, warnings = self._reasons(lambda r: O, np.array([len(O)]), tip[None], X, n_used, n_bad, n_tool)
        return X, refused[0], warnings[0]

    def features(self, cloud_mm, tool_tip_mm) -> np.ndarray:
        """The model's feature row of one cloud and tool tip (``cloud_grid(...).features(include_mask=True)``
        and the local tip displacement, to rounding); raises where :meth:`predict` refuses before the features."""
        tip = self._tip(tool_tip_mm)
        O = self._cloud(cloud_mm)
        counts = np.array([len(O)], np.int64)
        X, n_used, n_bad, n_tool = self._grid(O, np.zeros(1, np.int64), counts, tip[None])
        if self._flagged(counts, tip[None], n_used, n_bad, n_tool)[0]:
            why = self._refusal(O, tip, int(n_used[0]), int(n_tool[0, 0]))
            if why:
                raise PredictionInputError(why)
        return X[0]

    def predict(self, cloud_mm, tool_tip_mm) -> tuple[np.ndarray, np.ndarray | None, list[str]]:
        """Force (3,) N in the liver frame (the inputs' frame when compiled with one), the interval's half-widths
        (3,) N (local frame) or None, warnings."""
        X, why, warnings = self._one(cloud_mm, tool_tip_mm)
        if why is not None:
            raise PredictionInputError(why)
        F, S, D = self._head(X)
        half = self._half(F, S, D)
        return (self._out(F[0]), None if half is None else half[0],
                _with_force([warnings], F, self.scale, D, self._far)[0])

    def predict_batch(self, clouds, tool_tips, counts=None, *, threads: int = 1) -> CloudBatch:
        """Forces of many clouds at this exertion point in one go (a :class:`CloudBatch`).

        Parameters
        ----------
        clouds : list of (n_i, 3) arrays (mm, liver frame; else the input frame's units and frame), or one padded
            array (B, N, 3) with ``counts``
        tool_tips : (B, 3), as the clouds (one per cloud; a single (3,) tip is used for every cloud)
        counts : (B,) points of each padded cloud (rows ``[:counts[b]]``; default all N)
        threads : threads that grid the batch's clouds and run the head (default 1: this thread only; at most
            :func:`cores`, this process's cores). The gridding is most of a batch's time and each cloud's is
            independent, so ``threads`` up to the cores free speed a batch up nearly in proportion
            (``benchmarks/bench_camera.py --threads``); the results are the same bits

        Each cloud gives what :meth:`predict` gives it (bit for bit with an MLP, to rounding with a GP: module
        docstring); a cloud :meth:`predict` would refuse
        gets a NaN force and its reason in ``refused`` (the rest of the batch is predicted). One gridding
        pass over the batch (a list is read in place; a float32 or float64 padded array too; an input frame is
        folded into the kernel's rotation, so nothing is converted), then the checks and the head over all rows
        at once.
        """
        if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 1:
            raise PredictionInputError(f"threads: need a whole number >= 1, got {threads!r}")
        threads = min(int(threads), cores())  # more threads than cores only add switching
        tips = np.asarray(tool_tips, dtype=np.float64)
        B = len(clouds)
        if tips.ndim == 1 and tips.shape == (3,):
            tips = np.broadcast_to(tips, (B, 3))
        if tips.shape != (B, 3):
            raise PredictionInputError(f"tool_tips: need one (3,) tip per cloud ({B}), got shape {tips.shape}")
        tips = np.ascontiguousarray(tips)
        if isinstance(clouds, np.ndarray) and clouds.ndim == 3:
            if clouds.shape[2] != 3:
                raise PredictionInputError(f"clouds: expected (B, N, 3) points, got shape {clouds.shape}")
            N = clouds.shape[1]
            _check_size(N, f"clouds: {N} points per cloud")
            cnt = np.full(B, N, np.int64) if counts is None else np.asarray(counts, dtype=np.int64).reshape(-1)
            if cnt.shape != (B,) or (cnt < 0).any() or (cnt > N).any():
                raise PredictionInputError(f"counts: need {B} counts in [0, {N}], got {counts!r}")
            X = np.empty((B, self.n_features))
            n_used = np.zeros(B, dtype=np.int64)
            n_bad = np.zeros(B, dtype=np.int64)
            n_tool = np.zeros((B, 5))  # as _grid's
            direct = clouds.dtype in (np.float32, np.float64) and clouds.flags.c_contiguous
            # a conversion (or a change of shape's reshaping) is done a chunk at a time (bounds the copy)
            step = max(B, 1) if direct and self._reshape is None else _CHUNK
            for a in range(0, B, step):
                e = min(a + step, B)
                P = clouds[a:e] if direct else np.ascontiguousarray(clouds[a:e], dtype=np.float64)
                X[a:e], n_used[a:e], n_bad[a:e], n_tool[a:e] = self._grid(
                    P.reshape(-1, 3), np.arange(e - a, dtype=np.int64) * N, cnt[a:e], tips[a:e], threads)
            refused, warnings = self._reasons(lambda r: clouds[r, :cnt[r]], cnt, tips, X, n_used, n_bad, n_tool)
            F, S, D = self._forces(X, np.array([r is None for r in refused], dtype=bool), threads)
            return CloudBatch(self._out(F), self._half(F, S, D), _with_force(warnings, F, self.scale, D, self._far),
                              refused)
        if counts is not None:
            raise PredictionInputError("counts: only with one padded (B, N, 3) array of clouds")
        refused: list = [None] * B
        warnings: list = [None] * B
        arrays: list = [None] * B
        for i, c in enumerate(clouds):
            try:
                arrays[i] = self._cloud(c)
            except PredictionInputError as exc:  # the tip first, as the reference path checks it
                refused[i], warnings[i] = self._tip_refusal(tips[i]) or str(exc), []
        good = [i for i in range(B) if arrays[i] is not None]
        force = np.full((B, 3), np.nan)
        spread = np.full((B, 3), np.nan) if self._spread else None
        far = np.full(B, np.nan) if self._dist else None
        if good:
            P = [arrays[i] for i in good]
            X, n_used, n_bad, n_tool = self._grid(P, None, None, tips[good], threads)
            why, warn = self._reasons(lambda r: P[r], np.array([len(c) for c in P]), tips[good], X, n_used, n_bad,
                                      n_tool)
            force[good], S, D = self._forces(X, np.array([r is None for r in why], dtype=bool), threads)
            if spread is not None:
                spread[good] = S
            if far is not None:
                far[good] = D
            for k, i in enumerate(good):
                refused[i], warnings[i] = why[k], warn[k]
        return CloudBatch(self._out(force), self._half(force, spread, far),
                          _with_force(warnings, force, self.scale, far, self._far), refused)
