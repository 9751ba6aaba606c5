"""How well a sphere support's centre tells a frame mix-up (RAS read as LPS, or the reverse): the measurement
behind :data:`liverforce.mesh.supports.SPHERE_ON_SURFACE_MM` and ``SPHERE_OFF_SURFACE_MM``.

A lab gives a fixed or sliding support as ``sphere: {center_mm, radius_mm}``, often with its centre picked on the
liver's surface (a click in 3D Slicer). Read in the wrong frame the centre is mirrored in x and y; when the sphere
still selects facets (on a liver near symmetric about the file's superior axis), it holds the wrong side of the
liver and nothing else says so. The rule flags a sphere whose centre, mirrored, lies within ``on`` mm of the
surface while, as read, it lies ``off`` mm or more off it.

Livers: the procedural livers of seeds 0-5 and three ellipsoids (125 x 75 x 55 mm) centred 1-4 mm off the origin.
On each, ``--centres`` points drawn on the surface (area-weighted); centres: on the surface (``click``), moved
along the normal by Gaussian noise of 0.5 mm (``click_noisy``), or by 0-15 mm either way (``offset``: the middle
of a vessel beside the liver, a point inside it). A right-frame centre is flagged falsely; a wrong-frame one (the
centre mirrored) is counted only when a sphere of radius 10-40 mm there still selects a facet (its centre within
the radius of the surface) and is found when flagged.

Run: ``PYTHONPATH=. OMP_NUM_THREADS=1 python benchmarks/experiment_sphere_frame.py`` (about a minute).
"""

from __future__ import annotations

import argparse

import numpy as np
import trimesh

from liverforce.geometry.procedural import procedural_liver
from liverforce.mesh.supports import _LPS_RAS, SPHERE_OFF_SURFACE_MM, SPHERE_ON_SURFACE_MM, TriangleSet

MODES = ("click", "click_noisy", "offset")


def livers():
    """(name, vertices mm, faces) of the livers the rule is measured on."""
    for seed in range(6):
        s = procedural_liver(seed)
        yield f"procedural {seed}", np.asarray(s.vertices, float), np.asarray(s.faces)
    m = trimesh.creation.icosphere(subdivisions=5)
    for off in ([1.0, 0.5, 0.0], [2.0, 1.0, 0.0], [4.0, -2.0, 1.0]):
        yield f"ellipsoid at {off}", np.asarray(m.vertices) * [125.0, 75.0, 55.0] + off, np.asarray(m.faces)


def distances(n: int, seed: int) -> list:
    """Per liver and mode: the centres' distance to the surface as drawn and mirrored, and the spheres' radii."""
    rng = np.random.default_rng(seed)
    rows = []
    for name, V, F in livers():
        tri = TriangleSet(V[F])
        mesh = trimesh.Trimesh(V, F, process=False)
        p, face = trimesh.sample.sample_surface(mesh, n, seed=seed)
        normal = mesh.face_normals[face]
        for mode in MODES:
            shift = {"click": np.zeros(n), "click_noisy": rng.normal(0.0, 0.5, n),
                     "offset": rng.uniform(-15.0, 15.0, n)}[mode]
            c = p + shift[:, None] * normal
            rows.append((name, mode, tri.closest(c)[1], tri.closest(c * _LPS_RAS)[1], rng.uniform(10.0, 40.0, n)))
    return rows


def rates(rows: list, on: float, off: float) -> dict:
    """Per mode: (% of right-frame centres flagged, % of silent wrong-frame ones flagged, how many of those)."""
    def flag(read, mirrored):
        return (mirrored <= on) & (read >= off)

    out = {}
    for mode in MODES:
        mine = [r for r in rows if r[1] == mode]
        false = np.concatenate([flag(d, m) for _, _, d, m, _ in mine])
        silent = np.concatenate([flag(m, d)[m < r] for _, _, d, m, r in mine])  # read mirrored: d and m swap
        out[mode] = (100.0 * false.mean(), 100.0 * silent.mean(), len(silent), len(false))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--centres", type=int, default=1500, help="centres per liver and mode")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    rows = distances(args.centres, args.seed)
    print("rule: flagged when, mirrored, the centre lies within ON mm of the surface and, as read, OFF mm or more")
    print("ON mm | OFF mm | " + " | ".join(f"{m}: false / found (of n)" for m in MODES))
    for on in (0.5, 1.0, 2.0):
        for off in (3.0, 5.0, 8.0):
            r = rates(rows, on, off)
            shipped = " (shipped)" if (on, off) == (SPHERE_ON_SURFACE_MM, SPHERE_OFF_SURFACE_MM) else ""
            print(f"{on:g} | {off:g}{shipped} | " + " | ".join(
                f"{r[m][0]:.2f} % of {r[m][3]} / {r[m][1]:.1f} % of {r[m][2]}" for m in MODES))


if __name__ == "__main__":
    main()
