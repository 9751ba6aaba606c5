"""A trained model says what it was trained on: each liver's origin and the material, in the model and its run.

An auditor found that a lab's model, trained on its own liver (a Gmsh file in metres and LPS, Young's modulus
in Pa), named neither the file nor the units, frame or material. The train stage now reads the geometry
records and the case table the earlier stages wrote (no new rule input) into ``meta["provenance"]``, the
MLflow run's tags, params and ``training_provenance.json``, and ``Predictor.describe`` (``liverforce predict
--describe``) gives one line per liver. Each test runs the real geometry stage on its liver and the real train
stage on shards of synthetic cases laid out as a run lays them out (no FE): a few seconds each.
"""
from __future__ import annotations

import argparse
import hashlib
import json
from pathlib import Path

import meshio
import numpy as np
import pytest

from liverforce.config import compose
from liverforce.dataset import io as dio
from liverforce.dataset.schema import CASE_SCHEMA
from liverforce.learn.model import ForceModel
from liverforce.learn.synthetic import synthetic_arrays
from liverforce.pipeline.geometry import make_geometry
from liverforce.pipeline.plan import Plan
from liverforce.pipeline.train import train_model
from liverforce.serve.predictor import Predictor
from liverforce.tracking import Tracker

MODEL = {"encoder": "pca", "code_size": 3, "state_vector": True, "grid_size": 6, "hidden": [16],
         "dropout": 0.0, "occlusion": {"radius_mm": 0.0, "mode": "remove"}, "noise_mm": 0.0}
TRAIN = {"test_fraction": 0.25, "epochs": 3, "batch_size": 32, "lr": 3e-3, "weight_decay": 0.0, "seed": 0,
         "repeats": 1, "final_fit": False}
NO_TUNE = {"enabled": False, "trials": 1, "folds": 2, "sobol_trials": 1, "epochs": 1}
LPS = np.array([-1.0, -1.0, 1.0])


def shard_rows(arrays: dict, scenario: str, gid: str, material: dict) -> list[dict]:
    """Full-schema shard rows of the synthetic cases, on liver ``gid`` with the configured material."""
    names = list(material["params_mpa"])
    rows = []
    for i in range(len(arrays["case_id"])):
        und = np.asarray(arrays["roi_undeformed_mm"][i], dtype=np.float32)
        de = np.asarray(arrays["roi_deformed_mm"][i], dtype=np.float32)
        rows.append({
            "case_id": f"{scenario}-{i:06d}", "scenario": scenario, "geometry_id": gid, "shard_index": 0,
            "seed": i, "material_model": material["model"], "material_param_names": names,
            "material_params_mpa": [float(material["params_mpa"][k]) for k in names], "bulk_modulus_mpa": 0.25,
            "exertion_id": i % 4, "exertion_point_mm": arrays["exertion_point_mm"][i],
            "force_n": arrays["force_n"][i], "force_magnitude_n": float(np.linalg.norm(arrays["force_n"][i])),
            "frame_normal": arrays["frame_normal"][i], "frame_t1": arrays["frame_t1"][i],
            "frame_t2": arrays["frame_t2"][i], "liver_centroid_mm": arrays["liver_centroid_mm"][i],
            "inertia_mm5": arrays["inertia_mm5"][i], "tool_thickness_mm": float(arrays["tool_thickness_mm"][i]),
            "probe_compliance_mm_per_n": np.asarray(arrays["probe_compliance_mm_per_n"][i]).ravel(),
            "roi_fraction": 0.18, "roi_area_fraction": 0.18, "roi_node_ids": np.arange(len(und), dtype=np.int32),
            "roi_triangles": np.asarray(arrays["roi_triangles"][i], np.int32),
            "roi_undeformed_mm": und, "roi_deformed_mm": de, "roi_centroid_undeformed_mm": und.mean(0),
            "roi_centroid_deformed_mm": de.mean(0), "surface_displacement_mm": np.zeros((0, 3), np.float32),
            "max_displacement_mm": 1.0, "max_principal_stretch": 1.1, "min_principal_stretch": 0.9,
            "converged": True, "reason": "", "load_fraction": 1.0, "load_steps": 1, "newton_iterations": 3,
            "final_residual": 1e-9, "linear_solver": "cholmod", "wall_time_s": 0.1,
        })
    return rows


