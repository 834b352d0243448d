"""Assembly of the pairs' derivatives into dolfinx-made PETSc vectors and matrices.

The pair kernels give energies, gradients and Hessians over the pairs' held vertices (see
:mod:`fenics_matdepth.contact.surface`); here they are summed per dof, mapped to the global
dof numbering (``3 v + c`` for component c of global vertex v) and added with PETSc's
off-process assembly, which sends contributions to dofs owned by other ranks. The numba
kernels of the fixed sparsity pattern (row pointers and binary search over its sorted
vertex-coupling keys, Hessian blocks summed into it, the CSR handed to PETSc) are here too.
"""

from __future__ import annotations

import typing

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import numpy as np
from numba import njit

from fenics_matdepth._bulk import csr_blocks
from fenics_matdepth._constants import FLOAT, INDEX
from fenics_matdepth.contact.kernels.fastmath import FMA
from fenics_matdepth.contact.surface import ContactSurface

__all__ = [
    "BulkPattern",
    "add_jacobian_blocks",
    "add_lifting_pairs",
    "coupling_positions",
    "create_matrix",
    "global_dirichlet_dofs",
    "global_dofs",
    "gradient_array",
    "gradient_from_sums",
    "held_keys",
    "hessian_coo",
    "insert_blocks",
    "owned_dirichlet_dofs",
    "pair_dofs",
    "transposed_keys",
]


#: PETSc's index type, for numba to write indices in
_PETSC_INT = np.empty(0, dtype=PETSc.IntType)


# ------------------------------------------------------------------------------------------
# Assembly into a fixed sparsity pattern (no sorting of pair entries per iterate)
# ------------------------------------------------------------------------------------------


@njit(cache=True, fastmath=FMA)
def _add_vertex_block(blocks, key, hess, row, a, b, va, vb, bc_mask):
    """``blocks[key] +=`` the 3 x 3 block (a, b) of pair Hessian ``hess[row]`` (vertices
    ``va``, ``vb``), Dirichlet rows and columns left out."""
    for r in range(3):
        if bc_mask[3 * va + r]:
            continue
        for c in range(3):
            if not bc_mask[3 * vb + c]:
                blocks[key, r, c] += hess[row, 3 * a + r, 3 * b + c]


@njit(cache=True, fastmath=FMA)
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


@njit(cache=True, fastmath=FMA)
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


@njit(cache=True, fastmath=FMA)
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


@njit(cache=True, fastmath=FMA)
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


@njit(cache=True, fastmath=FMA)
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


@njit(cache=True, fastmath=FMA)
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


