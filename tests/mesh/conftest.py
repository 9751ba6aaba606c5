"""Shared small meshes for the mesh tests (built once per session; coarse)."""

from __future__ import annotations

import pytest

from liverforce.geometry.procedural import procedural_liver
from liverforce.mesh.build import build_liver_mesh


@pytest.fixture(scope="session")
def liver_surface():
    return procedural_liver(0)


@pytest.fixture(scope="session")
def liver_mesh(liver_surface):
    """Procedural liver (seed 0) at ~1500 nodes with default regions."""
    return build_liver_mesh(liver_surface, target_nodes=1500, seed=0)
