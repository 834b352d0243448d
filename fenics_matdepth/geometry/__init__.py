"""Numba geometry: element boxes and pair filters, AABB tree, point-triangle distance,
triangle-tetrahedron clipping and the intersection tests over many pairs."""

from __future__ import annotations

from fenics_matdepth.geometry.clip import intersection_polygon

__all__ = ["intersection_polygon"]
