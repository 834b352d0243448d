"""Continuous collision detection (CCD) of boundary primitives on linear trajectories (numba).

Two primitive pairs are tested: a vertex against a triangle, and an edge against an edge.
Every vertex moves on the straight line from its position ``x0`` (time 0) to ``x1`` (time 1).

Method: conservative advancement on the exact distance (the additive CCD of Li et al. 2021,
"Codimensional incremental potential contact", simplified). Along the trajectories the
distance ``d(t)`` between the two primitives changes no faster than ``l``, the largest
relative displacement of a point of one primitive against a point of the other, which for
linear motion is ``max_ij |dx_i - dy_j|`` over the vertex displacements of the two primitives
(the closest points are convex combinations of the vertices, and a minimum of l-Lipschitz
functions is l-Lipschitz). So no contact closer than ``s`` happens before ``t + (d - s) / l``;
the advancement steps by ``ADVANCE`` of that until the distance has come within a tolerance of
``s`` (an impact: the time returned is never later than the true one) or the step's end is
reached (none). Only distances are evaluated: parallel edges, coplanar motion and a vertex on
an edge need no special case.

The *entry cap* of a pair (:func:`entry_fraction`) is the fraction of the step that keeps the
pair from going deeper than an entry tolerance ``e`` past its first contact: once the
advancement stops at time t with distance d, the primitives cannot touch before ``t + d / l``
nor be more than ``e`` past their contact point before ``t + (d + e) / l``.

*Pass-through* (:func:`exit_fraction`): a vertex behind the plane of a triangle (inside that
body) is free to move, except out through a triangle whose outward normal points the way the
vertex's own surface does (``n_v . n_T > ALIGNED``): that is the far side of the body it
entered, as the face of a thin layer opposite the one a surface came in by. Its crossing of the
moving triangle is found exactly, as the first root of the cubic signed volume
``det(x_1 - x_0, x_2 - x_0, x_v - x_0)(t)`` at which the vertex projects into the triangle;
only vertices more than ``EXIT_DEPTH`` entry tolerances behind the plane are tested, and the
step is capped before they come that close (by ``EXIT_MARGIN`` entry tolerances, or half their
height beyond it where that is less). Unlike an entry, leaving is never allowed past that
level, so a vertex held against the far face step after step stays inside; a vertex on the
plane of a face (flush side faces of two bodies) is free.

Lengths are in the unit of the coordinates; times are fractions of the step, in [0, 1].
"""

from __future__ import annotations

import numpy as np
from numba import njit

from fenics_matdepth._constants import FLOAT, INDEX
from fenics_matdepth.geometry.distance import point_triangle_dist2

__all__ = [
    "ADVANCE",
    "ALIGNED",
    "EXIT_DEPTH",
    "EXIT_MARGIN",
    "MAX_ADVANCES",
    "PASS_THROUGH",
    "edge_edge_time_of_impact",
    "entry_fraction",
    "exit_fraction",
    "sweep_caps",
    "vertex_triangle_time_of_impact",
]

#: Fraction of the guaranteed-safe advance taken per step of the conservative advancement
#: (below 1, so rounding never carries the primitives into contact).
ADVANCE = 0.9

#: Largest number of advancement steps per pair; the time reached so far is returned after it
#: (still conservative). A head-on approach needs about log(d0 / tol) / log(10) steps, a
#: grazing one about l / (ADVANCE tol).
MAX_ADVANCES = 200

#: Kinds of primitive pairs: rows 0..3 of the (4, 3) coordinate blocks are the vertex, then
#: the triangle (VERTEX_TRIANGLE), or the first edge, then the second (EDGE_EDGE).
#: PASS_THROUGH: a vertex leaving a body through a triangle that faces its way (the vertex,
#: then the triangle).
VERTEX_TRIANGLE = 0
EDGE_EDGE = 1
PASS_THROUGH = 2

#: A vertex behind a triangle's plane may not leave through it when the cosine between the
#: vertex's surface normal and the triangle's exceeds this: the two surfaces face the same way,
#: so the vertex came in from the body's other side (60°: a surface sliding off a body's edge
#: and out through its side face, at about 90°, is free).
ALIGNED = 0.5

