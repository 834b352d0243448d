"""Numba geometry: AABB tree, point-triangle distance, triangle-tetrahedron clipping."""

from __future__ import annotations

from fenics_matdepth.geometry.clip import intersection_polygon

__all__ = ["intersection_polygon"]