def global_dofs(surface: ContactSurface, held_dofs: np.ndarray) -> np.ndarray:
    """Global dof numbers of held dofs ``3 h + c``."""
    held_dofs = np.asarray(held_dofs, dtype=INDEX)
    return 3 * surface.global_vertex[held_dofs // 3] + held_dofs % 3


def add_lifting_pairs(
    surface: ContactSurface,
    b: PETSc.Vec,
    offset: np.ndarray,
    verts: typing.Callable[[], np.ndarray],
    hessians: typing.Callable[[np.ndarray], np.ndarray],
) -> None:
    """``b += H[:, D] offset[D]`` over the pairs with a Dirichlet dof not yet on its value
    (collective): the contact share of DOLFINx's lifting, rows of Dirichlet dofs left out.

    Args:
        surface: what the rank holds.
        b: the residual vector (before ``set_bc``).
        offset: (3 n_owned,) ``g - x`` at the owned Dirichlet dofs, zero elsewhere.
        verts: returns the (n, m) held vertices of the pairs (called only if a dof is held).
        hessians: the (k, 3 m, 3 m) pair Hessians of the selected pairs (indices into verts).
    """
    held = surface.pull(np.asarray(offset, dtype=FLOAT).reshape(-1, 3)).reshape(-1)
    dofs = vals = np.empty(0)
    if held.any():
        dofs_of_pairs = pair_dofs(verts())
        moved = held[dofs_of_pairs]
        sel = np.flatnonzero(moved.any(axis=1))
        if sel.size:
            contrib = np.einsum("pij,pj->pi", hessians(sel), moved[sel])
            keep = ~surface.bc[dofs_of_pairs[sel]]
            dofs = global_dofs(surface, dofs_of_pairs[sel][keep])
            vals = contrib[keep]
    b.setValues(dofs.astype(PETSc.IntType), vals, addv=PETSc.InsertMode.ADD_VALUES)
    b.assemblyBegin()
    b.assemblyEnd()


def pair_dofs(verts: np.ndarray) -> np.ndarray:
    """(n, 3 m) held dofs of pairs over (n, m) held vertices, xyz interleaved."""
    return (3 * verts[:, :, None] + np.arange(3)).reshape(verts.shape[0], 3 * verts.shape[1])


def gradient_array(
    surface: ContactSurface, verts: np.ndarray, grad: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """This rank's gradient contributions: (global dofs, values), duplicates summed.

    Args:
        surface: what the rank holds.
        verts: (n, m) held vertices of the pairs.
        grad: (n, 3 m) pair gradients.
    """
    dofs = pair_dofs(verts).ravel()
    # summed over the held dofs (linear in what the rank holds, no sort of the pair entries)
    n = 3 * surface.num_held
    reached = np.zeros(n, dtype=bool)
    reached[dofs] = True
    return gradient_from_sums(
        surface, np.bincount(dofs, weights=grad.ravel(), minlength=n), reached
    )


def gradient_from_sums(
    surface: ContactSurface, grad_sum: np.ndarray, reached: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`gradient_array` from the gradient already summed per held dof (``grad_sum``,
    ``reached``: the dofs some pair has, from ``kernels._area_pairs_summed``)."""
    uniq = np.flatnonzero(reached).astype(INDEX)
    glob = global_dofs(surface, uniq)
    order = np.argsort(glob)
    return glob[order], grad_sum[uniq][order]


def hessian_coo(
    surface: ContactSurface, verts: np.ndarray, hess: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """This rank's Hessian contributions (global rows, cols, values), duplicates summed,
    sorted; entries in a Dirichlet row or column left out."""
    dofs = pair_dofs(verts)
    n = dofs.shape[1]
    rows = np.repeat(dofs, n, axis=1).ravel()
    cols = np.tile(dofs, (1, n)).ravel()
    keep = ~(surface.bc[rows] | surface.bc[cols])
    rows, cols = global_dofs(surface, rows[keep]), global_dofs(surface, cols[keep])
    n_global = 3 * surface.num_vertices
    uniq, inv = np.unique(rows * n_global + cols, return_inverse=True)
    sums = np.bincount(inv, weights=hess.reshape(-1)[keep], minlength=uniq.size)
    return uniq // n_global, uniq % n_global, sums


def held_keys(surface: ContactSurface, keys: np.ndarray) -> np.ndarray:
    """Global vertex-coupling keys in the held numbering (sorted; couplings of vertices the
    rank does not hold are dropped: no pair of the rank reaches them)."""
    nv = surface.num_vertices
    hi = surface.held_index(keys // nv)
    hj = surface.held_index(keys % nv)
    ok = (hi >= 0) & (hj >= 0)
    return np.unique(hi[ok] * surface.num_held + hj[ok])


def transposed_keys(surface: ContactSurface, keys: np.ndarray) -> np.ndarray:
    """The index in ``keys`` of each coupling's transpose (-1 where the pattern lacks it).

    Args:
        surface: what the rank holds.
        keys: sorted held-numbered coupling keys of the pattern (:func:`held_keys`).
    """
    nh = surface.num_held
    return _transposed_keys(keys, _key_rows(keys, nh), nh)


def coupling_positions(
    surface: ContactSurface,
    keys: np.ndarray,
    verts: np.ndarray,
    transposed: np.ndarray | None = None,
) -> tuple[np.ndarray, int]:
    """Where the pairs' vertex couplings lie in the held-numbered pattern ``keys``.

    Computed once per state and used twice: whether the pattern must be rebuilt (asked before
    the Jacobian is assembled) and where each pair's Hessian blocks are summed.

    Args:
        surface: what the rank holds.
        keys: sorted held-numbered coupling keys of the pattern (:func:`held_keys`).
        verts: (n, m) held vertices of the pairs.
        transposed: :func:`transposed_keys` of ``keys`` (computed here if not given).

    Returns:
        ``(pos, missing)``: (n, m, m) index in ``keys`` of each coupling (-1 outside the
        pattern), and the number of couplings outside it.
    """
    nh = surface.num_held
    rows = _key_rows(keys, nh)
    if transposed is None:
        transposed = _transposed_keys(keys, rows, nh)
    pos = np.empty((verts.shape[0], verts.shape[1], verts.shape[1]), dtype=INDEX)
    missing = _coupling_positions(keys, rows, nh, verts, transposed, pos)
    return pos, int(missing)


def add_jacobian_blocks(
    A: PETSc.Mat,
    surface: ContactSurface,
    keys: np.ndarray,
    pos: np.ndarray,
    verts: np.ndarray,
    hess: np.ndarray,
) -> None:
    """Add the pair Hessians into ``A`` (not assembled here), Dirichlet rows/columns skipped.

    Pair Hessians are summed by numba into 3 x 3 blocks of the pattern's vertex couplings
    (at the positions of :func:`coupling_positions`; no sort of the pairs' 441 entries each),
    and only the blocks that pairs reach are inserted. Couplings outside the pattern are left
    out.

    Args:
        A: the matrix.
        surface: what the rank holds.
        keys: sorted held-numbered coupling keys of the pattern (:func:`held_keys`).
        pos: (n, m, m) pattern index of each pair coupling (:func:`coupling_positions`).
        verts: (n, m) held vertices of the pairs.
        hess: (n, 3 m, 3 m) pair Hessians.
    """
    blocks = np.zeros((keys.size, 3, 3), dtype=FLOAT)
    touched = np.zeros(keys.size, dtype=bool)
    _accumulate_vertex_blocks(pos, verts, hess, surface.bc, blocks, touched)
    insert_blocks(A, surface, keys, blocks, touched)


def insert_blocks(
    A: PETSc.Mat, surface: ContactSurface, keys: np.ndarray, blocks: np.ndarray, touched: np.ndarray
) -> None:
    """Add the touched 3 x 3 blocks of the held-numbered pattern ``keys`` into ``A`` (not
    assembled here).

    Args:
        A: the matrix.
        surface: what the rank holds.
        keys: sorted held-numbered coupling keys of the pattern (:func:`held_keys`).
        blocks: (nk, 3, 3) summed blocks, Dirichlet rows and columns already left out.
        touched: (nk,) whether a pair reached each key (only those are inserted).
    """
    rows, indptr, cols, vals = _blocks_to_csr(
        keys, surface.num_held, blocks, touched, surface.global_vertex, _PETSC_INT
    )
    if rows.size:
        A.setValuesIJV(indptr, cols, vals, addv=PETSc.InsertMode.ADD_VALUES, rowmap=rows)


class BulkPattern:
    """The bulk form's sparsity pattern as :func:`create_matrix` needs it, made once per form:
    the vertex-coupling keys ``vi * num_vertices + vj`` of this rank's rows, sorted and unique,
    and the dofs' layout. The mesh does not change, so a matrix rebuilt for new contact
    couplings reuses it (the DOLFINx pattern and its keys: 15 to 20 ms on the knee).

    Args:
        a: the compiled bulk Jacobian form.
        num_vertices: global number of vertices.
    """

    @classmethod
    def of(cls, a: dolfinx.fem.Form, num_vertices: int, kept: BulkPattern | None) -> BulkPattern:
        """``kept`` where it is ``a``'s, else ``a``'s made now."""
        return kept if kept is not None and kept.form is a else cls(a, num_vertices)

    def __init__(self, a: dolfinx.fem.Form, num_vertices: int):
        self.form = a
        csr = dolfinx.fem.create_matrix(a)
        self.bs = csr.block_size[0]  # the space's dofmap block size
        self.row_map = csr.index_map(0)
        self.b0, self.n_blocks = self.row_map.local_range[0], self.row_map.size_local
        block_row, block_col = csr_blocks(csr)
        self.keys = np.unique((block_row + self.b0) * num_vertices + block_col)
        # sizes and local-to-global map from the dofs' index map, as
        # dolfinx.fem.petsc.create_matrix sets them (so that its assemble_matrix can add to A)
        imap = a.function_spaces[0].dofmap.index_map
        self.size = (self.bs * imap.size_local, self.bs * imap.size_global)
        self.held = imap.local_to_global(
            np.arange(imap.size_local + imap.num_ghosts, dtype=np.int32)
        ).astype(PETSc.IntType)


def create_matrix(
    comm: MPI.Comm,
    a: dolfinx.fem.Form | BulkPattern,
    keys: np.ndarray,
    num_vertices: int,
    dirichlet: np.ndarray | None = None,
):
    """A PETSc matrix holding the bulk form's pattern plus the contact vertex couplings.

    Args:
        comm: the mesh communicator.
        a: the compiled bulk Jacobian form, or its :class:`BulkPattern` (kept by a caller
            that rebuilds the matrix).
        keys: this rank's global vertex-coupling keys ``vi * num_vertices + vj``.
        num_vertices: global number of vertices.
        dirichlet: sorted global Dirichlet dofs (every rank's), or None. Their rows and
            columns keep only the diagonal in the pattern, and the matrix ignores the zeros
            assembly adds there (``MAT_IGNORE_ZERO_ENTRIES``).

    Returns:
        An AIJ matrix (block size 3) preallocated exactly, in which insertion never mallocs
        (collective).
    """
    # the bulk pattern from DOLFINx's native CSR matrix, without assembling the form (which
    # took 0.57 s at 172k cells)
    bulk = a if isinstance(a, BulkPattern) else BulkPattern(a, num_vertices)
    csr_ptr, cols = _pattern_csr(comm, bulk, keys, num_vertices, dirichlet)
    lgmap = PETSc.LGMap().create(bulk.held, bsize=bulk.bs, comm=comm)
    A = PETSc.Mat().create(comm=comm)
    A.setSizes((bulk.size, bulk.size), bsize=bulk.bs)
    A.setType(PETSc.Mat.Type.AIJ)
    A.setPreallocationCSR((csr_ptr.astype(PETSc.IntType), cols.astype(PETSc.IntType)))
    A.setLGMap(lgmap, lgmap)
    lgmap.destroy()
    A.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, True)
    A.setOption(PETSc.Mat.Option.KEEP_NONZERO_PATTERN, True)
    if dirichlet is not None:
        # assembly with the conditions adds zeros to their rows and columns off the diagonal
        A.setOption(PETSc.Mat.Option.IGNORE_ZERO_ENTRIES, True)
    return A


def _pattern_csr(
    comm: MPI.Comm,
    bulk: BulkPattern,
    keys: np.ndarray,
    num_vertices: int,
    dirichlet: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray]:
    """The owned rows' pattern of :func:`create_matrix`: its CSR row pointer (process-local
    rows) and global columns, from the bulk pattern's keys and the contact vertex couplings
    ``keys`` (any rank's rows; collective).

    The two are joined as vertex couplings (each a ``bs x bs`` block), one key per block, and
    only then written out per dof: a ninth of the entries to sort (on a 33.6k-tetrahedron box
    with 655k contact couplings, 0.17 s where joining the dof entries took 1 s)."""
    bs, b0, n_blocks = bulk.bs, bulk.b0, bulk.n_blocks
    # each contact coupling to the rank owning its row
    keys = np.asarray(keys, dtype=INDEX)
    ranges = np.asarray(comm.allgather(b0 + n_blocks), dtype=INDEX)
    owner = np.searchsorted(ranges, keys // num_vertices, side="right")
    order = np.argsort(owner, kind="stable")
    splits = np.cumsum(np.bincount(owner, minlength=comm.size))[:-1]
    received = comm.alltoall(np.split(keys[order], splits))
    blocks = np.unique(np.concatenate([bulk.keys] + received))
    # per block row g (its blocks in column order), dof rows bs g .. bs g + bs - 1 each hold
    # the columns bs c .. bs c + bs - 1 of every block c of the row
    block_row = blocks // num_vertices - b0
    per_row = np.bincount(block_row, minlength=n_blocks).astype(INDEX)
    first = np.concatenate(([0], np.cumsum(per_row)))
    block_cols = (bs * (blocks % num_vertices)[:, None] + np.arange(bs, dtype=INDEX)).ravel()
    row_length = np.repeat(bs * per_row, bs)
    ptr = np.concatenate(([0], np.cumsum(row_length)))
    row = np.repeat(np.arange(bs * n_blocks, dtype=INDEX), row_length)
    cols = block_cols[bs * first[row // bs] + np.arange(ptr[-1], dtype=INDEX) - ptr[row]]
    if dirichlet is None:
        return ptr, cols
    rows = row + bs * b0
    marked = np.zeros(bs * bulk.row_map.size_global, dtype=bool)
    marked[dirichlet] = True
    keep = (rows == cols) | ~(marked[rows] | marked[cols])
    kept_per_row = np.bincount(row[keep], minlength=bs * n_blocks)
    return np.concatenate(([0], np.cumsum(kept_per_row))), cols[keep]


def _dirichlet_dofs(bcs, owned_only: bool) -> np.ndarray:
    """Sorted process-local (unrolled) dofs of ``bcs``: the owned ones, or these and the ghosts."""
    local = [np.empty(0, dtype=INDEX)]
    for bc in bcs:
        dofs = np.asarray(bc.dof_indices()[0], dtype=INDEX)
        if owned_only:
            # by the index map, not by the count dof_indices() returns with the list: for a
            # condition on the blocked space that count included the ghosts (DOLFINx 0.9, 2
            # ranks: 60 dofs counted owned, 45 of them owned)
            dofmap = bc.function_space.dofmap
            dofs = dofs[dofs < dofmap.index_map.size_local * dofmap.index_map_bs]
        local.append(dofs)
    return np.unique(np.concatenate(local))


def owned_dirichlet_dofs(bcs) -> np.ndarray:
    """The owned (process-local, unrolled) dofs of the Dirichlet conditions ``bcs`` on the
    displacement space or its subspaces, sorted; each dof is owned by one rank."""
    return _dirichlet_dofs(bcs, owned_only=True)


def global_dirichlet_dofs(comm: MPI.Comm, V: dolfinx.fem.FunctionSpace, bcs) -> np.ndarray:
    """Sorted global (unrolled) dofs of the Dirichlet conditions ``bcs`` on ``V`` or its
    subspaces, from every rank, ghosts included (collective)."""
    imap, bs = V.dofmap.index_map, V.dofmap.index_map_bs
    dofs = _dirichlet_dofs(bcs, owned_only=False)
    glob = bs * imap.local_to_global(dofs // bs).astype(INDEX) + dofs % bs
    return np.unique(np.concatenate(comm.allgather(glob)))
