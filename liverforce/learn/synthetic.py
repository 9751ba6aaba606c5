"""Synthetic cases in the training input contract, with a known force -> displacement map.

For tests, demos and benchmarks of the learning stage without FE runs. Each
geometry is an ellipsoid (semi-axes ~ 100 x 70 x 40 mm) placed in its own
random source frame; exertion points lie on its upper half. The ROI is a
disc of radius ``roi_radius_mm`` of the surface's tangent paraboloid at the
exertion point, sampled at a random number of scattered nodes; the
displacement is a Gaussian dent, linear in the local force
``f = (F.t1, F.t2, F.n)``:

    d(u, v) = exp(-(u^2 + v^2) / (2 w^2)) * (c_t f_1, c_t f_2, c_n f_3) / s

with ``w = dent_width_mm``, compliances ``c_t``, ``c_n`` (mm/N) and the
stiffness scale ``s`` (1, or the first material constant relative to its
base value when ``material_varies``). The force has magnitude in
``[1, 5]`` N, pushes into the surface (``f_3 < 0``) within a 30 degree cone.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import Delaunay

from liverforce.dataset.roi import roi_triangles


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random proper rotation (QR of a Gaussian matrix)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def synthetic_arrays(
    n_cases: int,
    *,
    n_geometries: int = 1,
    seed: int = 0,
    nodes: tuple[int, int] = (200, 320),
    roi_radius_mm: float = 25.0,
    dent_width_mm: float = 9.0,
    compliance_mm_per_n: tuple[float, float] = (0.8, 1.5),
    material_varies: bool = False,
    fixed_exertion: bool = False,
    dtype=np.float32,
) -> dict:
    """``n_cases`` synthetic converged cases (module docstring) as the training input dict."""
    rng = np.random.default_rng(seed)
    geoms = []
    for g in range(n_geometries):
        axes = np.array([100.0, 70.0, 40.0]) * (1 + 0.1 * rng.normal(size=3))
        Q = random_rotation(rng)
        c = rng.normal(scale=80.0, size=3)
        inertia_principal = np.diag([axes[1] ** 2 + axes[2] ** 2, axes[0] ** 2 + axes[2] ** 2,
                                     axes[0] ** 2 + axes[1] ** 2]) * (4 / 3 * np.pi * axes.prod()) / 5
        geoms.append((axes, Q, c, Q @ inertia_principal @ Q.T))
    base_material = np.array([0.0016, 0.0125])
    fixed_angles = rng.uniform([0.3, 0.3], [2.5, 1.2])
    out: dict[str, list] = {k: [] for k in (
        "case_id", "geometry_id", "force_n", "exertion_point_mm", "frame_normal", "frame_t1", "frame_t2",
        "liver_centroid_mm", "inertia_mm5", "tool_thickness_mm", "probe_compliance_mm_per_n", "material_params_mpa",
        "roi_undeformed_mm",
        "roi_deformed_mm", "roi_centroid_undeformed_mm", "roi_centroid_deformed_mm", "roi_triangles")}
    ct, cn = compliance_mm_per_n
    for i in range(n_cases):
        g = i % n_geometries
        axes, Q, c, inertia = geoms[g]
        # exertion point on the upper half of the ellipsoid (geometry frame)
        phi, theta = fixed_angles if fixed_exertion else rng.uniform([0.0, 0.2], [2 * np.pi, 1.2])
        y = axes * np.array([np.cos(phi) * np.sin(theta), np.sin(phi) * np.sin(theta), np.cos(theta)])
        n_g = y / axes**2
        n_g /= np.linalg.norm(n_g)
        t1_g = np.array([1.0, 0.0, 0.0]) - n_g[0] * n_g
        t1_g /= np.linalg.norm(t1_g)
        t2_g = np.cross(n_g, t1_g)
        p, nrm, t1, t2 = c + Q @ y, Q @ n_g, Q @ t1_g, Q @ t2_g
        R = np.stack([t1, t2, nrm])  # rows
        # ROI in the local frame: paraboloid patch with the local curvature scale of the ellipsoid
        k = int(rng.integers(nodes[0], nodes[1] + 1))
        rad = roi_radius_mm * np.sqrt(rng.uniform(size=k))
        ang = rng.uniform(0, 2 * np.pi, size=k)
        u, v = rad * np.cos(ang), rad * np.sin(ang)
        curv = 0.5 / float(np.mean(axes))
        und_loc = np.column_stack([u, v, -curv * (u**2 + v**2)])
        # local force: into the surface, within a 30 degree cone
        mag = rng.uniform(1.0, 5.0)
        tilt = np.deg2rad(30.0) * np.sqrt(rng.uniform())
        az = rng.uniform(0, 2 * np.pi)
        f_loc = mag * np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), -np.cos(tilt)])
        material = base_material * (rng.uniform(0.7, 1.3, size=2) if material_varies else 1.0)
        stiff = material[0] / base_material[0]
        G = np.exp(-(u**2 + v**2) / (2 * dent_width_mm**2))
        disp_loc = G[:, None] * (np.array([ct, ct, cn]) * f_loc)[None, :] / stiff
        und = p + und_loc @ R
        dfm = p + (und_loc + disp_loc) @ R
        out["case_id"].append(f"S-{i:06d}")
        out["geometry_id"].append(f"syn-{g:04d}")
        out["force_n"].append(R.T @ f_loc)
        out["exertion_point_mm"].append(p)
        out["frame_normal"].append(nrm)
        out["frame_t1"].append(t1)
        out["frame_t2"].append(t2)
        out["liver_centroid_mm"].append(c)
        out["inertia_mm5"].append(inertia.ravel())
        out["tool_thickness_mm"].append(ellipsoid_chord(axes, y, n_g))
        # the probe at the base material: the dent's displacement at its centre per newton (local frame)
        out["probe_compliance_mm_per_n"].append(np.diag([ct, ct, cn]).ravel())
        out["material_params_mpa"].append(material)
        out["roi_undeformed_mm"].append(und.astype(dtype))
        out["roi_deformed_mm"].append(dfm.astype(dtype))
        out["roi_centroid_undeformed_mm"].append(und.mean(axis=0))
        out["roi_centroid_deformed_mm"].append(dfm.mean(axis=0))
        out["roi_triangles"].append(Delaunay(np.column_stack([u, v])).simplices.astype(np.int64))  # a height field
    arrays: dict = {}
    for key, vals in out.items():
        if key in ("case_id", "geometry_id"):
            arrays[key] = np.array(vals, dtype=object)
        elif key.startswith("roi_") and key.endswith("_mm") and not key.startswith("roi_centroid") or key == "roi_triangles":
            arrays[key] = vals
        else:
            arrays[key] = np.asarray(vals, dtype=np.float64)
    return arrays


def ellipsoid_chord(axes: np.ndarray, y: np.ndarray, n: np.ndarray) -> float:
    """Thickness along the inward normal: the chord from ``y`` on the ellipsoid ``sum (x/a)^2 = 1`` along ``-n``."""
    d = -np.asarray(n, float) / axes
    y_s = np.asarray(y, float) / axes
    # |y_s + t d|^2 = 1 with |y_s| = 1: t = -2 (y_s . d) / |d|^2
    return float(-2.0 * y_s.dot(d) / d.dot(d))


def rigid_motion(arrays: dict, Q: np.ndarray, c: np.ndarray) -> dict:
    """Apply ``x -> Q x + c`` to every point, direction, force and the inertia tensor (``Q I Q^T``)."""
    Q = np.asarray(Q, dtype=np.float64)
    c = np.asarray(c, dtype=np.float64)
    out = dict(arrays)
    for key in ("exertion_point_mm", "liver_centroid_mm", "roi_centroid_undeformed_mm", "roi_centroid_deformed_mm"):
        out[key] = np.asarray(arrays[key], dtype=np.float64) @ Q.T + c
    for key in ("frame_normal", "frame_t1", "frame_t2", "force_n"):
        out[key] = np.asarray(arrays[key], dtype=np.float64) @ Q.T
    for key in ("roi_undeformed_mm", "roi_deformed_mm"):
        out[key] = [(np.asarray(a, dtype=np.float64) @ Q.T + c).astype(np.asarray(a).dtype) for a in arrays[key]]
    I = np.asarray(arrays["inertia_mm5"], dtype=np.float64).reshape(-1, 3, 3)
    out["inertia_mm5"] = (Q @ I @ Q.T).reshape(-1, 9)
    return out


def ellipsoid_surface(axes, n_vertices: int = 6000) -> tuple[np.ndarray, np.ndarray]:
    """A closed, outward-oriented triangulation ``(V, T)`` of the ellipsoid ``sum (x/a)^2 = 1`` (mm).

    Vertices: a Fibonacci lattice on the unit sphere scaled by ``axes`` (near-uniform spacing); triangles:
    its convex hull (the ellipsoid is convex), each turned to face outwards.
    """
    from scipy.spatial import ConvexHull

    k = np.arange(n_vertices) + 0.5
    z = 1.0 - 2.0 * k / n_vertices
    r = np.sqrt(1.0 - z**2)
    phi = np.pi * (1.0 + 5**0.5) * k
    V = np.column_stack([r * np.cos(phi), r * np.sin(phi), z]) * np.asarray(axes, float)
    T = ConvexHull(V).simplices.astype(np.int64)
    a, b, c = V[T[:, 0]], V[T[:, 1]], V[T[:, 2]]
    inward = np.einsum("ij,ij->i", np.cross(b - a, c - a), (a + b + c) / 3.0) < 0
    T[inward] = T[inward][:, [0, 2, 1]]
    return V, T


def synthetic_surface_arrays(
    n_cases: int,
    *,
    n_geometries: int = 1,
    seed: int = 0,
    n_vertices: int = 6000,
    roi_radius_mm: float = 25.0,
    dent_width_mm: float = 9.0,
    compliance_mm_per_n: tuple[float, float] = (0.8, 1.5),
    material_varies: bool = False,
) -> dict:
    """Synthetic cases with whole closed surfaces, for camera-cloud models (:mod:`liverforce.learn.camera`).

    As :func:`synthetic_arrays` (same force law: a Gaussian dent linear in the local
    force), but each geometry is a triangulated ellipsoid (:func:`ellipsoid_surface`,
    in its own random source frame), every surface vertex moves (the dent is a Gaussian
    of the Euclidean distance from the exertion point, a surface vertex on the upper
    half), the ROI is the vertices within ``roi_radius_mm`` (with its own triangles,
    ``roi_triangles``), and the arrays carry the
    shards' ``surface_displacement_mm`` (per case, every vertex) plus the per-run entry
    ``surface_meshes`` (geometry id -> ``(V, T)``).
    """
    rng = np.random.default_rng(seed)
    base_material = np.array([0.0016, 0.0125])
    ct, cn = compliance_mm_per_n
    geoms = []
    for g in range(n_geometries):
        axes = np.array([100.0, 70.0, 40.0]) * (1 + 0.1 * rng.normal(size=3))
        Q = random_rotation(rng)
        c = rng.normal(scale=80.0, size=3)
        V, T = ellipsoid_surface(axes, n_vertices)
        inertia_principal = np.diag([axes[1] ** 2 + axes[2] ** 2, axes[0] ** 2 + axes[2] ** 2,
                                     axes[0] ** 2 + axes[1] ** 2]) * (4 / 3 * np.pi * axes.prod()) / 5
        Vs = c + V @ Q.T
        theta = np.arccos(np.clip(V[:, 2] / axes[2], -1, 1))
        candidates = np.flatnonzero((theta > 0.2) & (theta < 1.0))
        geoms.append((axes, Q, c, Q @ inertia_principal @ Q.T, V, Vs, T, candidates))
    out: dict[str, list] = {k: [] for k in (
        "case_id", "geometry_id", "force_n", "exertion_point_mm", "frame_normal", "frame_t1", "frame_t2",
        "liver_centroid_mm", "inertia_mm5", "tool_thickness_mm", "probe_compliance_mm_per_n", "material_params_mpa",
        "roi_undeformed_mm", "roi_deformed_mm", "roi_centroid_undeformed_mm", "roi_centroid_deformed_mm",
        "surface_displacement_mm", "roi_triangles")}
    for i in range(n_cases):
        g = i % n_geometries
        axes, Q, c, inertia, V, Vs, T, cand = geoms[g]
        y = V[int(rng.choice(cand))]
        n_g = y / axes**2
        n_g /= np.linalg.norm(n_g)
        t1_g = np.array([1.0, 0.0, 0.0]) - n_g[0] * n_g
        t1_g /= np.linalg.norm(t1_g)
        t2_g = np.cross(n_g, t1_g)
        p, nrm, t1, t2 = c + Q @ y, Q @ n_g, Q @ t1_g, Q @ t2_g
        R = np.stack([t1, t2, nrm])
        mag = rng.uniform(1.0, 5.0)
        tilt = np.deg2rad(30.0) * np.sqrt(rng.uniform())
        az = rng.uniform(0, 2 * np.pi)
        f_loc = mag * np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), -np.cos(tilt)])
        material = base_material * (rng.uniform(0.7, 1.3, size=2) if material_varies else 1.0)
        stiff = material[0] / base_material[0]
        d2 = np.sum((Vs - p) ** 2, axis=1)
        disp = np.exp(-d2 / (2 * dent_width_mm**2))[:, None] * ((np.array([ct, ct, cn]) * f_loc) @ R)[None, :] / stiff
        roi = d2 <= roi_radius_mm**2
        und, dfm = Vs[roi], Vs[roi] + disp[roi]
        out["case_id"].append(f"C-{i:06d}")
        out["geometry_id"].append(f"ell-{g:04d}")
        out["force_n"].append(R.T @ f_loc)
        out["exertion_point_mm"].append(p)
        out["frame_normal"].append(nrm)
        out["frame_t1"].append(t1)
        out["frame_t2"].append(t2)
        out["liver_centroid_mm"].append(c)
        out["inertia_mm5"].append(inertia.ravel())
        out["tool_thickness_mm"].append(ellipsoid_chord(axes, y, n_g))
        out["probe_compliance_mm_per_n"].append(np.diag([ct, ct, cn]).ravel())  # local frame, base material
        out["material_params_mpa"].append(material)
        out["roi_undeformed_mm"].append(und.astype(np.float32))
        out["roi_deformed_mm"].append(dfm.astype(np.float32))
        out["roi_centroid_undeformed_mm"].append(und.mean(axis=0))
        out["roi_centroid_deformed_mm"].append(dfm.mean(axis=0))
        out["surface_displacement_mm"].append(disp.astype(np.float32))
        out["roi_triangles"].append(roi_triangles(T, np.flatnonzero(roi)))
    arrays: dict = {}
    for key, vals in out.items():
        if key in ("case_id", "geometry_id"):
            arrays[key] = np.array(vals, dtype=object)
        elif key in ("roi_undeformed_mm", "roi_deformed_mm", "surface_displacement_mm", "roi_triangles"):
            arrays[key] = vals
        else:
            arrays[key] = np.asarray(vals, dtype=np.float64)
    arrays["surface_meshes"] = {f"ell-{g:04d}": (geoms[g][5], geoms[g][6]) for g in range(n_geometries)}
    return arrays
