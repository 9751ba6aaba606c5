"""Use a trained force model: one object, three ways to feed it.

>>> pred = Predictor.load("results/exp/models/II-pca/model")          # doctest: +SKIP
>>> ctx = pred.preop_from_surface(verts, tris, point_mm, material_mpa)  # doctest: +SKIP
>>> pred.predict(deformed_roi_nodes, ctx)          # (a) tracked ROI nodes -> (Fx, Fy, Fz) N
>>> pred.predict_cloud(camera_points, ctx)         # (b) unordered cloud (see serve.cloud)
>>> fast = pred.compile(ctx); fast.predict(deformed_roi_nodes)   # (a) at haptic rates
>>> force, half = fast.predict_interval(deformed_roi_nodes)      # (a) with its interval (local t1, t2, n)

Inputs are in the liver (source) frame, mm; material constants in MPa; the
force comes back in the liver frame, N. The preprocessing of training (local
frame, ROI resampling, scalers, encoder, state vector) lives in the model
(:class:`liverforce.learn.model.ForceModel`); the predictor only assembles
the input-contract arrays, checks them against the model's training scale
(:mod:`liverforce.serve.checks`) and calls the model.

Loading: :meth:`Predictor.load` takes a bundle directory; any other reference
(an MLflow run id, ``runs:/<id>/model``, ``models:/<name>/<version>`` or a
registered name) goes through a ``fetch`` callable that downloads the bundle into
a temporary folder, removed once the bundle is read (it is read whole, so no
download is left behind). Serving never imports :mod:`liverforce.tracking` (tracking
builds on serving): :class:`liverforce.tracking.MlflowPredictor` and
``liverforce predict`` pass the MLflow fetcher. The bundle is read by
:meth:`ForceModel.load` (JSON + ``torch.load(weights_only=True)`` +
``np.load(allow_pickle=False)``), never by unpickling.
"""

from __future__ import annotations

import hashlib
import pickle
import tempfile
from pathlib import Path
from typing import Callable

import numpy as np

from liverforce.learn import camera
from liverforce.learn.model import ForceModel, ModelFormatError, subset
from liverforce.learn.provenance import provenance_lines
from liverforce.learn.representation import ROW_KEY
from liverforce.serve.checks import (Limits, TrainingScale, check_case, check_on_surface, distance_warnings,
                                     force_warnings, outside_training)
from liverforce.serve.cloud import (camera_checks, check_camera_cloud, check_instrument, cloud_support, cloud_warnings,
                                    registration_warnings, cloud_to_arrays, tool_tip_of)
from liverforce.serve.compiled import CompiledROI
from liverforce.serve.errors import PredictionInputError
from liverforce.serve.preop import DEFAULT_FRAME_RADIUS_MM, DEFAULT_ROI_FRACTION, Preop, _points, _vector

#: input-contract columns of a camera model's registration refinement (:meth:`Predictor.refine_arrays`): per row the
#: camera's cloud before the tool pushed, and the tool tip at contact (optional)
UNLOADED_KEY = "unloaded_cloud_mm"
CONTACT_KEY = "contact_tip_mm"

#: keys of one case's pre-operative context in the input contract (everything but the deformed ROI and the
#: material): rows that agree on all of them share one compiled context (predict_arrays' fast path), so every
#: input a CompiledROI freezes must be here (the undeformed ROI centroid is the mean of roi_undeformed_mm)
CONTEXT_KEYS = ("exertion_point_mm", "frame_normal", "frame_t1", "frame_t2", "roi_undeformed_mm",
                "liver_centroid_mm", "inertia_mm5", "tool_thickness_mm", "probe_compliance_mm_per_n", "roi_triangles")

#: ``fetch(ref, dst_dir)``: downloads a model reference that is not a directory (run id, ``runs:/``/``models:/``
#: URI, registered name) into the folder ``dst_dir`` and returns the bundle directory inside it, or raises
#: :class:`PredictionInputError` saying why it cannot (e.g. :func:`liverforce.tracking.fetch_force_model`)
ModelFetcher = Callable[[str, Path], "str | Path"]


