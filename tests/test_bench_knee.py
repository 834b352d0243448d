"""``benchmarks/bench_knee.py``: every ``--env`` setting reaches the demo; the monitor lines
parsed into the iterations the demo counts."""

from __future__ import annotations

import pytest
from conftest import benchmark_module


@pytest.fixture(scope="module")
def bench():
    """``benchmarks/bench_knee.py`` (standard library only)."""
    return benchmark_module("bench_knee")


def test_repeated_env_flags_add_up(bench):
    # a second --env used to replace the first: the run went without the first's settings
    args = bench.arguments(["--env", "A=1", "B=x=y", "--env", "C=", "--steps", "5"])
    assert bench.demo_settings(args.env) == {"A": "1", "B": "x=y", "C": ""}
    assert args.steps == 5
    assert bench.demo_settings(bench.arguments([]).env) == {}


@pytest.mark.parametrize("item", ["A", "=1"])
def test_an_env_item_that_is_not_key_value_is_refused(bench, item):
    with pytest.raises(SystemExit, match="KEY=VALUE"):
        bench.demo_settings(["A=1", item])


#: A step of the knee as monitored (its first 51 degrees in 17 steps, the step to 48 degrees): two
#: Newton solves (a pressure update between them), each resumed once after GMRES failed on a
#: kept factorisation; 8 Newton steps in all, as the demo's step line says.
STEP_MONITOR = """\
  0 SNES Function norm 3.857531404703e+03
      Line search: Using full step: old obj 7.440274269134e+06 new obj 2.192997191838e+02
  1 SNES Function norm 2.094276577646e+01
      Line search: Using full step: old obj 1.787033980064e+03 new obj 1.784442501718e+03
  2 SNES Function norm 9.251013445226e-01
    Linear knee_ solve did not converge due to DIVERGED_ITS iterations 20
  0 SNES Function norm 9.251013445226e-01
      Line search: Using full step: old obj 1.784442501718e+03 new obj 1.784433840770e+03
  1 SNES Function norm 5.032154523569e-02
      Line search: Using full step: old obj 1.784433840770e+03 new obj 1.784433736049e+03
  2 SNES Function norm 2.133893833748e-03
  0 SNES Function norm 8.233531634926e+01
      Line search: Using full step: old obj 1.819367219497e+03 new obj 1.799769493730e+03
  1 SNES Function norm 8.656908660944e+00
    Linear knee_ solve did not converge due to DIVERGED_ITS iterations 20
  0 SNES Function norm 8.656908660944e+00
      Line search: Using full step: old obj 1.799769493730e+03 new obj 1.799124925462e+03
  1 SNES Function norm 6.424065294987e-01
      Line search: Using full step: old obj 1.799124925462e+03 new obj 1.799120750349e+03
  2 SNES Function norm 1.872427619707e-02
      Line search: Using full step: old obj 1.799120750349e+03 new obj 1.799120745202e+03
  3 SNES Function norm 1.847627153306e-04
step  16  load 0.9412  newton  8 it  |r| 1.85e-04  cuts 0  active pairs 711
"""


def test_the_monitor_lines_count_the_steps_the_demo_counts(bench):
    """One iteration per Newton step taken: not the line after which GMRES failed (the solve
    goes on from there), nor a solve's converged state before a pressure update (counted once
    too many per update before)."""
    (attempts,) = bench.parse(STEP_MONITOR.splitlines())
    (attempt,) = attempts
    assert attempt.converged and attempt.linear_failures == 2
    assert attempt.linear_failed_iterations == 40  # (each failed GMRES ran to its limit of 20)
    assert attempt.linear_rate_stops == 0
    # the same step with its first failure stopped by the rate test at the 5th iteration
    stopped = STEP_MONITOR.replace("iterations 20", "iterations 5", 1).splitlines()
    ((early,),) = bench.parse(stopped)
    assert (early.linear_failures, early.linear_failed_iterations) == (2, 25)
    assert early.linear_rate_stops == 1
    assert len(attempt.iterations) == 8
    assert [it.solve_index for it in attempt.iterations] == [0] * 4 + [1] * 4
    assert attempt.iterations[3].residual_after == 2.133893833748e-03
    assert attempt.iterations[4].residual_before == 8.233531634926e01


def test_one_run_per_penalty_each_with_its_own_output_and_log(bench, tmp_path):
    """``--penalties``: one run per value, the penalty in the demo's environment and in the
    names of its output folder and log (two runs side by side must not share them); without
    it, the one run as before."""
    output = tmp_path / "knee"
    argv = ["--output", str(output), "--log", str(tmp_path / "run.log"), "--env", "A=1"]
    (single,) = bench.planned_runs(bench.arguments(argv), {"PETSC_OPTIONS": "-x"})
    assert single.output == output and single.log == str(tmp_path / "run.log")
    assert "MATDEPTH_KNEE_PENALTY" not in single.env and single.env["A"] == "1"
    assert single.env["PETSC_OPTIONS"] == "-x " + bench.MONITORS
    args = bench.arguments([*argv, "--penalties", "2", "2.000001", "--jobs", "2"])
    runs = bench.planned_runs(args, {})
    assert [run.penalty for run in runs] == ["2", "2.000001"]
    assert [run.env["MATDEPTH_KNEE_PENALTY"] for run in runs] == ["2", "2.000001"]
    assert [run.env["MATDEPTH_DEMO_OUTPUT"] for run in runs] == [str(run.output) for run in runs]
    assert len({run.output for run in runs}) == 2 and len({run.log for run in runs}) == 2
    assert all(run.env["A"] == "1" and run.output.parent == tmp_path for run in runs)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--penalties", "2", "two"], "numbers"),
        # (the usage line names --from-log too: the test looks for the reason)
        (["--penalties", "2", "--from-log", "x.log"], "reads one earlier run"),
        (["--jobs", "0"], "at least 1"),
    ],
)
def test_paths_arguments_that_cannot_run_are_refused(bench, argv, message, capsys):
    with pytest.raises(SystemExit):
        bench.arguments(argv)
    assert message in capsys.readouterr().err


def test_the_paths_table_gives_the_spread_of_the_iterations(bench):
    row = dict(converged=0, steps=50, cuts=0, at_limit=0, stalled=0, penetration=0.1, wall=1.0)
    rows = [dict(row, penalty=p, iterations=n) for p, n in (("2", 554), ("2.000001", 609))]
    lines = bench.paths_table(rows, 400)
    assert len(lines) == 3 + len(rows)  # a title, the header, the rows, the spread
    assert lines[2].split()[:2] == ["2", "554"] and lines[3].split()[:2] == ["2.000001", "609"]
    assert lines[-1] == "  iterations: mean 582, least 554, most 609 (target <= 400)"
    assert bench.paths_table(rows)[-1].endswith("most 609")
