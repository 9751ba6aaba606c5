"""One quiet, single-threaded, seeded gmsh session, always finalised.

gmsh runs in-process and is not re-entrant: do not open a session from two
threads of one process (separate processes are fine).
"""

from __future__ import annotations

from contextlib import contextmanager

from liverforce.mesh.meshing_info import MeshingError
from liverforce.seeds import gmsh_random_seed

__all__ = ["gmsh_session", "last_errors"]


@contextmanager
def gmsh_session(seed: int):
    """Initialise gmsh quietly with one thread; always finalise."""
    import gmsh

    if gmsh.isInitialized():
        raise MeshingError("gmsh is already initialised in this process; tetrahedralise is not re-entrant")
    gmsh.initialize(readConfigFiles=False, interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.Verbosity", 2)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.option.setNumber("Mesh.MaxNumThreads2D", 1)
        gmsh.option.setNumber("Mesh.MaxNumThreads3D", 1)
        gmsh.option.setNumber("Mesh.RandomSeed", gmsh_random_seed(seed))
        gmsh.logger.start()
        yield gmsh
    finally:
        gmsh.finalize()


def last_errors(gmsh) -> str:
    """The last three error messages of the gmsh logger, joined (for exception messages)."""
    try:
        msgs = [m for m in gmsh.logger.get() if "Error" in m or "error" in m]
    except Exception:  # pragma: no cover - logger unavailable
        msgs = []
    return " | ".join(msgs[-3:])
