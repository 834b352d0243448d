"""ContactOperator: residual and Jacobian against finite differences of its own energy, the
same answers on any partition, and a sparsity pattern that never mallocs."""

from __future__ import annotations

from mpi4py import MPI

import dolfinx
import dolfinx.fem.petsc
import numpy as np
import pytest
import ufl
from conftest import assert_operator_derivatives, merged_mesh, neo_hookean, operator_residual

import fenics_matdepth as fm
from fenics_matdepth._compat import create_tetrahedral_mesh
from fenics_matdepth.contact import assembly, evaluation
from fenics_matdepth.contact.operator import ContactOperator
from fenics_matdepth.meshing import box_tetrahedra


def _two_boxes(comm: MPI.Comm, n: int = 3) -> dolfinx.mesh.Mesh:
    """Two unit boxes in one mesh, the upper one sunk 0.2 into the lower one and shifted."""
    return merged_mesh(
        comm,
        box_tetrahedra(n, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)),
        box_tetrahedra(n + 1, (0.23, 0.11, 0.8), (0.9, 0.8, 1.0)),
    )


def _setup(comm, integration):
    mesh = _two_boxes(comm)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    x = V.tabulate_dof_coordinates()
    # A smooth, partition-independent perturbation, so that no pair sits on a degenerate case.
    u.x.array[:] = (0.02 * np.sin([3.1, 2.3, 1.7] * x + np.array([0.3, 0.1, 0.7]))).ravel()
    op = ContactOperator(
        u, fm.material_depth(mesh), penalty=50.0, integration=integration,
        allow_reference_overlap=True,  # the boxes overlap in the mesh on purpose
    )  # fmt: skip
    return mesh, V, u, op


@pytest.mark.parametrize("integration", ["area", "collocation"])
def test_derivatives_match_finite_differences(integration):
    comm = MPI.COMM_WORLD
    _, _, u, op = _setup(comm, integration)
    assert op.energy() > 0.0
    assert_operator_derivatives(op, u, h=1e-6, rtol=1e-6)


def _dense(comm, rows, cols, vals, n) -> np.ndarray:
    """The n x n matrix summed over the ranks' (rows, cols, vals) entries."""
    out = np.zeros((n, n))
    np.add.at(out, (rows, cols), vals)
    return comm.allreduce(out)


def _clamped_bottom_and_top(mesh, V) -> list:
    """Zero displacement on the lower box's bottom (z = 0) and the upper box's top (z = 1.8)."""
    bcs = []
    for z in (0.0, 1.8):
        facets = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x, z=z: np.isclose(x[2], z))
        dofs = dolfinx.fem.locate_dofs_topological(V, 2, facets)
        bcs.append(dolfinx.fem.dirichletbc(dolfinx.fem.Function(V), dofs))
    return bcs


@pytest.mark.parametrize("integration", ["area", "collocation"])
def test_jacobian_insertion_matches_sorted_coo(integration):
    """add_jacobian (pair Hessians summed by numba into the pattern's 3 x 3 blocks) puts into
    the matrix exactly the duplicate-summed entries of hessian_coo (an independent sort of
    all pair entries), with the Dirichlet rows and columns left out."""
    comm = MPI.COMM_WORLD
    mesh, V, _, op = _setup(comm, integration)
    bcs = _clamped_bottom_and_top(mesh, V)
    op.set_bcs(bcs)
    a = dolfinx.fem.form(ufl.inner(ufl.TrialFunction(V), ufl.TestFunction(V)) * ufl.dx)
    A = op.create_matrix(a)
    A.zeroEntries()
    op.add_jacobian(A)
    n = 3 * op.num_vertices
    indptr, indices, values = A.getValuesCSR()
    r0, r1 = A.getOwnershipRange()
    rows = np.repeat(np.arange(r0, r1), np.diff(indptr))
    inserted = _dense(comm, rows, indices, values, n)
    reference = _dense(comm, *op.hessian_coo(), n)
    scale = np.abs(reference).max()
    assert scale > 0.0
    assert np.abs(inserted - reference).max() <= 1e-13 * scale
    # the Dirichlet rows and columns stay empty, and there are some
    fixed = np.flatnonzero(op.surface.gathered()["bc"])  # the same on every rank
    assert len(fixed) > 0 and not inserted[fixed].any() and not inserted[:, fixed].any()
    A.destroy()


