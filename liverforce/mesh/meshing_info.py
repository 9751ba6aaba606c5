"""What a meshing run reports: its provenance (:class:`MeshingInfo`) or its failure (:class:`MeshingError`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


class MeshingError(RuntimeError):
    """The mesher could not produce a valid tetrahedral mesh."""


@dataclass
class MeshingInfo:
    """How a mesh was made (JSON-friendly via :meth:`as_dict`)."""

    mesher: str = "gmsh"
    gmsh_version: str = ""
    route: str = ""
    edge_length_mm: float = 0.0
    target_nodes: int | None = None
    attempts: list[dict] = field(default_factory=list)
    refine: dict | None = None
    seed: int = 0
    #: with ``surface_labels``: boundary triangles of the output (indices into
    #: the returned points) and the label of the surface patch each lies on
    #: (not serialised by :meth:`as_dict`)
    boundary_triangles: np.ndarray | None = field(default=None, repr=False)
    boundary_labels: np.ndarray | None = field(default=None, repr=False)

    def as_dict(self) -> dict:
        return {
            "mesher": self.mesher,
            "gmsh_version": self.gmsh_version,
            "route": self.route,
            "edge_length_mm": self.edge_length_mm,
            "target_nodes": self.target_nodes,
            "attempts": self.attempts,
            "refine": self.refine,
            "seed": self.seed,
        }
