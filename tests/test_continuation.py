"""Penalty continuation (fm.PenaltyContinuation): the operator's penalty setter, a press where a
large penalty fails without continuation and converges with it, the retry and restore logic."""

from __future__ import annotations

import types

from mpi4py import MPI

import numpy as np
import pytest
from test_hard_steps import _soft_block_press
from test_solvers import _touching_problem

import fenics_matdepth as fm
from fenics_matdepth.results import SolveResult


def _max_abs(comm, a: np.ndarray) -> float:
    return comm.allreduce(float(np.abs(a).max(initial=0.0)), op=MPI.MAX)


def test_penalty_setter_rescales_the_contact_terms():
    """Assigning ``contact.penalty`` at an unchanged ``u`` changes the next evaluation (the
    operator caches its pair terms per state): energy and forces are linear in eps."""
    comm = MPI.COMM_WORLD
    problem, g = _touching_problem(comm)
    g.x.array.reshape(-1, 3)[:, 2] = -0.02
    problem.solve()
    contact = problem.contact
    energy = contact.energy()
    forces = contact.force_resultants()
    assert energy > 0.0 and np.abs(forces).max() > 0.0
    contact.penalty = 3.0 * contact.penalty
    assert contact.penalty == 600.0
    assert contact.energy() == pytest.approx(3.0 * energy, rel=1e-12)
    assert np.allclose(contact.force_resultants(), 3.0 * forces, rtol=1e-12, atol=0.0)
    for bad in (0.0, -1.0, np.nan, np.inf):
        with pytest.raises(ValueError, match="penalty must be a positive number"):
            contact.penalty = bad
    assert contact.penalty == 600.0


def test_the_operator_owns_the_penalty():
    """``penalty_revision`` moves only when the value changes; ``penalty_set_to`` restores the
    penalty after its block, also when the block raises; a problem starts a solve on the last
    solve's factorisation only at the revision that solve converged at."""
    comm = MPI.COMM_WORLD
    problem, g = _touching_problem(comm)
    contact = problem.contact
    start, revision = contact.penalty, contact.penalty_revision
    contact.penalty = start
    assert contact.penalty_revision == revision
    with contact.penalty_set_to(2.0 * start) as op:
        assert op is contact and contact.penalty == 2.0 * start
        assert contact.penalty_revision == revision + 1
    assert contact.penalty == start and contact.penalty_revision == revision + 2
    with pytest.raises(RuntimeError, match="inside"):
        with contact.penalty_set_to(5.0 * start):
            raise RuntimeError("inside")
    assert contact.penalty == start
    with pytest.raises(ValueError, match="penalty must be a positive number"):
        with contact.penalty_set_to(-1.0):
            pass
    assert contact.penalty == start
    g.x.array.reshape(-1, 3)[:, 2] = -0.02
    assert problem.solve().converged
    assert problem._carried_revision == contact.penalty_revision


def _press(comm, factor: float, mesh=None, **snes_tolerances):
    """The soft block of tests/test_hard_steps.py at a penalty of ``factor`` E/h; returns the
    problem, the function setting the press for a load factor (1: one element height, 0.05)
    and the penalty of 10 E/h."""
    problem, g, _ = _soft_block_press(comm, "snes", mesh)
    if snes_tolerances:
        problem.snes.setTolerances(**snes_tolerances)
    mesh = problem.u.function_space.mesh
    problem.contact.penalty = fm.propose_penalty(mesh, 1.0, factor=factor)

    def set_load(t):
        g.x.array.reshape(-1, 3)[:, 2] = -0.05 * t

    return problem, set_load, fm.propose_penalty(mesh, 1.0, factor=10.0)