def test_pattern_is_the_assembled_bulk_pattern_and_the_contact_blocks():
    """create_matrix's pattern (the bulk part taken from DOLFINx's native CSR matrix, without
    assembling) is, entry for entry, the pattern of the bulk form assembled by
    dolfinx.fem.petsc joined with the 3 x 3 blocks of every rank's contact couplings."""
    comm = MPI.COMM_WORLD
    _, V, _, op = _setup(comm, "area")
    a = dolfinx.fem.form(
        ufl.inner(ufl.grad(ufl.TrialFunction(V)), ufl.grad(ufl.TestFunction(V))) * ufl.dx
    )
    A = op.create_matrix(a)
    A.assemble()
    indptr, indices, _ = A.getValuesCSR()
    r0, r1 = A.getOwnershipRange()
    n = 3 * op.num_vertices
    pattern = np.repeat(np.arange(r0, r1), np.diff(indptr)) * n + indices
    bulk = dolfinx.fem.petsc.assemble_matrix(a)
    bulk.assemble()
    b_indptr, b_indices, _ = bulk.getValuesCSR()
    expected = [np.repeat(np.arange(r0, r1), np.diff(b_indptr)) * n + b_indices]
    keys = np.concatenate(comm.allgather(op._pattern_keys))
    assert keys.size > 0
    vi, vj = keys // op.num_vertices, keys % op.num_vertices
    for r in range(3):
        for c in range(3):
            row, col = 3 * vi + r, 3 * vj + c
            mine = (row >= r0) & (row < r1)
            expected.append(row[mine] * n + col[mine])
    assert np.array_equal(np.sort(pattern), np.unique(np.concatenate(expected)))
    for mat in (A, bulk):
        mat.destroy()


