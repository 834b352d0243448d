"""Triangle-tetrahedron tests over many candidate pairs, built on the clipper of
`fenics_matdepth.geometry.clip`: the exact intersection test (`intersect_pairs`: non-empty
intersection polygon, the same decision as the clip of the pair kernels) and the conservative
proximity filter of the separating axis theorem (`near_pairs`).

Every kernel here is compiled with ``fastmath=False`` spelt out, as in
`fenics_matdepth.geometry.clip` (see there): the intersection test and the pair kernels must
agree on every pair, whichever caller compiles them first.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from fenics_matdepth._constants import FLOAT
from fenics_matdepth.geometry.boxes import kept_pairs
from fenics_matdepth.geometry.clip import (
    CLIP_TOL,
    MAX_POLYGON_VERTICES,
    TET_VOLUME_RTOL,
    area2_of,
    clip_nonempty,
    edges_normal_of,
    shift_of,
    tet_frame,
)

__all__ = ["intersect_pairs", "near_pairs"]


#: Pairs per block of `intersect_pairs`: gathered into a work array, then tested in one loop
#: that the compiler vectorises (4 pairs an instruction with AVX2).
_BLOCK = 64


#: Row offsets of that work array (row r of pair k at ``r * _BLOCK + k``): rows 0-8 the
#: triangle's corners, 9-20 the tetrahedron's, 21-32 the snapped rows ``lam[i, j]`` at
#: ``21 + 4 i + j``, 33 the decision. Unsigned, so that the compiler sees non-negative indices
#: (numba adds a wrap-around select to signed ones, which keeps the loop from vectorising).
_ROW = tuple(np.uint64(r * _BLOCK) for r in range(34))


@njit(cache=True, fastmath=False)
def _snapped_row_of(dx, dy, dz, g1x, g1y, g1z, g2x, g2y, g2z, g3x, g3y, g3z):
    """One corner's row of the clipper's `_shifted_rows` (``d`` its shifted offset from the
    tetrahedron's vertex 0, ``g`` the gradients of lambda 1 to 3), snapped as its `_snap`;
    scalars in and out."""
    v1 = g1x * dx + g1y * dy + g1z * dz
    v2 = g2x * dx + g2y * dy + g2z * dz
    v3 = g3x * dx + g3y * dy + g3z * dz
    v0 = 1.0 - (((0.0 + v1) + v2) + v3)
    tol = CLIP_TOL * (1.0 + abs(v0) + abs(v1) + abs(v2) + abs(v3))
    return (
        0.0 if abs(v0) <= tol else v0,
        0.0 if abs(v1) <= tol else v1,
        0.0 if abs(v2) <= tol else v2,
        0.0 if abs(v3) <= tol else v3,
    )


@njit(cache=True, error_model="numpy", fastmath=False)
def _decide_block(w, m):
    """The intersection test of `intersect_pairs` on the first m pairs of a work block ``w``,
    up to the clip: 0 (empty: zero-area triangle, flat tetrahedron or a separating face plane),
    1 (a corner strictly inside) or 2 (the clip decides, on the snapped rows also written).

    The operations of the clipper's `triangle_area2`, `_clip_shift`, `tet_gradients`,
    `_shifted_rows` and `_snap`, in the same order (hence the same values), on scalars and
    with selects instead of branches, so that the loop vectorises; the tests become sign tests
    of a min-max: a face plane separates where ``min_j max_i lam[i, j] < 0``, a corner is
    inside where ``max_i min_j lam[i, j] > 0``. A zero-area triangle or a flat tetrahedron
    gives infinite or NaN values here (the numpy error model: no exceptions), which are
    discarded.
    """
    for k in range(m):
        q = np.uint64(k)
        x0 = w[_ROW[0] + q]
        y0 = w[_ROW[1] + q]
        z0 = w[_ROW[2] + q]
        x1 = w[_ROW[3] + q]
        y1 = w[_ROW[4] + q]
        z1 = w[_ROW[5] + q]
        x2 = w[_ROW[6] + q]
        y2 = w[_ROW[7] + q]
        z2 = w[_ROW[8] + q]
        ax, ay, az, bx, by, bz, nx, ny, nz = edges_normal_of(x0, y0, z0, x1, y1, z1, x2, y2, z2)
        area2 = area2_of(ax, ay, az, bx, by, bz, nx, ny, nz, x2 - x1, y2 - y1, z2 - z1)
        sx, sy, sz = shift_of(ax, ay, az, nx, ny, nz)
        p0x = w[_ROW[9] + q]
        p0y = w[_ROW[10] + q]
        p0z = w[_ROW[11] + q]
        det, h2, g1x, g1y, g1z, g2x, g2y, g2z, g3x, g3y, g3z = tet_frame(
            p0x, p0y, p0z, w[_ROW[12] + q], w[_ROW[13] + q], w[_ROW[14] + q],
            w[_ROW[15] + q], w[_ROW[16] + q], w[_ROW[17] + q],
            w[_ROW[18] + q], w[_ROW[19] + q], w[_ROW[20] + q],
        )  # fmt: skip
        valid = (area2 != 0.0) & (abs(det) > TET_VOLUME_RTOL * h2 * np.sqrt(h2))
        inv = 1.0 / det
        g1x *= inv
        g1y *= inv
        g1z *= inv
        g2x *= inv
        g2y *= inv
        g2z *= inv
        g3x *= inv
        g3y *= inv
        g3z *= inv
        # the three corners' rows: `_shifted_rows`, then `_snap`
        l00, l01, l02, l03 = _snapped_row_of(
            (x0 - p0x) + sx, (y0 - p0y) + sy, (z0 - p0z) + sz,
            g1x, g1y, g1z, g2x, g2y, g2z, g3x, g3y, g3z,
        )  # fmt: skip
        l10, l11, l12, l13 = _snapped_row_of(
            (x1 - p0x) + sx, (y1 - p0y) + sy, (z1 - p0z) + sz,
            g1x, g1y, g1z, g2x, g2y, g2z, g3x, g3y, g3z,
        )  # fmt: skip
        l20, l21, l22, l23 = _snapped_row_of(
            (x2 - p0x) + sx, (y2 - p0y) + sy, (z2 - p0z) + sz,
            g1x, g1y, g1z, g2x, g2y, g2z, g3x, g3y, g3z,
        )  # fmt: skip
        w[_ROW[21] + q] = l00
        w[_ROW[22] + q] = l01
        w[_ROW[23] + q] = l02
        w[_ROW[24] + q] = l03
        w[_ROW[25] + q] = l10
        w[_ROW[26] + q] = l11
        w[_ROW[27] + q] = l12
        w[_ROW[28] + q] = l13
        w[_ROW[29] + q] = l20
        w[_ROW[30] + q] = l21
        w[_ROW[31] + q] = l22
        w[_ROW[32] + q] = l23
        separating = min(
            min(max(max(l00, l10), l20), max(max(l01, l11), l21)),
            min(max(max(l02, l12), l22), max(max(l03, l13), l23)),
        )
        inside = max(
            max(min(min(l00, l01), min(l02, l03)), min(min(l10, l11), min(l12, l13))),
            min(min(l20, l21), min(l22, l23)),
        )
        decided = 1.0 if inside > 0.0 else 2.0
        w[_ROW[33] + q] = decided if (valid & (separating >= 0.0)) else 0.0


@njit(cache=True, fastmath=False)
def intersect_pairs(x, tri, tet, pair_tri, pair_tet, out):
    """Intersection test for many pairs: ``out[p] = True`` where the polygon is non-empty.

    The decisions of `triangle_area2`, `tet_gradients`, `triangle_rows`, `_snap`, the
    separating face plane and the corner inside (as `clip_triangle`) and `clip_nonempty`. The pairs
    go in blocks of _BLOCK: their 7 vertices are gathered into a work array, `_decide_block`
    computes every pair's snapped rows and settles the pairs that need no clip in one
    vectorised loop, and `clip_nonempty` decides the rest, one by one.

    Args:
        x: (nv, 3) current vertex coordinates.
        tri: (nt, 3) boundary triangles (vertex indices).
        tet: (nk, 4) tetrahedra (vertex indices).
        pair_tri, pair_tet: (np,) candidate pairs.
        out: (np,) bool output.

    Returns:
        Number of intersecting pairs.
    """
    w = np.empty(34 * _BLOCK, dtype=FLOAT)
    lam = np.empty((3, 4), dtype=FLOAT)
    buf = np.empty((2, MAX_POLYGON_VERTICES, 4), dtype=FLOAT)
    count = 0
    n = pair_tri.shape[0]
    for start in range(0, n, _BLOCK):
        m = min(_BLOCK, n - start)
        for k in range(m):
            t = pair_tri[start + k]
            c = pair_tet[start + k]
            for a in range(3):
                v = tri[t, a]
                for r in range(3):
                    w[(3 * a + r) * _BLOCK + k] = x[v, r]
            for a in range(4):
                v = tet[c, a]
                for r in range(3):
                    w[(9 + 3 * a + r) * _BLOCK + k] = x[v, r]
        _decide_block(w, m)
        for k in range(m):
            decided = w[33 * _BLOCK + k]
            hit = decided == 1.0
            if decided == 2.0:
                for i in range(3):
                    for j in range(4):
                        lam[i, j] = w[(21 + 4 * i + j) * _BLOCK + k]
                hit = clip_nonempty(lam, buf)
            out[start + k] = hit
            count += hit
    return count


@njit(cache=True, fastmath=False)
def _axis_gap(xs, xt, nx, ny, nz):
    """Gap between the projections of triangle ``xs`` and tetrahedron ``xt`` on the axis n
    (length times |n|; negative when the projections overlap)."""
    t_lo = np.inf
    t_hi = -np.inf
    for a in range(3):
        d = xs[a, 0] * nx + xs[a, 1] * ny + xs[a, 2] * nz
        t_lo = min(t_lo, d)
        t_hi = max(t_hi, d)
    k_lo = np.inf
    k_hi = -np.inf
    for a in range(4):
        d = xt[a, 0] * nx + xt[a, 1] * ny + xt[a, 2] * nz
        k_lo = min(k_lo, d)
        k_hi = max(k_hi, d)
    return max(k_lo - t_hi, t_lo - k_hi)


@njit(cache=True, fastmath=False)
def near_pairs(x, tri, tet, pair_tri, pair_tet, gap):
    """The pairs that no separating axis holds more than ``gap`` apart (conservative).

    The axes are those of the separating axis theorem for a triangle and a tetrahedron: the
    triangle's normal, the four face normals and the 18 cross products of a triangle edge with
    a tetrahedron edge. A pair is dropped when the projections of the two on one axis are more
    than ``gap`` apart: they are then further apart than ``gap``. Every pair within ``gap`` is
    kept (and some slightly further apart, whose closest points are two vertices or a vertex
    and an edge, where the projected gap underestimates the distance).

    Args:
        x: (nv, 3) vertex coordinates (length).
        tri: (nt, 3) triangles; tet: (nk, 4) tetrahedra (vertex indices).
        pair_tri, pair_tet: (np,) candidate pairs.
        gap: distance (length) up to which pairs are kept.

    Returns:
        The kept pairs (pair_tri, pair_tet), order preserved.
    """
    m = pair_tri.shape[0]
    keep = np.empty(m, dtype=np.bool_)
    xt = np.empty((4, 3), dtype=FLOAT)
    xs = np.empty((3, 3), dtype=FLOAT)
    te = np.empty((6, 3), dtype=FLOAT)
    se = np.empty((3, 3), dtype=FLOAT)
    tet_edges = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))
    faces = ((1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2))
    n_keep = 0
    for p in range(m):
        for a in range(4):
            for r in range(3):
                xt[a, r] = x[tet[pair_tet[p], a], r]
        for a in range(3):
            for r in range(3):
                xs[a, r] = x[tri[pair_tri[p], a], r]
        for e in range(6):
            for r in range(3):
                te[e, r] = xt[tet_edges[e][1], r] - xt[tet_edges[e][0], r]
        for e in range(3):
            for r in range(3):
                se[e, r] = xs[(e + 1) % 3, r] - xs[e, r]
        separated = False
        # triangle normal (edges 0 x 1) and face normals (edges of each face)
        for f in range(5):
            if f == 0:
                ax, ay, az = se[0, 0], se[0, 1], se[0, 2]
                bx, by, bz = se[1, 0], se[1, 1], se[1, 2]
            else:
                i0, i1, i2 = faces[f - 1]
                ax = xt[i1, 0] - xt[i0, 0]
                ay = xt[i1, 1] - xt[i0, 1]
                az = xt[i1, 2] - xt[i0, 2]
                bx = xt[i2, 0] - xt[i0, 0]
                by = xt[i2, 1] - xt[i0, 1]
                bz = xt[i2, 2] - xt[i0, 2]
            nx = ay * bz - az * by
            ny = az * bx - ax * bz
            nz = ax * by - ay * bx
            norm = np.sqrt(nx * nx + ny * ny + nz * nz)
            if norm > 0.0 and _axis_gap(xs, xt, nx, ny, nz) > gap * norm:
                separated = True
                break
        if not separated:
            for e in range(3):
                for f in range(6):
                    nx = se[e, 1] * te[f, 2] - se[e, 2] * te[f, 1]
                    ny = se[e, 2] * te[f, 0] - se[e, 0] * te[f, 2]
                    nz = se[e, 0] * te[f, 1] - se[e, 1] * te[f, 0]
                    norm = np.sqrt(nx * nx + ny * ny + nz * nz)
                    if norm > 0.0 and _axis_gap(xs, xt, nx, ny, nz) > gap * norm:
                        separated = True
                        break
                if separated:
                    break
        keep[p] = not separated
        if keep[p]:
            n_keep += 1
    return kept_pairs(pair_tri, pair_tet, keep, n_keep)
