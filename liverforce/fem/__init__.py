"""Finite-element mechanics of the liver: materials, stability, fitting, solver.

Units: mm, N, MPa (N/mm²). Public entry points:

* :func:`make_material` — hyperelastic models (neo-Hookean, Mooney–Rivlin
  2/3/5, Yeoh, Ogden) with a volumetric term.
* :func:`check_stability` — Drucker stability over a stretch range.
* :func:`fit_material` — least-squares fit to stress–stretch data.
* :class:`LiverModel` / :func:`solve_case` — static large-deformation solve of
  a tool pushing on a meshed liver.
"""

from .fitting import FitResult, fit_material
from .materials import Material, available_models, bulk_from_poisson, make_material
from .newton import DiscreteSystem, NewtonResult, SolverOptions
from .problem import BoundaryParams, CaseResult, LiverModel, ToolLoad, solve_case
from .stability import StabilityReport, UnstableMaterialError, check_stability, require_stable

__all__ = [
    "BoundaryParams",
    "CaseResult",
    "DiscreteSystem",
    "FitResult",
    "LiverModel",
    "Material",
    "NewtonResult",
    "SolverOptions",
    "StabilityReport",
    "ToolLoad",
    "UnstableMaterialError",
    "available_models",
    "bulk_from_poisson",
    "check_stability",
    "fit_material",
    "make_material",
    "require_stable",
    "solve_case",
]