def test_pattern_without_dirichlet_couplings():
    """create_matrix(a, bcs) leaves the Dirichlet rows and columns (whole vertices and single
    components) out of the pattern but for the diagonal; assembled with those conditions it
    holds the values of the full pattern's matrix, and MUMPS's LDL^T factors hold fewer
    entries."""
    from petsc4py import PETSc

    comm = MPI.COMM_WORLD
    mesh, V, u, op = _setup(comm, "area")
    roller = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[0], 0.0))
    bcs = _clamped_bottom_and_top(mesh, V) + [
        dolfinx.fem.dirichletbc(
            0.0, dolfinx.fem.locate_dofs_topological(V.sub(0), 2, roller), V.sub(0)
        )
    ]
    op.set_bcs(bcs)
    psi, _ = neo_hookean(u)
    a = dolfinx.fem.form(ufl.derivative(ufl.derivative(psi * ufl.dx, u), u))
    n = 3 * op.num_vertices
    matrices, dense, factor_entries = [], [], []
    for given in (None, bcs):
        A = op.create_matrix(a, given)
        dolfinx.fem.petsc.assemble_matrix(A, a, bcs)
        A.assemble()
        op.add_jacobian(A)
        assert A.getInfo()["mallocs"] == 0
        indptr, indices, values = A.getValuesCSR()
        r0, r1 = A.getOwnershipRange()
        rows = np.repeat(np.arange(r0, r1), np.diff(indptr))
        matrices.append((rows, indices, values))
        dense.append(_dense(comm, rows, indices, values, n))
        ksp = PETSc.KSP().create(comm)
        ksp.setType("preonly")
        pc = ksp.getPC()
        pc.setType("cholesky")
        pc.setFactorSolverType("mumps")
        A.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        ksp.setOperators(A)
        ksp.setUp()
        factor_entries.append(pc.getFactorMatrix().getMumpsInfog(29))
        del pc
        ksp.destroy()
        A.destroy()
    scale = np.abs(dense[0]).max()
    assert np.abs(dense[1] - dense[0]).max() <= 1e-14 * scale
    fixed = np.flatnonzero(op.surface.gathered()["bc"])  # the same on every rank
    free = np.setdiff1d(np.arange(n), fixed)
    whole = fixed[np.isin(fixed // 3 * 3, fixed) & np.isin(fixed // 3 * 3 + 1, fixed)]
    assert fixed.size > whole.size > 0  # whole vertices and single components
    stored = []
    for rows, cols, _ in matrices:
        mask = np.zeros((n, n), dtype=bool)
        mask[rows, cols] = True
        stored.append(comm.allreduce(mask.astype(np.int8)) > 0)
    full, lean = stored
    # the full pattern stores zeros off the diagonal of the Dirichlet rows; the lean one none
    off = ~np.eye(n, dtype=bool)
    assert (full[fixed] & off[fixed]).any() and not (lean[fixed] & off[fixed]).any()
    assert not (lean[:, fixed] & off[:, fixed]).any()
    assert lean[fixed, fixed].all()
    # the rest of the pattern is kept
    assert (lean[np.ix_(free, free)] == full[np.ix_(free, free)]).all()
    assert factor_entries[1] < factor_entries[0]


def test_summed_passes_match_per_pair_arrays():
    """The residual and Jacobian passes that sum each chunk of pair gradients and Hessians as
    the kernel makes them (`_summed`) give the energies, the summed gradient and the pattern's
    3 x 3 blocks of the per-pair arrays (`_evaluate`) summed afterwards, Dirichlet rows and
    columns left out; over many chunks, with split tetrahedra among the pairs."""
    from fenics_matdepth.contact.assembly import _accumulate_vertex_blocks
    from fenics_matdepth.contact.kernels.drivers import _SUM_CHUNK

    comm = MPI.COMM_WORLD
    mesh, V, _, op = _setup(comm, "area")
    bottom = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[2], 0.0))
    dofs = dolfinx.fem.locate_dofs_topological(V, 2, bottom)
    op.set_bcs([dolfinx.fem.dirichletbc(dolfinx.fem.Function(V), dofs)])
    a = dolfinx.fem.form(ufl.inner(ufl.TrialFunction(V), ufl.TestFunction(V)) * ufl.dx)
    A = op.create_matrix(a)
    s = op.surface
    n_pairs = op._intersecting_pairs().size
    split = s.kernel_tets[op.pair_search.pair_k[op._intersecting_pairs()], 4] >= 0
    assert comm.allreduce(n_pairs) > 4 * _SUM_CHUNK * comm.size
    assert comm.allreduce(int(np.count_nonzero(split))) > 0
    assert comm.allreduce(int(np.count_nonzero(s.bc))) > 0

    per_pair = op._evaluate(False, True)
    keys = op._pattern_in_held_numbering()
    blocks = np.zeros((keys.size, 3, 3))
    touched = np.zeros(keys.size, dtype=bool)
    pos = op._coupling_positions()
    _accumulate_vertex_blocks(pos, per_pair["verts"], per_pair["hess"], s.bc, blocks, touched)
    dofs_ref, grad_ref = assembly.gradient_array(s, per_pair["verts"], per_pair["grad"])
    scale_h = comm.allreduce(np.abs(blocks).max(initial=0.0), op=MPI.MAX)
    scale_g = comm.allreduce(np.abs(grad_ref).max(initial=0.0), op=MPI.MAX)
    assert scale_h > 0.0 and scale_g > 0.0

    for want_hess in (False, True):
        op._cache.pop("summed_grad", None)
        op._cache.pop("summed_hess", None)
        summed = op._summed(want_hess)
        assert np.allclose(summed["energy"], per_pair["energy"], rtol=1e-12, atol=0.0)
        dofs, grad = assembly.gradient_from_sums(s, summed["grad_sum"], summed["reached"])
        assert np.array_equal(dofs, dofs_ref)
        assert np.abs(grad - grad_ref).max(initial=0.0) <= 1e-12 * scale_g
        if want_hess:
            assert np.array_equal(summed["touched"], touched)
            assert np.abs(summed["blocks"] - blocks).max(initial=0.0) <= 1e-12 * scale_h
    A.destroy()


def test_coupling_positions_of_grouped_pairs_in_an_asymmetric_pattern():
    """The pattern positions (searched for the couplings (a, b) with a <= b only, (b, a) from
    the transpose's index, a triangle's own couplings copied from the pair before when it is
    the same triangle) equal a search of the whole pattern for every coupling, and the count
    of those missing is theirs; on a pattern lacking some couplings, some of them without
    their transpose, and a triangle that comes back after another."""
    from fenics_matdepth.contact.assembly import _coupling_positions, _key_rows, _transposed_keys

    rng = np.random.default_rng(5)
    nv = 30
    tri = np.array([rng.choice(nv, 3, replace=False) for _ in range(5)])
    tet = np.array([rng.choice(nv, 4, replace=False) for _ in range(12)])
    pair_tri = np.array([0, 0, 0, 1, 1, 2, 0, 0, 3, 4, 4, 4])
    verts = np.hstack((tri[pair_tri], tet[rng.integers(0, 12, size=pair_tri.size)]))
    every = np.unique((verts[:, :, None] * nv + verts[:, None, :]).ravel())
    keys = np.sort(rng.choice(every, size=int(0.8 * every.size), replace=False))
    rows = _key_rows(keys, nv)
    transposed = _transposed_keys(keys, rows, nv)
    swapped = (keys % nv) * nv + keys // nv
    at = np.minimum(np.searchsorted(keys, swapped), keys.size - 1)
    np.testing.assert_array_equal(transposed, np.where(keys[at] == swapped, at, -1))
    assert np.count_nonzero(transposed < 0) > 0

    pos = np.empty((verts.shape[0], 7, 7), dtype=np.int64)
    missing = _coupling_positions(keys, rows, nv, verts, transposed, pos)
    wanted = verts[:, :, None] * nv + verts[:, None, :]
    at = np.minimum(np.searchsorted(keys, wanted), keys.size - 1)
    found = keys[at] == wanted
    np.testing.assert_array_equal(pos, np.where(found, at, -1))
    assert missing == np.count_nonzero(~found) > 0


