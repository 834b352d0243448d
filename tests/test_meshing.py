"""fenics_matdepth.meshing: structured boxes of tetrahedra, meshes from arrays and from gmsh.

Checked against what a box is (vertex and cell counts, volumes and surface that add up to the
box's, every point inside in exactly one tetrahedron, faces shared by at most two cells) and
against integrals DOLFINx computes on the meshes made from it.
"""

from __future__ import annotations

import itertools

from mpi4py import MPI

import dolfinx
import numpy as np
import pytest
import ufl

import fenics_matdepth as fm
from fenics_matdepth.meshing import (
    box_tetrahedra,
    create_tetrahedral_mesh,
    gmsh_build_to_mesh,
    gmsh_model_to_mesh,
    interpolation_points,
)

ORIGIN, SIZE, N = (0.5, -1.0, 2.0), (2.0, 1.5, 0.75), (2, 3, 4)


def _signed_volumes(x: np.ndarray, cells: np.ndarray) -> np.ndarray:
    p = x[cells]
    return np.linalg.det(p[:, 1:] - p[:, :1]) / 6.0


def _volume(mesh, integrand=1.0) -> float:
    form = dolfinx.fem.form(dolfinx.fem.Constant(mesh, integrand) * ufl.dx(domain=mesh))
    return mesh.comm.allreduce(dolfinx.fem.assemble_scalar(form), op=MPI.SUM)


def test_box_tetrahedra_counts_and_grid():
    """(nx+1)(ny+1)(nz+1) vertices on the grid, in the documented order; 6 nx ny nz cells."""
    x, cells = box_tetrahedra(N, ORIGIN, SIZE)
    nx, ny, nz = N
    assert x.shape == ((nx + 1) * (ny + 1) * (nz + 1), 3) and x.dtype == np.float64
    assert cells.shape == (6 * nx * ny * nz, 4) and cells.dtype == np.int64
    assert cells.min() == 0 and cells.max() == x.shape[0] - 1
    assert np.all(np.sort(cells, axis=1)[:, 1:] != np.sort(cells, axis=1)[:, :-1])
    for i, j, k in [(0, 0, 0), (1, 2, 3), (nx, ny, nz), (2, 0, 4)]:
        row = (i * (ny + 1) + j) * (nz + 1) + k
        expected = np.asarray(ORIGIN) + np.asarray(SIZE) * (i / nx, j / ny, k / nz)
        assert np.allclose(x[row], expected, rtol=0.0, atol=1e-15)
    # a scalar n is the same number of cubes along every axis
    x3, cells3 = box_tetrahedra(3)
    assert x3.shape == (64, 3) and cells3.shape == (162, 4)
    assert np.allclose(x3.min(axis=0), 0.0) and np.allclose(x3.max(axis=0), 1.0)


def test_box_tetrahedra_volumes_and_orientation():
    """Every tetrahedron is a sixth of its cuboid, the volumes add up to the box's, and half
    of them are negatively oriented (three of each cuboid's six), as documented."""
    x, cells = box_tetrahedra(N, ORIGIN, SIZE)
    volumes = _signed_volumes(x, cells)
    cuboid = np.prod(np.asarray(SIZE) / np.asarray(N))
    assert np.allclose(np.abs(volumes), cuboid / 6.0, rtol=1e-12, atol=0.0)
    assert np.abs(volumes).sum() == pytest.approx(np.prod(SIZE), rel=1e-12)
    per_cuboid = (volumes.reshape(-1, 6) > 0.0).sum(axis=1)
    assert np.all(per_cuboid == 3)


