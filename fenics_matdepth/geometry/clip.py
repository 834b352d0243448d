"""Triangle-tetrahedron intersection, computed in the triangle's barycentric parameter domain.

A point of the triangle with barycentric coordinates ``mu`` (``mu_i >= 0``, ``sum(mu) = 1``) has
barycentric coordinates ``L_j(mu) = sum_i mu_i Lam[i, j]`` in the tetrahedron, where
``Lam[i, j] = lambda_j(x_i)`` is the j-th barycentric coordinate of triangle vertex i. The
intersection is therefore the convex polygon cut from the parameter simplex by the four
half-planes ``L_j(mu) >= 0``: at most 7 vertices, each the intersection of two of 7 lines
(``mu_i = 0``, i = 0..2, labelled 0..2; ``L_j = 0``, j = 0..3, labelled 3..6). In homogeneous
coordinates every line is a 3-vector ``c`` (``c . mu = 0``): ``e_i`` for a triangle edge and
the column ``Lam[:, j]`` for a tetrahedron face, and the vertex where lines a and b meet is
``mu = m / sum(m)`` with ``m = c_a x c_b``. The clipper records these two labels per vertex so
that the contact kernels (`fenics_matdepth.contact.kernels`) can differentiate the polygon
exactly. The tests over many candidate pairs built on this clipper are in
`fenics_matdepth.geometry.intersect`.

Robustness: the clipper works on barycentric values only (dimensionless). Barycentric
coordinates of the triangle corners within rounding noise of zero (``|Lam[i, j]| <= CLIP_TOL *
(1 + sum_j |Lam[i, j]|)``) are snapped to exactly zero, so that exact incidences of the input
(a corner on a face plane, a triangle in a face plane, an edge through an edge) are seen as
such; the clipping itself then uses exact sign tests (a vertex is kept if ``L >= 0``, a new
vertex is made only where an edge strictly changes sign, at ``t = L_p / (L_p - L_q)`` with a
non-zero denominator), so the result is the exact intersection for barycentric data perturbed
by at most CLIP_TOL: continuous, never NaN. (Near-coplanar configurations are intrinsically
ill-conditioned: a triangle tilted by an angle a out of a face plane has its cut points
determined to rounding / a.) Flat tetrahedra
(``|6 V| <= TET_VOLUME_RTOL * h^3``, h the longest edge) and zero-area triangles give an empty
intersection.

Every kernel here is compiled with ``fastmath=False`` spelt out: numba gives a function without
its own setting the fast-math flags of the caller it is first compiled for (the contact pair
kernels fuse multiply-adds), and the clip's sign tests must come out the same whoever calls
them first (the intersection test and the pair kernels must agree on every pair).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from fenics_matdepth._constants import FLOAT

__all__ = [
    "CLIP_TOL",
    "MAX_POLYGON_VERTICES",
    "CLIP_SHIFT",
    "SHIFT_TANGENT",
    "TET_VOLUME_RTOL",
    "TRI_AREA_RTOL",
    "area2_of",
    "clip_nonempty",
    "clip_shift",
    "clip_triangle",
    "edges_and_normal",
    "edges_normal_of",
    "intersection_polygon",
    "shift_of",
    "tet_frame",
    "tet_gradients",
    "triangle_area2",
    "triangle_rows",
]

#: Relative threshold (barycentric units) below which a triangle corner's barycentric
#: coordinate is rounding noise and is snapped to exactly zero (a few ulps of the row's size).
CLIP_TOL = 1e-14


#: A tetrahedron with ``|6 V| <= TET_VOLUME_RTOL * h**3`` (h = longest edge) is flat: its
#: barycentric coordinates are not defined and it contributes nothing.
TET_VOLUME_RTOL = 1e-12


#: A triangle with ``2 A <= TRI_AREA_RTOL * h**2`` (h = longest edge) has zero area: it
#: contributes nothing (and its normal, hence the area gradient, is undefined).
TRI_AREA_RTOL = 1e-14


#: Every triangle is clipped as if moved by ``CLIP_SHIFT * sqrt(2 A)`` (A its area) along its
#: normal ``(x1 - x0) x (x2 - x0)`` (outward for the contact surface's triangles), plus a
#: generic in-plane component (SHIFT_TANGENT): a consistent perturbation that takes the
#: triangle off every exact incidence of the input (its plane holding a tetrahedron edge, an
#: edge in a face, a corner on a face, the triangle in a face), the same for all tetrahedra it
#: meets. Without it, a plane holding an edge makes the two faces through that edge one line
#: of the parameter plane up to rounding, and clipping by both cuts a rounding-noise sliver
#: whose vertices, meeting points of almost parallel lines, have derivatives of order
#: 1 / rounding (Hessian entries of 1e23 and forces 1e5 times too large were measured on the
#: patch test); whether such a sliver exists, and which of two coincident lines bounds a
#: polygon, was decided by rounding, pair by pair, so the force jumped with perturbations of
#: the order of rounding. With the shift, every such sliver is a strip of width
#: ``~CLIP_SHIFT h`` between two parallel lines (well-conditioned vertices) or nothing, as the
#: perturbed geometry says, for every tetrahedron around the edge alike. The energy is that of
#: the shifted surface (relative change of order ``CLIP_SHIFT h / g``); the kernels
#: differentiate through the shift too (`fenics_matdepth.contact.kernels`), leaving out only
#: its second derivatives (relative ``CLIP_SHIFT`` in the Hessian). The shift is far above the
#: rounding of barycentric values (``~1e-14`` for coordinates 100 elements from the origin) and
#: above the accuracy to which a Newton solution keeps two faces coplanar that are coplanar in
#: the exact solution (about 1e-12 of the element size: at 1e-11 such near-incidences of the
#: solution stalled 1 patch solve in 6 on 2 ranks), so two face lines do not meet inside an
#: element.
CLIP_SHIFT = 1e-9


#: In-plane components of the clip shift, in units of its normal component, along the
#: triangle's first edge and perpendicular to it: generic numbers, so that the shift also moves
#: a triangle edge off a tetrahedron face through it whatever the face's orientation (a face
#: perpendicular to the triangle, which a shift along the normal alone leaves in place: the
#: patch test's vertical faces under its horizontal contact triangles).
SHIFT_TANGENT = (0.3183098861837907, 0.4472135954999579)


#: Triangle (3) plus at most one new vertex per tetrahedron face (4).
MAX_POLYGON_VERTICES = 8


@njit(cache=True, fastmath=False)
def tet_frame(p0x, p0y, p0z, p1x, p1y, p1z, p2x, p2y, p2z, p3x, p3y, p3z):
    """6 x signed volume, squared longest edge and the cross products ``e2 x e3``, ``e3 x e1``,
    ``e1 x e2`` (``e_k = x_k - x_0``: det times the barycentric gradients 1 to 3) of a
    tetrahedron given by its vertex coordinates, as a 11-tuple (det, h2, c1x, ..., c3z). Scalars
    in and out, so that `intersect_pairs` runs it on many tetrahedra in one vectorised loop."""
    e1x = p1x - p0x
    e1y = p1y - p0y
    e1z = p1z - p0z
    e2x = p2x - p0x
    e2y = p2y - p0y
    e2z = p2z - p0z
    e3x = p3x - p0x
    e3y = p3y - p0y
    e3z = p3z - p0z
    c1x = e2y * e3z - e2z * e3y
    c1y = e2z * e3x - e2x * e3z
    c1z = e2x * e3y - e2y * e3x
    c2x = e3y * e1z - e3z * e1y
    c2y = e3z * e1x - e3x * e1z
    c2z = e3x * e1y - e3y * e1x
    c3x = e1y * e2z - e1z * e2y
    c3y = e1z * e2x - e1x * e2z
    c3z = e1x * e2y - e1y * e2x
    det = e1x * c1x + e1y * c1y + e1z * c1z
    # longest edge, the six edges in the order (0 1) (0 2) (0 3) (1 2) (1 3) (2 3)
    h2 = max(0.0, e1x * e1x + e1y * e1y + e1z * e1z)
    h2 = max(h2, e2x * e2x + e2y * e2y + e2z * e2z)
    h2 = max(h2, e3x * e3x + e3y * e3y + e3z * e3z)
    dx = p2x - p1x
    dy = p2y - p1y
    dz = p2z - p1z
    h2 = max(h2, dx * dx + dy * dy + dz * dz)
    dx = p3x - p1x
    dy = p3y - p1y
    dz = p3z - p1z
    h2 = max(h2, dx * dx + dy * dy + dz * dz)
    dx = p3x - p2x
    dy = p3y - p2y
    dz = p3z - p2z
    h2 = max(h2, dx * dx + dy * dy + dz * dz)
    return det, h2, c1x, c1y, c1z, c2x, c2y, c2z, c3x, c3y, c3z


@njit(cache=True, fastmath=False)
def tet_gradients(x_tet, grads):
    """Barycentric gradients of a tetrahedron.

    Args:
        x_tet: (4, 3) vertex coordinates (length).
        grads: (4, 3) output, ``grads[j] = grad lambda_j`` (1 / length).

    Returns:
        6 x signed volume (length^3); 0.0 for a flat tetrahedron (grads then untouched).
    """
    det, h2, c1x, c1y, c1z, c2x, c2y, c2z, c3x, c3y, c3z = tet_frame(
        x_tet[0, 0], x_tet[0, 1], x_tet[0, 2], x_tet[1, 0], x_tet[1, 1], x_tet[1, 2],
        x_tet[2, 0], x_tet[2, 1], x_tet[2, 2], x_tet[3, 0], x_tet[3, 1], x_tet[3, 2],
    )  # fmt: skip
    if not (abs(det) > TET_VOLUME_RTOL * h2 * np.sqrt(h2)):
        return 0.0
    inv = 1.0 / det
    grads[1, 0] = c1x * inv
    grads[1, 1] = c1y * inv
    grads[1, 2] = c1z * inv
    grads[2, 0] = c2x * inv
    grads[2, 1] = c2y * inv
    grads[2, 2] = c2z * inv
    grads[3, 0] = c3x * inv
    grads[3, 1] = c3y * inv
    grads[3, 2] = c3z * inv
    for a in range(3):
        grads[0, a] = -(grads[1, a] + grads[2, a] + grads[3, a])
    return det


@njit(cache=True, fastmath=False)
def edges_and_normal(x_tri):
    """Edges ``a = x1 - x0``, ``b = x2 - x0`` and normal ``n = a x b`` of a triangle, as a
    9-tuple (ax, ay, az, bx, by, bz, nx, ny, nz)."""
    return edges_normal_of(
        x_tri[0, 0], x_tri[0, 1], x_tri[0, 2], x_tri[1, 0], x_tri[1, 1], x_tri[1, 2],
        x_tri[2, 0], x_tri[2, 1], x_tri[2, 2],
    )  # fmt: skip


@njit(cache=True, fastmath=False)
def edges_normal_of(x0, y0, z0, x1, y1, z1, x2, y2, z2):
    """`edges_and_normal` from the corners' coordinates (scalars)."""
    ax = x1 - x0
    ay = y1 - y0
    az = z1 - z0
    bx = x2 - x0
    by = y2 - y0
    bz = z2 - z0
    return ax, ay, az, bx, by, bz, ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx


