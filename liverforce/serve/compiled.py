"""Fast path for a fixed ROI topology: the whole pre-processing as one precomputed affine map.

In a haptic loop the tool rests at one exertion point while the camera (or a
tracker) reports, many times a second, the deformed positions of the same ROI
nodes. Everything before the first nonlinearity is then affine in the
deformed positions ``D`` (``k x 3``, liver frame, mm) for models with
``roi_features: displacement``:

    D_loc = (D - p) R^T                       local frame
    d     = D_loc - U_loc                     node displacement
    x     = W d  (channel-major)              grid resampling: W (g² x k) are the
                                              piecewise-linear weights over the fixed
                                              undeformed patch (its top sheet, or the
                                              nodes' Delaunay) / nearest
    c     = C (x - mu_f) / s_f - ...           PCA + scalers (AE/DAE: first Linear)
    s     = (state(D) - mu_s) / s_s           deformed ROI centroid = mean D (constant under an observation model), the
                                              linear force estimate C^-1 sum w x and the indentation
                                              strain (sum w x_n) / h: affine; the rest of the state is
                                              constant

With ``rigid_motion: remove`` each call first undoes the far ROI nodes' best
rigid motion on ``D`` (:func:`liverforce.learn.representation.undo_rigid_motion`,
the reference path's function; nonlinear, one 3x3 SVD per call); the rest is
affine in the corrected ``D``, whose mean is the state's deformed centroid.

so :class:`CompiledROI` precomputes ``z = A vec(D) + b`` once (``W`` is read
off the reference interpolant itself, :func:`liverforce.learn.grid.interpolate_top_sheet` or
:func:`liverforce.learn.representation.interpolate_to_grid` applied to the identity, so the
resampling is the reference one by construction). A call is then one matrix-vector product plus the small MLP
in NumPy (float32 like the torch reference; batch norm folded into the
preceding linear layer, dropout dropped, the target scaling and the rotation
back to the liver frame applied at the end).

The reference path (:meth:`liverforce.learn.model.ForceModel.predict`) stays
the oracle: tests check both agree to 1e-6 N.

Per call only cheap checks run: the input's shape, a finite output (a NaN or
inf anywhere in ``D`` makes every output non-finite, which is then reported
with the row that caused it) and the displacement magnitude. The context
(ROI, frame, liver, material) is checked once, when compiling.

The calibrated interval (:mod:`liverforce.learn.interval`) comes with the force on request:
:meth:`CompiledROI.predict_interval` and ``predict_batch(..., with_interval=True)`` give the half-widths per
local component (t1, t2, n) that :meth:`~liverforce.learn.model.ForceModel.predict_interval` gives, from the
context's stiffness factor ``C10 / C10_ref`` (:meth:`~liverforce.learn.model.Preprocessor.material_factor`,
with :meth:`CompiledROI.with_material` or each row's ``material_params_mpa``), the predicted force and, for an
interval scaled by the GP ensemble members' spread, the members' sd of the local force (a second GP head, built
on the first call that asks for it). :meth:`CompiledROI.predict` and ``predict_batch`` without it compute none
of that (the force alone, at its own per-call cost); a model trained without ``train.interval`` gives no interval
and says so.
"""

from __future__ import annotations

import numpy as np
from torch import nn

from liverforce.learn.encoders import PCAEncoder
from liverforce.learn.grid import interpolate_top_sheet, top_sheet_nodes
from liverforce.learn.representation import interpolate_to_grid, keep_triangles, rigid_fit_nodes, undo_rigid_motion
from liverforce.learn.state import MATERIAL_START, THICKNESS_COLUMN, compliance_matrices, state_vector
from liverforce.serve.checks import Limits, TrainingScale, check_displacement, check_material
from liverforce.serve.errors import PredictionInputError
from liverforce.serve.preop import Preop, _points, _vector

_STATE_DEF_CENTROID = slice(6, 9)  # roi_centroid_deformed columns of the state vector


