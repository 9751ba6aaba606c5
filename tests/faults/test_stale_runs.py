"""A training process SIGKILLed mid-run leaves its MLflow run RUNNING; the next Tracker closes it.

Two real processes each open a run in one SQLite store; one is SIGKILLed, the
other stays alive. A new :class:`~liverforce.tracking.Tracker` on the same
experiment marks the dead process's run KILLED (with the reason as a tag) and
leaves the live process's run, and its own, alone.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from liverforce.tracking import HOST_TAG, PID_TAG, Tracker

CHILD = textwrap.dedent("""
    import sys, time
    from liverforce.tracking import Tracker
    t = Tracker(sys.argv[1], "stale-test")
    run_id = t.start_run(sys.argv[2])
    t.log_metrics(run_id, {"epoch_loss": 1.0})
    print(run_id, flush=True)
    time.sleep(600)
""")


def _start(uri: str, name: str) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen([sys.executable, "-c", CHILD, uri, name], stdout=subprocess.PIPE, text=True,
                            start_new_session=True)
    line = proc.stdout.readline().strip()
    assert len(line) == 32, f"child did not start a run: {line!r}"
    return proc, line


@pytest.mark.slow  # one of the default set's slowest (CI's --durations): run with -m slow
def test_runs_of_killed_processes_are_closed_live_ones_are_not(tmp_path, fault_ledger):
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    victim, victim_run = _start(uri, "victim")
    alive, alive_run = _start(uri, "alive")
    try:
        os.killpg(victim.pid, signal.SIGKILL)
        victim.wait(timeout=30)
        with fault_ledger.check("SIGKILL of a process with an open MLflow run", rows_expected=3) as seen:
            tracker = Tracker(uri, "stale-test")  # closes stale runs on opening the experiment
            own_run = tracker.start_run("own")
            closed_again = tracker.close_stale_runs()
            client = tracker.client
            runs = client.search_runs([tracker.experiment_id])
            seen.rows_found = len(runs)
            victim_info = client.get_run(victim_run)
            assert victim_info.info.status == "KILLED"
            assert str(victim.pid) in victim_info.data.tags["liverforce.stale"]
            assert victim_info.data.metrics["epoch_loss"] == 1.0  # what it logged is kept
            assert client.get_run(alive_run).info.status == "RUNNING"
            assert client.get_run(own_run).info.status == "RUNNING"
            assert client.get_run(own_run).data.tags[PID_TAG] == str(os.getpid())
            assert HOST_TAG in client.get_run(own_run).data.tags
            assert closed_again == []
            assert len(runs) == 3  # nothing deleted
    finally:
        if alive.poll() is None:
            os.killpg(alive.pid, signal.SIGKILL)
            alive.wait(timeout=30)
