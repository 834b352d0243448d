"""Numba pair kernels of the material-depth penalty contact energy, with exact derivatives.

Two integrations of the same penalty energy density ``(eps/2) g^2`` (``g`` = material depth,
P1-interpolated in the current tetrahedron):

* area integration (the paper's method), one (boundary triangle T, tetrahedron K) pair:
  ``E = (eps/2) int_{T cap K} g_K^2 dA = eps * A_T * Phi(Lam)``, with ``A_T`` the current area of
  T, ``Lam[i, j] = lambda_j(x_i)`` the barycentric coordinates of the triangle vertices in K and
  ``Phi = int_P (G . mu)^2 dxi`` over the clipped polygon P of the parameter simplex
  (``G = Lam @ d``). 21 dofs: triangle vertices 0..2 then tetrahedron vertices 0..3, xyz
  interleaved.
* point collocation (baseline), one (boundary vertex a, tetrahedron K) pair:
  ``E = (eps/2) W_a g_K(x_a)^2`` if ``x_a`` is in K (all barycentrics >= 0), else 0. 15 dofs.

Gradients and Hessians are the exact derivatives of these per-pair energies (including the
motion of polygon edges that lie on tetrahedron faces); see ``docs/kernels.md`` for the
derivation: ``Phi`` is differentiated with respect to the 12 numbers ``Lam`` through the
polygon vertices (each the meeting point of two lines whose coefficients are columns of
``Lam``), then the chain rule through ``Lam(x)`` and ``A_T(x)`` uses the closed forms
``d lambda_j / d y = grad lambda_j`` and ``d lambda_j / d X_k = -lambda_k grad lambda_j``.

Units: coordinates in length, depths in length, penalty in pressure / length, energies in
energy; gradients in energy / length, Hessians in energy / length^2.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from fenics_matdepth._constants import FLOAT, INDEX
from fenics_matdepth.geometry.clip import (
    CLIP_SHIFT,
    MAX_POLYGON_VERTICES,
    SHIFT_TANGENT,
    clip_triangle,
    edges_and_normal,
    tet_gradients,
    triangle_area2,
    triangle_rows,
)
from fenics_matdepth.geometry.intersect import intersect_pairs

__all__ = [
    "augmented_pair_energy",
    "collocation_energy",
    "pair_energy",
    "pressure_moments",
]

_NV = MAX_POLYGON_VERTICES
# triangle of the single-pair helper (its tetrahedron is 3..6)
_ONE_TRI = np.array([[0, 1, 2]], dtype=INDEX)
#: Below this |sum(c_a x c_b)| two polygon lines are taken as parallel (derivative guard; the
#: coefficients are barycentric values of order one, so this only catches exact parallelism).
_PARALLEL_TOL = 1e-100
#: Floating-point licence of the pair kernels: "contract" lets LLVM fuse a multiplication and
#: an addition into one fused multiply-add (one rounding instead of two); with it the Hessian
#: pass takes about 0.81 of the time it takes without (docs/kernels.md). No other fast-math
#: licence: NaN and inf propagate and sums keep their order. The clip (geometry/clip.py), whose
#: signs decide which pairs intersect, is compiled without it.
_FMA = {"contract"}


@njit(cache=True, fastmath=_FMA)
def _area_work():
    """Scratch arrays of one area-integration kernel call (allocated once per driver call)."""
    return (
        np.empty((4, 3), dtype=FLOAT),  # 0 grads: barycentric gradients of the tetrahedron
        np.empty((3, 4), dtype=FLOAT),  # 1 lam
        np.empty((2, _NV, 3), dtype=FLOAT),  # 2 mu (clipper buffers)
        np.empty((2, _NV, 2), dtype=np.int64),  # 3 vertex labels
        np.empty((2, _NV), dtype=np.int64),  # 4 edge labels
        np.empty((_NV, 3, 6), dtype=FLOAT),  # 5 d mu_k / d Lam, live columns only
        np.empty((_NV, 3), dtype=FLOAT),  # 6 d Phi / d mu_k
        np.empty(12, dtype=FLOAT),  # 7 d Phi / d Lam
        np.empty((12, 12), dtype=FLOAT),  # 8 d2 Phi / d Lam2
        np.empty((_NV, 6), dtype=np.int64),  # 9 Lam index of the live columns of 5
        np.empty((4, _NV, 3, 3), dtype=FLOAT),  # 10 Hessian blocks over (mu_k, G)
        np.empty((9, 9), dtype=FLOAT),  # 11 T: Hessian of Phi w.r.t. triangle vertices
        np.empty((9, 12), dtype=FLOAT),  # 12 V: triangle-tetrahedron block of J^T H_Lam J
        np.empty((12, 9), dtype=FLOAT),  # 13 U
        np.empty(21, dtype=FLOAT),  # 14 d Phi / d x
        np.empty(9, dtype=FLOAT),  # 15 d A / d x
        np.empty((9, 9), dtype=FLOAT),  # 16 d2 A / d x2
        np.empty((3, 3), dtype=FLOAT),  # 17 W[i] = sum_j dPhi/dLam_ij grad lambda_j
        np.empty((9, 3), dtype=FLOAT),  # 18 dn[3 i + a] = d (triangle normal) / d x_ia
        np.empty(_NV, dtype=np.int64),  # 19 number of live columns per vertex
        np.empty((3, 9), dtype=FLOAT),  # 20 vectors of an edge integrand's Hessian; scratch
        np.empty((3, 9), dtype=FLOAT),  # 21 d (clip shift) / d x_tri
        # 22 the triangle cache: [this pair's triangle (-1: unknown), the triangle whose
        # quantities 15, 16, 18 and 21 hold, what they hold (1: to the gradient, 2: and d2 A)]
        np.full(3, -1, dtype=np.int64),
    )


@njit(cache=True, fastmath=_FMA)
def _line(lam, label, r):
    """Component r of the homogeneous coefficient vector of line ``label`` (0..6)."""
    if label < 3:
        return 1.0 if r == label else 0.0
    return lam[r, label - 3]


@njit(cache=True, fastmath=_FMA)
def _line_sum_cross(lam, la, lb):
    """``s = sum(c_a x c_b)`` (the homogeneous weight of the vertex on lines la, lb)."""
    ca0 = _line(lam, la, 0)
    ca1 = _line(lam, la, 1)
    ca2 = _line(lam, la, 2)
    cb0 = _line(lam, lb, 0)
    cb1 = _line(lam, lb, 1)
    cb2 = _line(lam, lb, 2)
    return (ca1 * cb2 - ca2 * cb1) + (ca2 * cb0 - ca0 * cb2) + (ca0 * cb1 - ca1 * cb0)


@njit(cache=True, fastmath=_FMA)
def _vertex_gradient(lam, mu_k, la, lb, w, gphi):
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


@njit(cache=True, fastmath=_FMA)
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


@njit(cache=True, fastmath=_FMA)
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


@njit(cache=True, fastmath=_FMA)
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


# not inlined into `_area_pair` either: it runs once per pair when the Hessian is wanted, and
# compiling it on its own shortens the first run's compilation further
@njit(cache=True, fastmath=_FMA)
def _assemble_phi_hessian(lam, dt, mu, vlab, n, wmu, jmu, jidx, ncol, blk, hphi, cg):
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


@njit(cache=True, fastmath=_FMA)
def _clip_shift_jacobian(xs, ds):
    """``ds[a, 3 m + b] = d s_a / d x_mb`` of the clip shift s (`_clip_shift`), exactly.

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


@njit(cache=True, fastmath=_FMA)
def _shift_rows(g, ds):
    """``g[:9] <- T^T g[:9]``, ``T = I + [ds; ds; ds]`` (every corner moves by the same s)."""
    g0 = g[0] + g[3] + g[6]
    g1 = g[1] + g[4] + g[7]
    g2 = g[2] + g[5] + g[8]
    for c in range(9):
        g[c] += g0 * ds[0, c] + g1 * ds[1, c] + g2 * ds[2, c]


