"""The whole workflow for real on the smoke experiment, then the re-run rules.

One Snakemake run (session fixture) feeds every test here: the outputs of
every stage exist and agree with each other, the report cites MLflow runs
whose numbers it shows, and changing one config value re-runs exactly that
value's stage and its descendants.
"""
from __future__ import annotations

import json
import re

import numpy as np
import pytest

from test_workflow import job_counts, snakemake

# the whole smoke workflow (every stage, the camera model and the interval folds included) and its re-runs:
# in the CI slow set, keeping the default set well under 15 minutes
pytestmark = [pytest.mark.slow, pytest.mark.workflow]


@pytest.fixture(scope="session")
def smoke_run(tmp_path_factory):
    work = tmp_path_factory.mktemp("smoke")
    snakemake("--cores", "2", "--directory", str(work), "--config", "experiment=smoke", timeout=1500)
    return work


def test_every_stage_produced_its_outputs(smoke_run):
    root = smoke_run / "results" / "smoke"
    assert sorted(p.name for p in (root / "mesh").glob("*.vtu")) == ["proc-0000.vtu", "proc-0001.vtu", "proc-0002.vtu", "val-1000.vtu", "val-1001.vtu"]
    for scenario in ("I", "II", "III", "IV", "V"):
        m = json.loads((root / "shards" / scenario / "manifest.json").read_text())
        assert m["rows"] == (12 if scenario != "V" else 2 * 4)  # V: 2 unseen livers x 4 cases
        assert m["failed"] <= m["rows"] // 4, f"too many failed cases in {scenario}: {m}"
    for scenario in ("I", "II", "III", "IV"):
        for variant in ("pca_sv", "ae_sv", "cloud_sv"):
            metrics = json.loads((root / "models" / scenario / variant / "metrics.json").read_text())
            assert metrics["run_id"]
    iv = json.loads((root / "models" / "IV" / "pca_sv" / "metrics.json").read_text())
    ot = iv["outside_training"]  # IV test cases outside the training livers' range, over every split
    assert ot["n_splits"] == iv["n_splits"] and ot["n_cases"] == sum(r["outside_training"]["n_cases"] for r in iv["repeats"])
    cam_doc = json.loads((root / "models" / "IV" / "cloud_sv" / "metrics.json").read_text())
    cam = cam_doc["outside_training"]
    assert cam["n_cases"] == ot["n_cases"]  # the camera model has the same test livers and the state vector
    # the camera model is also scored on every split with an exact tool tip; a node model has no tip to make exact
    assert cam_doc["exact_tip"]["n_splits"] == cam_doc["n_splits"] == len(cam_doc["repeats"])
    assert cam_doc["exact_tip"]["metrics_mean"]["mae_vec"] == pytest.approx(
        np.mean([r["exact_tip"]["mae_vec"] for r in cam_doc["repeats"]]))
    assert iv["exact_tip"] is None and all("exact_tip" not in r for r in iv["repeats"])
    hp = json.loads((root / "models" / "II" / "pca_sv" / "metrics.json").read_text())["heldout_points"]
    assert hp["folds"] >= 2 and sum(f["n_test"] for f in hp["per_fold"]) == 12  # every II case, by point
    val = json.loads((root / "validate" / "metrics.json").read_text())
    # validate.input: camera -> the main camera-cloud variant is validated; the node models are the reference
    assert set(val["all_variants"]) == {"pca_sv", "ae_sv", "cloud_sv"} and val["model_variant"] == "cloud_sv"
    assert val["metrics"] == pytest.approx(val["all_variants"]["cloud_sv"]["metrics"])
    # every variant's error per force bin; the validated one's is the headline's
    assert (json.dumps(val["all_variants"]["cloud_sv"]["error_by_force_magnitude"])
            == json.dumps(val["error_by_force_magnitude"]))
    sens = val["camera_sensitivity"]
    assert [r["value"] for r in sens["n_points"]] == [200, 2000]  # the smoke experiment's
    assert all(np.isfinite(r["mae_vec"]) for k in ("n_points", "noise_sd_mm", "cone_half_angle_deg", "tip_noise_mm")
               for r in sens[k])
    assert sorted(val["per_liver"]) == ["val-1000", "val-1001"] and val["livers"]["n"] == 2
    # the calibrated interval, measured on the unseen livers (smoke: too few calibration cases -> unbounded)
    iv = val["interval"]
    assert iv["nominal"] == 0.9 and len(iv["coverage"]) == 3 and sorted(iv["coverage_per_liver"]) == ["val-1000", "val-1001"]
    # a width per bin of the predicted force (the default), with its coverage per quintile of |F|
    assert iv["scale"] == "force_bins" and 1 <= len(iv["coverage_by_force"]) <= 5
    assert sum(b["n"] for b in iv["coverage_by_force"]) == val["n_cases"]
    # the unseen cases the input-distance flag warns about (the validated camera model is a GP ensemble)
    far = iv["input_distance"]
    assert far["quantile"] == 0.9 and far["n_cases"] == val["n_cases"] and far["threshold"] > 0
    assert sum(far["per_liver"].values()) == far["n_flagged"]
    assert (far["mae_flagged_n"] is None) == (far["n_flagged"] == 0)
    # the unseen cases serving would warn about (state outside the training range), counted per input and liver
    ext = val["outside_training"]
    assert ext["n_cases"] == val["n_cases"] and sum(ext["per_liver"].values()) == ext["n_outside"]
    assert set(ext["by_input"]) == {"tool_thickness_mm", "probe_compliance_mm_per_n", "liver_size_mm",
                                    "centroid_distance_mm"} and max(ext["by_input"].values()) <= ext["n_outside"]
    assert (ext["mae_outside_n"] is None) == (ext["n_outside"] == 0)
    for study in ("roi_fraction", "encoder", "state_vector", "occlusion", "noise", "train_size", "train_livers"):
        doc = json.loads((root / "studies" / f"{study}.json").read_text())
        assert len(doc["points"]) == 2 and (root / "studies" / f"{study}.png").stat().st_size > 5000
        assert all(p["run_id"] for p in doc["points"])
    assert (root / "report" / "index.html").stat().st_size > 1000
    page = (root / "report" / "index.html").read_text()
    assert "id='camera'" in page and "class='camera-sens'" in page  # camera vs correspondence, sensitivity
    # the camera table's exact-tip columns: each scenario's from its metrics.json, the unseen livers' from the
    # validated camera model's sensitivity row at tip noise 0
    cam_rows = {_text(c[0]): c for c in (_cells(r) for r in re.findall(r"<tr class='cam'>.*?</tr>", page))}
    ex = cam_doc["exact_tip"]
    assert _text(cam_rows["IV"][4]) == f"{ex['metrics_mean']['accuracy_pct']:.1f} ± {ex['metrics_sd']['accuracy_pct']:.1f}"
    assert _text(cam_rows["IV"][7]) == f"{ex['metrics_mean']['mae_vec']:.3f} ± {ex['metrics_sd']['mae_vec']:.3f}"
    t0 = next(r for r in sens["tip_noise_mm"] if r["value"] == 0.0)
    assert _text(cam_rows["unseen livers"][7]) == f"{t0['mae_vec']:.3f} ± {t0['mae_sd']:.3f}"
    assert (root / "report" / "figures" / "population.png").stat().st_size > 20000
    # no half-written file anywhere
    assert not list(root.rglob(".*.tmp*"))