@pytest.mark.parametrize("share", [None, 1.0])
def test_candidate_pairs_serve_later_updates_within_the_skin(share, monkeypatch):
    """The candidate pairs of a search with the skin serve the updates after it until a held
    vertex has moved by about half the skin, and are then searched again round the moved
    vertices only: at every state of a slide in steps of 0.05 to 1.2 skins, those whose boxes
    overlap now are the pairs of a fresh search without skin, and the intersecting pairs are
    that search's in its order, while fewer searches were made than updates. The upper box
    holds half the surface, more than a search in part takes: with ``PARTIAL_SEARCH_SHARE``
    raised to 1 the updates past the skin search round it only."""
    from fenics_matdepth.contact import pairs
    from fenics_matdepth.contact.kernels.drivers import intersecting
    from fenics_matdepth.geometry.boxes import overlapping_pairs

    comm = MPI.COMM_WORLD
    if share is not None:
        monkeypatch.setattr(pairs, "PARTIAL_SEARCH_SHARE", share)
    _, V, u, op = _setup(comm, "area")
    skin = op.pair_skin
    assert skin > 0.0
    s = op.surface
    upper = op.body_of_vertex[np.argmax(s.gathered()["X"][:, 2])]
    n_owned = V.dofmap.index_map.size_local
    glob = V.dofmap.index_map.local_to_global(np.arange(n_owned, dtype=np.int32))
    on_upper = op.body_of_vertex[glob] == upper
    # scatter the vertices (partition-independent), so that box gaps take every size and not
    # only the mesh's multiples of its spacing
    gdof = (3 * glob[:, None] + np.arange(3)).ravel()
    u.x.array[: 3 * n_owned] += 0.2 * s.mean_edge * np.sin(12.9898 * gdof + 78.233)
    u.x.scatter_forward()
    steps = [0.2, 0.3, 0.1, 0.5, 1.2, 0.05, 0.4, 0.45, 0.9, 0.3, 0.25, 0.7]
    for step in steps:
        ux = u.x.array[: 3 * n_owned].reshape(-1, 3)
        ux[on_upper, 0] += step * skin
        ux[on_upper, 1] -= 0.5 * step * skin
        u.x.scatter_forward()
        op.update()
        fa, fk = pairs.candidate_pairs(s, "area", 0.0)
        pa, pk = op.pair_search.pair_a, op.pair_search.pair_k
        near = overlapping_pairs(s.x, s.tri, s.tets, pa, pk)
        kept = zip(pa[near].tolist(), pk[near].tolist(), strict=True)
        assert set(kept) == set(zip(fa.tolist(), fk.tolist(), strict=True))
        hit = intersecting(s.x, s.tri, s.kernel_tets, fa, fk)
        active = op._intersecting_pairs()
        np.testing.assert_array_equal(pa[active], fa[hit])
        np.testing.assert_array_equal(pk[active], fk[hit])
        assert comm.allreduce(active.size) > 0
    searches = comm.allreduce(op.pair_searches)
    partial = comm.allreduce(op.pair_search.partial_searches)
    if share is None:
        assert partial == 0 and comm.size < searches < comm.size * (len(steps) + 1)
    else:
        assert searches < partial and searches + partial < comm.size * (len(steps) + 1)
    # a new skin is searched with at once, however little the vertices moved
    op.pair_skin = 3.0 * skin
    u.x.array[: 3 * n_owned].reshape(-1, 3)[on_upper, 0] += 0.01 * skin
    u.x.scatter_forward()
    op.update()
    assert comm.allreduce(op.pair_searches) == searches + comm.size


