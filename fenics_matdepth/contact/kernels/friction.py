"""Coulomb friction over the intersection polygons: lagged quadrature data and the smoothed
friction potential with its exact derivatives.

The friction of a step is the lagged dissipative potential of IPC (Li et al. 2020), integrated
over the same (triangle T, tetrahedron K) intersection polygons as the normal force:

    ``D(x) = sum_q c_q f0(|P_q (du_T(xi_q) - du_K(eta_q))|)``,  ``du = x - x_ref``,

over quadrature points q of the polygons at the reference state ``x_ref`` (the last converged
one): ``xi_q`` the triangle's barycentric coordinates of the point, ``eta_q`` the
tetrahedron's at the same place, ``P_q = I - n_q n_q^T`` the projector on the tangent plane of
the contact normal ``n_q`` (the direction of ``grad g_K``, the force direction of the normal
model) and ``c_q = w_q mu p_q`` (quadrature weight, friction coefficient, normal traction
``p_q = (k g_q + p_aug) |grad g_K|`` of the penalty ``k``, the augmented Lagrangian's pressure
``p_aug`` where it is on). ``f0`` is IPC's mollified slip magnitude with slip tolerance ``e``:

    ``f0(y) = y^2 / e - y^3 / (3 e^2)`` for ``y < e``, ``y - e / 3`` beyond,

``f1 = f0'`` (``2 y / e - y^2 / e^2``, then 1) the ratio ``|t_T| / (mu p)`` of the tangential
traction to its Coulomb bound. At fixed lagged data ``D`` is a C2 function of the 21
coordinates of the pair's 7 vertices (3 of T, 4 of K; ``xi``, ``-eta`` the linear map from
them to the relative slip), convex, and the derivatives below are exact.

Quadrature: the polygon (of each sub-tetrahedron when K is split around its centroid) is
fan-triangulated from its first vertex and each fan triangle gets the 3-point rule of degree 2
(points ``2/3, 1/6, 1/6`` of its corners, weights 1/3 of its area).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from fenics_matdepth._constants import FLOAT, INDEX
from fenics_matdepth.contact.kernels.fastmath import FMA
from fenics_matdepth.contact.kernels.polygon import gather_triangle, polygon_work, sub_polygon
from fenics_matdepth.contact.kernels.split import gather_tet, is_split
from fenics_matdepth.geometry.clip import tet_gradients

__all__ = [
    "empty_reference",
    "friction_blocks",
    "friction_pairs",
    "friction_points",
    "friction_reference",
]

#: below this length of ``grad g_K`` (dimensionless) a (sub-)tetrahedron has no depth
#: direction, so no normal force and no friction
_FLAT_DEPTH = 1e-12


@njit(cache=True, fastmath=FMA, inline="always")
def _barycentrics(grads, x0, y, out):
    """``out[j] = lambda_j(y)`` of the tetrahedron with first vertex ``x0`` and barycentric
    gradients ``grads``."""
    s = 0.0
    for j in range(1, 4):
        v = (
            grads[j, 0] * (y[0] - x0[0])
            + grads[j, 1] * (y[1] - x0[1])
            + grads[j, 2] * (y[2] - x0[2])
        )
        out[j] = v
        s += v
    out[0] = 1.0 - s


@njit(cache=True, fastmath=FMA)
def friction_reference(
    x, depth, tri, tet, pair_tri, pair_tet, stiffness, offset, scale, fill, qpair, coef,
    normal, weight, area,
):  # fmt: skip
    """The quadrature points of the pairs' friction at the state ``x`` (the reference).

    Args:
        x, depth, tri, tet, pair_tri, pair_tet: as `drivers.area_pairs` (``tet`` may carry the
            split column).
        stiffness: (np,) each pair's penalty k (pressure / L).
        offset: (np, 3) the augmented Lagrangian's pressure at the triangle's corners, added
            to ``k g`` (zeros: none).
        scale: (np,) each pair's friction coefficient mu (pairs with 0 get no points).
        fill: False: count only; True: write the points into the arrays below.
        qpair: (nq,) the pair of each point.
        coef: (nq, 7) ``xi_0..2`` then ``-eta_0..3``: the slip at the point is
            ``sum_a coef[a] du_a`` over the pair's 7 vertices.
        normal: (nq, 3) the contact normal.
        weight: (nq,) ``c_q = w_q mu p_q`` (force: area times pressure).
        area: (nq,) ``w_q`` (L^2).

    Returns:
        The number of points (those with a positive normal traction).
    """
    work = polygon_work()
    xs, mu, gi = work.xs, work.mu, work.corner_depth
    xt0 = np.empty((4, 3), dtype=FLOAT)
    dt0 = np.empty(4, dtype=FLOAT)
    g0 = np.empty((4, 3), dtype=FLOAT)
    eta = np.empty((3, 4), dtype=FLOAT)
    xi = np.empty(3, dtype=FLOAT)
    nrm = np.empty(3, dtype=FLOAT)
    count = 0
    for p in range(pair_tri.shape[0]):
        if scale[p] <= 0.0:
            continue
        area2 = gather_triangle(x, tri, pair_tri[p], xs)
        if area2 == 0.0:
            continue
        k = pair_tet[p]
        gather_tet(x, depth, tet, k, 0, False, xt0, dt0)
        if tet_gradients(xt0, g0) == 0.0:
            continue
        for a in range(3):
            _barycentrics(g0, xt0[0], xs[a], eta[a])
        split = is_split(tet, k)
        for s in range(4 if split else 1):
            n = sub_polygon(x, depth, tet, k, s, split, work)
            if n < 3:
                continue
            for r in range(3):
                nrm[r] = (
                    work.dt[0] * work.grads[0, r]
                    + work.dt[1] * work.grads[1, r]
                    + work.dt[2] * work.grads[2, r]
                    + work.dt[3] * work.grads[3, r]
                )
            gn = np.sqrt(nrm[0] ** 2 + nrm[1] ** 2 + nrm[2] ** 2)
            if gn <= _FLAT_DEPTH:
                continue  # no depth direction: no normal force, so no friction
            for r in range(3):
                nrm[r] /= gn
            for t in range(1, n - 1):
                # fan triangle (0, t, t + 1): its share of the triangle's area
                d1 = mu[0, t, 1] - mu[0, 0, 1]
                d2 = mu[0, t, 2] - mu[0, 0, 2]
                e1 = mu[0, t + 1, 1] - mu[0, 0, 1]
                e2 = mu[0, t + 1, 2] - mu[0, 0, 2]
                w = 0.5 * area2 * abs(d1 * e2 - d2 * e1) / 3.0
                if w == 0.0:
                    continue
                for corner in range(3):
                    for a in range(3):
                        # 1/6 of each corner, plus 1/2 more of this one
                        xi[a] = (mu[0, 0, a] + mu[0, t, a] + mu[0, t + 1, a]) / 6.0
                        xi[a] += 0.5 * mu[0, (0, t, t + 1)[corner], a]
                    g = xi[0] * gi[0] + xi[1] * gi[1] + xi[2] * gi[2]
                    if g <= 0.0:
                        continue
                    press = stiffness[p] * g
                    press += xi[0] * offset[p, 0] + xi[1] * offset[p, 1] + xi[2] * offset[p, 2]
                    press *= gn  # the force density is (k g + p_aug) grad g
                    if press <= 0.0:
                        continue
                    if fill:
                        qpair[count] = p
                        for a in range(3):
                            coef[count, a] = xi[a]
                        for j in range(4):
                            coef[count, 3 + j] = -(
                                xi[0] * eta[0, j] + xi[1] * eta[1, j] + xi[2] * eta[2, j]
                            )
                        for r in range(3):
                            normal[count, r] = nrm[r]
                        weight[count] = w * scale[p] * press
                        area[count] = w
                    count += 1
    return count


@njit(cache=True, fastmath=FMA, inline="always")
def _slip(x, verts, xref, coef, normal, p, q, s):
    """The tangential slip ``s`` (3,) of point q of pair p; returns its length."""
    for r in range(3):
        s[r] = 0.0
    for a in range(7):
        v = verts[p, a]
        c = coef[q, a]
        for r in range(3):
            s[r] += c * (x[v, r] - xref[p, a, r])
    sn = s[0] * normal[q, 0] + s[1] * normal[q, 1] + s[2] * normal[q, 2]
    for r in range(3):
        s[r] -= sn * normal[q, r]
    return np.sqrt(s[0] * s[0] + s[1] * s[1] + s[2] * s[2])


@njit(cache=True, fastmath=FMA, inline="always")
def _mollified(y, e):
    """``(f0(y), f1(y), f1(y) / y)`` of IPC's mollified slip magnitude (tolerance e)."""
    if y < e:
        r = y / e
        return y * r * (1.0 - r / 3.0), r * (2.0 - r), (2.0 - r) / e
    return y - e / 3.0, 1.0, 1.0 / y


