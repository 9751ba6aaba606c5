"""Warm starts across the cases of one geometry (continuation in load space).

A sweep solves many cases on one mesh. Newton from a converged neighbouring
case needs one factorisation and a few cheap iterations; from rest it needs
load stepping. How far apart two cases are is measured as a change of load
(N) that Newton has to make up:

* same exertion point: ``|F_a - F_b|``;
* different points: ``sqrt(|F_a|^2 + |F_b|^2)`` (the dent at one point must be
  undone and the other made: as far as going through rest);
* different material constants: the out-of-balance force of a stiffness
  change at the same displacement is about the relative change times the
  load, so ``(|F_a| + |F_b|) / 2 * rms((p_a - p_b) / max(|p_a|, |p_b|))`` is
  added in quadrature;
* rest (no load, the cold start): ``|F|``.

:func:`case_distance` is that measure; :func:`chain_order` orders the cases at
one exertion point so that each is near its predecessor;
:class:`WarmStartPool` keeps the last converged solutions of a geometry and
picks the nearest one for a new case.
"""

from __future__ import annotations

from collections import deque

import numpy as np


def _relative_change(params_a, params_b) -> np.ndarray:
    """RMS relative change of material constants, row-wise for ``params_b`` of shape (n, k)."""
    a = np.asarray(params_a, dtype=float)
    b = np.asarray(params_b, dtype=float)
    scale = np.maximum(np.maximum(np.abs(a), np.abs(b)), 1e-300)
    return np.sqrt(np.mean(((a - b) / scale) ** 2, axis=-1))


def _distances(point, force, params, points, forces, params_rows, same_point_mm: float = 1e-6) -> np.ndarray:
    """:func:`case_distance` from one case to each row of ``points``, ``forces``, ``params_rows``."""
    f = np.asarray(force, dtype=float)
    F = np.asarray(forces, dtype=float).reshape(-1, 3)
    na, nb = float(np.linalg.norm(f)), np.linalg.norm(F, axis=1)
    same = np.linalg.norm(np.asarray(points, float).reshape(-1, 3) - np.asarray(point, float), axis=1) <= same_point_mm
    d_load = np.where(same, np.linalg.norm(F - f, axis=1), np.hypot(na, nb))
    return np.hypot(d_load, 0.5 * (na + nb) * _relative_change(params, params_rows))


def case_distance(point_a, force_a, params_a, point_b, force_b, params_b, same_point_mm: float = 1e-6) -> float:
    """Distance of two cases (N) for warm starts; see the module notes (inf for another material model)."""
    pa, pb = np.ravel(params_a), np.ravel(params_b)
    if pa.shape != pb.shape:
        return np.inf
    return float(_distances(point_a, force_a, pa, [point_b], [force_b], pb[None], same_point_mm)[0])


def chain_order(forces, params) -> list[int]:
    """Nearest-neighbour chain (:func:`case_distance`) over cases at one exertion point.

    ``forces`` (n, 3) in N, ``params`` (n, k) material constants. Starts at
    the smallest force; returns the visiting order. Deterministic: ties go to
    the lower index.
    """
    f = np.asarray(forces, dtype=float).reshape(-1, 3)
    if len(f) == 0:
        return []
    p = np.asarray(params, dtype=float).reshape(len(f), -1)
    at = np.zeros_like(f)  # one exertion point
    left = np.ones(len(f), bool)
    i = int(np.argmin(np.linalg.norm(f, axis=1)))
    order = []
    while True:
        order.append(i)
        left[i] = False
        if not left.any():
            return order
        i = int(np.argmin(np.where(left, _distances(at[i], f[i], p[i], at, f, p), np.inf)))


class WarmStartPool:
    """The last ``size`` converged solutions of one geometry; :meth:`nearest` picks a warm start.

    Parameters
    ----------
    size : solutions kept (each is one displacement vector of the model).
    """

    def __init__(self, size: int = 8):
        if size < 1:
            raise ValueError("WarmStartPool: size must be >= 1")
        self._items: deque = deque(maxlen=int(size))

    def __len__(self) -> int:
        return len(self._items)

    def add(self, result, params) -> None:
        """Keep a converged :class:`~liverforce.fem.problem.CaseResult` (its ``load`` set) with its constants."""
        if result is None or not result.converged or result.load is None:
            return
        self._items.append((result, np.asarray(params, dtype=float).copy()))

    def nearest(self, load, params):
        """The kept result nearest to ``(load, params)``, or None when rest (a cold start) is nearer."""
        best, best_d = None, float(np.linalg.norm(np.asarray(load.force_N, float)))
        for res, p in reversed(self._items):  # most recent first: it wins ties
            d = case_distance(res.load.point_mm, res.load.force_N, p, load.point_mm, load.force_N, params)
            if d < best_d:
                best, best_d = res, d
        return best
