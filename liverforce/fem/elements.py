"""Linear (P1) and quadratic (P2) tetrahedra: nodes, shape-function gradients, quadrature.

Conventions
-----------
* Nodes: the mesh vertices first (same order as ``points``), then, for P2, one
  node per unique edge at its midpoint (straight-sided elements).
* Degrees of freedom are interleaved, ``dof = 3 * node + component`` (as in
  scikit-fem's ``ElementVector``).
* Local P2 node order: vertices 0-3, then edges (0,1), (1,2), (0,2), (0,3),
  (1,3), (2,3). P2 triangle (facet) order: vertices 0-2, edges (0,1), (1,2), (0,2).
* Quadrature: P1 one point (exact for constant gradients); P2 the symmetric
  4-point degree-2 rule (as in Abaqus' C3D10).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from liverforce.mesh.quality import orient_positive as orient_tets  # the one tet-orientation rule

TET_EDGES = np.array([(0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3)])
TRI_EDGES = np.array([(0, 1), (1, 2), (0, 2)])

_A4, _B4 = 0.5854101966249685, 0.1381966011250105
#: 4-point degree-2 tetrahedron rule (barycentric coordinates, weights sum to 1).
TET_Q4 = (np.array([[_A4, _B4, _B4, _B4], [_B4, _A4, _B4, _B4], [_B4, _B4, _A4, _B4], [_B4, _B4, _B4, _A4]]),
          np.full(4, 0.25))
TET_Q1 = (np.full((1, 4), 0.25), np.ones(1))

# Dunavant degree-5 7-point triangle rule (barycentric, weights sum to 1).
_a1, _b1, _w1 = 0.059715871789770, 0.470142064105115, 0.132394152788506
_a2, _b2, _w2 = 0.797426985353087, 0.101286507323456, 0.125939180544827
TRI_Q7 = (
    np.array([[1 / 3, 1 / 3, 1 / 3], [_a1, _b1, _b1], [_b1, _a1, _b1], [_b1, _b1, _a1],
              [_a2, _b2, _b2], [_b2, _a2, _b2], [_b2, _b2, _a2]]),
    np.array([0.225, _w1, _w1, _w1, _w2, _w2, _w2]),
)


def tet_shape_bary_grad(order: int, bary: np.ndarray) -> np.ndarray:
    """``dN_a / dL_m`` at barycentric points: ``(nq, nen, 4)``."""
    nq = bary.shape[0]
    if order == 1:
        return np.broadcast_to(np.eye(4), (nq, 4, 4)).copy()
    g = np.zeros((nq, 10, 4))
    for a in range(4):
        g[:, a, a] = 4 * bary[:, a] - 1
    for k, (i, j) in enumerate(TET_EDGES):
        g[:, 4 + k, i] = 4 * bary[:, j]
        g[:, 4 + k, j] = 4 * bary[:, i]
    return g


def tri_shape(order: int, bary: np.ndarray) -> np.ndarray:
    """Triangle shape function values at barycentric points ``(nq, 3)`` -> ``(nq, nfn)``."""
    if order == 1:
        return bary.copy()
    L = bary
    return np.concatenate([L * (2 * L - 1), 4 * L[:, TRI_EDGES[:, 0]] * L[:, TRI_EDGES[:, 1]]], axis=1)


@dataclass
class TetDiscretization:
    """Nodes, connectivity, quadrature and reference gradients of a P1 or P2 tet mesh.

    Attributes
    ----------
    order : 1 or 2.
    n_vertices : number of mesh vertices (the first nodes).
    nodes : (n_nodes, 3) reference coordinates (mm).
    tets : (ne, 4) positively oriented vertex connectivity.
    conn : (ne, nen) node connectivity (nen = 4 or 10).
    edges : (n_edges, 2) vertex pairs of the P2 edge nodes (empty for P1).
    dN : (ne, nq, nen, 3) reference gradients of the shape functions (1/mm).
    w : (ne, nq) quadrature weights times element volume (mm³).
    volume : (ne,) element volumes (mm³).
    """

    order: int
    n_vertices: int
    nodes: np.ndarray
    tets: np.ndarray
    conn: np.ndarray
    edges: np.ndarray
    dN: np.ndarray
    w: np.ndarray
    volume: np.ndarray
    _edge_keys: np.ndarray

    @property
    def n_nodes(self) -> int:
        return self.nodes.shape[0]

    @property
    def n_dofs(self) -> int:
        return 3 * self.nodes.shape[0]

    @property
    def element_dofs(self) -> np.ndarray:
        """(ne, 3 * nen) interleaved dofs per element."""
        return (3 * self.conn[:, :, None] + np.arange(3)).reshape(self.conn.shape[0], -1)

    def edge_node(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Node index of the midpoint node of edges (a, b) (P2 only)."""
        a, b = np.asarray(a, np.int64), np.asarray(b, np.int64)
        key = np.minimum(a, b) * self.n_vertices + np.maximum(a, b)
        idx = np.searchsorted(self._edge_keys, key)
        if np.any(idx >= len(self._edge_keys)) or np.any(self._edge_keys[np.minimum(idx, len(self._edge_keys) - 1)] != key):
            raise ValueError("facet edge is not an edge of any tetrahedron: facets do not match tets")
        return self.n_vertices + idx

    def facet_nodes(self, facets: np.ndarray) -> np.ndarray:
        """Node connectivity of boundary triangles: (k, 3) for P1, (k, 6) for P2."""
        facets = np.asarray(facets, dtype=np.int64)
        if self.order == 1:
            return facets
        e = [self.edge_node(facets[:, i], facets[:, j]) for i, j in TRI_EDGES]
        return np.column_stack([facets] + e)


