"""Derivative helpers of the area-integration pair kernel (`area.area_pair`).

``Phi = int_P (G . mu)^2 dxi`` is differentiated with respect to the 12 numbers ``Lam`` through
the vertices of the clipped polygon P, each the meeting point of two lines whose homogeneous
coefficients are columns of ``Lam`` (see ``docs/kernels.md``); here are the per-vertex
gradient, Jacobian and curvature terms, their assembly into ``d2 Phi / d Lam2``, the Jacobian
of the clip shift and the Hessian of the triangle's area.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from fenics_matdepth.contact.kernels.fastmath import FMA
from fenics_matdepth.geometry.clip import CLIP_SHIFT, SHIFT_TANGENT, edges_and_normal

__all__ = [
    "area_hessian",
    "assemble_phi_hessian",
    "clip_shift_jacobian",
    "shift_rows",
    "vertex_gradient",
]

#: Below this |sum(c_a x c_b)| two polygon lines are taken as parallel (derivative guard; the
#: coefficients are barycentric values of order one, so this only catches exact parallelism).
_PARALLEL_TOL = 1e-100


@njit(cache=True, fastmath=FMA)
def _line(lam, label, r):
    """Component r of the homogeneous coefficient vector of line ``label`` (0..6)."""
    if label < 3:
        return 1.0 if r == label else 0.0
    return lam[r, label - 3]


@njit(cache=True, fastmath=FMA)
def _line_sum_cross(lam, la, lb):
    """``s = sum(c_a x c_b)`` (the homogeneous weight of the vertex on lines la, lb)."""
    ca0 = _line(lam, la, 0)
    ca1 = _line(lam, la, 1)
    ca2 = _line(lam, la, 2)
    cb0 = _line(lam, lb, 0)
    cb1 = _line(lam, lb, 1)
    cb2 = _line(lam, lb, 2)
    return (ca1 * cb2 - ca2 * cb1) + (ca2 * cb0 - ca0 * cb2) + (ca0 * cb1 - ca1 * cb0)


@njit(cache=True, fastmath=FMA)
def vertex_gradient(lam, mu_k, la, lb, w, gphi):
    """``gphi += (d mu / d Lam)^T w`` for the vertex on lines la, lb.

    With ``v = (d mu / d m)^T w = (w - (w . mu) 1) / s``: ``d Phi / d c_a = c_b x v`` and
    ``d Phi / d c_b = v x c_a``.
    """
    if la < 3 and lb < 3:
        return
    s = _line_sum_cross(lam, la, lb)
    if not (abs(s) > _PARALLEL_TOL):
        return
    wmu = w[0] * mu_k[0] + w[1] * mu_k[1] + w[2] * mu_k[2]
    v0 = (w[0] - wmu) / s
    v1 = (w[1] - wmu) / s
    v2 = (w[2] - wmu) / s
    if la >= 3:
        cb0 = _line(lam, lb, 0)
        cb1 = _line(lam, lb, 1)
        cb2 = _line(lam, lb, 2)
        gphi[la - 3] += cb1 * v2 - cb2 * v1
        gphi[4 + la - 3] += cb2 * v0 - cb0 * v2
        gphi[8 + la - 3] += cb0 * v1 - cb1 * v0
    if lb >= 3:
        ca0 = _line(lam, la, 0)
        ca1 = _line(lam, la, 1)
        ca2 = _line(lam, la, 2)
        gphi[lb - 3] += v1 * ca2 - v2 * ca1
        gphi[4 + lb - 3] += v2 * ca0 - v0 * ca2
        gphi[8 + lb - 3] += v0 * ca1 - v1 * ca0


@njit(cache=True, fastmath=FMA)
def _vertex_jacobian(lam, mu_k, la, lb, jac, idx):
    """Live columns of ``d mu / d Lam`` for the vertex on lines la, lb.

    Writes ``jac[:, :nc]`` (3, nc) and their Lam indices ``idx[:nc]``; returns ``(s, nc)`` with
    ``s = sum(c_a x c_b)`` (``inf`` and ``nc = 0`` when the lines are parallel to rounding).
    """
    if la < 3 and lb < 3:
        return 1.0, 0
    s = _line_sum_cross(lam, la, lb)
    if not (abs(s) > _PARALLEL_TOL):
        # the two lines are parallel to rounding (an edge lying in a face plane): the vertex
        # does not move to first order in any direction we can resolve; report no motion
        return np.inf, 0
    inv = 1.0 / s
    nc = 0
    for col in range(6):
        if (col < 3 and la < 3) or (col >= 3 and lb < 3):
            continue
        d0, d1, d2 = _dm_column(lam, la, lb, col)
        sd = d0 + d1 + d2
        jac[0, nc] = (d0 - mu_k[0] * sd) * inv
        jac[1, nc] = (d1 - mu_k[1] * sd) * inv
        jac[2, nc] = (d2 - mu_k[2] * sd) * inv
        idx[nc] = 4 * (col % 3) + (la if col < 3 else lb) - 3
        nc += 1
    return s, nc


@njit(cache=True, fastmath=FMA)
def _dm_column(lam, la, lb, col):
    """Column ``col`` (0..5) of d m / d (c_a, c_b), m = c_a x c_b: e_i x c_b or c_a x e_i."""
    if col < 3:
        i = col
        c0 = _line(lam, lb, 0)
        c1 = _line(lam, lb, 1)
        c2 = _line(lam, lb, 2)
        if i == 0:
            return 0.0, -c2, c1
        if i == 1:
            return c2, 0.0, -c0
        return -c1, c0, 0.0
    i = col - 3
    c0 = _line(lam, la, 0)
    c1 = _line(lam, la, 1)
    c2 = _line(lam, la, 2)
    if i == 0:
        return 0.0, c2, -c1
    if i == 1:
        return -c2, 0.0, c0
    return c1, -c0, 0.0


@njit(cache=True, fastmath=FMA)
def _vertex_curvature(lam, mu_k, la, lb, s, w, hphi):
    """``hphi += sum_r w_r d2 mu_r / d Lam2`` for the vertex on lines la, lb."""
    if (la < 3 and lb < 3) or not np.isfinite(s):
        return
    wmu = w[0] * mu_k[0] + w[1] * mu_k[1] + w[2] * mu_k[2]
    inv2 = 1.0 / (s * s)
    # d2 mu_r / dm_t dm_u = (2 mu_r - delta_rt - delta_ru) / s^2, contracted with w:
    # Wm = (2 w.mu - w_t - w_u) / s^2, then hphi += dm^T Wm dm over the live columns
    for al in range(6):
        if (al < 3 and la < 3) or (al >= 3 and lb < 3):
            continue
        ra = 4 * (al % 3) + (la if al < 3 else lb) - 3
        a0, a1, a2 = _dm_column(lam, la, lb, al)
        sa = a0 + a1 + a2
        wa = w[0] * a0 + w[1] * a1 + w[2] * a2
        for be in range(6):
            if (be < 3 and la < 3) or (be >= 3 and lb < 3):
                continue
            rb = 4 * (be % 3) + (la if be < 3 else lb) - 3
            b0, b1, b2 = _dm_column(lam, la, lb, be)
            sb = b0 + b1 + b2
            wb = w[0] * b0 + w[1] * b1 + w[2] * b2
            # sum_tu a_t (2 wmu - w_t - w_u) b_u = 2 wmu sa sb - wa sb - sa wb
            hphi[ra, rb] += (2.0 * wmu * sa * sb - wa * sb - sa * wb) * inv2
    if la >= 3 and lb >= 3:
        # d2 m / dc_a[i] dc_b[i'] = e_i x e_i', contracted with v = (d mu / d m)^T w
        v0 = (w[0] - wmu) / s
        v1 = (w[1] - wmu) / s
        v2 = (w[2] - wmu) / s
        for i in range(3):
            for i2 in range(3):
                if i == i2:
                    continue
                # v . (e_i x e_i2) = levi-civita(i, i2, third) * v_third
                t = 3 - i - i2
                sign = 1.0 if (i2 - i) % 3 == 1 else -1.0
                vt = v0 if t == 0 else (v1 if t == 1 else v2)
                val = sign * vt
                hphi[4 * i + la - 3, 4 * i2 + lb - 3] += val
                hphi[4 * i2 + lb - 3, 4 * i + la - 3] += val


# not inlined into `area_pair` either: it runs once per pair when the Hessian is wanted, and
# compiling it on its own shortens the first run's compilation further
@njit(cache=True, fastmath=FMA)
def assemble_phi_hessian(lam, dt, mu, vlab, n, wmu, jmu, jidx, ncol, blk, hphi, cg):
    """``hphi += J^T B J + sum_k w_k . d2 mu_k``: the Hessian blocks over (mu_0.., G) pulled
    back to Lam through the sparse vertex Jacobians (at most 6 live columns each) and
    ``d G_i / d Lam_ij = d_j``. ``cg`` (12, >= 3) is scratch: the (mu, G) blocks pulled back
    on the mu side are summed there over the vertices and multiplied by ``d`` once."""
    for r in range(12):
        cg[r, 0] = 0.0
        cg[r, 1] = 0.0
        cg[r, 2] = 0.0
    for k in range(n):
        s, nc = _vertex_jacobian(lam, mu[0, k], vlab[0, k, 0], vlab[0, k, 1], jmu[k], jidx[k])
        ncol[k] = nc
        _vertex_curvature(lam, mu[0, k], vlab[0, k, 0], vlab[0, k, 1], s, wmu[k], hphi)
    for k in range(n):
        k1 = k + 1 if k + 1 < n else 0
        nc = ncol[k]
        nc1 = ncol[k1]
        for a in range(nc):
            ia = jidx[k, a]
            # row a of J_k^T B_kk, J_k^T B_k,k+1 and J_k^T B_kG
            t0 = t1 = t2 = 0.0
            u0 = u1 = u2 = 0.0
            c0 = c1 = c2 = 0.0
            for r in range(3):
                jr = jmu[k, r, a]
                t0 += jr * blk[0, k, r, 0]
                t1 += jr * blk[0, k, r, 1]
                t2 += jr * blk[0, k, r, 2]
                u0 += jr * blk[1, k, r, 0]
                u1 += jr * blk[1, k, r, 1]
                u2 += jr * blk[1, k, r, 2]
                c0 += jr * blk[2, k, r, 0]
                c1 += jr * blk[2, k, r, 1]
                c2 += jr * blk[2, k, r, 2]
            for b in range(nc):
                hphi[ia, jidx[k, b]] += t0 * jmu[k, 0, b] + t1 * jmu[k, 1, b] + t2 * jmu[k, 2, b]
            for b in range(nc1):
                val = u0 * jmu[k1, 0, b] + u1 * jmu[k1, 1, b] + u2 * jmu[k1, 2, b]
                hphi[ia, jidx[k1, b]] += val
                hphi[jidx[k1, b], ia] += val
            cg[ia, 0] += c0
            cg[ia, 1] += c1
            cg[ia, 2] += c2
    for r in range(12):
        for i in range(3):
            ci = cg[r, i]
            if ci != 0.0:
                for j in range(4):
                    hphi[r, 4 * i + j] += ci * dt[j]
                    hphi[4 * i + j, r] += ci * dt[j]
    for i in range(3):
        for i2 in range(3):
            bg = blk[3, 0, i, i2]
            for j in range(4):
                for j2 in range(4):
                    hphi[4 * i + j, 4 * i2 + j2] += bg * dt[j] * dt[j2]


@njit(cache=True, fastmath=FMA)
def clip_shift_jacobian(xs, ds):
    """``ds[a, 3 m + b] = d s_a / d x_mb`` of the clip shift s (`geometry.clip`), exactly.

    With ``n = (x1 - x0) x (x2 - x0)``, ``N = |n|``, ``a = x1 - x0``, ``L = |a|`` and
    ``C = CLIP_SHIFT``: ``s = C N^(-1/2) n + C t1 N^(1/2) L^(-1) a + C t2 N^(-1/2) L^(-1) (n x
    a)`` ((t1, t2) = SHIFT_TANGENT), differentiated with ``dN = n . dn / N``, ``dL = a . da /
    L`` and, for a move ``e`` of corner 0, 1, 2: ``(da, dn) = (-e, e x (a - b))``, ``(e, e x
    b)``, ``(0, a x e)`` (``b = x2 - x0``). Called only for triangles of non-zero area.
    """
    ax, ay, az, bx, by, bz, nx, ny, nz = edges_and_normal(xs)
    # n x a
    wx = ny * az - nz * ay
    wy = nz * ax - nx * az
    wz = nx * ay - ny * ax
    nn = np.sqrt(nx * nx + ny * ny + nz * nz)
    ll = np.sqrt(ax * ax + ay * ay + az * az)
    rn = 1.0 / np.sqrt(nn)  # N^(-1/2)
    il = 1.0 / ll
    c0 = CLIP_SHIFT * rn  # coefficient of n
    c1 = CLIP_SHIFT * SHIFT_TANGENT[0] * nn * rn * il  # of a (N^(1/2) = N N^(-1/2))
    c2 = CLIP_SHIFT * SHIFT_TANGENT[1] * rn * il  # of n x a
    for m in range(3):
        for b in range(3):
            ex = 1.0 if b == 0 else 0.0
            ey = 1.0 if b == 1 else 0.0
            ez = 1.0 if b == 2 else 0.0
            if m == 0:
                dax, day, daz = -ex, -ey, -ez
                # e x (a - b)
                px, py, pz = ax - bx, ay - by, az - bz
                dnx = ey * pz - ez * py
                dny = ez * px - ex * pz
                dnz = ex * py - ey * px
            elif m == 1:
                dax, day, daz = ex, ey, ez
                dnx = ey * bz - ez * by
                dny = ez * bx - ex * bz
                dnz = ex * by - ey * bx
            else:
                dax, day, daz = 0.0, 0.0, 0.0
                dnx = ay * ez - az * ey
                dny = az * ex - ax * ez
                dnz = ax * ey - ay * ex
            dlog_n = (nx * dnx + ny * dny + nz * dnz) / (nn * nn)  # dN / N
            dlog_l = (ax * dax + ay * day + az * daz) * il * il  # dL / L
            # d(n x a) = dn x a + n x da
            dwx = dny * az - dnz * ay + ny * daz - nz * day
            dwy = dnz * ax - dnx * az + nz * dax - nx * daz
            dwz = dnx * ay - dny * ax + nx * day - ny * dax
            # d c0 = -c0 dN / 2N, d c1 = c1 (dN / 2N - dL / L), d c2 = -c2 (dN / 2N + dL / L)
            f0 = -0.5 * dlog_n * c0
            f1 = (0.5 * dlog_n - dlog_l) * c1
            f2 = -(0.5 * dlog_n + dlog_l) * c2
            col = 3 * m + b
            ds[0, col] = f0 * nx + c0 * dnx + f1 * ax + c1 * dax + f2 * wx + c2 * dwx
            ds[1, col] = f0 * ny + c0 * dny + f1 * ay + c1 * day + f2 * wy + c2 * dwy
            ds[2, col] = f0 * nz + c0 * dnz + f1 * az + c1 * daz + f2 * wz + c2 * dwz


@njit(cache=True, fastmath=FMA)
def shift_rows(g, ds):
    """``g[:9] <- T^T g[:9]``, ``T = I + [ds; ds; ds]`` (every corner moves by the same s)."""
    g0 = g[0] + g[3] + g[6]
    g1 = g[1] + g[4] + g[7]
    g2 = g[2] + g[5] + g[8]
    for c in range(9):
        g[c] += g0 * ds[0, c] + g1 * ds[1, c] + g2 * ds[2, c]


@njit(cache=True, fastmath=FMA)
def area_hessian(nx, ny, nz, inv_n, dn, ga, zv, ha):
    """``ha = d2 A / d x2`` (9 x 9) of a triangle of normal n = (nx, ny, nz) (``inv_n = 1 /
    |n|``), from ``dn`` and ``ga = d A / d x`` (`area_pair`); ``zv`` (>= 3 x 3) is scratch.

    d2 A = (dn . dn + n . d2n) / (2|n|) - (n . dn)^2 / (2 |n|^3); d E_i / d x_m = +1 if
    m = i - 1, -1 if m = i + 1, and n . (e_b x e_a) = zv[a, b] (the cross-product matrix of n).
    """
    zv[0, 0] = 0.0
    zv[0, 1] = -nz
    zv[0, 2] = ny
    zv[1, 0] = nz
    zv[1, 1] = 0.0
    zv[1, 2] = -nx
    zv[2, 0] = -ny
    zv[2, 1] = nx
    zv[2, 2] = 0.0
    for i in range(3):
        for m in range(3):
            sgn = 0.0 if m == i else (1.0 if m == (i + 2) % 3 else -1.0)
            for a in range(3):
                r = 3 * i + a
                for b in range(3):
                    c = 3 * m + b
                    val = dn[r, 0] * dn[c, 0] + dn[r, 1] * dn[c, 1] + dn[r, 2] * dn[c, 2]
                    ha[r, c] = (0.5 * (val + sgn * zv[a, b]) - 2.0 * ga[r] * ga[c]) * inv_n
