"""The comparison studies in the workflow DAG, and the report's layout from small hand-made stage outputs."""
from __future__ import annotations

import json
import re

import pytest

from test_workflow import job_counts, snakemake


@pytest.mark.parametrize("experiment", ["smoke", "default"])
def test_study_rules_are_in_the_dry_run_dag_and_feed_the_report(experiment, tmp_path):
    from liverforce.config import compose
    from liverforce.learn.study import enabled_studies

    out = snakemake("-n", "-p", "--directory", str(tmp_path), "--config", f"experiment={experiment}").stdout
    counts = job_counts(out)
    names = enabled_studies(compose([f"experiment={experiment}"])["study"])
    assert names == ["roi_fraction", "encoder", "state_vector", "occlusion", "noise", "train_size", "train_livers"]
    assert counts["study"] == len(names)
    for name in names:
        assert f"results/{experiment}/studies/{name}.json" in out
    # the report waits for the studies: they are among its inputs
    block = out[out.index("rule report:"):]
    block = block[:block.index("\n\n")]
    assert all(f"studies/{n}.json" in block for n in names)
    if experiment != "smoke":
        return
    # the `studies` target builds just the studies (and what they need: shards, main models), no validation
    targ = job_counts(snakemake("-n", "--directory", str(tmp_path), "--config", f"experiment={experiment}",
                                "--", "studies").stdout)
    assert targ["study"] == len(names) and "report" not in targ and "validate" not in targ


def test_studies_can_be_switched_off(tmp_path):
    out = snakemake("-n", "--directory", str(tmp_path), "--config", "experiment=smoke",
                    "overrides=study.enabled=false").stdout
    assert "study" not in job_counts(out) and job_counts(out)["report"] == 1


def test_study_config_is_checked():
    from liverforce.config import ConfigError, compose

    with pytest.raises(ConfigError, match="study.encoder.scenarios"):
        compose(["experiment=smoke", "train.scenarios=[I,II]"])
    with pytest.raises(ConfigError, match="study.occlusion.modes"):
        compose(["experiment=smoke", "study.occlusion.modes=[hide]"])
    with pytest.raises(ConfigError, match="study.epochs"):
        compose(["study.epochs=0"])
    assert compose(["experiment=smoke", "train.scenarios=[I,II]", "study.enabled=false"])["study"]["enabled"] is False


def _write(path, obj):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj))
    return path


