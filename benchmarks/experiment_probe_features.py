"""Experiment: does the pre-operative stiffness probe help scenario IV and unseen livers?

Reads a finished default run (shards, meshes), computes the linear compliance
at every case's exertion point (:mod:`liverforce.fem.probe`, reference
material = scenario I's), and trains the scenario-IV model twice on the same
splits: with today's state vector, and with the 6 compliance entries (local
frame) plus the linear force estimate ``C^-1 u_w`` (``u_w``: the ROI
displacement averaged with a Gaussian of the tool radius) inserted before the
material columns. Prints test accuracy/MAE (mean +- sd over ``train.repeats``
splits) and the MAE on the unseen livers (scenario V) of the first split's model.

The probe is not yet a shard column; this script patches the state vector of
:mod:`liverforce.learn.model` in-process to measure it.

    PYTHONPATH=. .venv/bin/python benchmarks/experiment_probe_features.py --results results/default
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import yaml

TRIU = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def compliances(results: Path, scenario: str, sim: dict, boundary: dict) -> dict:
    """case id -> (3, 3) compliance (mm/N) in the case's local frame."""
    import pyarrow.parquet as pq

    from liverforce.dataset import io as dio
    from liverforce.fem.materials import make_material
    from liverforce.fem.probe import ComplianceProbe
    from liverforce.fem.problem import LiverModel
    from liverforce.mesh.io import read_mesh
    from liverforce.pipeline.simulate import boundary_params, solver_options

    row = pq.read_table(dio.verify_manifest(results / "shards/I/manifest.json")[0]).slice(0, 1).to_pylist()[0]
    ref = make_material(row["material_model"], dict(zip(row["material_param_names"], row["material_params_mpa"])),
                        bulk_mpa=row["bulk_modulus_mpa"])
    a = dio.load_training_arrays(dio.verify_manifest(results / f"shards/{scenario}/manifest.json"))
    probes, cache, out = {}, {}, {}
    for i, (cid, gid) in enumerate(zip(a["case_id"], a["geometry_id"])):
        if gid not in probes:
            mesh = read_mesh(results / f"mesh/{gid}.vtu")
            fe = LiverModel(mesh.points, mesh.tets, mesh.facets, mesh.facet_region, ref,
                            boundary_params(mesh, boundary), solver_options(sim))
            probes[gid] = ComplianceProbe(fe)
        key = (gid, tuple(np.round(a["exertion_point_mm"][i], 6)))
        if key not in cache:
            frame = np.stack([a["frame_t1"][i], a["frame_t2"][i], a["frame_normal"][i]])
            cache[key] = probes[gid].compliance(a["exertion_point_mm"][i], frame, sim["tool_radius_mm"])
        out[str(cid)] = cache[key]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results/default")
    ap.add_argument("--variant", default="pca_sv")
    ap.add_argument("--config", default="config")
    ap.add_argument("--no-linear-force", action="store_true",
                    help="add only the compliance entries (no C^-1 u_w, which reads the displacement under the tool)")
    args = ap.parse_args()
    results, cfg = Path(args.results), Path(args.config)

    import liverforce.learn.model as M
    from liverforce.dataset import io as dio
    from liverforce.learn.frames import local_rotations
    from liverforce.learn.train import train_scenario

    def y(p):
        return yaml.safe_load((cfg / p).read_text())

    sim, boundary = y("simulate/default.yaml"), y("boundary/study.yaml")
    t0 = time.perf_counter()
    comp = {**compliances(results, "IV", sim, boundary), **compliances(results, "V", sim, boundary)}
    print(f"probe: {len(comp)} cases in {time.perf_counter() - t0:.1f} s", flush=True)

    base_state, base_start = M.state_vector, M.MATERIAL_START

    def probe_state(arrays):
        s = base_state(arrays)
        C = np.stack([comp[str(c)] for c in arrays["case_id"]])
        C = 0.5 * (C + np.transpose(C, (0, 2, 1)))
        R = local_rotations(arrays["frame_normal"], arrays["frame_t1"], arrays["frame_t2"])
        p = np.asarray(arrays["exertion_point_mm"], float)
        uw = []
        for i in range(len(p)):
            und = np.asarray(arrays["roi_undeformed_mm"][i], float)
            de = np.asarray(arrays["roi_deformed_mm"][i], float)
            w = np.exp(-0.5 * (np.linalg.norm(und - p[i], axis=1) / sim["tool_radius_mm"]) ** 2)
            uw.append((w[:, None] * (de - und)).sum(0) / w.sum())
        u_loc = np.einsum("nij,nj->ni", R, np.array(uw))
        f_lin = np.linalg.solve(C, u_loc[:, :, None])[:, :, 0]
        extra = np.stack([C[:, a, b] for a, b in TRIU], 1)
        if not args.no_linear_force:
            extra = np.column_stack([extra, f_lin])
        return np.column_stack([s[:, :base_start], extra, s[:, base_start:]])

    model = y("model/default.yaml")
    train = y("train/default.yaml")
    tune = y("tune/default.yaml")
    v = {x["name"]: x for x in train["variants"]}[args.variant]
    model.update({k: val for k, val in v.items() if k != "name"})
    train = {k: val for k, val in train.items() if k != "variants"}
    arrays = dio.load_training_arrays(dio.verify_manifest(results / "shards/IV/manifest.json"))
    unseen = dio.load_training_arrays(dio.verify_manifest(results / "shards/V/manifest.json"))
    for name, state, start in (("state vector", base_state, base_start), ("+ probe", probe_state, base_start + (6 if args.no_linear_force else 9))):
        M.state_vector, M.MATERIAL_START = state, start
        t = time.perf_counter()
        res = train_scenario(arrays, model, train, tune, "IV", args.variant, out_dir=f"/tmp/probe-exp-{start}")
        fm = M.ForceModel.load(res["model_path"])
        pred = fm.predict(unseen, observation_seed=M.eval_seed(res["seed"]))
        true = np.asarray(unseen["force_n"], float)
        g = np.asarray(unseen["geometry_id"]).astype(str)
        per = [float(np.linalg.norm(pred[g == x] - true[g == x], axis=1).mean()) for x in sorted(set(g))]
        m, s = res["metrics_mean"], res["metrics_sd"]
        print(f"{name:13s} IV test accuracy {m['accuracy_pct']:.1f} +- {s['accuracy_pct']:.1f} %, "
              f"MAE {m['mae_vec']:.3f} +- {s['mae_vec']:.3f} N ({res['n_splits']} splits); "
              f"unseen livers MAE {np.mean(per):.3f} +- {np.std(per, ddof=1):.3f} N over {len(per)} "
              f"(worst {max(per):.3f}); {time.perf_counter() - t:.0f} s", flush=True)
    M.state_vector, M.MATERIAL_START = base_state, base_start
    print(json.dumps({"note": "reference material = scenario I's; probe features inserted before the material"}))


if __name__ == "__main__":
    main()
