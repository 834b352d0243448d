"""The discrete gradient of one (triangle, tetrahedron) pair's contact energy over a step
(Gonzalez 1996), from the pair kernel's values at the step's start, midpoint and end.

With ``x0``, ``x1`` the pair's 21 vertex coordinates at the start and end of a step,
``m = (x0 + x1) / 2``, ``dU = x1 - x0``, ``g_m`` the energy's gradient at the midpoint and
``w = P dU`` the step with the pair's rigid motion at the midpoint removed (``P`` projects out,
in R^21, the 3 translations and the 3 rotations ``e_k x (m_a - mean m)`` of the 7 vertices:
symmetric, idempotent; ``w_a = dU_a - mean dU - omega x r_a`` with ``r_a = m_a - mean m`` and
``omega = G^-1 sum_a r_a x dU_a``, ``G = sum_a (|r_a|^2 I - r_a r_a^T)``),

    ``DG = g_m + c w``,  ``c = (W(x1) - W(x0) - g_m . dU) / (w . w)``.

Then ``DG . dU = W(x1) - W(x0)`` exactly (``w . dU = w . w``); ``DG`` sums to zero over the
pair's vertices per component and has no moment about the midpoint configuration,
``sum_a m_a x DG_a = 0`` (``g_m`` by the energy's invariance under translations and rotations,
``w`` by construction): a force whose work over the step is the change of the pair's energy and
which moves neither linear nor (with the trapezoidal rule's midpoint positions) angular
momentum. Where ``w . w`` is at rounding level (a step that only moves the pair rigidly, or no
step) ``c = 0``: there ``W(x1) - W(x0) - g_m . dU`` is itself of order ``|w|^2`` (a rigid
rotation's step is a rigid mode at ``m`` exactly, the Cayley form, so it vanishes).

The derivative of ``DG`` with respect to ``x1`` (``dg_m/dx1 = H_m / 2``, ``dm/dx1 = 1/2``),
with ``D = d(P dU)/dm`` at fixed ``dU`` (the rotation fit following the midpoint):

    ``J = H_m / 2 + c (P + D / 2) + w (x) q``,
    ``q = (g_1 - g_m - H_m dU / 2 - 2 c w - c D^T w) / (w . w)``,

not symmetric (the rank-one part and ``D``).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from fenics_matdepth._constants import FLOAT
from fenics_matdepth.contact.kernels.fastmath import FMA

__all__ = ["GUARD_RTOL", "discrete_gradient_jacobians", "discrete_gradients"]

#: ``c = 0`` where ``|w| <= GUARD_RTOL * h``, h the pair's extent at the step's end: the
#: rounding of ``W(x1) - W(x0) - g_m . dU`` (about 1e-16 of the energy) divided by ``|w|`` stays
#: below 1e-8 of the force there, and the energy error left, of order ``|H| |w|^2``, is
#: negligible.
GUARD_RTOL = 1e-8


@njit(inline="always")
def _pair_step(x0, x1, verts, p, du, w, r, g, ginv, omega):
    """``du = x1 - x0`` and ``w = P du`` over pair p's 7 vertices, with ``r`` (7, 3) the
    midpoint's positions about their mean, ``g`` (3, 3) ``G``, ``ginv`` its inverse and
    ``omega`` (3,) the removed rotation; returns ``(w . w, h^2)`` with h the largest extent of
    the pair's box at ``x1``."""
    for a in range(7):
        v = verts[p, a]
        for k in range(3):
            du[3 * a + k] = x1[v, k] - x0[v, k]
            r[a, k] = 0.5 * (x0[v, k] + x1[v, k])
    ext = 0.0
    for k in range(3):
        mean = 0.0
        centre = 0.0
        lo = x1[verts[p, 0], k]
        hi = lo
        for a in range(7):
            mean += du[3 * a + k]
            centre += r[a, k]
            c = x1[verts[p, a], k]
            lo = min(lo, c)
            hi = max(hi, c)
        mean /= 7.0
        centre /= 7.0
        for a in range(7):
            w[3 * a + k] = du[3 * a + k] - mean
            r[a, k] -= centre
        ext = max(ext, hi - lo)
    # the rotation: G omega = sum_a r_a x w_a (w's mean is 0, so this is sum_a r_a x du_a)
    g[:] = 0.0
    ang0 = ang1 = ang2 = 0.0
    for a in range(7):
        rr = r[a, 0] * r[a, 0] + r[a, 1] * r[a, 1] + r[a, 2] * r[a, 2]
        for k in range(3):
            g[k, k] += rr
            for j in range(3):
                g[k, j] -= r[a, k] * r[a, j]
        ang0 += r[a, 1] * w[3 * a + 2] - r[a, 2] * w[3 * a + 1]
        ang1 += r[a, 2] * w[3 * a] - r[a, 0] * w[3 * a + 2]
        ang2 += r[a, 0] * w[3 * a + 1] - r[a, 1] * w[3 * a]
    _inverse3(g, ginv)
    for k in range(3):
        omega[k] = ginv[k, 0] * ang0 + ginv[k, 1] * ang1 + ginv[k, 2] * ang2
    ww = 0.0
    for a in range(7):
        w[3 * a] -= omega[1] * r[a, 2] - omega[2] * r[a, 1]
        w[3 * a + 1] -= omega[2] * r[a, 0] - omega[0] * r[a, 2]
        w[3 * a + 2] -= omega[0] * r[a, 1] - omega[1] * r[a, 0]
        for k in range(3):
            ww += w[3 * a + k] * w[3 * a + k]
    return ww, ext * ext