@pytest.fixture(scope="module")
def uri(tmp_path_factory) -> str:
    """One MLflow store for the module's runs, created once (creating a store takes seconds)."""
    from liverforce.tracking import ensure_store

    uri = f"sqlite:///{tmp_path_factory.mktemp('store') / 'mlflow.db'}"
    ensure_store(uri)
    return uri


def run_stages(tmp_path, uri: str, overrides: list[str], gid: str, scenario: str = "II",
               records: bool = True) -> dict:
    """The geometry stage on liver ``gid`` of the composed config, the sweep's case table metadata, shards of
    synthetic cases on that liver and the train stage, all in the run's results layout; ``records=False``
    removes the geometry record and the case table first (a run made before they were read)."""
    cfg = compose(["experiment=smoke", f"results_dir={tmp_path / 'results'}", "study.enabled=false",
                   *overrides], run=False)
    plan = Plan(cfg)
    P = plan.paths
    make_geometry(plan.geometry_spec(gid), P.surface(gid), P.surface_meta(gid))
    params = plan.sweep_params(scenario)
    rows = shard_rows(synthetic_arrays(40, seed=3, n_geometries=1, nodes=(60, 90)), scenario, gid,
                      params["material"])
    case_rows = [{**{k: r[k] for k in CASE_SCHEMA.names if k in r}, "exertion_normal": r["frame_normal"]}
                 for r in rows]
    dio.write_case_table(case_rows, P.cases(scenario), extra_meta={"sweep": params})  # as make_sweep writes it
    probe = {"model": params["material"]["model"], "params_mpa": params["material"]["params_mpa"], "bulk_mpa": 0.25}
    dio.write_shard(rows, P.shard(scenario, 0), extra_meta={"simulate": dict(cfg["simulate"]), "probe": probe,
                                                             "boundary": dict(cfg["boundary"]),
                                                             "dataset": dict(cfg["dataset"])})
    dio.write_manifest([P.shard(scenario, 0)], P.manifest(scenario))
    if not records:
        for p in (P.surface_meta(gid), P.cases(scenario)):
            Path(p).unlink()
    res = train_model(P.manifest(scenario), scenario, "pca_sv", MODEL, TRAIN, NO_TUNE, uri, "liverforce-test",
                      "smoke", 0, 1, P.model_metrics(scenario, "pca_sv"), P.model_dir(scenario, "pca_sv"))
    run = Tracker(uri, "liverforce-test").client.get_run(res["run_id"])
    return {"res": res, "run": run, "meta": ForceModel.load(res["model_path"]).meta,
            "model_path": res["model_path"]}


def describe_cli(model_path, capsys) -> dict:
    """``liverforce predict -m <model> --describe``, parsed."""
    from liverforce.serve.cli import register

    parser = argparse.ArgumentParser(prog="liverforce")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["predict", "-m", str(model_path), "--describe"])
    assert args.func(args) == 0
    return json.loads(capsys.readouterr().out)