def test_box_tetrahedra_tile_the_box():
    """Points drawn inside the box lie in exactly one tetrahedron (barycentric coordinates),
    so the tetrahedra cover the box without overlapping."""
    x, cells = box_tetrahedra(N, ORIGIN, SIZE)
    rng = np.random.default_rng(7)
    points = np.asarray(ORIGIN) + rng.random((400, 3)) * np.asarray(SIZE)
    p = x[cells]
    T = np.transpose(p[:, 1:] - p[:, :1], (0, 2, 1))  # columns: edges from vertex 0
    lam = np.linalg.solve(T[None], points[:, None, :, None] - p[None, :, 0, :, None])[..., 0]
    bary = np.concatenate((1.0 - lam.sum(axis=2, keepdims=True), lam), axis=2)
    inside = np.all(bary >= -1e-12, axis=2)
    assert np.all(inside.sum(axis=1) >= 1)
    # a point on a shared face lies in two: random points almost surely lie on none
    assert np.all(np.all(bary > 1e-12, axis=2).sum(axis=1) == 1)


def test_box_tetrahedra_are_conforming():
    """Each face belongs to one tetrahedron (the box's surface) or two (interior, matching
    faces); the boundary faces are two triangles per cuboid face of the surface and their
    areas add up to the box's surface area."""
    x, cells = box_tetrahedra(N, ORIGIN, SIZE)
    faces = np.sort(cells[:, list(itertools.combinations(range(4), 3))].reshape(-1, 3), axis=1)
    unique, counts = np.unique(faces, axis=0, return_counts=True)
    assert set(counts.tolist()) == {1, 2}
    nx, ny, nz = N
    boundary = unique[counts == 1]
    assert boundary.shape[0] == 4 * (nx * ny + ny * nz + nx * nz)
    p = x[boundary]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum()
    a, b, c = SIZE
    assert area == pytest.approx(2.0 * (a * b + b * c + a * c), rel=1e-12)


def test_create_tetrahedral_mesh_from_a_box():
    """The DOLFINx mesh of two stacked boxes holds every cell once and their volume."""
    comm = MPI.COMM_WORLD
    xa, ca = box_tetrahedra(3, (0.0, 0.0, 0.0), (1.5, 1.5, 0.5))
    xb, cb = box_tetrahedra((2, 2, 1), (0.25, 0.25, 0.5), (1.0, 1.0, 0.5))
    cells = np.vstack((ca, cb + xa.shape[0]))
    mesh = create_tetrahedral_mesh(comm, cells, np.vstack((xa, xb)))
    assert mesh.topology.index_map(3).size_global == 6 * (27 + 4)
    assert _volume(mesh) == pytest.approx(1.5 * 1.5 * 0.5 + 0.5, rel=1e-12)


def test_create_tetrahedral_mesh_places_cells_where_asked():
    """all_cells_on_rank0 keeps every cell on rank 0; cell_ranks sends each where it says."""
    comm = MPI.COMM_WORLD
    x, cells = box_tetrahedra(2)
    mesh = create_tetrahedral_mesh(comm, cells, x, all_cells_on_rank0=True)
    owned = mesh.topology.index_map(3).size_local
    assert owned == (cells.shape[0] if comm.rank == 0 else 0)
    ranks = np.arange(cells.shape[0], dtype=np.int32) % comm.size
    mesh = create_tetrahedral_mesh(comm, cells, x, cell_ranks=ranks)
    assert mesh.topology.index_map(3).size_local == np.count_nonzero(ranks == comm.rank)
    assert _volume(mesh) == pytest.approx(1.0, rel=1e-12)


