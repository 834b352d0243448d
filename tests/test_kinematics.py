"""Rigid-rotation Dirichlet data: exact rotations of known points, composition, zero angle, and
a Dirichlet condition that moves a body's vertices rigidly."""

from __future__ import annotations

from mpi4py import MPI

import dolfinx
import numpy as np
import pytest

import fenics_matdepth as fm
from fenics_matdepth.kinematics import rotation_displacement, rotation_matrix


def test_quarter_turns_of_known_points():
    # a right-handed quarter turn about +z takes x to y and y to -x
    R = rotation_matrix((0.0, 0.0, 2.0), np.pi / 2)
    np.testing.assert_allclose(R @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(R @ [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(R @ [0.0, 0.0, 1.0], [0.0, 0.0, 1.0], atol=1e-15)
    # about the axis through (1, 1, 0), parallel to x: (1, 1, 1) -> (1, 0, 0) after +90 deg
    u = rotation_displacement(
        [[1.0, 1.0, 1.0], [5.0, 1.0, 0.0]], (1.0, 1.0, 0.0), (1, 0, 0), np.pi / 2
    )
    np.testing.assert_allclose(u[0], [0.0, -1.0, -1.0], atol=1e-14)
    np.testing.assert_allclose(u[1], [0.0, 0.0, 0.0], atol=1e-14)  # a point on the axis stays


def test_rotation_is_orthogonal_and_keeps_distances_to_the_axis():
    rng = np.random.default_rng(3)
    axis, angle = rng.normal(size=3), 2.1
    R = rotation_matrix(axis, angle)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-14)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-14)
    np.testing.assert_allclose(R @ axis, axis, atol=1e-14)
    # the angle between a vector normal to the axis and its image is the rotation angle
    normal = np.cross(axis, rng.normal(size=3))
    cos = normal @ (R @ normal) / (normal @ normal)
    assert np.arccos(cos) == pytest.approx(angle, abs=1e-12)


def test_composition_about_one_axis_adds_the_angles():
    rng = np.random.default_rng(5)
    X = rng.normal(size=(20, 3))
    center, axis = (0.3, -1.0, 2.0), (1.0, 2.0, -0.5)
    a, b = 0.4, -1.3
    once = X + rotation_displacement(X, center, axis, a)
    twice = once + rotation_displacement(once, center, axis, b)
    direct = X + rotation_displacement(X, center, axis, a + b)
    np.testing.assert_allclose(twice, direct, atol=1e-13)
    # and a full turn is the identity
    np.testing.assert_allclose(rotation_displacement(X, center, axis, 2 * np.pi), 0.0, atol=1e-13)


def test_zero_angle_is_zero_displacement():
    X = np.random.default_rng(0).normal(size=(7, 3))
    assert np.all(rotation_displacement(X, (1, 2, 3), (0, 1, 0), 0.0) == 0.0)


def test_bad_axis_raises():
    with pytest.raises(ValueError, match="non-zero 3-vector"):
        rotation_matrix((0.0, 0.0, 0.0), 1.0)
    with pytest.raises(ValueError, match="non-zero 3-vector"):
        rotation_matrix((1.0, 0.0), 1.0)


def test_rigid_rotation_dirichlet_condition_on_a_mesh():
    """The Function holds the rotation at every vertex; a Dirichlet condition on some vertices
    moves exactly those, and their distances stay those of the reference (rigid)."""
    mesh = dolfinx.mesh.create_unit_cube(MPI.COMM_WORLD, 3, 3, 3)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    center, axis = (0.5, 0.0, 0.0), (-1.0, 0.0, 0.0)
    rotation = fm.RigidRotation(V, center, axis)
    assert np.all(rotation.function.x.array == 0.0)
    angle = np.radians(30.0)
    rotation.set_angle(angle)
    X = V.tabulate_dof_coordinates()
    u = rotation.function.x.array.reshape(-1, 3)
    np.testing.assert_allclose(u, rotation_displacement(X, center, axis, angle), atol=1e-14)
    # rotation about -x by +30 deg: y -> y cos + z sin, z -> -y sin + z cos (about the centre)
    y, z = X[:, 1], X[:, 2]
    expected_y = y * np.cos(angle) + z * np.sin(angle)
    expected_z = -y * np.sin(angle) + z * np.cos(angle)
    np.testing.assert_allclose(X[:, 1] + u[:, 1], expected_y, atol=1e-14)
    np.testing.assert_allclose(X[:, 2] + u[:, 2], expected_z, atol=1e-14)

    top = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[2], 1.0))
    dofs = dolfinx.fem.locate_dofs_topological(V, 2, top)
    bc = dolfinx.fem.dirichletbc(rotation.function, dofs)
    w = dolfinx.fem.Function(V)
    bc.set(w.x.array)
    moved = w.x.array.reshape(-1, 3)
    on_top = np.isclose(X[:, 2], 1.0)
    np.testing.assert_allclose(moved[on_top], u[on_top], atol=1e-14)
    assert np.all(moved[~on_top] == 0.0)
    # callable form, back to zero
    rotation(0.0)
    assert np.all(rotation.function.x.array == 0.0) and rotation.angle == 0.0


