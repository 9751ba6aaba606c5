"""Made-up shard rows for the dataset and fault tests (importable: tests/ is on sys.path)."""
from __future__ import annotations

import numpy as np


def fake_row(i: int, rng, converged: bool = True, k: int | None = None) -> dict:
    """One full-schema shard row of made-up numbers (ROI of ``k`` nodes; default 5 + i, sizes differ)."""
    k = 5 + i if k is None else k
    und = rng.normal(size=(k, 3)).astype(np.float32)
    de = und + 0.1
    return {
        "case_id": f"I-{i:06d}", "scenario": "I", "geometry_id": "proc-0000", "shard_index": 0, "seed": i,
        "material_model": "yeoh", "material_param_names": ["C10", "C20", "C30"],
        "material_params_mpa": [0.0016, 0.0125, 0.0053], "bulk_modulus_mpa": 0.5, "exertion_id": 0,
        "exertion_point_mm": [1.0, 2.0, 3.0], "force_n": [0.1, 0.2, -1.0 * i], "force_magnitude_n": 1.0,
        "frame_normal": [0, 0, 1.0], "frame_t1": [1.0, 0, 0], "frame_t2": [0, 1.0, 0],
        "liver_centroid_mm": [0, 0, 0.0], "inertia_mm5": list(np.eye(3).ravel()),
        "tool_thickness_mm": 40.0, "probe_compliance_mm_per_n": list(np.diag([1.0, 1.0, 2.0]).ravel()),
        "roi_fraction": 0.18, "roi_area_fraction": 0.181, "roi_node_ids": np.arange(k, dtype=np.int32),
        "roi_triangles": np.array([[0, j, j + 1] for j in range(1, k - 1)], dtype=np.int32).reshape(-1, 3),
        "roi_undeformed_mm": und, "roi_deformed_mm": de,
        "roi_centroid_undeformed_mm": und.mean(0), "roi_centroid_deformed_mm": de.mean(0),
        "surface_displacement_mm": np.full((7, 3), 0.1, np.float32), "max_displacement_mm": 0.17,
        "max_principal_stretch": 1.12, "min_principal_stretch": 0.91,
        "converged": converged, "reason": "" if converged else "diverged", "load_fraction": 1.0 if converged else 0.4,
        "load_steps": 3, "newton_iterations": 9, "final_residual": 1e-9, "linear_solver": "cholmod",
        "wall_time_s": float(rng.random()),
    }


def top_face_cases(mesh, material: dict, gid: str, n_cases: int, n_points: int, max_n: float, rng) -> list[dict]:
    """``n_cases`` case-table rows on liver ``gid`` (a ``LiverMesh``): pushes at the ``n_points`` highest visible
    nodes in turn, forces of 0.3-``max_n`` N within about 17 degrees of straight down, ``material`` the config's
    slice (for the physics tests, whose small ellipsoid livers have their top face visible)."""
    from liverforce.fem.materials import make_material

    visible = np.unique(mesh.facets[mesh.facet_visible])
    tops = visible[np.argsort(-mesh.points[visible, 2])[:n_points]]
    bulk = make_material(material["model"], material["params_mpa"], nu=material["nu"]).bulk
    cases = []
    for i in range(n_cases):
        d = np.array([0.3 * rng.standard_normal(), 0.3 * rng.standard_normal(), -1.0])
        f = rng.uniform(0.3, max_n) * d / np.linalg.norm(d)
        cases.append({"case_id": f"V-{i:06d}", "scenario": "V", "geometry_id": gid, "shard_index": 0, "seed": i,
                      "material_model": material["model"], "material_param_names": list(material["params_mpa"]),
                      "material_params_mpa": list(material["params_mpa"].values()), "bulk_modulus_mpa": bulk,
                      "exertion_id": int(i % n_points), "exertion_point_mm": mesh.points[tops[i % n_points]].tolist(),
                      "exertion_normal": [0.0, 0.0, 1.0], "force_n": f.tolist(),
                      "force_magnitude_n": float(np.linalg.norm(f))})
    return cases
