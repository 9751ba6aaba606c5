"""The test set's own workers (pytest-xdist, set up in tests/conftest.py): how many, how tests are dealt out."""
from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
from conftest_tree import conftest_tree

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent


@pytest.fixture(scope="module")
def root_conftest():
    """tests/conftest.py as a module of its own (``import conftest`` may give another folder's)."""
    spec = importlib.util.spec_from_file_location("_root_conftest_under_test", HERE / "conftest.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _config(numprocesses=None, dist="no", args=("tests",), tx=(), xdist=True, worker=False):
    cfg = SimpleNamespace(option=SimpleNamespace(numprocesses=numprocesses, dist=dist, tx=list(tx)),
                          pluginmanager=SimpleNamespace(hasplugin=lambda name: xdist and name == "xdist"),
                          args=list(args), invocation_params=SimpleNamespace(dir=ROOT))
    if worker:
        cfg.workerinput = {"workerid": "gw0"}
    return cfg


def _cmdline_main(conftest, cfg):
    """Run the conftest's ``pytest_cmdline_main`` wrapper around a main that does nothing; ``cfg.option``."""
    gen = conftest.pytest_cmdline_main(cfg)
    next(gen)
    with pytest.raises(StopIteration):
        gen.send(0)
    return cfg.option


@pytest.mark.parametrize("cpus,physical,expect", [
    (2, 2, 2),  # this 2-core host: both cores
    (64, 32, 4),  # a big machine: 4, not 32 workers fitting models and running Snakemake at once
    (64, 3, 3),  # physical cores, not hyper-threads
    (2, 32, 2),  # a container given 2 CPUs of a big host: the CPUs it may use
    (1, 1, 0),  # one core: no worker process at all
])
def test_auto_takes_the_physical_cores_it_may_use_at_most_four(root_conftest, monkeypatch, cpus, physical, expect):
    monkeypatch.delenv("PYTEST_XDIST_AUTO_NUM_WORKERS", raising=False)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(cpus)))
    fake_psutil = SimpleNamespace(cpu_count=lambda logical=True: cpus if logical else physical)
    monkeypatch.setitem(sys.modules, "psutil", fake_psutil)
    assert root_conftest.pytest_xdist_auto_num_workers(_config(numprocesses="auto")) == expect
    monkeypatch.setitem(sys.modules, "psutil", None)  # no psutil: the CPUs it may use, at most four
    assert root_conftest.pytest_xdist_auto_num_workers(_config(numprocesses="auto")) == (min(cpus, 4) if cpus > 1
                                                                                          else 0)


def test_auto_leaves_the_environment_variable_and_logical_to_xdist(root_conftest, monkeypatch):
    monkeypatch.setenv("PYTEST_XDIST_AUTO_NUM_WORKERS", "3")
    assert root_conftest.pytest_xdist_auto_num_workers(_config(numprocesses="auto")) is None
    monkeypatch.delenv("PYTEST_XDIST_AUTO_NUM_WORKERS")
    assert root_conftest.pytest_xdist_auto_num_workers(_config(numprocesses="logical")) is None


@pytest.mark.parametrize("kwargs,expect", [
    ({}, ("auto", "loadfile")),  # plain `pytest` (testpaths): the test set on the workers, a file per worker
    ({"args": ["tests/fem", "tests/mesh"]}, ("auto", "loadfile")),
    ({"dist": "load"}, ("auto", "load")),  # a --dist of one's own is kept
    ({"numprocesses": 0}, (0, "no")),  # -n 0: one process
    ({"numprocesses": 3}, (3, "loadfile")),  # -n 3: a file per worker too (xdist alone would deal out tests)
    ({"numprocesses": 3, "dist": "load"}, (3, "load")),  # ... unless --dist says otherwise
    ({"args": ["tests/test_atomic.py"]}, (None, "no")),  # one file: one worker would run it all anyway
    ({"args": ["tests/test_atomic.py::test_a", "tests/test_atomic.py::test_b"]}, (None, "no")),
    ({"tx": ["popen"]}, (None, "no")),  # --tx: the user's own gateways
    ({"xdist": False}, (None, "no")),  # -p no:xdist
    ({"worker": True}, (None, "no")),  # an xdist worker starts no workers of its own
])
def test_a_plain_run_goes_to_the_workers_unless_the_command_line_says_otherwise(root_conftest, kwargs, expect):
    opt = _cmdline_main(root_conftest, _config(**kwargs))
    assert (opt.numprocesses, opt.dist) == expect


_PROBE = '''import os


def test_{name}():
    assert os.environ.get("PYTEST_XDIST_WORKER", "main") {op} "main"
'''


def test_plain_pytest_runs_on_workers_and_p_no_xdist_in_one_process(tmp_path):
    """A copy of the test set's conftests and two probe files: plain ``pytest`` deals the files out to 2 workers
    (the count from ``$PYTEST_XDIST_AUTO_NUM_WORKERS``, as on a 2-core host); ``-p no:xdist`` runs them here."""
    env = conftest_tree(tmp_path, "[pytest]\ntestpaths = tests\naddopts = -p no:cacheprovider\n")

    def run(op, *args):
        for name in ("one", "two"):
            (tmp_path / "tests" / f"test_{name}.py").write_text(_PROBE.format(name=name, op=op))
        proc = subprocess.run([sys.executable, "-m", "pytest", "-v", *args], cwd=tmp_path, capture_output=True,
                              text=True, timeout=300, env={**env, "PYTEST_XDIST_AUTO_NUM_WORKERS": "2"})
        out = proc.stdout + proc.stderr
        assert proc.returncode == 0, out[-3000:]
        return out

    out = run("!=")
    assert "created: 2/2 workers" in out and "scheduling tests via LoadFileScheduling" in out, out[-3000:]
    assert "2 passed" in out
    for args in (["-p", "no:xdist"], ["-n", "0"]):
        out = run("==", *args)
        assert "workers" not in out and "2 passed" in out, out[-3000:]
