"""The pre-operative context of one prediction: where the tool pushes, on what, and how stiff.

A force model needs, besides the deformed ROI, what was known before the
surgery (the "state" of :mod:`liverforce.learn.state`) and the undeformed
geometry of the observed region. :class:`Preop` holds it for one exertion
point, in the liver (source) frame, mm and MPa:

==========================  =========  =============================================
field                       shape      meaning
==========================  =========  =============================================
``exertion_point_mm``       (3,)       tool contact point on the undeformed surface
``frame``                   (3, 3)     rows ``t1, t2, n``: local frame at the point
                                       (outward normal ``n``, ``t1 x t2 = n``)
``roi_undeformed_mm``       (k, 3)     undeformed ROI nodes (the surface patch)
``material_params_mpa``     (p,)       material constants, MPa (state vector only)
``liver_centroid_mm``       (3,)       volume centroid of the liver (state only)
``inertia_mm5``             (3, 3)     volume inertia tensor about the centroid,
                                       unit density (state only)
``tool_thickness_mm``       scalar     tissue thickness under the tool along the
                                       inward normal, mm (state only)
``probe_compliance_mm_per_n`` (3, 3)   the pre-operative stiffness probe at the
                                       point: compliance in the local frame, mm/N
                                       (state only; :mod:`liverforce.serve.probe`
                                       computes it from the tet mesh)
``roi_point_ids``           (k,)       optional: rows of the surface the ROI came
                                       from (``deformed_surface[roi_point_ids]``)
``roi_triangles``           (m, 3)     the ROI patch's own triangles, indices into
                                       ``roi_undeformed_mm`` (models read the
                                       patch's top sheet through them)
``surface_mm``              tuple      optional: the pre-operative surface the
                                       context was built from, ``(points (s, 3),
                                       triangles (m, 3))`` (:meth:`Preop.from_surface`):
                                       the input checks measure the exertion point's
                                       distance to its triangles
                                       (:attr:`Preop.surface_point_mm`)
==========================  =========  =============================================

:attr:`Preop.rotation` is the local rotation of ``frame``
(:func:`liverforce.learn.frames.local_rotations`, re-orthonormalised), computed
once per context and used by every serving step (input checks, cloud cropping,
the compiled paths, the model's features and state vector), exactly as
training computes it from the same frame.

:meth:`Preop.from_surface` computes everything from the undeformed liver
surface exactly as the data factory does (:mod:`liverforce.dataset.roi` and
:mod:`liverforce.pipeline.simulate`): frame by :func:`~liverforce.dataset.roi.local_frame`
with the tool radius, ROI by :func:`~liverforce.dataset.roi.extract_roi` with the
ROI area fraction, and the volume centroid and inertia of the closed surface
(divergence theorem: exact for the polyhedron, so equal to the tet mesh's
values when the surface is the tet mesh's boundary).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np

from liverforce.learn.frames import local_rotations
from liverforce.serve.errors import PredictionInputError

#: data-factory defaults (config ``dataset.roi_fraction``, ``simulate.tool_radius_mm``)
DEFAULT_ROI_FRACTION = 0.18
DEFAULT_FRAME_RADIUS_MM = 5.0


def _points(name: str, a, *, min_points: int = 1) -> np.ndarray:
    try:
        x = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise PredictionInputError(f"{name}: not a numeric array ({exc})") from exc
    if x.ndim != 2 or x.shape[1] != 3:
        raise PredictionInputError(f"{name}: expected an (n, 3) array of xyz points in mm, got shape {x.shape}")
    if len(x) < min_points:
        raise PredictionInputError(
            f"{name}: {len(x)} points; at least {min_points} are needed"
            + (" (the cloud is empty)" if len(x) == 0 else "")
        )
    bad = ~np.isfinite(x).all(axis=1)
    if bad.any():
        raise PredictionInputError(
            f"{name}: {int(bad.sum())} of {len(x)} points contain NaN or inf (first at row {int(np.argmax(bad))}); "
            "drop invalid points (e.g. missing depth) before predicting"
        )
    return x


def _vector(name: str, a, size: int | None = None) -> np.ndarray:
    try:
        x = np.asarray(a, dtype=np.float64).ravel()
    except (TypeError, ValueError) as exc:
        raise PredictionInputError(f"{name}: not a numeric vector ({exc})") from exc
    if size is not None and x.size != size:
        raise PredictionInputError(f"{name}: expected {size} numbers, got {x.size}")
    if not np.isfinite(x).all():
        raise PredictionInputError(f"{name}: contains NaN or inf ({x.tolist()})")
    return x


def surface_moments(points: np.ndarray, facets: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Volume (mm³), centroid (mm) and inertia tensor (mm⁵, about the centroid) of a closed surface.

    Notes
    -----
    The body is split into the signed tetrahedra ``(o, a, b, c)`` from an
    interior-ish apex ``o`` to every facet; with outward facets the signed
    volumes add up to the enclosed polyhedron exactly, and so do the moments
    (same formulas as :func:`liverforce.mesh.features.volume_moments`):
    ``∫ r rᵀ dV = V/20 (Σ_a v_a v_aᵀ + s sᵀ)`` per tet, ``J = tr(M) I − M``.
    A negative total volume means inward facets (the caller flips them).
    """
    o = points.mean(axis=0)
    tet = np.concatenate([np.broadcast_to(o, (len(facets), 1, 3)), points[facets]], axis=1)  # (m, 4, 3)
    e = tet[:, 1:] - tet[:, :1]
    vol = np.einsum("ti,ti->t", e[:, 0], np.cross(e[:, 1], e[:, 2])) / 6.0
    total = float(vol.sum())
    if abs(total) < 1e-300:
        return 0.0, o, np.zeros((3, 3))
    centroid = (vol[:, None] * tet.mean(axis=1)).sum(axis=0) / total
    v = tet - centroid
    s = v.sum(axis=1)
    m = (np.einsum("t,tai,taj->ij", vol, v, v) + np.einsum("t,ti,tj->ij", vol, s, s)) / 20.0
    if total < 0:  # inward facets: every moment flips sign with the volume
        m = -m
    inertia = np.trace(m) * np.eye(3) - m
    return total, centroid, inertia