def _cells(row_html: str) -> list[str]:
    return re.findall(r"<t[dh]>(.*?)</t[dh]>", row_html)


def _text(cell: str) -> str:
    return re.sub(r"<[^>]+>", "", cell).strip()


def _unflagged(cell: str, values) -> str:
    """An accuracy cell's number as printed; a cell flagged as extrapolation only where one of ``values`` (%, the
    accuracies it stands for) is below 0 % (the errors exceed the forces), and then with the lowest of them."""
    m = re.search(r"⚠ extrapolation: (.*?) <small>\(below 0 %.*?lowest (\S+) %\)", cell)
    low = [v for v in values if v < 0.0]
    assert bool(m) == bool(low), (cell, values)
    if m:
        assert float(m.group(2)) == pytest.approx(min(low), abs=0.051, rel=0.01)
        return m.group(1)
    return cell


def test_report_numbers_match_the_mlflow_runs_they_cite(smoke_run):
    import mlflow

    root = smoke_run / "results" / "smoke"
    html = (root / "report" / "index.html").read_text()
    html = html[html.index("id='models'"):html.index("id='validation'")]
    client = mlflow.tracking.MlflowClient(tracking_uri=f"sqlite:///{smoke_run / 'results' / 'mlflow.db'}")
    rows = [_cells(r) for r in re.findall(r"<tr class='model'>(.*?)</tr>", html)]
    assert len(rows) == 12  # 4 scenarios x pca_sv, ae_sv, cloud_sv
    for c in rows:
        scenario, variant = c[0], c[1]
        doc = json.loads((root / "models" / scenario / variant / "metrics.json").read_text())
        acc_pm = _unflagged(c[4], [doc["metrics_mean"]["accuracy_pct"]]
                            + [r["metrics"]["accuracy_pct"] for r in doc["repeats"]])
        acc = _unflagged(c[7], [doc["metrics"]["accuracy_pct"]])
        mae_pm, n_splits, mae = c[5], c[6], c[9]
        run_id = re.search(r"<code>(\w+)</code>", c[12]).group(1)
        run = client.get_run(run_id)
        assert doc["run_id"] == run_id
        assert run.data.tags["scenario"] == scenario and run.data.tags["variant"] == variant
        assert float(acc) == pytest.approx(run.data.metrics["accuracy_pct"], abs=0.051)
        assert float(mae) == pytest.approx(run.data.metrics["mae_vec"], abs=0.0006)
        # mean ± sd over the repeated splits: in metrics.json and in the run, and the splits really differ
        assert int(n_splits) == doc["n_splits"] == len(doc["repeats"]) == 2 == run.data.metrics["n_splits"]
        assert len({json.dumps(r["metrics"], sort_keys=True) for r in doc["repeats"]}) == 2
        if variant == "cloud_sv":  # the exact-tip figures of the camera table are the run's too
            assert run.data.metrics["exact_tip_accuracy_pct_mean"] == pytest.approx(
                doc["exact_tip"]["metrics_mean"]["accuracy_pct"])
        else:
            assert "exact_tip_accuracy_pct_mean" not in run.data.metrics
        for shown, key, nd in ((acc_pm, "accuracy_pct", 1), (mae_pm, "mae_vec", 3)):
            assert shown == f"{doc['metrics_mean'][key]:.{nd}f} ± {doc['metrics_sd'][key]:.{nd}f}"
            m, sd = (float(x) for x in shown.split(" ± "))
            assert m == pytest.approx(run.data.metrics[f"{key}_mean"], abs=0.6 * 10 ** -nd)
            assert sd == pytest.approx(run.data.metrics[f"{key}_sd"], abs=0.6 * 10 ** -nd)
        # Ax trials are nested runs under the scenario's run (the MLP variant); the GP has no search
        children = client.search_runs([run.info.experiment_id], f"tags.mlflow.parentRunId = '{run_id}'")
        assert len(children) == (2 if variant == "ae_sv" else 0)
        assert doc["best_params"].get("regressor", "mlp") == ("mlp" if variant == "ae_sv" else "gp")


