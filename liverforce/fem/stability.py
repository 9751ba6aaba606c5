"""Drucker stability of hyperelastic constants (ANSYS-style check).

Drucker's postulate asks for positive incremental work ``d tau : d eps > 0``
(Kirchhoff stress, logarithmic strain) for *every* strain increment. For an
incompressible isotropic material in a principal state this is positive
definiteness of the 2 × 2 tangent ``D = d tau / d eps`` of
:func:`liverforce.fem.homogeneous.log_strain_tangent` (directions 1, 2; the
pressure makes ``tau_3 = 0``). As ANSYS does, the check walks the three test
modes (uniaxial, equibiaxial, planar) over a stretch range and records where
the smallest eigenvalue of ``D`` stays positive. Checking only the loaded
direction (``d tau_1 d eps_1 > 0``) would miss the transverse instability
that makes, e.g., uniaxial compression of the study's MR5 set unstable at
``lam < 0.87``.

Example
-------
>>> from liverforce.fem.materials import make_material
>>> mr5 = make_material("mooney_rivlin_5", {"C10": -584.5e-6, "C01": 863.5e-6,
...     "C20": -6228.9e-6, "C11": 3228.7e-6, "C02": 3328.3e-6}, nu=0.49)
>>> report = check_stability(mr5, (0.5, 2.0))
>>> report.stable, [round(x, 3) for x in report.modes["uniaxial"].around_one]
(False, [0.865, 1.105])
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import brentq

from .homogeneous import MODES, log_strain_tangent, mode_stretches


class UnstableMaterialError(ValueError):
    """Raised when material constants are not Drucker-stable over the required range."""


@dataclass
class ModeStability:
    """Stability of one test mode over the checked stretch range.

    Attributes
    ----------
    intervals : list of (lo, hi) stretch intervals where ``D`` is positive definite.
    around_one : the stable interval containing ``lam = 1`` (``None`` if ``lam = 1``
        itself is unstable, i.e. ``mu0 <= 0``).
    stable : True if the whole checked range is stable.
    """

    mode: str
    intervals: list[tuple[float, float]]
    around_one: tuple[float, float] | None
    stable: bool


@dataclass
class StabilityReport:
    """Verdict of :func:`check_stability`."""

    model: str
    params: dict
    stretch_range: tuple[float, float]
    modes: dict[str, ModeStability] = field(default_factory=dict)

    @property
    def stable(self) -> bool:
        """True if every mode is stable over the whole ``stretch_range``."""
        return all(m.stable for m in self.modes.values())

    @property
    def message(self) -> str:
        lo, hi = self.stretch_range
        if self.stable:
            return f"{self.model} {self.params} is Drucker-stable for stretches {lo:g}-{hi:g} in all modes"
        parts = []
        for m in self.modes.values():
            if not m.stable:
                a = m.around_one
                rng = "unstable at zero strain" if a is None else f"stable only {a[0]:.3g}-{a[1]:.3g}"
                parts.append(f"{m.mode}: {rng}")
        return (
            f"{self.model} constants {self.params} (MPa) are not Drucker-stable over stretch "
            f"{lo:g}-{hi:g}: " + "; ".join(parts) + ". Refit the constants, or restrict the "
            "sweep (force range) so strains stay in the stable range."
        )

    def raise_if_unstable(self) -> None:
        """Raise :class:`UnstableMaterialError` with :attr:`message` if not stable."""
        if not self.stable:
            raise UnstableMaterialError(self.message)


def _min_eig(material, mode, lam):
    s, _ = mode_stretches(mode, lam)
    return np.linalg.eigvalsh(log_strain_tangent(material, s))[..., 0]


def check_stability(material, stretch_range=(0.5, 2.0), n: int = 2001) -> StabilityReport:
    """Drucker stability of ``material`` along the three incompressible test modes.

    Parameters
    ----------
    material : :class:`~liverforce.fem.materials.Material`
    stretch_range : (lo, hi) stretches in the loaded direction, ``lo < 1 < hi``.
    n : grid points per mode (log-spaced); boundaries are refined by root finding.

    Returns
    -------
    StabilityReport
        Per-mode stable intervals, the interval around ``lam = 1`` and a verdict.
    """
    lo, hi = map(float, stretch_range)
    if not (0.0 < lo < 1.0 < hi):
        raise ValueError(f"stretch_range must satisfy 0 < lo < 1 < hi, got {stretch_range}")
    lam = np.unique(np.concatenate([np.geomspace(lo, hi, n), [1.0]]))
    report = StabilityReport(material.model, dict(material.params), (lo, hi))
    for mode in MODES:
        ev = _min_eig(material, mode, lam)
        ok = ev > 0.0
        intervals: list[tuple[float, float]] = []
        i = 0
        while i < len(lam):
            if not ok[i]:
                i += 1
                continue
            j = i
            while j + 1 < len(lam) and ok[j + 1]:
                j += 1
            a = lam[i] if i == 0 else _edge(material, mode, lam[i - 1], lam[i])
            b = lam[j] if j == len(lam) - 1 else _edge(material, mode, lam[j], lam[j + 1])
            intervals.append((float(a), float(b)))
            i = j + 1
        around = next((iv for iv in intervals if iv[0] <= 1.0 <= iv[1]), None)
        stable = bool(ok.all())
        report.modes[mode] = ModeStability(mode, intervals, around, stable)
    return report


def _edge(material, mode, a, b):
    f = lambda x: float(_min_eig(material, mode, np.array([x]))[0])  # noqa: E731
    try:
        return brentq(f, a, b, xtol=1e-10)
    except ValueError:
        return 0.5 * (a + b)


def require_stable(material, stretch_range=(0.5, 2.0)) -> StabilityReport:
    """:func:`check_stability` that raises :class:`UnstableMaterialError` if unstable."""
    report = check_stability(material, stretch_range)
    report.raise_if_unstable()
    return report
