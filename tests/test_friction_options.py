"""Coulomb friction's options and cases beyond two bodies: mu by cell tag, fixed-point updates
of the lagged quantities within a step, and friction in self-contact (serially and on several
processes alike)."""

from __future__ import annotations

import itertools

from mpi4py import MPI

import dolfinx
import numpy as np
import pytest
import ufl
from conftest import clamped_and_moved, merged_mesh, neo_hookean_residual

import fenics_matdepth as fm
from fenics_matdepth._compat import create_tetrahedral_mesh
from fenics_matdepth.meshing import box_tetrahedra

# -- mu by cell tag ----------------------------------------------------------------------------

LOWER, UPPER, SIDE = 7, 9, 11


def _two_boxes_tagged(comm: MPI.Comm):
    """Two boxes in one mesh, the upper one sunk 0.2 into the lower one (as in test_friction),
    and cell tags LOWER and UPPER of the two boxes."""
    lower = box_tetrahedra(3, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    upper = box_tetrahedra(4, (0.23, 0.11, 0.8), (0.9, 0.8, 1.0))
    mesh = merged_mesh(comm, lower, upper)
    n_cells = mesh.topology.index_map(3).size_local + mesh.topology.index_map(3).num_ghosts
    original = np.asarray(mesh.topology.original_cell_index)[:n_cells]
    values = np.where(original < lower[1].shape[0], LOWER, UPPER).astype(np.int32)
    cells = np.arange(n_cells, dtype=np.int32)
    tags = dolfinx.mesh.meshtags(mesh, 3, cells, values)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    return V, tags


def _sliding_dissipation(V: dolfinx.fem.FunctionSpace, law: fm.Coulomb) -> float:
    """The friction dissipation of a sliding displacement from the overlapping reference."""
    u = dolfinx.fem.Function(V)
    op = fm.ContactOperator(
        u, fm.material_depth(V.mesh), penalty=50.0, friction=law,
        allow_reference_overlap=True,  # the boxes overlap in the mesh on purpose
    )  # fmt: skip
    x = V.tabulate_dof_coordinates()
    u.x.array[:] = (0.02 * np.sin([3.1, 2.3, 1.7] * x + np.array([0.3, 0.1, 0.7]))).ravel()
    op.update()
    return op.friction_diagnostics()["friction_dissipation"]


def test_mu_by_cell_tag():
    """``Coulomb({(tag_a, tag_b): mu}, cell_tags=tags)`` gives the pair of bodies whose cells
    carry those tags that coefficient (the dissipation of a slide, proportional to mu, equal
    to that of ``Coulomb(mu)`` to rounding), and ``default`` the pairs it does not name."""
    V, tags = _two_boxes_tagged(MPI.COMM_WORLD)
    reference = _sliding_dissipation(V, fm.Coulomb(0.4, slip_tol=0.002))
    assert reference > 0.0
    named = fm.Coulomb({(UPPER, LOWER): 0.4}, slip_tol=0.002, cell_tags=tags)
    assert _sliding_dissipation(V, named) == pytest.approx(reference, rel=1e-12)
    # the pair (LOWER, UPPER) not named: the default, a quarter of 0.4
    other = fm.Coulomb({(LOWER, LOWER): 0.4}, slip_tol=0.002, cell_tags=tags, default=0.1)
    assert _sliding_dissipation(V, other) == pytest.approx(0.25 * reference, rel=1e-12)
    with pytest.raises(ValueError, match="dict mu"):
        fm.Coulomb(0.3, cell_tags=tags)
    facets = dolfinx.mesh.meshtags(V.mesh, 0, np.zeros(0, dtype=np.int32), np.zeros(0, np.int32))
    with pytest.raises(ValueError, match="cell MeshTags"):
        fm.Coulomb({(1, 2): 0.3}, cell_tags=facets)
    with pytest.raises(ValueError, match="updates must be"):
        fm.Coulomb(0.3, updates=-1)


def test_mu_by_cell_tag_within_one_body():
    """Regions of one body get their own coefficient: the lower box's cells are tagged LOWER
    where their centroid has x < 0.5 and SIDE elsewhere (tags given on the owned cells only),
    and a pair takes the coefficient of its triangle's cell's tag and its tetrahedron's tag.
    The dissipation is linear in each pair's coefficient, so the two regions' parts add up to
    the whole and mix by their coefficients; the upper box (x from 0.23 to 0.9, slid rigidly
    along x) lies about two fifths over the LOWER half, and so is that region's share."""
    V, tags = _two_boxes_tagged(MPI.COMM_WORLD)
    mesh = V.mesh
    n_owned = mesh.topology.index_map(3).size_local
    x = mesh.geometry.x[mesh.geometry.dofmap[:n_owned]].mean(axis=1)
    values = tags.values[:n_owned].copy()
    values[(values == LOWER) & (x[:, 0] >= 0.5)] = SIDE
    split = dolfinx.mesh.meshtags(mesh, 3, np.arange(n_owned, dtype=np.int32), values)
    upper_dofs = np.unique(V.dofmap.list[tags.find(UPPER)])

    def slide(law: fm.Coulomb) -> float:
        u = dolfinx.fem.Function(V)
        op = fm.ContactOperator(
            u, fm.material_depth(mesh), penalty=50.0, friction=law,
            allow_reference_overlap=True,  # the boxes overlap in the mesh on purpose
        )  # fmt: skip
        u.x.array.reshape(-1, 3)[upper_dofs, 0] = 0.01
        op.update()
        return op.friction_diagnostics()["friction_dissipation"]

    whole = slide(fm.Coulomb(0.4, slip_tol=0.002))
    lower = slide(fm.Coulomb({(UPPER, LOWER): 0.4}, slip_tol=0.002, cell_tags=split))
    side = slide(fm.Coulomb({(UPPER, SIDE): 0.4}, slip_tol=0.002, cell_tags=split))
    mixed = slide(fm.Coulomb({(UPPER, LOWER): 0.4, (SIDE, UPPER): 0.1}, 0.002, cell_tags=split))
    assert lower > 0.0 and side > 0.0
    assert lower + side == pytest.approx(whole, rel=1e-10)
    assert mixed == pytest.approx(lower + 0.25 * side, rel=1e-10)
    assert 0.3 < lower / whole < 0.5, lower / whole


# -- fixed-point updates of the lagged quantities ----------------------------------------------

MU, PRESS, PULL = 0.3, 0.02, 0.05


def _block_on_slab_problem(comm: MPI.Comm, updates: int):
    """The block of test_friction on its slab (E = 1, nu = 0.3), touching it at u = 0, the
    slab's bottom clamped, the block's top moved by ``g``."""
    mesh = merged_mesh(
        comm,
        box_tetrahedra((6, 6, 2), (0.0, 0.0, 0.0), (1.5, 1.5, 0.5)),
        box_tetrahedra((4, 4, 2), (0.3, 0.45, 0.5), (0.6, 0.6, 0.4)),
    )
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    residual, psi = neo_hookean_residual(u)
    bcs, g = clamped_and_moved(V, lambda x: np.isclose(x[2], 0.0), lambda x: np.isclose(x[2], 0.9))
    eps = fm.propose_penalty(mesh, 1.0)
    contact = fm.ContactOperator(
        u, fm.material_depth(mesh), penalty=eps, friction=fm.Coulomb(MU, updates=updates)
    )
    problem = fm.ContactProblem(
        residual, u, contact, bcs=bcs, energy=psi * ufl.dx, petsc_options_prefix="updates_"
    )
    return problem, contact, g


def _move(g: dolfinx.fem.Function, ux: float, uz: float) -> None:
    g.interpolate(lambda x: np.vstack((np.full(x.shape[1], ux), 0 * x[0], np.full(x.shape[1], uz))))


def _lagged_and_current_bound(contact: fm.ContactOperator) -> tuple[float, float]:
    """``mu N`` of the lagged pressure (the friction's bound) and of the current one."""
    comm = contact.comm
    lagged = comm.allreduce(float(contact.friction_points()["weight"].sum()))
    current = comm.allreduce(float(contact.contact_points(friction=True)["weight"].sum()))
    return lagged, current


def test_fixed_point_updates_take_the_lagged_pressure_to_the_final_one():
    """The block pressed by PRESS (step 1), then in one step pressed by 2 PRESS and pulled by
    PULL (it slides): with the pressure lagged from step 1 the friction's bound ``mu N_lag``
    is about half the final ``mu N``. Each fixed-point update (``update_lagged`` and a solve
    again) takes the lagged pressure to the solution's: the gap shrinks by at least half per
    update and is below 1 % after three; ``Coulomb(updates=3)`` does the same inside
    ``ContactProblem.solve`` (in both steps: the same bound to 1e-6, the iterations of all the
    solves), and a step solved again starts from the reference's lagged data."""
    comm = MPI.COMM_WORLD
    problem, contact, g = _block_on_slab_problem(comm, updates=0)
    _move(g, 0.0, -PRESS)
    iterations = problem.solve().iterations
    for _ in range(3):  # as Coulomb(updates=3) does below
        contact.update_lagged()
        iterations += problem.solve().iterations
    contact.advance()
    _move(g, PULL, -2 * PRESS)
    iterations += problem.solve().iterations
    gaps = []
    for k in range(4):
        lagged, current = _lagged_and_current_bound(contact)
        gaps.append(abs(lagged / current - 1.0))
        if k < 3:
            contact.update_lagged()
            iterations += problem.solve().iterations
    if comm.rank == 0:
        print(f"relative gap of the lagged bound per update: {gaps}")
    assert gaps[0] > 0.3
    for before, after in itertools.pairwise(gaps):
        assert after < 0.5 * before
    assert gaps[3] < 0.01
    final = _lagged_and_current_bound(contact)[0]

    problem, contact, g = _block_on_slab_problem(comm, updates=3)
    _move(g, 0.0, -PRESS)
    first = problem.solve().iterations
    contact.advance()
    _move(g, PULL, -2 * PRESS)
    result = problem.solve()
    assert _lagged_and_current_bound(contact)[0] == pytest.approx(final, rel=1e-6)
    assert first + result.iterations == pytest.approx(iterations, abs=2)
    # a step solved again (as after a failure) starts from the reference's lagged data
    contact.update_lagged()
    problem.solve()
    assert _lagged_and_current_bound(contact)[0] == pytest.approx(final, rel=1e-6)


# -- self-contact --------------------------------------------------------------------------------

#: the C-shaped body: a box 1.2 x 0.6 x 0.5 with a slot 0.1 high from x = 0.2 to its end
SLOT_X, SLOT_Z = 0.2, (0.2, 0.3)


def _c_shape(comm: MPI.Comm) -> dolfinx.mesh.Mesh:
    """One body whose two arms face each other across the slot (elements of 0.1)."""
    X, cells = box_tetrahedra((12, 6, 5), (0.0, 0.0, 0.0), (1.2, 0.6, 0.5))
    mid = X[cells].mean(axis=1)
    slot = (mid[:, 0] > SLOT_X) & (mid[:, 2] > SLOT_Z[0]) & (mid[:, 2] < SLOT_Z[1])
    cells = cells[~slot]
    used, cells = np.unique(cells, return_inverse=True)
    return create_tetrahedral_mesh(comm, cells.reshape(-1, 4), X[used])


def _folded_c(comm: MPI.Comm, mu: float | None) -> dict:
    """The C's lower arm held (its bottom face clamped), the upper arm's top face beyond
    x = 0.7 pressed down across the slot (contact within the body) in two steps, then pulled
    along x in one. Returns the pull's reaction (x force on the moved face), the friction
    diagnostics of the last step and the number of bodies."""
    mesh = _c_shape(comm)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    residual, psi = neo_hookean_residual(u)
    bcs, g = clamped_and_moved(
        V, lambda x: np.isclose(x[2], 0.0), lambda x: np.isclose(x[2], 0.5) & (x[0] > 0.7 - 1e-9)
    )
    eps = fm.propose_penalty(mesh, 1.0)
    law = None if mu is None else fm.Coulomb(mu)
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=eps, friction=law)
    problem = fm.ContactProblem(
        residual, u, contact, bcs=bcs, energy=psi * ufl.dx, petsc_options_prefix="selfc_"
    )
    table = [(0.0, 0.0), (0.0, -0.07), (0.0, -0.12), (0.03, -0.12)]

    def set_load(t):
        i = min(int(t), len(table) - 2)
        (x0, z0), (x1, z1) = table[i], table[i + 1]
        _move(g, x0 + (t - i) * (x1 - x0), z0 + (t - i) * (z1 - z0))

    records = fm.solve_load_steps(problem, set_load, num_steps=3, end=3.0, progress=False)
    contact.update()
    b = dolfinx.fem.assemble_vector(dolfinx.fem.form(residual))
    b.scatter_reverse(dolfinx.la.InsertMode.add)
    moved = dolfinx.fem.locate_dofs_topological(
        V, 2, dolfinx.mesh.locate_entities_boundary(
            mesh, 2, lambda x: np.isclose(x[2], 0.5) & (x[0] > 0.7 - 1e-9)
        ),
    )  # fmt: skip
    moved = moved[moved < V.dofmap.index_map.size_local]
    reaction = comm.allreduce(float(b.array.reshape(-1, 3)[moved, 0].sum()))
    return {
        "reaction": reaction,
        "loads": [r.load for r in records],
        "bodies": contact.surface.num_bodies,
        **records[-1].diagnostics,
    }