@njit(cache=True, fastmath=_FMA)
def _area_hessian(nx, ny, nz, inv_n, dn, ga, zv, ha):
    """``ha = d2 A / d x2`` (9 x 9) of a triangle of normal n = (nx, ny, nz) (``inv_n = 1 /
    |n|``), from ``dn`` and ``ga = d A / d x`` (`_area_pair`); ``zv`` (>= 3 x 3) is scratch.

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


# A function of its own, called from the pair loops, not inlined there (inline="always"):
# numba's IR inlining of this large kernel made the first run's compilation about three
# times longer, for no measurable gain in speed (docs/solvers.md, start-up). The same holds
# for every helper of this module and of geometry/clip.py: none is IR-inlined any more.
@njit(cache=True, fastmath=_FMA)
def _no_contribution(grad, hess, p, n, want_grad, want_hess):
    """Zero row p of the wanted outputs (n dofs a pair) of a pair that does not contribute;
    returns -1.0."""
    if want_grad:
        for c in range(n):
            grad[p, c] = 0.0
    if want_hess:
        for c in range(n):
            for c2 in range(n):
                hess[p, c, c2] = 0.0
    return -1.0


@njit(cache=True, fastmath=_FMA)
def _area_pair(xs, xt, dt, offset, penalty, want_grad, want_hess, work, grad, hess, p):
    """Area-integration energy of one (triangle, tetrahedron) pair.

    Args:
        xs: (3, 3) triangle vertices; xt: (4, 3) tetrahedron vertices (length).
        dt: (4,) material depths of the tetrahedron vertices (length).
        offset: (3,) constant added to the integrand's value at each triangle vertex,
            ``G_i = sum_j Lam_ij d_j + offset_i`` (length; zeros for the plain penalty energy,
            ``p_i / eps`` for the augmented Lagrangian, see `_area_pairs_augmented`). Being
            constant, it adds nothing to ``d G / d Lam``.
        penalty: eps (pressure / length).
        want_grad, want_hess: which derivatives to write.
        work: tuple from `_area_work`.
        grad: (np, 21) output, row p written if want_grad; hess: (np, 21, 21) output, block p
            written if want_hess (rows of the outputs are indexed here, not sliced: a view per
            pair costs reference counting).
        p: the output row.

    Returns:
        The pair energy (>= 0), or -1.0 (with zero outputs) when the pair does not contribute:
        empty intersection, flat tetrahedron or zero-area triangle.
    """
    (
        grads,
        lam,
        mu,
        vlab,
        elab,
        jmu,
        wmu,
        gphi,
        hphi,
        jidx,
        blk,
        tt,
        vv,
        uu,
        gx,
        ga,
        ha,
        ww,
        dn,
        ncol,
        zv,
        ds,
        tri_state,
    ) = work
    # a contributing pair writes every entry of its outputs; the others are zeroed here
    a2 = triangle_area2(xs)
    if a2 == 0.0:
        return _no_contribution(grad, hess, p, 21, want_grad, want_hess)
    if tet_gradients(xt, grads) == 0.0:
        return _no_contribution(grad, hess, p, 21, want_grad, want_hess)
    triangle_rows(xs, xt, grads, lam)
    n = clip_triangle(lam, mu, vlab, elab)
    if n < 3:
        return _no_contribution(grad, hess, p, 21, want_grad, want_hess)
    area = 0.5 * a2
    g0 = lam[0, 0] * dt[0] + lam[0, 1] * dt[1] + lam[0, 2] * dt[2] + lam[0, 3] * dt[3]
    g1 = lam[1, 0] * dt[0] + lam[1, 1] * dt[1] + lam[1, 2] * dt[2] + lam[1, 3] * dt[3]
    g2 = lam[2, 0] * dt[0] + lam[2, 1] * dt[1] + lam[2, 2] * dt[2] + lam[2, 3] * dt[3]
    g0 += offset[0]
    g1 += offset[1]
    g2 += offset[2]

    # ---- Phi and its derivatives with respect to Lam (fan of signed triangles from mu = e_0)
    phi = 0.0
    wg0 = 0.0
    wg1 = 0.0
    wg2 = 0.0
    if want_grad:
        for k in range(n):
            for r in range(3):
                wmu[k, r] = 0.0
    if want_hess:
        for c in range(12):
            for c2 in range(12):
                hphi[c, c2] = 0.0
        # blk[0, k] = d2Phi/dmu_k2, blk[1, k] = d2Phi/dmu_k dmu_k+1, blk[2, k] = d2Phi/dmu_k dG,
        # blk[3, 0] = d2Phi/dG2: each edge's 9 x 9 Hessian is added into these blocks first
        for b in range(4):
            for k in range(n):
                for r in range(3):
                    for c in range(3):
                        blk[b, k, r, c] = 0.0
    for k in range(n):
        k1 = k + 1 if k + 1 < n else 0
        p0 = mu[0, k, 0]
        p1 = mu[0, k, 1]
        p2 = mu[0, k, 2]
        q0 = mu[0, k1, 0]
        q1 = mu[0, k1, 1]
        q2 = mu[0, k1, 2]
        dd = (p1 * q2 - p2 * q1) / 12.0
        va = g0
        vb = g0 * p0 + g1 * p1 + g2 * p2
        vc = g0 * q0 + g1 * q1 + g2 * q2
        qq = va * va + vb * vb + vc * vc + va * vb + vb * vc + vc * va
        phi += dd * qq
        if not want_grad:
            continue
        qa = 2.0 * va + vb + vc
        qb = 2.0 * vb + va + vc
        qc = 2.0 * vc + va + vb
        # gradient of f = dd * qq over (p, q, G)
        wmu[k, 0] += dd * qb * g0
        wmu[k, 1] += qq * q2 / 12.0 + dd * qb * g1
        wmu[k, 2] += -qq * q1 / 12.0 + dd * qb * g2
        wmu[k1, 0] += dd * qc * g0
        wmu[k1, 1] += -qq * p2 / 12.0 + dd * qc * g1
        wmu[k1, 2] += qq * p1 / 12.0 + dd * qc * g2
        wg0 += dd * (qa + qb * p0 + qc * q0)
        wg1 += dd * (qb * p1 + qc * q1)
        wg2 += dd * (qb * p2 + qc * q2)
        if not want_hess:
            continue
        # Hessian of f = dd qq over z = (p, q, G), block by block (dd bilinear in p and q, qq
        # quadratic in (va, vb, vc) = (G_0, G . p, G . q) with Hessian I + 1 1^T):
        #   d2f/dp2 = qb (dp G^T + G dp^T) + 2 dd G G^T, the same in q with (qc, dq),
        #   d2f/dp dq = qq D + qc dp G^T + qb G dq^T + dd G G^T (D: d2 dd / dp dq),
        #   d2f/dp dG = dp gG^T + dd (G (2 p + q + e_0)^T + qb I), the same in q,
        #   d2f/dG2 = dd (p p^T + q q^T + s s^T + e_0 e_0^T), s = p + q + e_0,
        # with dp = d dd / dp, dq = d dd / dq and gG = d qq / dG
        zv[0, 0] = g0
        zv[0, 1] = g1
        zv[0, 2] = g2
        zv[0, 3] = 0.0  # dp
        zv[0, 4] = q2 / 12.0
        zv[0, 5] = -q1 / 12.0
        zv[0, 6] = 0.0  # dq
        zv[0, 7] = -p2 / 12.0
        zv[0, 8] = p1 / 12.0
        zv[1, 0] = qa + qb * p0 + qc * q0  # gG
        zv[1, 1] = qb * p1 + qc * q1
        zv[1, 2] = qb * p2 + qc * q2
        zv[1, 3] = 2.0 * p0 + q0 + 1.0  # 2 p + q + e_0
        zv[1, 4] = 2.0 * p1 + q1
        zv[1, 5] = 2.0 * p2 + q2
        zv[1, 6] = 2.0 * q0 + p0 + 1.0  # 2 q + p + e_0
        zv[1, 7] = 2.0 * q1 + p1
        zv[1, 8] = 2.0 * q2 + p2
        zv[2, 0] = p0 + q0 + 1.0  # s
        zv[2, 1] = p1 + q1
        zv[2, 2] = p2 + q2
        for r in range(3):
            gr = zv[0, r]
            dpr = zv[0, 3 + r]
            dqr = zv[0, 6 + r]
            pr = mu[0, k, r]
            qr = mu[0, k1, r]
            sr = zv[2, r]
            for c in range(3):
                gc = zv[0, c]
                ggd = dd * gr * gc
                blk[0, k, r, c] += qb * (dpr * gc + gr * zv[0, 3 + c]) + 2.0 * ggd
                blk[0, k1, r, c] += qc * (dqr * gc + gr * zv[0, 6 + c]) + 2.0 * ggd
                blk[1, k, r, c] += qc * dpr * gc + qb * gr * zv[0, 6 + c] + ggd
                blk[2, k, r, c] += dpr * zv[1, c] + dd * gr * zv[1, 3 + c]
                blk[2, k1, r, c] += dqr * zv[1, c] + dd * gr * zv[1, 6 + c]
                blk[3, 0, r, c] += dd * (pr * mu[0, k, c] + qr * mu[0, k1, c] + sr * zv[2, c])
            blk[2, k, r, r] += dd * qb
            blk[2, k1, r, r] += dd * qc
        blk[3, 0, 0, 0] += dd
        blk[1, k, 1, 2] += qq / 12.0
        blk[1, k, 2, 1] -= qq / 12.0

    energy = penalty * area * phi
    if not want_grad:
        return energy

    for j in range(4):
        gphi[j] = wg0 * dt[j]
        gphi[4 + j] = wg1 * dt[j]
        gphi[8 + j] = wg2 * dt[j]
    for k in range(n):
        _vertex_gradient(lam, mu[0, k], vlab[0, k, 0], vlab[0, k, 1], wmu[k], gphi)
    if want_hess:
        _assemble_phi_hessian(lam, dt, mu, vlab, n, wmu, jmu, jidx, ncol, blk, hphi, uu)

    # ---- chain rule through Lam(x): d Lam_ij / d x_i = grad_j, d Lam_ij / d X_k = -Lam_ik grad_j
    for i in range(3):
        for a in range(3):
            acc = 0.0
            for j in range(4):
                acc += gphi[4 * i + j] * grads[j, a]
            ww[i, a] = acc
    for i in range(3):
        for a in range(3):
            gx[3 * i + a] = ww[i, a]
    for k in range(4):
        for a in range(3):
            gx[9 + 3 * k + a] = -(
                lam[0, k] * ww[0, a] + lam[1, k] * ww[1, a] + lam[2, k] * ww[2, a]
            )

    # ---- area and its derivatives: dn/dx_i [delta] = E_i x delta, E_i = x_{i-1} - x_{i+1}
    nx = (xs[1, 1] - xs[0, 1]) * (xs[2, 2] - xs[0, 2]) - (xs[1, 2] - xs[0, 2]) * (
        xs[2, 1] - xs[0, 1]
    )
    ny = (xs[1, 2] - xs[0, 2]) * (xs[2, 0] - xs[0, 0]) - (xs[1, 0] - xs[0, 0]) * (
        xs[2, 2] - xs[0, 2]
    )
    nz = (xs[1, 0] - xs[0, 0]) * (xs[2, 1] - xs[0, 1]) - (xs[1, 1] - xs[0, 1]) * (
        xs[2, 0] - xs[0, 0]
    )
    inv_n = 1.0 / a2
    # What depends on the triangle alone (dn, d A / d x, the clip shift's Jacobian, d2 A) is
    # computed once for the pairs of one triangle that come one after the other, eight on
    # average at a flat interface; the caller names the pair's triangle in tri_state[0].
    fresh = tri_state[0] < 0 or tri_state[1] != tri_state[0]
    if fresh:
        for i in range(3):
            im = (i + 2) % 3
            ip = (i + 1) % 3
            ex = xs[im, 0] - xs[ip, 0]
            ey = xs[im, 1] - xs[ip, 1]
            ez = xs[im, 2] - xs[ip, 2]
            dn[3 * i + 0, 0] = 0.0
            dn[3 * i + 0, 1] = ez
            dn[3 * i + 0, 2] = -ey
            dn[3 * i + 1, 0] = -ez
            dn[3 * i + 1, 1] = 0.0
            dn[3 * i + 1, 2] = ex
            dn[3 * i + 2, 0] = ey
            dn[3 * i + 2, 1] = -ex
            dn[3 * i + 2, 2] = 0.0
        for r in range(9):
            ga[r] = 0.5 * (nx * dn[r, 0] + ny * dn[r, 1] + nz * dn[r, 2]) * inv_n
        _clip_shift_jacobian(xs, ds)
        tri_state[1] = tri_state[0]
        tri_state[2] = 1
    # Phi is evaluated at the shifted corners y_i = x_i + s(x_tri) (the clip shift): its
    # triangle gradient is T^T dPhi/dy with T = dy/dx = I + [ds/dx] for every corner
    _shift_rows(gx, ds)

    for c in range(9):
        grad[p, c] = penalty * (phi * ga[c] + area * gx[c])
    for c in range(9, 21):
        grad[p, c] = penalty * area * gx[c]
    if not want_hess:
        return energy

    if fresh or tri_state[2] < 2:
        _area_hessian(nx, ny, nz, inv_n, dn, ga, zv, ha)
        tri_state[2] = 2

    # J^T H_Lam J with J_(ij) = p_i (x) grad_j, p_i = (e_i, -Lam[i, :]) over the 7 vertices:
    # tt = (I (x) grads^T) H_Lam (I (x) grads) over the triangle corners is the triangle block;
    # the tetrahedron's rows and columns are -sum_i Lam[i, k] times the corners'
    for r in range(12):
        for i2 in range(3):
            for b in range(3):
                acc = 0.0
                for j2 in range(4):
                    acc += hphi[r, 4 * i2 + j2] * grads[j2, b]
                uu[r, 3 * i2 + b] = acc
    for i in range(3):
        for a in range(3):
            for c in range(9):
                acc = 0.0
                for j in range(4):
                    acc += grads[j, a] * uu[4 * i + j, c]
                tt[3 * i + a, c] = acc
    # vv[:, 3 k + b] (9 x 12): the triangle-tetrahedron block without the second derivatives
    for r in range(9):
        for k in range(4):
            for b in range(3):
                vv[r, 3 * k + b] = -(
                    lam[0, k] * tt[r, b] + lam[1, k] * tt[r, 3 + b] + lam[2, k] * tt[r, 6 + b]
                )
    # the blocks of H_Phi over x, upper block triangle only (mirrored in the product rule):
    # triangle-tetrahedron, with sum_ij dPhi/dLam_ij d2 Lam_ij = -grads[k, a] ww[i, b]
    for i in range(3):
        for a in range(3):
            r = 3 * i + a
            for k in range(4):
                for b in range(3):
                    hess[p, r, 9 + 3 * k + b] = vv[r, 3 * k + b] - grads[k, a] * ww[i, b]
    # tetrahedron-tetrahedron, with sum_i (lam_il ww_ia grads_kb + lam_ik grads_la ww_ib), where
    # the tetrahedron part of gx holds -sum_i lam_ik ww_ia
    for k in range(4):
        for l in range(k, 4):
            for a in range(3):
                for b in range(3):
                    hess[p, 9 + 3 * k + a, 9 + 3 * l + b] = -(
                        lam[0, k] * vv[a, 3 * l + b]
                        + lam[1, k] * vv[3 + a, 3 * l + b]
                        + lam[2, k] * vv[6 + a, 3 * l + b]
                    ) - (gx[9 + 3 * l + a] * grads[k, b] + gx[9 + 3 * k + b] * grads[l, a])
    # the clip shift: T^T H T on the triangle rows and columns, T = I + [ds; ds; ds] (the
    # second derivatives of the shift, of relative size CLIP_SHIFT, are left out): the
    # triangle block from both sides, the triangle-tetrahedron block from the left
    for r in range(9):  # tt T
        s0 = tt[r, 0] + tt[r, 3] + tt[r, 6]
        s1 = tt[r, 1] + tt[r, 4] + tt[r, 7]
        s2 = tt[r, 2] + tt[r, 5] + tt[r, 8]
        for c in range(9):
            zv[0, c] = s0 * ds[0, c] + s1 * ds[1, c] + s2 * ds[2, c]
        for c in range(9):
            tt[r, c] += zv[0, c]
    for c in range(9):  # T^T (tt T)
        s0 = tt[0, c] + tt[3, c] + tt[6, c]
        s1 = tt[1, c] + tt[4, c] + tt[7, c]
        s2 = tt[2, c] + tt[5, c] + tt[8, c]
        for r in range(9):
            tt[r, c] += s0 * ds[0, r] + s1 * ds[1, r] + s2 * ds[2, r]
    for c in range(9, 21):
        s0 = hess[p, 0, c] + hess[p, 3, c] + hess[p, 6, c]
        s1 = hess[p, 1, c] + hess[p, 4, c] + hess[p, 7, c]
        s2 = hess[p, 2, c] + hess[p, 5, c] + hess[p, 8, c]
        for r in range(9):
            hess[p, r, c] += s0 * ds[0, r] + s1 * ds[1, r] + s2 * ds[2, r]
    # E = eps (A Phi): product rule, each block written with its mirror image
    for r in range(9):
        for c in range(9):
            val = area * tt[r, c] + ga[r] * gx[c] + gx[r] * ga[c] + phi * ha[r, c]
            hess[p, r, c] = penalty * val
        for c in range(9, 21):
            val = penalty * (area * hess[p, r, c] + ga[r] * gx[c])
            hess[p, r, c] = val
            hess[p, c, r] = val
    scale = penalty * area
    for k in range(4):
        for l in range(k, 4):
            for a in range(3):
                for b in range(3):
                    val = scale * hess[p, 9 + 3 * k + a, 9 + 3 * l + b]
                    hess[p, 9 + 3 * k + a, 9 + 3 * l + b] = val
                    if l > k:
                        hess[p, 9 + 3 * l + b, 9 + 3 * k + a] = val
    return energy


@njit(cache=True, fastmath=_FMA)
def _is_split(tet, k):
    """Whether tetrahedron k is evaluated as four sub-tetrahedra around its centroid: a fifth
    column of ``tet``, when present, holds the index in ``depth`` of the centroid's depth
    (``-1``: not split)."""
    return tet.shape[1] > 4 and tet[k, 4] >= 0


@njit(cache=True, fastmath=_FMA)
def _gather_tet(x, depth, tet, k, s, split, xt, dt):
    """Vertices ``xt`` (4, 3) and depths ``dt`` (4,) of tetrahedron k, or, when ``split``, of
    its sub-tetrahedron s: vertex s replaced by the centroid (the mean of the four current
    vertices, so linear in them) with the centroid's depth."""
    for a in range(4):
        v = tet[k, a]
        dt[a] = depth[v]
        for r in range(3):
            xt[a, r] = x[v, r]
    if split:
        for r in range(3):
            xt[s, r] = 0.25 * (
                x[tet[k, 0], r] + x[tet[k, 1], r] + x[tet[k, 2], r] + x[tet[k, 3], r]
            )
        dt[s] = depth[tet[k, 4]]