class Predictor:
    """A loaded force model plus the serving checks.

    Parameters
    ----------
    model : ForceModel
    limits : Limits, optional
        Tolerances of the input checks.
    source : str
        Where the model came from (for messages and ``describe``).
    """

    def __init__(self, model: ForceModel, *, limits: Limits | None = None, source: str = ""):
        self.model = model
        self.limits = limits or Limits()
        self.scale = TrainingScale.of(model)
        self.source = source

    # ------------------------------------------------------------------ loading
    @classmethod
    def from_dir(cls, path: str | Path, **kw) -> "Predictor":
        """Load a bundle directory written by :meth:`ForceModel.save`."""
        try:
            model = ForceModel.load(path)
        except ModelFormatError as exc:
            raise PredictionInputError(f"model: {exc}") from exc
        except (KeyError, ValueError, RuntimeError, OSError, pickle.UnpicklingError) as exc:
            # truncated or edited bundle; a weights file holding pickled code is refused by weights_only=True
            raise PredictionInputError(f"model {path}: unreadable bundle ({type(exc).__name__}: {exc})") from exc
        return cls(model, source=str(path), **kw)

    @classmethod
    def load(cls, ref: str | Path, *, fetch: ModelFetcher | None = None, **kw) -> "Predictor":
        """A bundle directory if ``ref`` is one, else what ``fetch`` downloads (the source stays ``ref``).

        Parameters
        ----------
        ref : str or path
            A bundle directory, or a reference ``fetch`` understands (for the
            MLflow fetcher: a run id, ``runs:/`` or ``models:/`` URI, or a registered name).
        fetch : callable, optional
            ``fetch(ref, dst_dir) -> bundle directory``, raising :class:`PredictionInputError`
            when it cannot; ``dst_dir`` is a temporary folder, removed once the
            bundle is read. Without it only directories load
            (:class:`liverforce.tracking.MlflowPredictor` passes the MLflow one).
        """
        if Path(ref).is_dir():
            return cls.from_dir(ref, **kw)
        if Path(ref).exists():
            raise PredictionInputError(f"model {ref}: a file, not a model directory (model.json + weights)")
        if fetch is None:
            raise PredictionInputError(
                f"model {ref}: no such model directory; to load an MLflow run id, runs:/ or models:/ URI or "
                "registered name use liverforce.tracking.MlflowPredictor.load (or `liverforce predict -m`)"
            )
        # the bundle is read whole (ForceModel.load), so its download need not outlive this call
        with tempfile.TemporaryDirectory(prefix="liverforce-model-") as tmp:
            try:
                pred = cls.from_dir(fetch(str(ref), Path(tmp)), **kw)
            except PredictionInputError as exc:  # name what the user gave, not the removed download folder
                raise PredictionInputError(f"model {ref} (downloaded): {exc}") from exc
        pred.source = str(ref)
        return pred

    # ------------------------------------------------------------------ context
    @property
    def roi_fraction(self) -> float:
        """ROI area fraction of the training data (bundle meta, else the shipped default)."""
        return float(self.model.meta.get("roi_fraction", DEFAULT_ROI_FRACTION))

    @property
    def frame_radius_mm(self) -> float:
        """Frame averaging radius of the training data (bundle meta, else the shipped default)."""
        return float(self.model.meta.get("frame_radius_mm", DEFAULT_FRAME_RADIUS_MM))

    def preop_from_surface(self, points, facets, exertion_point_mm, material_params_mpa=None, *,
                           mesh=None, probe_compliance_mm_per_n=None) -> Preop:
        """:meth:`Preop.from_surface` with this model's ROI fraction and frame radius; checked.

        A state-vector model also needs the stiffness probe at the point: give the
        liver's tet ``mesh`` (path or :class:`~liverforce.mesh.types.LiverMesh`;
        :func:`liverforce.serve.probe.with_probe` computes it with the model's
        settings) or the compliance itself (3 x 3, mm/N, local frame).
        """
        preop = Preop.from_surface(points, facets, exertion_point_mm, material_params_mpa,
                                   roi_fraction=self.roi_fraction, frame_radius_mm=self.frame_radius_mm)
        if probe_compliance_mm_per_n is not None:
            preop = preop.with_compliance(probe_compliance_mm_per_n)
        elif mesh is not None and self.model.uses_state:
            from liverforce.serve.probe import with_probe

            preop = with_probe(preop, mesh, self.model.meta)
        self.check_preop(preop)
        return preop

    def check_preop(self, preop: Preop, frame=None) -> None:
        """Refuse a context the model cannot use (missing state inputs, units, point off the surface).

        A context built from the pre-operative surface (:meth:`Preop.from_surface`) has its exertion point
        measured to the surface's triangles; ``frame`` (the inputs'
        :class:`~liverforce.serve.input_frame.InputFrame`, None: RAS mm) says in what units and frame a refusal
        gives the point back."""
        self._check_state_inputs(preop)
        exact = preop.surface_point_mm is not None
        if exact:
            check_on_surface(preop.exertion_point_mm, preop.surface_point_mm, self.limits, "", frame,
                             lambda: preop.surface_search)
        check_case(preop.to_arrays(preop.roi_undeformed_mm), 0, self.model, self.scale, self.limits, label="",
                   rotation=preop.rotation, on_surface=exact, input_frame=frame)

    def context_warnings(self, preop: Preop) -> list[str]:
        """Why the model extrapolates in this context: its geometric state outside the training range.

        Empty for a model without the state vector, or a context inside the
        range (:func:`liverforce.serve.checks.outside_training`).
        """
        if not self.model.uses_state:
            return []
        self._check_state_inputs(preop)
        return self.arrays_warnings(preop.to_arrays(preop.roi_undeformed_mm))[0]

    def arrays_warnings(self, arrays: dict) -> list[list[str]]:
        """:meth:`context_warnings` of every row of input-contract ``arrays`` (the first of each row's warnings
        that :meth:`predict_arrays`, ``liverforce predict --shards`` and the MLflow pyfunc return)."""
        if not self.model.uses_state:
            return [[] for _ in range(len(arrays["exertion_point_mm"]))]
        return outside_training(arrays, self.scale)[1]

    def force_warnings(self, force) -> list[list[str]]:
        """Per predicted force ``(n, 3)`` N (or one ``(3,)``): a warning where ``|F|`` exceeds every training
        case's (:func:`liverforce.serve.checks.force_warnings`); every path adds it after the inputs' warnings."""
        return force_warnings(force, self.scale, camera=self.model.representation.is_camera)

    def distance_warnings(self, distance) -> list[list[str]]:
        """Per input distance ``(n,)`` (``Forward.input_distance``; None: none): a warning where the case lies
        farther from every training case than the model's training-side quantile
        (:func:`liverforce.serve.checks.distance_warnings`); every path adds it after the force's."""
        return distance_warnings(distance, self.model.distance_flag, camera=self.model.representation.is_camera)

    def _check_state_inputs(self, preop: Preop) -> None:
        if self.model.uses_state:
            missing = [k for k in ("liver_centroid_mm", "inertia_mm5", "material_params_mpa", "tool_thickness_mm",
                                   "probe_compliance_mm_per_n") if getattr(preop, k) is None]
            if missing:
                raise PredictionInputError(
                    f"the model uses the state vector and the context lacks {missing}: give the material constants "
                    "(MPa), a closed pre-operative surface (or the liver centroid, inertia tensor and the tissue "
                    "thickness under the tool) and the liver's tet mesh for the stiffness probe (`--mesh`; or "
                    "probe_compliance_mm_per_n)"
                )

    # ------------------------------------------------------------------ predictions
    def _checked_arrays(self, deformed_roi_mm, preop: Preop) -> dict:
        """One-row input arrays of a deformed ROI in node correspondence, every check run."""
        D = _points("roi_deformed_mm", deformed_roi_mm, min_points=1)
        if D.shape != preop.roi_undeformed_mm.shape:
            raise PredictionInputError(
                f"roi_deformed_mm: {len(D)} points but the context's ROI has {len(preop.roi_undeformed_mm)} nodes; "
                "in correspondence mode give the deformed position of every ROI node, in the same order "
                "(Preop.roi_of_surface slices a deformed surface), or use predict_cloud for an unordered cloud"
            )
        self._check_state_inputs(preop)
        arrays = preop.to_arrays(D)
        check_case(arrays, 0, self.model, self.scale, self.limits, label="", rotation=preop.rotation,
                   on_surface=preop.surface_point_mm is not None)
        return arrays

    def predict(self, deformed_roi_mm, preop: Preop) -> np.ndarray:
        """(a) Force ``(3,)`` N from the deformed ROI nodes ``(k, 3)`` mm (order of ``preop.roi_undeformed_mm``)."""
        return self.model.predict(self._checked_arrays(deformed_roi_mm, preop), rotations=preop.rotation[None])[0]

    def interval(self, deformed_roi_mm, preop: Preop) -> dict | None:
        """The force of :meth:`predict` with its calibrated interval (None for a model without one).

        ``{"force_n" (liver frame), "coverage", "frame" (rows t1, t2, n), "force_local_n",
        "half_width_local_n", "lower_local_n", "upper_local_n", "input_distance"}``: per local component, the
        interval ``force_local_n +- half_width_local_n`` covers the true component with the
        nominal probability on livers like the calibration livers (the unseen-liver
        validation reports the coverage actually reached); ``input_distance``: a GP's distance from the case's
        inputs to its nearest training row (``Forward.input_distance``; None for an MLP), which
        :meth:`distance_warnings` words when it is beyond the model's threshold.
        """
        if self.model.interval is None:
            return None
        return interval_doc(self.model, self._checked_arrays(deformed_roi_mm, preop), rotations=preop.rotation[None])

    def refine_registration(self, unloaded_cloud_mm, preop: Preop, contact_tip_mm=None, *,
                            shape_degree: int | None = None):
        """The registration refinement (:class:`liverforce.learn.registration.Refinement`) that puts the camera's
        unloaded cloud (the same region before the tool pushed, model frame, mm) on ``preop``'s surface; pass it to
        :meth:`predict_cloud` (``registration=``). ``contact_tip_mm``: the tool tip at contact (robot kinematics).
        ``shape_degree``: the liver's change of shape since the scan, fitted to that degree and taken off the
        points' height (0: the rigid motion only; default
        :data:`~liverforce.learn.registration.SHAPE_DEGREE`). Camera-cloud models only; refused
        (:class:`PredictionInputError`, the reason said) when the cloud does not lie on the surface, the
        correction is beyond a refinement or the liver has changed shape there beyond a local correction."""
        from liverforce.learn.cloud_features import ReferenceSurface
        from liverforce.learn.registration import RegistrationError, refine_registration

        rep = self.model.representation
        if not rep.is_camera:
            raise PredictionInputError("an unloaded cloud refines a camera-cloud model's registration; this model "
                                       f"reads {rep.features} node displacements (give the deformed ROI instead)")
        self.check_preop(preop)
        spec = camera.grid_spec(rep.grid_size, rep.half_width_mm, rep.camera)
        cloud = _points("unloaded cloud", unloaded_cloud_mm, min_points=1)
        tip = None if contact_tip_mm is None else _vector("contact_tip_mm", contact_tip_mm, 3)
        try:
            ref = ReferenceSurface.for_case(preop.roi_undeformed_mm, preop.roi_triangles, preop.exertion_point_mm,
                                            preop.rotation, spec, label="the pre-operative surface")
            return refine_registration(ref, spec, cloud, tip,
                                       **({} if shape_degree is None else {"shape_degree": shape_degree}))
        except RegistrationError as exc:
            raise PredictionInputError(f"registration refinement: {exc}") from None

    def predict_cloud(self, cloud_mm, preop: Preop, *, approximate: bool = False, tool_tip_mm=None,
                      return_info: bool = False, registration=None,
                      input_frame=None) -> np.ndarray | tuple[np.ndarray, dict]:
        """(b) Force ``(3,)`` N from an unordered observed cloud ``(m, 3)`` mm (:mod:`liverforce.serve.cloud`).

        Exact for camera-cloud models (``roi_features: cloud``; they need the
        tool tip's position ``tool_tip_mm`` from the robot) and for models
        trained with ``roi_features: deformed`` and no state vector; other models
        only with ``approximate=True`` (normal-only displacement estimate),
        refused otherwise. Camera-cloud inputs outside what training covered are
        refused, milder departures listed in ``info["warnings"]``, with the
        context's (:meth:`context_warnings`) for every model. ``registration``: a
        :meth:`refine_registration` result, applied to the cloud and the tool tip first (``info["registration"]``
        says what it moved); the force stays in ``preop``'s frame. ``input_frame``: the units and frame the user
        declared for the cloud and the tip (an :class:`~liverforce.serve.input_frame.InputFrame`), which the caller
        converted them from to the model's frame already (:meth:`InputFrame.points`): a refusal gives them back
        as entered, with what was declared (None: nothing declared, RAS mm).
        """
        self.check_preop(preop, frame=input_frame)
        given = (cloud_mm, tool_tip_mm)  # before the registration: as the user gave them, once converted back
        if registration is not None:
            cloud_mm = registration.points(_points("cloud", cloud_mm, min_points=1))
            tool_tip_mm = None if tool_tip_mm is None else registration.points(_vector("tool_tip_mm", tool_tip_mm, 3))
        arrays, info = cloud_to_arrays(self.model, cloud_mm, preop, approximate=approximate, scale=self.scale,
                                       limits=self.limits, tool_tip_mm=tool_tip_mm, frame=input_frame, given=given)
        R = preop.rotation[None]
        if info["mode"] == "approximate" and self.model.representation.features != "deformed":
            check_case(arrays, 0, self.model, self.scale, self.limits, label="", rotation=preop.rotation,
                       on_surface=preop.surface_point_mm is not None)
        rep = self.model.representation
        if rep.is_camera:
            spec, fitted, point_sd, dropped = (camera.grid_spec(rep.grid_size, rep.half_width_mm, rep.camera), [], [],
                                               [])
            x = camera.features_from_clouds(arrays[camera.CLOUD_KEY], arrays[camera.TIP_KEY], arrays, spec, R=R,
                                            fitted=fitted, point_sd=point_sd, outliers=dropped)
            own = cloud_warnings(spec, fitted[0] if fitted else None, point_sd[0] if point_sd else None, dropped[0])
            info["warnings"] = self.context_warnings(preop) + own + camera_checks(self.model, x[0], self.limits)
            arrays["camera_features"] = x  # computed once: the model reads them instead of the cloud
        else:
            info["warnings"] = self.context_warnings(preop)
        fw = self.model.forward(arrays, rotations=R)
        force = fw.force_source[0]
        if registration is not None:
            info["registration"] = {**registration.to_dict(), "description": registration.describe()}
        info["warnings"] = (info["warnings"] + registration_warnings(registration) + self.force_warnings(force)[0]
                            + (self.distance_warnings(fw.input_distance) or [[]])[0])
        if return_info and self.model.interval is not None:
            info["interval"] = interval_doc(self.model, arrays, rotations=R)
        return (force, info) if return_info else force

    @property
    def cloud_support(self) -> str:
        """``exact`` or ``approximate``: what :meth:`predict_cloud` can do for this model."""
        return cloud_support(self.model)

    def compile_cloud(self, preop: Preop, frame=None, units: str | None = None, registration=None, declared=None):
        """The camera-cloud fast path for ``preop`` (:class:`liverforce.serve.compiled_cloud.CompiledCloud`;
        the context is checked once here). ``frame`` and ``units``: the clouds' and tips' frame and units (an
        :class:`~liverforce.serve.input_frame.InputFrame`, or what :meth:`InputFrame.resolve` takes: ``"LPS"``, a
        4x4, an import record; ``"m"``); their forces come back in that frame. Default: RAS mm. ``registration``:
        a :meth:`refine_registration` result (computed from points in the model's frame) applied to every cloud and
        tip after the frame. ``declared``: without ``frame``, the :class:`InputFrame` the user declared for clouds
        and tips the caller converted to the model's frame already (refusals give them back as entered)."""
        from liverforce.serve.compiled_cloud import CompiledCloud
        from liverforce.serve.input_frame import InputFrame

        fr = None if frame is None and units is None else InputFrame.resolve(frame, units)
        self.check_preop(preop, frame=fr if fr is not None else declared)
        return CompiledCloud(self.model, preop, limits=self.limits, frame=fr, registration=registration,
                             declared=declared)

    def compile(self, preop: Preop) -> CompiledROI:
        """The fixed-topology fast path for ``preop`` (checked once here): :class:`CompiledROI`, whose ``predict`` and
        ``predict_batch`` give the force alone and ``predict_interval`` (``predict_batch(..., with_interval=True)``)
        the force with its calibrated interval's half-widths per local component, as :meth:`interval` gives them."""
        self.check_preop(preop)
        return CompiledROI(self.model, preop, limits=self.limits, scale=self.scale)

    def refine_arrays(self, arrays: dict, *, refused: list | None = None) -> tuple[dict, list | None]:
        """Input-contract arrays with the columns ``unloaded_cloud_mm`` (per row, the camera's cloud before the
        tool pushed; an empty one: none for that row) and optionally ``contact_tip_mm`` (the tool tip at contact,
        NaN where unknown): each row's registration refined (:meth:`refine_registration`, from the row's context)
        and applied to its ``camera_cloud_mm`` and ``tool_tip_mm``. Returns the arrays without those two columns
        and each row's refinement (None where none), or the arrays unchanged and None without the columns.
        ``refused``: a list of one ``""`` per row; a row whose refinement is refused gets the message it would
        raise there instead (it is left as given, its refinement None), and the other rows go on."""
        if UNLOADED_KEY not in arrays:
            if CONTACT_KEY in arrays:
                raise PredictionInputError(f"{CONTACT_KEY} (the tool tip at contact) goes with {UNLOADED_KEY}, the "
                                           "camera's cloud before the tool pushed; give both, or neither")
            return arrays, None
        if not self.model.representation.is_camera:
            raise PredictionInputError(f"{UNLOADED_KEY} refines a camera-cloud model's registration; this model reads "
                                       f"{self.model.representation.features} node displacements: leave it out")
        if camera.CLOUD_KEY not in arrays or camera.TIP_KEY not in arrays:
            raise PredictionInputError(f"{UNLOADED_KEY} refines the registration of camera clouds: give "
                                       f"'{camera.CLOUD_KEY}' and '{camera.TIP_KEY}' with it")
        n = len(arrays["exertion_point_mm"])
        unloaded, contact = arrays[UNLOADED_KEY], arrays.get(CONTACT_KEY)
        if len(unloaded) != n or (contact is not None and len(contact) != n):
            raise PredictionInputError(f"{UNLOADED_KEY} / {CONTACT_KEY}: one per case ({n} exertion points)")
        clouds = list(arrays[camera.CLOUD_KEY])
        tips = list(arrays[camera.TIP_KEY])
        ids = arrays.get("case_id")
        fixes: list = []
        for i in range(n):
            row = _row_label(ids, i)
            if refused is not None and refused[i]:
                fixes.append(None)
                continue
            try:
                empty = unloaded[i] is None or np.size(unloaded[i]) == 0
                u = None if empty else _points(UNLOADED_KEY, unloaded[i], min_points=1)
                if u is None:  # none for this row: predicted as registered
                    fixes.append(None)
                    continue
                c = None if contact is None or contact[i] is None else np.asarray(contact[i], dtype=np.float64)
                if c is not None and c.size == 1 and np.isnan(c).all():  # a missing value in the column
                    c = None
                fix = self.refine_registration(u, Preop.from_arrays(arrays, i),
                                               None if c is None else _vector(CONTACT_KEY, c, 3))
                clouds[i] = fix.points(_points(camera.CLOUD_KEY, clouds[i], min_points=1))
                tips[i] = fix.points(_vector(camera.TIP_KEY, tips[i], 3))
            except PredictionInputError as exc:
                if refused is None:
                    raise PredictionInputError(row + str(exc)) from None
                refused[i], fix = row + str(exc), None
            fixes.append(fix)
        out = {k: v for k, v in arrays.items() if k not in (UNLOADED_KEY, CONTACT_KEY)}
        out[camera.CLOUD_KEY] = clouds
        out[camera.TIP_KEY] = _tips_column(tips, refused, ids)
        return out, fixes

    def predict_arrays(self, arrays: dict, *, observation_seed: int | None = None, fast: bool = False,
                       min_group: int = 2, return_warnings: bool = False, registrations: list | None = None,
                       input_frame=None, entered: tuple | None = None, return_refused: bool = False):
        """Forces ``(n, 3)`` N for input-contract arrays (e.g. a shard), every row checked first; with
        ``return_warnings`` also each row's warnings, those :meth:`predict_cloud` gives one cloud (the context's,
        a camera cloud's, the registration's, a force beyond training's), as ``(force, warnings)``.
        ``registrations``: each row's refinement when the caller has already applied :meth:`refine_arrays`
        (its warnings; the arrays' own ``unloaded_cloud_mm`` are refined here otherwise). ``input_frame``: the
        units and frame the user declared for the arrays (an :class:`~liverforce.serve.input_frame.InputFrame`),
        which the caller converted them from to the model's frame already (:meth:`InputFrame.arrays`): a camera
        cloud's refusal says what was declared and gives the cloud and tip back as entered, as
        :meth:`predict_cloud` does (None: nothing declared, RAS mm). ``entered``: the clouds and tips
        (``camera_cloud_mm``, ``tool_tip_mm``, in the model's frame) before the caller's :meth:`refine_arrays`
        moved them, given back in a refusal (default: the arrays' own, before this call's refinement).

        A row its checks refuse raises :class:`PredictionInputError` (``"case <id>: <reason>"``, without
        ``case_id`` ``"row <i>: <reason>"`` by its index in ``arrays``, a single row's too: the MLflow pyfunc's
        words; the first refused row). With ``return_refused`` the other rows go on instead: a refused row's force
        is NaN, its warnings empty, and each row's reason (the message the call would raise for it; ``""`` when
        predicted) is returned last, as ``(force, refused)`` or ``(force, warnings, refused)``. A row that passes
        every check but that the model cannot take raises the model's ``ValueError``; with ``return_refused`` the
        rows are then predicted again in halves, down to single rows, and a row that raises alone is refused with
        the model's reason (``"case <id>: "`` or ``"row <i>: "`` before it), the others predicted as in a call of
        them alone. Inputs that are wrong for every row (a column missing, columns of different lengths, a camera
        model given no clouds) raise either way. The compiled (``fast``) and reference paths refuse the same rows
        in the same words: every refusal but the model's is made by the checks before either path runs. With a
        stochastic observation model (``observation_seed``) each predicted row draws by its ``case_id`` (without
        one, by its :data:`~liverforce.learn.representation.ROW_KEY`, by default its index in ``arrays``), so it
        draws the same whether other rows are refused or not; refused rows draw nothing.

        Parameters
        ----------
        arrays : dict
            ``ForceModel.required_inputs()`` (``case_id`` optional).
        observation_seed : int, optional
            Draw the stochastic observation model as in evaluation (simulated data only).
        fast : bool
            Rows sharing one context (same ROI, point, frame, liver; material
            may differ) in groups of at least ``min_group`` go through
            :class:`CompiledROI` (equal to the reference to ~1e-6 N); needs
            ``roi_features: displacement`` and no stochastic observation.
        return_refused : bool
            Refused rows get NaN forces and their reason instead of raising (above).

        Camera clouds with ``unloaded_cloud_mm`` (and ``contact_tip_mm``) are registered first
        (:meth:`refine_arrays`).
        """
        if entered is None:  # the clouds and tips before a registration moves them
            entered = ((arrays[camera.CLOUD_KEY], arrays[camera.TIP_KEY])
                       if camera.CLOUD_KEY in arrays and camera.TIP_KEY in arrays else None)
        n_rows = len(arrays["exertion_point_mm"]) if "exertion_point_mm" in arrays else 0
        refused = [""] * n_rows if return_refused else None
        arrays, fixes = self.refine_arrays(arrays, refused=refused)
        fixes = fixes if fixes is not None else registrations
        if self.model.representation.is_camera and "camera_cloud_mm" not in arrays:
            raise PredictionInputError(
                "this camera-cloud model predicts from camera clouds with the tool tip ('camera_cloud_mm', "
                "'tool_tip_mm'); shards and ROI nodes are not what it reads (Predictor.predict_cloud, "
                "`liverforce predict CLOUD --tool-tip X Y Z`)")
        missing = [k for k in self.model.required_inputs() if k not in arrays]
        if missing:
            raise PredictionInputError(f"the model needs the inputs {missing}; they are missing")
        n = len(arrays["exertion_point_mm"])
        bad = {k: len(arrays[k]) for k in self.model.required_inputs() if len(arrays[k]) != n}
        if bad:
            raise PredictionInputError(f"inputs disagree on the number of cases ({n} exertion points): {bad}")
        keep_going = refused is not None
        refused = refused if keep_going else [""] * n
        ids = arrays.get("case_id")
        if ids is None and ROW_KEY not in arrays:  # a row's draw and name: its place here, whatever rows are refused
            arrays = {**arrays, ROW_KEY: np.arange(n)}

        def refuse(i: int, why: str) -> None:
            """Row ``i`` refused: raise its message, or (``return_refused``) record it and go on."""
            if not keep_going:
                raise PredictionInputError(why) from None
            refused[i] = why

        def out(force, warnings):
            got = (force, warnings) if return_warnings else (force,)
            got = got + (refused,) if return_refused else got
            return got if len(got) > 1 else got[0]

        if n == 0:
            return out(np.zeros((0, 3)), [])
        # each row's frame is checked (and its rotation computed) once, here; the model reuses the rotations
        R = np.full((n, 3, 3), np.nan)
        for i in range(n):
            if refused[i]:
                continue
            try:
                R[i] = check_case(arrays, i, self.model, self.scale, self.limits, label=_row_label(ids, i),
                                  input_frame=input_frame)
            except PredictionInputError as exc:
                if not keep_going:
                    raise  # as raised (an OffSurfaceError stays one)
                refused[i] = str(exc)
        rep = self.model.representation
        own_warnings = [[] for _ in range(n)]
        if rep.is_camera and "camera_cloud_mm" in arrays:  # observed clouds: features once, each row checked
            if camera.TIP_KEY not in arrays:
                raise PredictionInputError(
                    "a camera-cloud model needs the tool tip position ('tool_tip_mm', from the robot's kinematics) "
                    "with each cloud")
            for i in range(n):  # predict_cloud's refusals of a cloud and its tip, in its order and words
                if refused[i]:
                    continue
                try:
                    tip = tool_tip_of(arrays[camera.TIP_KEY][i])
                    cloud = _points("cloud", arrays[camera.CLOUD_KEY][i], min_points=1)
                    check_camera_cloud(rep, cloud, tip, np.asarray(arrays["exertion_point_mm"][i], dtype=np.float64),
                                       R[i], self.limits, input_frame,
                                       None if entered is None else (entered[0][i], entered[1][i]))
                except PredictionInputError as exc:
                    refuse(i, f"{_row_label(ids, i)}{exc}")
            rows = [i for i in range(n) if not refused[i]]  # the features of the rows not refused
            spec, fitted, point_sd, dropped = (camera.grid_spec(rep.grid_size, rep.half_width_mm, rep.camera), [], [],
                                               [])
            x = np.zeros((n, 0))
            if rows:  # (none: every row refused, subset() of no rows would index with floats)
                sub = arrays if len(rows) == n else subset(arrays, rows)
                x_rows = camera.features_from_clouds(sub[camera.CLOUD_KEY], sub[camera.TIP_KEY], sub, spec, R=R[rows],
                                                     fitted=fitted, point_sd=point_sd, outliers=dropped)
                x = np.full((n, x_rows.shape[1]), np.nan, dtype=x_rows.dtype)  # refused rows: NaN, never read
                x[rows] = x_rows
            tris = arrays.get("roi_triangles")
            for j, i in enumerate(rows):
                try:  # the instrument in a cloud for a model trained without it, then the features' ranges
                    check_instrument(rep, arrays["camera_cloud_mm"][i], arrays["tool_tip_mm"][i],
                                     arrays["roi_undeformed_mm"][i], None if tris is None else tris[i],
                                     arrays["exertion_point_mm"][i], R[i])
                    checked = camera_checks(self.model, x[i], self.limits)
                except PredictionInputError as exc:
                    refuse(i, f"{_row_label(ids, i)}{exc}")
                    continue
                own_warnings[i] = cloud_warnings(spec, fitted[j] if fitted else None,  # predict_cloud's order
                                                 point_sd[j] if point_sd else None, dropped[j]) + checked
            arrays = {**arrays, camera.FEATURES_KEY: x}
        rows = [i for i in range(n) if not refused[i]]
        force = np.full((n, 3), np.nan)
        warnings: list[list[str]] = [[] for _ in range(n)]
        if not rows:
            return out(force, warnings)
        sub = arrays if len(rows) == n else subset(arrays, rows)
        dist = np.full(n, np.nan)  # the rows' input distances (NaN: none known), for their warnings
        try:
            force[rows], dist[rows] = self._forces(sub, R[rows], observation_seed, fast, min_group,
                                                          return_warnings)
        except ValueError as exc:  # a row every check passed that the model cannot take (raised unless keep_going)
            failed = (self._failing_rows(arrays, rows, R, exc, observation_seed, fast, min_group, return_warnings)
                      if keep_going else {})
            if not failed:
                raise
            for i, why in failed.items():
                refused[i] = _model_refusal(arrays, i, why)
            rows = [i for i in rows if i not in failed]
            if not rows:
                return out(force, warnings)
            sub = subset(arrays, rows)  # the others as in a call of them alone
            force[rows], dist[rows] = self._forces(sub, R[rows], observation_seed, fast, min_group,
                                                          return_warnings)
        if not return_warnings:
            return out(force, warnings)
        regs = [registration_warnings(fixes[i]) for i in rows] if fixes is not None else [[] for _ in rows]
        far = self.distance_warnings(dist[rows]) or [[] for _ in rows]
        for i, c, g, f, d in zip(rows, self.arrays_warnings(sub), regs, self.force_warnings(force[rows]), far):
            warnings[i] = c + own_warnings[i] + g + f + d
        return out(force, warnings)

    def _failing_rows(self, arrays: dict, rows: list[int], R: np.ndarray, exc: ValueError,
                      *args) -> dict[int, ValueError]:
        """Which of ``rows`` (indices into ``arrays`` and ``R``), which raised ``exc`` together in :meth:`_forces`,
        raise ValueError when predicted alone, with what they raise: the rows are split in halves and a half that
        raises is split again, down to single rows (``args``: the rest of :meth:`_forces`' arguments). Empty when
        no row raises alone."""
        if len(rows) == 1:
            return {rows[0]: exc}
        failed: dict[int, ValueError] = {}
        for half in (rows[:len(rows) // 2], rows[len(rows) // 2:]):
            try:
                self._forces(subset(arrays, half), R[half], *args)
            except ValueError as got:
                failed.update(self._failing_rows(arrays, half, R, got, *args))
        return failed

    def _forces(self, arrays: dict, R: np.ndarray, observation_seed, fast: bool, min_group: int,
                distances: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`predict_arrays`' forces ``(n, 3)`` of checked rows (``R``: their rotations), by the compiled node
        path where ``fast`` allows it, and their input distances ``(n,)`` (``Forward.input_distance``; NaN for a
        model without an input-distance flag). The compiled node path has no distance: for a model with the flag
        its rows' distances come from one more pass of the reference path's features and GP inputs
        (:meth:`~liverforce.learn.model.ForceModel.input_distances`, no GP mean), unless ``distances`` is False (no
        warnings asked for: NaN)."""
        n = len(R)
        rep = self.model.representation
        can_fast = fast and rep.features == "displacement" and not (observation_seed is not None and rep.stochastic)
        flagged = self.model.distance_flag is not None
        if not can_fast:
            fw = self.model.forward(arrays, observation_seed=observation_seed, rotations=R)
            dist = fw.input_distance if flagged and fw.input_distance is not None else np.full(n, np.nan)
            return fw.force_source, dist
        groups: dict[bytes, list[int]] = {}
        for i in range(n):
            groups.setdefault(_context_key(arrays, i), []).append(i)
        out = np.empty((n, 3))
        slow = []
        for rows in groups.values():
            if len(rows) < min_group:
                slow += rows
                continue
            preop = Preop.from_arrays(arrays, rows[0])
            comp = CompiledROI(self.model, preop, limits=self.limits, scale=self.scale)
            D = np.stack([np.asarray(arrays["roi_deformed_mm"][i], dtype=np.float64) for i in rows])
            kw = {}
            if self.model.uses_state:
                kw = {"roi_centroid_deformed_mm": np.asarray(arrays["roi_centroid_deformed_mm"])[rows],
                      "material_params_mpa": np.asarray(arrays["material_params_mpa"])[rows]}
            out[rows] = comp.predict_batch(D, **kw)
        if slow:
            slow = np.array(sorted(slow))
            out[slow] = self.model.predict(subset(arrays, slow), observation_seed=observation_seed, rotations=R[slow])
        dist = np.full(n, np.nan)
        if flagged and distances:
            dist = self.model.input_distances(arrays, observation_seed=observation_seed, rotations=R)
        return out, dist

    # ------------------------------------------------------------------ info
    def describe(self) -> dict:
        """What the model needs and how it was trained (JSON-ready); ``trained_on``: one line per training liver
        (its file, SHA-256 prefix, units and frame, or procedural with its seed) and the material's
        (:func:`liverforce.learn.provenance.provenance_lines`)."""
        m = self.model
        return {
            "source": self.source,
            "representation": m.representation.to_dict(),
            "encoder": m.pre.encoder.spec(),
            "uses_state_vector": m.uses_state,
            "n_material_params": self.scale.n_material,
            "required_inputs": list(m.required_inputs()),
            "command_line": self.command_line(),
            "cloud_support": self.cloud_support,
            "roi_fraction": self.roi_fraction,
            "frame_radius_mm": self.frame_radius_mm,
            "training_scale_source": self.scale.source,
            "scenario": m.meta.get("scenario"),
            "variant": m.meta.get("variant"),
            "test_metrics": m.meta.get("test_metrics"),
            "trained_on": provenance_lines(m.meta.get("provenance")),
        }

    def command_line(self) -> list[str]:
        """What ``liverforce predict`` needs for this model, option by option (:meth:`describe`): the
        ``required_inputs`` are the input contract's names, which the command computes from these."""
        m, rep = self.model, self.model.representation
        out = []
        if rep.is_camera:
            out += ["CLOUD: the camera's points of the liver round the tool, the instrument's included (PLY, CSV or "
                    "NPY; a folder or several files: a sequence, with --tool-tips FILE)",
                    "--tool-tip X Y Z: the tool tip now, from the robot's kinematics"]
        elif self.cloud_support == "exact":
            out += ["CLOUD: the deformed surface's points round the tool (PLY, CSV or NPY)"]
        else:
            out += ["--mode nodes NODES with --context (the deformed ROI nodes, in the context's order) or --mode "
                    "surface SURFACE (the deformed surface, same vertices as the undeformed one); a cloud only with "
                    "--approximate (normal motion only)"]
        out.append("--exertion-point X Y Z: where the tool touches the pre-operative surface")
        if m.uses_state:
            n = self.scale.n_material or 1
            out += ["--mesh MESH: the liver's tet mesh (results/<exp>/mesh/<id>.vtu): its surface is the pre-operative "
                    "one, its stiffness probe the state vector's compliance (--surface SURFACE replaces the surface; "
                    "a --context FILE may give both)",
                    f"--material {' '.join(f'C{j + 1}' for j in range(n))}: the {n} material constant"
                    f"{'s' if n > 1 else ''} of the liver, MPa"]
        else:
            out.append("--surface SURFACE or --mesh MESH: the pre-operative surface (or a --context FILE)")
        out.append("--units m / cm and --frame LPS | a 4x4 | results/<exp>/geometry/imp-<name>.json: inputs not in "
                   "RAS mm (say --frame RAS beside the mesh of a liver imported in another frame)")
        if rep.is_camera:
            out.append("optional: --unloaded CLOUD --contact-tip X Y Z (the view before the tool pushed, and the tip "
                       "at contact): the registration refined first")
        return out


def _row_label(ids, i: int) -> str:
    """``"case <id>: "`` of row ``i`` (``ids``: the arrays' ``case_id``, or None: ``"row <i>: "``), the prefix of a
    row's refusal."""
    return f"case {ids[i]}: " if ids is not None else f"row {i}: "


def _model_refusal(arrays: dict, i: int, exc: Exception) -> str:
    """Row ``i``'s refusal (``"case <id>: "`` or ``"row <i>: "``, :func:`_row_label`) of what the model raised for
    it after every check passed; the model's own name of the row (``"case <id>: "``, ``"case row <k>: "``), which
    the label replaces, is left out."""
    ids = arrays.get("case_id")
    why = str(exc)
    own = f"case {ids[i]}: " if ids is not None else f"case row {arrays[ROW_KEY][i] if ROW_KEY in arrays else i}: "
    return _row_label(ids, i) + (why[len(own):] if why.startswith(own) else why)


def _tips_column(tips: list, refused: list | None, ids) -> np.ndarray:
    """The ``(n, 3)`` ``tool_tip_mm`` column of :meth:`Predictor.refine_arrays`; a malformed tip raises, or with
    ``refused`` (one ``""`` per row) refuses its row (NaN; rows refused already are NaN too)."""
    out = np.full((len(tips), 3), np.nan)
    for i, t in enumerate(tips):
        if refused is not None and refused[i]:
            continue
        try:
            out[i] = _vector(camera.TIP_KEY, t, 3)
        except PredictionInputError as exc:
            if refused is None:
                raise
            refused[i] = _row_label(ids, i) + str(exc)
    return out


def _context_key(arrays: dict, i: int) -> bytes:
    """Hash of row ``i``'s context (ROI shape and bytes, point, frame, liver); material excluded."""
    h = hashlib.blake2b(digest_size=16)
    for k in CONTEXT_KEYS:
        if k in arrays:
            a = np.ascontiguousarray(np.asarray(arrays[k][i]))
            h.update(k.encode())
            h.update(str(a.shape).encode())
            h.update(a.tobytes())
    return h.digest()


def interval_doc(model, arrays: dict, *, rotations: np.ndarray | None = None) -> dict:
    """JSON-ready interval of the first row of ``arrays`` (:meth:`Predictor.interval`); ``rotations`` as in
    :meth:`~liverforce.learn.model.ForceModel.forward`."""
    got = model.predict_interval(arrays, rotations=rotations)
    f, h = got["force_local_n"][0], got["half_width_local_n"][0]

    def fl(v):
        return [float(x) if np.isfinite(x) else None for x in v]

    dist = got.get("input_distance")
    return {"force_n": got["force_n"][0].tolist(), "coverage": got["coverage"], "frame": got["frame"][0].tolist(),
            "force_local_n": fl(f),
            "half_width_local_n": fl(h), "lower_local_n": fl(f - h), "upper_local_n": fl(f + h),
            "input_distance": None if dist is None else float(dist[0])}
