"""Boundary extraction (fenics_matdepth/boundary.py) on a box of known surface: the face table
against an independent count of the cells' faces, the boundary triangles' number, area and
outward orientation, and the split of the exterior faces between ranks."""

from __future__ import annotations

from mpi4py import MPI

import dolfinx
import numpy as np
import pytest
from conftest import merged_mesh

from fenics_matdepth._compat import create_tetrahedral_mesh
from fenics_matdepth.boundary import (
    boundary_triangles,
    face_table,
    global_face_vertices,
    owned_boundary_triangle_dofs,
    owned_exterior_facets,
    p1_dof_coordinates,
)
from fenics_matdepth.meshing import box_tetrahedra

#: The box [0, 2] x [0, 1] x [0, 0.5] in 4 x 2 x 2 cubes of 6 tetrahedra each: every cube face
#: on the boundary is two triangles.
LO, HI, CELLS = np.zeros(3), np.array([2.0, 1.0, 0.5]), (4, 2, 2)
NUM_BOUNDARY_TRIANGLES = 4 * (4 * 2 + 2 * 2 + 4 * 2)  # 2 sides x 2 triangles x cube faces
SURFACE_AREA = 2.0 * (2.0 * 1.0 + 1.0 * 0.5 + 2.0 * 0.5)


@pytest.fixture(params=["ghosted", "unghosted"])
def box(request) -> dolfinx.mesh.Mesh:
    """The box from ``dolfinx.mesh.create_box`` (cells across a rank boundary are ghosts, so
    faces between ranks have a local neighbour), or from the package's mesh builder (no
    ghost cells: faces between ranks are told from exterior ones by the other ranks)."""
    comm = MPI.COMM_WORLD
    if request.param == "ghosted":
        return dolfinx.mesh.create_box(
            comm, [LO, HI], list(CELLS), dolfinx.mesh.CellType.tetrahedron
        )
    return create_tetrahedral_mesh(comm, *box_tetrahedra(CELLS, LO, HI - LO)[::-1])


def _areas(x: np.ndarray) -> np.ndarray:
    """Areas of triangles ``x`` (m, 3, 3)."""
    return 0.5 * np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1)


def _face_of_box(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(axis, side) of the box face each triangle ``x`` (m, 3, 3) lies in (side -1 at LO, +1
    at HI); -1 axis where a triangle lies in none."""
    axis = np.full(x.shape[0], -1)
    side = np.zeros(x.shape[0])
    for a in range(3):
        for s, value in ((-1.0, LO[a]), (1.0, HI[a])):
            on = np.all(np.abs(x[:, :, a] - value) <= 1e-14, axis=1)
            axis[on], side[on] = a, s
    return axis, side


def test_face_table_against_a_count_of_faces(box):
    """The face table's neighbours against a count of each face's vertex triple over the local
    cells: a face met by two local cells is matched both ways, a face met once has no
    neighbour; no face is met by three cells."""
    mesh = box
    table = face_table(mesh)
    assert table.overshared == 0
    c2v = table.cell_vertices
    faces = np.sort(np.stack([np.delete(c2v, i, axis=1) for i in range(4)], axis=1), axis=2)
    _, inverse, counts = np.unique(
        faces.reshape(-1, 3), axis=0, return_inverse=True, return_counts=True
    )
    count = counts[inverse.ravel()].reshape(-1, 4)
    assert np.array_equal(table.neighbour < 0, count == 1)
    assert np.all(count <= 2)
    c, i = np.nonzero(table.neighbour >= 0)
    other = table.neighbour[c, i]
    assert np.array_equal(table.neighbour[other // 4, other % 4], 4 * c + i)
    assert np.array_equal(faces[other // 4, other % 4], faces[c, i])
    # the same table again: it is kept with the mesh
    assert face_table(mesh) is table


def test_exterior_faces_are_owned_once(box):
    """Each exterior face is owned by exactly one rank: the ranks' counts add up to the box's
    triangles, the global vertex triples are distinct, and DOLFINx's exterior facets (an
    independent search, on facet entities) are as many."""
    mesh = box
    comm = mesh.comm
    table = face_table(mesh)
    num_owned = mesh.topology.index_map(3).size_local
    assert np.all(table.exterior[:, 0] < num_owned)
    assert comm.allreduce(table.exterior.shape[0]) == NUM_BOUNDARY_TRIANGLES
    triples = np.sort(global_face_vertices(mesh, table.cell_vertices, table.exterior), axis=1)
    gathered = np.vstack(comm.allgather(triples))
    assert np.unique(gathered, axis=0).shape[0] == NUM_BOUNDARY_TRIANGLES
    assert comm.allreduce(owned_exterior_facets(mesh).size) == NUM_BOUNDARY_TRIANGLES
    # the global vertex triples are those of the faces' coordinates
    imap = mesh.topology.index_map(0)
    local = np.array(
        [np.delete(table.cell_vertices[c], i) for c, i in table.exterior], dtype=np.int32
    ).reshape(-1, 3)
    expected = imap.local_to_global(local.ravel()).reshape(-1, 3)
    assert np.array_equal(np.sort(expected, axis=1), triples)


def test_boundary_triangles_cover_the_box_surface(box):
    """All ranks get every boundary triangle: 80 of them, each in a face of the box, with total
    area the box's surface area (rounding: 1e-13 relative)."""
    mesh = box
    x = boundary_triangles(mesh)
    assert x.shape == (NUM_BOUNDARY_TRIANGLES, 3, 3)
    axis, _ = _face_of_box(x)
    assert np.all(axis >= 0)
    assert np.all(_areas(x) > 0.0)
    assert abs(_areas(x).sum() - SURFACE_AREA) <= 1e-13 * SURFACE_AREA
    # the same on every rank
    comm = mesh.comm
    assert comm.allgather(x.tobytes()) == [x.tobytes()] * comm.size


