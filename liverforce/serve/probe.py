"""The pre-operative stiffness probe at serving time: the compliance a state-vector model needs.

A state-vector model reads, at the exertion point, the linear compliance ``C``
(3 x 3, mm/N, local frame) of the liver on its supports
(:mod:`liverforce.fem.probe`), computed for the reference material and the
support model of its training data. The model records both in its bundle
(``meta["probe"]``); this module recomputes ``C`` from the liver's tet mesh
with exactly those settings, as the data factory did
(:func:`liverforce.pipeline.simulate.probe_compliances`). It is
pre-operative: one factorisation per liver, then three back-solves per point.

    from liverforce.serve import Predictor
    from liverforce.serve.probe import with_probe
    pred = Predictor.load("results/default/models/IV/pca_sv/model")
    preop = with_probe(pred.preop_from_surface(pts, tri, p, mat), "liver.vtu", pred.model.meta)

The mesh must be the liver's tet mesh with its support regions tagged (the
mesh stage's ``mesh/<geometry>.vtu``, or a mesh meshed with ``liverforce mesh``);
its own foundation stiffness, if the mesh stage wrote one
(its features JSON, :func:`liverforce.layout.features_of_mesh`), is used as in
the simulation.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from liverforce.layout import features_of_mesh
from liverforce.serve.errors import OffSurfaceError, PredictionInputError
from liverforce.serve.preop import Preop


#: how far (mm) the exertion point may lie from the mesh's surface (the mesh may differ from a lab's own surface)
MESH_TOL_MM = 5.0


def probe_settings(meta: dict) -> dict:
    """The probe settings of a model bundle (``meta["probe"]``); a clear error when the bundle has none."""
    probe = (meta or {}).get("probe")
    if not probe:
        raise PredictionInputError(
            "this model's bundle does not record its stiffness-probe settings (meta['probe']); give "
            "probe_compliance_mm_per_n in the context instead of a mesh")
    return probe


class LiverProbe:
    """The probe of one liver mesh with a model's settings; :meth:`compliance` per exertion point."""

    def __init__(self, mesh, settings: dict, supports: dict | None = None):
        from liverforce.fem.problem import LiverModel
        from liverforce.mesh.io import read_mesh
        from liverforce.dataset.roi import surface_graph
        from liverforce.fem.materials import make_material
        from liverforce.fem.probe import ComplianceProbe
        from liverforce.pipeline.simulate import boundary_params, solver_options

        if isinstance(mesh, (str, Path)):
            path = Path(mesh)
            if not path.is_file():
                raise PredictionInputError(f"mesh {path}: no such file (the liver's tet mesh, e.g. results/<exp>/"
                                           "mesh/<geometry>.vtu)")
            feats = features_of_mesh(path)
            if supports is None and feats.is_file():
                supports = json.loads(feats.read_text()).get("support_boundary") or None
            try:
                mesh = read_mesh(path)
            except Exception as exc:
                raise PredictionInputError(f"mesh {path}: cannot be read as a liver tet mesh ({exc})") from None
        self.settings = settings
        self.surf = surface_graph(mesh.points, mesh.facets)
        ref = settings["reference"]
        mat = make_material(ref["model"], ref["params_mpa"], bulk_mpa=ref["bulk_mpa"])
        bp = boundary_params(mesh, settings["boundary"]).with_supports(supports)
        fe = LiverModel(mesh.points, mesh.tets, mesh.facets, mesh.facet_region, mat, bp,
                        solver_options(settings["simulate"]))
        try:
            self._probe = ComplianceProbe(fe)
        except ValueError as exc:
            raise PredictionInputError(f"the stiffness probe cannot run on this mesh: {exc}") from None

    def compliance(self, point_mm, frame) -> np.ndarray:
        """Compliance ``(3, 3)`` mm/N at ``point_mm`` in ``frame`` (rows t1, t2, n), symmetrised."""
        C = self._probe.compliance(np.asarray(point_mm, float), frame, float(self.settings["tool_radius_mm"]))
        C = 0.5 * (C + C.T)
        if not (np.isfinite(C).all() and np.linalg.eigvalsh(C)[0] > 0):
            raise PredictionInputError("the stiffness probe gave no finite positive-definite compliance on this "
                                       "mesh: a liver without supports, or a broken mesh")
        return C


def with_probe(preop: Preop, mesh, meta: dict, supports: dict | None = None, frame=None) -> Preop:
    """``preop`` with the probe compliance at its exertion point, from the liver's tet mesh.

    The mesh must be in the same frame and units (mm) as the context: the
    exertion point must lie on its surface. ``frame``: the inputs'
    :class:`~liverforce.serve.input_frame.InputFrame` (None: RAS mm, none declared), in which a refusal gives the
    point back.
    """
    from liverforce.mesh.supports import TriangleSet
    from liverforce.serve.checks import off_surface

    probe = LiverProbe(mesh, probe_settings(meta), supports)
    # to the surface's triangles, not its vertices: on a coarse mesh an exertion point (a P2 node, or a point the
    # user gave) lies far from every vertex while on the surface
    tri = TriangleSet(probe.surf.points[probe.surf.triangles])  # one search tree: the point and a refusal's readings
    near, dist, _ = tri.closest(preop.exertion_point_mm[None])
    d = float(dist[0])
    if d > MESH_TOL_MM:
        said = frame is not None and frame.declared
        raise OffSurfaceError(
            off_surface(d, preop.exertion_point_mm, near[0], MESH_TOL_MM, frame, tri, what="the mesh's surface")
            + " (the mesh and the context must be the same liver; the mesh is the mesh stage's copy, in RAS mm"
            + (")" if said else "; inputs in the liver file's own frame or units need --frame "
               "results/<exp>/geometry/imp-<name>.json, or --frame LPS and --units)"), preop.exertion_point_mm)
    return preop.with_compliance(probe.compliance(preop.exertion_point_mm, preop.frame))
