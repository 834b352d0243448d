"""Augmented Lagrangian (paper section 8.3): nodal contact pressures on the penetrating surface.

The pair energies at fixed pressures (`area_pairs_augmented`, through the area kernel with a
constant offset) and the integrals the Uzawa update of the pressures needs
(`area_pairs_pressure_moments`).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from fenics_matdepth._constants import FLOAT
from fenics_matdepth.contact.kernels.area import area_pair, area_work
from fenics_matdepth.contact.kernels.fastmath import FMA
from fenics_matdepth.contact.kernels.polygon import gather_triangle, polygon_work, sub_polygon
from fenics_matdepth.contact.kernels.split import (
    fold_centroid,
    gather_tet,
    is_split,
    store_folded,
    zero_folded,
)

__all__ = ["area_pairs_augmented", "area_pairs_pressure_moments"]


@njit(cache=True, fastmath=FMA)
def _scale_row(grad, hess, row, n, factor, want_grad, want_hess):
    """Multiply row ``row`` of grad (n,) and hess (n, n) by ``factor`` in place."""
    if want_grad:
        for c in range(n):
            grad[row, c] *= factor
    if want_hess:
        for r in range(n):
            for c in range(n):
                hess[row, r, c] *= factor


@njit(cache=True, fastmath=FMA)
def _add_row(grad, hess, row, n, want_grad, want_hess, acc_g, acc_h):
    """``acc += row`` of grad and hess."""
    if want_grad:
        for c in range(n):
            acc_g[c] += grad[row, c]
    if want_hess:
        for r in range(n):
            for c in range(n):
                acc_h[r, c] += hess[row, r, c]


@njit(cache=True, fastmath=FMA)
def area_pairs_augmented(
    x, depth, tri, tet, pair_tri, pair_tet, penalty, pressure, width, want_grad, want_hess
):
    """Augmented-Lagrangian energies of many (triangle, tetrahedron) pairs at fixed pressures.

    The energy of a pair is ``E = int_{T cap K} (p g + (eps/2) g^2) dA``, with ``g`` the material
    depth (as in `area_pairs`) and ``p`` the nodal pressures of the triangle's vertices
    interpolated linearly on the triangle (``p = sum_i p_i mu_i``, ``mu`` the barycentric
    coordinates in T): the pressure is a P1 field on the penetrating surface, carried with its
    material points, so the force it adds is ``p grad g`` (paper, section 8.3). Completing the
    square, with ``Phi(H) = int_P (H . mu)^2 dxi`` as in `area_pair`:

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
        x, depth, tri, tet, pair_tri, pair_tet, penalty, want_grad, want_hess: as `area_pairs`.
        pressure: (nv,) nodal contact pressure of each vertex (pressure units, >= 0); only
            the values at triangle vertices are read.
        width: 0 for the linear pressure term, else ``w`` (length) of the quadratic one.

    Returns:
        ``energy (np,)``, ``grad (np, 21)``, ``hess (np, 21, 21)`` as `area_pairs`.
    """
    npairs = pair_tri.shape[0]
    energy = np.zeros(npairs, dtype=FLOAT)
    grad = np.zeros((npairs if want_grad else 0, 21), dtype=FLOAT)
    hess = np.zeros((npairs if want_hess else 0, 21, 21), dtype=FLOAT)
    work = area_work()
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
        work.triangle_cache[0] = pair_tri[p]
        k = pair_tet[p]
        split = is_split(tet, k)
        zero_folded(21, want_grad, want_hess, acc_g, acc_h)
        e = 0.0
        hit = False
        for s in range(4 if split else 1):
            for term in range(2 if has_pressure else 1):
                gather_tet(x, depth, tet, k, s, split, xt, dt)
                if term == 1:
                    for a in range(4):
                        dt[a] = 0.0
                es = area_pair(xs, xt, dt, offset, stiffness, want_grad, want_hess, work, grad,
                                hess, p)  # fmt: skip
                if es < 0.0:
                    break  # no polygon: neither term contributes
                hit = True
                if term == 1:
                    es = -es
                    _scale_row(grad, hess, p, 21, -1.0, want_grad, want_hess)
                e += es
                if split:
                    fold_centroid(grad, hess, p, 9, 21, s, want_grad, want_hess, acc_g, acc_h)
                else:
                    _add_row(grad, hess, p, 21, want_grad, want_hess, acc_g, acc_h)
        store_folded(grad, hess, p, 21, want_grad, want_hess, acc_g, acc_h)
        energy[p] = e if hit else 0.0
    return energy, grad, hess


@njit(cache=True, fastmath=FMA)
def area_pairs_pressure_moments(x, depth, tri, tet, pair_tri, pair_tet):
    """The integrals the Uzawa update of the nodal pressures needs, per pair and triangle vertex.

    For each pair and each vertex i of its triangle, over the intersection polygon (current
    configuration; split tetrahedra summed over their sub-tetrahedra):
    ``gmom[p, i] = int_{T cap K} mu_i g dA`` (length^3) and
    ``amom[p, i] = int_{T cap K} mu_i dA`` (length^2), ``mu_i`` the hat function of vertex i
    on T. Exact: a fan of signed triangles in the parameter plane, on which ``mu_i`` and ``g``
    are linear (``int f h = area / 12 (sum_k f_k h_k + sum_k f_k sum_k h_k)``).

    Args:
        x, depth, tri, tet, pair_tri, pair_tet: as `area_pairs`.

    Returns:
        ``gmom (np, 3)``, ``amom (np, 3)``.
    """
    npairs = pair_tri.shape[0]
    gmom = np.zeros((npairs, 3), dtype=FLOAT)
    amom = np.zeros((npairs, 3), dtype=FLOAT)
    work = polygon_work()
    xs, mu, gi = work.xs, work.mu, work.corner_depth
    for p in range(npairs):
        a2 = gather_triangle(x, tri, pair_tri[p], xs)
        if a2 == 0.0:
            continue
        k = pair_tet[p]
        split = is_split(tet, k)
        for s in range(4 if split else 1):
            n = sub_polygon(x, depth, tet, k, s, split, work)
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
