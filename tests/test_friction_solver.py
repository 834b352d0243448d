"""Coulomb friction and the linear solver: the share of friction points whose tangential
stiffness moved since a mark (``ContactOperator.stick_slip_change``) against the friction
points' own slips, and the kept factorisation's rule that factorises once it exceeds
``linear_solver.FRICTION_SWITCH_SHARE`` (the Newton iterates unchanged, fewer failed GMRES)."""

from __future__ import annotations

from mpi4py import MPI

import dolfinx
import numpy as np
import pytest
import ufl
from conftest import clamped_and_moved, merged_mesh, neo_hookean_residual

import fenics_matdepth as fm
from fenics_matdepth import linear_solver
from fenics_matdepth.meshing import box_tetrahedra


def _stiffness(points: dict, slip_tol: float) -> np.ndarray:
    """Each friction point's tangential stiffness across its slip, ``c f1(y) / y``, from the
    points' traction ratio ``f1`` (``2 c / e`` at zero slip)."""
    y, c = points["slip_length"], points["weight"]
    at_rest = y <= 0.0
    return np.where(at_rest, 2.0 * c / slip_tol, c * points["ratio"] / np.where(at_rest, 1.0, y))


def test_stick_slip_change_counts_the_points_whose_stiffness_moved():
    comm = MPI.COMM_WORLD
    mesh = merged_mesh(
        comm,
        box_tetrahedra(3, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)),
        box_tetrahedra(4, (0.23, 0.11, 0.8), (0.9, 0.8, 1.0)),
    )
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    e = 0.002
    op = fm.ContactOperator(
        u, fm.material_depth(mesh), penalty=50.0, friction=fm.Coulomb(0.4, slip_tol=e),
        allow_reference_overlap=True,  # the boxes overlap in the mesh on purpose
    )  # fmt: skip
    # before any mark, and on a new reference: 1 (the friction acts: its points' stick
    # stiffness is far above the floor)
    assert op.stick_slip_change() == 1.0
    op.mark_stick_slip()
    assert op.stick_slip_change() == 0.0
    marked = _stiffness(op.friction_points(), e)
    x = V.tabulate_dof_coordinates()
    n = V.dofmap.index_map.size_local + V.dofmap.index_map.num_ghosts
    upper = op.body_of_vertex[V.dofmap.index_map.local_to_global(np.arange(n, dtype=np.int32))]
    upper = upper == op.body_of_vertex.max()
    # the upper box moved along a smooth field: slips of 0 to a few e, both branches
    for amplitude, some_change in ((0.1 * e, False), (8.0 * e, True)):
        u.x.array[:] = 0.0
        field = amplitude * (1.0 + np.sin([2.3, 1.7, 0.0] * x[:, [1, 0, 2]]))
        field[:, 2] = 0.0
        u.x.array.reshape(-1, 3)[upper] = field[upper]
        op.update()
        now = _stiffness(op.friction_points(), e)
        area = op.friction_points()["area"]
        floor = op.penalty * area * 1e-2
        changed = (np.maximum(now, marked) > floor) & ((now > 2 * marked) | (marked > 2 * now))
        expected = comm.allreduce(np.count_nonzero(changed)) / comm.allreduce(now.size)
        assert op.stick_slip_change() == pytest.approx(expected, rel=1e-12, abs=1e-15)
        assert (expected > 0.3) == some_change  # 0.1 e: none moved by 2x; 8 e: most
    op.advance()  # a new reference: its points are not the mark's
    assert op.stick_slip_change() == 1.0


def _pressed_and_pulled_block(comm: MPI.Comm) -> tuple[list, np.ndarray, int]:
    """A 0.6 x 0.6 x 0.4 block on a 1.5 x 1.5 x 0.5 slab (neo-Hookean, E = 1, nu = 0.3,
    ``Coulomb(0.3)``), pressed by 0.02 and pulled by 0.1 in two steps each: the load steps'
    records, the displacement (by vertex coordinates, on every rank) and the kept
    factorisations' failed GMRES solves."""
    mesh = merged_mesh(
        comm,
        box_tetrahedra((9, 9, 3), (0.0, 0.0, 0.0), (1.5, 1.5, 0.5)),
        box_tetrahedra((6, 6, 3), (0.3, 0.45, 0.5), (0.6, 0.6, 0.4)),
    )
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    residual, psi = neo_hookean_residual(u)
    bcs, g = clamped_and_moved(V, lambda x: np.isclose(x[2], 0.0), lambda x: np.isclose(x[2], 0.9))
    contact = fm.ContactOperator(
        u, fm.material_depth(mesh), penalty=fm.propose_penalty(mesh, 1.0),
        friction=fm.Coulomb(0.3),
    )  # fmt: skip
    problem = fm.ContactProblem(residual, u, contact, bcs=bcs, energy=psi * ufl.dx)
    failed = []
    solve = problem._solve_undamped

    def counted(*args, **kwargs):
        result = solve(*args, **kwargs)
        failed.append(problem._kept_failed)
        return result

    problem._solve_undamped = counted

    def set_load(t):
        ux, uz = 0.05 * max(t - 2.0, 0.0), 0.01 * min(t, 2.0)
        g.interpolate(
            lambda x: np.vstack((np.full(x.shape[1], ux), 0 * x[0], np.full(x.shape[1], -uz)))
        )

    records = fm.solve_load_steps(problem, set_load, num_steps=4, end=4.0, progress=False)
    # ordered by the vertices' coordinates (unique here): the two runs' meshes may be
    # partitioned and numbered differently
    n = V.dofmap.index_map.size_local
    rows = np.hstack((V.tabulate_dof_coordinates()[:n], u.x.array.reshape(-1, 3)[:n]))
    rows = np.vstack(comm.allgather(rows))
    solution = rows[np.lexsort(np.round(rows[:, :3], 9).T[::-1])][:, 3:]
    problem.destroy()
    return records, solution, comm.allreduce(sum(failed), op=MPI.MAX)


def test_the_switch_rule_keeps_the_newton_iterates_and_spares_failed_gmres(monkeypatch):
    comm = MPI.COMM_WORLD
    with_rule, u_with, failed_with = _pressed_and_pulled_block(comm)
    monkeypatch.setattr(linear_solver, "FRICTION_SWITCH_SHARE", np.inf)
    without, u_without, failed_without = _pressed_and_pulled_block(comm)
    # the linear solves are exact (GMRES to 1e-10 or a factorisation) either way: the same
    # Newton iterates
    assert [r.iterations for r in with_rule] == [r.iterations for r in without]
    assert np.abs(u_with - u_without).max() < 1e-8 * np.abs(u_without).max()
    # the block slides in the last step
    assert with_rule[-1].diagnostics["slip_points"] > with_rule[-1].diagnostics["stick_points"]
    # without the rule GMRES on kept factorisations fails where the stick/slip set moved
    assert failed_with < failed_without, (failed_with, failed_without)
