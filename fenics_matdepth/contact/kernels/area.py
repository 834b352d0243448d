"""Area integration of one (boundary triangle T, tetrahedron K) pair, exact derivatives.

``E = (eps/2) int_{T cap K} g_K^2 dA = eps * A_T * Phi(Lam)``, with ``A_T`` the current area of
T, ``Lam[i, j] = lambda_j(x_i)`` the barycentric coordinates of the triangle vertices in K and
``Phi = int_P (G . mu)^2 dxi`` over the clipped polygon P of the parameter simplex
(``G = Lam @ d``). 21 dofs: triangle vertices 0..2 then tetrahedron vertices 0..3, xyz
interleaved. The derivative helpers are in `fenics_matdepth.contact.kernels.area_derivatives`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from fenics_matdepth._constants import FLOAT
from fenics_matdepth.contact.kernels.area_derivatives import (
    area_hessian,
    assemble_phi_hessian,
    clip_shift_jacobian,
    shift_rows,
    vertex_gradient,
)
from fenics_matdepth.contact.kernels.fastmath import FMA
from fenics_matdepth.geometry.clip import (
    MAX_POLYGON_VERTICES,
    clip_triangle,
    tet_gradients,
    triangle_area2,
    triangle_rows,
)

__all__ = ["AreaWork", "area_pair", "area_work", "no_contribution"]

_NV = MAX_POLYGON_VERTICES


class AreaWork(NamedTuple):
    """Scratch arrays of one area-integration kernel call (`area_work`, allocated once per
    driver call), by name: ``Lam`` is the (3, 4) barycentric matrix of the triangle's corners
    in the tetrahedron, ``mu_k`` the polygon vertices, ``G = Lam @ d`` (see `area_pair`)."""

    grads: np.ndarray  #: (4, 3) barycentric gradients of the tetrahedron
    lam: np.ndarray  #: (3, 4) Lam
    mu: np.ndarray  #: (2, nv, 3) the clipper's polygon buffers
    vertex_labels: np.ndarray  #: (2, nv, 2) the two lines through each polygon vertex
    edge_labels: np.ndarray  #: (2, nv) the line of each polygon edge
    dmu_dlam: np.ndarray  #: (nv, 3, 6) d mu_k / d Lam, live columns only
    dphi_dmu: np.ndarray  #: (nv, 3) d Phi / d mu_k
    dphi_dlam: np.ndarray  #: (12,) d Phi / d Lam
    d2phi_dlam2: np.ndarray  #: (12, 12) d2 Phi / d Lam2
    live_columns: np.ndarray  #: (nv, 6) Lam index of the live columns of dmu_dlam
    phi_blocks: np.ndarray  #: (4, nv, 3, 3) Hessian blocks of Phi over (mu_k, G)
    tri_block: np.ndarray  #: (9, 9) T: Hessian of Phi w.r.t. the triangle vertices
    tri_tet_block: np.ndarray  #: (9, 12) V: triangle-tetrahedron block of J^T H_Lam J
    lam_tri_block: np.ndarray  #: (12, 9) U = H_Lam (I (x) grads); scratch of the Phi Hessian
    dphi_dx: np.ndarray  #: (21,) d Phi / d x
    darea_dx: np.ndarray  #: (9,) d A / d x
    d2area_dx2: np.ndarray  #: (9, 9) d2 A / d x2
    dphi_dcorner: np.ndarray  #: (3, 3) W[i] = sum_j dPhi/dLam_ij grad lambda_j
    dnormal_dx: np.ndarray  #: (9, 3) dn[3 i + a] = d (triangle normal) / d x_ia
    num_live_columns: np.ndarray  #: (nv,) number of live columns per polygon vertex
    scratch: np.ndarray  #: (3, 9) vectors of an edge integrand's Hessian; scratch
    dshift_dx: np.ndarray  #: (3, 9) d (clip shift) / d x_tri
    #: (3,) the triangle cache: [this pair's triangle (-1: unknown), the triangle whose
    #: darea_dx, d2area_dx2, dnormal_dx and dshift_dx hold, what they hold (1: to the
    #: gradient, 2: and d2 A)]; the drivers name the pair's triangle in ``triangle_cache[0]``
    triangle_cache: np.ndarray


@njit(cache=True, fastmath=FMA)
def area_work():
    """The scratch arrays of one area-integration kernel call (allocated once per driver call)."""
    return AreaWork(
        grads=np.empty((4, 3), dtype=FLOAT),
        lam=np.empty((3, 4), dtype=FLOAT),
        mu=np.empty((2, _NV, 3), dtype=FLOAT),
        vertex_labels=np.empty((2, _NV, 2), dtype=np.int64),
        edge_labels=np.empty((2, _NV), dtype=np.int64),
        dmu_dlam=np.empty((_NV, 3, 6), dtype=FLOAT),
        dphi_dmu=np.empty((_NV, 3), dtype=FLOAT),
        dphi_dlam=np.empty(12, dtype=FLOAT),
        d2phi_dlam2=np.empty((12, 12), dtype=FLOAT),
        live_columns=np.empty((_NV, 6), dtype=np.int64),
        phi_blocks=np.empty((4, _NV, 3, 3), dtype=FLOAT),
        tri_block=np.empty((9, 9), dtype=FLOAT),
        tri_tet_block=np.empty((9, 12), dtype=FLOAT),
        lam_tri_block=np.empty((12, 9), dtype=FLOAT),
        dphi_dx=np.empty(21, dtype=FLOAT),
        darea_dx=np.empty(9, dtype=FLOAT),
        d2area_dx2=np.empty((9, 9), dtype=FLOAT),
        dphi_dcorner=np.empty((3, 3), dtype=FLOAT),
        dnormal_dx=np.empty((9, 3), dtype=FLOAT),
        num_live_columns=np.empty(_NV, dtype=np.int64),
        scratch=np.empty((3, 9), dtype=FLOAT),
        dshift_dx=np.empty((3, 9), dtype=FLOAT),
        triangle_cache=np.full(3, -1, dtype=np.int64),
    )


# A function of its own, called from the pair loops, not inlined there (inline="always"):
# numba's IR inlining of this large kernel made the first run's compilation about three
# times longer, for no measurable gain in speed (docs/solvers.md, start-up). The same holds
# for every helper of this module and of geometry/clip.py: none is IR-inlined any more.
@njit(cache=True, fastmath=FMA)
def no_contribution(grad, hess, p, n, want_grad, want_hess):
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


@njit(cache=True, fastmath=FMA)
def area_pair(xs, xt, dt, offset, penalty, want_grad, want_hess, work, grad, hess, p):
    """Area-integration energy of one (triangle, tetrahedron) pair.

    Args:
        xs: (3, 3) triangle vertices; xt: (4, 3) tetrahedron vertices (length).
        dt: (4,) material depths of the tetrahedron vertices (length).
        offset: (3,) constant added to the integrand's value at each triangle vertex,
            ``G_i = sum_j Lam_ij d_j + offset_i`` (length; zeros for the plain penalty energy,
            ``p_i / eps`` for the augmented Lagrangian, see `area_pairs_augmented`). Being
            constant, it adds nothing to ``d G / d Lam``.
        penalty: eps (pressure / length).
        want_grad, want_hess: which derivatives to write.
        work: `AreaWork` from `area_work`.
        grad: (np, 21) output, row p written if want_grad; hess: (np, 21, 21) output, block p
            written if want_hess (rows of the outputs are indexed here, not sliced: a view per
            pair costs reference counting).
        p: the output row.

    Returns:
        The pair energy (>= 0), or -1.0 (with zero outputs) when the pair does not contribute:
        empty intersection, flat tetrahedron or zero-area triangle.
    """
    # the work arrays under the short names of the formulas below
    grads = work.grads
    lam = work.lam
    mu = work.mu
    vlab = work.vertex_labels
    elab = work.edge_labels
    jmu = work.dmu_dlam
    wmu = work.dphi_dmu
    gphi = work.dphi_dlam
    hphi = work.d2phi_dlam2
    jidx = work.live_columns
    blk = work.phi_blocks
    tt = work.tri_block
    vv = work.tri_tet_block
    uu = work.lam_tri_block
    gx = work.dphi_dx
    ga = work.darea_dx
    ha = work.d2area_dx2
    ww = work.dphi_dcorner
    dn = work.dnormal_dx
    ncol = work.num_live_columns
    zv = work.scratch
    ds = work.dshift_dx
    tri_state = work.triangle_cache
    # a contributing pair writes every entry of its outputs; the others are zeroed here
    a2 = triangle_area2(xs)
    if a2 == 0.0:
        return no_contribution(grad, hess, p, 21, want_grad, want_hess)
    if tet_gradients(xt, grads) == 0.0:
        return no_contribution(grad, hess, p, 21, want_grad, want_hess)
    triangle_rows(xs, xt, grads, lam)
    n = clip_triangle(lam, mu, vlab, elab)
    if n < 3:
        return no_contribution(grad, hess, p, 21, want_grad, want_hess)
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
        vertex_gradient(lam, mu[0, k], vlab[0, k, 0], vlab[0, k, 1], wmu[k], gphi)
    if want_hess:
        assemble_phi_hessian(lam, dt, mu, vlab, n, wmu, jmu, jidx, ncol, blk, hphi, uu)

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
    # average at a flat interface; the caller names the pair's triangle in tri_state[0]
    # (``work.triangle_cache``).
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
        clip_shift_jacobian(xs, ds)
        tri_state[1] = tri_state[0]
        tri_state[2] = 1
    # Phi is evaluated at the shifted corners y_i = x_i + s(x_tri) (the clip shift): its
    # triangle gradient is T^T dPhi/dy with T = dy/dx = I + [ds/dx] for every corner
    shift_rows(gx, ds)

    for c in range(9):
        grad[p, c] = penalty * (phi * ga[c] + area * gx[c])
    for c in range(9, 21):
        grad[p, c] = penalty * area * gx[c]
    if not want_hess:
        return energy

    if fresh or tri_state[2] < 2:
        area_hessian(nx, ny, nz, inv_n, dn, ga, zv, ha)
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
