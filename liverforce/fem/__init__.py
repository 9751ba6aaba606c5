"""Finite-element mechanics of the liver: materials, stability, fitting, solver.

Units: mm, N, MPa (N/mm²). Public entry points:

* :func:`make_material` — hyperelastic models (neo-Hookean, Mooney–Rivlin
  2/3/5, Yeoh, Ogden) with a volumetric term.
* :func:`check_stability` — Drucker stability over a stretch range.
* :func:`fit_material` — least-squares fit to stress–stretch data.
* :class:`LiverModel` / :func:`solve_case` — static large-deformation solve of
  a tool pushing on a meshed liver.
* :class:`LiverIndenter` / :class:`SphereContact` / :func:`indent` — the tool as a
  rigid sphere in frictionless contact (penalty, augmented Lagrangian), displacement-controlled.
"""

_LAZY = {
    "FitResult": "fitting", "fit_material": "fitting",
    "Material": "materials", "available_models": "materials", "bulk_from_poisson": "materials",
    "make_material": "materials",
    "LiverIndenter": "indenter", "SphereContact": "indenter", "indent": "indenter",
    "DiscreteSystem": "newton", "NewtonResult": "newton", "SolverOptions": "newton",
    "BoundaryParams": "problem", "CaseResult": "problem", "LiverModel": "problem", "ToolLoad": "problem",
    "solve_case": "problem",
    "StabilityReport": "stability", "UnstableMaterialError": "stability", "check_stability": "stability",
    "require_stable": "stability",
}


def __getattr__(name: str):
    """Lazy exports: the config check imports ``fem.materials`` / ``fem.assembly`` for their registries
    and must not pay for scipy.optimize and numba (the fitting and solver modules) at start-up."""
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    raise AttributeError(name)


__all__ = [
    "BoundaryParams",
    "CaseResult",
    "DiscreteSystem",
    "FitResult",
    "LiverIndenter",
    "LiverModel",
    "Material",
    "NewtonResult",
    "SolverOptions",
    "SphereContact",
    "StabilityReport",
    "ToolLoad",
    "UnstableMaterialError",
    "available_models",
    "bulk_from_poisson",
    "check_stability",
    "fit_material",
    "indent",
    "make_material",
    "require_stable",
    "solve_case",
]