def test_continuation_converges_where_the_large_penalty_fails():
    """The soft block pressed by one element height in one solve at a penalty of 1e4 E/h, at
    most 20 Newton iterations per solve, to 3e-7 of the initial residual (the residual's
    rounding floor at this penalty is near 2e-8, 4e-8 relative; at a tolerance of 1e-7 the last
    stage crept along that floor and took 24 iterations on DOLFINx 0.11 on 2 ranks): the plain
    solve fails (after 20 iterations its residual was still 0.15 of its start, after 50
    iterations 0.03 to 0.1); continued from 10 E/h, four stages converge within the same 20
    iterations in all (measured 16 and 17 serially)."""
    comm = MPI.COMM_WORLD
    plain, set_load, _ = _press(comm, 1e4, rtol=3e-7, max_it=20)
    set_load(1.0)
    failed = plain.solve(raise_on_failure=False)
    assert not failed.converged
    assert failed.residual_norms[-1] > 1e-3 * failed.residual_norms[0]

    problem, set_load, start = _press(comm, 1e4, plain.u.function_space.mesh, rtol=3e-7, max_it=20)
    target = problem.contact.penalty
    tolerances = problem.snes.getTolerances()
    solver = fm.PenaltyContinuation(problem, start=start, growth=10.0)
    set_load(1.0)
    result = solver.solve()
    history = solver.history
    assert [s.penalty for s in history] == pytest.approx(
        [start, 10 * start, 100 * start, target], rel=1e-12
    )
    assert all(s.converged for s in history)
    assert sum(s.newton_iterations for s in history) == result.iterations <= 20
    # the last stage met the plain solve's tolerance: 3e-7 of the first stage's start
    assert result.residual_norms[-1] <= 3e-7 * result.residual_norms[0]
    assert problem.contact.penalty == target
    assert problem.snes.getTolerances() == tolerances  # the stage tolerances are undone
    assert history[-1].overlap == pytest.approx(problem.contact.max_penetration(), rel=1e-12)
    # the overlap fell with the penalty (about as 1 / eps once the contact zone is set)
    assert history[-1].overlap < 0.2 * history[0].overlap
    if comm.rank == 0:
        print(
            f"\nplain at 1e4 E/h: {failed.iterations} it, residual "
            f"{failed.residual_norms[-1] / failed.residual_norms[0]:.1e} of its start; "
            f"continuation: {solver.diagnostics()}"
        )


def test_continuation_in_load_steps_ends_on_the_plain_solution():
    """At 100 E/h: continuation inside solve_load_steps, one step, no cut, ends where the
    plain penalty ends after four load steps (absolute tolerance 1e-10: the residual's
    rounding floor here is near 5e-12, which a tolerance relative to a small step's initial
    residual fell below)."""
    comm = MPI.COMM_WORLD
    tolerances = {"rtol": 1e-8, "atol": 1e-10}
    plain, set_load, _ = _press(comm, 100.0, **tolerances)
    steps = fm.solve_load_steps(plain, set_load, num_steps=4, progress=False)
    assert steps[-1].load == 1.0
    problem, set_load, start = _press(comm, 100.0, plain.u.function_space.mesh, **tolerances)
    solver = fm.PenaltyContinuation(problem, start=start)
    continued = fm.solve_load_steps(solver, set_load, num_steps=1, progress=False)
    assert [(s.load, s.cuts) for s in continued] == [(1.0, 0)]
    assert continued[0].iterations == sum(s.newton_iterations for s in solver.history)
    assert len(solver.history) == 2 and problem.contact.penalty == plain.contact.penalty
    scale = _max_abs(comm, plain.u.x.array)
    assert scale >= 0.05
    # both solves stop at a residual of 1e-10, which moves a vertex by about 1e-10 / (E h)
    # = 2e-8 in the soft block (E = 0.1, h = 0.05); a penalty off by 10 % would move the
    # contact face by 10 % of the overlap, about 1e-6 (overlap 1.6e-5 at 100 E/h)
    difference = _max_abs(comm, problem.u.x.array - plain.u.x.array)
    assert difference <= 1e-6 * scale
    if comm.rank == 0:
        print(
            f"\nplain at 100 E/h: 4 steps, {sum(s.cuts for s in steps)} cuts, "
            f"{sum(s.iterations for s in steps)} Newton it; continuation: one step, "
            f"{continued[0].iterations} it; largest difference {difference:.1e}"
        )


class _FailsOnLargeJumps:
    """Wraps a problem; a solve at a penalty below ``fail_below`` or more than ``limit`` times
    the last converged one fails (leaving NaN in u, as a diverged solve would); a converged
    one adds 1 to u."""

    def __init__(self, problem, limit: float, fail_below: float = 0.0):
        self.u, self.contact = problem.u, problem.contact
        self.limit, self.fail_below = limit, fail_below
        self.converged_penalty = None
        self.start_states: list[np.ndarray] = []
        self.penalties: list[float] = []

    def solve(self, raise_on_failure: bool = True) -> SolveResult:
        eps = self.contact.penalty
        self.start_states.append(self.u.x.array.copy())
        self.penalties.append(eps)
        last = self.converged_penalty
        if eps < self.fail_below or (last is not None and eps > self.limit * last * (1 + 1e-12)):
            self.u.x.array[:] = np.nan
            return SolveResult(False, -5, 50, np.array([1.0, 0.5]))
        self.u.x.array[:] += 1.0
        self.converged_penalty = eps
        return SolveResult(True, 2, 3, np.array([1.0, 1e-12]))


