"""Boundary terms on the tetrahedral surface: elastic foundations, rib penalty, tool load.

Elastic foundation (Robin) on a facet region, springs per unit *reference*
area with separate normal and tangential stiffness (N/mm³):

.. math::

    t = -\\big(k_n\\, n \\otimes n + k_t (I - n \\otimes n)\\big)\\, u,
    \\qquad K^{s}_{ai,bk} = \\int_{\\Gamma} N_a N_b\\,
    \\big(k_n n_i n_k + k_t(\\delta_{ik} - n_i n_k)\\big)\\, dA

with ``n`` the reference outward normal (a linear, constant stiffness). The
rib region is the same term with a large ``k_n`` and ``k_t = 0`` (no normal
motion, free sliding by penalty).

Tool load: a dead load ``F`` (N) spread as a smooth traction of fixed
physical width around the exertion point ``x0``,

.. math::

    t(X) = F \\frac{g(X)}{\\int_\\Gamma g\\, dA}, \\qquad
    g(X) = \\exp\\Big(-\\frac{|X - x_0|^2}{2 r^2}\\Big),

restricted to facets facing the same way as the surface at ``x0`` and within
``4 r``. The nodal loads ``f_a = F \\int N_a g / \\int g`` sum exactly to ``F``
because the shape functions sum to one.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .elements import TRI_Q7, TetDiscretization, facet_geometry, tri_shape


def region_areas(points: np.ndarray, facets: np.ndarray, facet_region: np.ndarray) -> dict[int, float]:
    """Reference area (mm²) of each facet region id present."""
    area, _ = facet_geometry(np.asarray(points, float), facets)
    reg = np.asarray(facet_region)
    return {int(r): float(area[reg == r].sum()) for r in np.unique(reg)}


def per_area_stiffness(total_n_per_mm: float, area_mm2: float) -> float:
    """Foundation stiffness per unit area (N/mm³) from a region's total stiffness (N/mm).

    The study reports foundation stiffness as a single number per region
    (56.3 N/mm for the ligaments, 42.6 N/mm for the lower visceral face). We
    read it as the stiffness of the whole region when the region translates
    rigidly along its normal: ``k = total / area``, so that
    ``integral_region k dA = total``.
    """
    if not area_mm2 > 0:
        raise ValueError(f"region area must be positive to spread a total stiffness, got {area_mm2}")
    return float(total_n_per_mm) / float(area_mm2)


def _facet_quadrature(disc: TetDiscretization, points, facets):
    """Facet nodes, quadrature points, weights (area × w), shape values and normals."""
    fn = disc.facet_nodes(facets)
    area, normal = facet_geometry(points, facets)
    bary, wq = TRI_Q7
    N = tri_shape(disc.order, bary)  # (nq, nfn)
    X = points[facets]  # (k, 3, 3)
    Xq = np.einsum("qm,kmi->kqi", bary, X)
    W = area[:, None] * wq[None, :]
    return fn, Xq, W, N, normal, area


def vertex_normals(points: np.ndarray, facets: np.ndarray) -> np.ndarray:
    """Unit outward normals at the vertices (n, 3): area-weighted mean of the adjacent facet normals.

    Vertices on no facet get a zero vector.
    """
    points = np.asarray(points, float)
    facets = np.asarray(facets, np.int64)
    area, n = facet_geometry(points, facets)
    vn = np.zeros((len(points), 3))
    for i in range(3):
        np.add.at(vn, facets[:, i], area[:, None] * n)
    length = np.linalg.norm(vn, axis=1, keepdims=True)
    return np.divide(vn, length, out=np.zeros_like(vn), where=length > 0)


def spring_matrix(
    disc: TetDiscretization,
    points: np.ndarray,
    facets: np.ndarray,
    facet_region: np.ndarray,
    stiffness: dict[int, tuple[float, float]],
    normals: np.ndarray | None = None,
) -> sp.csr_matrix:
    """Global (n_dofs × n_dofs) foundation stiffness for regions ``{id: (k_n, k_t)}`` (N/mm³).

    ``normals`` : optional (n_vertices, 3) vertex normals (e.g. :func:`vertex_normals`),
    interpolated linearly over each facet and normalised at the quadrature points: a
    continuous normal field, so that a penalty on normal motion (``k_t = 0``) lets the
    surface slide along itself instead of locking at the kinks between flat facets.
    Default: the (piecewise constant) facet normals.
    """
    facets = np.asarray(facets, np.int64)
    reg = np.asarray(facet_region)
    rows, cols, vals = [], [], []
    for rid, (kn, kt) in stiffness.items():
        sel = reg == rid
        if not np.any(sel) or (kn == 0.0 and kt == 0.0):
            continue
        fn, _, W, N, n, _ = _facet_quadrature(disc, points, facets[sel])
        if normals is None or kn == kt:  # isotropic springs do not need a normal
            M = np.einsum("kq,qa,qb->kab", W, N, N)  # (k, nfn, nfn)
            S = kn * np.einsum("ki,kj->kij", n, n) + kt * (np.eye(3) - np.einsum("ki,kj->kij", n, n))
            blk = np.einsum("kab,kij->kaibj", M, S)  # (k, nfn, 3, nfn, 3)
        else:
            nq = np.einsum("qm,kmi->kqi", TRI_Q7[0], np.asarray(normals, float)[facets[sel]])
            nq /= np.maximum(np.linalg.norm(nq, axis=-1, keepdims=True), 1e-300)
            nn = np.einsum("kqi,kqj->kqij", nq, nq)
            S = kn * nn + kt * (np.eye(3) - nn)  # (k, nq, 3, 3)
            blk = np.einsum("kq,qa,qb,kqij->kaibj", W, N, N, S)
        dofs = (3 * fn[:, :, None] + np.arange(3)).reshape(len(fn), -1)
        nd = dofs.shape[1]
        rows.append(np.repeat(dofs, nd, axis=1).ravel())
        cols.append(np.tile(dofs, (1, nd)).ravel())
        vals.append(blk.reshape(len(fn), -1).ravel())
    n = disc.n_dofs
    if not rows:
        return sp.csr_matrix((n, n))
    K = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
    return K.tocsr()


def tool_nodal_forces(
    disc: TetDiscretization,
    points: np.ndarray,
    facets: np.ndarray,
    point_mm,
    force_n,
    radius_mm: float,
    facet_mask: np.ndarray | None = None,
) -> np.ndarray:
    """Consistent nodal loads (n_dofs,) of the Gaussian tool traction; they sum to ``force_n``.

    Parameters
    ----------
    disc : discretisation (P1 or P2 facets).
    points, facets : reference vertices (mm) and boundary triangles (outward normals).
    point_mm : (3,) exertion point (on or near the surface).
    force_n : (3,) total force (N), dead load.
    radius_mm : Gaussian width ``r`` (standard deviation, mm); 39 % of the
        force lies within ``r`` and 86 % within ``2 r`` on a flat surface.
    facet_mask : optional (k,) bool, facets allowed to carry the load.
    """
    x0 = np.asarray(point_mm, float).reshape(3)
    F = np.asarray(force_n, float).reshape(3)
    r = float(radius_mm)
    if not r > 0:
        raise ValueError(f"tool radius_mm must be positive, got {radius_mm}")
    facets = np.asarray(facets, np.int64)
    area, normal = facet_geometry(points, facets)
    cent = points[facets].mean(axis=1)
    dist = np.linalg.norm(cent - x0, axis=1)
    allowed = np.ones(len(facets), bool) if facet_mask is None else np.asarray(facet_mask, bool)
    if not np.any(allowed):
        raise ValueError("facet_mask allows no facet to carry the tool load")
    d_allowed = np.where(allowed, dist, np.inf)
    nearest = int(np.argmin(d_allowed))
    # surface orientation at x0: Gaussian-weighted mean normal of nearby facets
    near = allowed & (dist <= max(r, dist[nearest] * 1.0001))
    gw = area * np.exp(-0.5 * (dist / r) ** 2)
    n0 = (gw[near, None] * normal[near]).sum(axis=0)
    n0 = n0 / np.linalg.norm(n0) if np.linalg.norm(n0) > 0 else normal[nearest]
    cutoff = 4.0 * r + (area[nearest] ** 0.5)
    sel = allowed & (dist <= cutoff) & (normal @ n0 > 0.0)
    sel[nearest] = True
    fn, Xq, W, N, _, _ = _facet_quadrature(disc, points, facets[sel])
    g = np.exp(-0.5 * np.sum((Xq - x0) ** 2, axis=-1) / r**2) * W  # (k, nq)
    total = g.sum()
    if not total > 1e-300:
        raise ValueError(
            f"exertion point {x0} is {dist[nearest]:.3g} mm from the nearest facet, far beyond the "
            f"tool radius {r} mm: no surface under the tool"
        )
    wa = np.einsum("kq,qa->ka", g, N) / total  # (k, nfn), sums to 1
    f = np.zeros(disc.n_dofs)
    for i in range(3):
        np.add.at(f, 3 * fn.ravel() + i, wa.ravel() * F[i])
    return f
