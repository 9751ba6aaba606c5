"""Geometry stage: procedural livers, a cube phantom, importers, repair, units.

Everything returns a :class:`~liverforce.geometry.surface.Surface` in mm
(frame: RAS, +x patient right, +y anterior, +z superior for built-in shapes;
imported files keep their own frame).
"""

from liverforce.geometry.errors import GeometryError
from liverforce.geometry.importers import load_surface
from liverforce.geometry.procedural import LiverShapeParams, cube_phantom, procedural_liver
from liverforce.geometry.surface import Surface

__all__ = ["GeometryError", "LiverShapeParams", "Surface", "cube_phantom", "load_surface", "procedural_liver"]