def test_failed_stage_is_retried_with_a_smaller_growth():
    """growth 10, a problem that fails for jumps above 4: the jump 1 -> 10 fails, is retried as
    1 -> sqrt(10) from the converged stage, and the rest goes on with growth sqrt(10)."""
    comm = MPI.COMM_WORLD
    problem, _ = _touching_problem(comm)
    start = problem.u.x.array.copy()
    fake = _FailsOnLargeJumps(problem, limit=4.0)
    solver = fm.PenaltyContinuation(fake, start=1.0, growth=10.0, target=1000.0)
    result = solver.solve()
    expected = [1.0, 10.0] + [10.0 ** (k / 2) for k in range(1, 7)]
    assert result.converged
    assert fake.penalties == pytest.approx(expected, rel=1e-12)
    assert [s.penalty for s in solver.history] == pytest.approx(expected, rel=1e-12)
    assert [s.converged for s in solver.history] == [True, False] + [True] * 6
    assert result.iterations == 7 * 3 + 50
    assert solver.total_retries == 1 and solver.total_stages == 8
    assert problem.contact.penalty == 1000.0
    # each stage started from the last converged one (never from the failed NaN state)
    assert all(np.all(np.isfinite(s)) for s in fake.start_states)
    assert np.array_equal(problem.u.x.array, start + 7.0)


def test_failed_first_stage_starts_higher():
    """A first stage that fails (here below 50) is retried from the starting state one growth
    factor higher; the target itself is the last try."""
    comm = MPI.COMM_WORLD
    problem, _ = _touching_problem(comm)
    problem.u.x.array[:] = 0.5
    fake = _FailsOnLargeJumps(problem, limit=np.inf, fail_below=50.0)
    solver = fm.PenaltyContinuation(fake, start=1.0, growth=10.0, target=1000.0)
    assert solver.solve().converged
    assert fake.penalties == pytest.approx([1.0, 10.0, 100.0, 1000.0], rel=1e-12)
    assert all(np.all(s == 0.5) for s in fake.start_states[:3])  # each first try from the start
    assert np.all(problem.u.x.array == 2.5)
    fake = _FailsOnLargeJumps(problem, limit=np.inf, fail_below=2000.0)
    solver = fm.PenaltyContinuation(fake, start=1.0, growth=10.0, target=1000.0)
    assert not solver.solve(raise_on_failure=False).converged
    assert fake.penalties == pytest.approx([1.0, 10.0, 100.0, 1000.0], rel=1e-12)
    assert np.all(problem.u.x.array == 2.5)


def test_failure_restores_the_state_and_the_penalty():
    """Retries down to growth 1.33 < min_growth 1.5 all fail: u is back where the solve began,
    the penalty is the target, and raise_on_failure raises with the stages tried."""
    comm = MPI.COMM_WORLD
    problem, _ = _touching_problem(comm)
    problem.u.x.array[:] = 0.25
    fake = _FailsOnLargeJumps(problem, limit=1.2)
    solver = fm.PenaltyContinuation(fake, start=1.0, growth=10.0, target=1000.0, min_growth=1.5)
    result = solver.solve(raise_on_failure=False)
    assert not result.converged
    assert fake.penalties == pytest.approx([1.0, 10.0, 10**0.5, 10**0.25], rel=1e-12)
    assert np.all(problem.u.x.array == 0.25)
    assert problem.contact.penalty == 1000.0
    with pytest.raises(RuntimeError, match="penalty continuation to 1000 failed"):
        solver.solve()
    assert np.all(problem.u.x.array == 0.25)
    assert problem.contact.penalty == 1000.0


