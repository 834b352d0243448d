"""Tetrahedra split into four sub-tetrahedra around their centroid (thin layers).

A fifth column of the kernels' ``tet`` array, when present and ``>= 0``, is the index in
``depth`` of the centroid's depth: the tetrahedron is then evaluated as its four
sub-tetrahedra (vertex s replaced by the centroid) and their derivatives are mapped back to its
four vertices (see ``docs/kernels.md``, thin layers).
"""

from __future__ import annotations

from numba import njit

from fenics_matdepth.contact.kernels.fastmath import FMA

__all__ = ["fold_centroid", "gather_tet", "is_split", "store_folded", "zero_folded"]


@njit(cache=True, fastmath=FMA)
def is_split(tet, k):
    """Whether tetrahedron k is evaluated as four sub-tetrahedra around its centroid: a fifth
    column of ``tet``, when present, holds the index in ``depth`` of the centroid's depth
    (``-1``: not split)."""
    return tet.shape[1] > 4 and tet[k, 4] >= 0


@njit(cache=True, fastmath=FMA)
def gather_tet(x, depth, tet, k, s, split, xt, dt):
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


@njit(cache=True, fastmath=FMA)
def fold_centroid(grad, hess, row, off, n, s, want_grad, want_hess, acc_g, acc_h):
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


@njit(cache=True, fastmath=FMA)
def store_folded(grad, hess, row, n, want_grad, want_hess, acc_g, acc_h):
    """Write the accumulated parent-tetrahedron derivatives into row ``row``."""
    if want_grad:
        for c in range(n):
            grad[row, c] = acc_g[c]
    if want_hess:
        for i in range(n):
            for c in range(n):
                hess[row, i, c] = acc_h[i, c]


@njit(cache=True, fastmath=FMA)
def zero_folded(n, want_grad, want_hess, acc_g, acc_h):
    if want_grad:
        for c in range(n):
            acc_g[c] = 0.0
    if want_hess:
        for i in range(n):
            for c in range(n):
                acc_h[i, c] = 0.0
