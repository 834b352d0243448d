"""The exit cap of continuous collision detection: a vertex inside a body leaving it through
the far side (numba; applied by :func:`fenics_matdepth.geometry.ccd.sweep_caps`).

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
plane of a face (flush side faces of two bodies) is free. So is a vertex that, at the time the
cap would stop it, lies within the entry tolerance of another face of the same body, one that
faces its own surface (``n_v . n_F < -ALIGNED``) and is not the other side of a layer under the
triangle (``n_F . n_T > -ALIGNED``): it is in contact with that face, as an edge of one body
sliding off another's edge out through its side face, not at the far side of a layer it came
through. (The mean normal of a vertex on an edge of its body lies between its two faces'
and does not tell the two apart; :func:`exit_exempt`.)

Lengths are in the unit of the coordinates; times are fractions of the step, in [0, 1].
"""

from __future__ import annotations

import numpy as np
from numba import njit

from fenics_matdepth._constants import FLOAT, INDEX
from fenics_matdepth.geometry.distance import point_triangle_dist2

__all__ = [
    "ALIGNED",
    "BARY_SLACK",
    "EXIT_DEPTH",
    "EXIT_MARGIN",
    "blocks_at",
    "exit_cap",
    "exit_exempt",
    "exit_fraction",
    "facing_cosine",
    "pair_blocks",
    "triangle_bodies",
    "vertex_normals",
]

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
def blocks_at(x0, x1, t, xs):
    """The (4, 3) block of a pair's points at time t of the step (``xs``, in place), from
    their blocks ``x0`` and ``x1`` at times 0 and 1 (linear trajectories)."""
    for i in range(4):
        for k in range(3):
            xs[i, k] = x0[i, k] + t * (x1[i, k] - x0[i, k])


def pair_blocks(first: np.ndarray, second: np.ndarray, n_first: int) -> np.ndarray:
    """The (n, 4, 3) blocks of n primitive pairs: ``first`` (n, n_first, 3) points of the first
    primitive (a vertex, 1; an edge, 2), then ``second``'s of the other (a single pair may
    drop the leading axis)."""
    first = np.asarray(first, dtype=FLOAT).reshape(-1, n_first, 3)
    second = np.asarray(second, dtype=FLOAT).reshape(-1, 4 - n_first, 3)
    if first.shape[0] != second.shape[0]:
        raise ValueError(
            f"got {first.shape[0]} first and {second.shape[0]} second primitives: give one "
            "of each per pair"
        )
    return np.ascontiguousarray(np.concatenate((first, second), axis=1))


@njit(inline="always")
def _signed_volume(x0, x1, t, xs):
    """det(x_2 - x_1, x_3 - x_1, x_0 - x_1) at time t of the (4, 3) blocks (vertex, then
    triangle): the vertex's height over the triangle's plane times twice its area (positive
    in front); ``xs`` is scratch."""
    blocks_at(x0, x1, t, xs)
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
    blocks_at(x0, x1, t, xs)
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
    blocks_at(x0, x1, t, xs)
    e1x, e1y, e1z = xs[2, 0] - xs[1, 0], xs[2, 1] - xs[1, 1], xs[2, 2] - xs[1, 2]
    e2x, e2y, e2z = xs[3, 0] - xs[1, 0], xs[3, 1] - xs[1, 1], xs[3, 2] - xs[1, 2]
    return np.sqrt(
        (e1y * e2z - e1z * e2y) ** 2 + (e1z * e2x - e1x * e2z) ** 2 + (e1x * e2y - e1y * e2x) ** 2
    )


@njit(cache=True)
def exit_cap(x0, x1, xs, depth, margin):
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
def vertex_normals(x, tri, nv):
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
def facing_cosine(x0, nv, v, a, b, c):
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
def _unit_normal(x, a, b, c, n):
    """The unit normal (n, in place) of the triangle of rows a, b, c of x; False where it has
    no area."""
    e1x, e1y, e1z = x[b, 0] - x[a, 0], x[b, 1] - x[a, 1], x[b, 2] - x[a, 2]
    e2x, e2y, e2z = x[c, 0] - x[a, 0], x[c, 1] - x[a, 1], x[c, 2] - x[a, 2]
    n[0] = e1y * e2z - e1z * e2y
    n[1] = e1z * e2x - e1x * e2z
    n[2] = e1x * e2y - e1y * e2x
    s = np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
    if not s > 0.0:
        return False
    n[0] /= s
    n[1] /= s
    n[2] /= s
    return True


