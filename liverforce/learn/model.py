"""The fitted force model: representation + scalers + encoder + regressor, with save/load.

Prediction pipeline for a set of cases (``arrays`` in the input contract)::

    R  = case_rotations(arrays)                    local frame, once per case
    x  = Representation.features_of(arrays, R)     ROI -> grid features (local frame)
    xs = feature_scaler(x);  c = encoder(xs);  cs = code_scaler(c)
    s  = state_scaler(state_vector(arrays, R))     (if the state vector is used)
    f  = target_scaler^-1( MLP([cs, s]) )          local force (F.t1, F.t2, F.n), N
    F  = R^T f                                     source-frame force, N

With ``force_scaling: stiffness`` (state-vector models) the material enters
by construction the way hyperelasticity does: scaling every constant of a
strain energy by ``k`` scales the stress at a given deformation by ``k``. The
model sees the constants' *ratios* ``c / c_1`` in the state vector and learns
the force divided by the stiffness ``k = c_1 / c_1,ref`` (``c_1`` the first
constant, C10 for neo-Hooke, Mooney-Rivlin and Yeoh; ``c_1,ref`` its training
mean)::

    s_mat = c / c_1;   f = k * target_scaler^-1( MLP([cs, s]) )

so constants x0.5 ... x2 scale the predicted force x0.5 ... x2 at the same
surface deformation, even outside the training range. But the supports'
springs do not scale with the liver, so the true force scales less than ``k``:
on the default run's unseen livers (constants x1.4) this model over-predicted
(median ratio 1.03, mean +0.12 N along the force).

With ``force_scaling: linear`` (the default) only the linear force estimate
``f_lin`` (below) is scaled: ``f_lin = k C^-1 u_w``, the target is the force
itself and the material constants enter as they are (MPa). The part of the
force that the tissue's stiffness carries moves with ``k`` through ``f_lin``
(for the same force on a k-times stiffer liver ``f_lin`` is unchanged), which
the GP's linear term carries beyond the training range; what the springs carry
is learned. Measured on the 95e8043 default run's shards (pca_sv, GP, 5 splits;
the 8 unseen livers at constants x0.6 / x1.4 / x2.0, all outside the training
range of +-30 %; ``benchmarks/experiment_force_scaling.py``): unseen MAE
0.297 / 0.163 / 0.276 N with ``linear``, 0.324 / 0.206 / 0.330 N with
``stiffness``, 0.360 / 0.164 / 0.407 N with ``none``; scenario III test
accuracy 95.5 / 92.6 / 95.3 %, IV 91.2 / 90.3 / 91.6 %.

Linear force estimate (state-vector models with displacement features): the
state vector carries the pre-operative probe's compliance ``C`` at the
exertion point (local frame, reference material). The regressor also sees
``f_lin = C^-1 u_w``, with ``u_w`` the displacement *as observed* (the grid
features, after occlusion and noise) averaged with a Gaussian of the tool
radius over the grid. It is the small-load answer of the linear problem; the
network learns the nonlinear correction. It reads only what the model's
features already hold, so occlusion and noise reach it as they reach the
encoder::

    u_w = sum_ij w_ij d(u_j, v_i),  w_ij ~ exp(-(u_j^2 + v_i^2) / (2 r^2));   f_lin = C^-1 u_w

(``r``: ``model.probe_force_radius_mm``, the tool radius; 0 turns it off.)
A camera-cloud model (``roi_features: cloud``) has no grid displacement; it
uses the tool tip's displacement the robot reports instead,
``f_lin = C^-1 tip`` (:mod:`liverforce.learn.camera`).

Indentation strain (``model.indentation_strain``, with the linear force
estimate): the regressor also sees ``e = u_w,n / h``, the normal displacement
under the tool over the tissue thickness there (``tool_thickness_mm`` of the
state vector). The linear estimate is exact only at small strain; how much a
hyperelastic layer stiffens (or a thin lobe bends away) depends on the depth
*relative to* the thickness, which the GP would otherwise have to build from
two inputs that it extrapolates separately. Measured on the default run's
shards (5 seeded splits, the pipeline's own seeds;
``benchmarks/experiment_indentation_strain.py``): IV test accuracy pca_sv
94.35 +- 1.65 -> 94.70 +- 1.56 % (better on every split), ae_sv 93.31 ->
93.85 %, cloud_sv 85.20 -> 85.47 %; II and III unchanged (99.81 / 98.78 ->
99.81 / 98.76 %); unseen-liver MAE pca_sv 0.130 -> 0.127 N, ae_sv 0.150 ->
0.137 N, cloud_sv 0.437 -> 0.437 N.

Bundle format (a directory, no pickle of arbitrary code)::

    model.json      format name + version, representation, encoder spec,
                    regressor spec, scalers (JSON floats round-trip exactly), meta
    regressor.pt    torch state_dict (loaded with ``weights_only=True``)
    encoder.pt      AE/DAE state_dict      | pca.npz  PCA mean + components

A bundle whose ``format_version`` is not in :data:`READ_VERSIONS` is
refused with :class:`ModelFormatError` (bundles are written at :data:`FORMAT_VERSION`).
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from liverforce.learn.camera import N_DENT
from liverforce.learn.cloud_features import ROI_TRIANGLES_KEY
from liverforce.learn.encoders import AutoEncoder, Encoder, PCAEncoder
from liverforce.learn.frames import case_rotations, force_to_local, force_to_source
from liverforce.learn.gp import GPEnsemble, GPRegressor, training_rows
from liverforce.learn.names import FORCE_SCALINGS
from liverforce.learn.regressor import (
    FitParams,
    RegressorSpec,
    fit_regressor,
    load_regressor,
    predict_regressor,
)
from liverforce.learn.representation import Representation
from liverforce.learn.scaling import Standardizer
from liverforce.learn.state import (
    COMPLIANCE_COLUMNS,
    MATERIAL_START,
    STATE_INPUTS,
    THICKNESS_COLUMN,
    compliance_matrices,
    outside_ranges,
    recorded_ranges,
    state_vector,
)
from liverforce.learn.torchutil import EpochCallback, as_tensor
from liverforce.seeds import derive

FORMAT = "liverforce.force_model"
FORMAT_VERSION = 18  # 3: probe compliance in the state vector (material from column 22), linear force estimate;
#                     4: the GP regressor may be a GPEnsemble (model.gp.code_members), which a reader of 3 cannot load;
#                     5: the state features may end with the indentation strain, which a reader of 4 would misread;
#                     6: a GP's kernel may be the rational quadratic (a ``shape`` buffer), which a reader of 5 would
#                        ignore and evaluate as the squared exponential;
#                     7: a camera model's pre-operative height is the top sheet of the ROI patch's triangles
#                        (camera.grid.reference: surface), which a reader of 6 would build from the ROI points;
#                     8: a node model's grid may be the patch's top sheet (representation interpolation: surface),
#                        a key a reader of 7 does not know;
#                     9: a state-vector model records C10's training mean (material_ref) whatever its force
#                        scaling: with force_scaling none a reader of 8 would never widen the interval outside the
#                        calibration's stiffness range
#                     10: the interval may scale with the predicted force (train.interval.scale: force), which a
#                        reader of 9 would read as scaled by the stiffness
#                     11: the interval may have a width per bin of the predicted force (scale: force_bins), which
#                        a reader of 10 would read as scaled by the stiffness
#                     12: a camera model's features may hold the dent fit (camera.grid.dent_radius_mm) and its state
#                        features end with it, which a reader of 11 would read as the tool tip
#                     13: a GP may have one kernel per force component (model.gp.per_output: length scales
#                        (outputs, inputs)), which a reader of 12 cannot evaluate
#                     14: the interval may widen outside the calibration's stiffness range as its residuals grow
#                        with the stiffness (train.interval.widen: fitted), which a reader of 13 would widen in
#                        proportion to it
#                     15: a camera model's point noise may be a range (observation.noise_sd_mm: [lo, hi]) and its
#                        grid records the range's most (instrument_point_sd_max_mm), which a reader of 14 cannot load
#                     16: a camera model's grid may drop a cloud's gross depth errors (camera.grid.outlier_mm) and its
#                        observation may add them (observation.outlier_fraction), keys a reader of 15 cannot load
#                     17: the interval may be scaled by the GP ensemble members' spread (train.interval.spread), which
#                        a reader of 16 would read as widths in N
#                     18: the interval may have far widths (train.interval.far_widths: a factor beyond the
#                        input-distance threshold, another below it), which a reader of 17 would ignore
READ_VERSIONS = (3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18)
# a version-3 bundle is a version-4 bundle with a single GP (or an MLP); 4 is 5
#                                     without the indentation strain; 5 is 6 with squared-exponential GPs (no shape
#                                     buffer); 6 is 7 with camera models on the ROI points' reference (reference:
#                                     points); 7 is 8 with node models on the points' interpolant (no interpolation
#                                     key: the Representation default, points); 8 is 9 without material_ref (the
#                                     force scaling's reference, if any, stands in); 10 is 11 without force_bins;
#                                     13 is 14 without widen (proportional)

ROI_INPUTS = (
    "exertion_point_mm",
    "frame_normal",
    "frame_t1",
    "frame_t2",
    "roi_undeformed_mm",
    "roi_deformed_mm",
)


class ModelFormatError(ValueError):
    """A model directory is missing, of another format, or of another format version."""


# --------------------------------------------------------------------------
# prepared learning inputs
# --------------------------------------------------------------------------


def linear_force_radius_of(model_cfg: dict) -> float:
    """Gaussian radius (mm) of the linear force estimate's ``u_w``; 0 when the model has none.

    Needs the state vector (the compliance) and displacement features (``displacement`` or ``both``).
    """
    if not bool(model_cfg.get("state_vector")) or model_cfg.get("roi_features", "displacement") == "deformed":
        return 0.0
    return float(model_cfg.get("probe_force_radius_mm") or 0.0)


def linear_force_weights(rep: Representation, radius_mm: float) -> np.ndarray:
    """Grid weights ``(g^2,)`` (sum 1) of ``u_w``: a Gaussian of ``radius_mm`` about the exertion point."""
    xy = rep.grid()
    w = np.exp(-0.5 * (xy[:, 0] ** 2 + xy[:, 1] ** 2) / float(radius_mm) ** 2)
    return w / w.sum()


def encoder_code_size(code_size: int, members) -> int:
    """The encoder's code size: the largest GP ensemble member's (``members``,
    :func:`liverforce.learn.regressor.gp_code_members`), else
    ``code_size`` (``model.code_size``)."""
    return max(members) if members else int(code_size)


def member_sizes(pre: "Preprocessor", members) -> list[int]:
    """The code sizes of the GP ensemble's members as fitted: each of ``members`` capped at the PCA code
    the encoder really has (PCA keeps at most as many components as training rows or features, so a
    small data set has fewer than the largest member), duplicates dropped; ``[]`` for no members."""
    if not members:
        return []
    if not isinstance(pre.encoder, PCAEncoder):
        raise ValueError("model.gp.code_members: a GP ensemble over code sizes needs the PCA encoder")
    return sorted({min(int(k), pre.encoder.code_size) for k in members})


def member_columns(pre: "Preprocessor", members) -> list[np.ndarray] | None:
    """The regressor-input columns of each GP ensemble member (:func:`member_sizes`): the leading ``k``
    code components and every state column (:meth:`Preprocessor.inputs` puts the code first); None for
    no members."""
    sizes = member_sizes(pre, members)
    if not sizes:
        return None
    rest = np.arange(pre.encoder.code_size, pre.n_inputs)
    return [np.concatenate([np.arange(k), rest]) for k in sizes]


def force_scaling_of(model_cfg: dict) -> str:
    """The force scaling a model config asks for: ``model.force_scaling`` for state-vector models, else none."""
    return str(model_cfg.get("force_scaling", "none")) if bool(model_cfg.get("state_vector")) else "none"


def indentation_strain_of(model_cfg: dict) -> bool:
    """Whether the regressor sees the indentation strain ``u_w,n / h`` (module docstring): ``model.indentation_strain``
    for models with the linear force estimate (it reads the same ``u_w``), else False."""
    return bool(model_cfg.get("indentation_strain", False)) and linear_force_radius_of(model_cfg) > 0


def state_options(model_cfg: dict) -> dict:
    """The keyword arguments of :func:`fit_force_model` that a model config sets about the state features."""
    return {"force_scaling": force_scaling_of(model_cfg), "linear_force_radius_mm": linear_force_radius_of(model_cfg),
            "indentation_strain": indentation_strain_of(model_cfg)}


#: entries of an arrays dict that are not per-case columns (passed through by :func:`subset`)
PER_RUN_KEYS = ("surface_meshes",)


def subset(arrays: dict, idx: np.ndarray) -> dict:
    """Rows ``idx`` of every entry of an input-contract dict (lists stay lists; :data:`PER_RUN_KEYS` as they are)."""
    idx = np.asarray(idx)
    out = {}
    for k, v in arrays.items():
        if k in PER_RUN_KEYS:
            out[k] = v
            continue
        out[k] = [v[i] for i in idx] if isinstance(v, list) else np.asarray(v)[idx]
    return out


@dataclass
class Prepared:
    """Per-case learning inputs of one set of cases.

    ``x_obs`` holds ``n_views`` observed feature matrices (the observation
    model drawn with different seeds), ``x_clean`` the un-corrupted features.
    """

    x_obs: np.ndarray  # (views, n, d)
    x_clean: np.ndarray  # (n, d)
    state: np.ndarray  # (n, m)
    y_local: np.ndarray  # (n, 3) N
    force: np.ndarray  # (n, 3) N, source frame
    R: np.ndarray  # (n, 3, 3)

    def rows(self, idx: np.ndarray) -> "Prepared":
        idx = np.asarray(idx)
        return Prepared(self.x_obs[:, idx], self.x_clean[idx], self.state[idx], self.y_local[idx],
                        self.force[idx], self.R[idx])


def view_seeds(seed: int, n_views: int) -> list[int]:
    """Observation seeds of the training views (stage ``observation.view``; :func:`eval_seed` is another stage)."""
    return [derive(seed, "observation.view", v) for v in range(n_views)]


def eval_seed(seed: int) -> int:
    """Observation seed used to evaluate on the test split (stage ``observation.eval``: no training view's)."""
    return derive(seed, "observation.eval")


def n_views_for(rep: Representation) -> int:
    """Observed views per training case: 2 when the observation model is stochastic, else 1; a camera model's
    ``camera.views`` (each view another camera pose, density, noise and tip noise)."""
    if rep.is_camera:
        return int(rep.camera.get("views", 2))
    return 2 if rep.stochastic else 1


def prepare(arrays: dict, rep: Representation, *, observation_seeds: list[int]) -> Prepared:
    """Features (one observed view per seed + clean), state vector and local targets of labelled cases.

    Use ``view_seeds(seed, n_views_for(rep))`` for training cases and
    ``[eval_seed(seed)]`` for the test split. The local frame is computed once
    (:func:`~liverforce.learn.frames.case_rotations`) and used by every view,
    the state vector and the targets.
    """
    R = case_rotations(arrays)
    views = [rep.features_of(arrays, observation_seed=s, R=R) for s in observation_seeds]
    x_clean = rep.features_of(arrays, clean=True, R=R) if rep.occludes else views[0]
    force = np.asarray(arrays["force_n"], dtype=np.float64)
    return Prepared(np.stack(views), x_clean, state_vector(rep.state_arrays(arrays), R=R), force_to_local(force, R),
                    force, R)


# --------------------------------------------------------------------------
# preprocessing: scalers + encoder
# --------------------------------------------------------------------------


def indentation_strain(u_w: np.ndarray, state: np.ndarray) -> np.ndarray:
    """``u_w,n / h`` ``(n, 1)``: the normal displacement under the tool (mm, local frame, negative into the liver)
    over the tissue thickness there (the state vector's ``tool_thickness_mm``)."""
    h = np.asarray(state, dtype=np.float64)[:, THICKNESS_COLUMN]
    bad = np.flatnonzero(~(h > 0))
    if bad.size:
        raise ValueError(f"the indentation strain needs a positive, finite tissue thickness under the tool "
                         f"(tool_thickness_mm); rows {bad[:5].tolist()} have {h[bad[:5]].tolist()} mm")
    return (np.asarray(u_w, dtype=np.float64)[:, 2] / h).reshape(-1, 1)


def _c1_ratio(state: np.ndarray | None, n: int, ref: float | None) -> np.ndarray:
    if ref is None:
        return np.ones((n, 1))
    return (np.asarray(state, dtype=np.float64)[:, MATERIAL_START] / ref).reshape(n, 1)


@dataclass
class Preprocessor:
    """Scalers and encoder fitted on one training set; maps features (+ state) to regressor inputs."""

    feature_scaler: Standardizer
    encoder: Encoder
    code_scaler: Standardizer
    state_scaler: Standardizer | None
    target_scaler: Standardizer
    stiffness_ref: float | None = None  # force_scaling: stiffness (first material constant's training mean, MPa)
    linear_force_weights: np.ndarray | None = None  # (g^2,) grid weights of u_w; None: no linear force estimate
    linear_force_tip: bool = False  # camera models: f_lin = C^-1 (tool tip displacement, the features' last 3)
    linear_force_ref: float | None = None  # force_scaling: linear: f_lin x C10 / linear_force_ref (MPa)
    indentation_strain: bool = False  # the state features end with u_w,n / h (after f_lin; module docstring)
    material_ref: float | None = None  # state-vector models, any force scaling: C10's training mean (MPa), the
    #                                    reference of material_factor (bundles before format 9: None)
    dent_force: bool = False  # camera models with the dent fit: the state features end with (amplitude / C_nn,
    #                           offset), the features' columns before the tip (liverforce.learn.camera.N_DENT)

    def inputs(self, x: np.ndarray, state: np.ndarray | None) -> np.ndarray:
        code = self.code_scaler.transform(self.encoder.encode(self.feature_scaler.transform(x)))
        if self.state_scaler is None:
            return code
        return np.hstack([code, self.state_scaler.transform(self.state_features(state, x))])

    def base_state_features(self, state: np.ndarray) -> np.ndarray:
        """The state vector with material constants as ratios ``c / c_1`` when force-scaled (same columns)."""
        if self.stiffness_ref is None:
            return np.asarray(state, dtype=np.float64)
        out = np.array(state, dtype=np.float64, copy=True)
        out[:, MATERIAL_START:] = out[:, MATERIAL_START:] / out[:, MATERIAL_START:MATERIAL_START + 1]
        return out

    def tool_displacement(self, x: np.ndarray) -> np.ndarray:
        """``u_w`` ``(n, 3)`` mm, local frame: the observed displacement under the tool (the tool tip's for a
        camera model) that the linear force estimate and the indentation strain read (module docstring)."""
        x = np.asarray(x, dtype=np.float64)
        if self.linear_force_tip:
            return x[:, -3:]
        w = self.linear_force_weights
        return x[:, :3 * w.size].reshape(len(x), 3, w.size) @ w

    def linear_force(self, x: np.ndarray, state: np.ndarray) -> np.ndarray:
        """``f_lin = C^-1 u_w`` ``(n, 3)`` N, local frame (module docstring), from features ``x`` and the state."""
        return self._linear_force(self.tool_displacement(x), state)

    def _linear_force(self, u_w: np.ndarray, state: np.ndarray) -> np.ndarray:
        f_ref = np.linalg.solve(compliance_matrices(state), u_w[:, :, None])[:, :, 0]
        return f_ref * self.linear_factor(state, len(u_w))

    def state_features(self, state: np.ndarray, x: np.ndarray | None = None) -> np.ndarray:
        """The state vector as the regressor sees it: :meth:`base_state_features`, then ``f_lin`` and the
        indentation strain ``u_w,n / h`` if used."""
        out = self.base_state_features(state)
        if self.n_linear_force == 0:
            return out
        if x is None:
            raise ValueError("this model's state features include the linear force estimate: pass the features x")
        u_w = self.tool_displacement(x)  # once: f_lin and the strain read the same u_w
        parts = [out, self._linear_force(u_w, state)]
        if self.indentation_strain:
            parts.append(indentation_strain(u_w, state))
        if self.dent_force:
            parts.append(self.dent_features(x, state))
        return np.hstack(parts)

    def dent_features(self, x: np.ndarray, state: np.ndarray) -> np.ndarray:
        """``(k amplitude / C_nn, offset)`` ``(n, 2)`` of a camera model's dent fit: its amplitude as a force (N;
        ``C_nn`` the probe's normal compliance at the reference material, ``k = C10 / C10_ref`` the case's
        stiffness relative to training, :meth:`material_factor`) and the plane's offset at the tool (mm)."""
        d = np.asarray(x, dtype=np.float64)[:, -3 - N_DENT:-3]
        c_nn = compliance_matrices(state)[:, 2, 2]
        return np.column_stack([d[:, 0] / c_nn * self.material_factor(state, len(d))[:, 0], d[:, 1]])

    @property
    def n_linear_force(self) -> int:
        return 0 if self.linear_force_weights is None and not self.linear_force_tip else 3

    @property
    def n_displacement_features(self) -> int:
        """State-feature columns after the material constants, read from the displacement: ``f_lin`` (3) and
        the indentation strain (1)."""
        return (self.n_linear_force + (1 if self.indentation_strain and self.n_linear_force else 0)
                + (N_DENT if self.dent_force else 0))

    @property
    def n_material(self) -> int | None:
        """Material constants in the state vector (None without the state vector)."""
        if self.state_scaler is None:
            return None
        return int(self.state_scaler.mean.size - MATERIAL_START - self.n_displacement_features)

    def stiffness(self, state: np.ndarray | None, n: int) -> np.ndarray:
        """Per-row factor the target is scaled by: ``k = c_1 / c_1,ref`` with ``force_scaling: stiffness``,
        else ones; shape ``(n, 1)``."""
        return _c1_ratio(state, n, self.stiffness_ref)

    def linear_factor(self, state: np.ndarray | None, n: int) -> np.ndarray:
        """Per-row factor of the linear force estimate: ``k = c_1 / c_1,ref`` with ``force_scaling: linear``,
        else ones; shape ``(n, 1)``."""
        return _c1_ratio(state, n, self.linear_force_ref)

    def material_factor(self, state: np.ndarray | None, n: int) -> np.ndarray:
        """The case's stiffness relative to training, ``k = c_1 / c_1,ref`` (``c_1,ref`` the training mean of
        the first constant, whatever the force scaling; ones without the state vector): what the interval
        widens by outside its calibration range. A bundle before format 9 has ``c_1,ref`` only when its force
        scaling set one (ones with none)."""
        ref = self.material_ref
        if ref is None:
            ref = self.stiffness_ref if self.stiffness_ref is not None else self.linear_force_ref
        return _c1_ratio(state, n, ref)

    @property
    def n_inputs(self) -> int:
        return self.encoder.code_size + (0 if self.state_scaler is None else self.state_scaler.mean.size)


def fit_preprocessor(
    prep: Prepared,
    rep: Representation,
    *,
    encoder: str,
    code_size: int,
    use_state: bool,
    seed: int,
    epochs: int,
    lr: float,
    batch_size: int,
    dae_input_noise: float = 0.1,
    on_epoch: EpochCallback | None = None,
    force_scaling: str = "none",
    linear_force_radius_mm: float = 0.0,
    indentation_strain: bool = False,
) -> Preprocessor:
    """Fit scalers (training rows only) and the encoder.

    ``linear_force_radius_mm > 0`` (needs ``use_state`` and displacement
    features) adds the linear force estimate ``C^-1 u_w`` to the state
    features, and ``indentation_strain`` then ``u_w,n / h`` (module docstring).

    PCA and AE learn the observed features (all views); the DAE maps observed
    views to the clean features (same scaler for input and target).
    ``force_scaling="stiffness"`` (needs ``use_state``) learns the force
    divided by the stiffness factor; ``"linear"`` scales the linear force
    estimate by it (module docstring; without a linear force estimate
    ``linear`` is ``none``).
    """
    v, n, d = prep.x_obs.shape
    x_in = prep.x_obs.reshape(v * n, d)
    fs = Standardizer.fit(x_in, groups=rep.channel_groups())
    xs = fs.transform(x_in)
    if encoder == "pca":
        enc: Encoder = PCAEncoder.fit(xs, code_size)
    elif encoder in ("ae", "dae"):
        target = xs if encoder == "ae" else fs.transform(np.tile(prep.x_clean, (v, 1)))
        enc = AutoEncoder.fit(
            xs, target, code_size, kind=encoder, epochs=epochs, lr=lr, batch_size=batch_size, seed=seed,
            input_noise=dae_input_noise if encoder == "dae" else 0.0, on_epoch=on_epoch,
        )
    else:
        raise ValueError(f"unknown encoder '{encoder}': use pca, ae or dae")
    cs = Standardizer.fit(enc.encode(xs))
    if force_scaling not in FORCE_SCALINGS:
        raise ValueError(f"unknown force_scaling '{force_scaling}': use one of {FORCE_SCALINGS}")
    ref = None  # C10's training mean: the force scaling's reference and, whatever the scaling, the interval's
    if use_state:
        c1 = prep.state[:, MATERIAL_START]
        ref = float(c1.mean()) if np.all(c1 > 0) else None
    if force_scaling != "none":
        if not use_state:
            raise ValueError(f"force_scaling: {force_scaling} needs the state vector (the material constants)")
        if ref is None:
            raise ValueError(f"force_scaling: {force_scaling} needs a positive first material constant (C10); the "
                             f"training cases have {float(c1.min()):.4g} MPa")
    pre = Preprocessor(fs, enc, cs, None, Standardizer.fit(prep.y_local), ref if force_scaling == "stiffness" else None,
                       linear_force_ref=ref if force_scaling == "linear" else None, material_ref=ref)
    if linear_force_radius_mm > 0:
        if not use_state or rep.features == "deformed":
            raise ValueError("the linear force estimate needs the state vector (the probe compliance) and "
                             "displacement features (roi_features: displacement, both or cloud)")
        if rep.is_camera:
            pre.linear_force_tip = True
            pre.dent_force = rep.dent
        else:
            pre.linear_force_weights = linear_force_weights(rep, linear_force_radius_mm)
    if indentation_strain:
        if pre.n_linear_force == 0:
            raise ValueError("the indentation strain reads the linear force estimate's u_w: it needs "
                             "model.probe_force_radius_mm > 0, the state vector and displacement features")
        pre.indentation_strain = True
    if use_state:
        pre.state_scaler = Standardizer.fit(np.vstack([pre.state_features(prep.state, xv) for xv in prep.x_obs]))
    pre.target_scaler = Standardizer.fit(prep.y_local / pre.stiffness(prep.state, len(prep.state)))
    return pre


def view_groups(prep: Prepared) -> np.ndarray:
    """The case index of each row of ``regressor_data(pre, prep)`` (all views stacked, view by view): rows with
    the same index are views of one case (the GP fits its hyper-parameters on one of them,
    :func:`liverforce.learn.gp.fit_gp`)."""
    return np.tile(np.arange(len(prep.y_local)), len(prep.x_obs))


def regressor_data(pre: Preprocessor, prep: Prepared, *, all_views: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Scaled regressor inputs and targets; ``all_views`` stacks every observed view (augmentation)."""
    views = prep.x_obs if all_views else prep.x_obs[:1]
    z = np.vstack([pre.inputs(x, prep.state) for x in views])
    y_scaled = prep.y_local / pre.stiffness(prep.state, len(prep.state))
    y = np.tile(pre.target_scaler.transform(y_scaled), (len(views), 1))
    return z, y


# --------------------------------------------------------------------------
# the fitted model
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class Forward:
    """What :meth:`ForceModel.forward` computed for a set of cases."""

    R: np.ndarray  # (n, 3, 3) local rotations, rows t1, t2, n
    force_local: np.ndarray  # (n, 3) N, (F.t1, F.t2, F.n)
    stiffness: np.ndarray  # (n, 1) the case's stiffness factor k = c_1 / c_1,ref (ones without force scaling)
    spread_local: np.ndarray | None = None  # (n, 3) N: the sd of a GP ensemble's members' local forces (ddof 1;
    # the interval's spread, liverforce.learn.interval); None for one GP or an MLP
    input_distance: np.ndarray | None = None  # (n,): a GP's inputs' distance to its nearest training row, in its
    # length scales (the members' mean; liverforce.learn.interval, the input-distance flag); None for an MLP

    @property
    def force_source(self) -> np.ndarray:
        """The force ``(n, 3)`` N in each case's source frame, ``F = R^T f``."""
        return force_to_source(self.force_local, self.R)


class ForceModel:
    """A fitted force estimator (see the module docstring for the pipeline and bundle format)."""

    def __init__(
        self,
        representation: Representation,
        preprocessor: Preprocessor,
        regressor_spec: RegressorSpec,
        regressor: torch.nn.Module,
        meta: dict | None = None,
    ):
        self.representation = representation
        self.pre = preprocessor
        self.regressor_spec = regressor_spec
        self.regressor = regressor.eval()
        self.meta = dict(meta or {})

    @property
    def uses_state(self) -> bool:
        return self.pre.state_scaler is not None

    def observed_with(self, camera: dict) -> "ForceModel":
        """This fitted model observing simulated cases with other camera settings (``Representation.camera``;
        a camera-cloud model only): what it gives under another camera or tool tracker, nothing refitted
        (the validation's camera sensitivity; the scenarios' accuracy with an exact tool tip)."""
        if not self.representation.is_camera:
            raise ValueError("observed_with: not a camera-cloud model (roi_features: cloud)")
        rep = dataclasses.replace(self.representation, camera=camera)
        return ForceModel(rep, self.pre, self.regressor_spec, self.regressor, self.meta)

    def required_inputs(self) -> tuple[str, ...]:
        """Input-contract keys that :meth:`predict` reads."""
        keys = list(ROI_INPUTS)
        if self.uses_state:
            keys += [k for k in STATE_INPUTS if k not in keys]
        if self.representation.is_camera:  # the camera cloud and tool tip are checked by liverforce.learn.camera
            keys = [k for k in keys if k not in ("roi_deformed_mm", "roi_centroid_deformed_mm")]
        if self.representation.uses_triangles:
            keys.append(ROI_TRIANGLES_KEY)
        return tuple(keys)

    def forward(self, arrays: dict, observation_seed: int | None = None, *,
                rotations: np.ndarray | None = None) -> "Forward":
        """The one forward path of a set of cases: local frame, features, state, inputs, local force.

        Every prediction (:meth:`predict`, :meth:`predict_local`,
        :meth:`predict_interval`) goes through here, so the local frame of each
        case is computed once per call and shared by the features, the state
        vector and the force back in the source frame.

        Parameters
        ----------
        arrays : dict
            Input-contract arrays (``required_inputs()``).
        observation_seed : int, optional
            As in :meth:`predict`.
        rotations : (n, 3, 3) array, optional
            The cases' local rotations when the caller already holds them
            (serving: ``Preop.rotation``; :func:`~liverforce.learn.frames.case_rotations`
            of the same arrays); computed here otherwise.
        """
        missing = [k for k in self.required_inputs() if k not in arrays]
        if missing:
            raise KeyError(f"ForceModel.predict needs the inputs {missing}")
        if rotations is None:
            R = case_rotations(arrays)
        else:
            R = np.asarray(rotations, dtype=np.float64)
            n = len(arrays["exertion_point_mm"])
            if R.shape != (n, 3, 3):
                raise ValueError(f"rotations: expected one 3 x 3 rotation per case, shape ({n}, 3, 3); got {R.shape}")
        x = self.representation.features_of(arrays, observation_seed=observation_seed, R=R)
        s = state_vector(self.representation.state_arrays(arrays), R=R) if self.uses_state else None
        z = self.pre.inputs(x, s)
        k = self.pre.stiffness(s, len(z))
        ts = self.pre.target_scaler
        if self.member_spread:
            self.regressor.eval()
            with torch.no_grad():
                each = self.regressor.forward_members(as_tensor(z)).double()  # float32 inputs, as predict_regressor
                mean = each.mean(0).numpy()  # what predict_regressor gives (GPEnsemble.forward): the same bits
            f_local = ts.inverse_transform(mean) * k
            spread = np.std(ts.inverse_transform(each.numpy()) * k, axis=0, ddof=1)
        else:
            f_local = ts.inverse_transform(predict_regressor(self.regressor, z)) * k
            spread = None
        dist = self.regressor.nearest_distance(np.float32(z)) if self.is_gp else None  # the float32 inputs it reads
        return Forward(R, f_local, self.pre.material_factor(s, len(z)), spread, dist)

    @property
    def is_gp(self) -> bool:
        """Whether the regressor is a GP (one or an ensemble): it has training rows to measure a case against."""
        return isinstance(self.regressor, (GPRegressor, GPEnsemble))

    def input_distances(self, arrays: dict, observation_seed: int | None = None, *,
                        rotations: np.ndarray | None = None) -> np.ndarray | None:
        """:attr:`Forward.input_distance` of ``arrays``' cases without the force: the features, the state and the GP
        inputs only (the compiled node path's rows, whose forces come from elsewhere). None for an MLP."""
        if not self.is_gp:
            return None
        R = case_rotations(arrays) if rotations is None else np.asarray(rotations, dtype=np.float64)
        x = self.representation.features_of(arrays, observation_seed=observation_seed, R=R)
        s = state_vector(self.representation.state_arrays(arrays), R=R) if self.uses_state else None
        return self.regressor.nearest_distance(np.float32(self.pre.inputs(x, s)))

    def predict_local(self, arrays: dict, observation_seed: int | None = None) -> np.ndarray:
        """Force in the local frame ``(n, 3)`` N (``F.t1, F.t2, F.n``)."""
        return self.forward(arrays, observation_seed).force_local

    @property
    def member_spread(self) -> bool:
        """Whether the regressor is a GP ensemble of two or more members, whose disagreement :meth:`forward` gives
        (``Forward.spread_local``) and an interval with ``spread_beta`` reads; one GP, an ensemble of one member
        and an MLP have none."""
        return isinstance(self.regressor, GPEnsemble) and len(self.regressor.members) > 1

    @property
    def interval(self):
        """The calibrated interval (:class:`liverforce.learn.interval.ConformalInterval`), or None.

        :class:`ModelFormatError` for an interval scaled by the GP ensemble members' spread (``spread_beta``) on a
        regressor without members' spread (:attr:`member_spread`, a bundle edited or put together by hand): no path
        can give its widths, and every one that would says so here."""
        from liverforce.learn.interval import ConformalInterval

        d = self.meta.get("interval")
        if not d:
            return None
        ci = ConformalInterval.from_dict(d)
        if ci.uses_distance and not self.is_gp:
            raise ModelFormatError(
                f"the model's interval (meta.interval) has far widths, which read each case's distance to the GP's "
                f"training rows, but its regressor is {type(self.regressor).__name__}, which has none: its widths "
                "cannot be computed. Use the bundle as it was trained, or retrain it")
        if ci.uses_spread and not self.member_spread:
            reg = self.regressor
            what = ("a GP ensemble of one member" if isinstance(reg, GPEnsemble)
                    else "one GP" if isinstance(reg, GPRegressor) else "an MLP")
            raise ModelFormatError(
                f"the model's interval (meta.interval) is scaled by the spread of a GP ensemble's members "
                f"(spread_beta {ci.spread_beta:g}), but its regressor is {what}, which has no members' spread: its "
                "widths cannot be computed. Use the bundle as it was trained, or retrain it (such an interval is "
                "calibrated on a GP ensemble of two or more code sizes, model.gp.code_members; "
                "train.interval.spread: null for one without)")
        return ci

    @property
    def distance_flag(self) -> dict | None:
        """The input-distance flag fitted with the model (``meta["input_distance"]``:
        :func:`liverforce.learn.interval.fit_input_distance`), or None (an MLP, a bundle before it, a model trained
        without ``train.interval.distance_quantile``)."""
        rec = self.meta.get("input_distance")
        return rec if rec and self.is_gp else None

    def predict_interval(self, arrays: dict, observation_seed: int | None = None, *,
                         rotations: np.ndarray | None = None) -> dict:
        """Force with its calibrated interval per local component.

        Returns ``force_n`` ``(n, 3)`` (source frame), ``force_local_n`` ``(n, 3)``
        (``F.t1, F.t2, F.n``), ``half_width_local_n`` ``(n, 3)`` (the interval is
        ``force_local_n +- half_width_local_n``), ``coverage`` (nominal),
        ``frame`` ``(n, 3, 3)`` (rows t1, t2, n) and ``input_distance`` ``(n,)`` (a GP's,
        :attr:`Forward.input_distance`; None for an MLP). A model without a calibrated
        interval raises ``ValueError``. ``rotations`` as in :meth:`forward`.
        """
        ci = self.interval
        if ci is None:
            raise ValueError("this model has no calibrated interval (trained without train.interval)")
        fw = self.forward(arrays, observation_seed, rotations=rotations)
        half = ci.half_widths(fw.stiffness, fw.force_local, fw.spread_local, fw.input_distance)
        return {"force_n": fw.force_source, "force_local_n": fw.force_local, "half_width_local_n": half,
                "coverage": ci.coverage, "frame": fw.R, "input_distance": fw.input_distance}

    def predict(self, arrays: dict, observation_seed: int | None = None, *,
                rotations: np.ndarray | None = None) -> np.ndarray:
        """Tool force ``(n, 3)`` in N, in each case's source frame.

        Parameters
        ----------
        arrays : dict
            Input-contract arrays (``required_inputs()``; no labels needed).
        observation_seed : int, optional
            Draw the stochastic observation model (tool occlusion in ``noise``
            mode, point noise) with this seed, to evaluate on simulated data as
            the model was trained. ``None`` for real observations (already
            noisy); deterministic ``remove`` occlusion always applies.
        rotations : (n, 3, 3) array, optional
            The cases' local rotations, if the caller holds them already (:meth:`forward`).
        """
        return self.forward(arrays, observation_seed, rotations=rotations).force_source

    # ------------------------------------------------------------------
    def save(self, path: str | Path) -> Path:
        """Write the bundle directory ``path`` atomically (temp dir, then rename)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
        try:
            enc = self.pre.encoder
            doc = {
                "format": FORMAT,
                "format_version": FORMAT_VERSION,
                "representation": self.representation.to_dict(),
                "encoder": enc.spec(),
                "regressor": self.regressor_spec.to_dict(),
                "scalers": {
                    "feature": self.pre.feature_scaler.to_dict(),
                    "code": self.pre.code_scaler.to_dict(),
                    "state": None if self.pre.state_scaler is None else self.pre.state_scaler.to_dict(),
                    "target": self.pre.target_scaler.to_dict(),
                    "stiffness_ref": self.pre.stiffness_ref,
                    "linear_force_weights": None if self.pre.linear_force_weights is None
                    else [float(v) for v in self.pre.linear_force_weights],
                    "linear_force_tip": bool(self.pre.linear_force_tip),
                    "linear_force_ref": self.pre.linear_force_ref,
                    "indentation_strain": bool(self.pre.indentation_strain),
                    "material_ref": self.pre.material_ref,
                    "dent_force": bool(self.pre.dent_force),
                },
                "meta": self.meta,
            }
            (tmp / "model.json").write_text(json.dumps(doc, indent=1, sort_keys=True))
            torch.save(self.regressor.state_dict(), tmp / "regressor.pt")
            if isinstance(enc, PCAEncoder):
                np.savez(tmp / "pca.npz", **enc.arrays())
            else:
                torch.save(enc.net.state_dict(), tmp / "encoder.pt")
            if path.exists():
                shutil.rmtree(path)
            os.replace(tmp, path)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return path

    @classmethod
    def load(cls, path: str | Path) -> "ForceModel":
        """Load a bundle written by :meth:`save` (no arbitrary code is unpickled)."""
        path = Path(path)
        meta_file = path / "model.json"
        if not meta_file.is_file():
            raise ModelFormatError(f"{path} is not a liverforce model directory (no model.json)")
        doc = json.loads(meta_file.read_text())
        if doc.get("format") != FORMAT:
            raise ModelFormatError(f"{meta_file}: format '{doc.get('format')}' is not '{FORMAT}'")
        if doc.get("format_version") not in READ_VERSIONS:
            raise ModelFormatError(
                f"{meta_file}: model format version {doc.get('format_version')} is not supported by this "
                f"liverforce (reads {', '.join(map(str, READ_VERSIONS))}); retrain the model or use the "
                "liverforce version that wrote it"
            )
        espec = doc["encoder"]
        if espec["kind"] == "pca":
            with np.load(path / "pca.npz", allow_pickle=False) as z:
                enc: Encoder = PCAEncoder(z["mean"], z["components"])
        else:
            enc = AutoEncoder.from_state(espec, torch.load(path / "encoder.pt", weights_only=True))
        sc = doc["scalers"]
        pre = Preprocessor(
            Standardizer.from_dict(sc["feature"]),
            enc,
            Standardizer.from_dict(sc["code"]),
            None if sc["state"] is None else Standardizer.from_dict(sc["state"]),
            Standardizer.from_dict(sc["target"]),
            sc.get("stiffness_ref"),
            None if sc.get("linear_force_weights") is None else np.asarray(sc["linear_force_weights"], np.float64),
            bool(sc.get("linear_force_tip", False)),
            sc.get("linear_force_ref"),
            bool(sc.get("indentation_strain", False)),
            sc.get("material_ref"),
            bool(sc.get("dent_force", False)),
        )
        rspec = RegressorSpec.from_dict(doc["regressor"])
        net = load_regressor(rspec, torch.load(path / "regressor.pt", weights_only=True))
        rdoc = doc["representation"]
        if doc["format_version"] < 7 and rdoc.get("camera") is not None:
            # written before the patch reference: its camera features were read over the ROI points' interpolant
            cam = dict(rdoc["camera"])
            cam["grid"] = {"reference": "points", **(cam.get("grid") or {})}
            rdoc = {**rdoc, "camera": cam}
        return cls(Representation.from_dict(rdoc), pre, rspec, net, doc.get("meta"))


def outside_training_range(model: "ForceModel", arrays: dict) -> tuple[np.ndarray, dict[str, np.ndarray]] | None:
    """Which rows of ``arrays`` lie outside the model's training range of the geometric state:
    ``(any input outside (n,) bool, masks by input)`` (:func:`liverforce.learn.state.outside_ranges` against
    ``meta["training_scale"]``). None for a model without the state vector or without recorded ranges:
    nothing to compare with (serving does not warn about it either). The IV test breakdown of training
    and the unseen-liver validation both count with it."""
    rec = (model.meta or {}).get("training_scale")
    if not model.uses_state or not rec:
        return None
    masks, _ = outside_ranges(arrays, recorded_ranges(rec))
    out = np.zeros(len(arrays["exertion_point_mm"]), dtype=bool)
    for v in masks.values():
        out |= v
    return out, masks


def training_distances(model: "ForceModel", prep: Prepared, prep_eval: Prepared, labels,
                       seed: int) -> np.ndarray | None:
    """Each training case's input distance (:attr:`Forward.input_distance`, its evaluation view ``prep_eval``) to
    the GP's training rows of other ``labels`` (one per case: its liver in IV, else the case itself, whose other
    views are then left out): what a case of a liver the model never saw is to it, in the served model's own
    space (the input-distance flag's training side, :mod:`liverforce.learn.interval`). ``prep``: the rows the
    model was fitted on (all views), ``seed`` its fit's (the GP's subset of rows). None for an MLP. RuntimeError
    when the GP's rows are not ``prep``'s (the labels could not be put on them)."""
    reg = model.regressor
    if not model.is_gp:
        return None
    z_all, _ = regressor_data(model.pre, prep)
    members = list(reg.members) if isinstance(reg, GPEnsemble) else [reg]
    cols = [reg.columns(i).numpy() for i in range(len(members))] if isinstance(reg, GPEnsemble) \
        else [np.arange(z_all.shape[1])]
    n_used = members[0].n_train
    rows = training_rows(len(z_all), seed, n_used)
    if not all(np.array_equal(m.X.numpy(), z_all[rows][:, c]) for m, c in zip(members, cols)):
        raise RuntimeError("training_distances: the GP's training rows are not the given training rows (another "
                           "seed, cap or data): the training side's distances cannot be measured")
    labels = np.asarray(labels).astype(str)
    z_eval, _ = regressor_data(model.pre, prep_eval, all_views=False)
    return reg.nearest_distance(np.float32(z_eval), groups=labels, row_groups=labels[view_groups(prep)][rows])


def training_scale(prep: Prepared, rep: Representation) -> dict:
    """Ranges of the training inputs, recorded in the bundle (``meta["training_scale"]``) for serving.

    Serving (:mod:`liverforce.serve`) refuses inputs far outside these ranges
    (e.g. a liver in metres or a material in Pa) instead of returning a
    silently wrong force. All from the training rows ``prep``:

    ``inertia_length_mm``
        ``[min, max]`` of ``(tr I / 2)^(1/5)`` (mm), a length that scales with
        the liver (``tr I = 2 V r_g^2`` for unit density).
    ``centroid_distance_mm``
        ``[min, max]`` of ``|c_liver - p|`` (mm).
    ``material_params_mpa``
        ``[[min...], [max...]]`` per constant (MPa).
    ``tool_thickness_mm``
        ``[min, max]`` of the tissue thickness under the tool (mm).
    ``probe_compliance_mm_per_n``
        ``[min, max]`` of the trace of the probe compliance (mm/N).
    ``feature_abs_max``
        Largest ``|feature|`` per representation channel (mm): displacement
        components and/or deformed height, as sampled on the grid.
    ``force_magnitude_n``
        ``[min, max]`` of ``|F|`` (N).
    """
    s = prep.state
    trace = s[:, 9] + s[:, 12] + s[:, 14]  # inertia xx + yy + zz (state.py column order)
    length = np.power(np.maximum(trace, 0.0) / 2.0, 0.2)
    dist = np.linalg.norm(s[:, 0:3], axis=1)
    mat = s[:, MATERIAL_START:]
    thick = s[:, THICKNESS_COLUMN]
    ctr = s[:, COMPLIANCE_COLUMNS][:, [0, 3, 5]].sum(axis=1)
    g2 = rep.grid_size**2
    x = np.abs(np.concatenate([prep.x_clean, *prep.x_obs], axis=0))
    feat_max = [float(x[:, c * g2:(c + 1) * g2].max()) for c in range(rep.channels)]
    fmag = np.linalg.norm(prep.force, axis=1)
    extra = {}
    if rep.is_camera:  # the camera checks of serving (liverforce.serve.cloud.camera_checks)
        xo = np.concatenate(list(prep.x_obs), axis=0)
        seen = xo[:, g2:2 * g2] > 0.5
        extra["camera"] = {
            "valid_fraction": [float(seen.mean(axis=1).min()), float(seen.mean(axis=1).max())],
            "height_abs_max_mm": float(np.abs(np.where(seen, xo[:, :g2], 0.0)).max()),
            "tip_displacement_max_mm": float(np.linalg.norm(xo[:, -3:], axis=1).max()),
        }
        feat_max = feat_max[:1]  # the mask channel is not a length
    return {**extra,
        "inertia_length_mm": [float(length.min()), float(length.max())],
        "centroid_distance_mm": [float(dist.min()), float(dist.max())],
        "material_params_mpa": [mat.min(axis=0).tolist(), mat.max(axis=0).tolist()],
        "tool_thickness_mm": [float(thick.min()), float(thick.max())],
        "probe_compliance_mm_per_n": [float(ctr.min()), float(ctr.max())],
        "feature_abs_max": feat_max,
        "force_magnitude_n": [float(fmag.min()), float(fmag.max())],
    }


def fit_force_model(
    prep: Prepared,
    rep: Representation,
    *,
    encoder: str,
    code_size: int,
    use_state: bool,
    hidden: list[int],
    dropout: float,
    fit: FitParams,
    seed: int,
    encoder_epochs: int | None = None,
    dae_input_noise: float = 0.1,
    monitor: tuple[Prepared, str] | None = None,
    on_epoch: EpochCallback | None = None,
    meta: dict | None = None,
    force_scaling: str = "none",
    linear_force_radius_mm: float = 0.0,
    indentation_strain: bool = False,
) -> tuple[ForceModel, dict[str, list[float]]]:
    """Fit preprocessing and regressor on ``prep`` (training rows) and bundle them.

    ``monitor=(prepared, name)`` records the eval-mode loss on another set
    per epoch under ``history["<name>_loss"]`` (monitoring only; nothing is
    selected on it).
    """
    members = fit.gp_code_members if fit.regressor == "gp" else ()
    pre = fit_preprocessor(
        prep, rep, encoder=encoder, code_size=encoder_code_size(code_size, members), use_state=use_state, seed=seed,
        epochs=encoder_epochs or fit.epochs, lr=fit.lr, batch_size=fit.batch_size, dae_input_noise=dae_input_noise,
        force_scaling=force_scaling, linear_force_radius_mm=linear_force_radius_mm,
        indentation_strain=indentation_strain,
    )
    z, y = regressor_data(pre, prep)
    zv = yv = None
    if monitor is not None:
        zv, yv = regressor_data(pre, monitor[0], all_views=False)
    gp = fit.regressor == "gp"
    spec = RegressorSpec(pre.n_inputs, () if gp else tuple(int(h) for h in hidden), 0.0 if gp else float(dropout),
                         kind=fit.regressor)
    net, hist = fit_regressor(z, y, spec, fit, seed=seed, z_val=zv, y_val=yv, on_epoch=on_epoch,
                              groups=view_groups(prep),
                              columns=member_columns(pre, members))
    if monitor is not None:
        hist[f"{monitor[1]}_loss"] = hist.pop("val_loss")
    else:
        hist.pop("val_loss")
    meta = dict(meta or {})
    if gp:
        meta["gp"] = hist.pop("gp")
        if members:
            meta["gp"]["code_members"] = member_sizes(pre, members)
    meta.setdefault("training_scale", training_scale(prep, rep))
    return ForceModel(rep, pre, spec, net, meta), hist
