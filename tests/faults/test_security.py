"""Security: loopback-only servers, no unpickling of untrusted files, names cannot escape results/.

- ``liverforce ui`` (and every MLflow server/UI command the project documents)
  binds to 127.0.0.1 unless the user asks otherwise;
- no code path of the package unpickles: ``pickle``/``joblib``/``read_pickle``
  calls are absent, ``torch.load`` always has ``weights_only=True``,
  ``np.load`` always ``allow_pickle=False``; and a model bundle whose weights
  file is a malicious pickle is refused without running it;
- names that become folders under results/ (imported geometry names, model
  variant names) cannot contain path separators or ``..``.
"""
from __future__ import annotations

import ast
import pickle
import re
import shutil
from pathlib import Path

import pytest

from liverforce.config import ConfigError, compose
from liverforce.pipeline.plan import Plan
from test_workflow import ROOT, snakemake

PACKAGE = ROOT / "liverforce"


# ----------------------------------------------------------------------------- servers bind to loopback


def test_liverforce_ui_binds_to_loopback_by_default(monkeypatch, tmp_path):
    from liverforce import cli

    seen = []
    monkeypatch.setattr(cli.subprocess, "call", lambda cmd, *a, **kw: seen.append(cmd) or 0)
    monkeypatch.chdir(tmp_path)
    assert cli.main(["ui", "-e", "smoke"]) == 0
    cmd = seen[0]
    assert cmd[cmd.index("--host") + 1] == "127.0.0.1"
    assert cmd[1] == "ui"


def test_documented_server_commands_bind_to_loopback():
    texts = {p: p.read_text() for p in [ROOT / "README.md", *(ROOT / "docs").glob("*.md"), *PACKAGE.rglob("*.py"),
                                        *(ROOT / "workflow").rglob("*"), *(ROOT / "scripts").rglob("*")]
             if p.is_file() and p.suffix != ".pyc"}
    commands = 0
    for path, text in texts.items():
        assert "0.0.0.0" not in text, f"{path} binds to every interface"
        for m in re.finditer(r"mlflow (?:ui|server|models serve)[^\n`]*", text):
            commands += 1
            window = text[m.start():m.end() + 200]  # the command may go on over a line break
            assert "--host 127.0.0.1" in window or "--host\", args.host" in window, (path, m.group(0))
    assert commands >= 2  # the README's ui and models serve lines at least


# ----------------------------------------------------------------------------- nothing unpickles


def _calls(tree: ast.AST):
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", "")
            owner = f.value.id if isinstance(f, ast.Attribute) and isinstance(f.value, ast.Name) else ""
            yield owner, name, {k.arg: k.value for k in node.keywords}


def test_no_code_path_unpickles():
    problems = []
    for path in PACKAGE.rglob("*.py"):
        tree = ast.parse(path.read_text())
        for owner, name, kw in _calls(tree):
            where = f"{path.relative_to(ROOT)}: {owner}.{name}"
            if owner in ("pickle", "cloudpickle", "dill", "joblib") and name in ("load", "loads"):
                problems.append(where)
            if name in ("read_pickle", "load_pickle"):
                problems.append(where)
            if owner == "torch" and name == "load":
                wo = kw.get("weights_only")
                if not (isinstance(wo, ast.Constant) and wo.value is True):
                    problems.append(where + " without weights_only=True")
            if owner == "np" and name == "load":
                ap = kw.get("allow_pickle")
                if not (isinstance(ap, ast.Constant) and ap.value is False):
                    problems.append(where + " without allow_pickle=False")
    assert not problems, problems


class _Payload:
    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):  # runs at unpickling time
        return (Path.touch, (self.marker,))


def test_a_malicious_weights_file_is_refused_without_running_it(tmp_path):
    from liverforce.learn.model import ForceModel
    from liverforce.learn.synthetic import synthetic_arrays
    from liverforce.learn.train import train_scenario

    model = {"encoder": "pca", "code_size": 3, "state_vector": False, "grid_size": 6, "hidden": [8], "dropout": 0.0,
             "occlusion": {"radius_mm": 0.0, "mode": "remove"}, "noise_mm": 0.0}
    train = {"test_fraction": 0.25, "epochs": 2, "batch_size": 16, "lr": 3e-3, "weight_decay": 0.0, "seed": 0}
    tune = {"enabled": False, "trials": 1, "folds": 2, "sobol_trials": 1, "epochs": 1}
    res = train_scenario(synthetic_arrays(24, seed=1, nodes=(80, 100)), model, train, tune, "II", "pca",
                         out_dir=tmp_path / "out")
    bundle = Path(res["model_path"])
    ForceModel.load(bundle)  # the honest bundle loads
    evil = tmp_path / "evil-bundle"
    shutil.copytree(bundle, evil)
    marker = tmp_path / "pwned"
    import torch

    torch.save({"x": _Payload(marker)}, evil / "regressor.pt")  # a torch file whose pickle runs code
    with open(evil / "extra.pkl", "wb") as fh:
        pickle.dump(_Payload(marker), fh)
    with pytest.raises(Exception):
        ForceModel.load(evil)
    assert not marker.exists(), "loading a model bundle executed code from a pickle"


# ----------------------------------------------------------------------------- names stay inside results/


@pytest.mark.parametrize("bad", ["../../evil", "a/b", "..", "/abs"])
@pytest.mark.parametrize("where", ["geometry", "variant"])
def test_names_that_become_folders_cannot_leave_results(where, bad, tmp_path):
    if where == "geometry":
        override, key = f"geometry.imported=[{{name: '{bad}', path: /tmp/x.stl, units: mm}}]", "geometry.imported[0].name"
    else:
        override, key = f"train.variants=[{{name: '{bad}', encoder: pca}}]", "train.variants"
    with pytest.raises(ConfigError, match=re.escape(key)):
        Plan(compose(["experiment=smoke", override]))


def test_every_planned_output_stays_under_the_results_folder():
    for exp in ("smoke", "default"):
        plan = Plan(compose([f"experiment={exp}"]))
        root = Path(plan.abs_root).resolve()
        names = [*plan.all_geometries, *plan.variants(), *plan.all_scenarios()]
        for n in names:
            assert (root / "x" / n).resolve().parent == (root / "x").resolve(), n


@pytest.mark.workflow
def test_workflow_refuses_an_escaping_variant_name_before_any_job(tmp_path):
    work = tmp_path / "a" / "b"
    work.mkdir(parents=True)
    proc = snakemake("-n", "--directory", str(work), "--config", "experiment=smoke",
                     "overrides=train.variants=[{name: '../../../../evil', encoder: pca}]", check=False)
    text = proc.stdout + proc.stderr
    assert proc.returncode != 0 and "train.variants" in text, text[-2000:]
    assert "Job stats" not in text
    assert not list(tmp_path.rglob("evil*"))
