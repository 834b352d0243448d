"""Automatic step control of load stepping (fm.StepControl): the next step scaled towards a
target number of Newton iterations, and attempts stopped by a rate test before their
iteration limit."""

from __future__ import annotations

from mpi4py import MPI
from petsc4py import PETSc

import numpy as np
import pytest
from conftest import min_det_F
from test_hard_steps import _indented_block

import fenics_matdepth as fm
from fenics_matdepth.snes_callbacks import SLOW_CONVERGENCE_REASON
from fenics_matdepth.step_control import SlowConvergence, find_contact_problem


def _judge(test: SlowConvergence, norms, target: float) -> int | None:
    """The iteration at which ``test`` stops a solve with these residual norms, or None."""
    for k, norm in enumerate(norms):
        if test(k, norm, target):
            return k
    return None


def test_rate_test_against_the_predicted_iterations():
    """A residual falling linearly by 0.5 an iteration needs 34 iterations from 1 to 1e-10:
    with 20 allowed it is stopped at the first check (iteration 4: 4 + log(1e-10 / 2**-4) /
    log(0.5) = 33.2 > 20), with 40 never; a residual falling by 0.1 an iteration (10 in all)
    is never stopped; a stagnating one is stopped at the first check. A solve entering its
    quadratic range is judged by its last iteration's rate: from iteration 6 (0.1 an
    iteration, 8 more to 1e-10: 14) it passes with 16 allowed and is stopped with 12."""
    halving = [0.5**k for k in range(60)]
    stopped = SlowConvergence(4, 20, 4)
    assert _judge(stopped, halving, 1e-10) == 4
    assert "30 more iterations" in stopped.message  # the test's own prediction: 29.2 more
    assert _judge(SlowConvergence(4, 40, 4), halving, 1e-10) is None
    assert _judge(SlowConvergence(4, 20, 4), [0.1**k for k in range(11)], 1e-10) is None
    flat = [1.0, 0.5, 0.4] + [0.39] * 30
    test = SlowConvergence(6, 30, 3)
    assert _judge(test, flat, 1e-10) == 6
    assert "no number of iterations" in test.message and test.stops == 1
    quadratic = [1.0, 0.9, 0.7, 0.5, 0.3, 1e-1, 1e-2, 1e-4, 1e-8, 1e-16]
    assert _judge(SlowConvergence(6, 16, 3), quadratic, 1e-10) is None
    assert _judge(SlowConvergence(6, 12, 3), quadratic, 1e-10) == 6
    # a new solve (iteration 0) clears the message; the same test judges it afresh
    assert not test(0, 1.0, 1e-10) and test.message == ""


def test_rate_test_stops_at_most_stops_per_step_solves_of_a_step():
    """With stops_per_step 1 the rate test stops the first stagnating solve of a step and lets
    the retries of that step run (a limit point of the load path: cutting on does not help);
    a new step is judged again. None: every solve is judged."""
    flat = [1.0, 0.5, 0.4] + [0.39] * 30
    test = SlowConvergence(6, 30, 3, stops_per_step=1)
    assert _judge(test, flat, 1e-10) == 6 and test.step_stops == 1
    assert not test.judging
    assert _judge(test, flat, 1e-10) is None  # the retry runs to its own limit
    assert test.stops == 1
    test.new_step()
    assert test.judging and _judge(test, flat, 1e-10) == 6 and test.stops == 2
    unlimited = SlowConvergence(6, 30, 3)
    assert [_judge(unlimited, flat, 1e-10) for _ in range(3)] == [6, 6, 6]
    assert fm.StepControl(10).rate_test().stops_per_step == 1  # the default
    assert fm.StepControl(10, stops_per_step=None).rate_test().stops_per_step is None
    with pytest.raises(ValueError, match="stops_per_step"):
        fm.StepControl(10, stops_per_step=0)


def test_step_scaling_and_bad_settings():
    """sqrt(target / iterations), between 1 / max_growth and max_growth; settings that cannot
    work are refused, naming the fix."""
    control = fm.StepControl(target_iterations=9)
    assert control.scale(4) == pytest.approx(1.5)
    assert control.scale(36) == pytest.approx(0.5)
    assert control.scale(100) == 0.5 and control.scale(1) == 2.0 and control.scale(0) == 2.0
    assert control.max_iterations == 27
    assert fm.StepControl(10, stop_iterations=15).max_iterations == 15
    with pytest.raises(ValueError, match="raise target_iterations or lower window"):
        fm.StepControl(target_iterations=2, window=4)
    with pytest.raises(ValueError, match="at least the target"):
        fm.StepControl(target_iterations=10, stop_iterations=5)
    with pytest.raises(ValueError, match="max_growth"):
        fm.StepControl(max_growth=0.5)
    # min_scale = 1: a hard converged step does not shrink the next one
    keep = fm.StepControl(target_iterations=9, min_scale=1.0)
    assert keep.scale(36) == 1.0 and keep.scale(4) == pytest.approx(1.5)
    assert fm.StepControl(target_iterations=9, min_scale=0.8).scale(36) == pytest.approx(0.8)
    with pytest.raises(ValueError, match="min_scale"):
        fm.StepControl(min_scale=1.5)
    with pytest.raises(TypeError, match="StepControl"):
        fm.solve_load_steps(None, lambda t: None, step_control={"target_iterations": 5})