def test_couplings_outside_the_pattern():
    """The pattern positions of the pairs' couplings (a search within each vertex's row) equal
    a search of the whole pattern; after the upper box slides further than the pattern's
    margin, pattern_needs_rebuild says so on every rank and add_jacobian refuses until
    create_matrix is called again."""
    comm = MPI.COMM_WORLD
    _, V, u, op = _setup(comm, "area")
    a = dolfinx.fem.form(ufl.inner(ufl.TrialFunction(V), ufl.TestFunction(V)) * ufl.dx)
    A = op.create_matrix(a)
    assert not op.pattern_needs_rebuild()

    def positions_agree() -> int:
        verts = op._evaluate(False, False)["verts"]
        keys = op._pattern_in_held_numbering()
        pos, missing = assembly.coupling_positions(op.surface, keys, verts)
        nh = op.surface.num_held
        wanted = verts[:, :, None] * nh + verts[:, None, :]
        at = np.minimum(np.searchsorted(keys, wanted), max(keys.size - 1, 0))
        found = keys[at] == wanted
        assert np.array_equal(pos, np.where(found, at, -1))
        assert missing == np.count_nonzero(~found)
        return missing

    assert comm.allreduce(positions_agree()) == 0
    upper = op.body_of_vertex[np.argmax(op.surface.gathered()["X"][:, 2])]
    n_owned = V.dofmap.index_map.size_local
    glob = V.dofmap.index_map.local_to_global(np.arange(n_owned, dtype=np.int32))
    ux = u.x.array[: 3 * n_owned].reshape(-1, 3)[:, 0]
    ux[op.body_of_vertex[glob] == upper] -= 0.4  # 1.2 elements of the lower box
    u.x.scatter_forward()
    op.update()
    assert comm.allreduce(positions_agree()) > 0
    assert op.pattern_needs_rebuild()
    A.zeroEntries()
    with pytest.raises(RuntimeError, match="outside the matrix sparsity pattern"):
        op.add_jacobian(A)
    A.destroy()
    A = op.create_matrix(a)
    assert not op.pattern_needs_rebuild()
    A.zeroEntries()
    op.add_jacobian(A)
    assert A.getInfo()["mallocs"] == 0
    A.destroy()


def _per_point(V, r) -> dict:
    """Residual summed per reference point over this rank's owned dofs.

    Coincident vertices of the two bodies share a point, so sums per point are compared.
    """
    n = V.dofmap.index_map.size_local
    out: dict = {}
    for i, p in enumerate(np.round(V.tabulate_dof_coordinates()[:n], 12)):
        out[tuple(p)] = out.get(tuple(p), 0.0) + r.array[3 * i : 3 * i + 3]
    return out


@pytest.mark.parametrize("integration", ["area", "collocation"])
def test_same_answer_on_one_process(integration):
    """The distributed operator equals one built on COMM_SELF from the same mesh."""
    comm = MPI.COMM_WORLD
    _, V, _, op = _setup(comm, integration)
    _, Vs, _, ops = _setup(MPI.COMM_SELF, integration)
    assert np.isclose(op.energy(), ops.energy(), rtol=1e-12, atol=0.0)
    serial = _per_point(Vs, operator_residual(ops, Vs))
    merged: dict = {}
    for part in comm.allgather(_per_point(V, operator_residual(op, V))):
        for p, val in part.items():
            merged[p] = merged.get(p, 0.0) + val
    assert merged.keys() == serial.keys()
    scale = max(np.abs(v).max() for v in serial.values())
    assert max(np.abs(merged[p] - serial[p]).max() for p in serial) <= 1e-12 * scale


def test_bad_input_is_named():
    comm = MPI.COMM_WORLD
    mesh = _two_boxes(comm, 2)
    d = fm.material_depth(mesh)
    V2 = dolfinx.fem.functionspace(mesh, ("Lagrange", 2, (3,)))
    with pytest.raises(ValueError, match="P1 vector space"):
        ContactOperator(dolfinx.fem.Function(V2), d, penalty=1.0)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    with pytest.raises(ValueError, match="penalty"):
        ContactOperator(dolfinx.fem.Function(V), d, penalty=-1.0)
    with pytest.raises(ValueError, match="integration"):
        ContactOperator(dolfinx.fem.Function(V), d, penalty=1.0, integration="nodes")


