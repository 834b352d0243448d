"""Exact point-triangle distance and nearest-triangle helpers (numba).

The closest point on a triangle is found by the Voronoi-region classification of the point
against the triangle's vertices, edges and face (the barycentric form used in real-time
collision detection): no square roots, no tolerance, exact up to floating-point rounding, and
exactly zero when the point coincides with a triangle vertex (which the material depth relies
on: boundary vertices must get depth 0).

All coordinates are in the caller's length unit; distances come back in that unit (squared
distances in that unit squared).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from fenics_matdepth._constants import FLOAT, INDEX

__all__ = [
    "point_box_dist2",
    "point_triangle_dist2",
    "nearest_triangle_bruteforce",
    "point_triangle_closest_point",
    "point_triangle_distance",
]


@njit(inline="always")
def _closest_point_segment(px, py, pz, ax, ay, az, bx, by, bz):
    """Closest point of segment [a, b] to p (a zero-length segment gives a)."""
    abx, aby, abz = bx - ax, by - ay, bz - az
    ll = abx * abx + aby * aby + abz * abz
    if ll <= 0.0:
        return ax, ay, az
    t = ((px - ax) * abx + (py - ay) * aby + (pz - az) * abz) / ll
    t = min(max(t, 0.0), 1.0)
    return ax + t * abx, ay + t * aby, az + t * abz


@njit(inline="always")
def _closest_point_degenerate(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):
    """Closest point of a zero-area triangle: the nearest of its three edges."""
    qx, qy, qz = _closest_point_segment(px, py, pz, ax, ay, az, bx, by, bz)
    best = (px - qx) ** 2 + (py - qy) ** 2 + (pz - qz) ** 2
    rx, ry, rz = _closest_point_segment(px, py, pz, bx, by, bz, cx, cy, cz)
    d = (px - rx) ** 2 + (py - ry) ** 2 + (pz - rz) ** 2
    if d < best:
        qx, qy, qz, best = rx, ry, rz, d
    rx, ry, rz = _closest_point_segment(px, py, pz, cx, cy, cz, ax, ay, az)
    d = (px - rx) ** 2 + (py - ry) ** 2 + (pz - rz) ** 2
    if d < best:
        qx, qy, qz = rx, ry, rz
    return qx, qy, qz


@njit(inline="always")
def _closest_point_triangle(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):
    """Closest point of triangle (a, b, c) to p, as a 3-tuple of floats.

    Classifies p into the Voronoi region of a vertex, an edge or the face using the signs of
    dot products. A zero denominator only happens for zero-area triangles, which are handed to
    an edge-wise search so the result stays exact and finite.
    """
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        return ax, ay, az
    bpx, bpy, bpz = px - bx, py - by, pz - bz
    d3 = abx * bpx + aby * bpy + abz * bpz
    d4 = acx * bpx + acy * bpy + acz * bpz
    if d3 >= 0.0 and d4 <= d3:
        return bx, by, bz
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0 and d1 - d3 > 0.0:
        v = d1 / (d1 - d3)
        return ax + v * abx, ay + v * aby, az + v * abz
    cpx, cpy, cpz = px - cx, py - cy, pz - cz
    d5 = abx * cpx + aby * cpy + abz * cpz
    d6 = acx * cpx + acy * cpy + acz * cpz
    if d6 >= 0.0 and d5 <= d6:
        return cx, cy, cz
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0 and d2 - d6 > 0.0:
        w = d2 / (d2 - d6)
        return ax + w * acx, ay + w * acy, az + w * acz
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0 and (d4 - d3) + (d5 - d6) > 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return bx + w * (cx - bx), by + w * (cy - by), bz + w * (cz - bz)
    denom = va + vb + vc
    if not denom > 0.0:
        return _closest_point_degenerate(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz)
    inv = 1.0 / denom
    v = vb * inv
    w = vc * inv
    return (
        ax + abx * v + acx * w,
        ay + aby * v + acy * w,
        az + abz * v + acz * w,
    )


@njit(inline="always")
def point_triangle_dist2(p, x, i0, i1, i2):
    """Squared distance from point p (3,) to the triangle with vertex rows i0, i1, i2 of x."""
    qx, qy, qz = _closest_point_triangle(
        p[0], p[1], p[2],
        x[i0, 0], x[i0, 1], x[i0, 2],
        x[i1, 0], x[i1, 1], x[i1, 2],
        x[i2, 0], x[i2, 1], x[i2, 2],
    )  # fmt: skip
    dx, dy, dz = p[0] - qx, p[1] - qy, p[2] - qz
    return dx * dx + dy * dy + dz * dz


@njit(inline="always")
def point_box_dist2(p, lo, hi):
    """Squared distance from point p (3,) to the box [lo, hi] (0 inside)."""
    d2 = 0.0
    for k in range(3):
        if p[k] < lo[k]:
            t = lo[k] - p[k]
            d2 += t * t
        elif p[k] > hi[k]:
            t = p[k] - hi[k]
            d2 += t * t
    return d2


@njit(cache=True)
def _closest_points_triangles(points, tri_x):
    """Closest point on triangle i to point i, for every i.

    Args:
        points: (n, 3) query points.
        tri_x: (n, 3, 3) triangle vertex coordinates.

    Returns:
        (n, 3) closest points.
    """
    n = points.shape[0]
    out = np.empty((n, 3), dtype=points.dtype)
    for i in range(n):
        t = tri_x[i]
        qx, qy, qz = _closest_point_triangle(
            points[i, 0], points[i, 1], points[i, 2],
            t[0, 0], t[0, 1], t[0, 2],
            t[1, 0], t[1, 1], t[1, 2],
            t[2, 0], t[2, 1], t[2, 2],
        )  # fmt: skip
        out[i, 0] = qx
        out[i, 1] = qy
        out[i, 2] = qz
    return out


@njit(cache=True)
def _nearest_triangle_bruteforce(points, x, triangles):
    """Nearest triangle to each point by checking every triangle: O(n_points * n_triangles).

    Reference implementation for tests and tiny inputs.

    Returns:
        (index (n,), squared distance (n,)).
    """
    n = points.shape[0]
    idx = np.full(n, -1, dtype=np.int64)
    best = np.full(n, np.inf, dtype=x.dtype)
    for i in range(n):
        p = points[i]
        for t in range(triangles.shape[0]):
            d2 = point_triangle_dist2(p, x, triangles[t, 0], triangles[t, 1], triangles[t, 2])
            if d2 < best[i]:
                best[i] = d2
                idx[i] = t
    return idx, best


def point_triangle_closest_point(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Closest point on each triangle to the matching point.

    Args:
        points: (3,) or (n, 3) points (length unit L).
        triangles: (3, 3) or (n, 3, 3) triangle vertex coordinates, one vertex per row (L).

    Returns:
        Closest points, (3,) or (n, 3) (L).
    """
    p = np.ascontiguousarray(points, dtype=FLOAT)
    t = np.ascontiguousarray(triangles, dtype=FLOAT)
    single = p.ndim == 1
    p = p.reshape(-1, 3)
    t = t.reshape(-1, 3, 3)
    if p.shape[0] != t.shape[0]:
        raise ValueError(
            f"got {p.shape[0]} points and {t.shape[0]} triangles: pass one triangle per point"
        )
    q = _closest_points_triangles(p, t)
    return q[0] if single else q