def boundary_edges(facets: np.ndarray) -> int:
    """Number of edges used by exactly one facet (0 for a closed surface)."""
    e = np.sort(np.concatenate([facets[:, [0, 1]], facets[:, [1, 2]], facets[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    return int((counts == 1).sum())


@dataclass(frozen=True)
class Preop:
    """Pre-operative context of one exertion point (module docstring); liver frame, mm, MPa."""

    exertion_point_mm: np.ndarray
    frame: np.ndarray
    roi_undeformed_mm: np.ndarray
    material_params_mpa: np.ndarray | None = None
    liver_centroid_mm: np.ndarray | None = None
    inertia_mm5: np.ndarray | None = None
    roi_point_ids: np.ndarray | None = field(default=None, compare=False)
    tool_thickness_mm: float | None = None
    probe_compliance_mm_per_n: np.ndarray | None = None
    roi_triangles: np.ndarray | None = field(default=None, compare=False)
    surface_mm: tuple | None = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "exertion_point_mm", _vector("exertion_point_mm", self.exertion_point_mm, 3))
        fr = _vector("frame", self.frame, 9).reshape(3, 3)
        object.__setattr__(self, "frame", fr)
        object.__setattr__(self, "roi_undeformed_mm", _points("roi_undeformed_mm", self.roi_undeformed_mm))
        if self.material_params_mpa is not None:
            object.__setattr__(self, "material_params_mpa", _vector("material_params_mpa", self.material_params_mpa))
        if self.liver_centroid_mm is not None:
            object.__setattr__(self, "liver_centroid_mm", _vector("liver_centroid_mm", self.liver_centroid_mm, 3))
        if self.inertia_mm5 is not None:
            object.__setattr__(self, "inertia_mm5", _vector("inertia_mm5", self.inertia_mm5, 9).reshape(3, 3))
        if self.roi_point_ids is not None:
            object.__setattr__(self, "roi_point_ids", np.asarray(self.roi_point_ids, dtype=np.int64).ravel())
        if self.tool_thickness_mm is not None:
            t = float(_vector("tool_thickness_mm", self.tool_thickness_mm, 1)[0])
            if not t > 0:
                raise PredictionInputError(f"tool_thickness_mm: must be > 0 mm, got {t}")
            object.__setattr__(self, "tool_thickness_mm", t)
        if self.probe_compliance_mm_per_n is not None:
            C = _vector("probe_compliance_mm_per_n", self.probe_compliance_mm_per_n, 9).reshape(3, 3)
            C = 0.5 * (C + C.T)
            if not np.linalg.eigvalsh(C)[0] > 0:
                raise PredictionInputError(
                    f"probe_compliance_mm_per_n: must be positive definite (mm/N), got eigenvalues "
                    f"{np.round(np.linalg.eigvalsh(C), 6).tolist()}")
            object.__setattr__(self, "probe_compliance_mm_per_n", C)
        if self.roi_triangles is not None:
            from liverforce.learn.grid import check_triangles

            try:
                T = np.asarray(self.roi_triangles)
                T = check_triangles(T.reshape(-1, 3) if T.ndim == 1 and T.size % 3 == 0 else T,
                                    len(self.roi_undeformed_mm), "roi_triangles")
            except (TypeError, ValueError) as exc:
                raise PredictionInputError(str(exc)) from None
            object.__setattr__(self, "roi_triangles", T)

    @cached_property
    def surface_point_mm(self) -> np.ndarray | None:
        """The closest point to the exertion point on the pre-operative surface's triangles (:attr:`surface_mm`;
        None without it), computed once per context: on a coarse mesh a point on the surface lies far from every
        vertex, and a fit of the nearest ones misjudges its distance to it."""
        if self.surface_mm is None:
            return None
        return self.surface_search.closest(self.exertion_point_mm[None])[0][0]

    @property
    def surface_triangles_mm(self) -> np.ndarray | None:
        """The pre-operative surface's triangles ``(m, 3, 3)`` mm (:attr:`surface_mm`), or None."""
        if self.surface_mm is None:
            return None
        pts, tri = self.surface_mm
        return np.asarray(pts, dtype=np.float64)[np.asarray(tri)]

    @cached_property
    def surface_search(self):
        """The surface's triangles with their search tree (:class:`~liverforce.mesh.supports.TriangleSet`), built
        once per context: the exertion point's closest point and a refusal's other readings share it. None
        without :attr:`surface_mm`."""
        if self.surface_mm is None:
            return None
        from liverforce.mesh.supports import TriangleSet

        return TriangleSet(self.surface_triangles_mm)

    @cached_property
    def rotation(self) -> np.ndarray:
        """The local rotation ``R`` (3 x 3, rows ``t1, t2, n``) of ``frame``, computed once per context.

        The same :func:`~liverforce.learn.frames.local_rotations` training applies to
        ``frame_normal``, ``frame_t1``, ``frame_t2`` (bit for bit). Computed on
        first use, so a context with a non-orthonormal frame can be built and is
        refused (:class:`PredictionInputError`) when checked or used.
        """
        f = self.frame
        try:
            return local_rotations(f[2][None], f[0][None], f[1][None])[0]
        except ValueError as exc:
            raise PredictionInputError(str(exc)) from None

    # ------------------------------------------------------------------
    @classmethod
    def from_surface(
        cls,
        points,
        facets,
        exertion_point_mm,
        material_params_mpa=None,
        *,
        roi_fraction: float = DEFAULT_ROI_FRACTION,
        frame_radius_mm: float = DEFAULT_FRAME_RADIUS_MM,
    ) -> "Preop":
        """Frame, ROI and liver features from the undeformed surface, as the data factory computes them.

        Parameters
        ----------
        points : (s, 3) array_like
            Undeformed surface vertices, mm, liver frame.
        facets : (m, 3) int array_like
            Triangles (either consistent orientation; flipped to outward).
        exertion_point_mm : (3,) array_like
            Tool contact point on the surface, mm.
        material_params_mpa : (p,) array_like, optional
            Material constants in MPa (needed by state-vector models).
        roi_fraction, frame_radius_mm : float
            ROI area fraction and the frame's averaging radius; must match the
            data factory that made the training data (defaults: the shipped
            config).

        Notes
        -----
        Liver centroid and inertia need a closed surface; an open one leaves
        them ``None`` (a state-vector model then refuses the context).
        """
        from liverforce.dataset.roi import (extract_roi, local_frame, roi_triangles, surface_graph,
                                            thickness_along_normal)

        pts = _points("surface points", points, min_points=4)
        try:
            tri = np.asarray(facets, dtype=np.int64)
        except (TypeError, ValueError) as exc:
            raise PredictionInputError(f"surface facets: not an integer array ({exc})") from exc
        if tri.ndim != 2 or tri.shape[1] != 3 or len(tri) == 0:
            raise PredictionInputError(f"surface facets: expected an (m, 3) array of triangles, got shape {tri.shape}")
        if tri.min() < 0 or tri.max() >= len(pts):
            raise PredictionInputError(
                f"surface facets: vertex indices must lie in [0, {len(pts) - 1}], found {tri.min()}..{tri.max()}"
            )
        p = _vector("exertion_point_mm", exertion_point_mm, 3)
        closed = boundary_edges(tri) == 0
        volume, centroid, inertia = surface_moments(pts, tri)
        if volume < 0:
            tri = tri[:, [0, 2, 1]]
            volume = -volume
        surf = surface_graph(pts, tri)
        if not 0.0 < float(roi_fraction) <= 1.0:
            raise PredictionInputError(f"roi_fraction must be in (0, 1], got {roi_fraction}")
        frame = local_frame(surf, p, float(frame_radius_mm))
        ids, _ = extract_roi(surf, p, float(roi_fraction))
        point_ids = surf.node_ids[ids]
        thickness = thickness_along_normal(pts, tri, p, frame[2]) if closed else float("nan")
        patch = roi_triangles(tri, point_ids)
        return cls(
            exertion_point_mm=p,
            frame=frame,
            roi_undeformed_mm=pts[point_ids],
            material_params_mpa=material_params_mpa,
            liver_centroid_mm=centroid if closed and volume > 0 else None,
            inertia_mm5=inertia if closed and volume > 0 else None,
            roi_point_ids=point_ids,
            tool_thickness_mm=thickness if np.isfinite(thickness) else None,
            roi_triangles=patch if len(patch) else None,  # no whole facet: none (models that read them refuse)
            surface_mm=(pts, tri),
        )

    @classmethod
    def from_arrays(cls, arrays: dict, i: int = 0) -> "Preop":
        """The context of row ``i`` of input-contract arrays (e.g. a shard loaded by ``load_training_arrays``)."""
        def get(k):
            return None if k not in arrays else np.asarray(arrays[k][i], dtype=np.float64)

        frame = np.stack([get("frame_t1"), get("frame_t2"), get("frame_normal")])
        ids = arrays.get("roi_node_ids")
        tris = arrays.get("roi_triangles")
        return cls(
            exertion_point_mm=get("exertion_point_mm"),
            frame=frame,
            roi_undeformed_mm=np.asarray(arrays["roi_undeformed_mm"][i], dtype=np.float64).reshape(-1, 3),
            material_params_mpa=get("material_params_mpa"),
            liver_centroid_mm=get("liver_centroid_mm"),
            inertia_mm5=get("inertia_mm5"),
            roi_point_ids=None if ids is None else ids[i],
            tool_thickness_mm=get("tool_thickness_mm"),
            probe_compliance_mm_per_n=get("probe_compliance_mm_per_n"),
            roi_triangles=None if tris is None else tris[i],
        )

    def with_material(self, material_params_mpa) -> "Preop":
        """The same context with other material constants (MPa)."""
        return replace(self, material_params_mpa=material_params_mpa)

    def with_compliance(self, probe_compliance_mm_per_n) -> "Preop":
        """The same context with the probe compliance (3 x 3, mm/N, local frame)."""
        return replace(self, probe_compliance_mm_per_n=probe_compliance_mm_per_n)

    def roi_of_surface(self, deformed_surface_mm) -> np.ndarray:
        """The ROI rows of a deformed surface with the vertex order of the one the context was built from."""
        if self.roi_point_ids is None:
            raise PredictionInputError("this context was not built from a surface: it has no roi_point_ids")
        s = _points("deformed surface", deformed_surface_mm)
        if self.roi_point_ids.max() >= len(s):
            raise PredictionInputError(
                f"deformed surface: {len(s)} points, but the ROI refers to vertex {int(self.roi_point_ids.max())}; "
                "pass the deformed positions of the same surface vertices"
            )
        return s[self.roi_point_ids]

    def to_arrays(self, deformed_roi_mm: np.ndarray) -> dict:
        """One-row input-contract arrays (``liverforce.learn``) for a deformed ROI in node correspondence."""
        und = self.roi_undeformed_mm
        dfm = np.asarray(deformed_roi_mm, dtype=np.float64)
        out = {
            "exertion_point_mm": self.exertion_point_mm[None],
            "frame_t1": self.frame[0][None],
            "frame_t2": self.frame[1][None],
            "frame_normal": self.frame[2][None],
            "roi_undeformed_mm": [und],
            "roi_deformed_mm": [dfm],
            "roi_centroid_undeformed_mm": und.mean(axis=0)[None],
            "roi_centroid_deformed_mm": (dfm if dfm.ndim == 2 and len(dfm) else und).mean(axis=0)[None],
        }
        if self.liver_centroid_mm is not None:
            out["liver_centroid_mm"] = self.liver_centroid_mm[None]
        if self.inertia_mm5 is not None:
            out["inertia_mm5"] = self.inertia_mm5.reshape(1, 9)
        if self.material_params_mpa is not None:
            out["material_params_mpa"] = self.material_params_mpa[None]
        if self.tool_thickness_mm is not None:
            out["tool_thickness_mm"] = np.array([self.tool_thickness_mm])
        if self.probe_compliance_mm_per_n is not None:
            out["probe_compliance_mm_per_n"] = self.probe_compliance_mm_per_n.reshape(1, 9)
        if self.roi_triangles is not None:
            out["roi_triangles"] = [self.roi_triangles]
        return out

    def to_dict(self) -> dict:
        """JSON-ready (lists of floats); :meth:`from_dict` inverts it."""
        d = {
            "exertion_point_mm": self.exertion_point_mm.tolist(),
            "frame": self.frame.tolist(),
            "roi_undeformed_mm": self.roi_undeformed_mm.tolist(),
        }
        for k in ("material_params_mpa", "liver_centroid_mm", "inertia_mm5", "roi_point_ids",
                  "probe_compliance_mm_per_n", "roi_triangles"):
            v = getattr(self, k)
            if v is not None:
                d[k] = v.tolist()
        if self.tool_thickness_mm is not None:
            d["tool_thickness_mm"] = float(self.tool_thickness_mm)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "Preop":
        return cls(**{k: d[k] for k in (
            "exertion_point_mm", "frame", "roi_undeformed_mm", "material_params_mpa", "liver_centroid_mm",
            "inertia_mm5", "roi_point_ids", "tool_thickness_mm", "probe_compliance_mm_per_n", "roi_triangles")
            if k in d})