def build_discretization(points: np.ndarray, tets: np.ndarray, order: int = 1) -> TetDiscretization:
    """Precompute nodes, connectivity and reference gradients for ``order`` 1 or 2.

    Parameters
    ----------
    points : (n, 3) vertex coordinates (mm).
    tets : (m, 4) vertex indices (any orientation; re-oriented here).
    order : 1 (linear) or 2 (quadratic, straight edges).
    """
    if order not in (1, 2):
        raise ValueError(f"element order must be 1 or 2, got {order}")
    points = np.ascontiguousarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (n, 3), got {points.shape}")
    tets = np.asarray(tets, dtype=np.int64)
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise ValueError(f"tets must have shape (m, 4), got {tets.shape}")
    if tets.min() < 0 or tets.max() >= len(points):
        raise ValueError("tets index outside points")
    tets = orient_tets(points, tets)
    nv = len(points)
    X = points[tets]
    M = np.stack([X[:, 1] - X[:, 0], X[:, 2] - X[:, 0], X[:, 3] - X[:, 0]], axis=-1)  # columns
    volume = np.linalg.det(M) / 6.0
    Minv = np.linalg.inv(M)  # rows: grad L1, L2, L3
    gL = np.concatenate([-Minv.sum(axis=1, keepdims=True), Minv], axis=1)  # (ne, 4, 3)
    if order == 1:
        bary, wq = TET_Q1
        conn = tets
        edges = np.zeros((0, 2), np.int64)
        keys = np.zeros(0, np.int64)
        nodes = points
    else:
        bary, wq = TET_Q4
        pairs = np.sort(tets[:, TET_EDGES], axis=-1)  # (ne, 6, 2)
        allkeys = pairs[..., 0] * nv + pairs[..., 1]
        keys, inv = np.unique(allkeys.ravel(), return_inverse=True)
        edges = np.column_stack([keys // nv, keys % nv])
        conn = np.concatenate([tets, nv + inv.reshape(-1, 6)], axis=1)
        nodes = np.concatenate([points, 0.5 * (points[edges[:, 0]] + points[edges[:, 1]])])
    gb = tet_shape_bary_grad(order, bary)  # (nq, nen, 4)
    dN = np.einsum("qam,emJ->eqaJ", gb, gL)
    w = volume[:, None] * wq[None, :]
    return TetDiscretization(order, nv, nodes, tets, np.ascontiguousarray(conn), edges,
                             np.ascontiguousarray(dN), np.ascontiguousarray(w), volume, keys)


def facet_geometry(points: np.ndarray, facets: np.ndarray):
    """Areas (k,) and unit normals (k, 3) of triangles (normal by right-hand rule)."""
    X = points[np.asarray(facets, np.int64)]
    n = np.cross(X[:, 1] - X[:, 0], X[:, 2] - X[:, 0])
    a2 = np.linalg.norm(n, axis=1)
    return 0.5 * a2, n / np.where(a2 > 0, a2, 1.0)[:, None]
