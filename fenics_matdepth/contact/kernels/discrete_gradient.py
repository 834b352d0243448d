"""The discrete gradient of one (triangle, tetrahedron) pair's contact energy over a step
(Gonzalez 1996), from the pair kernel's values at the step's start, midpoint and end.

With ``x0``, ``x1`` the pair's 21 vertex coordinates at the start and end of a step,
``dU = x1 - x0``, ``g_m`` the energy's gradient at the midpoint and ``w = M dU`` the step with
the pair's mean translation removed (``M`` subtracts the mean of each component over the 7
vertices: symmetric, idempotent, zero on rigid translations),

    ``DG = g_m + c w``,  ``c = (W(x1) - W(x0) - g_m . dU) / (w . w)``.

Then ``DG . dU = W(x1) - W(x0)`` exactly (``w . dU = w . w``), and ``DG`` sums to zero over
the pair's vertices per component (``g_m`` by the energy's translation invariance, ``w`` by
construction): a force whose work over the step is the change of the pair's energy and which
moves no momentum. Where ``w . w`` is at rounding level (a step that only translates the pair,
or no step) ``c = 0``: there ``W(x1) - W(x0) - g_m . dU`` is itself of order ``|w|^2``.

The derivative of ``DG`` with respect to ``x1`` (``dg_m/dx1 = H_m / 2``):

    ``J = H_m / 2 + c M + w (x) (g_1 - g_m - H_m dU / 2 - 2 c w) / (w . w)``,

not symmetric (the rank-one part).
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
def _pair_step(x0, x1, verts, p, du, w):
    """``du = x1 - x0`` and ``w = M du`` over pair p's 7 vertices; returns ``(w . w, h^2)``
    with h the largest extent of the pair's box at ``x1``."""
    for a in range(7):
        v = verts[p, a]
        for r in range(3):
            du[3 * a + r] = x1[v, r] - x0[v, r]
    ww = 0.0
    ext = 0.0
    for r in range(3):
        mean = 0.0
        lo = x1[verts[p, 0], r]
        hi = lo
        for a in range(7):
            mean += du[3 * a + r]
            c = x1[verts[p, a], r]
            lo = min(lo, c)
            hi = max(hi, c)
        mean /= 7.0
        for a in range(7):
            w[3 * a + r] = du[3 * a + r] - mean
            ww += w[3 * a + r] * w[3 * a + r]
        ext = max(ext, hi - lo)
    return ww, ext * ext


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
    for p in range(verts.shape[0]):
        ww, h2 = _pair_step(x0, x1, verts, p, du, w)
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
    for p in range(verts.shape[0]):
        ww, h2 = _pair_step(x0, x1, verts, p, du, w)
        for i in range(21):
            for j in range(21):
                jac[p, i, j] = 0.5 * hm[p, i, j]
        if not ww > GUARD_RTOL * GUARD_RTOL * h2:
            continue
        c = coef[p]
        for j in range(21):
            half_h_du = 0.0
            for k in range(21):
                half_h_du += hm[p, j, k] * du[k]
            q[j] = (g1[p, j] - gm[p, j] - 0.5 * half_h_du - 2.0 * c * w[j]) / ww
        for i in range(21):
            for j in range(21):
                jac[p, i, j] += w[i] * q[j]
                # c M: c on the diagonal, -c / 7 between equal components of any two vertices
                if i % 3 == j % 3:
                    jac[p, i, j] += c * ((1.0 if i == j else 0.0) - 1.0 / 7.0)