def test_rigid_rotation_needs_a_vector_space():
    mesh = dolfinx.mesh.create_unit_cube(MPI.COMM_WORLD, 1, 1, 1)
    Q = dolfinx.fem.functionspace(mesh, ("Lagrange", 1))
    with pytest.raises(ValueError, match="value size 3"):
        fm.RigidRotation(Q, (0, 0, 0), (0, 0, 1))


def test_cell_determinants_of_a_uniform_stretch():
    """u = (s - 1) x stretches every cell by s in each direction: det F = s^3 in each cell, and
    the smallest over the cells is that value."""
    mesh = dolfinx.mesh.create_unit_cube(
        MPI.COMM_WORLD, 2, 2, 2, cell_type=dolfinx.mesh.CellType.tetrahedron
    )
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    u.interpolate(lambda x: 0.5 * x)
    cells = fm.kinematics.CellDeterminants(V)
    values = cells.local_values(u.x.array)
    assert values.size == mesh.topology.index_map(3).size_local
    assert np.allclose(values, 1.5**3, rtol=1e-12)
    assert cells.min(u) == pytest.approx(1.5**3, rel=1e-12)


def test_cell_determinants_equal_det_f_of_a_nonuniform_displacement():
    """Per cell, det F from the signed volumes equals det(I + grad u) of the interpolated P1
    field evaluated by DOLFINx (a DG0 interpolation of the UFL expression); a displacement
    that turns a cell inside out gives a negative value, and NaN gives -inf."""
    import ufl

    mesh = dolfinx.mesh.create_unit_cube(
        MPI.COMM_WORLD, 3, 3, 3, cell_type=dolfinx.mesh.CellType.tetrahedron
    )
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    u.interpolate(
        lambda x: np.stack(
            (0.3 * x[1] ** 2 - 0.2 * x[2], 0.4 * x[0] * x[2], 0.2 * x[0] * x[1] - 0.5 * x[2] ** 2)
        )
    )
    Q = dolfinx.fem.functionspace(mesh, ("DG", 0))
    det_f = dolfinx.fem.Function(Q)
    expr = ufl.det(ufl.Identity(3) + ufl.grad(u))
    det_f.interpolate(dolfinx.fem.Expression(expr, fm.meshing.interpolation_points(Q)))
    num_owned = mesh.topology.index_map(3).size_local
    expected = det_f.x.array[np.asarray(Q.dofmap.list)[:num_owned, 0]]
    cells = fm.kinematics.CellDeterminants(V)
    values = cells.local_values(u.x.array)
    assert np.ptp(expected) > 0.3  # the field is far from uniform
    assert np.allclose(values, expected, rtol=1e-12, atol=1e-12)
    assert cells.min(u) == pytest.approx(mesh.comm.allreduce(expected.min(), op=MPI.MIN))
    # the first owned cell's first vertex moved through the opposite face: inverted
    array = u.x.array.copy()
    dofs = np.asarray(V.dofmap.list)[0]
    X = V.tabulate_dof_coordinates()
    centre = X[dofs[1:]].mean(axis=0)
    array[3 * dofs[0] : 3 * dofs[0] + 3] += 2.0 * (centre - X[dofs[0]])
    assert cells.local_values(array)[0] < 0.0
    array[0] = np.nan
    assert cells.local_min(array) == -np.inf