#: A vertex is tested for leaving through a triangle only when it is more than this fraction
#: of the entry tolerance behind the triangle's plane, and is stopped before it comes that
#: close: a vertex on (or within rounding of) the plane of a face, as the edge of a body
#: pressed onto another whose side faces are flush with its own, slides and leaves freely.
EXIT_DEPTH = 0.25

#: A vertex stopped short of leaving through a triangle stays behind the plane by the exit
#: depth plus half its height beyond it, or plus this fraction of the entry tolerance where
#: that is less.
EXIT_MARGIN = 1e-3

#: A crossing counts where the vertex projects into the triangle grown by this fraction of
#: its size (barycentric coordinates >= -BARY_SLACK): a vertex leaving exactly through an edge
#: between two triangles is caught by both.
BARY_SLACK = 1e-3


@njit(inline="always")
def _segment_dist2(x, a, b, c, d):
    """Squared distance between segments [x[a], x[b]] and [x[c], x[d]] (any may be a point;
    parallel segments included), by the clamped closest points of Ericson's Real-Time
    Collision Detection, 5.1.9."""
    d1x, d1y, d1z = x[b, 0] - x[a, 0], x[b, 1] - x[a, 1], x[b, 2] - x[a, 2]
    d2x, d2y, d2z = x[d, 0] - x[c, 0], x[d, 1] - x[c, 1], x[d, 2] - x[c, 2]
    rx, ry, rz = x[a, 0] - x[c, 0], x[a, 1] - x[c, 1], x[a, 2] - x[c, 2]
    aa = d1x * d1x + d1y * d1y + d1z * d1z
    ee = d2x * d2x + d2y * d2y + d2z * d2z
    f = d2x * rx + d2y * ry + d2z * rz
    tiny = 1e-300
    if aa <= tiny and ee <= tiny:
        s = 0.0
        t = 0.0
    elif aa <= tiny:
        s = 0.0
        t = min(max(f / ee, 0.0), 1.0)
    else:
        c1 = d1x * rx + d1y * ry + d1z * rz
        if ee <= tiny:
            t = 0.0
            s = min(max(-c1 / aa, 0.0), 1.0)
        else:
            bb = d1x * d2x + d1y * d2y + d1z * d2z
            denom = aa * ee - bb * bb
            # parallel segments (denom 0, or rounding-small): any s, here 0, then clamp t
            s = min(max((bb * f - c1 * ee) / denom, 0.0), 1.0) if denom > 1e-14 * aa * ee else 0.0
            t = (bb * s + f) / ee
            if t < 0.0:
                t = 0.0
                s = min(max(-c1 / aa, 0.0), 1.0)
            elif t > 1.0:
                t = 1.0
                s = min(max((bb - c1) / aa, 0.0), 1.0)
    px = x[a, 0] + d1x * s - x[c, 0] - d2x * t
    py = x[a, 1] + d1y * s - x[c, 1] - d2y * t
    pz = x[a, 2] + d1z * s - x[c, 2] - d2z * t
    return px * px + py * py + pz * pz


# The pair-level helpers below (_distance, _advance, _entry_cap, _primitive_cap) are compiled
# once each (cache=True) and called, not inlined into the drivers: inlining them at numba's IR
# level put a dozen copies of the two distance routines into _sweep_caps, whose first
# compilation then took minutes (1,050 s against 146 s for both drivers, measured on a loaded
# machine; in CPU time, benchmarks/bench_ccd.py's whole first run took 160 s inlined against
# 35 s called); LLVM still inlines the calls where it pays, and the query time is unchanged.


@njit(cache=True)
def _distance(kind, xs):
    """Distance of the pair whose (4, 3) coordinates are ``xs``."""
    if kind == VERTEX_TRIANGLE:
        return np.sqrt(point_triangle_dist2(xs[0], xs, 1, 2, 3))
    return np.sqrt(_segment_dist2(xs, 0, 1, 2, 3))


@njit(inline="always")
def _motion_bound(kind, x0, x1):
    """Bound l of the rate of change of the pair's distance (L per step)."""
    first = 1 if kind == VERTEX_TRIANGLE else 2
    bound = 0.0
    for i in range(first):
        for j in range(first, 4):
            s = 0.0
            for k in range(3):
                r = (x1[i, k] - x0[i, k]) - (x1[j, k] - x0[j, k])
                s += r * r
            bound = max(bound, s)
    return np.sqrt(bound)


