"""Small trained models (session-scoped; synthetic cases, a few seconds each) and helpers for the serving tests."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from scipy.spatial import ConvexHull

from liverforce.learn.frames import local_rotations, points_to_local
from liverforce.learn.model import subset
from liverforce.learn.synthetic import synthetic_arrays
from liverforce.learn.train import train_scenario

torch.set_num_threads(1)

DENT_WIDTH = 12.0
ROI_RADIUS = 25.0
BASE = {
    "encoder": "pca", "code_size": 4, "state_vector": True, "grid_size": 8, "hidden": [32, 32], "dropout": 0.0,
    "occlusion": {"radius_mm": 3.0, "mode": "remove"}, "noise_mm": 0.0,
}
TRAIN = {"test_fraction": 0.2, "epochs": 40, "batch_size": 32, "lr": 3e-3, "weight_decay": 0.0, "seed": 0,
         "interval": {"coverage": 0.9, "calibration_fraction": 0.2}}
NO_TUNE = {"enabled": False, "trials": 1, "folds": 2, "sobol_trials": 1, "epochs": 1}


@pytest.fixture(scope="session")
def data():
    """120 synthetic cases on 2 geometries with varying material (float64 clouds)."""
    return synthetic_arrays(120, n_geometries=2, seed=1, nodes=(180, 260), dent_width_mm=DENT_WIDTH,
                            material_varies=True, dtype=np.float64)


@pytest.fixture(scope="session")
def trained(data, tmp_path_factory):
    """``trained(name)`` -> model directory; variants: ``disp`` (PCA + state, the points' interpolant),
    ``dae`` (denoising AE + state), ``deformed`` (deformed height, no state: exact from an unordered cloud),
    ``gp`` (``disp`` with the Gaussian-process regressor), ``top`` (``disp`` on the top sheet of the ROI
    patch's triangles, ``interpolation: surface``; with the tool's 3 mm occlusion removing nodes)."""
    cache: dict[str, str] = {}
    variants = {
        "disp": {},
        "dae": {"encoder": "dae", "hidden": [16]},
        "deformed": {"roi_features": "deformed", "state_vector": False,
                     "occlusion": {"radius_mm": 0.0, "mode": "remove"}},
        "gp": {"regressor": "gp", "gp": {"max_points": 2000, "iterations": 100}},
        "top": {"interpolation": "surface"},
    }

    def get(name: str) -> str:
        if name not in cache:
            out = tmp_path_factory.mktemp(f"serve-{name}")
            train = {**TRAIN, "epochs": 25} if name == "dae" else TRAIN
            res = train_scenario(data, {**BASE, **variants[name]}, train, NO_TUNE, "III", name, out_dir=out)
            cache[name] = res["model_path"]
        return cache[name]

    return get


@pytest.fixture(scope="session")
def test_cases(data, trained):
    """The held-out cases of the ``disp`` model (never seen in training)."""
    from liverforce.learn.model import ForceModel

    model = ForceModel.load(trained("disp"))
    return subset(data, [list(data["case_id"]).index(c) for c in model.meta["test_case_ids"]])


def resampler(arrays: dict, i: int):
    """The synthetic case ``i``'s deformed surface as a function: ``f(k, rng) -> (k, 3)`` liver-frame points.

    The synthetic ROI is ``z = -curv (u² + v²)`` plus the dent ``G(u, v) c`` (local frame); both are
    recovered exactly from the case's nodes, so new samplings lie on the same deformed surface.
    """
    R = local_rotations(arrays["frame_normal"][i:i + 1], arrays["frame_t1"][i:i + 1], arrays["frame_t2"][i:i + 1])[0]
    p = np.asarray(arrays["exertion_point_mm"][i])
    U = points_to_local(arrays["roi_undeformed_mm"][i], p, R)
    D = points_to_local(arrays["roi_deformed_mm"][i], p, R)
    r2 = U[:, 0] ** 2 + U[:, 1] ** 2
    curv = -np.sum(U[:, 2] * r2) / np.sum(r2**2)
    G = np.exp(-r2 / (2 * DENT_WIDTH**2))
    c = (G[:, None] * (D - U)).sum(axis=0) / np.sum(G * G)

    def surface(u, v):
        g = np.exp(-(u * u + v * v) / (2 * DENT_WIDTH**2))
        return np.column_stack([u, v, -curv * (u * u + v * v)]) + g[:, None] * c

    assert np.abs(surface(U[:, 0], U[:, 1]) - D).max() < 1e-6  # the model of the case is exact

    def sample(k: int, rng: np.random.Generator) -> np.ndarray:
        rad = ROI_RADIUS * np.sqrt(rng.uniform(size=k))
        ang = rng.uniform(0, 2 * np.pi, size=k)
        return p + surface(rad * np.cos(ang), rad * np.sin(ang)) @ R

    return sample


@pytest.fixture(scope="session")
def resample():
    return resampler


def ellipsoid_surface(axes=(100.0, 70.0, 40.0), n=2000, seed=0):
    """Closed triangulated ellipsoid (convex hull of Fibonacci-sphere points), outward facets."""
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5**0.5) * i
    pts = np.column_stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)]) * axes
    hull = ConvexHull(pts)
    tri = hull.simplices.copy()
    a, b, c = pts[tri[:, 0]], pts[tri[:, 1]], pts[tri[:, 2]]
    flip = np.einsum("ij,ij->i", np.cross(b - a, c - a), hull.equations[:, :3]) < 0
    tri[flip] = tri[flip][:, [0, 2, 1]]
    return pts, tri


def shard_rows(arrays: dict, idx, scenario="III", converged=True, scale=1.0, suffix="") -> list[dict]:
    """Shard rows (the full schema) for cases ``idx``; ``scale`` scales each case's displacement."""
    rows = []
    for i in idx:
        und = np.asarray(arrays["roi_undeformed_mm"][i], dtype=np.float64)
        de = und + scale * (np.asarray(arrays["roi_deformed_mm"][i], dtype=np.float64) - und)
        rows.append({
            "case_id": f"{arrays['case_id'][i]}{suffix}", "scenario": scenario, "geometry_id": arrays["geometry_id"][i],
            "shard_index": 0, "seed": int(i), "material_model": "yeoh", "material_param_names": ["C10", "C20"],
            "material_params_mpa": list(arrays["material_params_mpa"][i]), "bulk_modulus_mpa": 0.5,
            "exertion_id": int(i), "exertion_point_mm": arrays["exertion_point_mm"][i],
            "force_n": arrays["force_n"][i] * scale, "force_magnitude_n": float(np.linalg.norm(arrays["force_n"][i])),
            "frame_normal": arrays["frame_normal"][i], "frame_t1": arrays["frame_t1"][i],
            "frame_t2": arrays["frame_t2"][i], "liver_centroid_mm": arrays["liver_centroid_mm"][i],
            "inertia_mm5": arrays["inertia_mm5"][i], "tool_thickness_mm": float(arrays["tool_thickness_mm"][i]),
            "probe_compliance_mm_per_n": np.asarray(arrays["probe_compliance_mm_per_n"][i]).ravel(),
            "roi_fraction": 0.18, "roi_area_fraction": 0.18,
            "roi_node_ids": np.arange(len(und), dtype=np.int32), "roi_triangles": np.asarray(arrays["roi_triangles"][i], np.int32),
            "roi_undeformed_mm": und.astype(np.float32),
            "roi_deformed_mm": de.astype(np.float32), "roi_centroid_undeformed_mm": und.mean(0),
            "roi_centroid_deformed_mm": de.mean(0), "surface_displacement_mm": np.zeros((0, 3), np.float32),
            "max_displacement_mm": 1.0, "max_principal_stretch": 1.1, "min_principal_stretch": 0.9,
            "converged": converged, "reason": "" if converged else "diverged",
            "load_fraction": 1.0, "load_steps": 1, "newton_iterations": 3, "final_residual": 1e-9,
            "linear_solver": "cholmod", "wall_time_s": 0.1,
        })
    return rows


@pytest.fixture(scope="session")
def ellipsoid():
    """``ellipsoid(axes, n)`` -> closed outward ``(points, triangles)``."""
    return ellipsoid_surface


@pytest.fixture(scope="session")
def make_shard_rows():
    """``make_shard_rows(arrays, idx, ...)`` -> full-schema shard rows."""
    return shard_rows


@pytest.fixture(scope="session")
def configs():
    """The training config slices of the session's models: ``(model, train, tune)``."""
    return BASE, TRAIN, NO_TUNE


def mid_range(ctx, rec: dict):
    """``ctx`` with its thickness, compliance trace, liver size and centroid distance in the middle of the
    training ranges ``rec`` (``meta["training_scale"]``)."""
    mid = {k: 0.5 * (rec[k][0] + rec[k][1]) for k in ("tool_thickness_mm", "probe_compliance_mm_per_n",
                                                       "inertia_length_mm", "centroid_distance_mm")}
    C = ctx.probe_compliance_mm_per_n.reshape(3, 3)
    length = (np.trace(ctx.inertia_mm5.reshape(3, 3)) / 2.0) ** 0.2
    off = ctx.liver_centroid_mm - ctx.exertion_point_mm
    return dataclasses.replace(
        ctx, tool_thickness_mm=mid["tool_thickness_mm"],
        probe_compliance_mm_per_n=C * (mid["probe_compliance_mm_per_n"] / np.trace(C)),
        inertia_mm5=ctx.inertia_mm5 * (mid["inertia_length_mm"] / length) ** 5,
        liver_centroid_mm=ctx.exertion_point_mm + off * (mid["centroid_distance_mm"] / np.linalg.norm(off)))


@pytest.fixture(scope="session", name="mid_range")
def mid_range_fixture():
    """``mid_range(ctx, meta["training_scale"])`` -> the context with its geometric state mid-range."""
    return mid_range
