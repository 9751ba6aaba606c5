"""Boundary terms on the tetrahedral surface: elastic foundations, rib penalty, tool load.

Elastic foundation (Robin) on a facet region, springs per unit *reference*
area with separate normal and tangential stiffness (N/mm³):

.. math::

    t = -\\big(k_n\\, n \\otimes n + k_t (I - n \\otimes n)\\big)\\, u,
    \\qquad K^{s}_{ai,bk} = \\int_{\\Gamma} N_a N_b\\,
    \\big(k_n n_i n_k + k_t(\\delta_{ik} - n_i n_k)\\big)\\, dA

with ``n`` the reference outward normal (a linear, constant stiffness). The
normal and tangential stiffnesses are independent parameters (the config sets
``k_t = tangential_ratio * k_n``). The rib region is, by default, the same term
with a large ``k_n`` and ``k_t = 0`` (no normal motion, free sliding by
penalty): a *bilateral* support that holds the liver back when it is pulled
away as firmly as when it is pushed in.

Unilateral rib contact (:class:`UnilateralPenalty`): the rib only pushes. With
``n`` the liver's outward normal on the rib region (the rib lies outside, so
motion along ``+n`` goes into the rib) the normal gap is ``g_n = -u . n``
(small sliding, reference normals, ribs touching at rest) and the penalty
energy is

.. math::

    \Pi_c(u) = \int_{\Gamma_{rib}} \tfrac12 k_n \langle g_n \rangle_-^2\, dA,
    \qquad \langle g \rangle_- = \min(g, 0),

evaluated at the 7 facet quadrature points. Residual
``f_ai = int k_n <u.n>_+ N_a n_i dA`` (it only pushes the liver inward) and the
generalised (semismooth Newton) tangent
``K_ai,bk = int k_n H(u.n) N_a N_b n_i n_k dA`` over the active set
``u.n >= 0`` (points touching the rib count as active, so at rest and under a
push the tangent equals the bilateral one). Where every quadrature point is in
contact the term equals the bilateral penalty exactly.

Gravity (:func:`gravity_body_force`, :func:`body_force_loads`): a dead body
force density ``b = rho g d`` (N/mm³) on the reference volume, nodal loads
``f_a = int N_a b dV``; they sum to the liver's weight ``V rho g``.

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


#: standard gravity (m/s²)
STANDARD_GRAVITY = 9.80665


def gravity_body_force(density_kg_per_m3: float, direction=(0.0, 0.0, -1.0),
                       g_m_per_s2: float = STANDARD_GRAVITY) -> np.ndarray:
    """Body force density (3,) in N/mm³ of a tissue of density ``rho`` (kg/m³) under gravity.

    ``rho g`` is in N/m³ (kg/m³ x m/s²); 1 m³ = 1e9 mm³, so
    ``b = rho * g * 1e-9`` N/mm³ along the unit ``direction`` (normalised
    here). Liver, 1060 kg/m³: 1.0395e-5 N/mm³, i.e. 13.1 N for a 1.26 L liver.
    """
    d = np.asarray(direction, float).reshape(3)
    length = np.linalg.norm(d)
    if not length > 0:
        raise ValueError(f"gravity direction must be a non-zero 3-vector, got {direction}")
    if not density_kg_per_m3 >= 0:
        raise ValueError(f"density must be >= 0 kg/m³, got {density_kg_per_m3}")
    return float(density_kg_per_m3) * float(g_m_per_s2) * 1e-9 * d / length


def body_force_loads(disc: TetDiscretization, body_force_n_per_mm3) -> np.ndarray:
    """Consistent nodal loads (n_dofs,) of a uniform dead body force ``b`` (N/mm³): ``f_a = b int N_a dV``.

    Exact integrals on straight tets: P1 ``V/4`` per vertex; P2 ``-V/20`` per
    vertex and ``V/5`` per edge node. They sum to ``b * sum(V)``.
    """
    b = np.asarray(body_force_n_per_mm3, float).reshape(3)
    V = disc.volume
    if disc.order == 1:
        share = np.broadcast_to(np.array([0.25] * 4), (len(V), 4))
    else:
        share = np.broadcast_to(np.array([-0.05] * 4 + [0.2] * 6), (len(V), 10))
    nodal = np.bincount(disc.conn.ravel(), weights=(V[:, None] * share).ravel(), minlength=disc.n_nodes)
    return (nodal[:, None] * b[None, :]).ravel()


class UnilateralPenalty:
    """Frictionless unilateral normal penalty on a facet set: ``0.5 k_n <u.n>_+^2`` per unit area.

    Parameters
    ----------
    disc : discretisation (P1 or P2 facets).
    points : (n, 3) reference vertices (mm).
    facets : (k, 3) the contact facets (outward normals: the obstacle lies along ``+n``).
    kn : penalty stiffness (N/mm³).
    normals : optional (n_vertices, 3) vertex normals interpolated at the quadrature points
        (as :func:`spring_matrix`); default the facet normals.

    The static block structure (``rows``, ``cols``: full dofs of every facet's
    ``(3 nfn)²`` block) is fixed; :meth:`tangent_values` gives its values at a
    state ``u`` in the same order.
    """

    def __init__(self, disc: TetDiscretization, points, facets, kn: float, normals=None):
        points = np.asarray(points, float)
        facets = np.asarray(facets, np.int64).reshape(-1, 3)
        self.kn = float(kn)
        self.n_dofs = disc.n_dofs
        fn, _, W, N, n, _ = _facet_quadrature(disc, points, facets)
        nq = len(TRI_Q7[1])
        if normals is None:
            nqv = np.broadcast_to(n[:, None, :], (len(facets), nq, 3)).copy()
        else:
            nqv = np.einsum("qm,kmi->kqi", TRI_Q7[0], np.asarray(normals, float)[facets])
            nqv /= np.maximum(np.linalg.norm(nqv, axis=-1, keepdims=True), 1e-300)
        self.W = W  # (k, nq) area weights
        # B[k, q, a*3+i] = N_qa n_kqi: the normal displacement u_n = B . u_facet
        self.B = np.einsum("qa,kqi->kqai", N, nqv).reshape(len(facets), nq, -1)
        self.dofs = (3 * fn[:, :, None] + np.arange(3)).reshape(len(fn), -1)  # (k, 3 nfn)
        nd = self.dofs.shape[1]
        self.rows = np.repeat(self.dofs, nd, axis=1).ravel()
        self.cols = np.tile(self.dofs, (1, nd)).ravel()

    def normal_displacement(self, u: np.ndarray) -> np.ndarray:
        """``u . n`` (k, nq) at the quadrature points (mm); > 0 is penetration into the obstacle."""
        return np.einsum("kqd,kd->kq", self.B, np.asarray(u, float)[self.dofs])

    def active(self, u: np.ndarray) -> np.ndarray:
        """(k, nq) bool: quadrature points in contact (``u . n >= 0``)."""
        return self.normal_displacement(u) >= 0.0

    def energy_force(self, u: np.ndarray) -> tuple[float, np.ndarray]:
        """Penalty energy (N mm) and its gradient (n_dofs,): the force the liver exerts on the obstacle."""
        pen = np.maximum(self.normal_displacement(u), 0.0)
        energy = 0.5 * self.kn * float(np.sum(self.W * pen**2))
        local = self.kn * np.einsum("kq,kqd->kd", self.W * pen, self.B)
        f = np.bincount(self.dofs.ravel(), weights=local.ravel(), minlength=self.n_dofs)
        return energy, f

    def tangent_values(self, u: np.ndarray) -> np.ndarray:
        """Values of the generalised tangent on (``rows``, ``cols``) at ``u`` (active set ``u.n >= 0``)."""
        w = self.kn * self.W * self.active(u)
        return np.einsum("kq,kqa,kqb->kab", w, self.B, self.B).ravel()

    def tangent_matrix(self, u: np.ndarray) -> sp.csr_matrix:
        """Full (n_dofs x n_dofs) generalised tangent at ``u``."""
        n = self.n_dofs
        return sp.coo_matrix((self.tangent_values(u), (self.rows, self.cols)), shape=(n, n)).tocsr()
