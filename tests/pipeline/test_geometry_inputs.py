"""An imported liver's own files are inputs of the rules that read them.

The geometry rule reads the liver file, the mesh rule reads it again and the
point files of the supports and exertion points (``Plan.geometry_files``).
Declared as Snakemake inputs, editing one re-runs that stage and everything
after it, and a missing one stops Snakemake before any job runs, naming it.
"""
from __future__ import annotations

import os
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from liverforce.config import compose
from liverforce.pipeline.plan import Plan

ROOT = Path(__file__).resolve().parents[2]
SNAKEMAKE = str(Path(sys.executable).with_name("snakemake"))


def _imported(path, points, ribs, cava=(0, 0, 0)) -> str:
    """``geometry.imported`` of one liver with a sphere, a file support and a points file (Hydra syntax)."""
    return (f"geometry.imported=[{{name:lab,path:{path},units:mm,supports:{{mode:add,list:["
            f"{{name:cava,kind:fixed,sphere:{{center_mm:[{','.join(f'{c:.2f}' for c in cava)}],radius_mm:20}}}},"
            f"{{name:ribs,kind:sliding,file:{{path:{ribs},units:mm}}}}]}},"
            f"exertion_points:{{path:{points}}}}}]")


def _plan(imported: str) -> Plan:
    # one liver: scenario IV (split by liver) left out, as liverforce.config asks of a one-liver run
    return Plan(compose(["experiment=smoke", "geometry.procedural.count=0", imported, "train.scenarios=[II]",
                         "study.enabled=false", "~sweep.scenarios.IV"]))


def test_an_imported_liver_lists_its_file_its_support_file_and_its_points_file(tmp_path):
    plan = _plan(_imported(tmp_path / "liver.stl", tmp_path / "pts.csv", tmp_path / "ribs.csv"))
    liver, ribs, pts = (str(tmp_path / n) for n in ("liver.stl", "ribs.csv", "pts.csv"))
    assert plan.geometry_files("imp-lab") == [liver, ribs, pts]
    assert plan.geometry_files("imp-lab", stage="mesh") == [liver, ribs, pts]
    assert plan.geometry_files("imp-lab", stage="geometry") == [liver]
    with pytest.raises(ValueError, match="stage"):
        plan.geometry_files("imp-lab", stage="sweep")


def test_a_markups_file_and_a_file_named_twice_are_listed_once(tmp_path):
    imported = (f"geometry.imported=[{{name:lab,path:{tmp_path}/liver.vtu,supports:{{mode:replace,list:["
                f"{{name:a,kind:fixed,file:{{path:{tmp_path}/ribs.csv}}}},"
                f"{{name:b,kind:sliding,file:{{path:{tmp_path}/ribs.csv}}}},"
                f"{{name:c,kind:sliding,group:7}}]}},exertion_points:{{path:{tmp_path}/tool.mrk.json}}}}]")
    plan = _plan(imported)
    assert plan.geometry_files("imp-lab") == [str(tmp_path / n) for n in ("liver.vtu", "ribs.csv", "tool.mrk.json")]


