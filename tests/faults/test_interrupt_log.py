"""Ctrl-C during a job (SIGINT to Snakemake's process group): one clear log line, no traceback, a non-zero exit.

An interrupt is not a failure of the code: the job's log says what was interrupted and that a re-run goes on,
without ``CRITICAL job failed: KeyboardInterrupt`` and a traceback. The job still exits non-zero, so Snakemake
does not take it as done. Ordinary failures keep their ``job failed`` line with the traceback, and SIGTERM keeps
its default (the process ends at once, nothing logged).
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
LINE = ("interrupted (SIGINT/KeyboardInterrupt) during train II-pca_sv: finished work is kept; "
        "re-run the same command to go on")

# a tiny job, set up as the workflow scripts do; argv: log path, what to do after set-up
JOB = textwrap.dedent("""
    import sys, time
    from liverforce.pipeline.job import setup_job
    log = setup_job(sys.argv[1], 1)
    log.info("training started")
    if sys.argv[2] == "raise":
        raise KeyboardInterrupt
    if sys.argv[2] == "cleanup-fails":
        try:
            raise KeyboardInterrupt
        finally:
            raise OSError("tracking server gone")
    if sys.argv[2] == "fail":
        raise ValueError("a real bug")
    print("ready", flush=True)
    time.sleep(120)
""")


def _start(tmp_path: Path, action: str) -> tuple[subprocess.Popen, Path]:
    log = tmp_path / "logs" / "train" / "II-pca_sv.log"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen([sys.executable, "-c", JOB, str(log), action], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env, cwd=tmp_path)
    return proc, log


def _signalled(tmp_path: Path, sig: int) -> tuple[subprocess.CompletedProcess, Path]:
    proc, log = _start(tmp_path, "sleep")
    try:
        assert proc.stdout.readline().strip() == "ready", proc.stderr.read()
        os.kill(proc.pid, sig)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err), log


def _ran(tmp_path: Path, action: str) -> tuple[subprocess.CompletedProcess, Path]:
    proc, log = _start(tmp_path, action)
    out, err = proc.communicate(timeout=60)
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err), log


def _assert_one_interrupt_line(done: subprocess.CompletedProcess, log: Path, extra: str = "") -> None:
    text = log.read_text()
    assert done.returncode != 0, "an interrupted job must not look done to Snakemake"
    assert "Traceback" not in text and "Traceback" not in done.stderr, text + done.stderr
    assert "CRITICAL" not in text and "job failed" not in text, text
    lines = [ln for ln in text.splitlines() if "interrupted" in ln]
    assert len(lines) == 1 and lines[0].endswith(LINE + extra), text
    assert text.splitlines()[-1] == lines[0], "the interrupt line is the log's last"
    assert LINE in done.stderr  # the console says it too, once
    assert done.stderr.count("interrupted") == 1, done.stderr


def test_sigint_during_a_job_logs_one_line_without_traceback_and_exits_nonzero(tmp_path):
    done, log = _signalled(tmp_path, signal.SIGINT)
    _assert_one_interrupt_line(done, log)
    assert done.returncode == -signal.SIGINT  # Python ends an unhandled interrupt by SIGINT, as a shell expects


def test_keyboard_interrupt_raised_in_the_work_logs_one_line(tmp_path):
    done, log = _ran(tmp_path, "raise")
    _assert_one_interrupt_line(done, log)


def test_a_clean_up_failing_during_the_interrupt_is_still_an_interrupt(tmp_path):
    done, log = _ran(tmp_path, "cleanup-fails")
    _assert_one_interrupt_line(done, log, " (while stopping: OSError: tracking server gone)")


def test_a_real_failure_still_logs_job_failed_with_its_traceback(tmp_path):
    done, log = _ran(tmp_path, "fail")
    text = log.read_text()
    assert done.returncode == 1
    assert "CRITICAL job failed: ValueError: a real bug" in text and "Traceback" in text, text
    assert "interrupted" not in text


@pytest.mark.skipif(not hasattr(signal, "SIGTERM"), reason="POSIX signals")
def test_sigterm_keeps_its_default(tmp_path):
    """A guard (passes before the change too): SIGTERM still ends the job at once, with no interrupt line."""
    done, log = _signalled(tmp_path, signal.SIGTERM)
    assert done.returncode == -signal.SIGTERM
    assert "interrupted" not in log.read_text() and "Traceback" not in done.stderr
