"""The fault ledger itself: a fault counts as survived only when its checks ran and passed."""
from __future__ import annotations

import ast
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from conftest_tree import conftest_tree
from faults.conftest import _RECORDS, FaultLedger

HERE = Path(__file__).parent


def test_no_fault_test_writes_survived_true_by_hand():
    """``record(..., survived=True)`` states a verdict nobody measured; use ``fault_ledger.check`` instead."""
    bad = []
    for path in sorted(HERE.glob("test_*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and getattr(node.func, "attr", None) == "record":
                for kw in node.keywords:
                    if kw.arg == "survived" and isinstance(kw.value, ast.Constant):
                        bad.append(f"{path.name}:{node.lineno} survived={kw.value.value!r}")
    assert not bad, "fault verdicts written by hand:\n" + "\n".join(bad)


def test_check_records_a_failed_check_as_not_survived_and_reraises():
    ledger = FaultLedger("tests/faults/test_ledger.py::probe")
    n = len(_RECORDS)
    with pytest.raises(AssertionError, match="the run lost a shard"):
        with ledger.check("probe: a check that fails", rows_expected=5) as seen:
            seen.rows_found = 3
            assert False, "the run lost a shard"
    rec = _RECORDS[n]
    assert (rec.survived, rec.rows_expected, rec.rows_found, rec.rows_lost) == (False, 5, 3, 2)
    assert "the run lost a shard" in rec.detail["failure"]
    with ledger.check("probe: a check that passes", rows_expected=2) as seen:
        seen.rows_found = 2
    assert _RECORDS[n + 1].survived and _RECORDS[n + 1].rows_lost == 0
    del _RECORDS[n:]  # probes, not injected faults: keep them out of the session's totals


_PROBE_ONE = '''import os


def test_one(fault_ledger):
    with fault_ledger.check("probe one: all rows kept", rows_expected=4,
                            worker=os.environ["PYTEST_XDIST_WORKER"]) as seen:
        seen.rows_found = 4
'''
_PROBE_TWO = '''import os


def test_two(fault_ledger):
    found = 3
    fault_ledger.record("probe two: rows lost", survived=found == 5, rows_expected=5, rows_found=found,
                        worker=os.environ["PYTEST_XDIST_WORKER"])
'''


_PROBE_CRASH = '''import os


def test_crash(fault_ledger):
    with fault_ledger.check("probe crash: recorded, then the worker dies", rows_expected=1) as seen:
        seen.rows_found = 1
    os._exit(3)
'''


def _session(tmp_path: Path, probes: dict[str, str], *args: str) -> tuple[subprocess.CompletedProcess, Path]:
    """A copy of the test set's conftests with ``probes`` (file name -> text) in tests/faults, run on 2 workers;
    ``(the run, its base temporary folder)``; ``$LIVERFORCE_FAULT_REPORT`` is ``tmp_path/report/faults.json``."""
    env = conftest_tree(tmp_path, "[pytest]\ntestpaths = tests\n")
    for name, text in probes.items():
        (tmp_path / "tests" / "faults" / name).write_text(text)
    env["LIVERFORCE_FAULT_REPORT"] = str(tmp_path / "report" / "faults.json")
    (tmp_path / "report").mkdir(exist_ok=True)
    basetemp = tmp_path / "basetemp"
    proc = subprocess.run([sys.executable, "-m", "pytest", "-n", "2", "--dist", "loadfile", "-p", "no:cacheprovider",
                           f"--basetemp={basetemp}", *args], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=300)
    return proc, basetemp


def test_the_controller_gathers_the_records_of_every_xdist_worker(tmp_path):
    """Under ``-n 2`` each worker holds its own records: the controller's totals and ``faults.json`` hold both."""
    proc, basetemp = _session(tmp_path, {"test_one.py": _PROBE_ONE, "test_two.py": _PROBE_TWO})
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-3000:]
    assert "2 workers [2 items]" in out, out[-3000:]
    assert "faults injected: 2, runs survived: 1, rows lost: 2" in out, out[-3000:]
    for report in (basetemp / "faults.json", tmp_path / "report" / "faults.json"):
        ledger = json.loads(report.read_text())
        assert (ledger["faults_injected"], ledger["runs_survived"], ledger["rows_lost"]) == (2, 1, 2), report
        seen = {(r["fault"], r["detail"]["worker"]) for r in ledger["faults"]}
        assert {f for f, _ in seen} == {"probe one: all rows kept", "probe two: rows lost"}, report
        assert {w for _, w in seen} == {"gw0", "gw1"}, report  # one record from each worker


def test_a_crashed_workers_records_are_said_to_be_lost_not_left_out_silently(tmp_path):
    """A worker that dies hands nothing over: the summary names it and where its own ``faults.json`` is."""
    proc, basetemp = _session(tmp_path, {"test_crash.py": _PROBE_CRASH, "test_one.py": _PROBE_ONE},
                              "--max-worker-restart=0")
    out = proc.stdout + proc.stderr
    assert proc.returncode != 0 and "crashed" in out, out[-3000:]
    lost = re.search(r"records of worker (gw\d) lost \(it crashed\): see its popen-(gw\d)/faults.json", out)
    assert lost and lost.group(1) == lost.group(2), out[-3000:]
    assert "faults injected: 1, runs survived: 1, rows lost: 0" in out, out[-3000:]  # the other worker's
    own = json.loads((basetemp / f"popen-{lost.group(1)}" / "faults.json").read_text())
    assert [r["fault"] for r in own["faults"]] == ["probe crash: recorded, then the worker dies"]
    whole = json.loads((tmp_path / "report" / "faults.json").read_text())
    assert [r["fault"] for r in whole["faults"]] == ["probe one: all rows kept"]


_PROBE_NONE = '''import os


def test_{name}():  # injects no fault; runs on a worker
    assert os.environ["PYTEST_XDIST_WORKER"].startswith("gw")
'''


def test_workers_without_a_fault_leave_the_last_report_alone(tmp_path):
    """As in one process, a session that injects no fault writes no ledger: an empty one from the controller would
    overwrite the last run's ``$LIVERFORCE_FAULT_REPORT`` with zeros."""
    report = tmp_path / "report" / "faults.json"
    report.parent.mkdir()
    report.write_text('{"faults_injected": 7}')
    probes = {f"test_{n}.py": _PROBE_NONE.format(name=n) for n in ("a", "b")}
    proc, basetemp = _session(tmp_path, probes)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0 and "2 workers [2 items]" in out and "faults injected" not in out, out[-3000:]
    assert report.read_text() == '{"faults_injected": 7}' and not (basetemp / "faults.json").exists()
