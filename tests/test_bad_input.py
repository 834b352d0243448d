"""Bad input gets a clear error, on every rank, and leaves the state unchanged.

Each case checks the exception type and the part of its message that names the problem.
Under ``mpirun -n 2`` every rank must raise (``pytest.raises`` on each rank), and meshes are
built twice: partitioned as usual, and with every cell on rank 0 (rank 1 empty).
"""

from __future__ import annotations

import warnings

from mpi4py import MPI

import dolfinx
import numpy as np
import pytest
from conftest import neo_hookean_residual

import fenics_matdepth as fm
from fenics_matdepth._compat import create_tetrahedral_mesh
from fenics_matdepth.meshing import box_tetrahedra

COMM = MPI.COMM_WORLD
LAYOUTS = ["partitioned", "rank0"]


def _mesh(cells, x, layout: str = "partitioned", degree: int = 1) -> dolfinx.mesh.Mesh:
    return create_tetrahedral_mesh(
        COMM, cells, x, degree=degree, all_cells_on_rank0=(layout == "rank0")
    )


def _cube(layout: str = "partitioned", n: int = 2, origin=(0.0, 0.0, 0.0), size=1.0):
    X, cells = box_tetrahedra(n, origin, (size, size, size))
    return _mesh(cells, X, layout)


def _merged(*pieces):
    """Concatenate (X, cells) pieces, merging vertices with equal coordinates."""
    X = np.vstack([p[0] for p in pieces])
    offsets = np.cumsum([0] + [p[0].shape[0] for p in pieces])[:-1]
    cells = np.vstack([p[1] + o for p, o in zip(pieces, offsets, strict=True)])
    _, first, inverse = np.unique(np.round(X, 12), axis=0, return_index=True, return_inverse=True)
    return X[first], first.size and inverse.reshape(-1)[cells]


def _separate(*pieces):
    """Concatenate (X, cells) pieces without merging vertices (separate bodies)."""
    offsets = np.cumsum([0] + [p[0].shape[0] for p in pieces])[:-1]
    cells = np.vstack([p[1] + o for p, o in zip(pieces, offsets, strict=True)])
    return np.vstack([p[0] for p in pieces]), cells


def _vector_space(mesh):
    return dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))


def _contact(mesh, **kwargs):
    u = dolfinx.fem.Function(_vector_space(mesh))
    return fm.ContactOperator(u, fm.material_depth(mesh), penalty=10.0, **kwargs)


# -- meshes -------------------------------------------------------------------------------------


def test_hexahedral_mesh():
    mesh = dolfinx.mesh.create_unit_cube(COMM, 2, 2, 2, dolfinx.mesh.CellType.hexahedron)
    with pytest.raises(ValueError, match="needs a tetrahedral mesh, got hexahedron"):
        fm.material_depth(mesh)
    u = dolfinx.fem.Function(_vector_space(mesh))
    depth = dolfinx.fem.Function(dolfinx.fem.functionspace(mesh, ("Lagrange", 1)))
    with pytest.raises(ValueError, match="tetrahedral mesh"):
        fm.ContactOperator(u, depth, penalty=1.0)


def test_two_dimensional_mesh():
    mesh = dolfinx.mesh.create_unit_square(COMM, 2, 2)
    with pytest.raises(ValueError, match="needs a tetrahedral mesh, got triangle"):
        fm.material_depth(mesh)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_curved_p2_geometry(layout):
    # one P2 tetrahedron, DOLFINx node order: vertices, then edges (2,3) (1,3) (1,2) (0,3)
    # (0,2) (0,1); one edge midpoint pushed out (a curved edge)
    v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    edges = [(2, 3), (1, 3), (1, 2), (0, 3), (0, 2), (0, 1)]
    x = np.vstack([v] + [0.5 * (v[a] + v[b]) for a, b in edges])
    x[9] += [0.0, -0.1, 0.0]
    mesh = _mesh(np.arange(10)[None, :], x, layout, degree=2)
    with pytest.raises(ValueError, match="affine"):
        fm.material_depth(mesh)