@njit(cache=True, fastmath=FMA, inline="always")
def _slip_hessian(y, s, c, e, normal, q, m):
    """``m`` (3, 3) = d2/ds2 of ``c f0(|P s|)``: ``c [f1/y P + (f1' - f1/y) s s^T / y^2]``."""
    _, _, f1y = _mollified(y, e)
    beta = 0.0
    if y > 0.0:
        beta = -1.0 / (y * e * e) if y < e else -1.0 / (y * y * y)
    for r in range(3):
        for t in range(3):
            pr = (1.0 if r == t else 0.0) - normal[q, r] * normal[q, t]
            m[r, t] = c * (f1y * pr + beta * s[r] * s[t])


@njit(cache=True, fastmath=FMA)
def friction_pairs(x, verts, xref, qptr, coef, normal, weight, slip_tol, want_grad, want_hess):
    """The friction potential of each pair and, on request, its gradient and Hessian over the
    pair's 7 vertices (21 dofs, xyz interleaved; see the module's docstring).

    Args:
        x: (nv, 3) current coordinates of the held vertices (L).
        verts: (np, 7) held vertices of the pairs (triangle then tetrahedron).
        xref: (np, 7, 3) their reference coordinates (L).
        qptr: (np + 1,) the pair's points are ``qptr[p]:qptr[p + 1]``.
        coef, normal, weight: per point, as `friction_reference` fills them.
        slip_tol: the slip tolerance e (L).
        want_grad, want_hess: whether to compute the gradients and the Hessians.

    Returns:
        ``(energy (np,), grad (np, 21), hess (np, 21, 21))`` (F L, F, F / L); the arrays not
        asked for have no rows.
    """
    n = verts.shape[0]
    energy = np.zeros(n, dtype=FLOAT)
    grad = np.zeros((n if want_grad or want_hess else 0, 21), dtype=FLOAT)
    hess = np.zeros((n if want_hess else 0, 21, 21), dtype=FLOAT)
    s = np.empty(3, dtype=FLOAT)
    m = np.empty((3, 3), dtype=FLOAT)
    e = slip_tol
    for p in range(n):
        for q in range(qptr[p], qptr[p + 1]):
            y = _slip(x, verts, xref, coef, normal, p, q, s)
            c = weight[q]
            f0, _, f1y = _mollified(y, e)
            energy[p] += c * f0
            if not (want_grad or want_hess):
                continue
            for a in range(7):
                ca = c * f1y * coef[q, a]
                for r in range(3):
                    grad[p, 3 * a + r] += ca * s[r]
            if not want_hess:
                continue
            _slip_hessian(y, s, c, e, normal, q, m)
            for a in range(7):
                for b in range(7):
                    cab = coef[q, a] * coef[q, b]
                    for r in range(3):
                        for t in range(3):
                            hess[p, 3 * a + r, 3 * b + t] += cab * m[r, t]
    return energy, grad, hess