def test_report_lays_out_table_59_encoders_and_studies_with_their_run_ids(tmp_path):
    from liverforce.report.html import STUDY_ACCURACY, collect, write_report

    root = tmp_path / "results" / "x"
    metrics = []
    for sc, acc in (("I", 97.0), ("II", 93.0), ("III", 89.0), ("IV", 80.0)):
        for variant, sv in (("pca_sv", True), ("pca_nosv", False)):
            metrics.append(_write(root / "models" / sc / variant / "metrics.json", {
                "scenario": sc, "variant": variant, "encoder": "pca", "state_vector": sv,
                "metrics": {"accuracy_pct": acc - (0 if sv else 5), "mae_vec": 0.1, "rmse_vec": 0.2},
                "run_id": f"run{sc}{variant}"}))
    manifest = _write(root / "shards" / "IV" / "manifest.json",
                      {"rows": 10, "failed": 1, "shards": [{}], "data_version": "abc"})
    val = _write(root / "validate" / "metrics.json", {
        "n_cases": 3, "metrics": {"mae_vec": 0.3, "rmse_vec": 0.4, "accuracy_pct": 81.0}, "run_id": "runval",
        "model_run_id": "runIVpca_sv", "figures": [],
        "error_by_force_magnitude": [{"force_lo_n": 0.0, "force_hi_n": 2.0, "n": 3, "mae_vec_n": 0.3}],
        "error_vs_distance": {"distance_mm": [1.0, 5.0, 9.0], "error_n": [0.1, 0.3, 0.5]},
        "corr_error_distance": 1.0,
        "predictions": {"case_id": ["a", "b", "c"], "true_n": [[1, 0, 0], [0, 2, 0], [0, 0, 3]],
                        "pred_n": [[1.1, 0, 0], [0, 2.2, 0], [0, 0, 2.6]]}})
    enc = _write(root / "studies" / "encoder.json", {
        "study": "encoder", "title": "encoders", "x_label": "encoder", "epochs": 7, "experiment_name": "e-studies",
        "points": [{"study": "encoder", "scenario": "II", "label": e, "value": e, "series": "II", "status": "ok",
                    "encoder": e, "state_vector": True, "metrics": {"accuracy_pct": a, "mae_vec": m, "rmse_vec": m},
                    "roi_nodes_mean": 100.0, "seconds": 1.0, "run_id": f"study{e}"}
                   for e, a, m in (("pca", 91.0, 0.21), ("ae", 90.0, 0.22), ("dae", 89.5, 0.23))]
        + [{"study": "encoder", "scenario": "IV", "label": "dae", "value": "dae", "series": "IV", "status": "failed",
            "reason": "ValueError: too few", "encoder": "dae", "state_vector": True, "metrics": {}, "run_id": "f1"}]})
    data = collect(metrics, [manifest], val, [], [enc])
    html = write_report(data, [], "x", root / "report" / "index.html",
                        solver_stats={"overall": {"cases simulated": 10}, "per_scenario": {
                            "IV": {"solve_time_total_s": 12.5, "solve_time_median_s": 1.1}},
                            "reasons": {"NewtonDiverged": 1}},
                        setup={"main_variant": "pca_sv", "material": {"model": "yeoh", "params_mpa": {"C10": 0.0016},
                                                                      "nu": 0.49, "vary_rel": 0.3}}).read_text()
    # Table 5.9 layout: scenario rows; ours without / study without / ours with / study with, with run ids
    t59 = html[html.index("class='t59'"):]
    t59 = t59[:t59.index("</table>")]
    rows = re.findall(r"<tr><td>(I|II|III|IV)</td>(.*?)</tr>", t59)
    assert [r[0] for r in rows] == ["I", "II", "III", "IV"]
    for sc, row in rows:
        cells = re.findall(r"<td>(.*?)</td>", row)
        assert cells[1].startswith("92.0 %" if sc == "I" else "") and f"run{sc}pca_nosv" in cells[1]
        assert f"{STUDY_ACCURACY[sc]['without']:.1f} %" == cells[2]
        assert f"run{sc}pca_sv" in cells[3] and f"{STUDY_ACCURACY[sc]['with']:.1f} %" == cells[4]
    # encoders table and the study rows cite their runs; a failed point says why
    assert "PCA vs autoencoder" in html and "studydae" in html
    pts = re.findall(r"<tr class='study-point'><td>(\w+)</td><td>(\w+)</td><td>(\w+)</td><td>([\d.–]+)</td>"
                     r"<td>([\d.–]+)</td>.*?<code>(\w+)</code>", html)
    assert [(p[1], p[2], p[3], p[5]) for p in pts] == [
        ("II", "pca", "91.0", "studypca"), ("II", "ae", "90.0", "studyae"), ("II", "dae", "89.5", "studydae"),
        ("IV", "dae", "–", "f1")]
    assert "failed: ValueError: too few" in html
    # validation figures made by the report, solver statistics, failure reasons
    figs = root / "report" / "figures"
    assert (figs / "validation_error_vs_force.png").stat().st_size > 3000
    assert (figs / "validation_error_vs_distance.png").stat().st_size > 3000
    assert "validation_error_vs_distance.png" in html and "12.5" in html and "NewtonDiverged" in html
    assert "C10 = 0.0016" in html
    # the sections the smoke test slices on come in this order
    assert html.index("Accuracy per scenario") < html.index("Unseen liver") < html.index("id='studies'")