@njit(cache=True, fastmath=False)
def _clip_shift(x_tri):
    """The clip shift of a triangle, as a 3-tuple (zeros for a zero-area triangle):
    ``CLIP_SHIFT / sqrt(|n|) * (n + SHIFT_TANGENT[0] |n| t_1 + SHIFT_TANGENT[1] |n| t_2)``,
    ``n = (x1 - x0) x (x2 - x0)``, ``t_1`` the unit vector along ``x1 - x0`` and ``t_2 = n x
    t_1 / |n|``."""
    ax, ay, az, _, _, _, nx, ny, nz = edges_and_normal(x_tri)
    return shift_of(ax, ay, az, nx, ny, nz)


@njit(cache=True, error_model="numpy", fastmath=False)
def shift_of(ax, ay, az, nx, ny, nz):
    """`_clip_shift` from the triangle's first edge ``a`` and normal ``n`` (scalars, so that
    `intersect_pairs` runs it on many triangles in one vectorised loop; the divisions are
    guarded, hence the numpy error model, which lets them vectorise)."""
    a2 = np.sqrt(nx * nx + ny * ny + nz * nz)
    la = np.sqrt(ax * ax + ay * ay + az * az)
    if not (a2 > 0.0 and la > 0.0):
        return 0.0, 0.0, 0.0
    f = CLIP_SHIFT / np.sqrt(a2)
    # |n| t_1 = (|n| / |a|) a and |n| t_2 = n x a / |a|
    c1 = SHIFT_TANGENT[0] * a2 / la
    c2 = SHIFT_TANGENT[1] / la
    return (
        f * (nx + c1 * ax + c2 * (ny * az - nz * ay)),
        f * (ny + c1 * ay + c2 * (nz * ax - nx * az)),
        f * (nz + c1 * az + c2 * (nx * ay - ny * ax)),
    )