@pytest.mark.parametrize("integration", ["area", "collocation"])
def test_max_penetration_of_sunk_block(integration):
    """A box resting on a larger one is moved 0.2 down into it. The lower box's depth is at
    most the (affine) distance to its top face, and equals it under the middle of that face,
    which the upper box covers; the upper box's depth is at most the distance to its bottom
    face. So the deepest point reached is exactly 0.2 (also for the collocation nodes: the
    upper box has a bottom vertex above the middle)."""
    mesh = merged_mesh(
        MPI.COMM_WORLD,
        box_tetrahedra(3, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)),
        box_tetrahedra(4, (0.23, 0.11, 1.0), (0.9, 0.8, 1.0)),
    )
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    depth = fm.material_depth(mesh)
    op = ContactOperator(u, depth, penalty=1.0, integration=integration)
    upper = op.body_of_vertex[np.argmax(op.surface.gathered()["X"][:, 2])]
    n_owned = V.dofmap.index_map.size_local
    glob = V.dofmap.index_map.local_to_global(np.arange(n_owned, dtype=np.int32))
    uz = u.x.array[: 3 * n_owned].reshape(-1, 3)[:, 2]
    # the plane z = 1 holds vertices of both boxes: select the upper box's by body
    uz[:] = np.where(op.body_of_vertex[glob] == upper, -0.2, 0.0)
    u.x.scatter_forward()
    op.update()
    # the clip shift moves each triangle by CLIP_SHIFT sqrt(2 A) (the lower box's top triangles
    # by 3.3e-10 up, into the upper box)
    assert np.isclose(op.max_penetration(), 0.2, rtol=1e-8, atol=0.0)
    # where: a surface of one box in a tetrahedron of the other, both on the plane z = 1 of
    # the reference configuration, the same answer on every rank
    deepest = op.deepest_contact()
    assert MPI.COMM_WORLD.allgather(deepest) == [deepest] * MPI.COMM_WORLD.size
    assert deepest["depth"] == op.max_penetration()
    X = op.surface.gathered()["X"]
    surface = np.asarray(deepest["surface_vertices"])
    tet = np.asarray(deepest["tetrahedron_vertices"])
    assert surface.size == (3 if integration == "area" else 1) and tet.size == 4
    assert np.allclose(X[surface, 2], 1.0)
    assert np.allclose(X[surface].mean(axis=0), deepest["surface_reference"])
    assert np.allclose(X[tet].mean(axis=0), deepest["tetrahedron_reference"])
    bodies = op.body_of_vertex
    assert len(set(bodies[surface])) == 1 and set(bodies[tet]) != set(bodies[surface])
    moved = np.where(bodies[surface] == upper, -0.2, 0.0)
    assert np.allclose(deepest["surface_position"][2], (X[surface, 2] + moved).mean())
    if integration == "area":
        edges = X[surface[[1, 2, 0]]] - X[surface]
        assert deepest["local_h"] == pytest.approx(np.linalg.norm(edges, axis=1).mean())
        # the peak contact pressure k g round each vertex: eps 0.2 at most, 0 away from the
        # contact (the boxes' bottoms); with pressures c and width w, k = eps + c / w
        peak = op.peak_pressure()
        assert MPI.COMM_WORLD.allgather(peak.tobytes()) == [peak.tobytes()] * MPI.COMM_WORLD.size
        assert peak.max() == pytest.approx(0.2, rel=1e-8)
        assert np.all(peak[X[:, 2] < 0.5] == 0.0) and np.all(peak >= 0.0)
        op.set_pressure(np.full(op.num_vertices, 3.0), width=0.5)
        assert op.peak_pressure().max() == pytest.approx((1.0 + 3.0 / 0.5) * 0.2, rel=1e-8)
        assert np.allclose(op.peak_pressure(), 7.0 * peak)
        op.set_pressure(None)
    # nothing penetrates: None
    u.x.array[:] = 0.0
    u.x.scatter_forward()
    u.x.array[: 3 * n_owned].reshape(-1, 3)[:, 2] = np.where(
        op.body_of_vertex[glob] == upper, 0.5, 0.0
    )
    u.x.scatter_forward()
    op.update()
    assert op.max_penetration() == 0.0 and op.deepest_contact() is None