@njit(cache=True, fastmath=FMA)
def friction_blocks(
    x, verts, xref, qptr, coef, normal, weight, slip_tol, slot, bc_mask, blocks
):  # fmt: skip
    """The friction potential's Hessian summed into 3 x 3 vertex-coupling blocks (the pair
    Hessians of `friction_pairs` without forming them: each point adds
    ``coef[a] coef[b] m_q`` to the block of vertices (a, b), ``m_q`` its 3 x 3 slip Hessian).

    Args:
        x, verts, xref, qptr, coef, normal, weight, slip_tol: as `friction_pairs`.
        slot: (np, 7, 7) the block of each pair coupling (-1: left out).
        bc_mask: (3 nv,) True on Dirichlet dofs, whose rows and columns are left out.
        blocks: (nb, 3, 3) output, added to (zero it first).
    """
    s = np.empty(3, dtype=FLOAT)
    m = np.empty((3, 3), dtype=FLOAT)
    for p in range(verts.shape[0]):
        for q in range(qptr[p], qptr[p + 1]):
            y = _slip(x, verts, xref, coef, normal, p, q, s)
            _slip_hessian(y, s, weight[q], slip_tol, normal, q, m)
            for a in range(7):
                va = verts[p, a]
                for b in range(7):
                    k = slot[p, a, b]
                    if k < 0:
                        continue
                    vb = verts[p, b]
                    cab = coef[q, a] * coef[q, b]
                    for r in range(3):
                        if bc_mask[3 * va + r]:
                            continue
                        for t in range(3):
                            if not bc_mask[3 * vb + t]:
                                blocks[k, r, t] += cab * m[r, t]


@njit(cache=True, fastmath=FMA)
def friction_points(x, verts, xref, qptr, coef, normal, weight, slip_tol):
    """Per point: the slip length ``y`` (L), the ratio ``f1(y) = |t_T| / (mu p)``, the
    tangential force ``-c f1(y) s / y`` on the triangle's side (F) and the slip vector ``s``
    of the triangle's point relative to the tetrahedron's (L) (points of pairs of ``verts``,
    the arguments as `friction_pairs`)."""
    nq = coef.shape[0]
    slip = np.zeros(nq, dtype=FLOAT)
    ratio = np.zeros(nq, dtype=FLOAT)
    force = np.zeros((nq, 3), dtype=FLOAT)
    vector = np.zeros((nq, 3), dtype=FLOAT)
    s = np.empty(3, dtype=FLOAT)
    for p in range(verts.shape[0]):
        for q in range(qptr[p], qptr[p + 1]):
            y = _slip(x, verts, xref, coef, normal, p, q, s)
            _, f1, f1y = _mollified(y, slip_tol)
            slip[q] = y
            ratio[q] = f1
            for r in range(3):
                force[q, r] = -weight[q] * f1y * s[r]
                vector[q, r] = s[r]
    return slip, ratio, force, vector


def empty_reference() -> tuple[np.ndarray, ...]:
    """Zero-size point arrays (qpair, coef, normal, weight, area) for a counting pass."""
    return (
        np.empty(0, dtype=INDEX),
        np.empty((0, 7), dtype=FLOAT),
        np.empty((0, 3), dtype=FLOAT),
        np.empty(0, dtype=FLOAT),
        np.empty(0, dtype=FLOAT),
    )