def test_relative_paths_are_taken_from_the_working_directory(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    plan = _plan(_imported("data/liver.stl", "pts.csv", "/abs/ribs.csv"))
    assert plan.geometry_files("imp-lab") == [str(tmp_path / "data/liver.stl"), "/abs/ribs.csv",
                                              str(tmp_path / "pts.csv")]
    assert all(os.path.isabs(p) for p in plan.geometry_files("imp-lab"))


def test_coordinates_and_vertex_ids_and_procedural_livers_name_no_file(tmp_path):
    plan = Plan(compose(["experiment=smoke", "geometry.cube.enabled=true",
                         f"geometry.imported=[{{name:lab,path:{tmp_path}/liver.stl,"
                         "exertion_points:{vertex_ids:[1,2]}}]"]))
    assert plan.geometry_files("imp-lab") == [str(tmp_path / "liver.stl")]
    for gid in ("proc-0000", "cube", plan.validation_geometries[0]):
        assert plan.geometry_files(gid) == []
        assert plan.geometry_files(gid, stage="geometry") == []


# ------------------------------------------------------------ through snakemake

MESH = "results/smoke/mesh/imp-lab.vtu"
SHARDS = "results/smoke/shards/II/manifest.json"


def _snakemake(work: Path, imported: str, *args, check=True) -> subprocess.CompletedProcess:
    cmd = [SNAKEMAKE, "--snakefile", str(ROOT / "Snakefile"), "--directory", str(work), "--cores", "1", *args,
           "--config", "experiment=smoke",
           f"overrides=geometry.procedural.count=0 {imported} train.scenarios=[II] study.enabled=false "
           "~sweep.scenarios.IV"]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"})
    if check and proc.returncode != 0:
        raise AssertionError(f"{' '.join(cmd)} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return proc


def _scheduled(proc: subprocess.CompletedProcess) -> set[str]:
    """Rules of the jobs a dry run would run (its job stats, up to the total)."""
    text = proc.stdout + proc.stderr
    if "Nothing to be done" in text:
        return set()
    rules = set()
    for line in text[text.index("Job stats:"):].splitlines()[3:]:
        name = line.split()[0]
        if name == "total":
            return rules
        rules.add(name)
    raise AssertionError(f"no job stats in:\n{text[-3000:]}")


@contextmanager
def _edited(path: Path):
    """An edit in place: a line added and the file's time past every output's; put back afterwards.

    Snakemake compares a changed input of up to 1 MB by checksum too: a touch alone does not re-run it."""
    st, data = path.stat(), path.read_bytes()
    path.write_bytes(data + b"\n# edited\n")
    t = time.time() + 5
    os.utime(path, (t, t))
    try:
        yield path
    finally:
        path.write_bytes(data)
        os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """A liver STL with a support file and an exertion points CSV, meshed through snakemake."""
    import trimesh

    from liverforce.geometry.procedural import LiverShapeParams, procedural_liver

    tmp = tmp_path_factory.mktemp("byo_inputs")
    surface = procedural_liver(3, LiverShapeParams(voxel_mm=6.0))  # coarse: 3.5k vertices
    surface.to_trimesh().export(tmp / "liver.stl")
    v = surface.vertices
    np.savetxt(tmp / "pts.csv", v[np.argsort(v[:, 2])[-2:]], delimiter=",")  # on top: visible
    dense, _ = trimesh.sample.sample_surface_even(surface.to_trimesh(), 20_000, seed=0)  # ~2 mm apart
    np.savetxt(tmp / "ribs.csv", dense[dense[:, 0] < v[:, 0].min() + 20.0], delimiter=",")  # the right tip
    work = tmp / "work"
    work.mkdir()
    imported = _imported(tmp / "liver.stl", tmp / "pts.csv", tmp / "ribs.csv", cava=v[np.argmin(v[:, 1])])
    _snakemake(work, imported, MESH)
    return {"tmp": tmp, "work": work, "imported": imported}


@pytest.mark.slow  # one of the default set's slowest (CI's --durations): run with -m slow
def test_editing_the_liver_file_reruns_its_geometry_and_everything_after(built):
    work, imported = built["work"], built["imported"]
    assert _scheduled(_snakemake(work, imported, "-n", MESH)) == set()  # geometry and mesh complete
    with _edited(built["tmp"] / "liver.stl") as liver:
        proc = _snakemake(work, imported, "-n", SHARDS)
    assert {"geometry", "mesh", "sweep", "simulate", "manifest"} <= _scheduled(proc)
    assert f"Updated input files: {liver}" in proc.stdout


def test_editing_a_points_file_reruns_the_mesh_not_the_geometry(built):
    with _edited(built["tmp"] / "pts.csv") as points:
        proc = _snakemake(built["work"], built["imported"], "-n", MESH)
    assert _scheduled(proc) == {"mesh"}
    assert f"Updated input files: {points}" in proc.stdout


def test_missing_files_stop_snakemake_before_any_job_naming_them(built, tmp_path):
    tmp = built["tmp"]
    imported = _imported(tmp / "gone.stl", tmp / "gone.csv", tmp / "ribs.csv")
    proc = _snakemake(tmp_path, imported, MESH, check=False)
    text = proc.stdout + proc.stderr
    assert proc.returncode != 0 and "MissingInputException" in text
    assert str(tmp / "gone.stl") in text and str(tmp / "gone.csv") in text
    assert not (tmp_path / "results").exists()  # no job started: not even the geometry's