def test_damping_only_in_the_first_stage():
    """Wrapping a RigidModeDamping, the first stage runs the damped solves (falling k, then
    k = 0) and the later stages the undamped problem alone: contact holds the body by then."""
    comm = MPI.COMM_WORLD
    problem, _ = _touching_problem(comm)
    fake = _FailsOnLargeJumps(problem, limit=np.inf)
    stiffness = types.SimpleNamespace(value=1.0)
    anchor = types.SimpleNamespace(x=types.SimpleNamespace(array=problem.u.x.array.copy()))
    seen = []
    solve = fake.solve

    def recording_solve(raise_on_failure=True):
        seen.append(stiffness.value)
        return solve(raise_on_failure)

    fake.solve = recording_solve
    damped = fm.RigidModeDamping(fake, stiffness, anchor, decrease=0.1)
    solver = fm.PenaltyContinuation(damped, start=1.0, growth=10.0, target=100.0)
    assert solver.solve().converged
    # each fake solve moves u by 1: the damped solves never settle (step 1 of a total j + 1)
    # and stop once the next k would fall below 1e-6 of its start, after 7 (k = 1 to 1e-6);
    # then one undamped solve
    first = [0.1**j for j in range(7)] + [0.0]
    assert seen == pytest.approx(first + [0.0, 0.0], rel=1e-12, abs=0.0)
    assert fake.penalties == pytest.approx([1.0] * 8 + [10.0, 100.0], rel=1e-12)
    assert [s.newton_iterations for s in solver.history] == [8 * 3, 3, 3]


class _HeldWhile:
    """Wraps a problem; records the damping stiffness of each solve; a solve with k = 0 fails
    (NaN in u, as a diverged solve) while ``free`` (the body not held by contact), any other
    adds 1 to u."""

    def __init__(self, problem, stiffness):
        self.u, self.contact, self.stiffness = problem.u, problem.contact, stiffness
        self.free = False
        self.seen: list[float] = []

    def solve(self, raise_on_failure: bool = True) -> SolveResult:
        self.seen.append(self.stiffness.value)
        if self.stiffness.value == 0.0 and self.free:
            self.u.x.array[:] = np.nan
            return SolveResult(False, -5, 50, np.array([1.0, 0.5]))
        self.u.x.array[:] += 1.0
        return SolveResult(True, 2, 3, np.array([1.0, 1e-12]))


def test_damping_only_until_contact_holds_the_body():
    """RigidModeDamping: the first call runs the damped solves (falling k) and the undamped one;
    after a converged call the next solves the undamped problem alone; where that fails (the
    body came free) the start is restored and the damped solves run again from it."""
    comm = MPI.COMM_WORLD
    problem, _ = _touching_problem(comm)
    start = problem.u.x.array.copy()
    stiffness = types.SimpleNamespace(value=1.0)
    anchor = types.SimpleNamespace(x=types.SimpleNamespace(array=problem.u.x.array.copy()))
    fake = _HeldWhile(problem, stiffness)
    damped = fm.RigidModeDamping(fake, stiffness, anchor, decrease=0.1)
    # each fake solve moves u by 1: the damped solves never settle and stop after 7 (k = 1 to
    # 1e-6); then one undamped solve
    sequence = [0.1**j for j in range(7)] + [0.0]
    first = damped.solve()
    assert first.converged and first.iterations == 8 * 3 and damped.damped_solves == 7
    assert fake.seen == pytest.approx(sequence, rel=1e-12, abs=0.0)
    fake.seen.clear()
    second = damped.solve()
    assert second.converged and second.iterations == 3 and damped.damped_solves == 0
    assert fake.seen == [0.0]
    assert np.array_equal(problem.u.x.array, start + 9.0)
    fake.seen.clear()
    fake.free = True
    with pytest.raises(RuntimeError):
        damped.solve()  # the undamped try fails, then the damped ones end in a failing k = 0
    assert fake.seen == pytest.approx([0.0] + sequence, rel=1e-12, abs=0.0)
    assert not damped.held
    fake.seen.clear()
    fake.free = False
    problem.u.x.array[:] = start  # as solve_load_steps restores a failed step's start
    third = damped.solve()  # not held after a failure: damped solves first
    assert fake.seen == pytest.approx(sequence, rel=1e-12, abs=0.0)
    assert third.converged and np.all(np.isfinite(problem.u.x.array))
    assert stiffness.value == 0.0
    stiffness.value = 1.0  # the k to start from, read by the constructor
    never = fm.RigidModeDamping(fake, stiffness, anchor, decrease=0.1, undamped_first=False)
    never.solve()
    fake.seen.clear()
    never.solve()
    assert fake.seen == pytest.approx(sequence, rel=1e-12, abs=0.0)
