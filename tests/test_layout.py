"""One owner of names and paths: liverforce.layout (through Plan.paths / Plan.experiment_name)."""
from __future__ import annotations

import ast
import re
import time
from pathlib import Path

import pytest

from liverforce import layout
from liverforce.config import compose
from liverforce.pipeline.plan import Plan

ROOT = Path(__file__).resolve().parent.parent
PKG = ROOT / "liverforce"


def test_paths_are_the_layout_users_see():
    """The names on disk, spelled out: a change here renames users' files (do it on purpose only)."""
    p = layout.Layout("results/x")
    assert p.surface("proc-0000") == "results/x/geometry/proc-0000.ply"
    assert p.surface_meta("proc-0000") == "results/x/geometry/proc-0000.json"
    assert p.mesh("val-1000") == "results/x/mesh/val-1000.vtu"
    assert p.features("val-1000") == "results/x/mesh/val-1000.features.json"
    assert p.regions_picture("cube") == "results/x/mesh/cube.regions.png"
    assert p.cases("II") == "results/x/sweep/II/cases.parquet"
    assert p.sweep_report("II") == "results/x/sweep/II/sweep.json"
    assert p.shard("IV", 3) == p.shard("IV", "0003") == "results/x/shards/IV/shard-0003.parquet"
    assert p.manifest("V") == "results/x/shards/V/manifest.json"
    assert p.progress("IV", 12) == "results/x/progress/IV-0012.json"
    assert p.model_metrics("I", "pca_sv") == "results/x/models/I/pca_sv/metrics.json"
    assert p.model_dir("I", "pca_sv") == "results/x/models/I/pca_sv/model"
    assert p.validation_metrics() == "results/x/validate/metrics.json"
    assert p.study("encoder") == "results/x/studies/encoder.json"
    assert p.study_picture("encoder") == "results/x/studies/encoder.png"
    assert p.report() == "results/x/report/index.html"
    assert p.case_picture("II-000012") == "results/x/cases/II-000012.png"
    assert p.log("simulate", "{scenario}-{shard}") == "results/x/logs/simulate/{scenario}-{shard}.log"
    # the defaults are the Snakemake wildcards
    assert p.mesh() == "results/x/mesh/{gid}.vtu" and p.shard() == "results/x/shards/{scenario}/shard-{shard}.parquet"
    assert p.model_metrics() == "results/x/models/{scenario}/{variant}/metrics.json"


def test_names_read_back_from_paths():
    p = layout.Layout("/abs/results/x")
    for gid in ("proc-0000", "imp-my_liver", "cube"):
        for path in (p.surface(gid), p.surface_meta(gid), p.mesh(gid), p.features(gid), p.regions_picture(gid)):
            assert layout.gid_of(path) == gid
    assert str(layout.features_of_mesh(p.mesh("proc-0001"))) == p.features("proc-0001")
    assert str(layout.surface_meta_of(p.surface("proc-0001"))) == p.surface_meta("proc-0001")
    assert layout.scenario_of_manifest(p.manifest("III")) == "III"
    assert str(layout.root_of_manifest(p.manifest("III"))) == "/abs/results/x"
    assert str(layout.root_of_manifest(p.shard("III", 2))) == "/abs/results/x"
    with pytest.raises(ValueError, match="not in a results layout's shards/<scenario>/ folder"):
        layout.root_of_manifest("/abs/elsewhere/manifest.json")
    assert layout.model_of_metrics(p.model_metrics("IV", "ae_sv")) == ("IV", "ae_sv")
    assert str(layout.progress_of_shard(p.shard("II", 7))) == p.progress("II", 7)
    assert str(layout.study_picture_of(p.study("noise"))) == p.study_picture("noise")
    assert layout.case_id("II", 12) == "II-000012" and layout.scenario_of_case("II-000012") == "II"
    with pytest.raises(ValueError):
        layout.gid_of("results/x/mesh/notes.txt")


def test_the_simulate_stage_writes_progress_where_the_display_reads_it():
    """pipeline.simulate derives the progress path from the shard path: it must be the layout's."""
    import liverforce.pipeline.simulate as sim

    p = layout.Layout("results/x")
    if hasattr(sim, "_progress_path"):  # its own derivation (until it calls layout.progress_of_shard)
        assert Path(sim._progress_path(p.shard("IV", 5))) == Path(p.progress("IV", 5))
    else:
        assert "progress_of_shard" in Path(sim.__file__).read_text()


