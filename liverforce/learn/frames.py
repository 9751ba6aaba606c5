"""The local frame at the exertion point: source frame <-> local frame.

Every case carries an orthonormal, right-handed frame at its exertion point
``p``: two surface tangents ``t1``, ``t2`` and the outward normal ``n``
(``t1 x t2 = n``). Stacking them as rows gives the rotation

    R = [t1; t2; n]        (3 x 3, rows),

and a point ``x`` (mm) or a force ``F`` (N) given in the source (e.g. CT)
frame has local coordinates

    x_loc = R (x - p),     F_loc = R F,     and back  F = R^T F_loc.

A rigid motion ``x -> Q x + c`` of the whole liver (with its frame, forces and
point clouds) leaves ``x_loc`` and ``F_loc`` unchanged, which is what makes
features and targets comparable across exertion points and geometries.

The rotations of a set of cases are computed once, by :func:`case_rotations`,
and passed as an argument to every step that needs them (features, state
vector, camera features, targets, the force back in the source frame):
:mod:`liverforce.learn.model` does this once per ``prepare`` and per
prediction, the serving context (:class:`liverforce.serve.preop.Preop`) once
per exertion point (``Preop.rotation``).

Example
-------
>>> import numpy as np
>>> R = local_rotations(np.eye(3)[[2]], np.eye(3)[[0]], np.eye(3)[[1]])
>>> force_to_local(np.array([[0.0, 0.0, -2.0]]), R)
array([[ 0.,  0., -2.]])
"""

from __future__ import annotations

import numpy as np

#: largest accepted deviation of a given frame from orthonormal + right-handed
FRAME_TOL = 1e-3


def local_rotations(normal: np.ndarray, t1: np.ndarray, t2: np.ndarray) -> np.ndarray:
    """Rotation matrices ``R_i = [t1_i; t2_i; n_i]`` (rows), shape ``(n, 3, 3)``.

    Parameters
    ----------
    normal, t1, t2 : (n, 3) array_like
        Outward unit normal and the two unit tangents at each exertion point,
        in the source frame.

    Returns
    -------
    (n, 3, 3) float64
        Orthonormal rotations. Frames within ``FRAME_TOL`` of orthonormal are
        re-orthonormalised (Gram-Schmidt from ``n`` then ``t1``) so the result
        is exact to rounding.

    Raises
    ------
    ValueError
        If a frame is not orthonormal or not right-handed (``t1 x t2 != n``);
        the message names the first offending row.
    """
    n = np.atleast_2d(np.asarray(normal, dtype=np.float64))
    a = np.atleast_2d(np.asarray(t1, dtype=np.float64))
    b = np.atleast_2d(np.asarray(t2, dtype=np.float64))
    if not (n.shape == a.shape == b.shape) or n.shape[-1] != 3:
        raise ValueError(
            f"frame_normal/frame_t1/frame_t2 must all have shape (n, 3); got {n.shape}, {a.shape}, {b.shape}"
        )
    R = np.stack([a, b, n], axis=1)
    err_orth = np.abs(R @ np.transpose(R, (0, 2, 1)) - np.eye(3)).max(axis=(1, 2))
    err_hand = np.abs(np.cross(a, b) - n).max(axis=1)
    bad = np.flatnonzero((err_orth > FRAME_TOL) | (err_hand > FRAME_TOL) | ~np.isfinite(err_orth))
    if bad.size:
        i = int(bad[0])
        raise ValueError(
            f"case row {i}: the local frame (frame_t1, frame_t2, frame_normal) is not orthonormal and "
            f"right-handed (orthonormality error {err_orth[i]:.2e}, |t1 x t2 - n| {err_hand[i]:.2e}); "
            "the dataset stage must write unit tangents with t1 x t2 = n"
        )
    # Gram-Schmidt: keep n, make t1 orthogonal to it, t2 = n x t1.
    nn = n / np.linalg.norm(n, axis=1, keepdims=True)
    aa = a - np.sum(a * nn, axis=1, keepdims=True) * nn
    aa /= np.linalg.norm(aa, axis=1, keepdims=True)
    bb = np.cross(nn, aa)
    return np.stack([aa, bb, nn], axis=1)


def case_rotations(arrays: dict) -> np.ndarray:
    """The local rotations ``(n, 3, 3)`` of the cases in an input-contract dict.

    :func:`local_rotations` of ``frame_normal``, ``frame_t1``, ``frame_t2``: the
    one place a set of cases gets its local frame. Compute it once and pass it
    on (``R=`` of :meth:`~liverforce.learn.representation.Representation.features_of`,
    :func:`~liverforce.learn.state.state_vector`, ...).
    """
    return local_rotations(arrays["frame_normal"], arrays["frame_t1"], arrays["frame_t2"])


def points_to_local(points: np.ndarray, origin: np.ndarray, R: np.ndarray) -> np.ndarray:
    """``R (x - p)`` for one case: points ``(k, 3)`` mm -> local ``(k, 3)`` mm (float64)."""
    return (np.asarray(points, dtype=np.float64) - np.asarray(origin, dtype=np.float64)) @ R.T


def vectors_to_local(v: np.ndarray, R: np.ndarray) -> np.ndarray:
    """``R_i v_i`` for many cases: ``(n, 3)`` source -> ``(n, 3)`` local."""
    return np.einsum("nij,nj->ni", R, np.asarray(v, dtype=np.float64))


def offsets_to_local(x: np.ndarray, origin: np.ndarray, R: np.ndarray) -> np.ndarray:
    """``R_i (x_i - p_i)`` for many cases: positions ``(n, 3)`` mm -> local ``(n, 3)`` mm."""
    return vectors_to_local(np.asarray(x, dtype=np.float64) - np.asarray(origin, dtype=np.float64), R)


def tip_offsets(tip, origin, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A tool tip's offsets from the exertion point ``origin`` in its local frame ``R`` (rows ``t1, t2, n``):
    ``(along, above)``, the larger of its ``|t1|``, ``|t2|`` parts (along the surface: the camera grid sees the
    tool while this is within the grid's half-width) and its ``n`` part (outward positive: a press is negative).
    One tip ``(3,)`` or many ``(..., 3)`` at one exertion point; many at their own, ``origin (n, 3)`` and ``R
    (n, 3, 3)``."""
    R = np.asarray(R, dtype=np.float64)
    d = np.asarray(tip, dtype=np.float64) - np.asarray(origin, dtype=np.float64)
    local = np.einsum("nij,nj->ni", R, d) if R.ndim == 3 else d @ R.T
    return np.abs(local[..., :2]).max(axis=-1), local[..., 2]


def force_to_local(force: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Force ``(n, 3)`` N in the source frame -> local frame ``(F.t1, F.t2, F.n)``."""
    return vectors_to_local(force, R)


def force_to_source(force_local: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Local force ``(n, 3)`` N -> source frame, ``F = R^T F_loc``."""
    return np.einsum("nji,nj->ni", R, np.asarray(force_local, dtype=np.float64))
