"""Contact: numba pair kernels (kernels.py) and the operator that assembles them."""

from __future__ import annotations

from fenics_matdepth.contact import kernels

__all__ = ["kernels"]