@njit(cache=True, fastmath=_FMA)
def _fold_centroid(grad, hess, row, off, n, s, want_grad, want_hess, acc_g, acc_h):
    """Map sub-tetrahedron s's derivatives (row ``row`` of grad and hess, changed in place) to
    the parent tetrahedron's vertices and add them to ``acc_g`` (n,) and ``acc_h`` (n, n).

    The centroid occupies slot s (dofs ``off + 3 s + r``) and is the mean of the four parent
    vertices (slots 0..3), so with that fixed linear map T: ``grad_parent = T^T grad_sub`` and
    ``hess_parent = T^T hess_sub T``, i.e. a quarter of slot s's row (column) is moved to each
    of the four slots.
    """
    cs = off + 3 * s
    if want_grad:
        for r in range(3):
            q = 0.25 * grad[row, cs + r]
            grad[row, cs + r] = 0.0
            for a in range(4):
                grad[row, off + 3 * a + r] += q
        for c in range(n):
            acc_g[c] += grad[row, c]
    if want_hess:
        for r in range(3):
            for c in range(n):
                q = 0.25 * hess[row, cs + r, c]
                hess[row, cs + r, c] = 0.0
                for a in range(4):
                    hess[row, off + 3 * a + r, c] += q
        for i in range(n):
            for r in range(3):
                q = 0.25 * hess[row, i, cs + r]
                hess[row, i, cs + r] = 0.0
                for a in range(4):
                    hess[row, i, off + 3 * a + r] += q
        for i in range(n):
            for c in range(n):
                acc_h[i, c] += hess[row, i, c]


