"""Shared fixtures: paths, the shared data folder, small meshes."""
from __future__ import annotations

from pathlib import Path

import pytest

from liverforce.pipeline.job import thread_env

ROOT = Path(__file__).resolve().parent.parent
SHARED_LIVERS = ROOT.parent / "shared" / "data" / "livers"

# one thread per pool in tests (2-core machine)
thread_env(1, override=False)


@pytest.fixture(scope="session")
def shared_livers() -> Path:
    if not SHARED_LIVERS.is_dir():
        pytest.skip(f"real liver meshes not present at {SHARED_LIVERS} (../shared/data/livers is outside the repo)")
    return SHARED_LIVERS