@njit(cache=True, fastmath=False)
def triangle_rows(x_tri, x_tet, grads, lam):
    """``lam[i, j] = lambda_j(x_tri[i] + shift)`` for the 3 triangle corners, moved by the
    consistent clip shift (CLIP_SHIFT) along the triangle's normal."""
    sx, sy, sz = _clip_shift(x_tri)
    _shifted_rows(x_tri, x_tet, grads, sx, sy, sz, lam)


@njit(cache=True, fastmath=False)
def _shifted_rows(x_tri, x_tet, grads, sx, sy, sz, lam):
    """`triangle_rows` with the triangle's clip shift ``(sx, sy, sz)`` given."""
    for i in range(3):
        dx = (x_tri[i, 0] - x_tet[0, 0]) + sx
        dy = (x_tri[i, 1] - x_tet[0, 1]) + sy
        dz = (x_tri[i, 2] - x_tet[0, 2]) + sz
        s = 0.0
        for j in range(1, 4):
            v = grads[j, 0] * dx + grads[j, 1] * dy + grads[j, 2] * dz
            lam[i, j] = v
            s += v
        lam[i, 0] = 1.0 - s


@njit(cache=True, fastmath=False)
def _snap(lam):
    """Set barycentric values within rounding noise of zero (CLIP_TOL) to exactly zero."""
    for i in range(3):
        size = 1.0 + abs(lam[i, 0]) + abs(lam[i, 1]) + abs(lam[i, 2]) + abs(lam[i, 3])
        for j in range(4):
            if abs(lam[i, j]) <= CLIP_TOL * size:
                lam[i, j] = 0.0


