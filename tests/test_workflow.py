"""The Snakemake workflow: lint, dry runs of every experiment, overrides reach the jobs."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
SNAKEMAKE = str(Path(sys.executable).with_name("snakemake"))


def snakemake(*args, cwd=None, check=True, timeout=600) -> subprocess.CompletedProcess:
    cmd = [SNAKEMAKE, "--snakefile", str(ROOT / "Snakefile"), *args]
    proc = subprocess.run(cmd, cwd=cwd or ROOT, capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, "PYTHONUNBUFFERED": "1"})
    if check and proc.returncode != 0:
        raise AssertionError(f"{' '.join(cmd)} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return proc


def job_counts(text: str) -> dict[str, int]:
    block = text[text.index("Job stats:"):]
    return {m.group(1): int(m.group(2)) for m in re.finditer(r"^(\w+)\s+(\d+)$", block, re.M) if m.group(1) != "total"}


def test_lint_is_clean(tmp_path):
    proc = snakemake("--lint", "--directory", str(tmp_path), check=False)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out
    assert "Lints for" not in out
    # its log in the test's folder, not in the repository's .snakemake (no test writes into the repository)
    assert list((tmp_path / ".snakemake" / "log").glob("*.snakemake.log")), out


@pytest.mark.slow  # one of the default set's slowest (CI's --durations): run with -m slow
@pytest.mark.parametrize("experiment", ["smoke", "default", "thesis"])
def test_dry_run_lists_the_whole_dag(experiment, tmp_path):
    out = snakemake("-n", "--directory", str(tmp_path), "--config", f"experiment={experiment}").stdout
    counts = job_counts(out)
    for rule in ("geometry", "mesh", "sweep", "simulate", "manifest", "train", "validate", "report", "all"):
        assert counts.get(rule, 0) >= 1, (rule, counts)
    from liverforce.config import compose
    from liverforce.pipeline.plan import Plan

    plan = Plan(compose([f"experiment={experiment}"]))
    assert counts["geometry"] == len(plan.all_geometries)
    assert counts["sweep"] == 5  # I-IV + validation
    assert counts["simulate"] == sum(len(plan.shard_ids(s)) for s in plan.all_scenarios())
    assert counts["train"] == len(plan.train_scenarios()) * len(plan.variants())


@pytest.mark.slow  # one of the default set's slowest (CI's --durations): run with -m slow
def test_a_run_without_scenario_iv_gets_its_models_and_a_named_refusal_for_the_report(tmp_path):
    """A lab's one-liver run (docs/own-liver.md: train.scenarios=[II] ~sweep.scenarios.IV): the models target plans its
    training; the default target (the report, which needs the unseen-liver validation of a scenario-IV model) is
    refused naming why and the fix, not with Snakemake's list of missing models/IV files."""
    one = ["--config", "experiment=smoke", "overrides=train.scenarios=[II] ~sweep.scenarios.IV study.enabled=false"]
    counts = job_counts(snakemake("-n", "--directory", str(tmp_path), "models", *one).stdout)
    assert counts["models"] == 1 and counts["train"] >= 1 and "validate" not in counts
    proc = snakemake("-n", "--directory", str(tmp_path), *one, check=False)
    out = proc.stdout + proc.stderr
    assert proc.returncode != 0 and "MissingInputException" not in out, out[-2000:]
    assert "needs scenario IV's models" in out and "trains scenarios II only" in out
    assert "snakemake --cores 2 models" in out


@pytest.mark.slow  # one of the default set's slowest (CI's --durations): run with -m slow
def test_overrides_reach_the_jobs(tmp_path):
    from liverforce.config import compose

    count = compose(["experiment=smoke"])["geometry"]["procedural"]["count"]
    base = job_counts(snakemake("-n", "--directory", str(tmp_path), "--config", "experiment=smoke").stdout)
    more = job_counts(snakemake("-n", "--directory", str(tmp_path), "--config", "experiment=smoke",
                                f"overrides=geometry.procedural.count={count + 1} sweep.cases_per_shard=3").stdout)
    assert more["geometry"] == base["geometry"] + 1
    assert more["simulate"] > base["simulate"]


def test_bad_override_stops_before_any_job(tmp_path):
    proc = snakemake("-n", "--directory", str(tmp_path), "--config", "experiment=smoke",
                     "overrides=dataset.roi_fraction=0", check=False)
    assert proc.returncode != 0
    assert "dataset.roi_fraction" in proc.stdout + proc.stderr
    assert not (tmp_path / "results").exists()


@pytest.mark.slow  # meshes a real liver through snakemake (~18 s); tests/test_byo_as_given.py covers the import
def test_imported_liver_runs_through_geometry_and_mesh_rules(tmp_path, shared_livers):
    src = shared_livers / "liver-smooth.obj"
    override = f"overrides=geometry.imported=[{{name:sofa,path:{src},units:'40'}}]"
    snakemake("--cores", "1", "--directory", str(tmp_path), "--config", "experiment=smoke", override,
              "--", "results/smoke/mesh/imp-sofa.vtu")
    from liverforce.mesh.io import read_mesh

    mesh = read_mesh(tmp_path / "results/smoke/mesh/imp-sofa.vtu")
    assert 250 < len(mesh.points) < 600  # smoke target 400 vertices
    assert set(mesh.facet_region.tolist()) >= {1, 2, 3, 4}
    log = (tmp_path / "results/smoke/logs/geometry/imp-sofa.log").read_text()
    assert "self-intersections removed" in log  # the repair is reported to the user


