"""Per-dof sums and PETSc insertion of pair derivatives (fenics_matdepth/contact/assembly.py)
against dense numpy sums: random pair gradients and Hessians over random held vertices of a
real surface (two boxes), with Dirichlet conditions, on any number of ranks."""

from __future__ import annotations

from mpi4py import MPI

import dolfinx
import dolfinx.fem.petsc
import numpy as np
import ufl
from conftest import dense_matrix
from test_pairs import two_box_surface

from fenics_matdepth.contact import assembly

#: Sums in another order than numpy's: relative to the largest entry.
RTOL = 1e-13


def _model(num_pairs: int = 40, seed: int = 0):
    """A surface with the bottom face clamped, and random pairs of 7 distinct held vertices
    with random gradients and Hessians (different on every rank)."""
    comm = MPI.COMM_WORLD
    surface = two_box_surface("area", perturbed=False)
    V = surface.u.function_space
    mesh = V.mesh
    facets = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[2], 0.0))
    bcs = [
        dolfinx.fem.dirichletbc(np.zeros(3), dolfinx.fem.locate_dofs_topological(V, 2, facets), V)
    ]
    mask = np.zeros(surface.owned_dof_count(), dtype=bool)
    mask[assembly.owned_dirichlet_dofs(bcs)] = True
    surface.set_bcs(mask)
    rng = np.random.default_rng(seed + comm.rank)
    verts = np.array([rng.choice(surface.num_held, 7, replace=False) for _ in range(num_pairs)])
    grad = rng.normal(size=(num_pairs, 21))
    # not symmetric: an entry put in its transpose's place would show
    hess = rng.normal(size=(num_pairs, 21, 21))
    return V, bcs, surface, verts, grad, hess


def _dense_sums(surface, verts, grad, hess) -> tuple[np.ndarray, np.ndarray]:
    """The gradient and Hessian summed over every rank's pairs in global dofs (numpy, dense),
    Dirichlet rows and columns of the Hessian zero."""
    n = 3 * surface.num_vertices
    dofs = (3 * surface.global_vertex[verts][:, :, None] + np.arange(3)).reshape(-1, 21)
    bc = (surface.bc.reshape(-1, 3)[verts]).reshape(-1, 21)
    g = np.zeros(n)
    np.add.at(g, dofs, grad)
    h = np.zeros((n, n))
    keep = ~(bc[:, :, None] | bc[:, None, :])
    np.add.at(
        h,
        (
            np.broadcast_to(dofs[:, :, None], hess.shape),
            np.broadcast_to(dofs[:, None, :], hess.shape),
        ),
        np.where(keep, hess, 0.0),
    )
    comm = surface.comm
    return comm.allreduce(g), comm.allreduce(h)