@njit(inline="always")
def _at(x0, x1, t, xs):
    for i in range(4):
        for k in range(3):
            xs[i, k] = x0[i, k] + t * (x1[i, k] - x0[i, k])


@njit(cache=True)
def _advance(kind, x0, x1, xs, stop, tol, max_steps):
    """Conservative advancement to distance ``stop`` (see the module doc).

    Returns:
        (t, d, l, hit): the time reached, the distance there, the motion bound; hit False
        where the distance stays above ``stop`` over the whole step (t = 1).
    """
    lip = _motion_bound(kind, x0, x1)
    _at(x0, x1, 0.0, xs)
    d = _distance(kind, xs)
    if not (lip > 0.0 and np.isfinite(lip) and np.isfinite(d)):
        return 1.0, d, lip, False
    t = 0.0
    for _ in range(max_steps):
        if d - stop <= tol:
            return t, d, lip, True
        t_next = t + ADVANCE * (d - stop) / lip
        if t_next >= 1.0:
            # (d - stop) / lip >= 1 - t: the distance stays above stop to the step's end
            return 1.0, d, lip, False
        t = t_next
        _at(x0, x1, t, xs)
        d = _distance(kind, xs)
    return t, d, lip, True


@njit(cache=True)
def _entry_cap(kind, x0, x1, xs, entry, max_steps):
    """Entry cap of one pair (the module doc): 1 where the pair starts within ``entry``."""
    _at(x0, x1, 0.0, xs)
    if _distance(kind, xs) <= entry:
        return 1.0
    t, d, lip, hit = _advance(kind, x0, x1, xs, 0.0, 0.5 * entry, max_steps)
    if not hit:
        return 1.0
    return min(1.0, t + (d + entry) / lip)


@njit(inline="always")
def _signed_volume(x0, x1, t, xs):
    """det(x_2 - x_1, x_3 - x_1, x_0 - x_1) at time t of the (4, 3) blocks (vertex, then
    triangle): the vertex's height over the triangle's plane times twice its area (positive
    in front); ``xs`` is scratch."""
    _at(x0, x1, t, xs)
    e1x, e1y, e1z = xs[2, 0] - xs[1, 0], xs[2, 1] - xs[1, 1], xs[2, 2] - xs[1, 2]
    e2x, e2y, e2z = xs[3, 0] - xs[1, 0], xs[3, 1] - xs[1, 1], xs[3, 2] - xs[1, 2]
    rx, ry, rz = xs[0, 0] - xs[1, 0], xs[0, 1] - xs[1, 1], xs[0, 2] - xs[1, 2]
    return (
        (e1y * e2z - e1z * e2y) * rx + (e1z * e2x - e1x * e2z) * ry + (e1x * e2y - e1y * e2x) * rz
    )


@njit(inline="always")
def _projects_inside(x0, x1, t, xs, slack):
    """Whether the vertex's projection on the triangle's plane at time t lies in the triangle
    grown by ``slack`` (barycentric coordinates >= -slack)."""
    _at(x0, x1, t, xs)
    d00 = d01 = d11 = d20 = d21 = 0.0
    for k in range(3):
        e0 = xs[2, k] - xs[1, k]
        e1 = xs[3, k] - xs[1, k]
        r = xs[0, k] - xs[1, k]
        d00 += e0 * e0
        d01 += e0 * e1
        d11 += e1 * e1
        d20 += r * e0
        d21 += r * e1
    denom = d00 * d11 - d01 * d01
    if not denom > 0.0:
        return False
    lb = (d11 * d20 - d01 * d21) / denom
    lc = (d00 * d21 - d01 * d20) / denom
    return lb >= -slack and lc >= -slack and 1.0 - lb - lc >= -slack


@njit(inline="always")
def _cubic(c0, c1, c2, c3, t):
    return c0 + t * (c1 + t * (c2 + t * c3))


