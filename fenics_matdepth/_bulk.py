"""The bulk Jacobian assembled by DOLFINx's native CSR matrix, then added to a PETSc matrix.

``dolfinx.fem.petsc.assemble_matrix`` adds every cell's element matrix into the PETSc matrix
entry by entry (``MatSetValuesLocal``: an index map and a search per entry): 0.20 s at 60.7k
tetrahedra of P1 elasticity (36k dofs, docs/solvers.md), where the same form compiled with
``-O3 -march=native`` took as long, so the kernels are not what costs. DOLFINx's own
``MatrixCSR`` takes the element matrices in 0.080 s; its summed rows (one entry per nonzero
instead of one per cell coupling, about a sixth as many) then go into the PETSc matrix row by
row with sorted columns in 0.015 s.

Where nothing the form reads has changed since the last assembly (its constants, its
coefficients' arrays, the mesh's coordinates: a Jacobian that does not depend on the
displacement, as in linear elasticity, between changes of its parameters), the last
assembly's values are added again without assembling.
"""

from __future__ import annotations

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import numpy as np
import ufl

from fenics_matdepth._compat import integral_domains
from fenics_matdepth._constants import INDEX

__all__ = [
    "BulkMatrix",
    "csr_blocks",
    "csr_entries",
    "everywhere_numbered",
    "fixed_cells",
    "without_cells",
]


def csr_blocks(csr) -> tuple[np.ndarray, np.ndarray]:
    """The owned block rows' blocks of a DOLFINx ``MatrixCSR``, in its order (by row, columns
    in block order within a row): each block's process-local block row and global block
    column."""
    row_map, col_map = csr.index_map(0), csr.index_map(1)
    n_blocks = row_map.size_local
    indptr = np.asarray(csr.indptr[: n_blocks + 1], dtype=INDEX)
    n_cols = col_map.size_local + col_map.num_ghosts
    global_block = col_map.local_to_global(np.arange(n_cols, dtype=np.int32)).astype(INDEX)
    block_row = np.repeat(np.arange(n_blocks, dtype=INDEX), np.diff(indptr))
    return block_row, global_block[np.asarray(csr.indices[: indptr[-1]], dtype=INDEX)]