def point_triangle_distance(points: np.ndarray, triangles: np.ndarray) -> np.ndarray | float:
    """Exact Euclidean distance from each point to the matching triangle.

    Args:
        points: (3,) or (n, 3) points (length unit L).
        triangles: (3, 3) or (n, 3, 3) triangle vertex coordinates (L).

    Returns:
        The distances (L), a float for a single point, else an (n,) array.
    """
    p = np.asarray(points, dtype=FLOAT)
    q = point_triangle_closest_point(p, triangles)
    d = np.linalg.norm(p.reshape(-1, 3) - q.reshape(-1, 3), axis=1)
    return float(d[0]) if p.ndim == 1 else d


def nearest_triangle_bruteforce(
    points: np.ndarray, x: np.ndarray, triangles: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest triangle to each point, checking all triangles (reference, O(n m)).

    Args:
        points: (n, 3) query points (L).
        x: (m, 3) vertex coordinates (L).
        triangles: (k, 3) vertex indices into ``x``.

    Returns:
        (index of the nearest triangle (n,), distance (n,) in L); index -1 and distance inf
        when there are no triangles.
    """
    p = np.ascontiguousarray(points, dtype=FLOAT).reshape(-1, 3)
    xx = np.ascontiguousarray(x, dtype=FLOAT).reshape(-1, 3)
    tri = np.ascontiguousarray(triangles, dtype=INDEX).reshape(-1, 3)
    idx, d2 = _nearest_triangle_bruteforce(p, xx, tri)
    return idx, np.sqrt(d2)