@njit(inline="always")
def _area2(x0, x1, t, xs):
    """Twice the area of the triangle (rows 1-3 of the blocks) at time t."""
    _at(x0, x1, t, xs)
    e1x, e1y, e1z = xs[2, 0] - xs[1, 0], xs[2, 1] - xs[1, 1], xs[2, 2] - xs[1, 2]
    e2x, e2y, e2z = xs[3, 0] - xs[1, 0], xs[3, 1] - xs[1, 1], xs[3, 2] - xs[1, 2]
    return np.sqrt(
        (e1y * e2z - e1z * e2y) ** 2 + (e1z * e2x - e1x * e2z) ** 2 + (e1x * e2y - e1y * e2x) ** 2
    )


@njit(cache=True)
def _exit_cap(x0, x1, xs, depth, margin):
    """The fraction of the step before the vertex (row 0 of the (4, 3) blocks), more than
    ``depth`` (L) behind the plane of the triangle (rows 1-3) at the start, could come within
    ``depth`` of it on its way out through the triangle (1: it does not within the step, or
    it starts within ``depth``); there it is still more than ``depth`` behind, by ``margin``
    or half its start height beyond ``depth``, whichever is less (module doc).

    The signed volume is a cubic in t, interpolated from four values; its monotone pieces
    (between the roots of its derivative) are searched in order for a rise through the stop
    level (a height, times the triangle's doubled area at the start), bisected, and the first
    rise where the vertex projects into the triangle caps the step at the bracket's lower end
    (or, where the triangle's area has grown so that the height there is too small, at the
    height's own crossing of the level halfway, bisected).
    """
    f0 = _signed_volume(x0, x1, 0.0, xs)
    area0 = _area2(x0, x1, 0.0, xs)
    if not (area0 > 0.0 and -f0 > depth * area0):
        return 1.0
    height0 = -f0 / area0
    shift = (depth + min(margin, 0.5 * (height0 - depth))) * area0
    f1 = _signed_volume(x0, x1, 1.0 / 3.0, xs)
    f2 = _signed_volume(x0, x1, 2.0 / 3.0, xs)
    f3 = _signed_volume(x0, x1, 1.0, xs)
    # g(t) = f(t) + shift = c0 + c1 t + c2 t^2 + c3 t^3, from forward differences (s = 3 t)
    d1, d2, d3 = f1 - f0, f2 - 2.0 * f1 + f0, f3 - 3.0 * f2 + 3.0 * f1 - f0
    c0 = f0 + shift
    c1 = 3.0 * (d1 - 0.5 * d2 + d3 / 3.0)
    c2 = 4.5 * (d2 - d3)
    c3 = 4.5 * d3
    # break points: 0, the roots of g' = c1 + 2 c2 t + 3 c3 t^2 inside (0, 1) in order, 1
    qa, qb, qc = 3.0 * c3, 2.0 * c2, c1
    scale = abs(qa) + abs(qb) + abs(qc)
    r0, r1 = 2.0, 2.0
    if abs(qa) > 1e-14 * scale:
        disc = qb * qb - 4.0 * qa * qc
        if disc >= 0.0:
            q = -0.5 * (qb + np.sqrt(disc)) if qb >= 0.0 else -0.5 * (qb - np.sqrt(disc))
            r0 = q / qa
            r1 = qc / q if q != 0.0 else 2.0
    elif abs(qb) > 1e-14 * scale:
        r0 = -qc / qb
    if r1 < r0:
        r0, r1 = r1, r0
    lo = 0.0
    for piece in range(3):
        hi = r0 if piece == 0 else (r1 if piece == 1 else 1.0)
        if not (lo < hi <= 1.0):
            continue
        a, b = lo, hi
        lo = hi
        if not (_cubic(c0, c1, c2, c3, a) < 0.0 <= _cubic(c0, c1, c2, c3, b)):
            continue
        for _ in range(64):  # bisection to rounding, keeping g(a) < 0 <= g(b)
            mid = 0.5 * (a + b)
            if not (a < mid < b):
                break
            if _cubic(c0, c1, c2, c3, mid) < 0.0:
                a = mid
            else:
                b = mid
        if _projects_inside(x0, x1, b, xs, BARY_SLACK):
            # the stop level was set with the start's area: where the area has grown, the
            # height at a may be below depth; then bisect the height itself over [0, a] for a
            # time where it is above depth by half the intended margin
            level = depth + 0.5 * (shift / area0 - depth)
            if -_signed_volume(x0, x1, a, xs) > level * _area2(x0, x1, a, xs):
                return a
            lo2, hi2 = 0.0, a
            for _ in range(64):
                mid = 0.5 * (lo2 + hi2)
                if not (lo2 < mid < hi2):
                    break
                if -_signed_volume(x0, x1, mid, xs) > level * _area2(x0, x1, mid, xs):
                    lo2 = mid
                else:
                    hi2 = mid
            return lo2
    return 1.0