def test_report_shows_every_unseen_liver_as_the_validation_json_and_run_have_it(smoke_run):
    import mlflow

    root = smoke_run / "results" / "smoke"
    html = (root / "report" / "index.html").read_text()
    val = json.loads((root / "validate" / "metrics.json").read_text())
    lv, per = val["livers"], val["per_liver"]
    client = mlflow.tracking.MlflowClient(tracking_uri=f"sqlite:///{smoke_run / 'results' / 'mlflow.db'}")
    run = client.get_run(val["run_id"])
    assert run.data.metrics["mae_vec_livers_mean"] == pytest.approx(lv["mean"]["mae_vec"])
    head = html[html.index("id='unseen-headline'"):]
    head = head[:head.index("</p>")]
    assert (f"MAE <b>{lv['mean']['mae_vec']:.3f} ± {lv['sd']['mae_vec']:.3f} N</b>, accuracy "
            f"<b>{lv['mean']['accuracy_pct']:.1f} ± {lv['sd']['accuracy_pct']:.1f} %</b> (mean ± sd over the "
            f"{len(per)} livers)") in head and f"worst liver <code>{lv['worst']}</code>" in head
    sec = html[html.index("id='validation'"):html.index("id='studies'")]
    rows = [_cells(r) for r in re.findall(r"<tr class='liver'>(.*?)</tr>", sec)]
    assert [_text(c[0]).split()[0] for c in rows] == sorted(per)
    for c in rows:
        m = per[_text(c[0]).split()[0]]
        assert c[2:] == [str(m["n"]), f"{m['mae_vec']:.3f}", f"{m['rmse_vec']:.3f}", f"{m['accuracy_pct']:.1f}"]
    mean_row = _cells(re.search(r"<tr class='livers-mean'>(.*?)</tr>", sec).group(1))
    assert mean_row[3] == f"{lv['mean']['mae_vec']:.3f} ± {lv['sd']['mae_vec']:.3f}"
    bins = [_cells(r) for r in re.findall(r"<tr class='force-bin'>(.*?)</tr>", sec)]
    assert len(bins) == len(val["error_by_force_magnitude"]) >= 1
    for c, b in zip(bins, val["error_by_force_magnitude"]):
        assert _text(c[5]).startswith(f"{100 * b['relative_mae']:.1f} %")
        assert ("⚠" in c[5]) == (b["relative_mae"] >= 0.2)
    # the population picture of every training and unseen liver, with its caption
    assert "<figure class='population'><img src='figures/population.png'" in html