def test_a_model_trained_on_an_imported_liver_names_its_file_hash_units_frame_and_e_as_entered(tmp_path, uri,
                                                                                               capsys):
    from liverforce.geometry.procedural import LiverShapeParams, procedural_liver

    surf = procedural_liver(1, LiverShapeParams(voxel_mm=4.0))
    src = tmp_path / "lab" / "liver.msh"
    src.parent.mkdir()
    meshio.write(src, meshio.Mesh(surf.vertices * LPS / 1000.0, [("triangle", surf.faces)]), file_format="gmsh")
    sha = hashlib.sha256(src.read_bytes()).hexdigest()
    got = run_stages(tmp_path, uri, [f"geometry.imported=[{{name:lab,path:{src},units:m,frame:LPS}}]",
                                     "geometry.procedural.count=1", "material=neo_hookean_from_e",
                                     "material.E_pa=14900"], "imp-lab")

    prov = got["meta"]["provenance"]
    (liver,) = prov["livers"]
    assert liver["geometry_id"] == "imp-lab" and liver["kind"] == "imported" and liver["name"] == "lab"
    assert liver["file"] == "liver.msh" and liver["sha256"] == sha
    assert str(src.parent) not in json.dumps(prov)  # no folder of the lab's travels with the model
    assert liver["units"] == "m" and liver["units_declared"] == "m" and liver["scale_to_mm"] == 1000.0
    assert liver["frame"] == "LPS" and "x and y negated to RAS" in liver["converted"]
    assert liver["conversion"]["frame_matrix"][0][0] == -1.0 and liver["mesh_mode"] == "remesh"
    mat = prov["material"]
    assert mat["source"] == "config" and mat["model"] == "neo_hookean" and mat["entered"] == {"E_pa": 14900.0}
    assert mat["params_mpa"]["C10"] == pytest.approx(0.0025, rel=1e-3) and mat["nu"] == 0.49
    assert "E 14.9 kPa" in mat["conversion"]

    # the run: searchable tags and params, and the whole record as an artifact
    tags, params = got["run"].data.tags, got["run"].data.params
    assert tags["training.livers"] == "imp-lab" and tags["training.kinds"] == "imported"
    assert tags["training.files"] == "liver.msh" and tags["training.sha256"] == f"liver.msh:{sha[:12]}"
    assert tags["training.units"] == "m" and tags["training.frames"] == "LPS"
    assert params["material.E_pa"] == "14900" and params["material.model"] == "neo_hookean"
    assert params["material.source"] == "config"
    assert float(params["material.params_mpa.C10"]) == mat["params_mpa"]["C10"]
    assert not any(k.startswith("model._meta.provenance") for k in params)  # not flattened into the model's params
    client = Tracker(uri, "liverforce-test").client
    art = client.download_artifacts(got["res"]["run_id"], "training_provenance.json", str(tmp_path / "dl"))
    assert json.loads(open(art).read()) == prov

    # read back: the model's description, one line per liver and the material's
    lines = Predictor.load(got["model_path"]).describe()["trained_on"]
    assert lines == describe_cli(got["model_path"], capsys)["trained_on"]
    assert lines[0] == (f"imp-lab: imported liver.msh (sha256 {sha[:12]}), units m (x1000 to mm), frame LPS -> RAS")
    assert lines[1].startswith("material: neo_hookean C10 0.0025") and lines[1].endswith("(entered as E_pa 14900)")


def test_a_model_trained_on_a_procedural_liver_names_its_generator_and_seed(tmp_path, uri):
    got = run_stages(tmp_path, uri, ["geometry.procedural.count=2", "geometry.procedural.seed=5",
                                     "geometry.procedural.shape.voxel_mm=4.0"], "proc-0006")
    prov = got["meta"]["provenance"]
    (liver,) = prov["livers"]
    assert liver["geometry_id"] == "proc-0006" and liver["kind"] == "procedural" and liver["seed"] == 6
    assert liver["generator"].startswith("procedural-liver") and liver["params"]["voxel_mm"] == 4.0
    assert "sha256" not in liver and "file" not in liver
    assert prov["material"]["entered"] is None and prov["material"]["model"] == "yeoh"  # given in MPa
    tags, params = got["run"].data.tags, got["run"].data.params
    assert tags["training.kinds"] == "procedural" and tags["training.units"] == "mm"
    assert tags["training.frames"] == "RAS" and "training.files" not in tags
    assert "material.E_pa" not in params and params["material.params_mpa.C20"] == "0.0125"
    lines = Predictor.load(got["model_path"]).describe()["trained_on"]
    assert lines[0] == f"proc-0006: procedural ({liver['generator']}, seed 6)"
    assert lines[1] == "material: yeoh C10 0.00161, C20 0.0125, C30 0.00531 MPa, nu 0.49"


def test_missing_records_are_recorded_as_unknown_and_training_goes_on(tmp_path, uri):
    """A run made before the records were read (here: the geometry record and the case table removed) trains as
    before; the liver is unknown with its reason, the material the shards' probe reference."""
    got = run_stages(tmp_path, uri, ["geometry.procedural.count=2", "geometry.procedural.shape.voxel_mm=4.0"],
                     "proc-0000", records=False)
    prov = got["meta"]["provenance"]
    (liver,) = prov["livers"]
    assert liver["kind"] == "unknown" and "no geometry record at" in liver["reason"]
    assert prov["material"]["source"] == "shards" and prov["material"]["entered"] == "unknown"
    assert "no case table at sweep/" in prov["material"]["note"]
    assert "no geometry record at geometry/proc-0000.json" in liver["reason"]
    assert str(tmp_path) not in json.dumps(prov)  # the reasons name the layout's files, not the lab's folders
    assert got["run"].data.tags["training.kinds"] == "unknown"
    lines = Predictor.load(got["model_path"]).describe()["trained_on"]
    assert lines[0].startswith("proc-0000: origin unknown (no geometry record at")
    assert lines[1].endswith("(how it was entered is not recorded)")
    # a model saved before models recorded it: its description says so
    doc_path = Path(got["model_path"]) / "model.json"
    doc = json.loads(doc_path.read_text())
    del doc["meta"]["provenance"]
    doc_path.write_text(json.dumps(doc))
    (line,) = Predictor.load(got["model_path"]).describe()["trained_on"]
    assert line.startswith("unknown: the model records no training livers")


