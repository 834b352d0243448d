"""Checkpoints of P1 fields (fenics_matdepth/checkpoint.py): the file holds each vertex's
values under its input index, and a checkpoint written on one partition reads back, bit for
bit, on another (all cells on rank 0, or the cells dealt out by hand)."""

from __future__ import annotations

from pathlib import Path

from mpi4py import MPI

import dolfinx
import numpy as np
import pytest

from fenics_matdepth._compat import create_tetrahedral_mesh
from fenics_matdepth.boundary import p1_dof_coordinates
from fenics_matdepth.checkpoint import FORMAT, Checkpoint
from fenics_matdepth.meshing import box_tetrahedra


def _field(X: np.ndarray) -> np.ndarray:
    """A vector field of the coordinates (n, 3), irrational values (all 52 bits used)."""
    return np.stack((np.sin(3.0 * X[:, 0]), X[:, 1] * np.exp(X[:, 2]), np.cos(X.sum(axis=1))), 1)


def _folder(tmp_path_factory, name: str) -> Path:
    """One folder for every rank (rank 0 writes the file, every rank reads it)."""
    comm = MPI.COMM_WORLD
    return Path(comm.bcast(str(tmp_path_factory.mktemp(name)) if comm.rank == 0 else None))


def _layouts(comm, cells, X):
    """The same mesh on three partitions: the partitioner's, all cells on rank 0, and cells
    dealt out to the ranks in turn."""
    ranks = np.arange(cells.shape[0]) % comm.size
    return {
        "partitioned": create_tetrahedral_mesh(comm, cells, X),
        "rank0": create_tetrahedral_mesh(comm, cells, X, all_cells_on_rank0=True),
        "dealt": create_tetrahedral_mesh(comm, cells, X, cell_ranks=ranks),
    }


def test_file_rows_are_input_vertices(tmp_path_factory):
    """The file's ``vertex`` is every input vertex once, sorted; its ``coordinates`` and field
    rows are those of the input vertices (an independent evaluation at the input
    coordinates, equal bit for bit); a scalar field has one column."""
    comm = MPI.COMM_WORLD
    folder = _folder(tmp_path_factory, "rows")
    X, cells = box_tetrahedra((3, 2, 2), (0.0, 0.0, 0.0), (1.5, 1.0, 1.0))
    mesh = create_tetrahedral_mesh(comm, cells, X)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    S = dolfinx.fem.functionspace(mesh, ("Lagrange", 1))
    u = dolfinx.fem.Function(V)
    u.x.array[:] = _field(p1_dof_coordinates(V)).ravel()
    s = dolfinx.fem.Function(S)
    s.x.array[:] = _field(p1_dof_coordinates(S))[:, 2]
    ckpt = Checkpoint(folder / "rows", V)
    assert not ckpt.exists()
    ckpt.save({"u": u.x.array}, step=3)
    Checkpoint(folder / "scalar", S).save({"s": s.x.array})
    assert ckpt.exists() and ckpt.path == folder / "rows.npz"
    if comm.rank == 0:
        with np.load(folder / "rows.npz") as f:
            assert str(f["format"]) == FORMAT
            assert np.array_equal(f["vertex"], np.arange(X.shape[0]))
            assert np.array_equal(f["coordinates"], X)
            assert np.array_equal(f["field/u"], _field(X))
        with np.load(folder / "scalar.npz") as f:
            assert np.array_equal(f["field/s"], _field(X)[:, 2:])
        # written through a temporary file, which is gone
        assert sorted(p.name for p in folder.iterdir()) == ["rows.npz", "scalar.npz"]
    comm.Barrier()


@pytest.mark.parametrize("writer", ["partitioned", "rank0", "dealt"])
def test_resume_on_another_partition(tmp_path_factory, writer):
    """Written on one partition, read on each of the three: every local value (ghosts
    included) is the field at that dof's vertex, bit for bit, and the scalars come back."""
    comm = MPI.COMM_WORLD
    folder = _folder(tmp_path_factory, f"resume_{writer}")
    X, cells = box_tetrahedra(3, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    meshes = _layouts(comm, cells, X)
    V = dolfinx.fem.functionspace(meshes[writer], ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    u.x.array[:] = _field(p1_dof_coordinates(V)).ravel()
    Checkpoint(folder / "state", V).save({"u": u.x.array, "v": 2.0 * u.x.array}, t=0.125)
    for mesh in meshes.values():
        W = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
        arrays, meta = Checkpoint(folder / "state", W).load()
        expected = _field(p1_dof_coordinates(W)).ravel()
        assert meta == {"t": 0.125}
        assert np.array_equal(arrays["u"], expected)
        assert np.array_equal(arrays["v"], 2.0 * expected)


def test_refuses_a_space_it_cannot_store(tmp_path_factory):
    """P2 fields are not vertex fields: refused when the checkpoint is made."""
    comm = MPI.COMM_WORLD
    X, cells = box_tetrahedra(1, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    mesh = create_tetrahedral_mesh(comm, cells, X)
    P2 = dolfinx.fem.functionspace(mesh, ("Lagrange", 2, (3,)))
    with pytest.raises(ValueError, match="P1 fields"):
        Checkpoint(_folder(tmp_path_factory, "p2") / "x", P2)