def test_report_study_numbers_match_their_mlflow_runs(smoke_run):
    import mlflow

    root = smoke_run / "results" / "smoke"
    html = (root / "report" / "index.html").read_text()
    html = html[html.index("id='studies'"):]
    client = mlflow.tracking.MlflowClient(tracking_uri=f"sqlite:///{smoke_run / 'results' / 'mlflow.db'}")
    rows = re.findall(r"<tr class='study-point'><td>(\w+)</td><td>(I|II|III|IV)</td><td>([^<]+)</td>"
                      r"<td>([-\d.–]+)</td><td>([\d.–]+)</td>.*?<code>(\w+)</code>", html)
    assert len(rows) == 14  # 7 studies x 2 points (smoke)
    ok = 0
    for study, scenario, label, acc, mae, run_id in rows:
        run = client.get_run(run_id)
        assert run.data.tags["study"] == study and run.data.tags["scenario"] == scenario
        assert run.data.tags["label"] == label
        assert client.get_experiment(run.info.experiment_id).name == "liverforce-smoke-studies"
        if acc != "–":
            ok += 1
            assert float(acc) == pytest.approx(run.data.metrics["accuracy_pct"], abs=0.051)
            assert float(mae) == pytest.approx(run.data.metrics["mae_vec"], abs=0.0006)
    assert ok >= 8
    # the Table 5.9 cells cite runs too, and those runs hold the numbers shown
    full = (root / "report" / "index.html").read_text()
    t59 = full[full.index("class='t59'"):]
    t59 = t59[:t59.index("</table>")]
    cells = re.findall(r"<span class='pm'>([-\d.]+) ± ([\d.]+) %</span>.*?<span class='split'>([-\d.]+) %"
                       r"</span>.*?run <code>(\w+)</code>", t59)
    assert len(cells) == 4  # smoke: scenarios I-IV with the state vector, each mean ± sd over the splits
    for mean, sd, acc, run_id in cells:
        metrics = client.get_run(run_id).data.metrics
        assert float(acc) == pytest.approx(metrics["accuracy_pct"], abs=0.051)
        assert float(mean) == pytest.approx(metrics["accuracy_pct_mean"], abs=0.051)
        assert float(sd) == pytest.approx(metrics["accuracy_pct_sd"], abs=0.051)