@njit(cache=True, fastmath=_FMA)
def _store_folded(grad, hess, row, n, want_grad, want_hess, acc_g, acc_h):
    """Write the accumulated parent-tetrahedron derivatives into row ``row``."""
    if want_grad:
        for c in range(n):
            grad[row, c] = acc_g[c]
    if want_hess:
        for i in range(n):
            for c in range(n):
                hess[row, i, c] = acc_h[i, c]


@njit(cache=True, fastmath=_FMA)
def _zero_folded(n, want_grad, want_hess, acc_g, acc_h):
    if want_grad:
        for c in range(n):
            acc_g[c] = 0.0
    if want_hess:
        for i in range(n):
            for c in range(n):
                acc_h[i, c] = 0.0


@njit(cache=True, fastmath=_FMA)
def _area_pairs_core(
    x,
    depth,
    tri,
    tet,
    pair_tri,
    pair_tet,
    penalty,
    want_grad,
    want_hess,
    active,
    energy,
    grad,
    hess,
):
    """The one loop over pairs behind `_area_pairs` and `_area_pairs_into` (a single compiled
    copy of the pair kernel). With a non-empty ``active``, row m of the outputs is the m-th
    contributing pair (``active[m]`` its index); with an empty one, row p is pair p.

    Returns:
        The number of contributing pairs.
    """
    # decided from the data, not passed as a constant: a literal argument would compile a
    # second copy of this large function
    compact = active.shape[0] > 0
    cap = energy.shape[0]
    work = _area_work()
    xs = np.empty((3, 3), dtype=FLOAT)
    xt = np.empty((4, 3), dtype=FLOAT)
    dt = np.empty(4, dtype=FLOAT)
    acc_g = np.empty(21, dtype=FLOAT)
    acc_h = np.empty((21, 21), dtype=FLOAT)
    no_offset = np.zeros(3, dtype=FLOAT)
    m = 0
    for p in range(pair_tri.shape[0]):
        for a in range(3):
            for r in range(3):
                xs[a, r] = x[tri[pair_tri[p], a], r]
        work[22][0] = pair_tri[p]
        k = pair_tet[p]
        split = _is_split(tet, k)
        row = m if compact else p
        fits = row < cap
        wg = want_grad and fits
        wh = want_hess and fits
        out_row = row if fits else 0
        if split:
            _zero_folded(21, wg, wh, acc_g, acc_h)
        e = -1.0
        # a split tetrahedron is four sub-tetrahedra: the pair's energy and derivatives are
        # the sums of theirs, mapped back to the parent's vertices
        for s in range(4 if split else 1):
            _gather_tet(x, depth, tet, k, s, split, xt, dt)
            es = _area_pair(xs, xt, dt, no_offset, penalty, wg, wh, work, grad, hess, out_row)
            if not split:
                e = es
            elif es >= 0.0:
                e = es if e < 0.0 else e + es
                _fold_centroid(grad, hess, out_row, 9, 21, s, wg, wh, acc_g, acc_h)
        if split:
            _store_folded(grad, hess, out_row, 21, wg, wh, acc_g, acc_h)
        if e >= 0.0:
            if fits:
                energy[row] = e
                if compact:
                    active[row] = p
            m += 1
        elif fits and not compact:
            energy[row] = 0.0
    return m


@njit(cache=True, fastmath=_FMA)
def _area_pairs(x, depth, tri, tet, pair_tri, pair_tet, penalty, want_grad, want_hess):
    """Area-integration energies of many (triangle, tetrahedron) pairs.

    Args:
        x: (nv, 3) current vertex coordinates (length).
        depth: (nv,) material depth per vertex (length).
        tri: (nt, 3) boundary triangles (vertex indices).
        tet: (nk, 4) tetrahedra (vertex indices), or (nk, 5): a fifth column ``c >= 0`` splits
            the tetrahedron into four sub-tetrahedra around its centroid, whose depth is
            ``depth[c]`` (its position is the mean of the four vertices); ``-1``: not split.
            The pair's energy and derivatives are then the sums over the sub-tetrahedra,
            mapped back to the four vertices (see ``docs/kernels.md``, thin layers).
        pair_tri, pair_tet: (np,) candidate pairs (indices into tri and tet).
        penalty: eps (pressure / length).
        want_grad, want_hess: whether to compute gradients and Hessians.

    Returns:
        ``energy (np,)``, ``grad (np, 21)`` (``(0, 21)`` unless want_grad) and
        ``hess (np, 21, 21)`` (``(0, 21, 21)`` unless want_hess); dofs of pair p are the
        vertices ``[tri[pair_tri[p]], tet[pair_tet[p]]]``, xyz interleaved.
    """
    npairs = pair_tri.shape[0]
    energy = np.zeros(npairs, dtype=FLOAT)
    grad = np.zeros((npairs if want_grad else 0, 21), dtype=FLOAT)
    hess = np.zeros((npairs if want_hess else 0, 21, 21), dtype=FLOAT)
    active = np.empty(0, dtype=INDEX)
    _area_pairs_core(
        x,
        depth,
        tri,
        tet,
        pair_tri,
        pair_tet,
        penalty,
        want_grad,
        want_hess,
        active,
        energy,
        grad,
        hess,
    )
    return energy, grad, hess


@njit(cache=True, fastmath=_FMA)
def _area_pairs_into(
    x,
    depth,
    tri,
    tet,
    pair_tri,
    pair_tet,
    penalty,
    want_grad,
    want_hess,
    active,
    energy,
    grad,
    hess,
):
    """Like `_area_pairs`, but writes only the contributing pairs, compactly, into preallocated
    arrays (reused across Newton iterations: no allocation, no page faults).

    Args:
        x, depth, tri, tet, pair_tri, pair_tet, penalty, want_grad, want_hess: as `_area_pairs`.
        active: (cap,) int output: index into the pair arrays of each written row.
        energy: (cap,) output; grad: (cap, 21) output if want_grad (else any, untouched);
            hess: (cap, 21, 21) output if want_hess (else any, untouched).

    Returns:
        The number m of contributing pairs (non-empty intersection); rows ``:min(m, cap)`` are
        written. If m > cap, the rest were counted but not written: grow the arrays to m and
        call again.
    """
    cap = active.shape[0]
    if energy.shape[0] != cap or (want_grad and grad.shape[0] < cap):
        raise ValueError("output arrays shorter than active")
    if want_hess and hess.shape[0] < cap:
        raise ValueError("output arrays shorter than active")
    return _area_pairs_core(
        x,
        depth,
        tri,
        tet,
        pair_tri,
        pair_tet,
        penalty,
        want_grad,
        want_hess,
        active,
        energy,
        grad,
        hess,
    )


@njit(cache=True, fastmath=_FMA)
def _add_vertex_block(blocks, key, hess, row, a, b, va, vb, bc_mask):
    """``blocks[key] +=`` the 3 x 3 block (a, b) of pair Hessian ``hess[row]`` (vertices
    ``va``, ``vb``), Dirichlet rows and columns left out."""
    for r in range(3):
        if bc_mask[3 * va + r]:
            continue
        for c in range(3):
            if not bc_mask[3 * vb + c]:
                blocks[key, r, c] += hess[row, 3 * a + r, 3 * b + c]


#: Pairs a chunk of `_area_pairs_summed`: their Hessians (3.5 kB each) stay in the cache
#: between the kernel that writes them and the sums that read them.
_SUM_CHUNK = 32


@njit(cache=True, fastmath=_FMA)
def _sum_pair_rows(
    tri, tet, pair_tri, pair_tet, start, count, grad, hess, want_hess, pos, grad_sum, reached,
    blocks, touched,
):  # fmt: skip
    """Add rows ``0..count`` of a chunk's pair gradients and Hessians (pairs ``start ..
    start + count``) into per-dof sums and the pattern's 3 x 3 blocks.

    The same sums, in the same order, as `gradient_array` (``np.bincount`` over the pairs'
    dofs) and `_accumulate_vertex_blocks` on the materialised arrays, but for the Dirichlet
    rows and columns, which `_zero_dirichlet` clears after the last chunk (a mask test per
    entry here cost more than the sums).
    """
    for q in range(count):
        p = start + q
        t = pair_tri[p]
        k = pair_tet[p]
        for a in range(7):
            va = tri[t, a] if a < 3 else tet[k, a - 3]
            for r in range(3):
                grad_sum[3 * va + r] += grad[q, 3 * a + r]
                reached[3 * va + r] = True
            if not want_hess:
                continue
            for b in range(7):
                key = pos[p, a, b]
                if key < 0:
                    continue
                touched[key] = True
                # the Dirichlet rows and columns are zeroed after the sums (`_zero_dirichlet`)
                for r in range(3):
                    for c in range(3):
                        blocks[key, r, c] += hess[q, 3 * a + r, 3 * b + c]


@njit(cache=True, fastmath=_FMA)
def _zero_dirichlet(keys, bc_mask, blocks, touched):
    """Zero the Dirichlet rows and columns of the touched blocks of the held-numbered pattern
    ``keys`` (``bc_mask`` over the held dofs)."""
    nh = bc_mask.shape[0] // 3
    for k in range(keys.shape[0]):
        if not touched[k]:
            continue
        vi = keys[k] // nh
        vj = keys[k] % nh
        for r in range(3):
            if bc_mask[3 * vi + r]:
                for c in range(3):
                    blocks[k, r, c] = 0.0
        for c in range(3):
            if bc_mask[3 * vj + c]:
                for r in range(3):
                    blocks[k, r, c] = 0.0


