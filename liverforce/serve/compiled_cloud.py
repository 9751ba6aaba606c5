"""Fast path of a camera-cloud model at one exertion point: raw clouds and tool tips -> forces and intervals.

In the operating room the tool rests at one exertion point while the camera
streams clouds. Everything that depends only on the pre-operative context is
done once, when compiling (:class:`CompiledCloud`):

- the pre-operative height raster of :class:`~liverforce.learn.cloud_features.ReferenceSurface`;
- the state vector (scaled), the compliance's inverse ``C^-1`` (for ``f_lin``),
  the stiffness factor of the material (force scaling) and so the interval's
  half-widths;
- the scalers and PCA folded into one affine map, the MLP as NumPy arrays
  (float32, as the torch reference; :func:`liverforce.serve.compiled.numpy_layers`).

A call (:meth:`CompiledCloud.predict`, one cloud) or a batch
(:meth:`CompiledCloud.predict_batch`, many clouds) then runs, per cloud, one
compiled (numba) pass that does what
:func:`~liverforce.learn.cloud_features.cloud_grid` does, in one loop over
the points instead of NumPy temporaries:

- rotate into the local frame, crop to the grid's reach, count the points
  over the grid (the refusal check of the reference path);
- merge exact duplicate points (a spatial hash instead of the reference's
  sort: the reference's canonical order only fixes the rounding of its sums);
- the height change over the pre-operative raster (same bilinear read), the
  biweight-kernel moments of every point's stencil cells, the per-cell
  weighted plane fit, the validity test (same formulas);
- the Laplace fill of the invalid cells as a banded Cholesky solve (the
  4-neighbour system of the unknowns has bandwidth ``<= g`` in flat cell
  order), instead of the reference's dense LU; ``nearest`` fill goes back to
  the reference's function.

The features agree with ``cloud_grid`` to rounding (sums in another order:
about 1e-15 mm; tests check 1e-9 mm and identical masks). The
out-of-distribution checks are those of
:func:`liverforce.serve.cloud.camera_checks` (called for every cloud near or
past a limit; the others pass them by construction), then the affine map and
the MLP run row by row in a fixed order (float64 affine, float32 MLP, as the
reference), so a cloud gives bit-identical forces alone or inside a batch of
any size. The reference path (:meth:`liverforce.serve.Predictor.predict_cloud`)
stays the oracle: a test checks both agree to 1e-6 N, and that both refuse
the same inputs with the same reasons (tool tip missing or off the grid, NaN
points, too few points over the grid, too little of the grid seen, heights or
tip displacements far outside training).

Measured with ``benchmarks/bench_camera.py`` (5,000-point clouds, 12 x 12
grid, 1 thread, a loaded 2-core VM): one cloud p50 0.23 ms, p99 0.54 ms
(reference ``predict_cloud`` 12.8 / 21.3 ms); ``predict_batch`` about 5,000
clouds/s, the numba pass being ~90 % of it (moments ~30 us, local frame +
height ~55 us per cloud).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from liverforce.learn import camera
from liverforce.learn.cloud_features import ReferenceSurface, _fill
from liverforce.learn.encoders import PCAEncoder
from liverforce.learn.state import compliance_matrices, state_vector
from liverforce.serve.checks import Limits
from liverforce.serve.cloud import camera_checks, tool_tip_of
from liverforce.serve.compiled import numpy_layers, regressor_head
from liverforce.serve.errors import PredictionInputError
from liverforce.serve.preop import Preop, _points

_FILL_CODES = {"zero": 0, "laplace": 1, "nearest": 2}
_CHUNK = 64  # clouds per kernel call when a list is concatenated (bounds the copy, stays in cache)


# --------------------------------------------------------------------------
# compiled kernels (numba; serial and deterministic)
# --------------------------------------------------------------------------


@njit(cache=True, fastmath={"reassoc", "nsz", "contract", "arcp"})
def _cell_moments(GU, GV, Z, first, g, kr, pad, M):
    """Biweight moments of every grid point ``(I, J)`` from the points sorted by half-cell.

    ``GU, GV``: grid-index coordinates, ``Z``: height change; the points in half-cell
    ``(floor(2 gv), floor(2 gu))`` are ``first[key]:first[key + 1]`` with ``key = (floor(2 gv) + pad) *
    (2 g + 2 pad) + floor(2 gu) + pad``, so the points within ``kr`` of a grid point are in a few runs.
    ``M[I * g + J]`` gets: sum of w, of 1 (points within the support), of w z, w du, w dv, w du^2, w dv^2,
    w du dv, w du z, w dv z (``w = (1 - q)^2``, ``q = (du^2 + dv^2) / kr^2 < 1``), the sums of
    ``cloud_features.cloud_grid``. Points outside the support add exact zeros. The fast-math flags let LLVM
    vectorise the sums: their order depends only on the points' order, never on the batch, so a cloud gives
    the same bits alone or in a batch (and the reference's sums to rounding).
    """
    gs = 2 * g + 2 * pad
    inv_kr2 = 1.0 / (kr * kr)
    for I in range(g):
        v_lo = int(math.floor(2.0 * (I - kr))) + pad
        v_hi = int(math.ceil(2.0 * (I + kr))) - 1 + pad  # half-cells starting below I + kr
        for J in range(g):
            u_lo = int(math.floor(2.0 * (J - kr))) + pad
            u_hi = int(math.ceil(2.0 * (J + kr))) - 1 + pad
            s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = s8 = s9 = 0.0
            for sv in range(v_lo, v_hi + 1):
                for t in range(first[sv * gs + u_lo], first[sv * gs + u_hi + 1]):
                    du = GU[t] - J
                    dv = GV[t] - I
                    q = (du * du + dv * dv) * inv_kr2
                    inside = q < 1.0
                    wt = (1.0 - q) * (1.0 - q) if inside else 0.0
                    z = Z[t]
                    s0 += wt
                    s1 += 1.0 if inside else 0.0
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


@njit(cache=True)
def _grid_clouds(P, starts, counts, tips, origin, R, raster, lo, rstep, g, h, gstep, kr_cells, max_abs,
                 min_points, max_leverage, linear, fill, reach_count, X, n_used, n_bad):
    """Feature rows ``X[b] = [height (g^2), mask (g^2), R (tip - p) (3)]`` of the clouds ``P[starts[b]:+counts[b]]``.

    Mirrors :func:`liverforce.learn.cloud_features.cloud_grid` (module docstring). Also returns per cloud the
    points over the grid (``|u|, |v| <= reach_count``) and the points with a NaN or inf coordinate.
    """
    B = starts.shape[0]
    gg = g * g
    r_last = raster.shape[0] - 1.000001
    reach = h + kr_cells * gstep
    kr2 = kr_cells ** 2
    pad = int(math.ceil(2.0 * kr_cells)) + 1  # half-cells beyond the grid a kept point can lie in
    gp = 2 * g + 2 * pad
    nmax = 1
    for b in range(B):
        nmax = max(nmax, counts[b])
    U = np.empty(nmax)
    V = np.empty(nmax)
    Wl = np.empty(nmax)
    GU = np.empty(nmax)
    GV = np.empty(nmax)
    Z = np.empty(nmax)
    key = np.empty(nmax, dtype=np.int64)
    GUs = np.empty(nmax)
    GVs = np.empty(nmax)
    Zs = np.empty(nmax)
    nxt = np.empty(nmax, dtype=np.int64)
    side_max = 1
    while side_max * side_max < nmax:
        side_max *= 2
    head = np.empty(side_max * side_max, dtype=np.int64)
    first = np.empty(gp * gp + 1, dtype=np.int64)
    fill_at = np.empty(gp * gp, dtype=np.int64)
    M = np.zeros((gg, 10))
    Hc = np.zeros(gg)
    valid = np.zeros(gg, dtype=np.bool_)
    idx = np.empty(gg, dtype=np.int64)
    unk = np.empty(gg, dtype=np.int64)
    Lb = np.zeros((gg, g + 1))
    rhs = np.zeros(gg)
    y = np.zeros(gg)
    kept = np.empty(nmax, dtype=np.int64)
    o0, o1, o2 = origin[0], origin[1], origin[2]
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2], R[2, 0], R[2, 1], R[2, 2]
    for b in range(B):
        s0 = starts[b]
        n = counts[b]
        # local frame, every point (branch-free: vectorised)
        for k in range(n):
            d0 = P[s0 + k, 0] - o0
            d1 = P[s0 + k, 1] - o1
            d2 = P[s0 + k, 2] - o2
            U[k] = d0 * r00 + d1 * r01 + d2 * r02
            V[k] = d0 * r10 + d1 * r11 + d2 * r12
            Wl[k] = d0 * r20 + d1 * r21 + d2 * r22
        # points with a NaN or inf, points over the grid (the refusal checks), points within the kernel's reach
        m = 0
        nu = 0
        nb = 0
        for k in range(n):
            x = P[s0 + k, 0] + P[s0 + k, 1] + P[s0 + k, 2]
            nb += (x - x) != 0.0  # NaN or inf in a coordinate; such a point is never kept (its u, v are NaN or inf)
            au = abs(U[k])
            av = abs(V[k])
            nu += (au <= reach_count) & (av <= reach_count)
            kept[m] = k
            m += (au < reach) & (av < reach)
        side = 1
        while side * side < m:
            side *= 2
        inv = side / (2.0 * reach)
        head[:side * side] = -1
        first[:] = 0
        mk = m
        m = 0
        for t in range(mk):
            k = kept[t]
            u = U[k]
            v = V[k]
            # height change over the pre-operative raster (ReferenceSurface.height: bilinear, clamped)
            fu = min(max((u - lo) / rstep, 0.0), r_last)
            fv = min(max((v - lo) / rstep, 0.0), r_last)
            j0 = int(fu)
            i0 = int(fv)
            a = fu - j0
            bb = fv - i0
            zr = ((1 - a) * (1 - bb) * raster[i0, j0] + a * (1 - bb) * raster[i0, j0 + 1]
                  + (1 - a) * bb * raster[i0 + 1, j0] + a * bb * raster[i0 + 1, j0 + 1])
            w = Wl[k]
            z = w - zr
            if not abs(z) <= max_abs:
                continue
            # exact duplicate points (equal local coordinates) count once: chained spatial hash on (u, v)
            bu = min(max(int((u + reach) * inv), 0), side - 1)
            bv = min(max(int((v + reach) * inv), 0), side - 1)
            slot = bv * side + bu
            q = head[slot]
            dup = False
            while q >= 0:
                if U[q] == u and V[q] == v and Wl[q] == w:
                    dup = True
                    break
                q = nxt[q]
            if dup:
                continue
            nxt[k] = head[slot]
            head[slot] = k
            gu = (u + h) / gstep
            gv = (v + h) / gstep
            kk = (int(math.floor(2.0 * gv)) + pad) * gp + int(math.floor(2.0 * gu)) + pad
            GU[m] = gu
            GV[m] = gv
            Z[m] = z
            key[m] = kk
            first[kk + 1] += 1
            m += 1
        n_used[b] = nu
        n_bad[b] = nb
        # counting sort by half-cell (stable): the points near a grid point are then a few runs
        for kk in range(gp * gp):
            first[kk + 1] += first[kk]
            fill_at[kk] = first[kk]
        for k in range(m):
            t = fill_at[key[k]]
            GUs[t] = GU[k]
            GVs[t] = GV[k]
            Zs[t] = Z[k]
            fill_at[key[k]] = t + 1
        _cell_moments(GUs, GVs, Zs, first, g, kr_cells, pad, M)
        n_valid = 0
        for I in range(g):
            for J in range(g):
                cell = I * g + J
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
                if linear and spread:
                    cuz = mom[8] / Wp - ub * zbar
                    cvz = mom[9] / Wp - vb * zbar
                    bs = (cvv * cuz - cuv * cvz) / dp
                    cs = (cuu * cvz - cuv * cuz) / dp
                    est = zbar - bs * ub - cs * vb
                ok = mom[1] >= min_points and W > 0 and lev <= max_leverage
                valid[cell] = ok
                Hc[cell] = est if ok else 0.0
                if ok:
                    n_valid += 1
        if fill == 1 and 0 < n_valid < gg:
            _laplace_fill(Hc, valid, g, idx, unk, Lb, rhs, y)
        for cell in range(gg):
            X[b, cell] = Hc[cell]
            X[b, gg + cell] = 1.0 if valid[cell] else 0.0
        t0 = tips[b, 0] - origin[0]
        t1 = tips[b, 1] - origin[1]
        t2 = tips[b, 2] - origin[2]
        for r in range(3):
            X[b, 2 * gg + r] = R[r, 0] * t0 + R[r, 1] * t1 + R[r, 2] * t2


@njit(cache=True)
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


@njit(cache=True)
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


@njit(cache=True)
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


class CloudBatch(NamedTuple):
    """What :meth:`CompiledCloud.predict_batch` returns (one entry per cloud).

    force : (B, 3) N, liver frame; NaN for a refused cloud
    half_width : (3,) N in the local frame (the interval depends on the context only) or None
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

    ``predict(cloud, tool_tip)`` returns ``(force (3,) N liver frame, half-widths (3,) N local or None,
    warnings)`` and raises :class:`PredictionInputError` where the reference path refuses;
    ``predict_batch(clouds, tool_tips)`` returns a :class:`CloudBatch`. Build it with
    :meth:`liverforce.serve.Predictor.compile_cloud` (the context is checked there).
    """

    def __init__(self, model, preop: Preop, *, limits: Limits | None = None):
        rep = model.representation
        if not rep.is_camera or not isinstance(model.pre.encoder, PCAEncoder):
            raise PredictionInputError("the compiled cloud path needs a camera-cloud model (roi_features: cloud) with "
                                       "the PCA encoder; use Predictor.predict_cloud")
        self.model, self.limits = model, limits or Limits()
        self.p = np.asarray(preop.exertion_point_mm, dtype=np.float64)
        self.R = np.ascontiguousarray(preop.rotation, dtype=np.float64)
        self.spec = camera.grid_spec(rep.grid_size, rep.half_width_mm, rep.camera)
        self.ref = ReferenceSurface.from_rotation(preop.roi_undeformed_mm, self.p, self.R, self.spec,
                                                  label="compiled cloud")
        self.half_width_mm = float(rep.half_width_mm)
        self.reach = rep.half_width_mm * (1.0 + 2.0 / (rep.grid_size - 1))
        self.g = int(self.spec.grid_size)
        pre = model.pre
        fs, enc, cs = pre.feature_scaler, pre.encoder, pre.code_scaler
        # code = ((x - mu_f) / s_f - mu_pca) C^T, scaled: one affine map A x + b
        A = (enc.components / fs.scale[None, :]) / cs.scale[:, None]
        self.A = np.ascontiguousarray(A, dtype=np.float64)
        self.AT = np.ascontiguousarray(self.A.T)
        self.b = -(enc.components @ (fs.mean / fs.scale + enc.mean) + cs.mean) / cs.scale
        self.uses_state = model.uses_state
        self.k = 1.0
        self.s_base = np.zeros(0)
        self.lin = False
        if self.uses_state:
            arrays = rep.state_arrays(preop.to_arrays(preop.roi_undeformed_mm))
            s = state_vector(arrays, R=self.R[None])
            self.k = float(pre.stiffness(s, 1)[0, 0])
            ss = pre.state_scaler
            base = pre.base_state_features(s)[0]
            n_base = base.size
            self.s_base = (base - ss.mean[:n_base]) / ss.scale[:n_base]
            self.lin = pre.n_linear_force == 3
            if self.lin:
                self.Cinv = np.linalg.inv(compliance_matrices(s)[0])
                self.lin_mean, self.lin_scale = ss.mean[n_base:], ss.scale[n_base:]
        self.layers = []
        self.gp = regressor_head(model.regressor)
        for W, b, sl in ([] if self.gp is not None else numpy_layers(model.regressor)):
            act, slope = (0, 0.0) if sl is None else ((1, 0.0) if sl == 0.0 else (2, float(sl)))
            self.layers.append((np.ascontiguousarray(W.astype(np.float32).T), b.astype(np.float32),
                                np.float32(slope), act))
        self.tmean, self.tscale = pre.target_scaler.mean, pre.target_scaler.scale
        ci = model.interval
        self.half = None if ci is None else ci.half_widths(np.array([[self.k]]))[0]
        self._rec = ((model.meta or {}).get("training_scale") or {}).get("camera")
        self._raster = np.ascontiguousarray(self.ref.raster, dtype=np.float64)
        # load (or compile) the kernels now, not on the first cloud in the operating room
        self._predict_rows(np.zeros((1, 3)), np.zeros(1, np.int64), np.ones(1, np.int64), self.p[None].copy())
        self._head(np.zeros((1, self.A.shape[1])))

    # -- per-cloud pieces ------------------------------------------------------

    def _grid(self, P: np.ndarray, starts: np.ndarray, counts: np.ndarray, tips: np.ndarray):
        """Feature rows, points over the grid, non-finite points of clouds ``P[starts[b]:starts[b] + counts[b]]``."""
        B = len(starts)
        sp = self.spec
        X = np.empty((B, 2 * self.g * self.g + 3))
        n_used = np.zeros(B, dtype=np.int64)
        n_bad = np.zeros(B, dtype=np.int64)
        if B:
            _grid_clouds(P, starts, counts, tips, self.p, self.R, self._raster, self.ref.lo, self.ref.step, self.g,
                         sp.half_width_mm, sp.spacing_mm, sp.kernel_radius_cells, sp.max_abs_height_mm,
                         sp.min_points, sp.max_leverage, sp.estimator == "linear", _FILL_CODES[sp.fill],
                         self.reach, X, n_used, n_bad)
            if sp.fill == "nearest":
                g, gg = self.g, self.g * self.g
                for r in range(B):
                    X[r, :gg] = _fill(X[r, :gg].reshape(g, g), X[r, gg:2 * gg].reshape(g, g) > 0.5, "nearest").ravel()
        return X, n_used, n_bad

    def _head(self, X: np.ndarray) -> np.ndarray:
        """Forces (n, 3) N in the liver frame of feature rows ``X`` (affine map, state, MLP, scaling)."""
        n = len(X)
        nz = self.A.shape[0]
        Z = np.empty((n, nz + self.s_base.size + (3 if self.lin else 0)))
        _affine_rows(X, self.AT, self.b, Z)
        if self.uses_state:
            Z[:, nz:nz + self.s_base.size] = self.s_base
            if self.lin:
                t = X[:, -3:]
                lin = (t[:, 0:1] * self.Cinv[:, 0] + t[:, 1:2] * self.Cinv[:, 1]) + t[:, 2:3] * self.Cinv[:, 2]
                Z[:, nz + self.s_base.size:] = (lin - self.lin_mean) / self.lin_scale
        h = Z.astype(np.float32)
        if self.gp is not None:
            h = self.gp(h)
        for WT, b, slope, act in self.layers:
            h = _dense_rows(h, WT, b, slope, act)
        f = (h.astype(np.float64) * self.tscale + self.tmean) * self.k  # local frame
        R = self.R
        return (f[:, 0:1] * R[0] + f[:, 1:2] * R[1]) + f[:, 2:3] * R[2]  # R^T f, row by row

    def _reasons(self, P, starts, counts, tips, X, n_used, n_bad) -> tuple[list, list]:
        """Per cloud: the refusal reason (None if predicted) and the warnings, in the reference path's order."""
        B = len(starts)
        refused: list = [None] * B
        warnings: list = [[] for _ in range(B)]
        tip_ok = np.isfinite(tips).all(axis=1)
        d_tip = np.linalg.norm(np.where(tip_ok[:, None], tips - self.p, 0.0), axis=1)
        lim = self.limits
        flagged = np.flatnonzero((counts == 0) | (n_bad > 0) | (n_used < lim.min_cloud_points) | ~tip_ok
                                 | (d_tip > self.half_width_mm))
        for r in flagged:
            refused[r] = self._refusal(P[starts[r]:starts[r] + counts[r]], tips[r], int(n_used[r]), int(n_bad[r]))
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
                    except PredictionInputError as exc:
                        refused[r] = str(exc)
        return refused, warnings

    def _refusal(self, O: np.ndarray, tip: np.ndarray, n_used: int, n_bad: int) -> str | None:
        """The reference path's message (``liverforce.serve.cloud._camera_arrays``, ``preop._points``)."""
        if not np.isfinite(tip).all():
            return f"tool_tip_mm: need 3 finite coordinates (mm), got {tip!r}"
        if len(O) == 0:
            return "cloud: 0 points; at least 1 are needed (the cloud is empty)"
        if n_bad:
            bad = ~np.isfinite(O).all(axis=1)
            return (f"cloud: {int(bad.sum())} of {len(O)} points contain NaN or inf (first at row "
                    f"{int(np.argmax(bad))}); drop invalid points (e.g. missing depth) before predicting")
        if n_used < self.limits.min_cloud_points:
            med = float(np.median(np.linalg.norm(O - self.p, axis=1)))
            return (f"cloud: only {n_used} of {len(O)} points lie over the model's {2 * self.half_width_mm:.3g} mm "
                    f"grid around the exertion point (at least {self.limits.min_cloud_points} needed; the points are "
                    f"a median {med:.4g} mm from it): is the cloud in mm, registered to the liver frame, and does it "
                    "show the tool region?")
        d_tip = float(np.linalg.norm(tip - self.p))
        if d_tip > self.half_width_mm:
            return (f"tool_tip_mm is {d_tip:.4g} mm from the exertion point, beyond the model's grid "
                    f"({self.half_width_mm:.3g} mm): is it in mm and in the liver frame, and is the tool at this "
                    "exertion point?")
        return None

    def _predict_rows(self, P, starts, counts, tips):
        X, n_used, n_bad = self._grid(P, starts, counts, tips)
        refused, warnings = self._reasons(P, starts, counts, tips, X, n_used, n_bad)
        F = np.full((len(starts), 3), np.nan)
        ok = np.array([r is None for r in refused], dtype=bool)
        if ok.all():
            F = self._head(X)
        elif ok.any():
            F[ok] = self._head(X[ok])
        return X, F, refused, warnings

    # -- public ------------------------------------------------------------------

    @staticmethod
    def _cloud(cloud_mm) -> np.ndarray:
        return np.ascontiguousarray(_points("cloud", cloud_mm, min_points=1))

    @staticmethod
    def _tip(tool_tip_mm) -> np.ndarray:
        return tool_tip_of(tool_tip_mm)

    def features(self, cloud_mm, tool_tip_mm) -> np.ndarray:
        """The model's feature row of one cloud and tool tip (``cloud_grid(...).features(include_mask=True)``
        and the local tip displacement, to rounding); raises where :meth:`predict` refuses before the features."""
        O, tip = self._cloud(cloud_mm), self._tip(tool_tip_mm)
        starts, counts = np.zeros(1, np.int64), np.array([len(O)], np.int64)
        X, n_used, n_bad = self._grid(O, starts, counts, tip[None])
        why = self._refusal(O, tip, int(n_used[0]), int(n_bad[0]))
        if why:
            raise PredictionInputError(why)
        return X[0]

    def predict(self, cloud_mm, tool_tip_mm) -> tuple[np.ndarray, np.ndarray | None, list[str]]:
        """Force (3,) N in the liver frame, the interval's half-widths (3,) N (local frame) or None, warnings."""
        O, tip = self._cloud(cloud_mm), self._tip(tool_tip_mm)
        _, F, refused, warnings = self._predict_rows(O, np.zeros(1, np.int64), np.array([len(O)], np.int64),
                                                     tip[None])
        if refused[0] is not None:
            raise PredictionInputError(refused[0])
        return F[0], self.half, warnings[0]

    def predict_batch(self, clouds, tool_tips, counts=None) -> CloudBatch:
        """Forces of many clouds at this exertion point in one go (a :class:`CloudBatch`).

        Parameters
        ----------
        clouds : list of (n_i, 3) arrays (mm, liver frame), or one padded array (B, N, 3) with ``counts``
        tool_tips : (B, 3) mm, liver frame (one per cloud; a single (3,) tip is used for every cloud)
        counts : (B,) points of each padded cloud (rows ``[:counts[b]]``; default all N)

        Each cloud gives what :meth:`predict` gives it, bit for bit; a cloud :meth:`predict` would refuse
        gets a NaN force and its reason in ``refused`` (the rest of the batch is predicted).
        """
        tips = np.asarray(tool_tips, dtype=np.float64)
        B = len(clouds)
        if tips.ndim == 1 and tips.shape == (3,):
            tips = np.broadcast_to(tips, (B, 3))
        if tips.shape != (B, 3):
            raise PredictionInputError(f"tool_tips: need one (3,) tip per cloud ({B}), got shape {tips.shape}")
        force = np.full((B, 3), np.nan)
        refused: list = [None] * B
        warnings: list = [[] for _ in range(B)]
        if isinstance(clouds, np.ndarray) and clouds.ndim == 3:
            if clouds.shape[2] != 3:
                raise PredictionInputError(f"clouds: expected (B, N, 3) points, got shape {clouds.shape}")
            N = clouds.shape[1]
            cnt = np.full(B, N, np.int64) if counts is None else np.asarray(counts, dtype=np.int64).reshape(-1)
            if cnt.shape != (B,) or (cnt < 0).any() or (cnt > N).any():
                raise PredictionInputError(f"counts: need {B} counts in [0, {N}], got {counts!r}")
            for a in range(0, B, _CHUNK):
                e = min(a + _CHUNK, B)
                P = np.ascontiguousarray(clouds[a:e], dtype=np.float64).reshape(-1, 3)
                _, force[a:e], refused[a:e], warnings[a:e] = self._predict_rows(
                    P, np.arange(e - a, dtype=np.int64) * N, cnt[a:e], np.ascontiguousarray(tips[a:e]))
            return CloudBatch(force, self.half, warnings, refused)
        if counts is not None:
            raise PredictionInputError("counts: only with one padded (B, N, 3) array of clouds")
        arrays: list = [None] * B
        for i, c in enumerate(clouds):
            try:
                arrays[i] = self._cloud(c)
            except PredictionInputError as exc:
                refused[i] = str(exc)
        good = [i for i in range(B) if arrays[i] is not None]
        for a in range(0, len(good), _CHUNK):
            rows = good[a:a + _CHUNK]
            cnt = np.array([len(arrays[i]) for i in rows], dtype=np.int64)
            starts = np.concatenate([[0], np.cumsum(cnt)[:-1]]).astype(np.int64)
            P = np.concatenate([arrays[i] for i in rows]) if rows else np.zeros((0, 3))
            _, F, why, warn = self._predict_rows(P, starts, cnt, np.ascontiguousarray(tips[rows]))
            force[rows] = F
            for k, i in enumerate(rows):
                refused[i], warnings[i] = why[k], warn[k]
        return CloudBatch(force, self.half, warnings, refused)
