"""The intersection polygon of a pair without derivatives: its buffers, the clip of a triangle
against a (sub-)tetrahedron, and the largest material depth reached on it over many pairs."""

from __future__ import annotations

from typing import NamedTuple

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
    "PolygonWork",
    "area_pairs_max_depth",
    "gather_triangle",
    "polygon_work",
    "sub_polygon",
]

_NV = MAX_POLYGON_VERTICES


class PolygonWork(NamedTuple):
    """Buffers of `sub_polygon` (`polygon_work`), by name."""

    xs: np.ndarray  #: (3, 3) the triangle's corners
    xt: np.ndarray  #: (4, 3) the (sub-)tetrahedron's vertices
    dt: np.ndarray  #: (4,) their material depths
    grads: np.ndarray  #: (4, 3) barycentric gradients of the (sub-)tetrahedron
    lam: np.ndarray  #: (3, 4) barycentric coordinates of the triangle's corners in it
    mu: np.ndarray  #: (2, nv, 3) the clipped polygon, as `clip_triangle` fills it
    vertex_labels: np.ndarray  #: (2, nv, 2) its vertex labels
    edge_labels: np.ndarray  #: (2, nv) its edge labels
    corner_depth: np.ndarray  #: (3,) the depth g_K at the triangle's corners, extended affinely


@njit(cache=True, fastmath=FMA)
def polygon_work():
    """The buffers of `sub_polygon`."""
    return PolygonWork(
        xs=np.empty((3, 3), dtype=FLOAT),
        xt=np.empty((4, 3), dtype=FLOAT),
        dt=np.empty(4, dtype=FLOAT),
        grads=np.empty((4, 3), dtype=FLOAT),
        lam=np.empty((3, 4), dtype=FLOAT),
        mu=np.empty((2, _NV, 3), dtype=FLOAT),
        vertex_labels=np.empty((2, _NV, 2), dtype=INDEX),
        edge_labels=np.empty((2, _NV), dtype=INDEX),
        corner_depth=np.empty(3, dtype=FLOAT),
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
    """Clip the triangle in ``work.xs`` against tetrahedron k (sub-tetrahedron s when split):
    the polygon in ``work.mu`` (parameter coordinates on the triangle, as `clip_triangle` gives
    them) and, in ``work.corner_depth``, the depth ``g_K`` at the triangle's corners, extended
    affinely over the parameter simplex. Returns the polygon's vertex count (0 for a flat
    tetrahedron)."""
    xs = work.xs
    xt = work.xt
    dt = work.dt
    grads = work.grads
    lam = work.lam
    mu = work.mu
    vlab = work.vertex_labels
    elab = work.edge_labels
    gi = work.corner_depth
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
    xs, mu, gi = work.xs, work.mu, work.corner_depth
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