@njit(cache=True, fastmath=_FMA)
def _area_pairs_summed(
    x, depth, tri, tet, pair_tri, pair_tet, penalty, want_hess, pos, keys, bc_mask, energy,
    grad_sum, reached, blocks, touched,
):  # fmt: skip
    """`_area_pairs` with the gradients (and Hessians) summed as they are made, never
    materialised for all pairs: chunks of `_SUM_CHUNK` pairs go through the one pair loop
    (`_area_pairs_core`) into small buffers, which are then added into per-dof sums and the
    3 x 3 blocks of a fixed vertex-coupling pattern.

    Args:
        x, depth, tri, tet, pair_tri, pair_tet, penalty: as `_area_pairs` (``tri`` and ``tet``
            in the numbering of the dofs, ``3 v + c``).
        want_hess: whether to compute and sum the Hessians.
        pos: (np, 7, 7) pattern index of each pair coupling, -1 outside the pattern (left
            out), as `_coupling_positions`; read only if want_hess.
        keys: (nk,) the pattern's sorted vertex-coupling keys ``vi * nv + vj`` (``pos``
            indexes them); read only if want_hess.
        bc_mask: (3 nv,) True on Dirichlet dofs, whose Hessian rows and columns are left out.
        energy: (np,) output, the pair energies (0 for a pair that does not contribute).
        grad_sum: (3 nv,) output, added to: the gradient summed over the pairs.
        reached: (3 nv,) bool output, set True on every dof of a pair.
        blocks: (nk, 3, 3) output, added to: the Hessians summed into the pattern's blocks
            (if want_hess); touched: (nk,) bool output, True on every key a pair reaches.
    """
    n = pair_tri.shape[0]
    grad = np.empty((_SUM_CHUNK, 21), dtype=FLOAT)
    hess = np.empty((_SUM_CHUNK if want_hess else 0, 21, 21), dtype=FLOAT)
    compact = np.empty(0, dtype=INDEX)  # row q of the buffers is pair start + q
    for start in range(0, n, _SUM_CHUNK):
        stop = min(start + _SUM_CHUNK, n)
        _area_pairs_core(
            x, depth, tri, tet, pair_tri[start:stop], pair_tet[start:stop], penalty, True,
            want_hess, compact, energy[start:stop], grad, hess,
        )  # fmt: skip
        _sum_pair_rows(
            tri, tet, pair_tri, pair_tet, start, stop - start, grad, hess, want_hess, pos,
            grad_sum, reached, blocks, touched,
        )  # fmt: skip
    if want_hess:
        _zero_dirichlet(keys, bc_mask, blocks, touched)


@njit(cache=True, fastmath=_FMA)
def _intersecting(x, tri, tet, pair_tri, pair_tet):
    """Indices of the pairs whose triangle meets the tetrahedron (the exact test of
    ``geometry.intersect``), in order."""
    flags = np.empty(pair_tri.shape[0], dtype=np.bool_)
    na = intersect_pairs(x, tri, tet, pair_tri, pair_tet, flags)
    active = np.empty(na, dtype=INDEX)
    m = 0
    for p in range(pair_tri.shape[0]):
        if flags[p]:
            active[m] = p
            m += 1
    return active


# ------------------------------------------------------------------------------------------
# Augmented Lagrangian (paper section 8.3): nodal contact pressures on the penetrating surface
# ------------------------------------------------------------------------------------------


@njit(cache=True, fastmath=_FMA)
def _scale_row(grad, hess, row, n, factor, want_grad, want_hess):
    """Multiply row ``row`` of grad (n,) and hess (n, n) by ``factor`` in place."""
    if want_grad:
        for c in range(n):
            grad[row, c] *= factor
    if want_hess:
        for r in range(n):
            for c in range(n):
                hess[row, r, c] *= factor


@njit(cache=True, fastmath=_FMA)
def _add_row(grad, hess, row, n, want_grad, want_hess, acc_g, acc_h):
    """``acc += row`` of grad and hess."""
    if want_grad:
        for c in range(n):
            acc_g[c] += grad[row, c]
    if want_hess:
        for r in range(n):
            for c in range(n):
                acc_h[r, c] += hess[row, r, c]


@njit(cache=True, fastmath=_FMA)
def _area_pairs_augmented(
    x, depth, tri, tet, pair_tri, pair_tet, penalty, pressure, width, want_grad, want_hess
):
    """Augmented-Lagrangian energies of many (triangle, tetrahedron) pairs at fixed pressures.

    The energy of a pair is ``E = int_{T cap K} (p g + (eps/2) g^2) dA``, with ``g`` the material
    depth (as in `_area_pairs`) and ``p`` the nodal pressures of the triangle's vertices
    interpolated linearly on the triangle (``p = sum_i p_i mu_i``, ``mu`` the barycentric
    coordinates in T): the pressure is a P1 field on the penetrating surface, carried with its
    material points, so the force it adds is ``p grad g`` (paper, section 8.3). Completing the
    square, with ``Phi(H) = int_P (H . mu)^2 dxi`` as in `_area_pair`:

        ``E = eps A [Phi(G + P / eps) - Phi(P / eps)]``,

    each term one call of the pair kernel with a constant offset ``P / eps`` (the second with
    zero depths), so the derivatives are the exact ones of the plain kernel. With all three
    pressures zero the second term is skipped and the result is the plain penalty energy.

    That energy has a kink where a face lies flat on the other body's boundary (its whole area
    enters at once and ``int p g dA`` grows linearly with the overlap). With ``width = w > 0``
    the pressure term is the quadratic ``p g^2 / (2 w)`` instead, with ``p`` the mean of the
    triangle's three nodal pressures:

        ``E = ((eps + p_mean / w) / 2) int_{T cap K} g^2 dA``,

    the plain kernel with the penalty ``eps + p_mean / w`` (C1 in the positions, like the plain
    penalty): the pressures act as a stiffness, the force ``(eps + p / w) g grad g`` is
    ``p`` where ``g = w``.

    Args:
        x, depth, tri, tet, pair_tri, pair_tet, penalty, want_grad, want_hess: as `_area_pairs`.
        pressure: (nv,) nodal contact pressure of each vertex (pressure units, >= 0); only
            the values at triangle vertices are read.
        width: 0 for the linear pressure term, else ``w`` (length) of the quadratic one.

    Returns:
        ``energy (np,)``, ``grad (np, 21)``, ``hess (np, 21, 21)`` as `_area_pairs`.
    """
    npairs = pair_tri.shape[0]
    energy = np.zeros(npairs, dtype=FLOAT)
    grad = np.zeros((npairs if want_grad else 0, 21), dtype=FLOAT)
    hess = np.zeros((npairs if want_hess else 0, 21, 21), dtype=FLOAT)
    work = _area_work()
    xs = np.empty((3, 3), dtype=FLOAT)
    xt = np.empty((4, 3), dtype=FLOAT)
    dt = np.empty(4, dtype=FLOAT)
    offset = np.empty(3, dtype=FLOAT)
    acc_g = np.empty(21, dtype=FLOAT)
    acc_h = np.empty((21, 21), dtype=FLOAT)
    quadratic = width > 0.0
    for p in range(npairs):
        # linear term: the penalty, offset P / eps and a second term when a pressure is set;
        # quadratic term: one term, the plain kernel at the pair's stiffness eps + p_mean / w
        has_pressure = False
        stiffness = penalty
        for a in range(3):
            v = tri[pair_tri[p], a]
            if quadratic:
                offset[a] = 0.0
                stiffness += pressure[v] / (3.0 * width)
            else:
                offset[a] = pressure[v] / penalty
                has_pressure = has_pressure or pressure[v] != 0.0
            for r in range(3):
                xs[a, r] = x[v, r]
        work[22][0] = pair_tri[p]
        k = pair_tet[p]
        split = _is_split(tet, k)
        _zero_folded(21, want_grad, want_hess, acc_g, acc_h)
        e = 0.0
        hit = False
        for s in range(4 if split else 1):
            for term in range(2 if has_pressure else 1):
                _gather_tet(x, depth, tet, k, s, split, xt, dt)
                if term == 1:
                    for a in range(4):
                        dt[a] = 0.0
                es = _area_pair(xs, xt, dt, offset, stiffness, want_grad, want_hess, work, grad,
                                hess, p)  # fmt: skip
                if es < 0.0:
                    break  # no polygon: neither term contributes
                hit = True
                if term == 1:
                    es = -es
                    _scale_row(grad, hess, p, 21, -1.0, want_grad, want_hess)
                e += es
                if split:
                    _fold_centroid(grad, hess, p, 9, 21, s, want_grad, want_hess, acc_g, acc_h)
                else:
                    _add_row(grad, hess, p, 21, want_grad, want_hess, acc_g, acc_h)
        _store_folded(grad, hess, p, 21, want_grad, want_hess, acc_g, acc_h)
        energy[p] = e if hit else 0.0
    return energy, grad, hess


