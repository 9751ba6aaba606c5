"""ROI point cloud -> fixed-length, ordered feature vector (the encoder input).

A case's ROI is a variable-size point cloud (``k_i`` nodes, undeformed and
deformed, same node order). To compare cases across exertion points and
geometries it is

1. moved into the local frame at the exertion point (see
   :mod:`liverforce.learn.frames`): ``x_loc = R (x - p)``, so the tangent
   plane is ``(u, v) = (x_loc[0], x_loc[1])`` and ``x_loc[2]`` is the height
   along the outward normal;
2. passed through the observation model (occlusion by the tool, point noise;
   see below);
3. resampled onto a canonical ``g x g`` grid on the square
   ``[-h, h]^2`` of the tangent plane (``g = grid_size``, ``h =
   half_width_mm``) by piecewise-linear interpolation: with
   ``interpolation: surface`` (the shipped config) on the top sheet of the
   ROI patch's own triangles (``roi_triangles``;
   :func:`liverforce.learn.grid.interpolate_top_sheet`: a patch that wraps
   round a thin edge of the liver has the lobe's other face under the grid,
   whose nodes are left out); with ``points`` (bundles before format 8) on
   the Delaunay triangulation of the nodes' tangent coordinates (the
   interpolant of ``scipy.interpolate.LinearNDInterpolator``); nearest-node
   values outside the convex hull either way.

Features (``features`` setting)
-------------------------------
``displacement`` (default)
    The local displacement ``d = R (x_def - x_undef)`` (3 channels) sampled
    at the grid over the *undeformed* tangent coordinates: ``3 g^2`` values.
    Uses the node correspondence the simulation provides.
``deformed``
    The deformed surface height ``x_def,loc[2]`` over the *deformed* tangent
    coordinates (1 channel, ``g^2`` values): what a stereo camera sees, no
    node correspondence needed.
``both``
    The two concatenated (``4 g^2`` values).
``cloud``
    What a camera and the robot give, no node correspondence
    (:mod:`liverforce.learn.camera`): the camera cloud's normal height change
    over the pre-operative surface and its coverage mask on the grid, then the
    tool tip's displacement (``2 g^2 + 3`` values). The camera settings
    (``camera``) replace the occlusion and noise below, which do not apply.

Channel-major order: feature ``c * g^2 + i * g + j`` is channel ``c`` at
``(u_j, v_i)``, ``u_j = -h + 2 h j / (g - 1)``.

Rigid motion (``rigid_motion`` setting; displacement features only)
---------------------------------------------------------------------
``keep`` (default)
    The displacement as simulated or measured, including the ROI's rigid-body
    motion (the whole liver moving on its supports).
``remove``
    The rigid transform (rotation + translation, least squares, Kabsch) that
    best maps the undeformed ROI nodes at tangent distance
    ``>= rigid_motion_radius_mm`` from the exertion point (all nodes of the
    outer half when fewer than 10 are that far) onto their deformed positions
    is undone on every deformed ROI node (:func:`undo_rigid_motion`), before
    the observation model; the state vector's deformed ROI centroid is that of
    the corrected nodes (:meth:`Representation.state_arrays`). A rigid motion
    of the deformed ROI then leaves the features unchanged, and a pure
    indentation (far nodes at rest) is kept as is. On the default run (IV
    pca_sv, 5 splits; ``benchmarks/experiment_rigid_motion.py``) it cut the
    physics study's foundations x0.25 MAE 0.66 -> 0.51 N and kt/kn 0.1 0.34 ->
    0.29 N, left the rib choices as they were, changed the unseen-liver MAE
    by -0.009 +- 0.011 N and cost 0.6 +- 0.5 pp of IV test accuracy, so it is
    not the default.

Grid extent
-----------
``h`` is fitted on the training split (:func:`fit_half_width`): for each
case, the half-width of the largest square centred on the exertion point
inside the ROI's tangent-plane bounding box (``min(max u, -min u, max v,
-min v)``); ``h`` is the median over the training cases. A fixed physical
extent (mm) keeps a dent of given width the same size on the grid for every
case; cells outside a smaller ROI get nearest-node values. A positive
``grid_half_width_mm`` in the model config fixes ``h`` instead; the default
config fixes it at 20 mm (4 tool radii), which keeps the grid on the dent
rather than on the ROI's far edge (about 47 mm on the default livers): the
training-side CV MAE of scenario IV fell from 0.236 to 0.186 N
(``config/model/default.yaml``). The ``roi_fraction`` study fits ``h`` on each
point's ROI, so there the grid follows the ROI.

Observation model
-----------------
The tool hides the surface around the exertion point: nodes whose
*undeformed* tangent distance ``sqrt(u^2 + v^2)`` is below ``radius_mm`` (a
cylinder along the normal) are

- ``remove``: dropped before resampling, so grid values come from visible
  nodes only (deterministic; always applied unless ``clean=True``);
- ``noise``: given a random deformed position ``x_undef + N(0, s^2 I)`` with
  ``s = max(noise_mm, rms |d|_component)`` of the case (stochastic).

Point noise ``N(0, noise_mm^2)`` is added to every deformed coordinate in the
local frame (stochastic). Stochastic parts run only when an
``observation_seed`` is given; each case draws from its own generator seeded
by ``derive(observation_seed, "observation", case_id)`` (:mod:`liverforce.seeds`),
so the draw does not depend on the row order, and because it is drawn in the
local frame a rigid motion of the input leaves the features unchanged.

Notes
-----
With ``interpolation: points`` the projection onto the tangent plane
assumes the ROI is a height field over that plane (no fold-over); the 18 %
ROIs of the default livers often are not (they wrap round thin edges), which
``surface`` handles. Delaunay triangulations are unique for points in general
position, and the top sheet follows the triangles, so permuting the node
order gives the same features (to rounding).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from liverforce.learn import names
from liverforce.learn.frames import case_rotations, points_to_local
from liverforce.learn.grid import check_triangles, interpolate_to_grid, interpolate_top_sheet, top_sheet_nodes
from liverforce.seeds import derive

FEATURE_KINDS = names.roi_features()
OCCLUSION_MODES = names.OCCLUSION_MODES
INTERPOLATIONS = ("surface", "points")
#: input-contract key of each row's place in a request (whole numbers): without ``case_id`` it keys the row's
#: observation draw (and names the row in messages) instead of its index in the arrays, so that a row of a
#: request draws the same whatever other rows are left out before it (:func:`liverforce.learn.model.subset`
#: carries it; the served model sets it, ``Predictor.predict_arrays`` too where neither is given)
ROW_KEY = "request_row"


@dataclass(frozen=True)
class Representation:
    """Settings of the ROI -> grid resampling (JSON-serialisable).

    Parameters
    ----------
    grid_size : int
        Grid points per side ``g`` (>= 3).
    half_width_mm : float
        Half the grid's side ``h`` in mm (> 0).
    features : str
        ``displacement``, ``deformed`` or ``both`` (module docstring).
    occlusion_radius_mm : float
        Tool occlusion radius (0 = none), mm.
    occlusion_mode : str
        ``remove`` or ``noise``.
    noise_mm : float
        Standard deviation of Gaussian point noise, mm.
    camera : dict, optional
        ``cloud`` features only: ``observation`` (ObservationConfig fields),
        ``grid`` (CloudGridSpec fields), ``tip_noise_mm`` and
        ``tip_noise_normal_mm`` (:mod:`liverforce.learn.camera`).
    rigid_motion : str
        ``keep`` or ``remove`` (module docstring; ``displacement`` and
        ``both`` features only).
    rigid_motion_radius_mm : float
        ``remove``: the rigid motion is fitted to the ROI nodes at least this
        far (tangent distance, mm) from the exertion point.
    interpolation : str
        How node displacements reach the grid (``displacement`` and ``both``
        features): ``surface``, the top sheet of the ROI patch's own triangles
        (``roi_triangles``; :func:`liverforce.learn.grid.interpolate_top_sheet`),
        so an ROI that wraps round a thin edge of the liver does not mix the
        lobe's two faces; ``points`` (the default here, and what bundles before
        format 7 did), the Delaunay interpolant of the nodes in the tangent
        plane. The ``deformed`` height channel is the points' interpolant
        either way (a cloud can stand in for its nodes).
    """

    grid_size: int
    half_width_mm: float
    features: str = "displacement"
    occlusion_radius_mm: float = 0.0
    occlusion_mode: str = "remove"
    noise_mm: float = 0.0
    camera: dict | None = None
    rigid_motion: str = "keep"
    rigid_motion_radius_mm: float = 15.0
    interpolation: str = "points"

    def __post_init__(self) -> None:
        if int(self.grid_size) < 3:
            raise ValueError(f"grid_size must be >= 3 (got {self.grid_size})")
        if not float(self.half_width_mm) > 0:
            raise ValueError(f"grid half width must be > 0 mm (got {self.half_width_mm})")
        if self.features not in names.ROI_FEATURE_CHANNELS:
            raise ValueError(f"unknown ROI features '{self.features}': use one of {names.roi_features()}")
        if self.occlusion_mode not in names.OCCLUSION_MODES:
            raise ValueError(f"unknown occlusion mode '{self.occlusion_mode}': use one of {names.OCCLUSION_MODES}")
        if self.occlusion_radius_mm < 0 or self.noise_mm < 0:
            raise ValueError("occlusion radius_mm and noise_mm must be >= 0 mm")
        if self.rigid_motion not in RIGID_MOTION_MODES:
            raise ValueError(f"unknown rigid_motion '{self.rigid_motion}': use one of {RIGID_MOTION_MODES}")
        if self.removes_rigid_motion and self.features not in ("displacement", "both"):
            raise ValueError(f"rigid_motion: remove needs node displacements (roi_features: displacement or both), "
                             f"not '{self.features}'")
        if not float(self.rigid_motion_radius_mm) >= 0:
            raise ValueError(f"rigid_motion_radius_mm must be >= 0 mm (got {self.rigid_motion_radius_mm})")
        if self.interpolation not in INTERPOLATIONS:
            raise ValueError(f"unknown interpolation '{self.interpolation}': use one of {INTERPOLATIONS}")
        if self.is_camera:
            if self.occlusion_radius_mm > 0 or self.noise_mm > 0:
                raise ValueError("roi_features: cloud models observe the surface with the camera model "
                                 "(model.camera: tool, noise, density); model.occlusion.radius_mm and "
                                 "model.noise_mm must be 0 for them")
            object.__setattr__(self, "camera", dict(self.camera or {}))
        elif self.camera:
            raise ValueError(f"camera settings apply to roi_features: cloud only (got '{self.features}')")
        else:
            object.__setattr__(self, "camera", None)

    # ------------------------------------------------------------------
    @property
    def channels(self) -> int:
        """Number of grid channels (3, 1 or 4)."""
        return names.ROI_FEATURE_CHANNELS[self.features]

    @property
    def uses_triangles(self) -> bool:
        """True if the features read the ROI patch's triangles (``roi_triangles``): node displacements on the
        patch's top sheet, or a camera model's patch reference."""
        if self.is_camera:
            return self.camera_reference == "surface"
        return self.interpolation == "surface" and self.features in ("displacement", "both")

    @property
    def removes_rigid_motion(self) -> bool:
        """True if the ROI's best rigid motion is taken out of the displacement (``rigid_motion: remove``)."""
        return self.rigid_motion == "remove"

    @property
    def is_camera(self) -> bool:
        """True for features a camera and the robot give (no node correspondence)."""
        return self.features in names.CAMERA_FEATURES

    @property
    def camera_reference(self) -> str | None:
        """A camera model's pre-operative height reference (``surface``: the ROI patch's triangles, needs
        ``roi_triangles``; ``points``: the ROI points), None for other features
        (:class:`liverforce.learn.cloud_features.CloudGridSpec`)."""
        if not self.is_camera:
            return None
        from liverforce.learn.cloud_features import CloudGridSpec

        return str((self.camera.get("grid") or {}).get("reference", CloudGridSpec.reference))

    @property
    def dent(self) -> bool:
        """A camera model whose features hold the dent fit round the tool (``camera.grid.dent_radius_mm > 0``)."""
        return self.is_camera and float((self.camera.get("grid") or {}).get("dent_radius_mm") or 0.0) > 0

    @property
    def n_features(self) -> int:
        """Length of the feature vector, ``channels * g^2`` (``+ 3``, the tool tip, for ``cloud``)."""
        if self.is_camera:
            from liverforce.learn import camera

            return camera.n_features(self.grid_size, self.dent)
        return self.channels * self.grid_size**2

    @property
    def stochastic(self) -> bool:
        """True if an observation seed changes the features (noise of any kind, a camera's pose)."""
        return self.is_camera or self.noise_mm > 0 or (self.occlusion_radius_mm > 0 and self.occlusion_mode == "noise")

    @property
    def occludes(self) -> bool:
        """True if the observation model differs from the clean ROI at all (camera models: no clean ROI)."""
        return not self.is_camera and (self.noise_mm > 0 or self.occlusion_radius_mm > 0)

    def channel_groups(self) -> np.ndarray:
        """Channel index of every feature, ``(n_features,)`` int (for per-channel scaling)."""
        if self.is_camera:
            from liverforce.learn import camera

            return camera.channel_groups(self.grid_size, self.dent)
        return np.repeat(np.arange(self.channels), self.grid_size**2)

    def state_arrays(self, arrays: dict) -> dict:
        """The arrays the state vector is built from: a camera model has no deformed ROI centroid (it needs
        node correspondence), so its column repeats the undeformed one and carries nothing. Nor does it under
        an observation model (occlusion or noise): the stored centroid is the mean of every clean ROI node,
        information the occluded, noisy view does not have (the observed features carry the mean motion).
        With ``rigid_motion: remove`` the deformed ROI centroid is that of the rigid-motion-free ROI."""
        out = dict(arrays)
        if self.is_camera or self.occludes:
            out["roi_centroid_deformed_mm"] = arrays["roi_centroid_undeformed_mm"]
        elif self.removes_rigid_motion:
            out["roi_centroid_deformed_mm"] = np.array(
                [d.mean(axis=0) for d in self.rigid_free_deformed(arrays)]).reshape(-1, 3)
        else:
            return arrays
        return out

    def rigid_free_deformed(self, arrays: dict, R: np.ndarray | None = None) -> list[np.ndarray]:
        """Every case's deformed ROI ``(k_i, 3)`` (source frame, float64) with the far nodes' best rigid motion
        undone (:func:`undo_rigid_motion`); ``R``: the cases' rotations if already computed."""
        R = case_rotations(arrays) if R is None else R
        P = np.asarray(arrays["exertion_point_mm"], dtype=np.float64)
        out = []
        for i in range(len(P)):
            U = np.asarray(arrays["roi_undeformed_mm"][i], dtype=np.float64).reshape(-1, 3)
            D = np.asarray(arrays["roi_deformed_mm"][i], dtype=np.float64).reshape(-1, 3)
            far = rigid_fit_nodes(points_to_local(U, P[i], R[i]), self.rigid_motion_radius_mm)
            out.append(undo_rigid_motion(U, D, far))
        return out

    def grid(self) -> np.ndarray:
        """Tangent-plane grid points ``(g^2, 2)`` mm, row-major in ``v`` then ``u``."""
        s = np.linspace(-self.half_width_mm, self.half_width_mm, self.grid_size)
        uu, vv = np.meshgrid(s, s)  # uu[i, j] = s[j], vv[i, j] = s[i]
        return np.column_stack([uu.ravel(), vv.ravel()])

    def to_dict(self) -> dict:
        return {k: (float(v) if isinstance(v, float) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> "Representation":
        return cls(**d)

    # ------------------------------------------------------------------
    def features_of(
        self,
        arrays: dict,
        *,
        observation_seed: int | None = None,
        clean: bool = False,
        R: np.ndarray | None = None,
    ) -> np.ndarray:
        """Feature matrix ``(n, n_features)`` float64 for the cases in ``arrays``.

        Parameters
        ----------
        arrays : dict
            Needs ``exertion_point_mm``, ``frame_normal``, ``frame_t1``,
            ``frame_t2`` (n, 3) and ``roi_undeformed_mm``,
            ``roi_deformed_mm`` (lists of ``(k_i, 3)``); ``case_id`` seeds the
            per-case noise when present (else the row's :data:`ROW_KEY`, else
            the row index).
        observation_seed : int, optional
            Seed of the stochastic observation model (occlusion mode
            ``noise``, point noise). ``None``: no stochastic corruption.
        clean : bool
            Ignore the observation model entirely (no occlusion, no noise):
            the denoising autoencoder's target.
        R : (n, 3, 3) array, optional
            The cases' local rotations, when already computed
            (:func:`liverforce.learn.frames.case_rotations` of the same
            arrays); computed here otherwise.
        """
        if self.is_camera:
            from liverforce.learn import camera

            return camera.camera_features(arrays, self.camera, self.grid_size, self.half_width_mm,
                                          None if clean else observation_seed, R=R)
        R = case_rotations(arrays) if R is None else R
        P = np.asarray(arrays["exertion_point_mm"], dtype=np.float64)
        und, dfm = arrays["roi_undeformed_mm"], arrays["roi_deformed_mm"]
        n = len(P)
        if len(und) != n or len(dfm) != n:
            raise ValueError(
                f"roi_undeformed_mm ({len(und)}) and roi_deformed_mm ({len(dfm)}) need one point cloud per case ({n})"
            )
        ids = arrays.get("case_id")
        rows = arrays.get(ROW_KEY) if ids is None else None  # each row's place in the request, without case_id
        tris = None
        if self.uses_triangles:
            tris = arrays.get("roi_triangles")
            if tris is None or len(tris) != n:
                raise KeyError(
                    "roi_triangles: this model resamples node displacements on the top sheet of the ROI patch's "
                    "triangles (model.interpolation: surface) and needs them per case (shards of schema 1.4, "
                    "Preop.from_surface, a context's roi_triangles)")
        out = np.empty((n, self.n_features))
        grid = self.grid()
        for i in range(n):
            U = points_to_local(np.asarray(und[i]).reshape(-1, 3), P[i], R[i])
            D = points_to_local(np.asarray(dfm[i]).reshape(-1, 3), P[i], R[i])
            if U.shape == D.shape and self.removes_rigid_motion:  # the same fit as the state's centroid
                D = points_to_local(undo_rigid_motion(np.asarray(und[i], dtype=np.float64).reshape(-1, 3),
                                                      np.asarray(dfm[i], dtype=np.float64).reshape(-1, 3),
                                                      rigid_fit_nodes(U, self.rigid_motion_radius_mm)), P[i], R[i])
            if U.shape != D.shape:
                raise ValueError(
                    f"case row {i}: undeformed ROI has {len(U)} nodes but deformed has {len(D)}; "
                    "they must list the same nodes in the same order"
                )
            row = i if rows is None else int(rows[i])
            label = str(ids[i]) if ids is not None else f"row {row}"
            patch = None
            if tris is not None:  # the top sheet's nodes are chosen on the whole patch, before any occlusion
                T = check_triangles(tris[i], len(U), f"case {label}: roi_triangles")
                patch = (T, top_sheet_nodes(U, T))
            if not clean:
                rng = None
                if observation_seed is not None and self.stochastic:
                    key = ids[i] if ids is not None else row
                    rng = np.random.default_rng(derive(observation_seed, "observation", key))
                U, D, patch = self._observe(U, D, rng, label, patch)
            out[i] = self._resample(U, D, grid, label, patch)
        return out

    # ------------------------------------------------------------------
    def _observe(self, U: np.ndarray, D: np.ndarray, rng, label: str, patch=None):
        """Apply occlusion and point noise (local frame) -> ``(U, D, patch)``; ``patch``: ``(triangles, top-sheet
        node mask)``, re-indexed (the triangles of removed nodes dropped) when occlusion removes nodes."""
        r = self.occlusion_radius_mm
        if r > 0:
            hidden = np.hypot(U[:, 0], U[:, 1]) < r
            if self.occlusion_mode == "remove":
                U, D = U[~hidden], D[~hidden]
                if patch is not None:
                    patch = (keep_triangles(patch[0], ~hidden), patch[1][~hidden])
                if len(U) < 3:
                    raise ValueError(
                        f"case {label}: only {len(U)} ROI nodes remain outside the occlusion radius "
                        f"{r} mm; reduce model.occlusion.radius_mm or enlarge the ROI"
                    )
            elif rng is not None and hidden.any():
                disp = D - U
                s = max(self.noise_mm, float(np.sqrt(np.mean(disp**2))))
                D = D.copy()
                D[hidden] = U[hidden] + rng.normal(0.0, s, size=(int(hidden.sum()), 3))
        if self.noise_mm > 0 and rng is not None:
            D = D + rng.normal(0.0, self.noise_mm, size=D.shape)
        return U, D, patch

    def _resample(self, U: np.ndarray, D: np.ndarray, grid: np.ndarray, label: str, patch=None) -> np.ndarray:
        parts = []
        if self.features in ("displacement", "both"):
            if self.uses_triangles:  # the top sheet's nodes only, so no fallback bridges to another face
                T, top = patch
                parts.append(interpolate_top_sheet(U[top], keep_triangles(T, top), (D - U)[top], grid, label))
            else:
                parts.append(interpolate_to_grid(U[:, :2], D - U, grid, label))
        if self.features in ("deformed", "both"):
            parts.append(interpolate_to_grid(D[:, :2], D[:, 2:3], grid, label))
        return np.concatenate([p.T.ravel() for p in parts])


def keep_triangles(T: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """The triangles ``T`` (indices into nodes) whose three nodes are all kept (boolean ``keep``), re-indexed
    into the kept nodes."""
    keep = np.asarray(keep, dtype=bool)
    pos = np.full(len(keep), -1, dtype=np.int64)
    pos[keep] = np.arange(int(keep.sum()))
    Tk = pos[np.asarray(T, dtype=np.int64).reshape(-1, 3)]
    return Tk[(Tk >= 0).all(axis=1)]


RIGID_MOTION_MODES = ("keep", "remove")
_MIN_RIGID_NODES = 10


def rigid_fit_nodes(U_loc: np.ndarray, radius_mm: float) -> np.ndarray:
    """Mask of the ROI nodes the rigid motion is fitted to: tangent distance ``>= radius_mm`` from the exertion
    point (local undeformed coordinates ``U_loc``), or the outer half of the nodes when fewer than 10 are."""
    r = np.hypot(U_loc[:, 0], U_loc[:, 1])
    far = r >= radius_mm
    if far.sum() < _MIN_RIGID_NODES:
        far = r >= np.median(r)
    return far


def undo_rigid_motion(U: np.ndarray, D: np.ndarray, fit_nodes: np.ndarray) -> np.ndarray:
    """Deformed nodes ``D`` ``(k, 3)`` with the rigid motion that best maps ``U[fit_nodes]`` onto
    ``D[fit_nodes]`` undone (float64, the frame of the input).

    The motion ``x -> Q x + t`` minimises ``sum |Q u_j + t - d_j|^2`` over the fit nodes (Kabsch, a proper
    rotation); the result is ``Q^T (d - t)`` for every node. A rigid motion ``A d + b`` of every deformed
    node gives the same result (the fit absorbs it), and a motion that leaves the fit nodes at rest gives ``D``.
    """
    U = np.asarray(U, dtype=np.float64)
    D = np.asarray(D, dtype=np.float64)
    A, B = U[fit_nodes], D[fit_nodes]
    ca, cb = A.mean(axis=0), B.mean(axis=0)
    Uh, _, Vt = np.linalg.svd((A - ca).T @ (B - cb))
    Q = Vt.T @ Uh.T
    if np.linalg.det(Q) < 0:  # a reflection: flip the least significant axis
        Q = Vt.T @ np.diag([1.0, 1.0, -1.0]) @ Uh.T
    return (D - cb) @ Q + ca


def roi_half_extent(arrays: dict, R: np.ndarray | None = None) -> np.ndarray:
    """Per case, half-width (mm) of the largest centred square inside the ROI's tangent bounding box.

    ``min(max u, -min u, max v, -min v)`` of the undeformed local tangent
    coordinates; invariant to rigid motion and node order. ``R``: the cases'
    rotations if already computed (:func:`liverforce.learn.frames.case_rotations`).
    """
    R = case_rotations(arrays) if R is None else R
    P = np.asarray(arrays["exertion_point_mm"], dtype=np.float64)
    out = np.empty(len(P))
    for i, pts in enumerate(arrays["roi_undeformed_mm"]):
        U = points_to_local(np.asarray(pts).reshape(-1, 3), P[i], R[i])
        out[i] = min(U[:, 0].max(), -U[:, 0].min(), U[:, 1].max(), -U[:, 1].min())
    return out


def fit_half_width(arrays: dict) -> float:
    """Grid half-width ``h`` (mm): median of :func:`roi_half_extent` over the given (training) cases."""
    ext = roi_half_extent(arrays)
    h = float(np.median(ext))
    if not h > 0:
        raise ValueError(
            f"cannot derive a grid extent: the median ROI half-extent is {h} mm (the exertion point lies on "
            "the edge of its ROI?); set model.grid_half_width_mm"
        )
    return h


def representation_from_config(model_cfg: dict, train_arrays: dict) -> Representation:
    """Build the :class:`Representation` from the ``model`` config slice, fitting ``h`` on ``train_arrays``.

    Keys used: ``grid_size``, ``occlusion.radius_mm``, ``occlusion.mode``,
    ``noise_mm`` and, optional, ``roi_features`` (default ``displacement``)
    and ``grid_half_width_mm`` (default 0 = fit on the training split),
    ``rigid_motion`` (default ``keep``) and ``rigid_motion_radius_mm`` (15).
    """
    occ = model_cfg.get("occlusion") or {}
    h = float(model_cfg.get("grid_half_width_mm") or 0.0)
    if h <= 0:
        h = fit_half_width(train_arrays)
    features = str(model_cfg.get("roi_features", "displacement"))
    cam = None
    if features in names.CAMERA_FEATURES:
        cam = _plain(model_cfg.get("camera") or {})
        # the bundle records the height reference even where the config leaves it to the default
        from liverforce.learn.cloud_features import CloudGridSpec

        cam["grid"] = {"reference": CloudGridSpec.reference, **(cam.get("grid") or {})}
        if float(cam["grid"].get("instrument_radius_mm") or 0.0) > 0:
            # the instrument fit's weights as trained (the observation's point noise, the kinematic tip's
            # tangential noise), so re-observing with other settings (validation) does not refit them
            from liverforce.learn.camera import instrument_sds

            cam["grid"] = {**instrument_sds(cam, h, int(model_cfg["grid_size"])), **cam["grid"]}
    return Representation(
        rigid_motion=str(model_cfg.get("rigid_motion", "keep")),
        rigid_motion_radius_mm=float(model_cfg.get("rigid_motion_radius_mm", 15.0)),
        interpolation=str(model_cfg.get("interpolation", "points")),
        grid_size=int(model_cfg["grid_size"]),
        half_width_mm=h,
        features=features,
        occlusion_radius_mm=float(occ.get("radius_mm", 0.0)),
        occlusion_mode=str(occ.get("mode", "remove")),
        noise_mm=float(model_cfg.get("noise_mm", 0.0)),
        camera=cam,
    )


def _plain(d):
    """A config slice as plain JSON types (lists for tuples), so the model bundle stores it as given."""
    if isinstance(d, dict):
        return {str(k): _plain(v) for k, v in d.items()}
    if isinstance(d, (list, tuple)):
        return [_plain(v) for v in d]
    return d


# --------------------------------------------------------------------------
# ROI fraction at training time (no new simulation)
# --------------------------------------------------------------------------


def with_roi_fraction(arrays: dict, fraction: float, surfaces: dict) -> dict:
    """The cases of ``arrays`` with the ROI re-selected at another area ``fraction``.

    The shards store every surface node's displacement
    (``dataset.store_full_surface``), so the geodesic ROI of any fraction can be
    grown again from the exertion point (:func:`liverforce.dataset.roi.extract_roi`,
    the rule the simulation used) without a new FE solve. With the shard's own
    fraction this reproduces the stored ROI (same nodes, same order).

    Parameters
    ----------
    arrays : dict
        Input-contract arrays plus ``surface_displacement_mm`` (list of
        ``(s, 3)`` per case, in the order of the geometry's surface nodes) and
        ``geometry_id``.
    fraction : float in (0, 1]
        Share of the liver's surface area covered by the ROI.
    surfaces : dict
        ``geometry_id -> SurfaceGraph`` of each geometry (built from its mesh
        with :func:`liverforce.dataset.roi.surface_graph`, as the simulation did).

    Returns
    -------
    dict
        A shallow copy of ``arrays`` with ``roi_undeformed_mm``,
        ``roi_deformed_mm``, ``roi_node_ids`` (mesh point ids),
        ``roi_centroid_undeformed_mm`` and ``roi_centroid_deformed_mm``
        replaced, and ``roi_area_fraction`` (achieved) added; ``roi_triangles`` (the patch's own
        triangles, which camera models read) too, where ``arrays`` had them. Frames, exertion points and
        forces are unchanged.
    """
    from liverforce.dataset.roi import extract_roi, roi_triangles

    if not 0.0 < float(fraction) <= 1.0:
        raise ValueError(f"ROI fraction must be in (0, 1], got {fraction}")
    if "surface_displacement_mm" not in arrays:
        raise KeyError("re-selecting the ROI needs 'surface_displacement_mm' (the full-surface displacements)")
    P = np.asarray(arrays["exertion_point_mm"], dtype=np.float64)
    geo = np.asarray(arrays["geometry_id"]).astype(str)
    und, dfm, ids, achieved, tris = [], [], [], [], []
    cache: dict[tuple, tuple[np.ndarray, float]] = {}
    for i in range(len(P)):
        gid = geo[i]
        if gid not in surfaces:
            raise KeyError(f"no surface graph for geometry '{gid}' (needed to re-select the ROI)")
        surf = surfaces[gid]
        u = np.asarray(arrays["surface_displacement_mm"][i], dtype=np.float64).reshape(-1, 3)
        if len(u) != len(surf.node_ids):
            raise ValueError(
                f"case {arrays['case_id'][i] if 'case_id' in arrays else i}: {len(u)} stored surface displacements "
                f"but geometry '{gid}' has {len(surf.node_ids)} surface nodes; the shards were written without "
                "dataset.store_full_surface or for another mesh"
            )
        key = (gid, *np.round(P[i], 6))
        if key not in cache:
            cache[key] = extract_roi(surf, P[i], float(fraction))
        local, frac = cache[key]
        x0 = surf.points[local]
        x1 = x0 + u[local]
        und.append(x0.astype(np.float32))
        dfm.append(x1.astype(np.float32))
        ids.append(surf.node_ids[local].astype(np.int64))
        achieved.append(frac)
        if "roi_triangles" in arrays:
            tris.append(roi_triangles(surf.triangles, local))
    out = dict(arrays)
    out["roi_undeformed_mm"] = und
    out["roi_deformed_mm"] = dfm
    out["roi_node_ids"] = ids
    out["roi_centroid_undeformed_mm"] = np.array([x.astype(np.float64).mean(axis=0) for x in und]).reshape(-1, 3)
    out["roi_centroid_deformed_mm"] = np.array([x.astype(np.float64).mean(axis=0) for x in dfm]).reshape(-1, 3)
    out["roi_area_fraction"] = np.asarray(achieved, dtype=np.float64)
    if "roi_triangles" in arrays:
        out["roi_triangles"] = tris
    return out
