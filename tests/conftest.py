"""Shared fixtures: paths, the shared data folder, small meshes; the test set's workers (pytest-xdist)."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from faults import conftest as fault_ledger_module
from liverforce.pipeline.job import thread_env

ROOT = Path(__file__).resolve().parent.parent
SHARED_LIVERS = ROOT.parent / "shared" / "data" / "livers"

# one thread per pool in tests (2-core machine); xdist's workers inherit it (the controller sets it before they start)
thread_env(1, override=False)

#: at most this many workers for ``-n auto``: each may fit torch models, run Snakemake or mesh
MAX_AUTO_WORKERS = 4


@pytest.fixture(scope="session")
def shared_livers() -> Path:
    if not SHARED_LIVERS.is_dir():
        pytest.skip(f"real liver meshes not present at {SHARED_LIVERS} (../shared/data/livers is outside the repo)")
    return SHARED_LIVERS


# -------------------------------------------------------------------------- both cores (pytest-xdist)


def _one_file(config) -> bool:
    """Whether the command line names tests of one file only (``loadfile`` would run them on one worker)."""
    files = {a.split("::", 1)[0] for a in config.args}
    return len(files) == 1 and Path(config.invocation_params.dir, *files).is_file()


@pytest.hookimpl(wrapper=True)
def pytest_cmdline_main(config):
    """``pytest`` runs on ``-n auto`` workers with ``--dist loadfile`` (a test file stays on one worker, so its
    module-scoped fixtures are built once); ``-n 0``, ``-n N``, ``--tx`` or ``-p no:xdist`` decide otherwise, and
    the tests of one file run in this process (one worker would run them all anyway). ``-n N`` keeps ``loadfile``
    too unless ``--dist`` says otherwise (xdist alone would take ``load`` and build a file's fixtures per worker).

    Set here, not in ``addopts``: with ``-n`` there, ``-p no:xdist`` (or a venv without pytest-xdist) would stop
    on an unknown option instead of running in one process.
    """
    opt = config.option
    if (config.pluginmanager.hasplugin("xdist") and not hasattr(config, "workerinput")
            and opt.numprocesses is None and not opt.tx and not _one_file(config)):
        opt.numprocesses = "auto"
    if (config.pluginmanager.hasplugin("xdist") and not hasattr(config, "workerinput") and opt.numprocesses
            and opt.dist == "no"):
        opt.dist = "loadfile"
    return (yield)


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_auto_num_workers(config):
    """``-n auto``: the physical cores this process may run on, at most :data:`MAX_AUTO_WORKERS`.

    ``$PYTEST_XDIST_AUTO_NUM_WORKERS`` and ``-n logical`` are left to xdist."""
    if os.environ.get("PYTEST_XDIST_AUTO_NUM_WORKERS") or config.option.numprocesses == "logical":
        return None
    try:
        cores = len(os.sched_getaffinity(0))  # a taskset or a container's cpuset
    except AttributeError:  # pragma: no cover - not Linux
        cores = os.cpu_count() or 1
    try:
        import psutil  # not a dependency of ours; without it, the CPUs above

        cores = min(cores, psutil.cpu_count(logical=False) or cores)
    except ImportError:
        pass
    n = min(cores, MAX_AUTO_WORKERS)
    return n if n > 1 else 0  # one core: no worker process, the tests run in this one


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node, error):
    """The controller: a worker finished (or died); the fault ledger takes its records."""
    fault_ledger_module.gather(node.config, node)


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    fault_ledger_module.terminal_summary(terminalreporter)