def test_shards_outside_a_results_layout_leave_every_record_unknown(tmp_path):
    from liverforce.pipeline.provenance import training_provenance

    prov = training_provenance(tmp_path / "manifest.json", ["proc-0001", "proc-0000", "proc-0001"])
    assert [r["geometry_id"] for r in prov["livers"]] == ["proc-0000", "proc-0001"]
    assert all(r["kind"] == "unknown" and "outside a results layout" in r["reason"] for r in prov["livers"])
    assert prov["material"]["source"] == "unknown" and "outside a results layout" in prov["material"]["reason"]
    assert str(tmp_path) not in json.dumps(prov)



def test_a_split_model_records_only_the_livers_it_was_fitted_on(tmp_path):
    """With ``train.final_fit`` off the saved model is the split model: in IV (split by liver) its test livers are
    not training livers, and the record says which they are."""
    from liverforce.learn.splits import train_test_split
    from liverforce.learn.train import train_scenario

    arrays = synthetic_arrays(48, seed=3, n_geometries=4, nodes=(60, 90))
    geo = np.asarray(arrays["geometry_id"]).astype(str)
    ids = sorted(set(geo.tolist()))
    prov = {"version": 1, "livers": [{"geometry_id": g, "kind": "procedural", "seed": i} for i, g in enumerate(ids)],
            "material": {"source": "config", "model": "neo_hookean", "params_mpa": {"C10": 0.0025},
                         "per_liver": {g: {"params_mpa": {"C10": 0.003}} for g in ids}}}
    res = train_scenario(arrays, MODEL, TRAIN, NO_TUNE, "IV", "pca_sv", threads=1, seed=0, out_dir=tmp_path,
                         provenance=prov)
    tr, te = train_test_split(geo, scenario="IV", test_fraction=TRAIN["test_fraction"], seed=0)
    fitted, held = sorted(set(geo[tr].tolist())), sorted(set(geo[te].tolist()))
    assert held and not set(held) & set(fitted)
    got = ForceModel.load(res["model_path"]).meta["provenance"]
    assert [r["geometry_id"] for r in got["livers"]] == fitted and got["test_livers"] == held
    assert sorted(got["material"]["per_liver"]) == fitted  # a test liver's own material is no training fact


def test_a_training_livers_own_material_is_recorded_with_the_run_material(tmp_path, uri, capsys):
    """A lab liver with its own material (``geometry.imported[].material``): the model names its constants and
    how they were entered beside the run's; the run gets them as params."""
    from liverforce.geometry.procedural import LiverShapeParams, procedural_liver

    src = tmp_path / "lab" / "liver.stl"
    src.parent.mkdir()
    procedural_liver(2, LiverShapeParams(voxel_mm=6.0)).to_trimesh().export(src)
    got = run_stages(tmp_path, uri, [f"geometry.imported=[{{name:lab,path:{src},units:mm,material:{{E_pa:9000}}}}]",
                                     "geometry.procedural.count=1", "material=neo_hookean"], "imp-lab")
    mat = got["meta"]["provenance"]["material"]
    own = mat["per_liver"]["imp-lab"]
    assert own["entered"] == {"E_pa": 9000} and own["params_mpa"]["C10"] == pytest.approx(9000e-6 / 2.98 / 2)
    lines = describe_cli(got["model_path"], capsys)["trained_on"]
    assert lines[-1] == f"material of imp-lab: its own, C10 {own['params_mpa']['C10']:.12g} MPa (entered as E_pa 9000)"
    # its only liver has its own material: the run's constants trained nothing, and a search by them must miss it
    assert lines[-2].startswith("material: not used (every training liver has its own, below); the run's "
                                "neo_hookean C10 0.0025")
    params = got["run"].data.params
    assert float(params["material.imp-lab.params_mpa.C10"]) == pytest.approx(own["params_mpa"]["C10"], rel=1e-11)
    assert params["material.run_constants"] == "unused" and "material.params_mpa.C10" not in params