def _depth_at_points_brute_force(mesh, gathered, points, own):
    """Reference for `ContactOperator.vertex_penetration`, independent of its tree and kernel:
    the P1 material depth at each point, from a 4 x 4 barycentric solve against every
    tetrahedron not holding the point's own vertex ``own`` (global numbers), the depth-deficient
    ones (four vertices at depth 0) split around their centroid as the operator does, the
    centroid at its exact reference distance to the boundary."""
    from fenics_matdepth.depth import boundary_triangles, distance_to_triangles

    X, x, depth, tets = (gathered[k] for k in ("X", "x", "depth", "tets"))
    centroid_depth = distance_to_triangles(X[tets].mean(axis=1), boundary_triangles(mesh))
    deficient = np.all(depth[tets] == 0.0, axis=1)
    out = np.zeros(points.shape[0])
    for i, (y, a) in enumerate(zip(points, own, strict=True)):
        for k in np.flatnonzero(np.all(tets != a, axis=1)):
            xt, dt = x[tets[k]], depth[tets[k]]
            subs = [(xt, dt)]
            if deficient[k]:
                subs = []
                for s in range(4):
                    xs, ds = xt.copy(), dt.copy()
                    xs[s], ds[s] = xt.mean(axis=0), centroid_depth[k]
                    subs.append((xs, ds))
            for xs, ds in subs:
                lam = np.linalg.solve(np.vstack((xs.T, np.ones(4))), np.append(y, 1.0))
                if lam.min() >= -1e-12:
                    out[i] = max(out[i], float(lam @ ds))
    return out


@pytest.mark.parametrize("integration", ["area", "collocation"])
def test_vertex_penetration(integration):
    """The depth each boundary vertex reaches: by hand for a box sunk 0.2 into another, and
    against a brute-force barycentric search (`_depth_at_points_brute_force`) for two boxes
    that overlap with a smooth perturbation, the same on every rank."""
    comm = MPI.COMM_WORLD
    # the sunk box of test_max_penetration_of_sunk_block: the upper box's bottom vertex at
    # (0.455, 0.51) lies, 0.2 down, in the lower box's cube column [1/3, 2/3]^2, whose top
    # layer has depth 0 above and 1/3 below (the distance of (1/3 or 2/3, 1/3 or 2/3, 2/3) to
    # the unit cube's faces): there the P1 depth is 1 - z, 0.2 exactly
    mesh = merged_mesh(
        comm,
        box_tetrahedra(3, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)),
        box_tetrahedra(4, (0.23, 0.11, 1.0), (0.9, 0.8, 1.0)),
    )
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    op = ContactOperator(u, fm.material_depth(mesh), penalty=1.0, integration=integration)
    X = op.surface.gathered()["X"]
    upper = op.body_of_vertex[np.argmax(X[:, 2])]
    n_owned = V.dofmap.index_map.size_local
    glob = V.dofmap.index_map.local_to_global(np.arange(n_owned, dtype=np.int32))
    u.x.array[: 3 * n_owned].reshape(-1, 3)[:, 2] = np.where(
        op.body_of_vertex[glob] == upper, -0.2, 0.0
    )
    u.x.scatter_forward()
    op.update()
    g = op.vertex_penetration()
    assert g.shape == (op.num_vertices,)
    assert comm.allgather(g.tobytes()) == [g.tobytes()] * comm.size
    vertex = np.flatnonzero(np.all(np.isclose(X, [0.455, 0.51, 1.0]), axis=1))
    vertex = vertex[op.body_of_vertex[vertex] == upper]
    assert vertex.size == 1 and g[vertex[0]] == pytest.approx(0.2, rel=1e-12)
    # the deepest vertex is no deeper than the deepest polygon point; vertices above the
    # common plane, and the lower box's below it, are in no tetrahedron of the other box
    assert g.max() <= op.max_penetration() * (1 + 1e-12)
    assert np.all(g[X[:, 2] > 1.0 + 1e-9] == 0.0) and np.all(g[X[:, 2] < 1.0 - 1e-9] == 0.0)

    # general positions, deficient tetrahedra split (both boxes are 3 and 4 cells across)
    mesh, V, u, op = _setup(comm, integration)
    gathered = op.surface.gathered()
    g = op.vertex_penetration()
    boundary = np.flatnonzero(gathered["depth"] == 0.0)
    expected = np.zeros(op.num_vertices)
    expected[boundary] = _depth_at_points_brute_force(
        mesh, gathered, gathered["x"][boundary], boundary
    )
    assert np.count_nonzero(expected > 0.0) >= 10
    assert np.allclose(g, expected, rtol=0.0, atol=1e-12)