@njit(cache=True)
def _vertex_normals(x, tri, nv):
    """Unit area-weighted normals (nv, in place) of the vertices of the outward triangles
    ``tri`` at positions ``x`` (zero for a vertex of no triangle)."""
    nv[:] = 0.0
    for f in range(tri.shape[0]):
        a, b, c = tri[f, 0], tri[f, 1], tri[f, 2]
        e1x, e1y, e1z = x[b, 0] - x[a, 0], x[b, 1] - x[a, 1], x[b, 2] - x[a, 2]
        e2x, e2y, e2z = x[c, 0] - x[a, 0], x[c, 1] - x[a, 1], x[c, 2] - x[a, 2]
        nx = e1y * e2z - e1z * e2y
        ny = e1z * e2x - e1x * e2z
        nz = e1x * e2y - e1y * e2x
        for j in range(3):
            w = tri[f, j]
            nv[w, 0] += nx
            nv[w, 1] += ny
            nv[w, 2] += nz
    for w in range(nv.shape[0]):
        s = np.sqrt(nv[w, 0] ** 2 + nv[w, 1] ** 2 + nv[w, 2] ** 2)
        if s > 0.0:
            nv[w, 0] /= s
            nv[w, 1] /= s
            nv[w, 2] /= s


@njit(inline="always")
def _facing_cosine(x0, nv, v, a, b, c):
    """Cosine between vertex v's unit normal and the normal of triangle (a, b, c)."""
    e1x, e1y, e1z = x0[b, 0] - x0[a, 0], x0[b, 1] - x0[a, 1], x0[b, 2] - x0[a, 2]
    e2x, e2y, e2z = x0[c, 0] - x0[a, 0], x0[c, 1] - x0[a, 1], x0[c, 2] - x0[a, 2]
    nx = e1y * e2z - e1z * e2y
    ny = e1z * e2x - e1x * e2z
    nz = e1x * e2y - e1y * e2x
    s = np.sqrt(nx * nx + ny * ny + nz * nz)
    if not s > 0.0:
        return 0.0
    return (nv[v, 0] * nx + nv[v, 1] * ny + nv[v, 2] * nz) / s


@njit(inline="always")
def _inner_side(x0, p, a, b, c):
    """Whether vertex row p of x0 lies strictly behind the plane of the (outward-oriented)
    triangle (a, b, c)."""
    e1x, e1y, e1z = x0[b, 0] - x0[a, 0], x0[b, 1] - x0[a, 1], x0[b, 2] - x0[a, 2]
    e2x, e2y, e2z = x0[c, 0] - x0[a, 0], x0[c, 1] - x0[a, 1], x0[c, 2] - x0[a, 2]
    nx = e1y * e2z - e1z * e2y
    ny = e1z * e2x - e1x * e2z
    nz = e1x * e2y - e1y * e2x
    rx, ry, rz = x0[p, 0] - x0[a, 0], x0[p, 1] - x0[a, 1], x0[p, 2] - x0[a, 2]
    return nx * rx + ny * ry + nz * rz < 0.0


@njit(cache=True)
def _pairs(kind, x0, x1, caps, entry, min_distance, tol, max_steps):
    """Per pair of the (n, 4, 3) coordinate blocks: the entry cap (``caps``; tolerance
    ``entry[i]``) or the time of impact at ``min_distance`` (inf: none)."""
    n = x0.shape[0]
    out = np.empty(n, dtype=x0.dtype)
    xs = np.empty((4, 3), dtype=x0.dtype)
    for i in range(n):
        if caps:
            out[i] = _entry_cap(kind, x0[i], x1[i], xs, entry[i], max_steps)
        else:
            t, _, _, hit = _advance(kind, x0[i], x1[i], xs, min_distance, tol, max_steps)
            out[i] = t if hit else np.inf
    return out


