"""Meshes for contact models: gmsh models to DOLFINx meshes, tetrahedral meshes from arrays.

The helpers the demos, the model builders (``meshes/``) and the benchmarks use, on every
supported DOLFINx (0.9, 0.10, 0.11): where DOLFINx's own functions differ between versions
(``dolfinx.io.gmshio`` became ``dolfinx.io.gmsh``; ``dolfinx.mesh.create_mesh`` swapped its
arguments; interpolation points became a property), these call the right one. Lengths are in
whatever unit the coordinates are given in; nothing here rescales them.

Example:
    A unit cube of 2 x 2 x 2 cubes, 48 tetrahedra, distributed over ``MPI.COMM_WORLD``::

        x, cells = fm.meshing.box_tetrahedra(2)
        mesh = fm.meshing.create_tetrahedral_mesh(MPI.COMM_WORLD, cells, x)
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from fenics_matdepth import _compat

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

    from mpi4py import MPI

    import dolfinx

__all__ = [
    "box_tetrahedra",
    "create_tetrahedral_mesh",
    "gmsh_build_to_mesh",
    "gmsh_model_to_mesh",
    "interpolation_points",
]

#: The six tetrahedra of a cube around its diagonal from corner 0 to corner 7 (Kuhn's
#: subdivision), corners numbered ``4 a + 2 b + c`` for the corner at ``(a, b, c)`` in {0, 1}^3.
#: Every cube is cut the same way, so neighbouring cubes' faces match (a conforming mesh).
_KUHN = np.array(
    [(0, 1, 3, 7), (0, 1, 5, 7), (0, 2, 3, 7), (0, 2, 6, 7), (0, 4, 5, 7), (0, 4, 6, 7)]
)


def gmsh_model_to_mesh(
    model, comm: MPI.Comm, rank: int = 0, gdim: int = 3
) -> tuple[dolfinx.mesh.Mesh, dolfinx.mesh.MeshTags, dolfinx.mesh.MeshTags]:
    """A DOLFINx mesh and its tags from a meshed gmsh model (collective).

    ``dolfinx.io.gmshio.model_to_mesh`` on DOLFINx 0.9 (a plain tuple),
    ``dolfinx.io.gmsh.model_to_mesh`` from 0.10 on (a named tuple with more fields); the
    result is the same three objects on every version.

    Args:
        model: ``gmsh.model``, holding a generated mesh with physical groups on ``rank``.
        comm: MPI communicator of the mesh.
        rank: the rank that holds the gmsh model.
        gdim: geometric dimension of the mesh.

    Returns:
        ``(mesh, cell_tags, facet_tags)``: the tags are the physical groups' numbers.
    """
    return _compat.gmsh_model_to_mesh(model, comm, rank, gdim=gdim)


def gmsh_build_to_mesh(
    build: Callable[[object], None], comm: MPI.Comm, gdim: int = 3
) -> tuple[dolfinx.mesh.Mesh, dolfinx.mesh.MeshTags, dolfinx.mesh.MeshTags]:
    """Build and mesh a gmsh model on rank 0, and distribute it over ``comm`` (collective).

    gmsh is initialised if it is not already (and finalised again afterwards), quiet and on
    one thread, so that every run gives the same mesh. ``build(gmsh.model)`` runs on rank 0
    only; the model is removed afterwards, also when ``build`` raises. Any DOLFINx 0.9 to 0.11
    (through :func:`gmsh_model_to_mesh`).

    Args:
        build: called with ``gmsh.model``: adds the geometry, the physical groups (cell and
            facet tags) and the mesh sizes, and generates the mesh.
        comm: MPI communicator of the mesh.
        gdim: geometric dimension of the mesh.

    Returns:
        ``(mesh, cell_tags, facet_tags)``.
    """
    return _compat.gmsh_build_to_mesh(build, comm, gdim=gdim)


def create_tetrahedral_mesh(
    comm: MPI.Comm,
    cells: np.ndarray,
    x: np.ndarray,
    degree: int = 1,
    all_cells_on_rank0: bool = False,
    cell_ranks: np.ndarray | None = None,
) -> dolfinx.mesh.Mesh:
    """A tetrahedral DOLFINx mesh from node coordinates and cells given on rank 0 (collective).

    The other ranks' arrays are ignored; DOLFINx's graph partitioner distributes the cells
    unless told otherwise. ``dolfinx.mesh.create_mesh`` takes ``(comm, cells, x, element)``
    on DOLFINx 0.9 and ``(comm, cells, element, x)`` from 0.10 on, and a custom partitioner
    returns the C++ adjacency list from 0.10 on; this works on 0.9 to 0.11.

    Args:
        comm: MPI communicator of the mesh.
        cells: ``(n, 4)`` vertex indices (degree 1) or ``(n, 10)`` node indices (degree 2, in
            DOLFINx's node order), into the rows of ``x``.
        x: ``(m, 3)`` node coordinates (any length unit).
        degree: degree of the coordinate element (1: straight-sided tetrahedra).
        all_cells_on_rank0: keep every cell on rank 0 (the other ranks get none).
        cell_ranks: ``(n,)`` the rank to own each cell, instead of the partitioner's choice.

    Returns:
        The distributed mesh (its cells and vertices renumbered by DOLFINx).
    """
    return _compat.create_tetrahedral_mesh(
        comm, cells, x, degree=degree, all_cells_on_rank0=all_cells_on_rank0,
        cell_ranks=cell_ranks,
    )  # fmt: skip


def interpolation_points(V: dolfinx.fem.FunctionSpace) -> np.ndarray:
    """The reference-cell interpolation points of a function space's element.

    For ``fem.Expression(expr, interpolation_points(V))``, to interpolate a UFL expression
    into ``V``. A method of ``V.element`` on DOLFINx 0.9, a property from 0.10 on.

    Args:
        V: the function space.

    Returns:
        ``(num_points, tdim)`` points of the reference cell.
    """
    return _compat.interpolation_points(V)


def box_tetrahedra(
    n: int | Sequence[int],
    origin: Sequence[float] = (0.0, 0.0, 0.0),
    size: Sequence[float] = (1.0, 1.0, 1.0),
) -> tuple[np.ndarray, np.ndarray]:
    """A structured, conforming mesh of a box by tetrahedra, as arrays (no DOLFINx needed).

    The box ``origin + [0, size_x] x [0, size_y] x [0, size_z]`` is cut into ``nx * ny * nz``
    equal cuboids, each into the same six tetrahedra around its diagonal from its lowest to
    its highest corner (Kuhn's subdivision), so every tetrahedron has the volume of its cuboid
    over six. Three of each cuboid's six tetrahedra have a negative signed volume in their
    vertex order (DOLFINx accepts either orientation and reorders the vertices itself).
    Vertex ``(i, j, k)`` of the grid is row ``(i * (ny + 1) + j) * (nz + 1) + k`` of ``x``.

    Pass the arrays to :func:`create_tetrahedral_mesh`; several boxes go in one mesh by
    stacking them (the second box's cells offset by the first box's number of vertices).

    Args:
        n: cuboids along each axis: one number for all three, or ``(nx, ny, nz)``.
        origin: the box's lowest corner (length unit L).
        size: the box's edge lengths along x, y, z (L).

    Returns:
        ``(x, cells)``: ``((nx + 1) (ny + 1) (nz + 1), 3)`` float64 vertex coordinates (L) and
        ``(6 nx ny nz, 4)`` int64 vertex indices into them.
    """
    nx, ny, nz = (n, n, n) if np.isscalar(n) else n
    g = [np.linspace(0.0, 1.0, m + 1) for m in (nx, ny, nz)]
    X = np.stack(np.meshgrid(*g, indexing="ij"), axis=-1).reshape(-1, 3)
    X = np.asarray(origin) + X * np.asarray(size)
    idx = np.arange(X.shape[0]).reshape(nx + 1, ny + 1, nz + 1)
    # the 8 corners of every cuboid, in the order (a, b, c) -> 4a + 2b + c
    corners = np.stack(
        [
            idx[a : nx + a, b : ny + b, c : nz + c].ravel()
            for a in (0, 1)
            for b in (0, 1)
            for c in (0, 1)
        ],
        axis=1,
    )
    return X, corners[:, _KUHN].reshape(-1, 4).astype(np.int64)