def test_force_resultants_are_opposite_and_match_rigid_translation():
    """Net contact force on each body: the two bodies' are opposite (action = reaction), and
    the upper body's equals -dE/dt for a rigid translation t of that body (central differences
    of the energy, an independent computation)."""
    comm = MPI.COMM_WORLD
    _, V, u, op = _setup(comm, "area")
    res = op.force_resultants()
    assert res.shape == (2, 3) and op.num_bodies == 2
    assert np.abs(res[0] + res[1]).max() <= 1e-12 * np.abs(res).max()
    # the body holding the vertex with the largest reference z is the upper one
    n_owned = V.dofmap.index_map.size_local
    glob = V.dofmap.index_map.local_to_global(np.arange(n_owned, dtype=np.int32))
    body = op.body_of_vertex[glob]
    upper = op.body_of_vertex[np.argmax(op.surface.gathered()["X"][:, 2])]
    assert res[upper, 2] > 0.0  # pushed up, out of the lower body
    u0 = u.x.array.copy()
    h = 1e-6
    for c in range(3):
        energies = []
        for t in (h, -h):
            u.x.array[:] = u0
            u.x.array[: 3 * n_owned].reshape(-1, 3)[body == upper, c] += t
            u.x.scatter_forward()
            op.update()
            energies.append(op.energy())
        fd = -(energies[0] - energies[1]) / (2 * h)
        assert abs(fd - res[upper, c]) <= 1e-6 * np.abs(res).max(), (c, fd, res[upper, c])


def test_diagnostics_and_unchanged_state():
    comm = MPI.COMM_WORLD
    _, _, u, op = _setup(comm, "area")
    d = op.diagnostics()
    assert d["active_pairs"] > 0 and d["candidate_pairs"] >= d["active_pairs"]
    assert d["energy"] == op.energy() and d["max_penetration"] == op.max_penetration()
    assert np.array_equal(d["force_resultant"], op.force_resultants())
    # an update at the same u keeps the evaluated pairs; a changed u recomputes them
    cached = op._evaluate(True, True)
    op.update()
    assert op._evaluate(False, False) is cached
    u.x.array[:] *= 1.01
    op.update()
    assert op._evaluate(False, False) is not cached


def test_an_augmented_energy_pass_serves_the_residual_after_it():
    """With the augmented Lagrangian's pressures the energy is the kernel's energy-only pass to
    the bit, though its pass computes the gradient too, and the residual at the same state
    takes that pass: no second kernel pass (a line search's accepted state)."""
    comm = MPI.COMM_WORLD
    _, V, _, op = _setup(comm, "area")
    op.set_pressure(np.full(op.num_vertices, 0.3))
    alone = evaluation.pair_arrays(
        op.surface, "area", *op._evaluated_pairs(), op.penalty, op.pressure, 0.0, False, False
    )[0]
    energy = op.energy()
    assert energy == comm.allreduce(float(np.sum(alone))) and energy > 0.0
    passes = op._cache["TrueFalse"]
    b = operator_residual(op, V)
    assert op._cache["TrueFalse"] is passes and b.norm() > 0.0
    b.destroy()


@pytest.mark.parametrize("integration", ["area", "collocation"])
def test_pair_energies_name_a_cell_and_sum_to_the_energy(integration):
    comm = MPI.COMM_WORLD
    mesh, V, _, op = _setup(comm, integration)
    verts, energy = op.pair_energies()
    assert verts.shape == (energy.size, 7 if integration == "area" else 5)
    # the fused pass of energy() (plain penalty, area) and the per-pair arrays agree
    assert comm.allreduce(float(np.sum(energy))) == pytest.approx(op.energy(), rel=1e-12)
    assert comm.allreduce(int(np.count_nonzero(energy > 0.0))) > 0
    # each pair's last four vertices, in the global numbering of u, are a tetrahedron's
    imap = V.dofmap.index_map
    n_cells = mesh.topology.index_map(3).size_local
    cells = imap.local_to_global(V.dofmap.list[:n_cells].ravel()).reshape(-1, 4)
    known = {tuple(c) for part in comm.allgather(np.sort(cells, axis=1).tolist()) for c in part}
    assert all(tuple(t) in known for t in np.sort(verts[:, -4:], axis=1).tolist())


def test_propose_penalty():
    """eps = factor * modulus / h, h the median boundary edge: for a Kuhn-split box of n = 3
    cells per side every boundary triangle has two axis edges (1/3) and one diagonal."""
    mesh = create_tetrahedral_mesh(MPI.COMM_WORLD, *box_tetrahedra(3, (0, 0, 0), (1, 1, 1))[::-1])
    assert np.isclose(fm.propose_penalty(mesh, 2.0, factor=10.0), 10.0 * 2.0 * 3.0, rtol=1e-12)
    assert fm.propose_penalty(mesh, 2.0, factor=10.0, h=0.5) == 40.0
    with pytest.raises(ValueError, match="positive"):
        fm.propose_penalty(mesh, -1.0)
