"""Pre-operative linear stiffness probe: the compliance of a liver at points of its surface.

For a liver on its supports, the small-load response to the tool traction at
an exertion point ``p`` is linear: ``u_w = C f`` with ``u_w`` the displacement
averaged with the traction's own nodal weights and ``C`` (3 x 3, mm/N) the
*compliance at p*. It carries what the liver's shape, thickness and supports
do to the force-displacement map at that point, which global features
(centroid, inertia) do not. It costs one factorisation of the tangent at rest
per liver (and material) and three back-substitutions per point, all
pre-operative.

By reciprocity (Maxwell-Betti) ``C`` is symmetric: the load and the
displacement are paired through the same weights.

The data factory stores ``C`` for every case (shard column
``probe_compliance_mm_per_n``, :func:`liverforce.pipeline.simulate.probe_compliances`),
state-vector models read it (:mod:`liverforce.learn.state`) together with the
linear force estimate ``C^-1 u_w`` (:mod:`liverforce.learn.model`), and serving
recomputes it from a liver's mesh (:mod:`liverforce.serve.probe`).
``benchmarks/experiment_probe_features.py`` measures what it adds.
"""

from __future__ import annotations

import numpy as np

from liverforce.fem.linsolve import LinearSolver
from liverforce.fem.materials import Material
from liverforce.fem.problem import LiverModel, ToolLoad


class ComplianceProbe:
    """Linear compliance of one liver model at any surface point.

    Parameters
    ----------
    fe : LiverModel
        The liver with its supports (the same boundary terms as the simulation).
    material : Material, optional
        The material of the probe (default the model's); the rest tangent is
        factorised once for it.
    """

    def __init__(self, fe: LiverModel, material: Material | None = None):
        self.fe = fe
        mat = material or fe.material
        system = fe.system
        ev = system.assembler.evaluate(np.zeros(fe.n_dofs), mat, True)
        if not ev.valid:
            raise ValueError("the rest configuration has an inverted element; the mesh cannot be probed")
        self._linear = LinearSolver(system.linear.method)
        self._linear.factorize(system.tangent_matrix(ev.data))
        self._free = system.free

    def displacement(self, f_ext: np.ndarray) -> np.ndarray:
        """Linear displacement (n_dofs,) in mm under nodal loads ``f_ext`` (N)."""
        u = np.zeros(self.fe.n_dofs)
        u[self._free] = self._linear.solve(np.asarray(f_ext, float)[self._free])
        return u

    def compliance(self, point_mm, frame, radius_mm: float) -> np.ndarray:
        """Compliance (3, 3) mm/N at ``point_mm`` in the frame ``frame`` (rows t1, t2, n).

        Entry ``(a, b)``: the displacement along axis ``a``, averaged with the
        traction weights, per newton of traction along axis ``b``.
        """
        frame = np.asarray(frame, float).reshape(3, 3)
        p = np.asarray(point_mm, float)
        weights = [self.fe.nodal_loads(ToolLoad(point_mm=p, force_N=frame[a], radius_mm=float(radius_mm)))
                   for a in range(3)]
        U = [self.displacement(w) for w in weights]
        return np.array([[weights[a] @ U[b] for b in range(3)] for a in range(3)])