#: the pull's reaction with mu = 0.5, its last step's dissipation, the reaction without
#: friction, as measured serially (DOLFINx 0.9)
SERIAL_SELF_CONTACT = [0.008822042116992612, 1.852856504338904e-05, 0.00028844800158845047]


def test_friction_in_self_contact():
    """The C's upper arm pressed onto its lower arm (one body) and pulled along it: the
    friction acts within the body (positive dissipation, points slipping, the pull's reaction
    30 times that without friction, at least 10 asserted) and the figures are the serial ones
    (to 1e-5) on any number of processes."""
    comm = MPI.COMM_WORLD
    with_mu = _folded_c(comm, 0.5)
    without = _folded_c(comm, None)
    if comm.rank == 0:
        print(f"self-contact: with friction {with_mu}, without {without['reaction']}")
    assert with_mu["bodies"] == 1 and with_mu["loads"] == [1.0, 2.0, 3.0]
    assert with_mu["friction_dissipation"] > 0.0 and with_mu["slip_points"] > 0
    # the arms slide over each other: friction, not the bent arm's stiffness, resists the pull
    assert with_mu["reaction"] > 10.0 * without["reaction"] > 0.0
    measured = [with_mu["reaction"], with_mu["friction_dissipation"], without["reaction"]]
    assert np.allclose(measured, SERIAL_SELF_CONTACT, rtol=1e-5)
