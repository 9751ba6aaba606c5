"""Fast path of a camera-cloud model at one exertion point: a raw cloud and the tool tip -> force and interval.

In the operating room the tool rests at one exertion point while the camera
streams clouds. Everything that depends only on the pre-operative context is
done once, when compiling (:class:`CompiledCloud`):

- the pre-operative height raster of :class:`~liverforce.learn.cloud_features.ReferenceSurface`;
- the state vector (scaled), the compliance's inverse ``C^-1`` (for ``f_lin``),
  the stiffness factor of the material (force scaling) and so the interval's
  half-widths;
- the scalers and PCA folded into one affine map, the MLP as NumPy arrays
  (float32, as the torch reference; :func:`liverforce.serve.compiled.numpy_layers`).

A call then grids the cloud (:func:`~liverforce.learn.cloud_features.cloud_grid`,
the reference code: same features by construction), runs the out-of-distribution
checks of :func:`liverforce.serve.cloud.camera_checks`, and one small affine map
and the MLP. The reference path (:meth:`liverforce.serve.Predictor.predict_cloud`)
stays the oracle: a test checks both agree to 1e-6 N.
"""

from __future__ import annotations

import numpy as np

from liverforce.learn import camera
from liverforce.learn.cloud_features import ReferenceSurface, cloud_grid
from liverforce.learn.encoders import PCAEncoder
from liverforce.learn.state import compliance_matrices, state_vector
from liverforce.serve.checks import Limits
from liverforce.serve.cloud import camera_checks
from liverforce.serve.compiled import _act, numpy_layers
from liverforce.serve.errors import PredictionInputError
from liverforce.serve.preop import Preop


class CompiledCloud:
    """A camera-cloud model (PCA encoder) specialised to one :class:`Preop` (module docstring).

    ``predict(cloud, tool_tip)`` returns ``(force (3,) N liver frame, half-widths (3,) N local or None,
    warnings)``. Build it with :meth:`liverforce.serve.Predictor.compile_cloud` (the context is checked there).
    """

    def __init__(self, model, preop: Preop, *, limits: Limits | None = None):
        rep = model.representation
        if not rep.is_camera or not isinstance(model.pre.encoder, PCAEncoder):
            raise PredictionInputError("the compiled cloud path needs a camera-cloud model (roi_features: cloud) with "
                                       "the PCA encoder; use Predictor.predict_cloud")
        self.model, self.limits = model, limits or Limits()
        self.p = np.asarray(preop.exertion_point_mm, dtype=np.float64)
        self.R = preop.rotation
        self.spec = camera.grid_spec(rep.grid_size, rep.half_width_mm, rep.camera)
        self.ref = ReferenceSurface.from_rotation(preop.roi_undeformed_mm, self.p, self.R, self.spec,
                                                  label="compiled cloud")
        self.reach = rep.half_width_mm * (1.0 + 2.0 / (rep.grid_size - 1))
        pre = model.pre
        fs, enc, cs = pre.feature_scaler, pre.encoder, pre.code_scaler
        # code = ((x - mu_f) / s_f - mu_pca) C^T, scaled: one affine map A x + b
        A = (enc.components / fs.scale[None, :]) / cs.scale[:, None]
        self.A = A
        self.b = -(enc.components @ (fs.mean / fs.scale + enc.mean) + cs.mean) / cs.scale
        self.uses_state = model.uses_state
        self.k = 1.0
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
        self.layers = [(W.astype(np.float32), b.astype(np.float32), sl) for W, b, sl in numpy_layers(model.regressor)]
        self.tmean, self.tscale = pre.target_scaler.mean, pre.target_scaler.scale
        ci = model.interval
        self.half = None if ci is None else ci.half_widths(np.array([[self.k]]))[0]

    def features(self, cloud_mm, tool_tip_mm) -> np.ndarray:
        """The model's feature row of one cloud and tool tip (the reference features, checked for size)."""
        O = np.asarray(cloud_mm, dtype=np.float64).reshape(-1, 3)
        tip = np.asarray(tool_tip_mm, dtype=np.float64).reshape(3)
        loc = (O - self.p) @ self.R.T
        n_used = int(np.count_nonzero((np.abs(loc[:, 0]) <= self.reach) & (np.abs(loc[:, 1]) <= self.reach)))
        if n_used < self.limits.min_cloud_points:
            raise PredictionInputError(f"cloud: only {n_used} of {len(O)} points lie over the model's grid around "
                                       f"the exertion point (at least {self.limits.min_cloud_points} needed)")
        x = np.empty(self.A.shape[1])
        x[:-3] = cloud_grid(O, self.ref, self.spec).features(include_mask=True)
        x[-3:] = self.R @ (tip - self.p)
        return x

    def predict(self, cloud_mm, tool_tip_mm) -> tuple[np.ndarray, np.ndarray | None, list[str]]:
        x = self.features(cloud_mm, tool_tip_mm)
        warnings = camera_checks(self.model, x, self.limits)
        z = self.A @ x + self.b
        if self.uses_state:
            parts = [z, self.s_base]
            if self.lin:
                parts.append((self.Cinv @ x[-3:] - self.lin_mean) / self.lin_scale)
            z = np.concatenate(parts)
        h = z.astype(np.float32)
        for W, b, sl in self.layers:
            h = _act(h @ W.T + b, sl)
        f_local = (h.astype(np.float64) * self.tscale + self.tmean) * self.k
        return self.R.T @ f_local, self.half, warnings