@njit(cache=True, fastmath=_FMA)
def _polygon_work():
    """Buffers of `_sub_polygon`: xs (3, 3), xt (4, 3), dt (4,), grads (4, 3), lam (3, 4),
    mu, vlab, elab (the clipped polygon, as `clip_triangle` fills them) and gi (3,)."""
    return (
        np.empty((3, 3), dtype=FLOAT),
        np.empty((4, 3), dtype=FLOAT),
        np.empty(4, dtype=FLOAT),
        np.empty((4, 3), dtype=FLOAT),
        np.empty((3, 4), dtype=FLOAT),
        np.empty((2, _NV, 3), dtype=FLOAT),
        np.empty((2, _NV, 2), dtype=INDEX),
        np.empty((2, _NV), dtype=INDEX),
        np.empty(3, dtype=FLOAT),
    )


@njit(cache=True, fastmath=_FMA)
def _gather_triangle(x, tri, t, xs):
    """Vertices of triangle t into xs (3, 3); returns twice its area."""
    for a in range(3):
        for r in range(3):
            xs[a, r] = x[tri[t, a], r]
    return triangle_area2(xs)


@njit(cache=True, fastmath=_FMA)
def _sub_polygon(x, depth, tet, k, s, split, work):
    """Clip the triangle in ``work[0]`` against tetrahedron k (sub-tetrahedron s when split):
    the polygon in ``work[5]`` (parameter coordinates on the triangle, as `clip_triangle` gives
    them) and, in ``work[8]``, the depth ``g_K`` at the triangle's corners, extended affinely
    over the parameter simplex. Returns the polygon's vertex count (0 for a flat
    tetrahedron)."""
    xs, xt, dt, grads, lam, mu, vlab, elab, gi = work
    _gather_tet(x, depth, tet, k, s, split, xt, dt)
    if tet_gradients(xt, grads) == 0.0:
        return 0
    triangle_rows(xs, xt, grads, lam)
    n = clip_triangle(lam, mu, vlab, elab)
    for i in range(3):
        gi[i] = lam[i, 0] * dt[0] + lam[i, 1] * dt[1] + lam[i, 2] * dt[2] + lam[i, 3] * dt[3]
    return n


@njit(cache=True, fastmath=_FMA)
def _area_pairs_pressure_moments(x, depth, tri, tet, pair_tri, pair_tet):
    """The integrals the Uzawa update of the nodal pressures needs, per pair and triangle vertex.

    For each pair and each vertex i of its triangle, over the intersection polygon (current
    configuration; split tetrahedra summed over their sub-tetrahedra):
    ``gmom[p, i] = int_{T cap K} mu_i g dA`` (length^3) and
    ``amom[p, i] = int_{T cap K} mu_i dA`` (length^2), ``mu_i`` the hat function of vertex i
    on T. Exact: a fan of signed triangles in the parameter plane, on which ``mu_i`` and ``g``
    are linear (``int f h = area / 12 (sum_k f_k h_k + sum_k f_k sum_k h_k)``).

    Args:
        x, depth, tri, tet, pair_tri, pair_tet: as `_area_pairs`.

    Returns:
        ``gmom (np, 3)``, ``amom (np, 3)``.
    """
    npairs = pair_tri.shape[0]
    gmom = np.zeros((npairs, 3), dtype=FLOAT)
    amom = np.zeros((npairs, 3), dtype=FLOAT)
    work = _polygon_work()
    xs, mu, gi = work[0], work[5], work[8]
    for p in range(npairs):
        a2 = _gather_triangle(x, tri, pair_tri[p], xs)
        if a2 == 0.0:
            continue
        k = pair_tet[p]
        split = _is_split(tet, k)
        for s in range(4 if split else 1):
            n = _sub_polygon(x, depth, tet, k, s, split, work)
            if n < 3:
                continue
            # fan from the parameter origin (mu = e_0), signed areas; dA = |n| dxi = a2 dxi
            h0 = gi[0]
            for v in range(n):
                v1 = v + 1 if v + 1 < n else 0
                area = 0.5 * (mu[0, v, 1] * mu[0, v1, 2] - mu[0, v, 2] * mu[0, v1, 1]) * a2
                hv = mu[0, v, 0] * gi[0] + mu[0, v, 1] * gi[1] + mu[0, v, 2] * gi[2]
                hw = mu[0, v1, 0] * gi[0] + mu[0, v1, 1] * gi[1] + mu[0, v1, 2] * gi[2]
                hsum = h0 + hv + hw
                for i in range(3):
                    f0 = 1.0 if i == 0 else 0.0
                    fv = mu[0, v, i]
                    fw = mu[0, v1, i]
                    amom[p, i] += area * (f0 + fv + fw) / 3.0
                    gmom[p, i] += (
                        area / 12.0 * (f0 * h0 + fv * hv + fw * hw + (f0 + fv + fw) * hsum)
                    )
    return gmom, amom


def augmented_pair_energy(
    x_tri: np.ndarray,
    x_tet: np.ndarray,
    depth_tet: np.ndarray,
    penalty: float,
    pressure_tri: np.ndarray,
    centroid_depth: float | None = None,
    width: float = 0.0,
) -> tuple[float, np.ndarray, np.ndarray]:
    """Augmented-Lagrangian energy of one (triangle, tetrahedron) pair, exact derivatives.

    Args:
        x_tri, x_tet, depth_tet, penalty, centroid_depth: as :func:`pair_energy`.
        pressure_tri: (3,) nodal contact pressures of the triangle's vertices (pressure).
        width: 0: the linear pressure term; ``w > 0``: the quadratic one (see ``width`` of
            `_area_pairs_augmented`).

    Returns:
        ``(E, grad, hess)``: ``int_{T cap K} (p g + (eps/2) g^2) dA`` with ``p`` interpolated
        linearly on the triangle, or ``((eps + p_mean / w) / 2) int_{T cap K} g^2 dA`` (energy),
        gradient (21,) and Hessian (21, 21) as :func:`pair_energy`.
    """
    xs = np.ascontiguousarray(x_tri, dtype=FLOAT).reshape(3, 3)
    x, depth, tet = _one_pair_arrays(xs, x_tet, depth_tet, centroid_depth)
    pressure = np.zeros(depth.shape[0], dtype=FLOAT)
    pressure[:3] = np.asarray(pressure_tri, dtype=FLOAT).reshape(3)
    one = np.zeros(1, dtype=INDEX)
    energy, grad, hess = _area_pairs_augmented(
        x, depth, _ONE_TRI, tet, one, one, penalty, pressure, float(width), True, True
    )
    return float(energy[0]), grad[0], hess[0]