@pytest.mark.slow  # voxelises a liver and meshes it through snakemake (~25 s)
def test_a_slicer_segmentation_in_lps_runs_through_geometry_and_mesh_by_segment_name(tmp_path):
    """A lab's 3D Slicer export: a .seg.nrrd in LPS with three segments; ``label: liver`` picks the liver and
    ``group: ivc`` fixes the liver where it touches the cava segment (its only support: ``mode: replace``)."""
    import slicerio
    import trimesh
    from scipy.ndimage import binary_dilation
    from scipy.spatial import cKDTree

    from liverforce.geometry.procedural import LiverShapeParams, procedural_liver
    from liverforce.mesh.io import read_mesh
    from liverforce.mesh.types import REGION_CODES

    liver = procedural_liver(7, LiverShapeParams())  # RAS mm
    vox = liver.to_trimesh().voxelized(2.0).fill()
    ijk_to_ras = np.asarray(vox.transform)
    shape = vox.matrix.shape
    ras = np.indices(shape).transpose(1, 2, 3, 0) @ ijk_to_ras[:3, :3].T + ijk_to_ras[:3, 3]
    centre = liver.vertices.mean(axis=0)
    # a cava: the voxels just outside the liver in a posterior band round the centre's x and z
    ivc = (binary_dilation(vox.matrix, iterations=2) & ~vox.matrix & (ras[..., 1] < centre[1] - 20.0)
           & (np.abs(ras[..., 0] - centre[0]) < 15.0) & (np.abs(ras[..., 2] - centre[2]) < 25.0))
    spleen = np.zeros(shape, bool)
    spleen[:6, :6, :6] = True  # a corner the liver does not reach
    assert ivc.sum() > 50 and not (spleen & vox.matrix).any()
    seg = slicerio.create_segmentation(shape, np.diag([-1.0, -1.0, 1.0, 1.0]) @ ijk_to_ras)  # Slicer writes LPS
    for k, (name, mask) in enumerate([("spleen", spleen), ("liver", vox.matrix), ("ivc", ivc)], start=1):
        slicerio.add_segment(seg, mask, {"id": f"Segment_{k}", "name": name})
    src = tmp_path / "Segmentation.seg.nrrd"
    slicerio.write_segmentation(str(src), seg)
    override = (f"overrides=geometry.imported=[{{name:seg,path:{src},label:liver,supports:{{mode:replace,"
                f"list:[{{name:cava,kind:fixed,group:ivc}}]}}}}]")
    snakemake("--cores", "1", "--directory", str(tmp_path), "--config", "experiment=smoke", override,
              "--", "results/smoke/mesh/imp-seg.vtu")
    record = json.loads((tmp_path / "results/smoke/geometry/imp-seg.json").read_text())
    assert record["label"] == 2 and record["segment"] == "Segment_2" and record["spec"]["label"] == "liver"
    assert any("segment 'liver' (ID Segment_2, label 2) used (label='liver')" in m for m in record["repairs"])
    mesh = read_mesh(tmp_path / "results/smoke/mesh/imp-seg.vtu")
    pts = np.asarray(mesh.points)[np.unique(mesh.facets)]  # the boundary's nodes
    dense, _ = trimesh.sample.sample_surface(liver.to_trimesh(), 200_000, seed=0)  # ~0.5 mm apart
    dist, _ = cKDTree(dense).query(pts)
    # in RAS, where the procedural liver is: within a voxel or two (a mirrored or LPS-read liver is cm off)
    assert np.median(dist) < 2.0 and dist.max() < 8.0
    features = json.loads((tmp_path / "results/smoke/mesh/imp-seg.features.json").read_text())
    (cava,) = [s for s in features["supports"] if s["name"] == "cava"]
    assert cava["segment"] == "segment 'ivc' (ID Segment_3, label 3)" and cava["n_facets"] > 0
    fixed = np.asarray(mesh.points)[mesh.facets[mesh.facet_region == REGION_CODES["ivc"]]].mean(axis=1)
    d_ivc, _ = cKDTree(ras[ivc]).query(fixed)
    # the only fixed facets (mode: replace) are the contact, to within the smoke mesh's facet size (~14 mm)
    assert len(fixed) > 10 and np.median(d_ivc) < 3.0 and d_ivc.max() < 15.0


def test_broken_import_stops_with_the_file_named(tmp_path, shared_livers):
    src = shared_livers / "liver_for_test_broken.vtk"
    override = f"overrides=geometry.imported=[{{name:broken,path:{src},units:mm}}]"
    proc = snakemake("--cores", "1", "--directory", str(tmp_path), "--config", "experiment=smoke", override,
                     "--", "results/smoke/geometry/imp-broken.ply", check=False)
    assert proc.returncode != 0
    log = (tmp_path / "results/smoke/logs/geometry/imp-broken.log")
    text = log.read_text()  # the job's own log says why it failed
    assert "liver_for_test_broken.vtk" in text and "GeometryError" in text
    assert not (tmp_path / "results/smoke/geometry/imp-broken.ply").exists()


def test_ci_runs_exactly_the_readme_test_command():
    readme = (ROOT / "README.md").read_text()
    block = readme[readme.index("## The two commands"):]
    commands = [ln.strip() for ln in block.split("```bash", 1)[1].split("```", 1)[0].splitlines()
                if ln.strip() and not ln.strip().startswith("#")]
    assert len(commands) == 2
    assert commands[0].endswith("snakemake --cores 2")
    ci = [ln.strip() for ln in (ROOT / ".ci" / "run").read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    assert commands[1] in ci