def test_plan_names_the_runs_paths_and_experiments(tmp_path):
    plan = Plan(compose(["experiment=smoke", f"results_dir={tmp_path}"]))
    assert plan.paths.root == plan.root == str(tmp_path / "smoke")
    assert plan.experiment_name("IV") == "liverforce-smoke-IV"
    assert plan.experiment_name("validation") == "liverforce-smoke-validation"
    assert plan.experiment_name("studies") == "liverforce-smoke-studies"
    other = Plan(compose(["experiment=smoke", "tracking.experiment_prefix=lab"]))
    assert other.experiment_name("I") == "lab-smoke-I"
    assert plan.shard_ids("I") == ["0000", "0001"]  # 12 cases, 6 per shard


def test_progress_display_reads_the_plans_files(tmp_path):
    from liverforce.atomic import write_json_atomic
    from liverforce.pipeline.progress import sweep_progress

    plan = Plan(compose(["experiment=smoke", f"results_dir={tmp_path}"]))
    now = time.time()
    write_json_atomic(plan.paths.progress("I", 0), {"done": 6, "failed": 1, "elapsed_s": 60.0, "updated": now})
    write_json_atomic(plan.paths.progress("II", 1), {"done": 2, "failed": 0, "elapsed_s": 20.0, "updated": now})
    Path(plan.paths.shard("I", 0)).parent.mkdir(parents=True)
    Path(plan.paths.shard("I", 0)).write_bytes(b"")  # shard I-0000 finished; II-0001 still running
    p = sweep_progress(plan)
    assert (p["done"], p["failed"], p["running_shards"]) == (8, 1, 1)
    assert p["total"] == sum(plan.scenario_spec(s)["n_cases"] for s in plan.all_scenarios())
    assert p["cases_per_hour_per_job"] == pytest.approx(360.0)


def test_cli_show_case_looks_in_the_plans_shards(tmp_path, capsys):
    from liverforce.cli import main

    assert main(["show-case", "II-000003", f"results_dir={tmp_path}", "-e", "smoke"]) == 2
    assert str(tmp_path / "smoke" / "shards" / "II") in capsys.readouterr().err


# --------------------------------------------------------------------------
# nobody else spells a file name of the layout
# --------------------------------------------------------------------------

_FRAGMENTS = (".features.json", ".regions.png", "shard-", "manifest.json", "metrics.json", "/progress/", "/shards/",
              "/models/", "/mesh/", "/geometry/", "/logs/")
_FOLDERS = {"shards", "progress", "models", "mesh", "geometry", "sweep", "studies", "validate", "report", "logs",
            "cases"}


def layout_spellings(path: Path) -> list[str]:
    """Path-like string constants (no spaces: not messages) holding a layout name, and ``x / "shards"`` joins."""
    tree = ast.parse(path.read_text(), filename=str(path))
    docs = {id(n.body[0].value) for n in ast.walk(tree)
            if isinstance(n, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and n.body
            and isinstance(n.body[0], ast.Expr) and isinstance(n.body[0].value, ast.Constant)}
    found = []
    for n in ast.walk(tree):
        if isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in docs \
                and not any(c.isspace() for c in n.value) and any(f in n.value for f in _FRAGMENTS):
            found.append(f"{n.lineno}: {n.value!r}")
        if isinstance(n, ast.BinOp) and isinstance(n.op, ast.Div) \
                and any(isinstance(x, ast.Constant) and x.value in _FOLDERS for x in (n.left, n.right)):
            found.append(f"{n.lineno}: {ast.unparse(n)}")
    return found


def test_the_package_spells_layout_names_only_in_liverforce_layout():
    found = {}
    for path in sorted(PKG.rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        if rel != "liverforce/layout.py" and (hits := layout_spellings(path)):
            found[rel] = hits
    assert not found, f"take paths from liverforce.layout (Plan.paths), do not spell them: {found}"


def test_rules_spell_no_paths_and_no_experiment_names():
    files = [ROOT / "Snakefile", *sorted((ROOT / "workflow" / "rules").glob("*.smk"))]
    for f in files:
        code = "\n".join(line.split("#", 1)[0] for line in f.read_text().splitlines())
        for bad in ('f"{E}', "results/", "experiment_prefix", "-validation", "-studies", "shards/", "mesh/"):
            assert bad not in code, f"{f.name} spells {bad!r}: use P (PLAN.paths) / PLAN.experiment_name"
        named = re.findall(r"[\w}-]+\.(?:vtu|parquet|ply|json|png|html|log)[\"']", code)
        assert not named, f"{f.name} spells file names {named}: use P (PLAN.paths)"