def test_changing_one_value_reruns_only_its_stage_and_descendants(smoke_run):
    def rerun(override):
        out = snakemake("-n", "--directory", str(smoke_run), "--config", "experiment=smoke",
                        f"overrides={override}").stdout
        return job_counts(out) if "Job stats" in out else {}

    assert rerun("tracking.experiment_prefix=liverforce") == {}  # nothing changed: nothing to do
    counts = rerun("model.dropout=0.3")
    assert set(counts) == {"train", "study", "validate", "physics", "report", "all"}  # physics scores the IV models
    counts = rerun("study.noise.values=[0.0,1.0]")  # one study's setting: that study and the report only
    assert counts == {"study": 1, "report": 1, "all": 1}
    counts = rerun("sweep.force.max_n=4.0")
    assert {"sweep", "simulate", "manifest", "train"} <= set(counts)
    assert "geometry" not in counts and "mesh" not in counts
    counts = rerun("mesh.target_nodes=900")
    assert "mesh" in counts and "geometry" not in counts


def test_a_variant_can_train_on_another_roi_fraction_without_new_simulations(smoke_run):
    """model.roi_fraction re-grows the ROI from the stored full surface; the saved model serves that fraction."""
    from liverforce.serve import Predictor

    root = smoke_run / "results" / "smoke"
    shards_before = {p: p.stat().st_mtime_ns for p in (root / "shards").rglob("*.parquet")}
    variant = "[{name:roi30,encoder:pca,state_vector:true,roi_fraction:0.3}]"
    proc = snakemake("--cores", "2", "--directory", str(smoke_run), "--config", "experiment=smoke",
                     f"overrides=train.variants={variant}", "--", "results/smoke/models/II/roi30/metrics.json")
    assert "rule simulate" not in proc.stdout and "rule mesh" not in proc.stdout
    assert {p: p.stat().st_mtime_ns for p in (root / "shards").rglob("*.parquet")} == shards_before
    metrics = json.loads((root / "models" / "II" / "roi30" / "metrics.json").read_text())
    base = json.loads((root / "models" / "II" / "pca_sv" / "metrics.json").read_text())
    assert metrics["run_id"] and metrics["metrics"]["mae_vec"] > 0
    assert Predictor.load(root / "models" / "II" / "roi30" / "model").roi_fraction == pytest.approx(0.3)
    assert Predictor.load(root / "models" / "II" / "pca_sv" / "model").roi_fraction == pytest.approx(0.18)
    log = (root / "logs" / "train" / "II-roi30.log").read_text()
    assert "ROI re-grown at 0.300" in log
    assert metrics["model_cfg"]["roi_fraction"] == 0.3 and base["model_cfg"].get("roi_fraction") is None


def test_adding_a_variant_reruns_only_that_variants_jobs(smoke_run):
    """A third variant: only its four trainings and what reads them (validation, the physics study that scores
    every IV variant, report) are out of date."""
    variants = ("train.variants=[{name:pca_sv,encoder:pca,state_vector:true},"
                "{name:ae_sv,encoder:ae,state_vector:true,regressor:mlp},{name:dae_sv,encoder:dae,state_vector:true}]")
    out = snakemake("-n", "--directory", str(smoke_run), "--config", "experiment=smoke",
                    f"overrides={variants}").stdout
    counts = job_counts(out)
    assert counts.get("train") == 4, counts
    assert set(counts) <= {"train", "models", "validate", "physics", "report", "all"}, counts
    trained = re.findall(r"wildcards: scenario=(\w+), variant=(\w+)", out)
    assert sorted(trained) == [(s, "dae_sv") for s in ("I", "II", "III", "IV")]