@njit(inline="always")
def _gather4(x, i0, i1, i2, i3, out):
    for k in range(3):
        out[0, k] = x[i0, k]
        out[1, k] = x[i1, k]
        out[2, k] = x[i2, k]
        out[3, k] = x[i3, k]


@njit(cache=True)
def _primitive_cap(kind, x0, x1, i0, i1, i2, i3, blk0, blk1, xs, entry, max_steps):
    """Entry cap of the pair of rows (i0, i1, i2, i3) of the positions ``x0``, ``x1`` (the
    vertex and the triangle, or the two edges), through the scratch blocks."""
    _gather4(x0, i0, i1, i2, i3, blk0)
    _gather4(x1, i0, i1, i2, i3, blk1)
    return _entry_cap(kind, blk0, blk1, xs, entry, max_steps)


@njit(cache=True)
def _sweep_caps(x0, x1, tri, tri_edge, edges, vertex_owner, edge_owner, entry, pair_a, pair_b,
                max_steps, exits):  # fmt: skip
    """The smallest entry cap over the primitive pairs of the triangle pairs (a, b).

    Each vertex is tested against triangle a from its owner triangle b only, each edge pair
    from the owner triangles of its edges with a < b only, so a primitive pair is tested once
    when every ordered pair of overlapping triangles is given once. A vertex behind the plane
    of a (the triangles point outwards) is inside or leaving, not entering: with ``exits``, it
    is tested for leaving through a when its surface faces the way a does (the exit cap,
    kind PASS_THROUGH), otherwise not tested. Pairs sharing a vertex are not tested.

    Returns:
        (smallest cap, number of pairs capped below 1, the pair kind and the two primitive
        indices of the smallest cap (vertex, triangle) or (edge, edge); -1 for none).
    """
    nv = np.zeros((x0.shape[0] if exits else 0, 3), dtype=x0.dtype)
    if exits:
        _vertex_normals(x0, tri, nv)
    blk0 = np.empty((4, 3), dtype=x0.dtype)
    blk1 = np.empty((4, 3), dtype=x0.dtype)
    xs = np.empty((4, 3), dtype=x0.dtype)
    best = 1.0
    capped = 0
    which = (-1, -1, -1)
    for q in range(pair_a.shape[0]):
        a = pair_a[q]
        b = pair_b[q]
        if a == b:
            continue
        ta0, ta1, ta2 = tri[a, 0], tri[a, 1], tri[a, 2]
        e = min(entry[a], entry[b])
        for j in range(3):
            v = tri[b, j]
            if vertex_owner[v] != b or v == ta0 or v == ta1 or v == ta2:
                continue
            if _inner_side(x0, v, ta0, ta1, ta2):
                if not (exits and _facing_cosine(x0, nv, v, ta0, ta1, ta2) > ALIGNED):
                    continue
                _gather4(x0, v, ta0, ta1, ta2, blk0)
                _gather4(x1, v, ta0, ta1, ta2, blk1)
                cap = _exit_cap(blk0, blk1, xs, EXIT_DEPTH * e, EXIT_MARGIN * e)
                if cap < 1.0:
                    capped += 1
                    if cap < best:
                        best = cap
                        which = (PASS_THROUGH, v, a)
                continue
            cap = _primitive_cap(VERTEX_TRIANGLE, x0, x1, v, ta0, ta1, ta2, blk0, blk1, xs, e,
                                 max_steps)  # fmt: skip
            if cap < 1.0:
                capped += 1
                if cap < best:
                    best = cap
                    which = (VERTEX_TRIANGLE, v, a)
        if a > b:
            continue
        for i in range(3):
            ea = tri_edge[a, i]
            if edge_owner[ea] != a:
                continue
            p0, p1 = edges[ea, 0], edges[ea, 1]
            for j in range(3):
                eb = tri_edge[b, j]
                if edge_owner[eb] != b:
                    continue
                q0, q1 = edges[eb, 0], edges[eb, 1]
                if p0 == q0 or p0 == q1 or p1 == q0 or p1 == q1:
                    continue
                cap = _primitive_cap(EDGE_EDGE, x0, x1, p0, p1, q0, q1, blk0, blk1, xs, e,
                                     max_steps)  # fmt: skip
                if cap < 1.0:
                    capped += 1
                    if cap < best:
                        best = cap
                        which = (EDGE_EDGE, ea, eb)
    return best, capped, which[0], which[1], which[2]


