"""Geometry stage: procedural livers, a cube phantom, importers, repair, units.

Everything returns a :class:`~liverforce.geometry.surface.Surface` in mm,
in the RAS frame (+x patient right, +y anterior, +z superior): built-in shapes
are made in it, imported files are converted to it from the frame they state
(``frame``: RAS, LPS or a 4×4, see :mod:`liverforce.geometry.frames`).
"""

from liverforce.geometry.errors import GeometryError
from liverforce.geometry.importers import load_surface
from liverforce.geometry.procedural import LiverShapeParams, cube_phantom, procedural_liver
from liverforce.geometry.surface import Surface

__all__ = ["GeometryError", "LiverShapeParams", "Surface", "cube_phantom", "load_surface", "procedural_liver"]
