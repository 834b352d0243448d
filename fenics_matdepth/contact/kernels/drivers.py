"""Batch drivers of the area-integration kernel over many (triangle, tetrahedron) pairs.

Plain (`area_pairs`: every pair's energy, gradient and Hessian), into preallocated arrays
(`area_pairs_into`: the contributing pairs only, compactly), summed (`area_pairs_summed`:
gradients and Hessians added into per-dof sums and pattern blocks as they are made) and the
exact intersection test over pairs (`intersecting`).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from fenics_matdepth._constants import FLOAT, INDEX
from fenics_matdepth.contact.kernels.area import area_pair, area_work
from fenics_matdepth.contact.kernels.fastmath import FMA
from fenics_matdepth.contact.kernels.split import (
    fold_centroid,
    gather_tet,
    is_split,
    store_folded,
    zero_folded,
)
from fenics_matdepth.geometry.intersect import intersect_pairs

__all__ = ["area_pairs", "area_pairs_into", "area_pairs_summed", "intersecting"]


@njit(cache=True, fastmath=FMA)
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
    """The one loop over pairs behind `area_pairs` and `area_pairs_into` (a single compiled
    copy of the pair kernel). With a non-empty ``active``, row m of the outputs is the m-th
    contributing pair (``active[m]`` its index); with an empty one, row p is pair p.

    Returns:
        The number of contributing pairs.
    """
    # decided from the data, not passed as a constant: a literal argument would compile a
    # second copy of this large function
    compact = active.shape[0] > 0
    cap = energy.shape[0]
    work = area_work()
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
        work.triangle_cache[0] = pair_tri[p]
        k = pair_tet[p]
        split = is_split(tet, k)
        row = m if compact else p
        fits = row < cap
        wg = want_grad and fits
        wh = want_hess and fits
        out_row = row if fits else 0
        if split:
            zero_folded(21, wg, wh, acc_g, acc_h)
        e = -1.0
        # a split tetrahedron is four sub-tetrahedra: the pair's energy and derivatives are
        # the sums of theirs, mapped back to the parent's vertices
        for s in range(4 if split else 1):
            gather_tet(x, depth, tet, k, s, split, xt, dt)
            es = area_pair(xs, xt, dt, no_offset, penalty, wg, wh, work, grad, hess, out_row)
            if not split:
                e = es
            elif es >= 0.0:
                e = es if e < 0.0 else e + es
                fold_centroid(grad, hess, out_row, 9, 21, s, wg, wh, acc_g, acc_h)
        if split:
            store_folded(grad, hess, out_row, 21, wg, wh, acc_g, acc_h)
        if e >= 0.0:
            if fits:
                energy[row] = e
                if compact:
                    active[row] = p
            m += 1
        elif fits and not compact:
            energy[row] = 0.0
    return m


@njit(cache=True, fastmath=FMA)
def area_pairs(x, depth, tri, tet, pair_tri, pair_tet, penalty, want_grad, want_hess):
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


@njit(cache=True, fastmath=FMA)
def area_pairs_into(
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
    """Like `area_pairs`, but writes only the contributing pairs, compactly, into preallocated
    arrays (reused across Newton iterations: no allocation, no page faults).

    Args:
        x, depth, tri, tet, pair_tri, pair_tet, penalty, want_grad, want_hess: as `area_pairs`.
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


#: Pairs a chunk of `area_pairs_summed`: their Hessians (3.5 kB each) stay in the cache
#: between the kernel that writes them and the sums that read them.
_SUM_CHUNK = 32


@njit(cache=True, fastmath=FMA)
def _sum_pair_rows(
    tri, tet, pair_tri, pair_tet, start, count, grad, hess, want_hess, pos, grad_sum, reached,
    blocks, touched,
):  # fmt: skip
    """Add rows ``0..count`` of a chunk's pair gradients and Hessians (pairs ``start ..
    start + count``) into per-dof sums and the pattern's 3 x 3 blocks.

    The same sums, in the same order, as `contact.assembly.gradient_array` (``np.bincount``
    over the pairs' dofs) and its `_accumulate_vertex_blocks` on the materialised arrays, but
    for the Dirichlet rows and columns, which `_zero_dirichlet` clears after the last chunk (a
    mask test per entry here cost more than the sums).
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


@njit(cache=True, fastmath=FMA)
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


@njit(cache=True, fastmath=FMA)
def area_pairs_summed(
    x, depth, tri, tet, pair_tri, pair_tet, penalty, want_hess, pos, keys, bc_mask, energy,
    grad_sum, reached, blocks, touched,
):  # fmt: skip
    """`area_pairs` with the gradients (and Hessians) summed as they are made, never
    materialised for all pairs: chunks of `_SUM_CHUNK` pairs go through the one pair loop
    (`_area_pairs_core`) into small buffers, which are then added into per-dof sums and the
    3 x 3 blocks of a fixed vertex-coupling pattern.

    Args:
        x, depth, tri, tet, pair_tri, pair_tet, penalty: as `area_pairs` (``tri`` and ``tet``
            in the numbering of the dofs, ``3 v + c``).
        want_hess: whether to compute and sum the Hessians.
        pos: (np, 7, 7) pattern index of each pair coupling, -1 outside the pattern (left
            out), as `contact.assembly`'s `_coupling_positions`; read only if want_hess.
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


@njit(cache=True, fastmath=FMA)
def intersecting(x, tri, tet, pair_tri, pair_tet):
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
