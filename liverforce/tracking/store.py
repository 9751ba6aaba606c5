"""The tracking store: SQLite lock retries, one-time store creation, runs left open by dead processes.

SQLite stores take one writer at a time: every MLflow call goes through
:func:`with_retry`, which retries with exponential back-off (plus jitter)
while the error says the database is locked. Create a fresh store once with
:func:`ensure_store` before parallel jobs start (two processes creating the
schema at once fail); it is idempotent and serialised by a lock file.

Every run carries the host and process id that created it (:func:`owner_tags`:
tags ``liverforce.host``, ``liverforce.pid``). A run left ``RUNNING`` by a
process that no longer exists on this host (a SIGKILLed job) is marked
``KILLED`` by :func:`close_stale_runs`, so a resumed workflow leaves no phantom
running runs; runs of live processes and of other hosts are never touched.
"""

from __future__ import annotations

import fcntl
import os
import random
import socket
import time
from pathlib import Path
from typing import Callable, TypeVar

from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient

T = TypeVar("T")

HOST_TAG, PID_TAG = "liverforce.host", "liverforce.pid"
STALE_TAG = "liverforce.stale"


# --------------------------------------------------------------------------
# retries and store creation
# --------------------------------------------------------------------------


def is_lock_error(exc: BaseException) -> bool:
    """True if ``exc`` (or an exception it wraps) says the SQLite database is locked/busy."""
    seen = 0
    e: BaseException | None = exc
    while e is not None and seen < 10:
        msg = str(e).lower()
        if "database is locked" in msg or "database table is locked" in msg or "database is busy" in msg:
            return True
        if type(e).__name__ == "OperationalError" and "locked" in msg:
            return True
        e = e.__cause__ or e.__context__
        seen += 1
    return False


def with_retry(fn: Callable[..., T], *args, retries: int = 12, backoff_s: float = 0.1, **kwargs) -> T:
    """Call ``fn(*args, **kwargs)``, retrying lock errors with back-off ``backoff_s * 2^i`` (max 5 s).

    Other exceptions propagate at once; after ``retries`` lock errors the
    last one propagates.
    """
    delay = backoff_s
    for attempt in range(retries + 1):
        try:
            return fn(*args, **kwargs)
        except Exception as exc:  # noqa: BLE001 - filtered by is_lock_error, others re-raised
            if attempt == retries or not is_lock_error(exc):
                raise
            time.sleep(delay * (1.0 + random.random()))
            delay = min(2.0 * delay, 5.0)
    raise AssertionError("unreachable")


def sqlite_path(uri: str) -> Path | None:
    """The database file of a ``sqlite:///`` URI (``None`` for other stores)."""
    if not uri.startswith("sqlite:///"):
        return None
    return Path(uri[len("sqlite:///"):])


def ensure_store(uri: str) -> None:
    """Create the tracking store behind ``uri`` once (idempotent, safe across processes).

    For SQLite the schema is created under an exclusive lock file
    (``<db>.lock``), so parallel jobs never race to create tables.
    """
    db = sqlite_path(uri)
    if db is None:
        with_retry(MlflowClient(tracking_uri=uri).search_experiments, max_results=1)
        return
    db.parent.mkdir(parents=True, exist_ok=True)
    with open(db.with_name(db.name + ".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            with_retry(MlflowClient(tracking_uri=uri).search_experiments, max_results=1)
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


# --------------------------------------------------------------------------
# runs left RUNNING by dead processes
# --------------------------------------------------------------------------


def owner_tags() -> dict[str, str]:
    """The tags naming this process as a run's owner (host name and process id)."""
    return {HOST_TAG: socket.gethostname(), PID_TAG: str(os.getpid())}


def pid_alive(pid: int) -> bool:
    """True if process ``pid`` exists on this host (this process counts as alive)."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def close_stale_runs(client: MlflowClient, experiment_id: str,
                     call: Callable[..., T] = with_retry) -> list[str]:
    """Mark ``KILLED`` the runs of ``experiment_id`` left ``RUNNING`` by processes of this host that no longer exist.

    Parameters
    ----------
    client : MlflowClient
    experiment_id : str
    call : callable
        How to call the store, ``call(fn, *args, **kwargs)`` (default :func:`with_retry`).

    Returns
    -------
    list of str
        The ids of the runs it closed (each tagged ``liverforce.stale`` with
        the reason). Runs without host/pid tags, of another host, or of a live
        process are left alone.
    """
    host = socket.gethostname()
    try:
        running = call(client.search_runs, [experiment_id],
                       filter_string="attributes.status = 'RUNNING'", max_results=10000)
    except MlflowException:
        return []
    closed = []
    for run in running:
        tags = run.data.tags
        if tags.get(HOST_TAG) != host or not str(tags.get(PID_TAG, "")).isdigit():
            continue
        if pid_alive(int(tags[PID_TAG])):
            continue
        call(client.set_tag, run.info.run_id, STALE_TAG,
             f"process {tags[PID_TAG]} on {host} ended without closing the run")
        call(client.set_terminated, run.info.run_id, "KILLED")
        closed.append(run.info.run_id)
    return closed
