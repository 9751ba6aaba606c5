"""Fault-injection tests: a ledger of what each test injected and what survived.

Every fault test records each fault it injects, with the rows it expected and
the rows it found afterwards (measured, e.g. case ids of the final shards
against the reference run), before any verdict is taken:

- ``with fault_ledger.check(fault, rows_expected=n) as seen:`` around the
  checks: ``seen.rows_found`` (and ``seen.detail``) are set from what was
  observed; the fault counts as survived only if every check in the block
  passed, and as NOT survived (recorded, then re-raised) if one failed;
- ``fault_ledger.record(fault, survived=<a measured boolean>, ...)`` where the
  verdict is computed from observations (``tests/faults/test_ledger.py`` fails
  on a literal ``survived=True``).

At the end of the session pytest prints

    faults injected: N, runs survived: M, rows lost: R

and writes the same numbers, one record per fault, to ``faults.json`` in
pytest's base temporary folder (and to ``$LIVERFORCE_FAULT_REPORT`` if set).

Under pytest-xdist the faults are injected in the workers: each worker keeps
its own records (and its own ``faults.json`` in its ``popen-gw<N>`` folder),
hands them to the controller when it finishes (``config.workeroutput``), and
the controller prints and writes the whole ledger (the hooks that gather and
print are in ``tests/conftest.py``, which the controller always loads; this
file's hooks act only in a worker, or without workers).
"""
from __future__ import annotations

import json
import os
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path

import pytest

from liverforce.atomic import write_text_atomic

_RECORDS: list["FaultRecord"] = []
_REPORT_PATH: list[Path] = []
_GATHERED: set[str] = set()  # the xdist workers whose records the controller has (or lost)
_LOST: list[str] = []  # xdist workers that died before handing over their records


@dataclass
class FaultRecord:
    test: str
    fault: str
    survived: bool
    rows_expected: int = 0
    rows_found: int = 0
    detail: dict = field(default_factory=dict)

    @property
    def rows_lost(self) -> int:
        return max(0, self.rows_expected - self.rows_found)


@dataclass
class Observation:
    """What a fault test saw, filled in inside :meth:`FaultLedger.check`."""

    rows_found: int = 0
    detail: dict = field(default_factory=dict)


class FaultLedger:
    def __init__(self, test: str):
        self.test = test

    @contextmanager
    def check(self, fault: str, *, rows_expected: int = 0, **detail):
        """Record ``fault`` as survived only if the block's checks all pass; a failure is recorded, then raised."""
        seen = Observation(detail=dict(detail))
        try:
            yield seen
        except BaseException as exc:
            self.record(fault, survived=False, rows_expected=rows_expected, rows_found=seen.rows_found,
                        failure=f"{type(exc).__name__}: {exc}"[:500], **seen.detail)
            raise
        self.record(fault, survived=True, rows_expected=rows_expected, rows_found=seen.rows_found,
                    **seen.detail)

    def record(self, fault: str, *, survived: bool, rows_expected: int = 0, rows_found: int = 0, **detail) -> FaultRecord:
        """One injected fault; ``survived`` = the run finished correctly afterwards."""
        rec = FaultRecord(self.test, fault, bool(survived), int(rows_expected), int(rows_found), detail)
        _RECORDS.append(rec)
        _write()
        return rec


def summary() -> dict:
    return {
        "faults_injected": len(_RECORDS),
        "runs_survived": sum(r.survived for r in _RECORDS),
        "rows_lost": sum(r.rows_lost for r in _RECORDS),
        "faults": [{**asdict(r), "rows_lost": r.rows_lost} for r in _RECORDS],
    }


def _write() -> None:
    text = json.dumps(summary(), indent=2, default=str)
    for p in _REPORT_PATH:
        write_text_atomic(p, text)


def _report_paths(basetemp: Path, *, whole: bool) -> None:
    """Write the ledger to ``basetemp/faults.json``, and to ``$LIVERFORCE_FAULT_REPORT`` if it holds ``whole``."""
    _REPORT_PATH.clear()
    _REPORT_PATH.append(Path(basetemp) / "faults.json")
    if whole and os.environ.get("LIVERFORCE_FAULT_REPORT"):
        _REPORT_PATH.append(Path(os.environ["LIVERFORCE_FAULT_REPORT"]))


def _is_worker(config) -> bool:
    return hasattr(config, "workerinput")


@pytest.fixture(scope="session", autouse=True)
def _fault_report_path(tmp_path_factory, pytestconfig):
    # a worker's ledger is a part: $LIVERFORCE_FAULT_REPORT is the controller's to write, with every worker's
    _report_paths(tmp_path_factory.getbasetemp(), whole=not _is_worker(pytestconfig))
    yield


@pytest.fixture
def fault_ledger(request) -> FaultLedger:
    return FaultLedger(request.node.nodeid)


def pytest_sessionfinish(session):
    """On an xdist worker: hand this worker's records to the controller (:func:`gather` there)."""
    if hasattr(session.config, "workeroutput"):
        session.config.workeroutput["fault_records"] = json.dumps([asdict(r) for r in _RECORDS], default=str)


def gather(config, node) -> None:
    """On the xdist controller: add the records of the worker ``node`` that finished; write the whole ledger."""
    if not _REPORT_PATH:
        # the folder xdist gives each worker a subfolder of (the controller runs no fixture)
        _report_paths(config._tmp_path_factory.getbasetemp(), whole=True)
    worker = node.gateway.id
    if worker in _GATHERED:  # xdist reports a worker stopped by Ctrl-C twice
        return
    _GATHERED.add(worker)
    output = getattr(node, "workeroutput", None)
    if output is None:  # the worker crashed: its records up to then are only in its own faults.json
        _LOST.append(worker)
        return
    _RECORDS.extend(FaultRecord(**r) for r in json.loads(output.get("fault_records", "[]")))
    if _RECORDS:  # as in one process: no fault injected, no report (an empty one would overwrite the last)
        _write()


def terminal_summary(terminalreporter) -> None:
    """The session's ledger: one line per fault, then the totals (called by ``tests/conftest.py``)."""
    if not _RECORDS and not _LOST:
        return
    s = summary()
    tr = terminalreporter
    tr.section("fault injection")
    for worker in _LOST:
        tr.write_line(f"records of worker {worker} lost (it crashed): see its popen-{worker}/faults.json", red=True)
    for r in _RECORDS:
        tr.write_line(f"{'survived' if r.survived else 'NOT SURVIVED'}: {r.fault} "
                      f"(rows {r.rows_found}/{r.rows_expected}) [{r.test}]")
    tr.write_line(f"faults injected: {s['faults_injected']}, runs survived: {s['runs_survived']}, "
                  f"rows lost: {s['rows_lost']}")
    if _REPORT_PATH:
        tr.write_line(f"fault report: {_REPORT_PATH[0]}")
