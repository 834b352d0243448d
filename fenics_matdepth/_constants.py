"""Dtypes and tolerances shared by the numba kernels (one place, so they agree)."""

from __future__ import annotations

import numpy as np

#: Floating-point type of coordinates, depths and kernel outputs.
FLOAT = np.float64
#: Integer type of vertex, element and pair indices.
INDEX = np.int64