@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_coordinates(layout, bad):
    X, cells = box_tetrahedra(2, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    X[13] = [0.5, bad, 0.5]  # the centre vertex
    mesh = _mesh(cells, X, layout)
    with pytest.raises(ValueError, match="non-finite vertex coordinates"):
        fm.material_depth(mesh)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_zero_volume_tetrahedron(layout):
    X, cells = box_tetrahedra(2, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    flat = np.array([[3.0, 0, 0], [4, 0, 0], [3, 1, 0], [4, 1, 0]])  # four coplanar points
    cells = np.vstack((cells, X.shape[0] + np.arange(4)[None, :]))
    mesh = _mesh(cells, np.vstack((X, flat)), layout)
    with pytest.raises(ValueError, match="zero volume"):
        fm.material_depth(mesh)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_duplicated_tetrahedron(layout):
    """A cell given twice: its faces are shared by three cells."""
    X, cells = box_tetrahedra(2, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    cells = np.vstack((cells, cells[7:8]))
    mesh = _mesh(cells, X, layout)
    with pytest.raises(ValueError, match="shared by more than two tetrahedra"):
        fm.material_depth(mesh)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_inverted_tetrahedra(layout):
    """The centre vertex of a 2 x 2 x 2 box moved out through the top: the tetrahedra around
    it fold over their neighbours (negative volume relative to the rest of the mesh)."""
    X, cells = box_tetrahedra(2, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    X[13] = [0.5, 0.5, 1.3]
    mesh = _mesh(cells, X, layout)
    with pytest.raises(ValueError, match="inverted, folded-over element"):
        fm.material_depth(mesh)


@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("shared", ["edge", "vertex"])
def test_non_manifold_boundary(layout, shared):
    """Two cubes that share only an edge, or only a vertex."""
    offset = (1.0, 1.0, 0.0) if shared == "edge" else (1.0, 1.0, 1.0)
    X, cells = _merged(
        box_tetrahedra(2, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)),
        box_tetrahedra(2, offset, (1.0, 1.0, 1.0)),
    )
    mesh = _mesh(cells, X, layout)
    with pytest.raises(ValueError, match="non-manifold"):
        fm.material_depth(mesh)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_single_tetrahedron(layout):
    """Every vertex lies on the boundary: depth zero everywhere, contact could not act."""
    x = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    mesh = _mesh(np.array([[0, 1, 2, 3]]), x, layout)
    depth = fm.material_depth(mesh)  # well defined: zero
    assert COMM.allreduce(np.abs(depth.x.array).max(initial=0.0), op=MPI.MAX) == 0.0
    u = dolfinx.fem.Function(_vector_space(mesh))
    with pytest.raises(ValueError, match="no vertex inside them"):
        fm.ContactOperator(u, depth, penalty=1.0, split_deficient=False)
    # By default the tetrahedron is split around its centroid, which has depth: accepted.
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        contact = fm.ContactOperator(u, depth, penalty=1.0)
    warned = any(issubclass(w.category, fm.contact.operator.DepthDeficiencyWarning) for w in caught)
    assert warned == (COMM.rank == 0)  # the warning is given once, on rank 0
    assert contact.num_split_tets == 1


@pytest.mark.parametrize("layout", LAYOUTS)
def test_bodies_overlapping_in_the_reference_configuration(layout):
    X, cells = _separate(
        box_tetrahedra(3, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)),
        box_tetrahedra(3, (0.3, 0.2, 0.8), (1, 1, 1)),
    )
    mesh = _mesh(cells, X, layout)
    with pytest.raises(ValueError, match="overlap in the reference configuration"):
        _contact(mesh)
    contact = _contact(mesh, allow_reference_overlap=True)  # on purpose
    assert contact.energy() > 0.0


@pytest.mark.parametrize("layout", LAYOUTS)
def test_coincident_unglued_surfaces_are_bodies_in_contact(layout):
    """Two boxes whose faces coincide without sharing vertices are two bodies touching: accepted,
    zero contact energy at rest, contact force as soon as one presses on the other."""
    X, cells = _separate(
        box_tetrahedra(2, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)),
        box_tetrahedra(3, (0.0, 0.0, 1.0), (1, 1, 1)),
    )
    mesh = _mesh(cells, X, layout)
    contact = _contact(mesh)
    assert contact.num_bodies == 2
    # Zero up to round-off: a face lying on a split tetrahedron's face has depth 0 in exact
    # arithmetic, about 1e-18 after the centroid's interpolation (the pressed state: ~1e-4).
    assert contact.energy() <= 1e-12
    upper = np.flatnonzero(contact.body_of_vertex == contact.body_of_vertex[-1])
    u = contact.u
    imap = u.function_space.dofmap.index_map
    glob = imap.local_to_global(np.arange(imap.size_local + imap.num_ghosts, dtype=np.int32))
    u.x.array.reshape(-1, 3)[np.isin(glob, upper), 2] = -0.01
    contact.update()
    assert contact.energy() > 0.0


# -- functions and parameters -------------------------------------------------------------------


@pytest.fixture(scope="module", params=LAYOUTS)
def cube(request):
    mesh = _cube(request.param, n=3)
    return mesh, fm.material_depth(mesh)


def test_u_on_wrong_spaces(cube):
    mesh, depth = cube
    for element in [("Lagrange", 2, (3,)), ("Lagrange", 1), ("Lagrange", 1, (2,))]:
        u = dolfinx.fem.Function(dolfinx.fem.functionspace(mesh, element))
        with pytest.raises(ValueError, match="P1 vector space of dimension 3"):
            fm.ContactOperator(u, depth, penalty=1.0)


def test_u_or_depth_on_another_mesh(cube):
    mesh, depth = cube
    other = _cube(n=3)
    u_other = dolfinx.fem.Function(_vector_space(other))
    with pytest.raises(ValueError, match="depth must be a P1 scalar Function on the mesh of u"):
        fm.ContactOperator(u_other, depth, penalty=1.0)
    u = dolfinx.fem.Function(_vector_space(mesh))
    with pytest.raises(ValueError, match="depth must be a P1 scalar Function on the mesh of u"):
        fm.ContactOperator(u, fm.material_depth(other), penalty=1.0)


@pytest.mark.parametrize("penalty", [0.0, -1.0, np.nan, np.inf])
def test_bad_penalty(cube, penalty):
    mesh, depth = cube
    u = dolfinx.fem.Function(_vector_space(mesh))
    with pytest.raises(ValueError, match="penalty must be a positive number"):
        fm.ContactOperator(u, depth, penalty=penalty)


def test_unknown_integration(cube):
    mesh, depth = cube
    u = dolfinx.fem.Function(_vector_space(mesh))
    with pytest.raises(ValueError, match="integration must be one of"):
        fm.ContactOperator(u, depth, penalty=1.0, integration="foo")


# -- problems and load stepping -----------------------------------------------------------------


def _problem(mesh, depth, bcs=None):
    V = _vector_space(mesh)
    u = dolfinx.fem.Function(V)
    F, _ = neo_hookean_residual(u)
    bottom = dolfinx.fem.locate_dofs_geometrical(V, lambda x: np.isclose(x[2], 0.0))
    top = dolfinx.fem.locate_dofs_geometrical(V, lambda x: np.isclose(x[2], 1.0))
    g = dolfinx.fem.Function(V)
    if bcs is None:
        bcs = [
            dolfinx.fem.dirichletbc(dolfinx.fem.Function(V), bottom),
            dolfinx.fem.dirichletbc(g, top),
        ]
    contact = fm.ContactOperator(u, depth, penalty=10.0)
    return u, F, bcs, contact, g


def test_bcs_on_another_space(cube):
    mesh, depth = cube
    W = dolfinx.fem.functionspace(mesh, ("Lagrange", 2, (3,)))
    dofs = dolfinx.fem.locate_dofs_geometrical(W, lambda x: np.isclose(x[2], 0.0))
    bc = dolfinx.fem.dirichletbc(dolfinx.fem.Function(W), dofs)
    u, F, _, contact, _ = _problem(mesh, depth)
    with pytest.raises(ValueError, match="different function space"):
        fm.ContactProblem(F, u, contact, bcs=[bc])
    with pytest.raises(ValueError, match="different function space"), warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        fm.NonlinearContactProblem(F, u, contact, bcs=[bc])


def _stepping(cube):
    mesh, depth = cube
    u, F, bcs, contact, g = _problem(mesh, depth)
    problem = fm.ContactProblem(F, u, contact, bcs=bcs, petsc_options_prefix="bad_input_")

    def set_load(t):
        g.x.array.reshape(-1, 3)[:, 2] = -0.05 * t

    return problem, set_load


def test_set_load_that_raises(cube):
    problem, set_load = _stepping(cube)
    fm.solve_load_steps(problem, set_load, num_steps=1, progress=False, end=0.5)
    before = problem.u.x.array.copy()

    def broken(t):
        if COMM.rank == COMM.size - 1:  # one rank only: the others must not hang
            raise KeyError("no such load case")
        set_load(t)

    with pytest.raises(RuntimeError, match=r"set_load\(.*\) raised KeyError.*no such load case"):
        fm.solve_load_steps(problem, broken, num_steps=1, progress=False, start=0.5)
    assert np.array_equal(problem.u.x.array, before)


def test_writer_that_cannot_write(cube, tmp_path):
    problem, set_load = _stepping(cube)

    def full_disk(t):
        if COMM.rank == 0:
            raise OSError(28, "No space left on device")

    with pytest.raises(RuntimeError, match=r"writer at load 0\.5 raised OSError.*No space left"):
        fm.solve_load_steps(problem, set_load, num_steps=1, end=0.5, writer=full_disk)
    with pytest.raises(RuntimeError, match="cannot write the checkpoint"):
        fm.solve_load_steps(
            problem, set_load, num_steps=1, end=0.5, checkpoint="/proc/no/such/dir/ckpt.npz"
        )
