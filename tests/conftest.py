"""Shared fixtures: paths, the shared data folder, small meshes."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SHARED_LIVERS = ROOT.parent / "shared" / "data" / "livers"

# one thread per pool in tests (2-core machine)
for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")


@pytest.fixture(scope="session")
def shared_livers() -> Path:
    if not SHARED_LIVERS.is_dir():
        pytest.skip(f"real liver meshes not present at {SHARED_LIVERS} (../shared/data/livers is outside the repo)")
    return SHARED_LIVERS