@njit(cache=True, fastmath=False)
def clip_triangle(lam, mu, vlab, elab):
    """Clip the parameter simplex by the half-planes ``sum_i mu_i lam[i, j] >= 0``.

    Sutherland-Hodgman on two alternating buffers. A vertex with ``L >= 0`` is kept with its
    labels; a new vertex is created only where an edge strictly changes sign, and gets the
    labels (edge line, face line).

    Args:
        lam: (3, 4) barycentric coordinates of the triangle vertices in the tetrahedron;
            entries within rounding noise of zero are set to exactly zero (in place).
        mu: (2, MAX_POLYGON_VERTICES, 3) work buffer; the result is in ``mu[0, :n]``.
        vlab: (2, MAX_POLYGON_VERTICES, 2) int work buffer: the two lines through each vertex.
        elab: (2, MAX_POLYGON_VERTICES) int work buffer: the line of the edge k -> k + 1.

    Returns:
        Number n of polygon vertices (counter-clockwise in the parameter plane), 0 if the
        intersection is empty, has fewer than 3 vertices or no area.
    """
    _snap(lam)
    # quick rejection: a tetrahedron face plane separates the triangle
    for j in range(4):
        if lam[0, j] < 0.0 and lam[1, j] < 0.0 and lam[2, j] < 0.0:
            return 0
    for i in range(3):
        for r in range(3):
            mu[0, i, r] = 0.0
        mu[0, i, i] = 1.0
        # vertex i lies on the edges mu_{i+1} = 0 and mu_{i+2} = 0; edge i -> i+1 on mu_{i+2} = 0
        vlab[0, i, 0] = (i + 1) % 3
        vlab[0, i, 1] = (i + 2) % 3
        elab[0, i] = (i + 2) % 3
    n = 3
    cur = 0
    for j in range(4):
        nxt = 1 - cur
        # all vertices inside: nothing to clip
        n_out = 0
        for k in range(n):
            L = mu[cur, k, 0] * lam[0, j] + mu[cur, k, 1] * lam[1, j] + mu[cur, k, 2] * lam[2, j]
            if L < 0.0:
                n_out += 1
        if n_out == 0:
            continue
        if n_out == n:
            return 0
        m = 0
        Lp = mu[cur, 0, 0] * lam[0, j] + mu[cur, 0, 1] * lam[1, j] + mu[cur, 0, 2] * lam[2, j]
        for k in range(n):
            k1 = k + 1 if k + 1 < n else 0
            Lq = (
                mu[cur, k1, 0] * lam[0, j] + mu[cur, k1, 1] * lam[1, j] + mu[cur, k1, 2] * lam[2, j]
            )
            p_in = Lp >= 0.0
            q_in = Lq >= 0.0
            cross = (Lp > 0.0 and Lq < 0.0) or (Lp < 0.0 and Lq > 0.0)
            if p_in:
                for r in range(3):
                    mu[nxt, m, r] = mu[cur, k, r]
                vlab[nxt, m, 0] = vlab[cur, k, 0]
                vlab[nxt, m, 1] = vlab[cur, k, 1]
                # the edge leaving a kept vertex follows the face once the old edge is gone
                elab[nxt, m] = elab[cur, k] if (q_in or cross) else 3 + j
                m += 1
            if cross:
                t = Lp / (Lp - Lq)
                for r in range(3):
                    mu[nxt, m, r] = mu[cur, k, r] + t * (mu[cur, k1, r] - mu[cur, k, r])
                vlab[nxt, m, 0] = elab[cur, k]
                vlab[nxt, m, 1] = 3 + j
                elab[nxt, m] = 3 + j if p_in else elab[cur, k]
                m += 1
            Lp = Lq
        n = m
        cur = nxt
        if n < 3:
            return 0
    if cur == 1:
        for k in range(n):
            for r in range(3):
                mu[0, k, r] = mu[1, k, r]
            vlab[0, k, 0] = vlab[1, k, 0]
            vlab[0, k, 1] = vlab[1, k, 1]
            elab[0, k] = elab[1, k]
    # collinear vertices: no area, and no defined derivatives
    area2 = 0.0
    for k in range(n):
        k1 = k + 1 if k + 1 < n else 0
        area2 += mu[0, k, 1] * mu[0, k1, 2] - mu[0, k, 2] * mu[0, k1, 1]
    if area2 == 0.0:
        return 0
    return n