@njit(inline="always")
def _inverse3(g, out):
    """``out = g^-1`` for a symmetric positive definite 3 x 3 ``g`` (the adjugate)."""
    out[0, 0] = g[1, 1] * g[2, 2] - g[1, 2] * g[2, 1]
    out[0, 1] = g[0, 2] * g[2, 1] - g[0, 1] * g[2, 2]
    out[0, 2] = g[0, 1] * g[1, 2] - g[0, 2] * g[1, 1]
    out[1, 0] = g[1, 2] * g[2, 0] - g[1, 0] * g[2, 2]
    out[1, 1] = g[0, 0] * g[2, 2] - g[0, 2] * g[2, 0]
    out[1, 2] = g[0, 2] * g[1, 0] - g[0, 0] * g[1, 2]
    out[2, 0] = g[1, 0] * g[2, 1] - g[1, 1] * g[2, 0]
    out[2, 1] = g[0, 1] * g[2, 0] - g[0, 0] * g[2, 1]
    out[2, 2] = g[0, 0] * g[1, 1] - g[0, 1] * g[1, 0]
    det = g[0, 0] * out[0, 0] + g[0, 1] * out[1, 0] + g[0, 2] * out[2, 0]
    for i in range(3):
        for j in range(3):
            out[i, j] /= det


@njit(cache=True, fastmath=FMA)
def discrete_gradients(x0, x1, verts, e0, e1, gm, dg, coef):
    """Per pair: ``dg[p] = DG`` (21,) and ``coef[p] = c`` (module docstring).

    Args:
        x0, x1: (nv, 3) vertex coordinates at the step's start and end.
        verts: (n, 7) vertices of each pair (triangle then tetrahedron).
        e0, e1: (n,) pair energies at ``x0`` and ``x1``.
        gm: (n, 21) pair gradients at the midpoint.
        dg: (n, 21) output; coef: (n,) output.
    """
    du = np.empty(21, dtype=FLOAT)
    w = np.empty(21, dtype=FLOAT)
    r = np.empty((7, 3), dtype=FLOAT)
    g = np.empty((3, 3), dtype=FLOAT)
    ginv = np.empty((3, 3), dtype=FLOAT)
    omega = np.empty(3, dtype=FLOAT)
    for p in range(verts.shape[0]):
        ww, h2 = _pair_step(x0, x1, verts, p, du, w, r, g, ginv, omega)
        c = 0.0
        if ww > GUARD_RTOL * GUARD_RTOL * h2:
            work = 0.0
            for i in range(21):
                work += gm[p, i] * du[i]
            c = (e1[p] - e0[p] - work) / ww
        coef[p] = c
        for i in range(21):
            dg[p, i] = gm[p, i] + c * w[i]


