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

*Pass-through*, a vertex inside a body leaving it through the far side, is capped by
:mod:`fenics_matdepth.geometry.ccd_exit` (the exit cap), applied in :func:`sweep_caps`.

Lengths are in the unit of the coordinates; times are fractions of the step, in [0, 1].
"""

from __future__ import annotations

import numpy as np
from numba import njit

from fenics_matdepth._constants import FLOAT, INDEX
from fenics_matdepth.geometry.ccd_exit import (
    ALIGNED,
    EXIT_DEPTH,
    EXIT_MARGIN,
    blocks_at,
    exit_cap,
    exit_exempt,
    exit_fraction,
    facing_cosine,
    pair_blocks,
    triangle_bodies,
    vertex_normals,
)
from fenics_matdepth.geometry.distance import point_triangle_dist2

__all__ = [
    "ADVANCE",
    "ALIGNED",
    "EXIT_DEPTH",
    "EXIT_MARGIN",
    "MAX_ADVANCES",
    "PASS_THROUGH",
    "STILL_REACH",
    "edge_edge_time_of_impact",
    "entry_fraction",
    "exit_fraction",
    "sweep_caps",
    "sweep_topology",
    "triangle_bodies",
    "triangle_travel",
    "vertex_triangle_time_of_impact",
]

#: Fraction of the guaranteed-safe advance taken per step of the conservative advancement
#: (below 1, so rounding never carries the primitives into contact).
ADVANCE = 0.9

#: Largest number of advancement steps per pair; the time reached so far is returned after it
#: (still conservative). A head-on approach needs about log(d0 / tol) / log(10) steps, a
#: grazing one about l / (ADVANCE tol).
MAX_ADVANCES = 200

#: A pair of triangles whose vertices move at most this many of its entry tolerances ``e`` in
#: all (the sum of the two triangles' largest vertex displacements, a bound on the motion
#: ``l`` of any primitive pair between them) has every entry cap 1 (``_sweep_caps`` skips
#: it): a pair starting within ``e`` is free, and one starting at ``d0 > e`` is capped only
#: where ``t + (d + e) / l < 1`` at a distance ``d >= d0 - l t``, which needs ``l > d0 + e > 2 e``.
#: The hundredth below 2 covers rounding.
STILL_REACH = 1.99

#: Kinds of primitive pairs: rows 0..3 of the (4, 3) coordinate blocks are the vertex, then
#: the triangle (VERTEX_TRIANGLE), or the first edge, then the second (EDGE_EDGE).
#: PASS_THROUGH: a vertex leaving a body through a triangle that faces its way (the vertex,
#: then the triangle).
VERTEX_TRIANGLE = 0
EDGE_EDGE = 1
PASS_THROUGH = 2


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


@njit(cache=True)
def _advance(kind, x0, x1, xs, stop, tol, max_steps):
    """Conservative advancement to distance ``stop`` (see the module doc).

    Returns:
        (t, d, l, hit): the time reached, the distance there, the motion bound; hit False
        where the distance stays above ``stop`` over the whole step (t = 1).
    """
    lip = _motion_bound(kind, x0, x1)
    blocks_at(x0, x1, 0.0, xs)
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
        blocks_at(x0, x1, t, xs)
        d = _distance(kind, xs)
    return t, d, lip, True


@njit(cache=True)
def _entry_cap(kind, x0, x1, xs, entry, max_steps):
    """Entry cap of one pair (the module doc): 1 where the pair starts within ``entry``."""
    blocks_at(x0, x1, 0.0, xs)
    if _distance(kind, xs) <= entry:
        return 1.0
    t, d, lip, hit = _advance(kind, x0, x1, xs, 0.0, 0.5 * entry, max_steps)
    if not hit:
        return 1.0
    return min(1.0, t + (d + entry) / lip)


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
def triangle_travel(x0, x1, tri):
    """The largest displacement of a vertex of each triangle from ``x0`` to ``x1`` (NaN where
    one is not finite)."""
    out = np.empty(tri.shape[0], dtype=x0.dtype)
    for f in range(tri.shape[0]):
        largest = 0.0
        for j in range(3):
            v = tri[f, j]
            s = 0.0
            for k in range(3):
                r = x1[v, k] - x0[v, k]
                s += r * r
            if s != s:  # NaN
                largest = s
                break
            largest = max(largest, s)
        out[f] = np.sqrt(largest)
    return out


@njit(cache=True)
def _sweep_caps(x0, x1, tri, tri_edge, edges, vertex_owner, edge_owner, entry, pair_a, pair_b,
                max_steps, exits, tri_body, body_start, body_tris, travel):  # fmt: skip
    """The smallest entry cap over the primitive pairs of the triangle pairs (a, b).

    Each vertex is tested against triangle a from its owner triangle b only, each edge pair
    from the owner triangles of its edges with a < b only, so a primitive pair is tested once
    when every ordered pair of overlapping triangles is given once. A vertex behind the plane
    of a (the triangles point outwards) is inside or leaving, not entering: with ``exits``, it
    is tested for leaving through a when its surface faces the way a does (the exit cap,
    kind PASS_THROUGH; not where :func:`exit_exempt` finds it in contact with a nearer face
    of a's body, given as the CSR ``body_start``, ``body_tris`` of the triangles of each body
    ``tri_body``), otherwise not tested. Pairs sharing a vertex are not tested.

    Given ``travel`` (:func:`triangle_travel`; empty: every pair swept), a pair whose motion
    bound cannot carry it past its entry tolerance is not swept for entries: its primitives'
    relative displacement is at most the sum ``T_a + T_b`` of the two triangles' largest
    vertex displacements, and where that is at most
    ``STILL_REACH`` times ``e`` every entry cap of the pair is 1 (see ``STILL_REACH``). The
    result is the same, pair for pair; the exit caps are swept as before.

    Returns:
        (smallest cap, number of pairs capped below 1, the pair kind and the two primitive
        indices of the smallest cap (vertex, triangle) or (edge, edge); -1 for none).
    """
    nv = np.zeros((x0.shape[0] if exits else 0, 3), dtype=x0.dtype)
    if exits:
        vertex_normals(x0, tri, nv)
    blk0 = np.empty((4, 3), dtype=x0.dtype)
    blk1 = np.empty((4, 3), dtype=x0.dtype)
    xs = np.empty((4, 3), dtype=x0.dtype)
    best = 1.0
    capped = 0
    which = (-1, -1, -1)
    skip_still = travel.size > 0
    for q in range(pair_a.shape[0]):
        a = pair_a[q]
        b = pair_b[q]
        if a == b:
            continue
        ta0, ta1, ta2 = tri[a, 0], tri[a, 1], tri[a, 2]
        e = min(entry[a], entry[b])
        # (a NaN travel compares False: swept)
        entering = not (skip_still and travel[a] + travel[b] <= STILL_REACH * e)
        if not (entering or exits):
            continue
        for j in range(3):
            v = tri[b, j]
            if vertex_owner[v] != b or v == ta0 or v == ta1 or v == ta2:
                continue
            if _inner_side(x0, v, ta0, ta1, ta2):
                if not (exits and facing_cosine(x0, nv, v, ta0, ta1, ta2) > ALIGNED):
                    continue
                _gather4(x0, v, ta0, ta1, ta2, blk0)
                _gather4(x1, v, ta0, ta1, ta2, blk1)
                cap = exit_cap(blk0, blk1, xs, EXIT_DEPTH * e, EXIT_MARGIN * e)
                if cap < 1.0 and not exit_exempt(x0, x1, cap, nv, v, a, e, tri, tri_body,
                                                  body_start, body_tris, xs):  # fmt: skip
                    capped += 1
                    if cap < best:
                        best = cap
                        which = (PASS_THROUGH, v, a)
                continue
            if not entering:
                continue
            cap = _primitive_cap(VERTEX_TRIANGLE, x0, x1, v, ta0, ta1, ta2, blk0, blk1, xs, e,
                                 max_steps)  # fmt: skip
            if cap < 1.0:
                capped += 1
                if cap < best:
                    best = cap
                    which = (VERTEX_TRIANGLE, v, a)
        if a > b or not entering:
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
    x0, x1 = pair_blocks(p0, tri0, 1), pair_blocks(p1, tri1, 1)
    return _times(x0, x1, VERTEX_TRIANGLE, min_distance, tol)


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
    return _times(pair_blocks(a0, b0, 2), pair_blocks(a1, b1, 2), EDGE_EDGE, min_distance, tol)


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
    x0 = pair_blocks(first0, second0, n_first)
    x1 = pair_blocks(first1, second1, n_first)
    entry = np.broadcast_to(np.asarray(entry, dtype=FLOAT), (x0.shape[0],)).copy()
    if np.any(~(entry > 0.0)):
        raise ValueError("entry tolerances must be > 0")
    code = VERTEX_TRIANGLE if n_first == 1 else EDGE_EDGE
    return _pairs(code, x0, x1, True, entry, 0.0, 1.0, MAX_ADVANCES)


def sweep_topology(tri: np.ndarray, num_vertices: int) -> tuple[np.ndarray, ...]:
    """The edges :func:`sweep_caps` takes for the triangles ``tri`` over ``num_vertices``
    vertices: ``(tri_edge, edges, vertex_owner, edge_owner)``, each triangle's three edges, the
    edges (sorted vertex pairs), and the owner triangle (the first holding it, which tests its
    pairs) of each vertex and edge (``len(tri)`` for a vertex of no triangle)."""
    m = tri.shape[0]
    sides = np.sort(np.stack((tri, tri[:, [1, 2, 0]]), axis=2).reshape(-1, 2), axis=1)
    keys = sides[:, 0] * max(num_vertices, 1) + sides[:, 1]
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    edges = np.ascontiguousarray(sides[first])
    tri_edge = np.ascontiguousarray(inverse.reshape(m, 3).astype(INDEX))
    vertex_owner = np.full(num_vertices, m, dtype=INDEX)
    np.minimum.at(vertex_owner, tri.ravel(), np.repeat(np.arange(m, dtype=INDEX), 3))
    return tri_edge, edges, vertex_owner, (first // 3).astype(INDEX)


def sweep_caps(
    x0, x1, tri, tri_edge, edges, vertex_owner, edge_owner, entry, pair_a, pair_b, exits=True,
    bodies=None, skip_still=True, travel=None,
):  # fmt: skip
    """Smallest entry cap over the primitive pairs of the triangle pairs (``_sweep_caps``);
    with ``exits``, also the exit caps of vertices leaving a body through its far side
    (``bodies``: :func:`triangle_bodies` of ``tri``, computed when None). ``skip_still``: the
    pairs whose vertices cannot move their entry tolerance are not swept for entries (the
    same result, faster; False sweeps every pair, as a reference), from ``travel``
    (:func:`triangle_travel` of the step, computed when None)."""
    tri_body, body_start, body_tris = triangle_bodies(tri) if bodies is None else bodies
    if not skip_still:
        travel = np.empty(0, dtype=x0.dtype)
    elif travel is None:
        travel = triangle_travel(x0, x1, tri)
    return _sweep_caps(
        x0, x1, tri, tri_edge, edges, vertex_owner, edge_owner, entry,
        np.asarray(pair_a, dtype=INDEX), np.asarray(pair_b, dtype=INDEX), MAX_ADVANCES,
        bool(exits), tri_body, body_start, body_tris, travel,
    )  # fmt: skip