# ------------------------------------------------------------------------------------------
# numpy front-ends (one call per batch of pairs)
# ------------------------------------------------------------------------------------------


def _blocks(first: np.ndarray, second: np.ndarray, n_first: int) -> np.ndarray:
    first = np.asarray(first, dtype=FLOAT).reshape(-1, n_first, 3)
    second = np.asarray(second, dtype=FLOAT).reshape(-1, 4 - n_first, 3)
    if first.shape[0] != second.shape[0]:
        raise ValueError(
            f"got {first.shape[0]} first and {second.shape[0]} second primitives: give one "
            "of each per pair"
        )
    return np.ascontiguousarray(np.concatenate((first, second), axis=1))


def vertex_triangle_time_of_impact(
    p0: np.ndarray,
    tri0: np.ndarray,
    p1: np.ndarray,
    tri1: np.ndarray,
    min_distance: float = 0.0,
    tol: float | None = None,
) -> np.ndarray:
    """Time at which a moving vertex first comes within ``min_distance`` of a moving triangle.

    Both move linearly from time 0 to time 1. Conservative: the time returned is never later
    than the true one, and earlier by at most the time the pair needs to close ``tol``.

    Args:
        p0, p1: (n, 3) or (3,) vertex positions at times 0 and 1 (L).
        tri0, tri1: (n, 3, 3) or (3, 3) triangle vertex positions at times 0 and 1 (L).
        min_distance: the separation that counts as impact (L), >= 0.
        tol: distance tolerance of the impact (L), > 0; default 1e-6 of the pair's initial
            distance bound (the largest coordinate extent of the pair).

    Returns:
        (n,) times in [0, 1], inf where the pair stays farther than ``min_distance``.
    """
    return _times(_blocks(p0, tri0, 1), _blocks(p1, tri1, 1), VERTEX_TRIANGLE, min_distance, tol)


def edge_edge_time_of_impact(
    a0: np.ndarray,
    b0: np.ndarray,
    a1: np.ndarray,
    b1: np.ndarray,
    min_distance: float = 0.0,
    tol: float | None = None,
) -> np.ndarray:
    """Time at which two moving edges first come within ``min_distance`` of each other.

    As :func:`vertex_triangle_time_of_impact`, for edges ``a`` and ``b`` given as (n, 2, 3)
    or (2, 3) end points at times 0 (``a0``, ``b0``) and 1 (``a1``, ``b1``).
    """
    return _times(_blocks(a0, b0, 2), _blocks(a1, b1, 2), EDGE_EDGE, min_distance, tol)


def _times(x0, x1, kind, min_distance, tol) -> np.ndarray:
    if x0.shape != x1.shape:
        raise ValueError(f"positions at time 0 {x0.shape} and 1 {x1.shape} differ in shape")
    if not min_distance >= 0.0:
        raise ValueError(f"min_distance must be >= 0, got {min_distance}")
    if tol is None:
        extent = np.ptp(np.concatenate((x0, x1), axis=1), axis=1).max(initial=0.0)
        tol = 1e-6 * max(float(extent), 1e-300)
    if not tol > 0.0:
        raise ValueError(f"tol must be > 0, got {tol}")
    entry = np.zeros(x0.shape[0], dtype=FLOAT)
    return _pairs(kind, x0, x1, False, entry, float(min_distance), float(tol), 100 * MAX_ADVANCES)


