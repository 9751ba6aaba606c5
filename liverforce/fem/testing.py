"""Small synthetic meshes for tests and benchmarks (topology from liverforce.mesh.boundary).

* :func:`box_mesh` — a structured tetrahedral block.
* :func:`ellipsoid_liver` — an ellipsoid with liver-like facet regions
  (RAS frame: +x right, +y anterior, +z superior), a stand-in for
  :class:`liverforce.mesh.types.LiverMesh` when only arrays are needed.
"""

from __future__ import annotations

import numpy as np

from liverforce.mesh.boundary import boundary_facets as mesh_boundary_facets

from .elements import orient_tets


def boundary_facets(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Boundary triangles (k, 3) of a tet mesh in any orientation, normals outward (:mod:`liverforce.mesh.boundary`)."""
    return mesh_boundary_facets(orient_tets(points, tets))


def box_mesh(shape=(2, 2, 2), size=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0)):
    """Structured tet mesh of a box: ``(points, tets, facets)`` (mm).

    ``shape`` counts cells per axis (each cell split into tetrahedra by
    scikit-fem's ``init_tensor``).
    """
    import skfem

    axes = [np.linspace(o, o + s, n + 1) for o, s, n in zip(origin, size, shape)]
    m = skfem.MeshTet.init_tensor(*axes)
    points = np.ascontiguousarray(m.p.T)
    tets = orient_tets(points, m.t.T)
    return points, tets, boundary_facets(points, tets)


def ellipsoid_liver(nrefs: int = 2, axes_mm=(125.0, 75.0, 45.0)):
    """Ellipsoid stand-in for a liver mesh with facet regions.

    Returns
    -------
    dict with ``points`` (n, 3), ``tets`` (m, 4), ``facets`` (k, 3),
    ``facet_region`` (k,) int8 (0 free, 1 ivc, 2 ligament, 3 visceral, 4 rib),
    ``facet_visible`` (k,) bool. ``nrefs`` 1/2/3/4 gives 25/129/833/6017 vertices.
    """
    import skfem

    m = skfem.MeshTet.init_ball(nrefs=nrefs)
    points = np.ascontiguousarray(m.p.T) * np.asarray(axes_mm, float)
    tets = orient_tets(points, m.t.T)
    facets = boundary_facets(points, tets)
    X = points[facets]
    c = X.mean(axis=1)
    n = np.cross(X[:, 1] - X[:, 0], X[:, 2] - X[:, 0])
    n /= np.linalg.norm(n, axis=1)[:, None]
    a = np.asarray(axes_mm, float)
    region = np.zeros(len(facets), np.int8)
    region[(n[:, 2] < -0.5)] = 3  # visceral (inferior) face
    region[(n[:, 2] > 0.4) & (n[:, 1] < -0.3)] = 2  # ligaments: superior-posterior
    region[(n[:, 0] > 0.7) & (n[:, 2] > -0.5)] = 4  # rib contact, right lateral
    d = np.asarray([0.25, -0.75, 0.35])
    p_ivc = d / np.sqrt(np.sum((d / a) ** 2))  # point on the ellipsoid
    region[np.linalg.norm(c - p_ivc, axis=1) < 0.25 * a[2] + 12.0] = 1  # ivc (fixed)
    visible = (region == 0) & ((n[:, 1] > 0.0) | (n[:, 2] > 0.3))
    return {"points": points, "tets": tets, "facets": facets, "facet_region": region,
            "facet_visible": visible}