def pressure_moments(
    x_tri: np.ndarray,
    x_tet: np.ndarray,
    depth_tet: np.ndarray,
    centroid_depth: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """``int_{T cap K} mu_i g dA`` and ``int_{T cap K} mu_i dA`` for the 3 triangle vertices.

    Args:
        x_tri, x_tet, depth_tet, centroid_depth: as :func:`pair_energy`.

    Returns:
        ``(gmom (3,), amom (3,))`` (length^3, length^2).
    """
    xs = np.ascontiguousarray(x_tri, dtype=FLOAT).reshape(3, 3)
    x, depth, tet = _one_pair_arrays(xs, x_tet, depth_tet, centroid_depth)
    one = np.zeros(1, dtype=INDEX)
    gmom, amom = _area_pairs_pressure_moments(x, depth, _ONE_TRI, tet, one, one)
    return gmom[0], amom[0]


@njit(cache=True, fastmath=_FMA)
def _area_pairs_max_depth(x, depth, tri, tet, pair_tri, pair_tet):
    """Largest material depth ``g_K`` reached on each pair's intersection polygon (length).

    ``g_K`` is affine on the polygon, so its maximum is at a polygon vertex. Pairs whose
    intersection is empty get 0.

    Args:
        x, depth, tri, tet, pair_tri, pair_tet: as `_area_pairs`.

    Returns:
        (np,) maximum depth per pair.
    """
    out = np.zeros(pair_tri.shape[0], dtype=FLOAT)
    work = _polygon_work()
    xs, mu, gi = work[0], work[5], work[8]
    for p in range(pair_tri.shape[0]):
        if _gather_triangle(x, tri, pair_tri[p], xs) == 0.0:
            continue
        k = pair_tet[p]
        split = _is_split(tet, k)
        best = 0.0
        for s in range(4 if split else 1):
            n = _sub_polygon(x, depth, tet, k, s, split, work)
            for v in range(n):
                g = mu[0, v, 0] * gi[0] + mu[0, v, 1] * gi[1] + mu[0, v, 2] * gi[2]
                best = max(best, g)
        out[p] = best
    return out


#: A point counts as inside a tetrahedron when its barycentric coordinates are all at least
#: ``-_POINT_INSIDE_TOL`` (dimensionless): a point on a face (a vertex on a symmetry plane, on the
#: other body's boundary face) is then not lost to the rounding of ``lambda_0 = 1 - sum``.
_POINT_INSIDE_TOL = 1e-12


@njit(cache=True, fastmath=_FMA)
def _point_depths(x, depth, tet, points, pair_point, pair_tet):
    """Material depth ``g_K`` at points, per (point, tetrahedron) pair (length).

    ``g_K(y) = sum_j lambda_j(y) d_j`` (as in the pair kernels) where the point y lies in K
    (every barycentric coordinate ``>= -_POINT_INSIDE_TOL``), else 0. A split tetrahedron
    (`_is_split`) gives the largest value over its sub-tetrahedra containing y (they agree up
    to rounding: the split depth is continuous), not their sum as the collocation energy does
    for a point on a face they share.

    Args:
        x, depth, tet: as `_area_pairs`.
        points: (n, 3) the points (length).
        pair_point, pair_tet: (np,) candidate pairs (row of ``points``, tetrahedron index).

    Returns:
        (np,) depth per pair.
    """
    out = np.zeros(pair_point.shape[0], dtype=FLOAT)
    xt = np.empty((4, 3), dtype=FLOAT)
    dt = np.empty(4, dtype=FLOAT)
    grads = np.empty((4, 3), dtype=FLOAT)
    lam = np.empty(4, dtype=FLOAT)
    for p in range(pair_point.shape[0]):
        q = pair_point[p]
        k = pair_tet[p]
        split = _is_split(tet, k)
        best = 0.0
        for s in range(4 if split else 1):
            _gather_tet(x, depth, tet, k, s, split, xt, dt)
            if tet_gradients(xt, grads) == 0.0:
                continue
            total = 0.0
            for j in range(1, 4):
                lam[j] = (
                    grads[j, 0] * (points[q, 0] - xt[0, 0])
                    + grads[j, 1] * (points[q, 1] - xt[0, 1])
                    + grads[j, 2] * (points[q, 2] - xt[0, 2])
                )
                total += lam[j]
            lam[0] = 1.0 - total
            if min(lam[0], lam[1], lam[2], lam[3]) < -_POINT_INSIDE_TOL:
                continue
            g = lam[0] * dt[0] + lam[1] * dt[1] + lam[2] * dt[2] + lam[3] * dt[3]
            best = max(best, g)
        out[p] = best
    return out


@njit(cache=True, fastmath=_FMA)
def _collocation_pair(xa, xt, dt, weight, penalty, want_grad, want_hess, work, grad, hess, p):
    """Point-collocation energy of one (vertex, tetrahedron) pair; 15 dofs (vertex, then tet).

    ``E = (eps/2) W g^2`` with ``g = sum_j lambda_j(x_a) d_j`` when every ``lambda_j >= 0``.
    """
    _no_contribution(grad, hess, p, 15, want_grad, want_hess)
    grads, lam, gg, dg = work
    if tet_gradients(xt, grads) == 0.0:
        return 0.0
    s = 0.0
    for j in range(1, 4):
        v = (
            grads[j, 0] * (xa[0] - xt[0, 0])
            + grads[j, 1] * (xa[1] - xt[0, 1])
            + grads[j, 2] * (xa[2] - xt[0, 2])
        )
        lam[j] = v
        s += v
    lam[0] = 1.0 - s
    if lam[0] < 0.0 or lam[1] < 0.0 or lam[2] < 0.0 or lam[3] < 0.0:
        return 0.0
    g = lam[0] * dt[0] + lam[1] * dt[1] + lam[2] * dt[2] + lam[3] * dt[3]
    c0 = penalty * weight
    energy = 0.5 * c0 * g * g
    if not want_grad:
        return energy
    # grad g (constant in K); d g / d X_k = -lambda_k grad g
    for a in range(3):
        gg[a] = 0.0
    for j in range(4):
        for a in range(3):
            gg[a] += dt[j] * grads[j, a]
    for a in range(3):
        dg[a] = gg[a]
        for k in range(4):
            dg[3 + 3 * k + a] = -lam[k] * gg[a]
    for c in range(15):
        grad[p, c] = c0 * g * dg[c]
    if not want_hess:
        return energy
    for r in range(15):
        for c in range(15):
            hess[p, r, c] = c0 * dg[r] * dg[c]
    # g * d2 g: node-tet block -grad_k[a] gg[b]; tet-tet block
    # lambda_l gg[a] grad_k[b] + lambda_k grad_l[a] gg[b]
    for k in range(4):
        for a in range(3):
            for b in range(3):
                val = -c0 * g * grads[k, a] * gg[b]
                hess[p, a, 3 + 3 * k + b] += val
                hess[p, 3 + 3 * k + b, a] += val
        for l in range(4):
            for a in range(3):
                for b in range(3):
                    val = lam[l] * gg[a] * grads[k, b] + lam[k] * grads[l, a] * gg[b]
                    hess[p, 3 + 3 * k + a, 3 + 3 * l + b] += c0 * g * val
    return energy


@njit(cache=True, fastmath=_FMA)
def _collocation_pairs(x, depth, weight, tet, pair_node, pair_tet, penalty, want_grad, want_hess):
    """Point-collocation energies of many (boundary vertex, tetrahedron) pairs.

    Args:
        x: (nv, 3) current vertex coordinates (length).
        depth: (nv,) material depth per vertex (length).
        weight: (nv,) collocation weight W_a per vertex (area, length^2; one third of the area of
            the boundary triangles around a).
        tet: (nk, 4) or (nk, 5) tetrahedra (vertex indices; a fifth column as in
            `_area_pairs`: the vertex is tested against, and interpolated in, the
            sub-tetrahedra around the centroid).
        pair_node, pair_tet: (np,) candidate pairs (vertex index, tetrahedron index).
        penalty: eps (pressure / length).
        want_grad, want_hess: whether to compute gradients and Hessians.

    Returns:
        ``energy (np,)``, ``grad (np, 15)``, ``hess (np, 15, 15)`` (first axis 0 when not
        wanted); dofs of pair p are the vertices ``[pair_node[p], tet[pair_tet[p]]]``.
    """
    npairs = pair_node.shape[0]
    energy = np.zeros(npairs, dtype=FLOAT)
    grad = np.zeros((npairs if want_grad else 0, 15), dtype=FLOAT)
    hess = np.zeros((npairs if want_hess else 0, 15, 15), dtype=FLOAT)
    work = (
        np.empty((4, 3), dtype=FLOAT),
        np.empty(4, dtype=FLOAT),
        np.empty(3, dtype=FLOAT),
        np.empty(15, dtype=FLOAT),
    )
    xt = np.empty((4, 3), dtype=FLOAT)
    xa = np.empty(3, dtype=FLOAT)
    dt = np.empty(4, dtype=FLOAT)
    acc_g = np.empty(15, dtype=FLOAT)
    acc_h = np.empty((15, 15), dtype=FLOAT)
    for p in range(npairs):
        node = pair_node[p]
        for r in range(3):
            xa[r] = x[node, r]
        k = pair_tet[p]
        split = _is_split(tet, k)
        if split:
            _zero_folded(15, want_grad, want_hess, acc_g, acc_h)
        e = 0.0
        # a vertex in a split tetrahedron lies in one of its sub-tetrahedra (in several only
        # on their common faces, a set of measure zero, as between any two tetrahedra)
        for s in range(4 if split else 1):
            _gather_tet(x, depth, tet, k, s, split, xt, dt)
            es = _collocation_pair(
                xa, xt, dt, weight[node], penalty, want_grad, want_hess, work, grad, hess, p
            )
            e += es
            if split:
                _fold_centroid(grad, hess, p, 3, 15, s, want_grad, want_hess, acc_g, acc_h)
        if split:
            _store_folded(grad, hess, p, 15, want_grad, want_hess, acc_g, acc_h)
        energy[p] = e
    return energy, grad, hess


def _one_pair_arrays(
    x_first: np.ndarray, x_tet: np.ndarray, depth_tet: np.ndarray, centroid_depth: float | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertex, depth and tetrahedron arrays of a single pair: the first points, then the
    tetrahedron's four vertices, then (when ``centroid_depth`` is given) the centroid's depth
    as the fifth column of the tetrahedron."""
    xt = np.ascontiguousarray(x_tet, dtype=FLOAT).reshape(4, 3)
    dt = np.ascontiguousarray(depth_tet, dtype=FLOAT).reshape(4)
    nf = x_first.shape[0]
    x = np.vstack([x_first, xt])
    depth = np.concatenate([np.zeros(nf, dtype=FLOAT), dt])
    tet = np.arange(nf, nf + 4, dtype=INDEX).reshape(1, 4)
    if centroid_depth is not None:
        centroid_depth = float(centroid_depth)
        if not (np.isfinite(centroid_depth) and centroid_depth > 0.0):
            raise ValueError(f"centroid_depth must be a positive length, got {centroid_depth}")
        depth = np.append(depth, centroid_depth)
        tet = np.array([[nf, nf + 1, nf + 2, nf + 3, nf + 4]], dtype=INDEX)
    return x, depth, tet


def pair_energy(
    x_tri: np.ndarray,
    x_tet: np.ndarray,
    depth_tet: np.ndarray,
    penalty: float,
    centroid_depth: float | None = None,
) -> tuple[float, np.ndarray, np.ndarray]:
    """Area-integrated penalty energy of one (triangle, tetrahedron) pair, exact derivatives.

    Args:
        x_tri: (3, 3) current triangle vertex coordinates (length).
        x_tet: (4, 3) current tetrahedron vertex coordinates (length).
        depth_tet: (4,) material depths of the tetrahedron vertices (length).
        penalty: eps (pressure / length).
        centroid_depth: if given (length, > 0), the tetrahedron is split into four
            sub-tetrahedra around its centroid, which carries this depth (the remedy the
            contact operator applies to tetrahedra whose four vertices have depth 0); the
            derivatives are still over the 7 vertices.

    Returns:
        ``(E, grad, hess)``: energy ``(eps/2) int_{T cap K} g^2 dA`` (energy), gradient (21,)
        and Hessian (21, 21) over the triangle then tetrahedron vertex coordinates, xyz
        interleaved.
    """
    xs = np.ascontiguousarray(x_tri, dtype=FLOAT).reshape(3, 3)
    x, depth, tet = _one_pair_arrays(xs, x_tet, depth_tet, centroid_depth)
    one = np.zeros(1, dtype=INDEX)
    energy, grad, hess = _area_pairs(x, depth, _ONE_TRI, tet, one, one, penalty, True, True)
    return float(energy[0]), grad[0], hess[0]


def collocation_energy(
    x_node: np.ndarray,
    x_tet: np.ndarray,
    depth_tet: np.ndarray,
    weight: float,
    penalty: float,
    centroid_depth: float | None = None,
) -> tuple[float, np.ndarray, np.ndarray]:
    """Point-collocation penalty energy of one (vertex, tetrahedron) pair, exact derivatives.

    Args:
        x_node: (3,) current vertex coordinates (length).
        x_tet: (4, 3) current tetrahedron vertex coordinates (length).
        depth_tet: (4,) material depths of the tetrahedron vertices (length).
        weight: W_a, the area the vertex represents (length^2).
        penalty: eps (pressure / length).
        centroid_depth: as in :func:`pair_energy` (split around the centroid).

    Returns:
        ``(E, grad, hess)``: ``(eps/2) W g(x_a)^2`` if the vertex is in the tetrahedron, else 0;
        gradient (15,) and Hessian (15, 15) over the vertex then tetrahedron coordinates.
    """
    xa = np.ascontiguousarray(x_node, dtype=FLOAT).reshape(1, 3)
    x, depth, tet = _one_pair_arrays(xa, x_tet, depth_tet, centroid_depth)
    weights = np.full(5, weight, dtype=FLOAT)
    zero = np.zeros(1, dtype=INDEX)
    energy, grad, hess = _collocation_pairs(x, depth, weights, tet, zero, zero, penalty, True, True)
    return float(energy[0]), grad[0], hess[0]


# ------------------------------------------------------------------------------------------
# Assembly into a fixed sparsity pattern (no sorting of pair entries per iterate)
# ------------------------------------------------------------------------------------------


@njit(cache=True, fastmath=_FMA)
def _key_rows(keys, num_vertices):
    """Row pointers of a sorted vertex-coupling pattern: the keys ``va * num_vertices + vb`` of
    vertex ``va`` are ``keys[rows[va]:rows[va + 1]]``.

    Args:
        keys: (nk,) sorted keys.
        num_vertices: number of vertices of the key numbering.

    Returns:
        (num_vertices + 1,) row pointers.
    """
    rows = np.zeros(num_vertices + 1, dtype=np.int64)
    for k in range(keys.shape[0]):
        rows[keys[k] // num_vertices + 1] += 1
    for v in range(num_vertices):
        rows[v + 1] += rows[v]
    return rows


@njit(cache=True, fastmath=_FMA)
def _find_key(keys, lo, hi, key):
    """Index of ``key`` in the sorted ``keys[lo:hi]`` (binary search), or -1."""
    end = hi
    while lo < hi:
        mid = (lo + hi) >> 1
        if keys[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    if lo < end and keys[lo] == key:
        return lo
    return -1


@njit(cache=True, fastmath=_FMA)
def _transposed_keys(keys, rows, num_vertices):
    """Where each coupling's transpose lies in a fixed pattern.

    Args:
        keys: (nk,) sorted vertex-coupling keys ``va * num_vertices + vb`` of the pattern.
        rows: (num_vertices + 1,) their row pointers (`_key_rows`).
        num_vertices: number of vertices of the key numbering.

    Returns:
        (nk,) the index in ``keys`` of ``(vb, va)`` for each key ``(va, vb)``, -1 where the
        pattern lacks it (never, for a pattern made of whole pairs, which is symmetric).
    """
    out = np.empty(keys.shape[0], dtype=np.int64)
    for k in range(keys.shape[0]):
        va = keys[k] // num_vertices
        vb = keys[k] - va * num_vertices
        out[k] = _find_key(keys, rows[vb], rows[vb + 1], vb * num_vertices + va)
    return out


@njit(cache=True, fastmath=_FMA)
def _coupling_positions(keys, rows, num_vertices, verts, transposed, pos):
    """Where each vertex coupling of the pairs lies in a fixed pattern.

    A binary search within the row of the coupling's first vertex (a few dozen keys), not
    over the whole pattern, for the couplings (a, b) with a <= b only: (b, a) is the
    transpose's index (``transposed``). A pair whose contact element (the first
    ``verts.shape[1] - 4`` vertices) is the previous pair's copies that element's couplings
    (pairs come grouped by element, eight a triangle on a flat interface).

    Args:
        keys: (nk,) sorted vertex-coupling keys ``va * num_vertices + vb`` of the pattern.
        rows: (num_vertices + 1,) their row pointers (`_key_rows`).
        num_vertices: number of vertices of the key numbering.
        verts: (np, m) vertices of each pair (m = 7 for area pairs, 5 for collocation).
        transposed: (nk,) `_transposed_keys` of ``keys``.
        pos: (np, m, m) output: ``pos[p, a, b]`` the index in ``keys`` of the coupling
            ``(verts[p, a], verts[p, b])``, -1 where the pattern lacks it.

    Returns:
        The number of couplings not in the pattern.
    """
    nvp = verts.shape[1]
    lead = nvp - 4
    missing = 0
    for p in range(verts.shape[0]):
        same = p > 0
        for a in range(lead):
            if same and verts[p, a] != verts[p - 1, a]:
                same = False
        for a in range(nvp):
            va = verts[p, a]
            lo = rows[va]
            hi = rows[va + 1]
            for b in range(a, nvp):
                vb = verts[p, b]
                if same and b < lead:
                    k = pos[p - 1, a, b]
                    kt = pos[p - 1, b, a]
                else:
                    k = _find_key(keys, lo, hi, va * num_vertices + vb)
                    if b == a:
                        kt = k
                    elif k >= 0:
                        kt = transposed[k]
                    else:
                        kt = _find_key(keys, rows[vb], rows[vb + 1], vb * num_vertices + va)
                pos[p, a, b] = k
                pos[p, b, a] = kt
                if k < 0:
                    missing += 1
                if kt < 0 and b != a:
                    missing += 1
    return missing


@njit(cache=True, fastmath=_FMA)
def _accumulate_vertex_blocks(pos, verts, hess, bc_mask, blocks, touched):
    """Sum the pairs' Hessians into 3 x 3 blocks of a fixed vertex-coupling pattern.

    Args:
        pos: (np, m, m) pattern index of each pair coupling, -1 if outside the pattern
            (`_coupling_positions`; those entries are left out).
        verts: (np, m) vertices of each pair (m = 7 for area pairs, 5 for collocation).
        hess: (np, 3 m, 3 m) pair Hessians, xyz interleaved in the order of ``verts``.
        bc_mask: (3 num_vertices,) True on Dirichlet dofs, whose rows and columns are skipped.
        blocks: (nk, 3, 3) output, added to (zero it first).
        touched: (nk,) bool output, set True on every key a pair reaches.
    """
    nvp = verts.shape[1]
    for p in range(verts.shape[0]):
        for a in range(nvp):
            va = verts[p, a]
            for b in range(nvp):
                k = pos[p, a, b]
                if k < 0:
                    continue
                vb = verts[p, b]
                touched[k] = True
                _add_vertex_block(blocks, k, hess, p, a, b, va, vb, bc_mask)


@njit(cache=True, fastmath=_FMA)
def _blocks_to_csr(keys, num_vertices, blocks, touched, global_vertex, int_type):
    """The touched 3 x 3 blocks as a CSR over global dof rows, for ``MatSetValuesIJV``.

    Args:
        keys: (nk,) sorted vertex-coupling keys ``va * num_vertices + vb`` of the pattern.
        num_vertices: number of vertices of the key numbering.
        blocks, touched: as filled by `_accumulate_vertex_blocks`.
        global_vertex: (num_vertices,) the global vertex number of each vertex.
        int_type: an array of the integer type of the outputs' indices (PETSc's).

    Returns:
        ``(rows, indptr, cols, vals)``: global dof rows (``3 global_vertex[va] + r``), row
        pointers into ``cols``/``vals``, global dof columns (in key order within a row) and
        values.
    """
    nk = keys.shape[0]
    n_touched = 0
    n_vrows = 0
    last = -1
    for k in range(nk):
        if touched[k]:
            n_touched += 1
            va = keys[k] // num_vertices
            if va != last:
                n_vrows += 1
                last = va
    rows = np.empty(3 * n_vrows, dtype=int_type.dtype)
    indptr = np.empty(3 * n_vrows + 1, dtype=int_type.dtype)
    cols = np.empty(9 * n_touched, dtype=int_type.dtype)
    vals = np.empty(9 * n_touched, dtype=FLOAT)
    indptr[0] = 0
    row = 0
    start = 0
    k = 0
    while k < nk:
        if not touched[k]:
            k += 1
            continue
        va = keys[k] // num_vertices
        # the touched keys of vertex row va: k .. end (exclusive), g of them
        g = 0
        end = k
        while end < nk and keys[end] // num_vertices == va:
            if touched[end]:
                g += 1
            end += 1
        ga = 3 * global_vertex[va]
        for r in range(3):
            rows[row + r] = ga + r
            indptr[row + r + 1] = start + 3 * g * (r + 1)
        j = 0
        for kk in range(k, end):
            if not touched[kk]:
                continue
            gb = 3 * global_vertex[keys[kk] % num_vertices]
            for r in range(3):
                base = start + 3 * g * r + 3 * j
                for c in range(3):
                    cols[base + c] = gb + c
                    vals[base + c] = blocks[kk, r, c]
            j += 1
        start += 9 * g
        row += 3
        k = end
    return rows, indptr, cols, vals
