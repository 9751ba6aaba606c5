"""The coordinate frame of an imported file and its conversion to the internal RAS frame.

Internally every geometry is in **RAS millimetres** (the NIfTI world
convention, right-handed): ``+x`` patient right, ``+y`` anterior, ``+z``
superior.  An imported file states its frame with ``frame``:

``"RAS"`` (default)
    The file is already RAS; nothing is changed.
``"LPS"``
    3D Slicer model exports (its default since Slicer 4.11) and DICOM:
    ``+x`` left, ``+y`` posterior, ``+z`` superior.  Converted by
    ``(x, y, z) -> (-x, -y, z)``.  This is a rotation of 180° about the
    superior axis (determinant +1), not a reflection: triangle orientation
    is kept.
a 4×4 matrix ``M`` (list of 4 rows of 4 numbers)
    An affine map from the file's coordinates, **after unit scaling to mm**,
    to RAS mm, acting on column vectors::

        [x_ras, y_ras, z_ras, 1]^T = M @ [s·x_file, s·y_file, s·z_file, 1]^T

    with ``s`` the ``units`` scale (mm per file unit); the translation
    ``M[:3, 3]`` is in mm; the last row must be ``[0, 0, 0, 1]``.  E.g.
    ``[[-1,0,0,0],[0,-1,0,0],[0,0,1,0],[0,0,0,1]]`` is the same as
    ``"LPS"``.  A matrix with a negative determinant (a reflection) reverses
    the triangle winding, so the winding is reversed back to keep the normals
    outward.  A matrix that also scales or shears is accepted and reported.

Label volumes (NIfTI, NRRD) carry their frame in the header and are already
converted to RAS by :mod:`liverforce.geometry.volumes`; for them ``frame``
must stay ``"RAS"`` (or be a 4×4 applied to the header's RAS coordinates,
e.g. a registration).
"""

from __future__ import annotations

import numpy as np

from liverforce.geometry.errors import refuse

#: Named frames: 3×3 linear map from the named frame to RAS.
NAMED_FRAMES = {"RAS": np.eye(3), "LPS": np.diag([-1.0, -1.0, 1.0])}

_FRAME_HINT = ("Use frame: RAS, frame: LPS (3D Slicer models, DICOM), or a 4x4 matrix "
               "[[r11,r12,r13,t1],[r21,r22,r23,t2],[r31,r32,r33,t3],[0,0,0,1]] mapping file mm to RAS mm")


def frame_matrix(frame, path=None) -> tuple[np.ndarray, str]:
    """The 4×4 map to RAS of a stated frame, and its label.

    Parameters
    ----------
    frame : {"RAS", "LPS"} or array_like of shape (4, 4) or None
        The frame of the file's coordinates (case-insensitive names; ``None``
        means RAS).  See the module docstring for the matrix convention.
    path : str or Path, optional
        Named in error messages.

    Returns
    -------
    matrix : numpy.ndarray
        ``(4, 4)`` float64 affine, file mm → RAS mm.
    label : str
        ``"RAS"``, ``"LPS"`` or ``"matrix"``.

    Raises
    ------
    GeometryError
        On an unknown name, a malformed or singular matrix.

    Examples
    --------
    >>> frame_matrix("lps")[0][:3, :3].diagonal().tolist()
    [-1.0, -1.0, 1.0]
    """
    if frame is None:
        frame = "RAS"
    if isinstance(frame, str):
        key = frame.strip().upper()
        if key not in NAMED_FRAMES:
            raise refuse(path, f"unknown frame {frame!r}", _FRAME_HINT)
        m = np.eye(4)
        m[:3, :3] = NAMED_FRAMES[key]
        return m, key
    try:
        m = np.array(frame, dtype=np.float64)
    except (TypeError, ValueError):
        raise refuse(path, f"frame {frame!r} is neither a name nor a 4x4 matrix of numbers", _FRAME_HINT) from None
    if m.shape != (4, 4):
        raise refuse(path, f"frame matrix has shape {m.shape}, expected 4x4 (4 rows of 4 numbers)", _FRAME_HINT)
    if not np.isfinite(m).all():
        raise refuse(path, "frame matrix holds NaN or infinite values", _FRAME_HINT)
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise refuse(path, f"frame matrix last row is {m[3].tolist()}, expected [0, 0, 0, 1] "
                           "(an affine transform)", _FRAME_HINT)
    det = float(np.linalg.det(m[:3, :3]))
    if abs(det) < 1e-9:
        raise refuse(path, f"frame matrix is singular (determinant of its 3x3 part {det:.3g})",
                     "Give an invertible transform (a rotation, possibly with a reflection)")
    return m, "matrix"


def to_ras(vertices: np.ndarray, faces: np.ndarray, matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
    """Apply a frame's 4×4 map to vertices in mm, keeping the triangles outward.

    Parameters
    ----------
    vertices : numpy.ndarray
        ``(n, 3)`` coordinates in mm, in the file's frame.
    faces : numpy.ndarray
        ``(k, 3)`` triangles.
    matrix : numpy.ndarray
        ``(4, 4)`` from :func:`frame_matrix`.

    Returns
    -------
    vertices, faces : numpy.ndarray
        RAS mm; ``faces`` has its winding reversed when ``det(M[:3, :3]) < 0``.
    info : dict
        ``determinant``, ``winding_reversed`` (bool), ``rigid`` (bool: the
        3×3 part is orthogonal) and ``singular_values``.

    Notes
    -----
    A triangle ``(a, b, c)`` has normal ``(b−a)×(c−a)``; under a linear map
    ``A`` it becomes ``det(A) A^{-T} n``, so a negative determinant turns
    outward normals inward, which reversing each triangle's vertex order undoes.
    """
    lin, shift = matrix[:3, :3], matrix[:3, 3]
    det = float(np.linalg.det(lin))
    sv = np.linalg.svd(lin, compute_uv=False)
    out = np.asarray(vertices, dtype=np.float64) @ lin.T + shift
    faces = np.asarray(faces, dtype=np.int64)
    if det < 0:
        faces = faces[:, ::-1].copy()
    info = {
        "determinant": det,
        "winding_reversed": det < 0,
        "rigid": bool(np.allclose(sv, 1.0, atol=1e-6)),
        "singular_values": [float(s) for s in sv],
    }
    return out, faces, info


def describe_frame(label: str, matrix: np.ndarray, info: dict | None = None) -> str:
    """One human-readable line saying what the frame conversion did."""
    if label == "RAS":
        return "frame RAS: coordinates kept (+x right, +y anterior, +z superior)"
    if label == "LPS":
        return "frame LPS: x and y negated to RAS (a 180 degree rotation about the superior axis; winding kept)"
    text = f"frame matrix: file mm mapped to RAS mm by {np.round(matrix, 6).tolist()}"
    if info:
        text += f" (determinant {info['determinant']:.4g}"
        if info["winding_reversed"]:
            text += ", a reflection: triangle winding reversed to keep the normals outward"
        if not info["rigid"]:
            text += f"; NOT rigid: it scales/shears (singular values {np.round(info['singular_values'], 4).tolist()})"
        text += ")"
    return text
