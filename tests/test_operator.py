"""ContactOperator: residual and Jacobian against finite differences of its own energy, the
same answers on any partition, and a sparsity pattern that never mallocs."""

from __future__ import annotations

from mpi4py import MPI

import dolfinx
import dolfinx.fem.petsc
import numpy as np
import pytest
import ufl

import fenics_matdepth as fm
from fenics_matdepth._compat import create_tetrahedral_mesh
from fenics_matdepth.contact.operator import ContactOperator


def _box_tets(n: int, origin, size) -> tuple[np.ndarray, np.ndarray]:
    """Structured tetrahedral mesh of a box: each of n^3 cubes split into 6 (Kuhn) tets."""
    g = np.linspace(0.0, 1.0, n + 1)
    X = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    X = np.asarray(origin) + X * np.asarray(size)
    idx = np.arange((n + 1) ** 3).reshape(n + 1, n + 1, n + 1)
    kuhn = [(0, 1, 3, 7), (0, 1, 5, 7), (0, 2, 3, 7), (0, 2, 6, 7), (0, 4, 5, 7), (0, 4, 6, 7)]
    cells = []
    for i in range(n):
        for j in range(n):
            for k in range(n):
                c = [idx[i + a, j + b, k + d] for a in (0, 1) for b in (0, 1) for d in (0, 1)]
                cells += [[c[q] for q in t] for t in kuhn]
    return X, np.asarray(cells, dtype=np.int64)


def _two_boxes(comm: MPI.Comm, n: int = 3) -> dolfinx.mesh.Mesh:
    """Two unit boxes in one mesh, the upper one sunk 0.2 into the lower one and shifted."""
    xa, ca = _box_tets(n, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    xb, cb = _box_tets(n + 1, (0.23, 0.11, 0.8), (0.9, 0.8, 1.0))
    return create_tetrahedral_mesh(comm, np.vstack((ca, cb + xa.shape[0])), np.vstack((xa, xb)))


def _setup(comm, integration):
    mesh = _two_boxes(comm)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    x = V.tabulate_dof_coordinates()
    # A smooth, partition-independent perturbation, so that no pair sits on a degenerate case.
    u.x.array[:] = (0.02 * np.sin([3.1, 2.3, 1.7] * x + np.array([0.3, 0.1, 0.7]))).ravel()
    op = ContactOperator(u, fm.material_depth(mesh), penalty=50.0, integration=integration)
    return mesh, V, u, op


def _residual(op, V):
    """A PETSc vector holding dE/du (a copy: a Function's petsc_vec dies with the Function)."""
    w = dolfinx.fem.Function(V)
    b = w.x.petsc_vec
    b.zeroEntries()
    op.add_residual(b)
    return b.copy()


@pytest.mark.parametrize("integration", ["area", "collocation"])
def test_derivatives_match_finite_differences(integration):
    comm = MPI.COMM_WORLD
    _, V, u, op = _setup(comm, integration)
    assert op.energy() > 0.0
    x = V.tabulate_dof_coordinates()
    v = dolfinx.fem.Function(V)
    v.x.array[:] = np.cos(np.array([1.3, 2.9, 0.7]) * x[:, [1, 2, 0]] + 0.2).ravel()
    u0 = u.x.array.copy()

    def at(t):
        u.x.array[:] = u0 + t * v.x.array
        op.update()

    h = 1e-6
    at(h)
    e_plus, r_plus = op.energy(), _residual(op, V)
    at(-h)
    e_minus, r_minus = op.energy(), _residual(op, V)
    at(0.0)
    r0 = _residual(op, V)
    slope = r0.dot(v.x.petsc_vec)
    assert abs((e_plus - e_minus) / (2 * h) - slope) <= 1e-6 * abs(slope)

    a = dolfinx.fem.form(ufl.inner(ufl.TrialFunction(V), ufl.TestFunction(V)) * ufl.dx)
    A = op.create_matrix(a)
    A.zeroEntries()
    op.add_jacobian(A)
    assert A.getInfo()["mallocs"] == 0
    Hv = A.createVecLeft()
    A.mult(v.x.petsc_vec, Hv)
    fd = r_plus.copy()
    fd.axpy(-1.0, r_minus)
    fd.scale(1.0 / (2 * h))
    fd.axpy(-1.0, Hv)
    assert fd.norm() <= 1e-6 * Hv.norm()
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
    serial = _per_point(Vs, _residual(ops, Vs))
    merged: dict = {}
    for part in comm.allgather(_per_point(V, _residual(op, V))):
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
