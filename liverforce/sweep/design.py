"""Design of experiments: the case table of a scenario.

A case = (geometry, material constants, exertion point, force vector, seed).
Factors are drawn from one scrambled Sobol sequence (or a Latin hypercube)
seeded with the scenario's seed (``Plan.seed("sweep", ...)``), so the same
config gives the same table; case ``i`` records ``derive(seed, "sweep.case", i)``
(:mod:`liverforce.seeds`).

Force model
-----------
Magnitude ``|F|`` uniform in ``[min_n, max_n]`` N. Direction within a cone of
half-angle ``cone_deg`` around the inward surface normal ``-n``, uniform over
the spherical cap (``cos θ`` uniform in ``[cos cone, 1]``), azimuth uniform:
``F = |F| (−cos θ n + sin θ (cos φ t1 + sin φ t2))``.

Material model
--------------
``fixed``: the configured constants. ``varies``: each constant ``p`` uniform in
``[p (1 − r), p (1 + r)]`` with ``r = vary_rel``; every sampled set is checked
for Drucker stability before any solve (refused, or dropped and reported with
``on_unstable: clip``). A liver with its own material (``material["per_liver"]``,
an imported liver's ``geometry.imported[].material``) takes its own constants
for ``p``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from liverforce.layout import case_id
from liverforce.seeds import derive


class SweepError(ValueError):
    """The sweep cannot be built from this configuration."""


@dataclass
class ExertionSet:
    """Candidate exertion points of one geometry (sampled on the visible surface, or the user's own)."""

    points: np.ndarray  # (k, 3) mm
    normals: np.ndarray  # (k, 3) outward unit normals
    frames: np.ndarray  # (k, 3, 3) rows t1, t2, n


@dataclass
class DesignResult:
    rows: list[dict]
    dropped_unstable: list[dict] = field(default_factory=list)


def sample_exertion_points(
    points: np.ndarray,
    facets: np.ndarray,
    facet_visible: np.ndarray,
    n_points: int,
    min_spacing_mm: float,
    seed: int,
) -> np.ndarray:
    """Sample ``n_points`` points on the visible surface, at least ``min_spacing_mm`` apart.

    Area-weighted random points on visible facets (seeded), accepted greedily
    in draw order when farther than the spacing from every accepted point. The
    first point is the visible facet centroid closest to the visible area's
    centroid (the natural "fixed" exertion point of scenario I).

    Raises
    ------
    SweepError
        If the visible region is empty or cannot hold that many points at that
        spacing (lower ``sweep.exertion.min_spacing_mm`` or ``n_points``).
    """
    vis = np.flatnonzero(facet_visible)
    if vis.size == 0:
        raise SweepError("the geometry has no visible surface facets: no exertion point can be placed")
    tri = points[facets[vis]]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    cent = tri.mean(axis=1)
    mid = (cent * area[:, None]).sum(axis=0) / area.sum()
    first = cent[np.argmin(np.linalg.norm(cent - mid, axis=1))]
    chosen = [first]
    rng = np.random.default_rng(seed)
    n_draw = max(200, 200 * n_points)
    which = rng.choice(vis.size, size=n_draw, p=area / area.sum())
    r1, r2 = rng.random(n_draw), rng.random(n_draw)
    s = np.sqrt(r1)
    bary = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    cand = np.einsum("nk,nkd->nd", bary, tri[which])
    for c in cand:
        if len(chosen) >= n_points:
            break
        if np.min(np.linalg.norm(np.asarray(chosen) - c, axis=1)) >= min_spacing_mm:
            chosen.append(c)
    if len(chosen) < n_points:
        raise SweepError(
            f"only {len(chosen)} exertion points fit on the visible surface at {min_spacing_mm} mm spacing "
            f"(asked {n_points}); lower sweep.exertion.min_spacing_mm or sweep.exertion.n_points"
        )
    return np.asarray(chosen)


def _sobol(n: int, d: int, seed: int) -> np.ndarray:
    from scipy.stats import qmc  # here: scipy.stats costs ~0.6 s to import, and the config check imports this module

    sampler = qmc.Sobol(d=d, scramble=True, seed=seed)
    m = int(np.ceil(np.log2(max(n, 2))))
    return sampler.random_base2(m)[:n]


def _lhs(n: int, d: int, seed: int) -> np.ndarray:
    from scipy.stats import qmc

    return qmc.LatinHypercube(d=d, seed=seed).random(n)


#: design name -> sampler ``(n, d, seed) -> (n, d)`` points in the unit cube
DESIGNS = {"sobol": _sobol, "lhs": _lhs}


def design_names() -> tuple[str, ...]:
    """Names accepted as ``sweep.design`` (the keys of :data:`DESIGNS`)."""
    return tuple(DESIGNS)


def _unit_samples(design: str, n: int, d: int, seed: int) -> np.ndarray:
    if design not in DESIGNS:
        raise SweepError(f"unknown design '{design}' (one of {', '.join(design_names())})")
    return DESIGNS[design](n, d, seed)


def force_vectors(u_mag, u_cos, u_az, frames, min_n, max_n, cone_deg) -> np.ndarray:
    """Force vectors (N) from unit samples and local frames (rows t1, t2, n)."""
    mag = min_n + u_mag * (max_n - min_n)
    cos_cone = np.cos(np.radians(cone_deg))
    cos_t = 1.0 - u_cos * (1.0 - cos_cone)
    sin_t = np.sqrt(np.clip(1.0 - cos_t**2, 0.0, None))
    phi = 2.0 * np.pi * u_az
    t1, t2, n = frames[:, 0], frames[:, 1], frames[:, 2]
    direction = -cos_t[:, None] * n + sin_t[:, None] * (np.cos(phi)[:, None] * t1 + np.sin(phi)[:, None] * t2)
    return mag[:, None] * direction


def build_cases(
    scenario: str,
    spec: dict,
    geometry_ids: list[str],
    exertion: dict[str, ExertionSet],
    material: dict,
    force: dict,
    design: str,
    seed: int,
    cases_per_shard: int,
    stability_check,
    bulk_modulus,
) -> DesignResult:
    """The case table of one scenario.

    Parameters
    ----------
    scenario : str
        ``I`` ... ``IV`` or ``V`` (validation).
    spec : dict
        ``n_cases``, ``exertion`` (fixed|varies), ``material`` (fixed|varies).
    geometry_ids : list of str
        Geometries this scenario draws from (cases spread evenly, in order).
    exertion : dict
        Candidate exertion points per geometry id.
    material : dict
        The ``material`` config slice (model, params_mpa, nu, vary_rel, on_unstable), and optionally
        ``per_liver``: geometry id -> ``{"params_mpa": ...}``, a liver's own constants in place of params_mpa.
    force : dict
        ``min_n``, ``max_n``, ``cone_deg``.
    stability_check : callable(model, params) -> (bool, str)
        Drucker check; ``(False, reason)`` for an unstable set.
    bulk_modulus : callable(model, params, nu) -> float
        Bulk modulus (MPa) of a constant set.

    Returns
    -------
    DesignResult
        ``rows`` ordered for warm starts (geometry, exertion point, then a
        nearest-neighbour chain of forces, see :func:`warm_start_order`) with
        their shard index; ``dropped_unstable`` the refused sets.
    """
    n = int(spec["n_cases"])
    names = sorted(material["params_mpa"])
    model = material["model"]
    own = material.get("per_liver") or {}
    bases = {}  # geometry id -> the constants its cases take or draw around
    for gid in dict.fromkeys(geometry_ids):
        given = (own.get(gid) or {}).get("params_mpa")
        if given is not None and set(given) != set(names):
            raise SweepError(f"{gid}: its own material gives {sorted(given)}, the run's {model} has {names}: give "
                             "geometry.imported[].material.params_mpa with the run's constant names, or a scale")
        bases[gid] = np.array([(given or material["params_mpa"])[k] for k in names], dtype=float)
        ok, why = stability_check(model, dict(zip(names, bases[gid])))
        if not ok:
            whose = (f"the liver {gid}'s own material (geometry.imported[].material)" if given is not None
                     else f"material '{model}'")
            raise SweepError(
                f"{whose} with constants {dict(zip(names, bases[gid].tolist()))} MPa is not Drucker-stable: {why}. "
                "Fit stable constants (liverforce.fem.fitting) or choose another material (config group material/)."
            )
    d = 5 + len(names)
    u = _unit_samples(design, n, d, seed)
    g_idx = np.minimum((np.arange(n) * len(geometry_ids)) // n, len(geometry_ids) - 1)

    rows, dropped = [], []
    for i in range(n):
        gid = geometry_ids[g_idx[i]]
        ex = exertion[gid]
        k = 0 if spec["exertion"] == "fixed" else min(int(u[i, 3] * len(ex.points)), len(ex.points) - 1)
        base = bases[gid]
        if spec["material"] == "fixed":
            params = base.copy()
        else:
            r = material["vary_rel"]
            params = base * (1.0 + r * (2.0 * u[i, 5:] - 1.0))
        pdict = dict(zip(names, params.tolist()))
        if spec["material"] != "fixed":
            ok, why = stability_check(model, pdict)
            if not ok:
                if material["on_unstable"] == "refuse":
                    raise SweepError(
                        f"scenario {scenario}: sampled constants {pdict} MPa are not Drucker-stable ({why}); "
                        "narrow material.vary_rel or set material.on_unstable=clip to drop such sets"
                    )
                dropped.append({"index": i, "params_mpa": pdict, "reason": why})
                continue
        f = force_vectors(u[i:i + 1, 0], u[i:i + 1, 1], u[i:i + 1, 2], ex.frames[k:k + 1], force["min_n"], force["max_n"], force["cone_deg"])[0]
        rows.append(
            {
                "case_id": case_id(scenario, i),
                "scenario": scenario,
                "geometry_id": gid,
                "shard_index": -1,
                "seed": derive(seed, "sweep.case", i),
                "material_model": model,
                "material_param_names": names,
                "material_params_mpa": params.tolist(),
                "bulk_modulus_mpa": float(bulk_modulus(model, pdict, material["nu"])),
                "exertion_id": int(k),
                "exertion_point_mm": ex.points[k].tolist(),
                "exertion_normal": ex.normals[k].tolist(),
                "force_n": f.tolist(),
                "force_magnitude_n": float(np.linalg.norm(f)),
            }
        )
    if not rows:
        raise SweepError(f"scenario {scenario}: every sampled material set was unstable; narrow material.vary_rel")
    rows = warm_start_order(rows)
    for j, r in enumerate(rows):
        r["shard_index"] = j // cases_per_shard
    return DesignResult(rows=rows, dropped_unstable=dropped)


def warm_start_order(rows: list[dict]) -> list[dict]:
    """Rows ordered for warm starts: by geometry and exertion point, then a nearest-neighbour chain.

    Each case starts from a neighbouring case's solution, so within one
    (geometry, exertion point) group the chain starts at the smallest force
    and always moves to the closest case not yet visited
    (:func:`liverforce.fem.continuation.case_distance`: the change of load,
    with a material change counted as the load it unbalances). Sorting by magnitude
    alone lets consecutive forces differ in direction by up to twice the cone
    angle; the chain keeps the steps short. Deterministic.
    """
    from liverforce.fem.continuation import chain_order

    groups: dict = {}
    for r in sorted(rows, key=lambda r: (r["geometry_id"], r["exertion_id"], r["case_id"])):
        groups.setdefault((r["geometry_id"], r["exertion_id"]), []).append(r)
    out = []
    for key in sorted(groups):
        g = groups[key]
        order = chain_order([r["force_n"] for r in g], [r["material_params_mpa"] for r in g])
        out.extend(g[i] for i in order)
    return out


def n_shards(n_cases: int, cases_per_shard: int) -> int:
    """Number of shards of a scenario (upper bound: dropped cases never add shards)."""
    return max(1, -(-int(n_cases) // int(cases_per_shard)))
