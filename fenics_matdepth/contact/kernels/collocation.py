"""Point collocation (the baseline), one (boundary vertex a, tetrahedron K) pair and many.

``E = (eps/2) W_a g_K(x_a)^2`` if ``x_a`` is in K (all barycentrics >= 0), else 0; 15 dofs
(the vertex, then the tetrahedron's four). Also the material depth ``g_K`` at points
(`point_depths`).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from fenics_matdepth._constants import FLOAT
from fenics_matdepth.contact.kernels.area import no_contribution
from fenics_matdepth.contact.kernels.fastmath import FMA
from fenics_matdepth.contact.kernels.split import (
    fold_centroid,
    gather_tet,
    is_split,
    store_folded,
    zero_folded,
)
from fenics_matdepth.geometry.clip import tet_gradients

__all__ = ["collocation_pairs", "point_depths"]


#: A point counts as inside a tetrahedron when its barycentric coordinates are all at least
#: ``-_POINT_INSIDE_TOL`` (dimensionless): a point on a face (a vertex on a symmetry plane, on the
#: other body's boundary face) is then not lost to the rounding of ``lambda_0 = 1 - sum``.
_POINT_INSIDE_TOL = 1e-12


@njit(cache=True, fastmath=FMA)
def point_depths(x, depth, tet, points, pair_point, pair_tet):
    """Material depth ``g_K`` at points, per (point, tetrahedron) pair (length).

    ``g_K(y) = sum_j lambda_j(y) d_j`` (as in the pair kernels) where the point y lies in K
    (every barycentric coordinate ``>= -_POINT_INSIDE_TOL``), else 0. A split tetrahedron
    (`is_split`) gives the largest value over its sub-tetrahedra containing y (they agree up
    to rounding: the split depth is continuous), not their sum as the collocation energy does
    for a point on a face they share.

    Args:
        x, depth, tet: as `area_pairs`.
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
        split = is_split(tet, k)
        best = 0.0
        for s in range(4 if split else 1):
            gather_tet(x, depth, tet, k, s, split, xt, dt)
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


@njit(cache=True, fastmath=FMA)
def _collocation_pair(xa, xt, dt, weight, penalty, want_grad, want_hess, work, grad, hess, p):
    """Point-collocation energy of one (vertex, tetrahedron) pair; 15 dofs (vertex, then tet).

    ``E = (eps/2) W g^2`` with ``g = sum_j lambda_j(x_a) d_j`` when every ``lambda_j >= 0``.
    """
    no_contribution(grad, hess, p, 15, want_grad, want_hess)
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


@njit(cache=True, fastmath=FMA)
def collocation_pairs(x, depth, weight, tet, pair_node, pair_tet, penalty, want_grad, want_hess):
    """Point-collocation energies of many (boundary vertex, tetrahedron) pairs.

    Args:
        x: (nv, 3) current vertex coordinates (length).
        depth: (nv,) material depth per vertex (length).
        weight: (nv,) collocation weight W_a per vertex (area, length^2; one third of the area of
            the boundary triangles around a).
        tet: (nk, 4) or (nk, 5) tetrahedra (vertex indices; a fifth column as in
            `area_pairs`: the vertex is tested against, and interpolated in, the
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
        split = is_split(tet, k)
        if split:
            zero_folded(15, want_grad, want_hess, acc_g, acc_h)
        e = 0.0
        # a vertex in a split tetrahedron lies in one of its sub-tetrahedra (in several only
        # on their common faces, a set of measure zero, as between any two tetrahedra)
        for s in range(4 if split else 1):
            gather_tet(x, depth, tet, k, s, split, xt, dt)
            es = _collocation_pair(
                xa, xt, dt, weight[node], penalty, want_grad, want_hess, work, grad, hess, p
            )
            e += es
            if split:
                fold_centroid(grad, hess, p, 3, 15, s, want_grad, want_hess, acc_g, acc_h)
        if split:
            store_folded(grad, hess, p, 15, want_grad, want_hess, acc_g, acc_h)
        energy[p] = e
    return energy, grad, hess