class _Recorder:
    """A wrapper of a problem (found through ``problem``) keeping every attempt's result."""

    def __init__(self, problem):
        self.problem, self.u, self.contact = problem, problem.u, problem.contact
        self.results = []

    def solve(self, raise_on_failure: bool = True):
        result = self.problem.solve(raise_on_failure=False)
        self.results.append(result)
        return result


def test_attempt_stopped_early_then_the_step_grows_back():
    """The indented block of test_hard_steps pressed 0.4 deep (80 % of its thickness), held
    from load 1 to 2, in two nominal steps, with a step control allowing 6 iterations: one
    solve takes 9 (test_hard_steps), so the first attempt is stopped by the rate test at its
    6th iteration (its SNES limit is 50) and the step cut; once the indentation is held the
    steps converge at once and grow back (doubling) to the nominal step. The end state is the
    one-step solve's."""
    comm = MPI.COMM_WORLD
    reference = _indented_block(comm, "snes", 0.4)
    assert reference.solve().iterations > 6

    problem = _indented_block(comm, "snes", 0.0)
    g = problem.bcs[1].g

    def set_load(t):
        g.x.array.reshape(-1, 3)[:, 2] = -0.4 * min(t, 1.0)

    recorder = _Recorder(problem)
    assert find_contact_problem(recorder) is problem
    control = fm.StepControl(target_iterations=6, stop_iterations=6, window=2)
    steps = fm.solve_load_steps(
        recorder, set_load, num_steps=2, end=2.0, progress=False, step_control=control
    )
    assert problem.stop_test is None  # set for the run only
    stopped = [r for r in recorder.results if r.reason == SLOW_CONVERGENCE_REASON]
    assert stopped and recorder.results[0] in stopped
    assert all(r.iterations == 6 and not r.converged for r in stopped)
    assert len(stopped) == sum(s.cuts for s in steps)  # each cut by the rate test
    assert all(s.iterations <= 6 for s in steps)
    loads = np.array([0.0] + [s.load for s in steps])
    increments = np.diff(loads)
    assert np.isclose(loads[-1], 2.0) and increments[0] < 1.0
    # the steps ending where the indentation is held, but the last (cut to reach the end)
    held = increments[:-1][loads[1:-1] > 1.0 + 1e-12]
    assert np.all(held[1:] >= held[:-1] - 1e-12)
    assert np.any(held[1:] > 1.5 * held[:-1])  # it grew back
    assert np.all(increments <= 1.0 + 1e-12)  # never beyond the nominal step
    assert all(s.diagnostics["min_det_F"] > 0.0 for s in steps)
    # (two meshes, partitioned independently on several ranks: compared by global norms)
    for norm in (PETSc.NormType.NORM_2, PETSc.NormType.NORM_INFINITY):
        a, b = reference.u.x.petsc_vec.norm(norm), problem.u.x.petsc_vec.norm(norm)
        assert abs(a - b) <= 1e-6 * a, (norm, a, b)
    assert min_det_F(problem.u) > 0.0


def test_a_step_slow_at_half_its_increment_is_let_run():
    """A rate test stopping every solve not converged at its 3rd iteration (target 3, stop 3,
    window 1; the block indented 0.3 takes more at its first steps): with one stop a step (the
    default) a stopped attempt's retry at half the increment runs to convergence (4
    iterations), and the run ends with at most one cut a step; judging every attempt, a step
    whose retries need more than 3 however small the increment is cut until load stepping gives
    up: the stall the default avoids."""
    comm = MPI.COMM_WORLD
    for stops_per_step in (1, None):
        problem = _indented_block(comm, "snes", 0.0)
        g = problem.bcs[1].g

        def set_load(t, g=g):
            g.x.array.reshape(-1, 3)[:, 2] = -0.3 * t

        recorder = _Recorder(problem)
        control = fm.StepControl(3, stop_iterations=3, window=1, stops_per_step=stops_per_step)
        settings = dict(num_steps=2, progress=False, step_control=control)
        if stops_per_step == 1:
            steps = fm.solve_load_steps(recorder, set_load, **settings)
            assert np.isclose(steps[-1].load, 1.0)
            assert all(s.cuts <= 1 for s in steps) and sum(s.cuts for s in steps) >= 1
            stopped = [r for r in recorder.results if r.reason == SLOW_CONVERGENCE_REASON]
            assert len(stopped) == sum(s.cuts for s in steps)
            # the retries were not judged: some of them needed more than the 3 allowed
            assert any(s.iterations > 3 for s in steps if s.cuts)
        else:
            with pytest.raises(RuntimeError, match=r"load stepping stopped.*rate test"):
                fm.solve_load_steps(recorder, set_load, min_step=0.5 / 8, **settings)
            stopped = [r for r in recorder.results if r.reason == SLOW_CONVERGENCE_REASON]
            assert recorder.results[-1].reason == SLOW_CONVERGENCE_REASON and len(stopped) > 2
        problem.destroy()