@njit(cache=True, fastmath=FMA)
def discrete_gradient_jacobians(x0, x1, verts, gm, g1, hm, coef, jac):
    """Per pair: ``jac[p]`` (21, 21), the derivative of ``DG`` with respect to ``x1``.

    Args:
        x0, x1, verts, gm: as `discrete_gradients`.
        g1: (n, 21) pair gradients at ``x1``.
        hm: (n, 21, 21) pair Hessians at the midpoint.
        coef: (n,) ``c`` of `discrete_gradients`.
        jac: (n, 21, 21) output.
    """
    du = np.empty(21, dtype=FLOAT)
    w = np.empty(21, dtype=FLOAT)
    q = np.empty(21, dtype=FLOAT)
    r = np.empty((7, 3), dtype=FLOAT)
    g = np.empty((3, 3), dtype=FLOAT)  # scratch: G, then the rotation derivative's vectors
    ginv = np.empty((3, 3), dtype=FLOAT)
    omega = np.empty(3, dtype=FLOAT)
    d = np.empty((21, 21), dtype=FLOAT)
    bw = np.empty((21, 3), dtype=FLOAT)
    bg = np.empty((21, 3), dtype=FLOAT)
    for p in range(verts.shape[0]):
        ww, h2 = _pair_step(x0, x1, verts, p, du, w, r, g, ginv, omega)
        for i in range(21):
            for j in range(21):
                jac[p, i, j] = 0.5 * hm[p, i, j]
        if not ww > GUARD_RTOL * GUARD_RTOL * h2:
            continue
        c = coef[p]
        _rotation_derivative(du, r, ginv, omega, d, g)
        # the rotation modes' columns, e_k x r_a, for P = M - B G^-1 B^T
        for a in range(7):
            bw[3 * a, 0], bw[3 * a + 1, 0], bw[3 * a + 2, 0] = 0.0, -r[a, 2], r[a, 1]
            bw[3 * a, 1], bw[3 * a + 1, 1], bw[3 * a + 2, 1] = r[a, 2], 0.0, -r[a, 0]
            bw[3 * a, 2], bw[3 * a + 1, 2], bw[3 * a + 2, 2] = -r[a, 1], r[a, 0], 0.0
        for i in range(21):  # B G^-1, once per pair
            for k in range(3):
                bg[i, k] = bw[i, 0] * ginv[0, k] + bw[i, 1] * ginv[1, k] + bw[i, 2] * ginv[2, k]
        for j in range(21):
            half_h_du = 0.0
            dtw = 0.0
            for k in range(21):
                half_h_du += hm[p, j, k] * du[k]
                dtw += d[k, j] * w[k]
            q[j] = (g1[p, j] - gm[p, j] - 0.5 * half_h_du - 2.0 * c * w[j] - c * dtw) / ww
        for i in range(21):
            for j in range(21):
                # c P: c on the diagonal, -c / 7 between equal components of any two vertices,
                # minus c B G^-1 B^T (the rotations)
                proj = -(bg[i, 0] * bw[j, 0] + bg[i, 1] * bw[j, 1] + bg[i, 2] * bw[j, 2])
                if i % 3 == j % 3:
                    proj += (1.0 if i == j else 0.0) - 1.0 / 7.0
                jac[p, i, j] += w[i] * q[j] + c * (proj + 0.5 * d[i, j])


@njit(inline="always")
def _rotation_derivative(du, r, ginv, omega, d, tmp):
    """``d[:, 3 c + s] = d(P du)/dm_{c s}`` at fixed ``du`` (``tmp``: (3, 3) scratch): with
    ``dL = e_s x du'_c`` (``du'`` the step less its mean) and ``dG = 2 r_{c s} I - e_s r_c^T -
    r_c e_s^T``, ``d omega = G^-1 (dL - dG omega)`` and ``d w_a = -d omega x r_a - (delta_ac -
    1/7) omega x e_s``."""
    m0 = m1 = m2 = 0.0
    for a in range(7):
        m0 += du[3 * a] / 7.0
        m1 += du[3 * a + 1] / 7.0
        m2 += du[3 * a + 2] / 7.0
    e, rhs, dom = tmp[0], tmp[1], tmp[2]
    for cv in range(7):
        dp0 = du[3 * cv] - m0
        dp1 = du[3 * cv + 1] - m1
        dp2 = du[3 * cv + 2] - m2
        for s in range(3):
            e[:] = 0.0
            e[s] = 1.0
            # dL = e_s x du'_c
            rhs[0] = e[1] * dp2 - e[2] * dp1
            rhs[1] = e[2] * dp0 - e[0] * dp2
            rhs[2] = e[0] * dp1 - e[1] * dp0
            # - dG omega = -(2 r_cs omega - e_s (r_c . omega) - r_c omega_s)
            rdo = r[cv, 0] * omega[0] + r[cv, 1] * omega[1] + r[cv, 2] * omega[2]
            for k in range(3):
                rhs[k] -= 2.0 * r[cv, s] * omega[k] - e[k] * rdo - r[cv, k] * omega[s]
            for k in range(3):
                dom[k] = ginv[k, 0] * rhs[0] + ginv[k, 1] * rhs[1] + ginv[k, 2] * rhs[2]
            ox0 = omega[1] * e[2] - omega[2] * e[1]
            ox1 = omega[2] * e[0] - omega[0] * e[2]
            ox2 = omega[0] * e[1] - omega[1] * e[0]
            col = 3 * cv + s
            for a in range(7):
                f = (1.0 if a == cv else 0.0) - 1.0 / 7.0
                d[3 * a, col] = -(dom[1] * r[a, 2] - dom[2] * r[a, 1]) - f * ox0
                d[3 * a + 1, col] = -(dom[2] * r[a, 0] - dom[0] * r[a, 2]) - f * ox1
                d[3 * a + 2, col] = -(dom[0] * r[a, 1] - dom[1] * r[a, 0]) - f * ox2
