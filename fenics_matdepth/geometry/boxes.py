"""Axis-aligned boxes of simplices and the pair filters made of them (numba).

Element boxes are ``(lo xyz, hi xyz)`` rows, closed (touching boxes overlap). The filters take
(triangle, tetrahedron) candidate pairs as flat arrays and keep, order preserved, those that
share no vertex (`exclude_shared_vertex_pairs`) or whose boxes overlap now
(`overlapping_pairs`); `kept_pairs` gathers the pairs a filter keeps. The tree that finds
candidate pairs is `fenics_matdepth.geometry.bvh`.

Lengths are in the unit of ``points``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from fenics_matdepth._constants import FLOAT, INDEX

__all__ = [
    "as_points",
    "element_box_rows",
    "element_boxes",
    "exclude_shared_vertex_pairs",
    "kept_pairs",
    "overlapping_pairs",
    "rows_overlap",
    "share_vertex",
]


@njit(inline="always")
def rows_overlap(a, i, b, j, margin):
    """Closed-interval overlap of box row a[i] inflated by margin with box row b[j].

    Touching boxes overlap. Rows are indexed explicitly instead of sliced so that no array
    views are created on the hot path.
    """
    return (
        a[i, 0] - margin <= b[j, 3]
        and a[i, 1] - margin <= b[j, 4]
        and a[i, 2] - margin <= b[j, 5]
        and b[j, 0] <= a[i, 3] + margin
        and b[j, 1] <= a[i, 4] + margin
        and b[j, 2] <= a[i, 5] + margin
    )


@njit(cache=True)
def element_box_rows(points, cells):
    """Boxes (n, 6) = (lo xyz, hi xyz) of the elements ``cells`` (n, k) over ``points``."""
    n = cells.shape[0]
    k = cells.shape[1]
    box = np.empty((n, 6), dtype=points.dtype)
    for e in range(n):
        v = cells[e, 0]
        for d in range(3):
            box[e, d] = points[v, d]
            box[e, d + 3] = points[v, d]
        for j in range(1, k):
            v = cells[e, j]
            for d in range(3):
                c = points[v, d]
                if c < box[e, d]:
                    box[e, d] = c
                elif c > box[e, d + 3]:
                    box[e, d + 3] = c
    return box


@njit(cache=True)
def kept_pairs(pair_tri, pair_tet, keep, n_keep):
    """The pairs whose ``keep`` flag is set (``n_keep`` of them), in their order."""
    out_t = np.empty(n_keep, dtype=pair_tri.dtype)
    out_k = np.empty(n_keep, dtype=pair_tet.dtype)
    j = 0
    for p in range(keep.size):
        if keep[p]:
            out_t[j] = pair_tri[p]
            out_k[j] = pair_tet[p]
            j += 1
    return out_t, out_k


@njit(inline="always")
def share_vertex(a_cells, a, b_cells, b):
    """Whether row a of a_cells and row b of b_cells have a vertex number in common."""
    for i in range(a_cells.shape[1]):
        va = a_cells[a, i]
        for j in range(b_cells.shape[1]):
            if va == b_cells[b, j]:
                return True
    return False


@njit(cache=True)
def _exclude_shared_vertex_pairs(tri_cells, tet_cells, pair_tri, pair_tet):
    """Keep the (triangle, tetrahedron) pairs that share no vertex.

    Args:
        tri_cells: (nt, 3) triangle vertex indices.
        tet_cells: (nk, 4) tetrahedron vertex indices, same vertex numbering.
        pair_tri, pair_tet: (m,) candidate pairs (rows of tri_cells / tet_cells).

    Returns:
        The kept pairs (pair_tri, pair_tet), order preserved.
    """
    m = pair_tri.shape[0]
    keep = np.empty(m, dtype=np.bool_)
    n_keep = 0
    for p in range(m):
        shared = share_vertex(tri_cells, pair_tri[p], tet_cells, pair_tet[p])
        keep[p] = not shared
        if not shared:
            n_keep += 1
    return kept_pairs(pair_tri, pair_tet, keep, n_keep)


def as_points(points: np.ndarray) -> np.ndarray:
    p = np.ascontiguousarray(points, dtype=FLOAT)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must have shape (n, 3), got {p.shape}")
    return p


def element_boxes(points: np.ndarray, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned boxes of elements.

    Args:
        points: (nv, 3) vertex coordinates (L).
        cells: (n, k) vertex indices per element.

    Returns:
        (lo (n, 3), hi (n, 3)) box corners (L).
    """
    box = element_box_rows(as_points(points), np.ascontiguousarray(cells, dtype=INDEX))
    return box[:, :3].copy(), box[:, 3:].copy()


def exclude_shared_vertex_pairs(
    tri_cells: np.ndarray, tet_cells: np.ndarray, pair_tri: np.ndarray, pair_tet: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Drop (triangle, tetrahedron) candidate pairs that share a vertex.

    A boundary triangle always touches the tetrahedra around its own vertices; those pairs are
    not contacts (paper 4.3.1) and are removed here.

    Args:
        tri_cells: (nt, 3) triangle vertex indices.
        tet_cells: (nk, 4) tetrahedron vertex indices, same vertex numbering as tri_cells.
        pair_tri: (m,) triangle index of each pair.
        pair_tet: (m,) tetrahedron index of each pair.

    Returns:
        The pairs that share no vertex, (pair_tri, pair_tet), order preserved.
    """
    return _exclude_shared_vertex_pairs(
        np.ascontiguousarray(tri_cells, dtype=INDEX),
        np.ascontiguousarray(tet_cells, dtype=INDEX),
        np.ascontiguousarray(pair_tri, dtype=INDEX),
        np.ascontiguousarray(pair_tet, dtype=INDEX),
    )


def overlapping_pairs(
    points: np.ndarray,
    tri_cells: np.ndarray,
    tet_cells: np.ndarray,
    pair_tri: np.ndarray,
    pair_tet: np.ndarray,
) -> np.ndarray:
    """Which (triangle, tetrahedron) pairs have overlapping boxes now (closed boxes, no margin).

    The test of :meth:`~fenics_matdepth.geometry.bvh.AABBTree.query_boxes` with margin 0 on
    the same boxes, so that pairs found with a margin and filtered here are exactly those a
    search without margin finds.

    Args:
        points: (nv, 3) vertex coordinates (L).
        tri_cells: (nt, 3) triangle vertex indices.
        tet_cells: (nk, 4) tetrahedron vertex indices.
        pair_tri, pair_tet: (m,) the pairs.

    Returns:
        Indices of the overlapping pairs, in order.
    """
    points = as_points(points)
    return _overlapping_pairs(
        element_box_rows(points, np.ascontiguousarray(tri_cells, dtype=INDEX)),
        element_box_rows(points, np.ascontiguousarray(tet_cells, dtype=INDEX)),
        np.ascontiguousarray(pair_tri, dtype=INDEX),
        np.ascontiguousarray(pair_tet, dtype=INDEX),
    )


@njit(cache=True)
def _overlapping_pairs(tri_box, tet_box, pair_tri, pair_tet):
    keep = np.empty(pair_tri.shape[0], dtype=np.int64)
    m = 0
    for p in range(pair_tri.shape[0]):
        if rows_overlap(tri_box, pair_tri[p], tet_box, pair_tet[p], 0.0):
            keep[m] = p
            m += 1
    return keep[:m].copy()