@njit(cache=True, fastmath=False)
def clip_nonempty(lam, buf):
    """Whether `clip_triangle` would return a polygon (n >= 3), without building it.

    The same sign logic on ``lam`` (already snapped by the caller), but each vertex carries only
    its four barycentric values, interpolated along clipped edges; no labels, no early copy.

    Args:
        lam: (3, 4) snapped barycentric coordinates of the triangle vertices.
        buf: (2, MAX_POLYGON_VERTICES, 4) work buffer.
    """
    for i in range(3):
        for j in range(4):
            buf[0, i, j] = lam[i, j]
    n = 3
    cur = 0
    for j in range(4):
        nxt = 1 - cur
        m = 0
        Lp = buf[cur, 0, j]
        for k in range(n):
            k1 = k + 1 if k + 1 < n else 0
            Lq = buf[cur, k1, j]
            if Lp >= 0.0:
                for r in range(4):
                    buf[nxt, m, r] = buf[cur, k, r]
                m += 1
            if (Lp > 0.0 and Lq < 0.0) or (Lp < 0.0 and Lq > 0.0):
                t = Lp / (Lp - Lq)
                for r in range(4):
                    buf[nxt, m, r] = buf[cur, k, r] + t * (buf[cur, k1, r] - buf[cur, k, r])
                m += 1
            Lp = Lq
        if m < 3:
            return False
        n = m
        cur = nxt
    return True