def csr_entries(csr) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The owned rows' entries of a DOLFINx ``MatrixCSR`` (its pattern: ghost rows' entries
    are in their owners' rows too, from the sparsity pattern's exchange).

    Returns:
        ``(data_index, row, col)``, sorted by row (columns in block order within a row): the
        entry's index in ``csr.data``, its process-local scalar row and its global scalar
        column.
    """
    bs = csr.block_size[0]
    # MatrixCSR stores bs x bs blocks row-major: entry (r, c) of block k is data[k bs^2 + r bs
    # + c]. The scalar rows are ordered (block row, r), each holding its blocks' entries
    # (block, c) in block order.
    block_row, block_col = csr_blocks(csr)
    k = np.arange(block_col.size, dtype=INDEX)
    r = np.arange(bs, dtype=INDEX)
    c = np.arange(bs, dtype=INDEX)
    data_index = (k[None, :, None] * bs * bs + r[:, None, None] * bs + c[None, None, :]).ravel()
    row = np.broadcast_to(
        block_row[None, :, None] * bs + r[:, None, None], (bs, k.size, bs)
    ).ravel()
    col = np.broadcast_to(
        bs * block_col[None, :, None] + c[None, None, :], (bs, k.size, bs)
    ).ravel()
    order = np.argsort(row, kind="stable")
    return data_index[order], row[order], col[order]


class BulkMatrix:
    """Adds the bulk form's Jacobian to a PETSc matrix whose pattern holds the form's.

    The form is assembled into a ``dolfinx.la.MatrixCSR`` (Dirichlet rows and columns zeroed);
    its owned rows, ghost contributions summed in and 1 on the Dirichlet diagonal (as
    ``dolfinx.fem.petsc.assemble_matrix`` gives them), are added to the PETSc matrix. The
    entries of Dirichlet rows and columns off the diagonal (zeros) are left out, so the target
    may omit them from its pattern (``contact.assembly.create_matrix``).

    Args:
        a: compiled bilinear form, test and trial space the same.
        bcs: the Dirichlet conditions.
        dirichlet: sorted global dofs of ``bcs`` (every rank's).
        assembled: the form assembled, if not ``a``: ``a`` over fewer cells (its pattern is
            ``a``'s).
    """

    def __init__(
        self,
        a: dolfinx.fem.Form,
        bcs: list[dolfinx.fem.DirichletBC],
        dirichlet: np.ndarray,
        assembled: dolfinx.fem.Form | None = None,
    ):
        self.a, self.bcs = (a if assembled is None else assembled), list(bcs)
        self.csr = dolfinx.fem.create_matrix(a)
        data_index, row, col = csr_entries(self.csr)
        bs = self.csr.block_size[0]
        row_map = self.csr.index_map(0)
        n_blocks = row_map.size_local
        r0 = bs * row_map.local_range[0]
        global_row = row + r0
        in_dirichlet_row = np.isin(global_row, dirichlet)
        keep = (global_row == col) | ~(in_dirichlet_row | np.isin(col, dirichlet))
        data_index, row, col = data_index[keep], row[keep], col[keep]
        # the Dirichlet diagonal is set after the ghost rows are summed in: as DOLFINx's CSR
        # assembly leaves it, it was not 1 at Dirichlet dofs on a rank boundary (2 ranks)
        self._dirichlet_diagonal = np.flatnonzero(in_dirichlet_row[keep])
        self._data_index = data_index
        self._indptr = np.searchsorted(row, np.arange(bs * n_blocks + 1)).astype(PETSc.IntType)
        self._cols = col.astype(PETSc.IntType)
        self._rows = np.arange(r0, r0 + bs * n_blocks, dtype=PETSc.IntType)
        self._inputs: tuple | None = None  # what the form read at the last assembly
        self._values: np.ndarray | None = None  # and the values it gave
        #: assemblies skipped because nothing the form reads had changed
        self.reused = 0

    def _read_inputs(self) -> tuple:
        """The arrays the form's kernels read: its packed constants, its coefficients' values
        (ghosts included) and the mesh's coordinates (views, not copies)."""
        cpp = self.a._cpp_object
        return (
            dolfinx.cpp.fem.pack_constants(cpp),
            *(c.x.array for c in cpp.coefficients),
            self.a.mesh.geometry.x,
        )

    def _unchanged(self, inputs: tuple) -> bool:
        """Whether ``inputs`` equal those of the last assembly on every rank (collective)."""
        same = self._inputs is not None and all(
            np.array_equal(now, then) for now, then in zip(inputs, self._inputs, strict=True)
        )
        return self.a.mesh.comm.allreduce(same, op=MPI.LAND)

    def add_to(self, A: PETSc.Mat) -> None:
        """Assemble the form, unless nothing it reads has changed since the last assembly,
        and add it to ``A``'s owned rows (``A`` not assembled here; collective)."""
        inputs = self._read_inputs()
        if self._unchanged(inputs):
            self.reused += 1
        else:
            self.csr.set_value(0.0)
            dolfinx.fem.assemble_matrix(self.csr, self.a, self.bcs)
            self.csr.scatter_reverse()
            self._values = self.csr.data[self._data_index]
            self._values[self._dirichlet_diagonal] = 1.0
            self._inputs = tuple(np.copy(array) for array in inputs)
        A.setValuesIJV(
            self._indptr,
            self._cols,
            self._values,
            addv=PETSc.InsertMode.ADD_VALUES,
            rowmap=self._rows,
        )


def fixed_cells(V: dolfinx.fem.FunctionSpace, owned_dirichlet: np.ndarray) -> np.ndarray:
    """Whether each of this process's cells (owned, then ghosts) has every dof prescribed: a
    mask, from the owned (process-local, unrolled) Dirichlet dofs
    (:func:`~fenics_matdepth.contact.assembly.owned_dirichlet_dofs`), so that a dof counts
    where its owner prescribes it (collective)."""
    imap, bs = V.dofmap.index_map, V.dofmap.index_map_bs
    marked = dolfinx.la.vector(imap, bs)
    marked.array[owned_dirichlet] = 1.0
    marked.scatter_forward()
    cells = np.asarray(V.dofmap.list)
    dofs = (bs * cells[:, :, None] + np.arange(bs)).reshape(cells.shape[0], bs * cells.shape[1])
    return (marked.array[dofs] == 1.0).all(axis=1)


def everywhere_numbered(form: ufl.Form, ident: int) -> ufl.Form:
    """``form`` with its cell integrals over every cell under the subdomain id ``ident``: their
    cells can then be given (DOLFINx finds an id -1 integral's cells itself, whatever cells a
    form is given for it)."""
    return ufl.Form(
        [
            itg.reconstruct(subdomain_id=ident)
            if itg.integral_type() == "cell" and itg.subdomain_id() in ("everywhere", "otherwise")
            else itg
            for itg in form.integrals()
        ]
    )


def without_cells(
    form: ufl.Form,
    compiled: dolfinx.fem.Form,
    left_out: np.ndarray,
    form_compiler_options: dict | None = None,
    jit_options: dict | None = None,
) -> dolfinx.fem.Form:
    """``compiled`` (DOLFINx's form of the UFL ``form``) with the cells of the mask
    ``left_out`` taken out of its cell integrals: its other integrals, and the cells it keeps
    in the order it had them, are the same, so whatever it adds elsewhere is the same to the
    bit.

    An integral over every cell is compiled under an id of its own (:func:`everywhere_numbered`),
    one below the smallest other cell id, which keeps it first in the order DOLFINx assembles
    the integrals in; where the smallest other id is 0 it keeps every cell.

    The problems assemble their residual and Jacobian over the cells that hold a free dof:
    a cell whose every dof is prescribed (a bone moved as a whole by its Dirichlet
    conditions) adds only to Dirichlet rows and columns, which the conditions overwrite.
    """
    cell, facet = dolfinx.fem.IntegralType.cell, dolfinx.fem.IntegralType.exterior_facet
    if set(compiled.integral_types) - {cell, facet}:
        raise NotImplementedError(
            "a form with interior-facet or vertex integrals is assembled over every cell"
        )
    cells = integral_domains(compiled, cell)
    own = min([i for i, _ in cells if i != -1], default=1) - 1
    renumber = own >= 0 and any(i == -1 for i, _ in cells)
    if renumber:
        form = everywhere_numbered(form, own)
    subdomains = {
        cell: [(own if renumber and i == -1 else i, e[~left_out[e]]) for i, e in cells],
        facet: [(i, np.ascontiguousarray(e)) for i, e in integral_domains(compiled, facet)],
    }
    spaces = [argument.ufl_function_space() for argument in form.arguments()]
    return dolfinx.fem.create_form(
        dolfinx.fem.compile_form(
            spaces[0].mesh.comm, form, form_compiler_options=form_compiler_options,
            jit_options=jit_options,
        ),
        spaces,
        spaces[0].mesh,
        {kind: entries for kind, entries in subdomains.items() if entries},
        {c: c for c in form.coefficients()},
        {c: c for c in form.constants()},
    )  # fmt: skip
