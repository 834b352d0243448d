"""The intersection polygon of a pair without derivatives: its buffers, the clip of a triangle
against a (sub-)tetrahedron, and the largest material depth reached on it over many pairs."""

from __future__ import annotations

import numpy as np
from numba import njit

from fenics_matdepth._constants import FLOAT, INDEX
from fenics_matdepth.contact.kernels.fastmath import FMA
from fenics_matdepth.contact.kernels.split import gather_tet, is_split
from fenics_matdepth.geometry.clip import (
    MAX_POLYGON_VERTICES,
    clip_triangle,
    tet_gradients,
    triangle_area2,
    triangle_rows,
)

__all__ = [
    "area_pairs_max_depth",
    "gather_triangle",
    "polygon_work",
    "sub_polygon",
]

_NV = MAX_POLYGON_VERTICES


@njit(cache=True, fastmath=FMA)
def polygon_work():
    """Buffers of `sub_polygon`: xs (3, 3), xt (4, 3), dt (4,), grads (4, 3), lam (3, 4),
    mu, vlab, elab (the clipped polygon, as `clip_triangle` fills them) and gi (3,)."""
    return (
        np.empty((3, 3), dtype=FLOAT),
        np.empty((4, 3), dtype=FLOAT),
        np.empty(4, dtype=FLOAT),
        np.empty((4, 3), dtype=FLOAT),
        np.empty((3, 4), dtype=FLOAT),
        np.empty((2, _NV, 3), dtype=FLOAT),
        np.empty((2, _NV, 2), dtype=INDEX),
        np.empty((2, _NV), dtype=INDEX),
        np.empty(3, dtype=FLOAT),
    )


@njit(cache=True, fastmath=FMA)
def gather_triangle(x, tri, t, xs):
    """Vertices of triangle t into xs (3, 3); returns twice its area."""
    for a in range(3):
        for r in range(3):
            xs[a, r] = x[tri[t, a], r]
    return triangle_area2(xs)


@njit(cache=True, fastmath=FMA)
def sub_polygon(x, depth, tet, k, s, split, work):
    """Clip the triangle in ``work[0]`` against tetrahedron k (sub-tetrahedron s when split):
    the polygon in ``work[5]`` (parameter coordinates on the triangle, as `clip_triangle` gives
    them) and, in ``work[8]``, the depth ``g_K`` at the triangle's corners, extended affinely
    over the parameter simplex. Returns the polygon's vertex count (0 for a flat
    tetrahedron)."""
    xs, xt, dt, grads, lam, mu, vlab, elab, gi = work
    gather_tet(x, depth, tet, k, s, split, xt, dt)
    if tet_gradients(xt, grads) == 0.0:
        return 0
    triangle_rows(xs, xt, grads, lam)
    n = clip_triangle(lam, mu, vlab, elab)
    for i in range(3):
        gi[i] = lam[i, 0] * dt[0] + lam[i, 1] * dt[1] + lam[i, 2] * dt[2] + lam[i, 3] * dt[3]
    return n


@njit(cache=True, fastmath=FMA)
def area_pairs_max_depth(x, depth, tri, tet, pair_tri, pair_tet):
    """Largest material depth ``g_K`` reached on each pair's intersection polygon (length).

    ``g_K`` is affine on the polygon, so its maximum is at a polygon vertex. Pairs whose
    intersection is empty get 0.

    Args:
        x, depth, tri, tet, pair_tri, pair_tet: as `area_pairs`.

    Returns:
        (np,) maximum depth per pair.
    """
    out = np.zeros(pair_tri.shape[0], dtype=FLOAT)
    work = polygon_work()
    xs, mu, gi = work[0], work[5], work[8]
    for p in range(pair_tri.shape[0]):
        if gather_triangle(x, tri, pair_tri[p], xs) == 0.0:
            continue
        k = pair_tet[p]
        split = is_split(tet, k)
        best = 0.0
        for s in range(4 if split else 1):
            n = sub_polygon(x, depth, tet, k, s, split, work)
            for v in range(n):
                g = mu[0, v, 0] * gi[0] + mu[0, v, 1] * gi[1] + mu[0, v, 2] * gi[2]
                best = max(best, g)
        out[p] = best
    return out