def test_gmsh_build_to_mesh_tags_and_cleans_up():
    """A gmsh box with tagged volumes and faces comes back with those tags and its volume;
    gmsh is left as it was found (finalised), also when the build raises."""
    gmsh = pytest.importorskip("gmsh")

    def build(model):
        box = model.occ.addBox(0.0, 0.0, 0.0, 2.0, 1.0, 0.5)
        model.occ.synchronize()
        model.addPhysicalGroup(3, [box], 7)
        bottom = [t for _, t in model.getEntities(2) if abs(model.getBoundingBox(2, t)[5]) < 1e-6]
        model.addPhysicalGroup(2, bottom, 3)
        gmsh.option.setNumber("Mesh.MeshSizeMax", 0.25)
        model.mesh.generate(3)

    mesh, cell_tags, facet_tags = gmsh_build_to_mesh(build, MPI.COMM_WORLD)
    assert not gmsh.isInitialized()
    assert _volume(mesh) == pytest.approx(1.0, rel=1e-12)
    comm = mesh.comm
    num_cells = mesh.topology.index_map(3).size_local
    tagged = comm.allreduce(
        int(np.count_nonzero(cell_tags.values[cell_tags.indices < num_cells] == 7))
    )
    assert tagged == mesh.topology.index_map(3).size_global
    bottom = dolfinx.fem.form(
        dolfinx.fem.Constant(mesh, 1.0)
        * ufl.ds(domain=mesh, subdomain_data=facet_tags, subdomain_id=3)
    )
    assert comm.allreduce(dolfinx.fem.assemble_scalar(bottom), op=MPI.SUM) == pytest.approx(2.0)

    def fails(model):
        model.occ.addBox(0.0, 0.0, 0.0, 1.0, 1.0, 1.0)
        raise ValueError("no mesh")

    if comm.size == 1:  # only rank 0 builds: elsewhere the others would wait for it
        with pytest.raises(ValueError, match="no mesh"):
            gmsh_build_to_mesh(fails, comm)
        assert not gmsh.isInitialized()


def test_gmsh_model_to_mesh_from_an_open_session():
    """A model meshed in a session the caller holds converts, and the session stays open."""
    gmsh = pytest.importorskip("gmsh")
    comm = MPI.COMM_WORLD
    gmsh.initialize()
    gmsh.option.setNumber("General.Terminal", 0)
    try:
        if comm.rank == 0:
            gmsh.model.add("cube")
            cube = gmsh.model.occ.addBox(0.0, 0.0, 0.0, 1.0, 1.0, 1.0)
            gmsh.model.occ.synchronize()
            gmsh.model.addPhysicalGroup(3, [cube], 1)
            gmsh.option.setNumber("Mesh.MeshSizeMax", 0.5)
            gmsh.model.mesh.generate(3)
        mesh, cell_tags, _ = gmsh_model_to_mesh(gmsh.model, comm, rank=0, gdim=3)
        assert gmsh.isInitialized()
    finally:
        gmsh.finalize()
    assert mesh.geometry.dim == 3
    assert _volume(mesh) == pytest.approx(1.0, rel=1e-12)
    assert set(np.unique(cell_tags.values).tolist()) <= {1}


@pytest.mark.parametrize(
    ("element", "points"),
    [
        (("Lagrange", 1), [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]),  # the vertices
        (("DG", 0), [[0.25, 0.25, 0.25]]),  # the centroid
    ],
)
def test_interpolation_points(element, points):
    """The reference points of P1 (the vertices) and DG0 (the centroid)."""
    x, cells = box_tetrahedra(1)
    mesh = create_tetrahedral_mesh(MPI.COMM_WORLD, cells, x)
    V = dolfinx.fem.functionspace(mesh, element)
    got = np.asarray(interpolation_points(V))
    assert got.shape == (len(points), 3)
    expected = np.asarray(points, dtype=float)
    # the same rows in any order: compare in lexicographic row order
    got, expected = (a[np.lexsort(a.T[::-1])] for a in (got, expected))
    assert np.allclose(got, expected, rtol=0.0, atol=1e-14)


def test_the_package_exports_the_helpers():
    """fm.meshing and fm.solve_nonlinear are reachable from the top level."""
    assert fm.meshing.box_tetrahedra is box_tetrahedra
    assert set(fm.meshing.__all__) == {
        "box_tetrahedra",
        "create_tetrahedral_mesh",
        "gmsh_build_to_mesh",
        "gmsh_model_to_mesh",
        "interpolation_points",
    }
    assert callable(fm.solve_nonlinear)