def test_owned_triangles_point_outward(box):
    """The owned boundary triangles as P1 dofs: their normals ``(x1 - x0) x (x2 - x0)`` are
    the outward normals of the box faces they lie in, and they tile the surface once across
    the ranks."""
    mesh = box
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    X = p1_dof_coordinates(V)
    cells = np.asarray(V.dofmap.list).reshape(-1, 4)
    tri = owned_boundary_triangle_dofs(mesh, cells, X)
    x = X[tri]
    axis, side = _face_of_box(x)
    assert np.all(axis >= 0)
    normal = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    along = normal[np.arange(len(tri)), axis] * side
    assert np.all(along > 0.0)
    # the normal is along the face's axis only (a flat triangle in an axis plane)
    off = normal.copy()
    off[np.arange(len(tri)), axis] = 0.0
    assert np.abs(off).max(initial=0.0) <= 1e-14
    comm = mesh.comm
    area = comm.allreduce(float(_areas(x).sum()))
    assert abs(area - SURFACE_AREA) <= 1e-13 * SURFACE_AREA
    assert comm.allreduce(tri.shape[0]) == NUM_BOUNDARY_TRIANGLES


def test_p1_dof_coordinates_are_the_vertices(box):
    """The P1 dofs' coordinates against DOLFINx's tabulated ones (1e-15: the same vertices),
    owned and ghost."""
    mesh = box
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1))
    X = p1_dof_coordinates(V)
    imap = V.dofmap.index_map
    assert X.shape == (imap.size_local + imap.num_ghosts, 3)
    assert np.abs(X - V.tabulate_dof_coordinates()).max() <= 1e-15


def test_two_touching_boxes_keep_their_faces():
    """Two boxes meeting face to face in one mesh, not glued (distinct vertices): the faces in
    contact are exterior faces of both, so the surface is both boxes' surfaces."""
    comm = MPI.COMM_WORLD
    mesh = merged_mesh(
        comm,
        box_tetrahedra(2, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)),
        box_tetrahedra(2, (0.0, 0.0, 1.0), (1.0, 1.0, 1.0)),
    )
    x = boundary_triangles(mesh)
    assert x.shape[0] == 2 * 6 * 4 * 2
    assert abs(_areas(x).sum() - 12.0) <= 1e-13 * 12.0