def test_predict_from_the_liver_files_matches_the_data_factory(smoke_run, tmp_path, capsys):
    """`liverforce predict` with only files a lab has (the liver's tet mesh for the surface and the stiffness
    probe, the deformed ROI nodes, the exertion point, the material) gives the model's prediction on the
    shard row: the context (frame, ROI, liver features, thickness, probe compliance) is rebuilt exactly."""
    import numpy as np

    from liverforce.dataset import io as dio
    from liverforce.learn.model import ForceModel
    from liverforce.cli import main

    root = smoke_run / "results" / "smoke"
    model_dir = root / "models" / "IV" / "pca_sv" / "model"
    model = ForceModel.load(model_dir)
    assert model.meta["probe"]["reference"]["model"] and model.pre.linear_force_weights is not None
    a = dio.load_training_arrays(dio.verify_manifest(root / "shards" / "IV" / "manifest.json"))
    i = 0
    row = {k: (v[i:i + 1] if not isinstance(v, list) else v[i:i + 1]) for k, v in a.items()}
    expect = model.predict(row)[0]
    np.save(tmp_path / "nodes.npy", np.asarray(a["roi_deformed_mm"][i], float))
    mesh = root / "mesh" / f"{a['geometry_id'][i]}.vtu"
    args = ["predict", "-m", str(model_dir), str(tmp_path / "nodes.npy"), "--mode", "nodes", "--surface", str(mesh),
            "--exertion-point", *map(str, a["exertion_point_mm"][i]),
            "--material", *map(str, a["material_params_mpa"][i]), "--out", str(tmp_path / "f.json")]
    assert main(args) == 2  # without the mesh for the probe: refused, naming --mesh
    assert main(args + ["--mesh", str(mesh)]) == 0
    got = json.loads((tmp_path / "f.json").read_text())["force_n"]
    np.testing.assert_allclose(got, expect, atol=1e-5)
    # the same files in a lab's frame (a scanner's rotation with a reflection, and a shift) and in metres; the
    # mesh stays the mesh stage's copy (RAS mm): with --frame and --units, the same force, given back rotated
    from liverforce.serve.files import read_surface

    q, _ = np.linalg.qr(np.random.default_rng(0).normal(size=(3, 3)))
    M = np.eye(4)
    M[:3, :3] = q * np.sign(np.linalg.det(q)) @ np.diag([1.0, 1.0, -1.0])
    M[:3, 3] = [150.0, -80.0, 600.0]
    np.save(tmp_path / "M.npy", M)

    def lab(x):  # RAS mm -> the lab's frame, metres
        return (np.asarray(x, float) - M[:3, 3]) @ M[:3, :3] / 1000.0

    V, T = read_surface(mesh)
    np.savez(tmp_path / "lab_surface.npz", points=lab(V), facets=T[:, ::-1])  # outward in the reflected frame
    np.save(tmp_path / "lab_nodes.npy", lab(a["roi_deformed_mm"][i]))
    lab_args = ["predict", "-m", str(model_dir), str(tmp_path / "lab_nodes.npy"), "--mode", "nodes", "--surface",
                str(tmp_path / "lab_surface.npz"), "--exertion-point", *map(str, lab(a["exertion_point_mm"][i])),
                "--material", *map(str, a["material_params_mpa"][i]), "--mesh", str(mesh), "--units", "m",
                "--out", str(tmp_path / "lab.json")]
    capsys.readouterr()
    assert main(lab_args) == 2  # without the frame the exertion point is off the mesh (in RAS mm): refused
    err = capsys.readouterr().err
    assert "off the mesh's surface" in err and "no frame given" in err and "--frame" in err, err
    assert main(lab_args + ["--frame", str(tmp_path / "M.npy")]) == 0
    out = json.loads((tmp_path / "lab.json").read_text())
    np.testing.assert_allclose(out["force_n_model"], expect, atol=1e-5)
    np.testing.assert_allclose(out["force_n"], np.asarray(expect) @ M[:3, :3], atol=1e-5)