def test_global_and_pair_dofs():
    """Held dof ``3 h + c`` is global dof ``3 global_vertex[h] + c``; a pair's dofs are its
    vertices' xyz interleaved."""
    _, _, surface, verts, _, _ = _model(5)
    held = np.arange(3 * surface.num_held)
    expected = np.array([3 * surface.global_vertex[d // 3] + d % 3 for d in held.tolist()])
    assert np.array_equal(assembly.global_dofs(surface, held), expected)
    dofs = assembly.pair_dofs(verts)
    assert dofs.shape == (5, 21)
    for p in range(5):
        assert dofs[p].tolist() == [3 * v + c for v in verts[p].tolist() for c in range(3)]


def test_gradient_sums_match_dense():
    """``gradient_array``: the ranks' (dof, value) lists, each dof once per rank and sorted,
    add up to the dense sum."""
    _, _, surface, verts, grad, hess = _model()
    g_dense, _ = _dense_sums(surface, verts, grad, hess)
    dofs, values = assembly.gradient_array(surface, verts, grad)
    assert np.all(np.diff(dofs) > 0)
    reached = np.unique(assembly.global_dofs(surface, assembly.pair_dofs(verts).ravel()))
    assert np.array_equal(dofs, reached)
    n = 3 * surface.num_vertices
    total = surface.comm.allreduce(np.bincount(dofs, weights=values, minlength=n))
    assert np.abs(total - g_dense).max() <= RTOL * np.abs(g_dense).max()


def test_hessian_coo_matches_dense():
    """``hessian_coo``: sorted distinct (row, col) entries, none in a Dirichlet row or column,
    adding up over the ranks to the dense sum."""
    _, _, surface, verts, grad, hess = _model()
    _, h_dense = _dense_sums(surface, verts, grad, hess)
    rows, cols, vals = assembly.hessian_coo(surface, verts, hess)
    n = 3 * surface.num_vertices
    key = rows * n + cols
    assert np.all(np.diff(key) > 0)
    bc_global = np.flatnonzero(surface.gathered()["bc"])
    assert bc_global.size > 0
    assert not np.any(np.isin(rows, bc_global) | np.isin(cols, bc_global))
    h = np.zeros((n, n))
    np.add.at(h, (rows, cols), vals)
    h = surface.comm.allreduce(h)
    assert np.abs(h - h_dense).max() <= RTOL * np.abs(h_dense).max()


def test_jacobian_blocks_inserted_into_the_pattern():
    """``create_matrix`` with the pairs' vertex couplings, then ``coupling_positions`` and
    ``add_jacobian_blocks``: the assembled matrix is the dense Hessian sum (Dirichlet rows
    and columns left alone), inserted without a malloc."""
    V, bcs, surface, verts, grad, hess = _model()
    comm = surface.comm
    nv = surface.num_vertices
    g = surface.global_vertex[verts]
    keys = np.unique((g[:, :, None] * nv + g[:, None, :]).ravel())
    a = dolfinx.fem.form(ufl.inner(ufl.TrialFunction(V), ufl.TestFunction(V)) * ufl.dx)
    dirichlet = assembly.global_dirichlet_dofs(comm, V, bcs)
    A = assembly.create_matrix(comm, a, keys, nv, dirichlet)
    held = assembly.held_keys(surface, keys)
    transposed = assembly.transposed_keys(surface, held)
    # the pattern holds every coupling's transpose (the pairs' couplings come both ways)
    assert np.all(transposed >= 0)
    nh = surface.num_held
    assert np.array_equal(held[transposed], (held % nh) * nh + held // nh)
    pos, missing = assembly.coupling_positions(surface, held, verts, transposed)
    assert missing == 0
    assert np.array_equal(held[pos], verts[:, :, None] * nh + verts[:, None, :])
    A.zeroEntries()
    assembly.add_jacobian_blocks(A, surface, held, pos, verts, hess)
    A.assemble()
    assert A.getInfo()["mallocs"] == 0
    _, h_dense = _dense_sums(surface, verts, grad, hess)
    dense = dense_matrix(A)
    assert np.abs(dense - h_dense).max() <= RTOL * np.abs(h_dense).max()
    A.destroy()


def test_couplings_outside_the_pattern_are_counted():
    """A pattern without the couplings of the first pair's first vertex (with the others):
    ``coupling_positions`` reports each such coupling (-1) and counts them."""
    _, _, surface, verts, _, _ = _model(10)
    nh = surface.num_held
    keys = np.unique((verts[:, :, None] * nh + verts[:, None, :]).ravel())
    v = verts[0, 0]
    drop = ((keys // nh == v) | (keys % nh == v)) & (keys // nh != keys % nh)
    pos, missing = assembly.coupling_positions(surface, keys[~drop], verts)
    outside = (verts[:, :, None] == v) ^ (verts[:, None, :] == v)
    assert missing == np.count_nonzero(outside) > 0
    assert np.array_equal(pos < 0, outside)


def _pattern(A) -> tuple[np.ndarray, np.ndarray]:
    """The owned rows' CSR pattern (row pointer, global columns) of ``A``."""
    indptr, cols, _ = A.getValuesCSR()
    return indptr.copy(), cols.copy()


def test_a_kept_bulk_pattern_builds_the_same_matrix():
    """``create_matrix`` from a :class:`~assembly.BulkPattern` made once and kept (as the
    operator keeps it for its rebuilds) gives the pattern it gives from the form, for other
    contact couplings too; ``BulkPattern.of`` keeps it for that form only."""
    V, bcs, surface, verts, _, _ = _model()
    comm, nv = surface.comm, surface.num_vertices
    g = surface.global_vertex[verts]
    a = dolfinx.fem.form(ufl.inner(ufl.TrialFunction(V), ufl.TestFunction(V)) * ufl.dx)
    dirichlet = assembly.global_dirichlet_dofs(comm, V, bcs)
    bulk = assembly.BulkPattern.of(a, nv, None)
    assert assembly.BulkPattern.of(a, nv, bulk) is bulk
    other = dolfinx.fem.form(ufl.inner(ufl.TrialFunction(V), ufl.TestFunction(V)) * ufl.dx)
    assert assembly.BulkPattern.of(other, nv, bulk).form is other
    # without contact couplings, the pattern is that of DOLFINx's assembled matrix
    reference = dolfinx.fem.petsc.assemble_matrix(a)
    reference.assemble()
    A = assembly.create_matrix(comm, bulk, np.empty(0, dtype=np.int64), nv)
    for p, q in zip(_pattern(A), _pattern(reference), strict=True):
        assert np.array_equal(p, q)
    A.destroy()
    reference.destroy()
    for rows in (g, g[: g.shape[0] // 2]):  # two sets of contact couplings
        keys = np.unique((rows[:, :, None] * nv + rows[:, None, :]).ravel())
        for marked in (None, dirichlet):
            A = assembly.create_matrix(comm, a, keys, nv, marked)
            B = assembly.create_matrix(comm, bulk, keys, nv, marked)
            assert all(np.array_equal(p, q) for p, q in zip(_pattern(A), _pattern(B), strict=True))
            assert A.getSizes() == B.getSizes() and A.getBlockSize() == B.getBlockSize()
            assert np.array_equal(A.getLGMap()[0].getIndices(), B.getLGMap()[0].getIndices())
            A.destroy()
            B.destroy()
