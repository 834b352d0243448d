"""DOLFINx version differences (0.9, 0.10, 0.11), kept in this one module.

Everything else in the package calls these helpers instead of testing versions itself.
"""

from __future__ import annotations

import dolfinx

__all__ = ["DOLFINX_VERSION"]

#: (major, minor) of the DOLFINx in use.
DOLFINX_VERSION: tuple[int, int] = tuple(int(p) for p in dolfinx.__version__.split(".")[:2])