def numpy_layers(seq: nn.Sequential) -> list[tuple[np.ndarray, np.ndarray, float | None]]:
    """``(W, b, slope)`` per affine layer of an eval-mode ``Sequential`` (float64).

    ``Linear`` layers, each optionally followed by ``BatchNorm1d`` (folded in:
    ``W' = g W / sqrt(var + eps)``, ``b' = g (b - mu) / sqrt(var + eps) + beta``)
    and an activation: ``slope`` 0 for ReLU, the negative slope for
    LeakyReLU, ``None`` for none. ``Dropout`` is the identity in eval mode.
    """
    out: list[list] = []
    for m in seq:
        if isinstance(m, nn.Linear):
            out.append([m.weight.detach().double().numpy().copy(), m.bias.detach().double().numpy().copy(), None])
        elif isinstance(m, nn.BatchNorm1d):
            W, b, _ = out[-1]
            g = m.weight.detach().double().numpy() / np.sqrt(m.running_var.double().numpy() + m.eps)
            out[-1][0] = W * g[:, None]
            out[-1][1] = (b - m.running_mean.double().numpy()) * g + m.bias.detach().double().numpy()
        elif isinstance(m, nn.ReLU):
            out[-1][2] = 0.0
        elif isinstance(m, nn.LeakyReLU):
            out[-1][2] = float(m.negative_slope)
        elif isinstance(m, nn.Dropout):
            continue
        else:
            raise TypeError(f"numpy_layers: unsupported layer {type(m).__name__}")
    return [(W, b, s) for W, b, s in out]


def regressor_head(module: nn.Module, fixed: dict | None = None, members: bool = False, distance: bool = False):
    """The GP regressor's NumPy posterior mean (:meth:`liverforce.learn.gp.GPRegressor.numpy_head`, or
    :meth:`liverforce.learn.gp.GPEnsemble.numpy_head`; ``fixed``: ``{input column: value}`` of inputs the same
    in every row, folded in once: the head then takes the other columns); None for an MLP (served layer by
    layer from :func:`numpy_layers`). ``members``: a GP ensemble's head returns ``(mean, members' sd)`` (the
    interval's spread); ValueError for a regressor that is not one, or an ensemble of one member. ``distance``:
    the GP head's result is followed by each row's input distance (``GPEnsemble.numpy_head``)."""
    from liverforce.learn.gp import GPEnsemble, GPRegressor

    if members:
        if not isinstance(module, GPEnsemble):
            raise ValueError(f"the interval reads a GP ensemble's members' spread; this regressor is a "
                             f"{type(module).__name__}")
        return module.numpy_head(fixed, members=True, distance=distance)
    return module.numpy_head(fixed, distance=distance) if isinstance(module, (GPRegressor, GPEnsemble)) else None


def _act(h: np.ndarray, slope: float | None) -> np.ndarray:
    if slope is None:
        return h
    if slope == 0.0:
        return np.maximum(h, 0.0, out=h)
    return np.where(h > 0, h, slope * h)