def entry_fraction(
    first0: np.ndarray,
    second0: np.ndarray,
    first1: np.ndarray,
    second1: np.ndarray,
    entry: float | np.ndarray,
    kind: str = "vertex_triangle",
) -> np.ndarray:
    """The entry cap of each pair: the fraction of the step after which the pair could be
    more than ``entry`` past its first contact (1 where it cannot within the step, or where
    it starts within ``entry``).

    Args:
        first0, first1: the vertices (n, 3) or first edges (n, 2, 3) at times 0 and 1 (L).
        second0, second1: the triangles (n, 3, 3) or second edges (n, 2, 3) (L).
        entry: entry tolerance (L), per pair or one for all.
        kind: ``"vertex_triangle"`` or ``"edge_edge"``.

    Returns:
        (n,) fractions in (0, 1].
    """
    if kind not in ("vertex_triangle", "edge_edge"):
        raise ValueError(f"kind must be 'vertex_triangle' or 'edge_edge', got {kind!r}")
    n_first = 1 if kind == "vertex_triangle" else 2
    x0 = _blocks(first0, second0, n_first)
    x1 = _blocks(first1, second1, n_first)
    entry = np.broadcast_to(np.asarray(entry, dtype=FLOAT), (x0.shape[0],)).copy()
    if np.any(~(entry > 0.0)):
        raise ValueError("entry tolerances must be > 0")
    code = VERTEX_TRIANGLE if n_first == 1 else EDGE_EDGE
    return _pairs(code, x0, x1, True, entry, 0.0, 1.0, MAX_ADVANCES)


def sweep_caps(
    x0, x1, tri, tri_edge, edges, vertex_owner, edge_owner, entry, pair_a, pair_b, exits=True
):
    """Smallest entry cap over the primitive pairs of the triangle pairs (``_sweep_caps``);
    with ``exits``, also the exit caps of vertices leaving a body through its far side."""
    return _sweep_caps(
        x0, x1, tri, tri_edge, edges, vertex_owner, edge_owner, entry,
        np.asarray(pair_a, dtype=INDEX), np.asarray(pair_b, dtype=INDEX), MAX_ADVANCES,
        bool(exits),
    )  # fmt: skip


@njit(cache=True)
def _exit_caps(x0, x1, depth, margin):
    out = np.empty(x0.shape[0], dtype=x0.dtype)
    xs = np.empty((4, 3), dtype=x0.dtype)
    for i in range(x0.shape[0]):
        out[i] = _exit_cap(x0[i], x1[i], xs, depth[i], margin[i])
    return out


def exit_fraction(
    p0: np.ndarray,
    tri0: np.ndarray,
    p1: np.ndarray,
    tri1: np.ndarray,
    depth: float | np.ndarray,
    margin: float | np.ndarray | None = None,
) -> np.ndarray:
    """The exit cap of each vertex-triangle pair: the fraction of the step before the vertex,
    more than ``depth`` behind the triangle's plane at the start, could come within ``depth``
    of it on its way out through the triangle (the module doc, "pass-through"); at the cap it
    is still behind by ``depth`` plus ``margin``, or plus half its start height beyond
    ``depth`` where that is less.

    Args:
        p0, p1: (n, 3) or (3,) vertex positions at times 0 and 1 (L).
        tri0, tri1: (n, 3, 3) or (3, 3) triangle vertex positions at times 0 and 1, the
            outward normal by the right-hand rule (L).
        depth: the height behind the plane below which a vertex is not tested, and to which
            a tested one may come (L), >= 0, per pair or one for all.
        margin: see above (L), > 0; default ``depth`` (or 1e-12 where ``depth`` is 0).

    Returns:
        (n,) fractions in [0, 1]; 1 where the vertex does not leave through the triangle within
        the step, or is not more than ``depth`` behind its plane at the start.
    """
    x0 = _blocks(p0, tri0, 1)
    x1 = _blocks(p1, tri1, 1)
    if x0.shape != x1.shape:
        raise ValueError(f"positions at time 0 {x0.shape} and 1 {x1.shape} differ in shape")
    n = x0.shape[0]
    depth = np.broadcast_to(np.asarray(depth, dtype=FLOAT), (n,)).copy()
    if np.any(~(depth >= 0.0)):
        raise ValueError("depths must be >= 0")
    margin = np.where(depth > 0.0, depth, 1e-12) if margin is None else margin
    margin = np.broadcast_to(np.asarray(margin, dtype=FLOAT), (n,)).copy()
    if np.any(~(margin > 0.0)):
        raise ValueError("margins must be > 0")
    return _exit_caps(x0, x1, depth, margin)
