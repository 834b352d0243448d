"""material_depth: analytic box, gmsh ball against brute force, MPI against serial, bad input."""

from __future__ import annotations

from mpi4py import MPI

import dolfinx
import numpy as np
import pytest

from fenics_matdepth import material_depth
from fenics_matdepth._compat import gmsh_model_to_mesh
from fenics_matdepth.depth import distance_to_triangles
from fenics_matdepth.geometry.distance import nearest_triangle_bruteforce

gmsh = pytest.importorskip("gmsh")

BALL_RADIUS = 1.0
INNER_RADIUS = 0.5


def _dof_coordinates(d):
    """Coordinates of the local (owned + ghost) P1 dofs, independent of material_depth's map."""
    return d.function_space.tabulate_dof_coordinates()[:, :3]


def _ball_model(order: int = 1, h: float = 0.35):
    """Ball of radius 1 made of two glued volumes (inner ball r=0.5 + shell), on rank 0.

    Returns the outer-sphere triangles (m, 3, 3) read from gmsh (None on other ranks): an
    exterior boundary independent of DOLFINx, without the internal glued sphere.
    """
    gmsh.initialize()
    gmsh.option.setNumber("General.Terminal", 0)
    triangles = None
    if MPI.COMM_WORLD.rank == 0:
        gmsh.model.add("ball")
        outer = gmsh.model.occ.addSphere(0, 0, 0, BALL_RADIUS)
        inner = gmsh.model.occ.addSphere(0, 0, 0, INNER_RADIUS)
        gmsh.model.occ.fragment([(3, outer)], [(3, inner)])
        gmsh.model.occ.synchronize()
        vols = [tag for _, tag in gmsh.model.getEntities(3)]
        gmsh.model.addPhysicalGroup(3, vols, 1)
        gmsh.option.setNumber("Mesh.CharacteristicLengthMax", h)
        gmsh.option.setNumber("Mesh.CharacteristicLengthMin", h)
        gmsh.model.mesh.generate(3)
        gmsh.model.mesh.setOrder(order)
        tags, coords, _ = gmsh.model.mesh.getNodes()
        coords = coords.reshape(-1, 3)
        node_pos = np.empty(int(tags.max()) + 1, dtype=np.int64)
        node_pos[tags.astype(np.int64)] = np.arange(len(tags))
        tris = []
        for _, surf in gmsh.model.getEntities(2):
            xmax = gmsh.model.getBoundingBox(2, surf)[3]
            if xmax < 0.9 * BALL_RADIUS:
                continue  # the glued inner sphere: not exterior boundary
            _, _, nodes = gmsh.model.mesh.getElements(2, surf)
            corners = nodes[0].reshape(-1, 3 if order == 1 else 6)[:, :3]
            tris.append(coords[node_pos[corners.astype(np.int64)]])
        triangles = np.concatenate(tris)
    mesh, _, _ = gmsh_model_to_mesh(gmsh.model, MPI.COMM_WORLD, 0, gdim=3)
    gmsh.finalize()
    return mesh, MPI.COMM_WORLD.bcast(triangles, root=0)


# ------------------------------------------------------------------------------------------
# values
# ------------------------------------------------------------------------------------------


def test_box_analytic():
    lo = np.array([-0.5, 0.0, 0.2])
    hi = np.array([1.0, 2.0, 1.7])
    mesh = dolfinx.mesh.create_box(
        MPI.COMM_WORLD, [lo, hi], [5, 7, 6], dolfinx.mesh.CellType.tetrahedron
    )
    d = material_depth(mesh)
    V = d.function_space
    x = _dof_coordinates(d)
    expected = np.minimum(x - lo, hi - x).min(axis=1)
    assert d.x.array.shape == (x.shape[0],)  # owned and ghost values present
    np.testing.assert_allclose(d.x.array, expected, rtol=0.0, atol=1e-12)
    # boundary vertices: exactly zero
    mesh.topology.create_connectivity(2, 3)
    facets = dolfinx.mesh.exterior_facet_indices(mesh.topology)
    bdofs = dolfinx.fem.locate_dofs_topological(V, 2, facets)
    assert bdofs.size > 0 or mesh.comm.size > 1
    assert np.all(d.x.array[bdofs] == 0.0)
    # and nowhere else (interior vertices are at least one cell layer deep)
    interior = np.setdiff1d(np.arange(x.shape[0]), bdofs)
    on_face = np.isclose(expected[interior], 0.0, atol=1e-12)
    assert np.all(d.x.array[interior[~on_face]] > 0.2)


def test_ball_bruteforce_and_glued_interface():
    mesh, triangles = _ball_model()
    d = material_depth(mesh)
    x = _dof_coordinates(d)
    # brute force over every exterior triangle (read from gmsh, not from DOLFINx)
    pts = triangles.reshape(-1, 3)
    cells = np.arange(pts.shape[0]).reshape(-1, 3)
    _, ref = nearest_triangle_bruteforce(x, pts, cells)
    np.testing.assert_allclose(d.x.array, ref, rtol=0.0, atol=1e-12)
    # inscribed polyhedron: r_in - |X| <= d <= R - |X|, r_in = nearest approach to the centre
    _, r_in = nearest_triangle_bruteforce(np.zeros((1, 3)), pts, cells)
    r = np.linalg.norm(x, axis=1)
    assert np.all(d.x.array <= BALL_RADIUS - r + 1e-12)
    assert np.all(d.x.array >= r_in[0] - r - 1e-12)
    assert BALL_RADIUS - r_in[0] < 0.1  # the surface is a fair approximation of the sphere
    # vertices on the glued inner sphere are deep inside, not on a boundary
    on_inner = np.abs(r - INNER_RADIUS) < 1e-6
    assert mesh.comm.allreduce(int(on_inner.sum())) > 0
    assert np.all(d.x.array[on_inner] > 0.5 * (r_in[0] - INNER_RADIUS))


