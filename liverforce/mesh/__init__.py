"""Mesh stage: quality tetrahedral meshes, boundary regions, features, I/O.

Main entry points: :func:`~liverforce.mesh.build.build_liver_mesh` (surface →
tagged :class:`~liverforce.mesh.types.LiverMesh`),
:func:`~liverforce.mesh.tetra.tetrahedralise`,
:func:`~liverforce.mesh.regions.tag_regions`,
:func:`~liverforce.mesh.features.compute_features`,
:func:`~liverforce.mesh.io.write_mesh` / :func:`~liverforce.mesh.io.read_mesh`,
:func:`~liverforce.mesh.plot.plot_regions`.  Units: mm.
"""

from liverforce.mesh.build import build_liver_mesh
from liverforce.mesh.features import compute_features
from liverforce.mesh.io import read_mesh, write_mesh
from liverforce.mesh.quality import mesh_quality
from liverforce.mesh.regions import RegionParams, tag_regions
from liverforce.mesh.tetra import MeshingError, tetrahedralise
from liverforce.mesh.types import REGION_CODES, LiverMesh

__all__ = [
    "LiverMesh",
    "MeshingError",
    "REGION_CODES",
    "RegionParams",
    "build_liver_mesh",
    "compute_features",
    "mesh_quality",
    "read_mesh",
    "tag_regions",
    "tetrahedralise",
    "write_mesh",
]