def test_a_finished_runs_scenario_loads_for_the_experiments(smoke_run):
    """run_arrays (what benchmarks/experiment_*.py load): a scenario's verified shards; for a camera model also
    the full-surface displacements and every liver's surface from the run's meshes; a manifest of other shards of
    the same livers by path; a missing scenario named in the error."""
    from liverforce.pipeline.shared import run_arrays

    root = smoke_run / "results" / "smoke"
    nodes = run_arrays(root, "IV", False, "test")
    cam = run_arrays(root, "IV", True, "test")
    assert list(nodes["case_id"]) == list(cam["case_id"]) and "surface_meshes" not in nodes
    assert set(np.asarray(cam["geometry_id"]).astype(str)) <= set(cam["surface_meshes"])
    assert all(len(d) > 0 for d in cam["surface_displacement_mm"])
    other = run_arrays(root, None, True, "test", manifest=root / "shards" / "V" / "manifest.json")
    assert list(other["case_id"]) == list(run_arrays(root, "V", True, "test")["case_id"])
    with pytest.raises(Exception, match="nosuch"):
        run_arrays(root, "nosuch", False, "test")


def test_a_camera_cloud_in_a_labs_frame_with_only_the_mesh_gives_the_shard_contexts_force(smoke_run, tmp_path, capsys):
    """The camera model from a lab's files: the cloud, the tool tip and the exertion point in the lab's frame and in
    metres, and the mesh stage's mesh, no surface. The pre-operative surface is then the mesh's own, the one the
    training cases were cut from, so the force is the one the shard row's own context gives (ROI, frame,
    thickness, liver size, probe), given back in the lab's frame."""
    from liverforce.cli import main
    from liverforce.learn.observation import ObservationConfig, observe_many, surface_point_displacement
    from liverforce.pipeline.shared import run_arrays
    from liverforce.serve import Predictor
    from liverforce.serve.preop import Preop

    root = smoke_run / "results" / "smoke"
    model_dir = root / "models" / "IV" / "cloud_sv" / "model"
    a = run_arrays(root, "IV", True, "test")
    i = 1
    g = str(a["geometry_id"][i])
    V, T = a["surface_meshes"][g]
    p = a["exertion_point_mm"][i]
    u = np.asarray(a["surface_displacement_mm"][i], float)
    tip = p + surface_point_displacement(V, T, p[None], [u])[0]
    cfg = ObservationConfig(n_points=(4000, 4000), noise_sd_mm=0.5, instrument_in_cloud=True)
    cloud = observe_many(V, T, [u], p[None], a["frame_normal"][i:i + 1], cfg, seed=3)[0][0]
    pred = Predictor.load(model_dir)
    expect, info = pred.predict_cloud(cloud, Preop.from_arrays(a, i), tool_tip_mm=tip, return_info=True)

    q, _ = np.linalg.qr(np.random.default_rng(1).normal(size=(3, 3)))
    M = np.eye(4)
    M[:3, :3] = q * np.sign(np.linalg.det(q))
    M[:3, 3] = [-40.0, 220.0, 35.0]
    np.save(tmp_path / "M.npy", M)

    def lab(x):  # RAS mm -> the lab's frame, metres
        return (np.asarray(x, float) - M[:3, 3]) @ M[:3, :3] / 1000.0

    np.save(tmp_path / "cloud_m.npy", lab(cloud))
    mesh = root / "mesh" / f"{g}.vtu"
    args = ["predict", "-m", str(model_dir), str(tmp_path / "cloud_m.npy"), "--mesh", str(mesh),
            "--exertion-point", *map(str, lab(p)), "--tool-tip", *map(str, lab(tip)),
            "--material", *map(str, a["material_params_mpa"][i]), "--units", "m", "--frame", str(tmp_path / "M.npy"),
            "--out", str(tmp_path / "f.json")]
    assert main(args) == 0, capsys.readouterr().err
    out = json.loads((tmp_path / "f.json").read_text())
    np.testing.assert_allclose(out["force_n_model"], expect, atol=1e-6)
    np.testing.assert_allclose(out["force_n"], np.asarray(expect) @ M[:3, :3], atol=1e-6)
    assert out.get("warnings", []) == info["warnings"]  # none of its own: no liver size or thickness of another