def test_parallel_equals_serial():
    """Distributed values equal a serial computation on the whole mesh, on every rank."""
    lo, hi, n = np.zeros(3), np.array([1.0, 0.7, 0.5]), [6, 5, 4]

    def make(comm):
        mesh = dolfinx.mesh.create_box(comm, [lo, hi], n, dolfinx.mesh.CellType.tetrahedron)
        x = mesh.geometry.x
        # a smooth non-affine deformation, so the depth is not a simple function of x
        x[:, 0] += 0.08 * np.sin(3.0 * x[:, 1]) * x[:, 2]
        x[:, 2] += 0.05 * np.cos(4.0 * x[:, 0])
        return mesh

    d_par = material_depth(make(MPI.COMM_WORLD))
    d_ser = material_depth(make(MPI.COMM_SELF))
    x_par = _dof_coordinates(d_par)
    x_ser = _dof_coordinates(d_ser)
    key = {tuple(np.round(p, 10)): i for i, p in enumerate(x_ser)}
    match = np.array([key[tuple(np.round(p, 10))] for p in x_par])
    np.testing.assert_array_equal(x_par.shape[0], match.shape[0])
    np.testing.assert_allclose(d_par.x.array, d_ser.x.array[match], rtol=0.0, atol=1e-14)
    # guard against a trivial pass: the field is not identically zero
    assert d_ser.x.array.max() > 0.2


def _global_face_rows(mesh, cells, faces):
    """Sorted global topology vertices of faces given as (cell, local face), gathered."""
    from fenics_matdepth._mpi import allgather_rows
    from fenics_matdepth.boundary import FACE_VERTICES

    c2v = np.asarray(mesh.topology.connectivity(3, 0).array).reshape(-1, 4)
    local = c2v[np.asarray(cells)[:, None], FACE_VERTICES[np.asarray(faces)]]
    glob = mesh.topology.index_map(0).local_to_global(local.ravel().astype(np.int32))
    rows = np.sort(np.asarray(glob, dtype=np.int64).reshape(-1, 3), axis=1)
    return allgather_rows(mesh.comm, rows)


@pytest.mark.parametrize(
    "ghost_mode", [dolfinx.mesh.GhostMode.none, dolfinx.mesh.GhostMode.shared_facet]
)
def test_face_table_equals_dolfinx_facets(ghost_mode):
    """The face table (no DOLFINx facets) finds the same exterior faces as DOLFINx's facet
    entities, each on one rank only, and the same neighbour across every local face; on a
    box cut into two bodies glued along a plane (the interface is no boundary)."""
    from fenics_matdepth.boundary import face_table

    mesh = dolfinx.mesh.create_box(
        MPI.COMM_WORLD,
        [np.zeros(3), np.array([1.0, 0.8, 0.6])],
        [6, 5, 4],
        dolfinx.mesh.CellType.tetrahedron,
        ghost_mode=ghost_mode,
    )
    table = face_table(mesh)  # before DOLFINx creates any facet
    assert face_table(mesh) is table  # kept with the mesh
    assert table.overshared == 0
    ours = _global_face_rows(mesh, *table.exterior.T)
    assert ours.shape[0] == 2 * (6 * 5 + 6 * 4 + 5 * 4) * 2  # two triangles per square
    assert np.unique(ours, axis=0).shape[0] == ours.shape[0]  # each face on one rank

    mesh.topology.create_connectivity(2, 3)
    mesh.topology.create_connectivity(3, 2)
    facets = dolfinx.mesh.exterior_facet_indices(mesh.topology)
    facets = facets[facets < mesh.topology.index_map(2).size_local]
    f2c = mesh.topology.connectivity(2, 3)
    c2f = np.asarray(mesh.topology.connectivity(3, 2).array).reshape(-1, 4)
    cell = np.asarray(f2c.array)[np.asarray(f2c.offsets)[facets]]
    face = np.argmax(c2f[cell] == facets[:, None], axis=1)
    theirs = _global_face_rows(mesh, cell, face)
    np.testing.assert_array_equal(np.unique(ours, axis=0), np.unique(theirs, axis=0))

    # neighbours: across face i of cell c lies the other local cell of DOLFINx's facet
    offsets, links = np.asarray(f2c.offsets), np.asarray(f2c.array)
    for c in range(c2f.shape[0]):
        for i in range(4):
            f = c2f[c, i]
            others = [o for o in links[offsets[f] : offsets[f + 1]] if o != c]
            across = table.neighbour[c, i]
            if others:
                assert across // 4 == others[0] and c2f[across // 4, across % 4] == f
            else:
                assert across == -1


# ------------------------------------------------------------------------------------------
# bad input
# ------------------------------------------------------------------------------------------


def test_rejects_non_tetrahedral():
    hexes = dolfinx.mesh.create_unit_cube(MPI.COMM_WORLD, 2, 2, 2, dolfinx.mesh.CellType.hexahedron)
    with pytest.raises(ValueError, match="tetrahedral"):
        material_depth(hexes)
    tris = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 2, 2)
    with pytest.raises(ValueError, match="tetrahedral"):
        material_depth(tris)
    with pytest.raises(TypeError, match="Mesh"):
        material_depth(np.zeros((4, 3)))


def test_rejects_curved_geometry():
    mesh, _ = _ball_model(order=2, h=0.6)
    with pytest.raises(ValueError, match="affine"):
        material_depth(mesh)


def test_no_boundary_core():
    with pytest.raises(ValueError, match="no boundary"):
        distance_to_triangles(np.zeros((3, 3)), np.zeros((0, 3, 3)))
