"""Homogeneous incompressible test modes: stretch paths and nominal stresses.

The three standard modes of material testing, each parametrised by the
stretch ``lam`` in the loaded direction 1 (incompressible, ``J = 1``):

===============  ==================================  ================================
mode             principal stretches                 nominal stress (loaded directions)
===============  ==================================  ================================
``uniaxial``     ``(lam, lam^-1/2, lam^-1/2)``       ``T = dW/d lam``
``equibiaxial``  ``(lam, lam, lam^-2)``              ``T = (1/2) dW/d lam``
``planar``       ``(lam, 1, 1/lam)`` (pure shear)    ``T = dW/d lam``
===============  ==================================  ================================

where ``W(lam)`` is the isochoric energy along the path; the hydrostatic
pressure makes direction 3 (and the lateral directions in uniaxial tension)
traction free.
"""

from __future__ import annotations

import numpy as np

MODES = ("uniaxial", "equibiaxial", "planar")


def mode_stretches(mode: str, lam) -> tuple[np.ndarray, np.ndarray]:
    """Principal stretches ``(..., 3)`` along a mode and their derivative in ``lam``."""
    lam = np.asarray(lam, dtype=float)
    one = np.ones_like(lam)
    if mode == "uniaxial":
        s = np.stack([lam, lam**-0.5, lam**-0.5], -1)
        d = np.stack([one, -0.5 * lam**-1.5, -0.5 * lam**-1.5], -1)
    elif mode == "equibiaxial":
        s = np.stack([lam, lam, lam**-2.0], -1)
        d = np.stack([one, one, -2.0 * lam**-3.0], -1)
    elif mode == "planar":
        s = np.stack([lam, one, 1.0 / lam], -1)
        d = np.stack([one, 0.0 * lam, -(lam**-2.0)], -1)
    else:
        raise ValueError(f"unknown test mode {mode!r}; choose one of {MODES}")
    return s, d


def nominal_stress(material, mode: str, lam) -> np.ndarray:
    """Nominal (engineering, 1st PK) stress in MPa along an incompressible test mode.

    Parameters
    ----------
    material : :class:`~liverforce.fem.materials.Material`
    mode : ``"uniaxial"``, ``"equibiaxial"`` or ``"planar"``
    lam : stretch(es) in the loaded direction.
    """
    s, d = mode_stretches(mode, lam)
    _, dW = material.incompressible_dW(s)
    T = np.sum(dW * d, axis=-1)
    return 0.5 * T if mode == "equibiaxial" else T


def log_strain_tangent(material, stretches: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """Incompressible tangent ``D_ij = d tau_i / d eps_j`` (i, j = 1, 2), MPa.

    With logarithmic strains ``eps_a = ln lam_a``, ``eps_3 = -eps_1 - eps_2``
    and ``w(eps_1, eps_2) = W(lam)``, the Kirchhoff stresses with
    ``tau_3 = 0`` are ``tau_i = dw/d eps_i`` and ``D`` is the Hessian of
    ``w``. The first derivatives are analytic; ``D`` is their central
    difference with step ``h`` (error ~1e-9 relative), then symmetrised.
    Returns shape ``(..., 2, 2)``.
    """
    e = np.log(np.asarray(stretches, dtype=float))

    def grad(e1, e2):
        lam = np.exp(np.stack([e1, e2, -e1 - e2], -1))
        _, dW = material.incompressible_dW(lam)
        t = lam * dW
        return np.stack([t[..., 0] - t[..., 2], t[..., 1] - t[..., 2]], -1)

    e1, e2 = e[..., 0], e[..., 1]
    c1 = (grad(e1 + h, e2) - grad(e1 - h, e2)) / (2 * h)
    c2 = (grad(e1, e2 + h) - grad(e1, e2 - h)) / (2 * h)
    D = np.stack([c1, c2], -1)  # D[..., i, j] = d tau_i / d eps_j
    return 0.5 * (D + np.swapaxes(D, -1, -2))
