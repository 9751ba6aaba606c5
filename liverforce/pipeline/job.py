"""Per-job set-up for workflow scripts: thread limits, logging, and killed runs' stray temporary files."""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

from liverforce.atomic import remove_stale_temps  # standard library only, like this module

#: the environment variables that size every thread pool of a process (the one list; stdlib-only module,
#: so scripts can import it before numpy)
THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")


def thread_env(n: int = 1, env=None, *, override: bool = True) -> dict:
    """``env`` (default ``os.environ``) with every :data:`THREAD_VARS` set to ``n`` (kept if set and not ``override``)."""
    target = os.environ if env is None else env
    for var in THREAD_VARS:
        if override or var not in target:
            target[var] = str(int(n))
    return target


def limit_threads(n: int) -> None:
    """Cap every thread pool (BLAS, OpenMP, numba, torch) of this process at ``n``.

    On 2 cores, oversubscription is the biggest performance risk (STACK_NOTES:
    2.9 s with 1 thread vs 77 s with 2 under load).
    """
    n = max(1, int(n))
    for var in THREAD_VARS:
        os.environ[var] = str(n)
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(n)
    except ImportError:  # pragma: no cover - threadpoolctl is a dependency
        pass
    if "torch" in sys.modules:
        import torch

        torch.set_num_threads(n)


def job_name(log_path: str | Path | None) -> str:
    """What a job is, for its messages, from its log ``logs/<stage>/<name>.log``: ``"<stage> <name>"``."""
    if not log_path:
        return Path(sys.argv[0]).stem or "this job"
    p = Path(log_path)
    return f"{p.parent.name} {p.stem}" if p.parent.name else p.stem


def interrupted_line(what: str) -> str:
    """The one line a job logs when it is interrupted (Ctrl-C): not a failure of the code, so no traceback."""
    return (f"interrupted (SIGINT/KeyboardInterrupt) during {what}: finished work is kept; "
            "re-run the same command to go on")


def run_status(exc: BaseException) -> str:
    """The MLflow status of a run that ``exc`` ended: ``KILLED`` for an interrupt (Ctrl-C, or an error raised
    while one unwound the job), else ``FAILED``."""
    return "KILLED" if _during_interrupt(exc) else "FAILED"


def _during_interrupt(exc: BaseException | None) -> bool:
    """Whether ``exc`` was raised while a ``KeyboardInterrupt`` was being handled (its context chain holds one)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, KeyboardInterrupt):
            return True
        exc = exc.__cause__ or exc.__context__
    return False


def setup_job(log_path: str | Path | None, threads: int = 1, outputs=(), what: str | None = None) -> logging.Logger:
    """Log to the job's log file and to stderr; limit threads; remove killed runs' temporary files beside outputs.

    ``outputs``: the job's output paths. A killed earlier run of the job may have left the temporary
    file of an atomic write beside one (:func:`liverforce.atomic.remove_stale_temps`); the job owns its
    outputs, so those are removed, and logged. Returns the logger.

    An exception the job does not catch is logged as ``job failed`` with its traceback; an interrupt
    (``KeyboardInterrupt``: Ctrl-C, SIGINT to the process group) as one line (:func:`interrupted_line`,
    ``what`` defaults to :func:`job_name` of the log) without a traceback. Either way the process exits
    non-zero (Python ends an unhandled interrupt by SIGINT), so Snakemake does not take the job as done.
    SIGTERM is left to its default (the process ends at once).
    """
    limit_threads(threads)
    logger = logging.getLogger("liverforce")
    logger.setLevel(logging.INFO)
    logger.handlers.clear()
    fmt = logging.Formatter("%(asctime)s %(levelname)s %(message)s", "%H:%M:%S")
    err = logging.StreamHandler(sys.stderr)
    err.setFormatter(fmt)
    logger.addHandler(err)
    if log_path:
        Path(log_path).parent.mkdir(parents=True, exist_ok=True)
        fh = logging.FileHandler(log_path, mode="w")
        fh.setFormatter(fmt)
        logger.addHandler(fh)

    name = what or job_name(log_path)

    def _log_uncaught(exc_type, exc, tb, _previous=sys.excepthook):
        # the job's log must say why it failed (Snakemake points the user to it); an interrupt is no failure
        if issubclass(exc_type, KeyboardInterrupt):
            logger.warning(interrupted_line(name))
        elif _during_interrupt(exc):  # e.g. a clean-up that failed while the interrupt unwound the job
            logger.warning("%s (while stopping: %s: %s)", interrupted_line(name), exc_type.__name__, exc)
        else:
            logger.critical("job failed: %s: %s", exc_type.__name__, exc, exc_info=(exc_type, exc, tb))
        for h in logger.handlers:
            h.flush()

    sys.excepthook = _log_uncaught
    for out in outputs:
        for p in remove_stale_temps(out):
            logger.info("removed %s, left by a killed earlier run of this job", p)
    return logger