class CompiledROI:
    """A model specialised to one :class:`~liverforce.serve.preop.Preop` (module docstring).

    Parameters
    ----------
    model : liverforce.learn.model.ForceModel
        With ``roi_features: displacement`` (any encoder, with or without the
        state vector).
    preop : Preop
        The fixed context; checked by the caller (:meth:`Predictor.compile`).
    limits, scale : Limits, TrainingScale
        For the per-call displacement check.
    """

    def __init__(self, model, preop: Preop, *, limits: Limits | None = None, scale: TrainingScale | None = None):
        rep = model.representation
        if rep.features != "displacement":
            raise PredictionInputError(
                f"the fixed-topology fast path needs a model trained with roi_features: displacement (this one uses "
                f"'{rep.features}', whose grid depends on the deformed positions); use Predictor.predict"
            )
        self.limits = limits or Limits()
        self.scale = scale or TrainingScale.of(model)
        self.preop = preop
        p = preop.exertion_point_mm
        R = preop.rotation
        self.R = R
        U = preop.roi_undeformed_mm
        k = len(U)
        self.k = k
        self._U_flat = U.ravel().copy()
        U_loc = (U - p) @ R.T
        keep = np.ones(k, dtype=bool)
        if rep.occlusion_radius_mm > 0 and rep.occlusion_mode == "remove":
            keep = np.hypot(U_loc[:, 0], U_loc[:, 1]) >= rep.occlusion_radius_mm
            if keep.sum() < 3:
                raise PredictionInputError(
                    f"only {int(keep.sum())} ROI nodes remain outside the model's occlusion radius "
                    f"{rep.occlusion_radius_mm} mm; the ROI is too small"
                )
        # rigid_motion: remove -- the far nodes' best rigid motion is undone on every call's D first (the same
        # function as the reference path); what follows is then affine in the corrected D
        self._rigid_nodes = rigid_fit_nodes(U_loc, rep.rigid_motion_radius_mm) if rep.removes_rigid_motion else None
        kk = int(keep.sum())
        g2 = rep.grid_size**2
        W = np.zeros((g2, k))
        if rep.uses_triangles:  # the top sheet of the patch's triangles (of the kept nodes), as the reference path
            if preop.roi_triangles is None:
                raise PredictionInputError(
                    "this model resamples node displacements on the top sheet of the ROI patch's triangles: give "
                    "the context's roi_triangles (Preop.from_surface computes them; a context file's roi_triangles)")
            # the top sheet's nodes chosen on the whole patch, then the occlusion (as the reference path)
            keep = keep & top_sheet_nodes(U_loc, preop.roi_triangles)
            kk = int(keep.sum())
            W[:, keep] = interpolate_top_sheet(U_loc[keep], keep_triangles(preop.roi_triangles, keep), np.eye(kk),
                                               rep.grid(), "compiled ROI")
        else:
            W[:, keep] = interpolate_to_grid(U_loc[keep, :2], np.eye(kk), rep.grid(), "compiled ROI")
        # x[c g2 + i] = sum_j W[i, j] (R (D_j - p) - U_loc_j)[c]
        M = np.einsum("ij,ca->cija", W, R).reshape(3 * g2, 3 * k)
        off = p @ R.T + U_loc  # (k, 3)
        x0 = -(W @ off).T.ravel()
        pre = model.pre
        fs = pre.feature_scaler
        Mx = M / fs.scale[:, None]
        bx = (x0 - fs.mean) / fs.scale
        enc = pre.encoder
        cs = pre.code_scaler
        if isinstance(enc, PCAEncoder):
            A_code = enc.components @ Mx
            b_code = enc.components @ (bx - enc.mean)
            self._enc_layers: list = []
            A_code = A_code / cs.scale[:, None]
            b_code = (b_code - cs.mean) / cs.scale
        else:
            layers = numpy_layers(enc.net.encoder)
            W1, b1, s1 = layers[0]
            A_code = W1 @ Mx
            b_code = W1 @ bx + b1
            self._first_slope = s1
            self._enc_layers = layers[1:]
            self._cs = (cs.mean, cs.scale)
        self._pca = isinstance(enc, PCAEncoder)
        self.A_code, self.b_code = A_code, b_code
        # state vector: constant except the deformed ROI centroid (affine in D) and, per call, the material
        self.uses_state = model.uses_state
        if self.uses_state:
            ss = pre.state_scaler
            s_state = state_vector(preop.to_arrays(U), R=R[None])  # deformed centroid = undeformed here; replaced below
            self._stiff = float(pre.stiffness(s_state, 1)[0, 0])  # force scaling by the material's stiffness
            s_ref = pre.state_features(s_state, np.zeros((1, 3 * g2)))[0]  # features at rest: no displacement
            self._s_mean, self._s_scale = ss.mean, ss.scale
            s0 = (s_ref - ss.mean) / ss.scale
            sc = _STATE_DEF_CENTROID
            # columns 6..8: R (mean_j D_j - p) -> scaled
            Rs = R / ss.scale[sc][:, None]
            self._S_c = Rs  # (3, 3) acting on the centroid
            s0 = s0.copy()
            A_state = np.zeros((s0.size, 3 * k))
            # under an observation model the state's deformed centroid is the undeformed one (s_ref's):
            # Representation.state_arrays; otherwise the mean of D
            self._centroid_from_d = not model.representation.occludes
            if self._centroid_from_d:
                s0[sc] = -(Rs @ p) - ss.mean[sc] / ss.scale[sc]
                mean_op = np.zeros((3, 3 * k))
                for a in range(3):
                    mean_op[a, a::3] = 1.0 / k
                A_state[sc] = Rs @ mean_op
            self._s0 = s0
            self._lin_slice = self._disp_slice = None
            if pre.linear_force_weights is not None:
                # f_lin = C^-1 u_w, u_w = sum_i w_i x_c,i (channels 0..2): affine in D like the grid features
                lc = slice(s_state.shape[1], s_state.shape[1] + 3)
                w = pre.linear_force_weights
                Cinv = np.linalg.inv(compliance_matrices(s_state)[0])
                Mw = np.stack([w @ M[c * g2:(c + 1) * g2] for c in range(3)])
                xw0 = np.array([w @ x0[c * g2:(c + 1) * g2] for c in range(3)])
                self._lin_parts = (Cinv @ Mw, Cinv @ xw0)  # f_lin at k = 1: affine in D
                self._lin_slice = lc
                self._k_lin = float(pre.linear_factor(s_state, 1)[0, 0])  # force_scaling: linear (else 1)
                self._set_linear(A_state, s0)
                self._disp_slice = slice(lc.start, lc.start + pre.n_displacement_features)
                if pre.indentation_strain:  # u_w,n / h: affine in D too, and the same for every material
                    ec = lc.stop
                    h = float(s_state[0, THICKNESS_COLUMN])
                    A_state[ec] = Mw[2] / h / ss.scale[ec]
                    s0[ec] = (xw0[2] / h - ss.mean[ec]) / ss.scale[ec]
            self.A_state = A_state
            self._mat_slice = slice(MATERIAL_START, MATERIAL_START + pre.n_material)
        else:
            self._stiff = 1.0
        self._pre = pre
        self._model = model  # its interval and the GP ensemble's members' head, read on the first call asking
        self._interval = self._member_head = self._kf = None  # for an interval (_interval_parts)
        self._kmat = float(pre.material_factor(s_state, 1)[0, 0]) if self.uses_state else 1.0  # the interval's k
        self._gp = regressor_head(model.regressor)
        self._reg = [] if self._gp is not None else numpy_layers(model.regressor)
        self._tmean, self._tscale = pre.target_scaler.mean, pre.target_scaler.scale
        self._rebuild()

    # ------------------------------------------------------------------
    def _rebuild(self) -> None:
        """Stack the code and state parts into one ``z = A vec(D) + b`` (first network input)."""
        parts_A, parts_b = [self.A_code], [self.b_code]  # PCA code, or the AE's first pre-activation
        if self.uses_state:
            parts_A.append(self.A_state)
            parts_b.append(self._s0)
        self.A = np.ascontiguousarray(np.vstack(parts_A))
        self.b = np.concatenate(parts_b)
        # applied to the displacement Δ = vec(D) - vec(U) (small numbers: no cancellation of large offsets)
        self.bU = self.b + self.A @ self._U_flat
        self._n_code = self.A_code.shape[0]
        # rows of z that depend on D (code + deformed centroid); the rest of the state is constant
        self._dyn = np.flatnonzero(np.abs(self.A).max(axis=1) > 0)
        self._A_dyn = np.ascontiguousarray(self.A[self._dyn])
        self._all_dyn = len(self._dyn) == len(self.A)
        self._reg32 = [(W.astype(np.float32), b.astype(np.float32), s) for W, b, s in self._reg]
        self._enc32 = [(W.astype(np.float32), b.astype(np.float32), s) for W, b, s in self._enc_layers]

    def _set_linear(self, A_state: np.ndarray, s0: np.ndarray) -> None:
        """The linear force estimate's rows of the state map: ``k_lin C^-1 u_w``, scaled."""
        lc, (A1, b1) = self._lin_slice, self._lin_parts
        A_state[lc] = self._k_lin * A1 / self._s_scale[lc][:, None]
        s0[lc] = (self._k_lin * b1 - self._s_mean[lc]) / self._s_scale[lc]

    def with_material(self, material_params_mpa) -> "CompiledROI":
        """Change the material constants (MPa) of the compiled context in place; returns self."""
        if not self.uses_state:
            return self
        mat = np.asarray(material_params_mpa, dtype=np.float64).ravel()
        sl = self._mat_slice
        if mat.size != sl.stop - sl.start:
            raise PredictionInputError(f"material_params_mpa: expected {sl.stop - sl.start} constants, got {mat.size}")
        check_material(_vector("material_params_mpa", mat), self.scale, self.limits, "")
        full = np.zeros((1, sl.stop))
        full[0, sl] = mat
        self._stiff = float(self._pre.stiffness(full, 1)[0, 0])
        self._kmat = float(self._pre.material_factor(full, 1)[0, 0])
        self._kf = None  # the interval's widening for this material: computed again when asked
        self._s0[sl] = (self._pre.base_state_features(full)[0, sl] - self._s_mean[sl]) / self._s_scale[sl]
        if self._lin_slice is not None:
            self._k_lin = float(self._pre.linear_factor(full, 1)[0, 0])
            self._set_linear(self.A_state, self._s0)
        self._rebuild()
        return self

    # ------------------------------------------------------------------
    @property
    def interval(self):
        """The model's calibrated interval (:class:`liverforce.learn.interval.ConformalInterval`), or None for a
        model trained without ``train.interval``; :class:`~liverforce.learn.model.ModelFormatError` for a bundle
        whose interval cannot be computed (:attr:`liverforce.learn.model.ForceModel.interval`)."""
        if self._interval is None:
            self._interval = self._model.interval
        return self._interval

    @property
    def coverage(self) -> float | None:
        """The interval's nominal coverage (None without an interval)."""
        ci = self.interval
        return None if ci is None else ci.coverage

    def _interval_parts(self):
        """``(interval, widening of the context's material (1, 1) or (1, 3), whether the members' sd is read)``;
        PredictionInputError for a model without an interval (the words of ``ForceModel.predict_interval``)."""
        ci = self.interval
        if ci is None:
            raise PredictionInputError(
                "this model has no calibrated interval (trained without train.interval): predict and predict_batch "
                "without with_interval give the force alone; train the model with train.interval for its interval")
        wide = ci.uses_spread or ci.uses_distance  # the widths read the members' sd, the input distance or both
        if wide and self._member_head is None:  # the GP's head that also gives them
            self._member_head = regressor_head(self._model.regressor, members=ci.uses_spread,
                                               distance=ci.uses_distance)
        if self._kf is None:
            self._kf = ci.stiffness_factor(np.array([[self._kmat]]))
        return ci, self._kf, wide

    def _network(self, z: np.ndarray, members: bool = False):
        """Rows ``z`` (float64, first-stage outputs) -> local force (float64), float32 like the reference.

        ``members`` (a GP whose interval reads the members' spread, the input distance or both):
        ``(local force, sd, distance)``, ``sd`` the members' sd of the local force before the force scaling's
        factor (what ``Forward.spread_local`` is over it; None when the interval does not read it), ``distance``
        each row's input distance (``Forward.input_distance``; None likewise), the force the same bits as
        without."""
        nc = self._n_code
        if self._pca:
            h = z.astype(np.float32)
        else:
            e = _act(z[..., :nc].astype(np.float32), self._first_slope)
            for W, b, s in self._enc32:
                e = _act(e @ W.T + b, s)
            code = (e.astype(np.float64) - self._cs[0]) / self._cs[1]
            h = np.concatenate([code, z[..., nc:]], axis=-1).astype(np.float32) if self.uses_state else \
                code.astype(np.float32)
        if members:
            ci = self.interval
            got = self._member_head(h.reshape(-1, h.shape[-1]))
            h, sd, near = got[0], got[1] if ci.uses_spread else None, got[-1] if ci.uses_distance else None
            h = h.reshape(*z.shape[:-1], -1)
            # the sd of (h tscale + tmean) over the members (Forward.spread_local, before its stiffness factor)
            sd = None if sd is None else (sd * np.abs(self._tscale)).reshape(h.shape)
            return h * self._tscale + self._tmean, sd, near
        if self._gp is not None:
            h = self._gp(h.reshape(-1, h.shape[-1])).reshape(*h.shape[:-1], -1)
        for W, b, s in self._reg32:
            h = _act(h @ W.T + b, s)
        return h.astype(np.float64) * self._tscale + self._tmean

    def _rigid_free(self, D: np.ndarray) -> np.ndarray:
        """``D`` ``(k, 3)`` with the far nodes' best rigid motion undone (``rigid_motion: remove``; else ``D``).
        Non-finite input is passed on as it is (the output is then non-finite and reported)."""
        if self._rigid_nodes is None or not np.isfinite(D).all():
            return D
        return undo_rigid_motion(self.preop.roi_undeformed_mm, D, self._rigid_nodes)

    def _fail(self, D: np.ndarray, label: str = "") -> None:
        _points(f"{label}roi_deformed_mm", D.reshape(-1, 3))  # names NaN/inf rows
        raise PredictionInputError(f"{label}roi_deformed_mm: the prediction is not finite")

    def predict(self, deformed_roi_mm: np.ndarray) -> np.ndarray:
        """Force ``(3,)`` N in the liver frame for the deformed ROI ``(k, 3)`` mm (same node order as the context)."""
        D = np.asarray(deformed_roi_mm, dtype=np.float64)
        z, dmax = self.first_stage(D)
        return self.finish(z, dmax, D)

    def predict_interval(self, deformed_roi_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Force ``(3,)`` N in the liver frame (:meth:`predict`'s) and its calibrated interval's half-widths ``(3,)``
        N per local component (t1, t2, n; the interval is ``force_local +- half``, ``force_local = R force``), as
        :meth:`liverforce.learn.model.ForceModel.predict_interval` gives them (module docstring).
        :class:`PredictionInputError` for a model trained without ``train.interval``."""
        ci, kf, members = self._interval_parts()
        D = np.asarray(deformed_roi_mm, dtype=np.float64)
        z, dmax = self.first_stage(D)
        f, sd, near = self._network(z, members=True) if members else (self._network(z), None, None)
        f_loc = f * self._stiff
        F = self._checked(f_loc @ self.R, dmax, D)
        half = kf * ci.force_widths(f_loc[None], None if sd is None else sd[None] * self._stiff, near)
        return F, half[0]

    def first_stage(self, D: np.ndarray) -> tuple[np.ndarray, float]:
        """Preprocessing of one call: shape check, displacement, ``z = A Δ + b`` and the largest displacement."""
        if D.shape != (self.k, 3):
            raise PredictionInputError(
                f"roi_deformed_mm: expected shape ({self.k}, 3) (the compiled ROI's nodes in order), got {D.shape}"
            )
        d = D.ravel() - self._U_flat
        dmax = np.abs(d).max()  # the check reads the displacement as given
        if self._rigid_nodes is not None:
            d = self._rigid_free(D).ravel() - self._U_flat
        if self._all_dyn:
            return self._A_dyn @ d + self.bU, dmax
        z = self.bU.copy()
        z[self._dyn] += self._A_dyn @ d
        return z, dmax

    def finish(self, z: np.ndarray, dmax: float, D: np.ndarray) -> np.ndarray:
        """Network of one call: MLP (and AE encoder), target scaling, rotation to the liver frame, checks."""
        return self._checked((self._network(z) * self._stiff) @ self.R, dmax, D)

    def _checked(self, f: np.ndarray, dmax: float, D: np.ndarray) -> np.ndarray:
        """The force ``f`` of one call, once it is finite and the displacement within the training's scale."""
        if not (np.isfinite(f).all() and np.isfinite(dmax)):
            self._fail(D)
        if dmax > self._dlim:
            check_displacement(float(dmax), self.scale, self.limits, "")
        return f

    @property
    def _dlim(self) -> float:
        fam = self.scale.feature_abs_max
        if fam is None:
            return np.inf
        return self.limits.scale_factor * max(max(fam[:3]), 1e-6)

    def predict_batch(self, deformed_roi_mm: np.ndarray, *, roi_centroid_deformed_mm: np.ndarray | None = None,
                      material_params_mpa: np.ndarray | None = None, with_interval: bool = False):
        """Forces ``(n, 3)`` N for ``n`` deformed ROIs ``(n, k, 3)`` of the compiled context.

        ``roi_centroid_deformed_mm`` ``(n, 3)`` overrides the mean of each
        deformed ROI (shards store it from float64 positions);
        ``material_params_mpa`` ``(n, p)`` gives per-row material constants.
        ``with_interval``: ``(forces (n, 3), half-widths (n, 3))``, the half-widths of each row's calibrated
        interval per local component (:meth:`predict_interval`; each row's own stiffness factor with
        ``material_params_mpa``); :class:`PredictionInputError` for a model trained without ``train.interval``.
        """
        if with_interval:
            ci, kf, members = self._interval_parts()
        D = np.asarray(deformed_roi_mm, dtype=np.float64)
        if D.ndim != 3 or D.shape[1:] != (self.k, 3):
            raise PredictionInputError(f"roi_deformed_mm: expected shape (n, {self.k}, 3), got {D.shape}")
        n = len(D)
        X = D.reshape(n, 3 * self.k) - self._U_flat  # displacements
        dmax = np.maximum(X.max(axis=1), -X.min(axis=1))
        if self._rigid_nodes is not None:  # the state's deformed centroid is then the corrected ROI's, not given
            X = np.stack([self._rigid_free(Di) for Di in D]).reshape(n, 3 * self.k) - self._U_flat
            roi_centroid_deformed_mm = None
        if self.uses_state and not self._centroid_from_d:  # an observed model never reads a given centroid
            roi_centroid_deformed_mm = None
        stiff = np.full((n, 1), self._stiff)
        kmat = None  # the rows' stiffness factors (the interval's), when they differ from the context's
        if self.uses_state and (roi_centroid_deformed_mm is not None or material_params_mpa is not None):
            nc = self._n_code
            z = np.empty((n, self.A.shape[0]))
            z[:, :nc] = X @ self.A[:nc].T + self.bU[:nc]
            z[:, nc:] = self._s0
            sc = slice(nc + _STATE_DEF_CENTROID.start, nc + _STATE_DEF_CENTROID.stop)
            if roi_centroid_deformed_mm is None:
                z[:, sc] = X @ self.A[sc].T + self.bU[sc]
            else:
                c = np.asarray(roi_centroid_deformed_mm, dtype=np.float64).reshape(n, 3)
                z[:, sc] = c @ self._S_c.T + self.b[sc]
            if self._disp_slice is not None:  # the linear force estimate and the indentation strain: affine in D
                lc = slice(nc + self._disp_slice.start, nc + self._disp_slice.stop)
                z[:, lc] = X @ self.A[lc].T + self.bU[lc]
            if material_params_mpa is not None:
                ms = self._mat_slice
                mat = np.asarray(material_params_mpa, dtype=np.float64).reshape(n, -1)
                if mat.shape[1] != ms.stop - ms.start:
                    raise PredictionInputError(
                        f"material_params_mpa: expected {ms.stop - ms.start} constants per row, got {mat.shape[1]}")
                for row in np.unique(mat, axis=0):
                    check_material(_vector("material_params_mpa", row), self.scale, self.limits, "")
                full = np.zeros((n, ms.stop))
                full[:, ms] = mat
                stiff = self._pre.stiffness(full, n)
                kmat = self._pre.material_factor(full, n)
                z[:, nc + ms.start:nc + ms.stop] = (self._pre.base_state_features(full)[:, ms] - self._s_mean[ms]) \
                    / self._s_scale[ms]
                if self._lin_slice is not None:  # f_lin of each row's own material (force_scaling: linear)
                    lc = slice(nc + self._lin_slice.start, nc + self._lin_slice.stop)
                    mean, scale = self._s_mean[self._lin_slice], self._s_scale[self._lin_slice]
                    f1 = (z[:, lc] * scale + mean) / self._k_lin
                    z[:, lc] = (f1 * self._pre.linear_factor(full, n) - mean) / scale
        else:
            z = np.empty((n, len(self.bU)))
            z[:] = self.bU
            z[:, self._dyn] += X @ self._A_dyn.T
        if with_interval:
            f, sd, near = self._network(z, members=True) if members else (self._network(z), None, None)
            f_loc = f * stiff
            F = f_loc @ self.R
        else:
            F = (self._network(z) * stiff) @ self.R
        bad = ~(np.isfinite(F).all(axis=1) & np.isfinite(dmax))
        if bad.any():
            i = int(np.argmax(bad))
            self._fail(D[i], f"row {i}: ")
        over = dmax > self._dlim
        if over.any():
            i = int(np.argmax(over))
            check_displacement(float(dmax[i]), self.scale, self.limits, f"row {i}: ")
        if not with_interval:
            return F
        k = kf if kmat is None else ci.stiffness_factor(kmat)
        return F, k * ci.force_widths(f_loc, None if sd is None else sd * stiff, near)