@njit(cache=True, fastmath=False)
def triangle_area2(x_tri):
    """Twice the triangle area (length^2), 0.0 below TRI_AREA_RTOL."""
    ax, ay, az, bx, by, bz, nx, ny, nz = edges_and_normal(x_tri)
    cx = x_tri[2, 0] - x_tri[1, 0]
    cy = x_tri[2, 1] - x_tri[1, 1]
    cz = x_tri[2, 2] - x_tri[1, 2]
    return area2_of(ax, ay, az, bx, by, bz, nx, ny, nz, cx, cy, cz)


@njit(cache=True, fastmath=False)
def area2_of(ax, ay, az, bx, by, bz, nx, ny, nz, cx, cy, cz):
    """`triangle_area2` from the edges ``a``, ``b``, ``c = x2 - x1`` and normal (scalars)."""
    a2 = np.sqrt(nx * nx + ny * ny + nz * nz)
    h2 = max(ax * ax + ay * ay + az * az, bx * bx + by * by + bz * bz, cx * cx + cy * cy + cz * cz)
    if not (a2 > TRI_AREA_RTOL * h2):
        return 0.0
    return a2


@njit(cache=True, fastmath=False)
def _intersection_polygon(x_tri, x_tet, mu, vlab, elab):
    """Clip one pair; returns n (polygon in ``mu[0, :n]``, labels in ``vlab[0, :n]``)."""
    grads = np.empty((4, 3), dtype=FLOAT)
    if tet_gradients(x_tet, grads) == 0.0:
        return 0
    if triangle_area2(x_tri) == 0.0:
        return 0
    lam = np.empty((3, 4), dtype=FLOAT)
    triangle_rows(x_tri, x_tet, grads, lam)
    return clip_triangle(lam, mu, vlab, elab)


def intersection_polygon(x_tri: np.ndarray, x_tet: np.ndarray) -> np.ndarray:
    """Intersection of a triangle with a tetrahedron.

    Args:
        x_tri: (3, 3) triangle vertex coordinates (length).
        x_tet: (4, 3) tetrahedron vertex coordinates (length).

    Returns:
        (n, 3) vertices of the convex intersection polygon (length), ordered
        counter-clockwise about the triangle normal ``(x1 - x0) x (x2 - x0)``; n = 0 when they
        do not intersect (or the tetrahedron is flat, or the triangle has zero area).
    """
    x_tri = np.ascontiguousarray(x_tri, dtype=FLOAT).reshape(3, 3)
    x_tet = np.ascontiguousarray(x_tet, dtype=FLOAT).reshape(4, 3)
    mu = np.empty((2, MAX_POLYGON_VERTICES, 3), dtype=FLOAT)
    vlab = np.empty((2, MAX_POLYGON_VERTICES, 2), dtype=np.int64)
    elab = np.empty((2, MAX_POLYGON_VERTICES), dtype=np.int64)
    n = _intersection_polygon(x_tri, x_tet, mu, vlab, elab)
    return mu[0, :n] @ (x_tri + clip_shift(x_tri))


def clip_shift(x_tri: np.ndarray) -> np.ndarray:
    """The consistent displacement (length) with which the clipper moves a triangle off exact
    incidences: ``CLIP_SHIFT * sqrt(2 A)`` along ``(x1 - x0) x (x2 - x0)`` plus a generic
    in-plane part (SHIFT_TANGENT; zeros for a zero-area triangle). The intersection polygons
    and the contact energy are those of the moved triangle.

    Args:
        x_tri: (3, 3) triangle vertex coordinates (length).

    Returns:
        (3,) displacement.
    """
    x_tri = np.ascontiguousarray(x_tri, dtype=FLOAT).reshape(3, 3)
    return np.array(_clip_shift_tuple(x_tri), dtype=FLOAT)


@njit(cache=True, fastmath=False)
def _clip_shift_tuple(x_tri):
    return _clip_shift(x_tri)