@njit(inline="always")
def _triangle_at(x0, x1, t, tri, f, xt):
    """Rows 1-3 of ``xt``: the vertices of triangle f at time t of the step."""
    for r in range(3):
        w = tri[f, r]
        for k in range(3):
            xt[r + 1, k] = x0[w, k] + t * (x1[w, k] - x0[w, k])


@njit(cache=True)
def exit_exempt(x0, x1, t, nv, v, a, e, tri, tri_body, body_start, body_tris, xt):
    """Whether vertex v, at the time t at which the exit cap would stop it behind triangle a,
    is in contact with another face of a's body, one that faces v's surface (the cosine
    between their normals below ``-ALIGNED``) and is not the opposite side of a layer under a
    (the cosine between its normal and a's above ``-ALIGNED``): within ``e`` of it (the
    module doc). ``xt`` is (4, 3) scratch."""
    for k in range(3):
        xt[0, k] = x0[v, k] + t * (x1[v, k] - x0[v, k])
    na = np.empty(3, dtype=x0.dtype)
    n = np.empty(3, dtype=x0.dtype)
    _triangle_at(x0, x1, t, tri, a, xt)
    if not _unit_normal(xt, 1, 2, 3, na):
        return False
    body = tri_body[a]
    for i in range(body_start[body], body_start[body + 1]):
        f = body_tris[i]
        if f == a or tri[f, 0] == v or tri[f, 1] == v or tri[f, 2] == v:
            continue
        _triangle_at(x0, x1, t, tri, f, xt)
        if not _unit_normal(xt, 1, 2, 3, n):
            continue
        if not (nv[v, 0] * n[0] + nv[v, 1] * n[1] + nv[v, 2] * n[2] < -ALIGNED):
            continue
        if not (na[0] * n[0] + na[1] * n[1] + na[2] * n[2] > -ALIGNED):
            continue
        off = ((xt[0, 0] - xt[1, 0]) * n[0] + (xt[0, 1] - xt[1, 1]) * n[1]
               + (xt[0, 2] - xt[1, 2]) * n[2])  # fmt: skip
        if abs(off) < e and point_triangle_dist2(xt[0], xt, 1, 2, 3) < e * e:
            return True
    return False


def triangle_bodies(tri: np.ndarray, tri_body: np.ndarray | None = None) -> tuple:
    """The triangles of each body as a CSR, ``(tri_body, body_start, body_tris)``: the
    triangles of body k are ``body_tris[body_start[k]:body_start[k + 1]]``.

    Args:
        tri: (m, 3) triangles (vertex rows).
        tri_body: (m,) body of each triangle; None: the connected components of the surface
            (triangles sharing a vertex).
    """
    tri = np.asarray(tri, dtype=INDEX)
    m = tri.shape[0]
    if tri_body is None:
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        n = int(tri.max()) + 1 if m else 0
        rows = np.repeat(np.arange(m), 3)
        link = coo_matrix((np.ones(3 * m, dtype=np.int8), (rows, m + tri.ravel())),
                          shape=(m + n, m + n))  # fmt: skip
        tri_body = connected_components(link, directed=False)[1][:m] if m else np.empty(0)
    tri_body = np.ascontiguousarray(tri_body, dtype=INDEX)
    counts = np.bincount(tri_body, minlength=1) if m else np.zeros(1, dtype=INDEX)
    body_start = np.concatenate(([0], np.cumsum(counts))).astype(INDEX)
    body_tris = np.argsort(tri_body, kind="stable").astype(INDEX)
    return tri_body, body_start, body_tris


@njit(cache=True)
def _exit_caps(x0, x1, depth, margin):
    out = np.empty(x0.shape[0], dtype=x0.dtype)
    xs = np.empty((4, 3), dtype=x0.dtype)
    for i in range(x0.shape[0]):
        out[i] = exit_cap(x0[i], x1[i], xs, depth[i], margin[i])
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
    x0 = pair_blocks(p0, tri0, 1)
    x1 = pair_blocks(p1, tri1, 1)
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
