"""The fault ledger itself: a fault counts as survived only when its checks ran and passed."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

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
