"""The knee's Newton iterations, attributed: where the iterations of a flexion go.

Runs ``demos/demo_knee.py`` (the coarse leg) in a subprocess with PETSc's SNES, line-search and
KSP monitors on, reads the monitor lines of every attempt (converged or cut) and the demo's
``knee.json``, and prints

- the Newton iterations of each step, failed attempts included, and the total;
- each iteration attributed to one cause: a full step the line search had to shorten because
  the trial state was inadmissible (an element inverted: det F <= 0, the residual NaN), a step
  the merit function shortened, a full Newton step in the quadratic range (the residual fell at
  least tenfold) or outside it (slow: the model changed under the step, e.g. contact entering),
  and the iterations of attempts that were then cut, and of the augmented Lagrangian's solves
  after the first one of a step (pressure updates);
- the targets of issue #42: the first 30° in 10 steps in at most 60 iterations with no step over
  10; the full 150° in at most 400 with no attempt reaching the iteration limit, in at most
  3 minutes; and the demo's own checks (penetration, lowest det F, the patella, the fold).

Run: ``scripts/fenicsx python3 benchmarks/bench_knee.py [--degrees 30 --steps 10]
[--predictor extrapolate|rotation|0] [--processes 2] [--env KEY=VALUE ...] [--log FILE]``
(defaults: the first 30° in 10 steps, the demo's predictor; ``--log`` keeps every monitor line,
e.g. to count the iterations a solve spends below a tolerance). ``--degrees 150 --steps 50``
is the full demo. ``--penalties 2 2.000001 1.999999 2.000002 [--jobs 2]`` runs the demo once
per penalty (each in its own output folder and log, named with the penalty): a change of one
part in a million parts the paths by rounding, and the late steps' iteration counts move by
tens with the path, so one run cannot judge a remedy; a table of the runs follows their
figures. Prints figures; asserts nothing about time.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import contextlib
import dataclasses
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

from fenics_matdepth.linear_solver import KEPT_MAX_ITERATIONS

HERE = Path(__file__).resolve().parent
DEMO = HERE.parent / "demos" / "demo_knee.py"

#: the issue's targets
TARGET_30_ITERATIONS, TARGET_30_STEP_MAX = 60, 10
TARGET_150_ITERATIONS, TARGET_150_SECONDS = 400, 180.0

MONITORS = "-knee_snes_monitor -knee_snes_linesearch_monitor -knee_ksp_converged_reason"
ITERATION = re.compile(r"^\s*(\d+) SNES Function norm\s+(\S+)")
LAMBDA = re.compile(r"(?<![a-z])lambda=\s*([^\s,]+)")
STEP = re.compile(r"^step\s+(\d+)\s+load\s+(\S+)\s+newton\s+(\d+) it")
FAILED = re.compile(r"the step to .* deg failed")
LINEAR_ITERATIONS = re.compile(r"Linear .* solve did not converge due to \S+ iterations (\d+)")


@dataclasses.dataclass
class Iteration:
    """One Newton iteration as the monitors showed it."""

    residual_before: float
    residual_after: float = float("nan")
    nan_cuts: int = 0  # trial states the line search found inadmissible
    step_length: float = 1.0
    solve_index: int = 0  # 0: the attempt's first Newton solve; > 0: after a pressure update


@dataclasses.dataclass
class Attempt:
    """The Newton iterations of one attempt at a step (converged, or cut afterwards)."""

    iterations: list[Iteration] = dataclasses.field(default_factory=list)
    linear_failures: int = 0
    linear_failed_iterations: int = 0  # the GMRES iterations of those failed linear solves
    linear_rate_stops: int = 0  # of those, stopped before their limit (linear_solver.KeptRateTest)
    converged: bool = False
    stopped_early: bool = False  # by the step control's rate test (reason DIVERGED_DTOL)


def parse(lines: list[str]) -> list[list[Attempt]]:
    """The monitor lines grouped into steps, each a list of attempts (the last converged)."""
    steps: list[list[Attempt]] = []
    attempts: list[Attempt] = [Attempt()]
    current: Iteration | None = None
    solve_index = -1
    after_linear_failure = False
    for line in lines:
        m = ITERATION.match(line)
        if m:
            k, norm = int(m.group(1)), float(m.group(2))
            if k == 0 and not after_linear_failure:
                # a new solve (after a pressure update): the last one's final line was its
                # converged state, from which no step was taken
                solve_index += 1
                current = None
            if current is not None:
                current.residual_after = norm
                attempts[-1].iterations.append(current)
                current = None
            after_linear_failure = False
            current = Iteration(norm, solve_index=solve_index)
            continue
        if current is None:
            continue
        if "is Inf or Nan" in line:
            current.nan_cuts += 1
        elif "Using full step" in line:
            current.step_length = 0.5**current.nan_cuts
        elif "lambda=" in line:
            current.step_length = float(LAMBDA.search(line).group(1))
        elif "did not converge" in line and "Linear" in line:
            attempts[-1].linear_failures += 1
            gmres = LINEAR_ITERATIONS.search(line)
            if gmres:
                iterations = int(gmres.group(1))
                attempts[-1].linear_failed_iterations += iterations
                attempts[-1].linear_rate_stops += iterations < KEPT_MAX_ITERATIONS
            after_linear_failure = True
            current = None  # the solve restarts from this iterate: no Newton step taken
        if FAILED.search(line) or STEP.match(line):
            current = None
            if STEP.match(line):
                attempts[-1].converged = True
                steps.append(attempts)
                attempts = [Attempt()]
            else:
                attempts[-1].stopped_early = "DIVERGED_DTOL" in line
                attempts.append(Attempt())
            solve_index = -1
    return steps


def attribute(steps: list[list[Attempt]]) -> dict[str, int]:
    """Each iteration's cause (see the module docstring)."""
    causes = dict.fromkeys(
        ("inadmissible full step", "merit-shortened step", "quadratic full step",
         "slow full step", "in attempts then cut", "augmented-Lagrangian re-solves"), 0,
    )  # fmt: skip
    for attempts in steps:
        for attempt in attempts:
            for it in attempt.iterations:
                if not attempt.converged:
                    causes["in attempts then cut"] += 1
                elif it.solve_index > 0:
                    causes["augmented-Lagrangian re-solves"] += 1
                elif it.nan_cuts:
                    causes["inadmissible full step"] += 1
                elif it.step_length < 1.0:
                    causes["merit-shortened step"] += 1
                elif it.residual_after <= 0.1 * it.residual_before:
                    causes["quadratic full step"] += 1
                else:
                    causes["slow full step"] += 1
    return causes


def run_demo(
    command: list[str], env: dict, log_path: str | None, lines: list[str], echo: bool = True
) -> None:
    """Run the demo, appending its output lines to ``lines``; print its own progress lines
    (with ``echo``) and write every line to ``log_path`` (if given) as it comes, so that a run
    stopped or killed keeps them."""
    keep = open(log_path, "w") if log_path else contextlib.nullcontext()
    with (
        keep as log,
        subprocess.Popen(
            command, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
        ) as run,
    ):
        for line in run.stdout:
            lines.append(line.rstrip("\n"))
            if log is not None:
                log.write(line)
                log.flush()
            progress = not line.lstrip().startswith(("Line", "Linear"))
            if echo and progress and not ITERATION.match(line):
                print(line, end="", flush=True)  # the demo's own progress lines


def demo_settings(items: list[str]) -> dict[str, str]:
    """The ``--env`` items as a dict; an item that is not KEY=VALUE is an error."""
    settings = {}
    for item in items:
        key, equals, value = item.partition("=")
        if not key or not equals:
            raise SystemExit(f"--env takes KEY=VALUE items, got {item!r}")
        settings[key] = value
    return settings


def arguments(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line (``argv``, default ``sys.argv[1:]``)."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--degrees", type=float, default=30.0)
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--predictor", default=None, help="MATDEPTH_KNEE_PREDICTOR")
    parser.add_argument("--processes", type=int, default=1)
    # (extend: a second --env adds to the first instead of replacing it)
    parser.add_argument(
        "--env", nargs="+", action="extend", default=[], help="more KEY=VALUE for the demo"
    )
    parser.add_argument("--output", default=None, help="the demo's output folder")
    parser.add_argument(
        "--log", default=None, help="write the demo's whole output (monitors included) here"
    )
    parser.add_argument(
        "--from-log",
        default=None,
        help="no run: the figures of an earlier run from its --log file and --output folder",
    )
    parser.add_argument(
        "--penalties",
        nargs="+",
        default=None,
        help="one run per penalty (MPa/mm), e.g. 2 2.000001 1.999999 2.000002: the paths "
        "parted by rounding, their figures side by side",
    )
    parser.add_argument("--jobs", type=int, default=1, help="with --penalties: runs at a time")
    args = parser.parse_args(argv)
    if args.penalties is not None:
        if args.from_log:
            parser.error("--penalties runs the demo; --from-log reads one earlier run")
        for penalty in args.penalties:
            try:
                float(penalty)
            except ValueError:
                parser.error(f"--penalties takes numbers, got {penalty!r}")
    if args.jobs < 1:
        parser.error(f"--jobs is at least 1, got {args.jobs}")
    return args


@dataclasses.dataclass
class Run:
    """One run of the demo: its settings, where it writes, and (once run) its output."""

    env: dict
    output: Path
    log: str | None
    penalty: str | None = None
    lines: list[str] = dataclasses.field(default_factory=list)
    wall: float = float("nan")


def planned_runs(args: argparse.Namespace, environ: dict) -> list[Run]:
    """The demo's runs the command line asks for: one, or one per ``--penalties`` value, each
    with its own output folder and log (the penalty appended to their names)."""
    tag = f"{args.degrees:g}deg_{args.steps}steps_{args.processes}p"
    output = Path(args.output or HERE / "output" / f"knee_{tag}").resolve()
    env = dict(environ)
    env.update(
        MATDEPTH_KNEE_DEGREES=str(args.degrees),
        MATDEPTH_KNEE_STEPS=str(args.steps),
        MATDEPTH_DEMO_OUTPUT=str(output),
        PETSC_OPTIONS=(env.get("PETSC_OPTIONS", "") + " " + MONITORS).strip(),
    )
    if args.predictor is not None:
        env["MATDEPTH_KNEE_PREDICTOR"] = args.predictor
    env.update(demo_settings(args.env))
    if args.penalties is None:
        return [Run(env, output, args.log)]
    runs = []
    for penalty in args.penalties:
        folder = output.with_name(f"{output.name}_penalty{penalty}")
        log = f"{args.log}.penalty{penalty}" if args.log else None
        settings = dict(env, MATDEPTH_KNEE_PENALTY=penalty, MATDEPTH_DEMO_OUTPUT=str(folder))
        runs.append(Run(settings, folder, log, penalty))
    return runs


def execute(run: Run, command: list[str], echo: bool) -> None:
    """Run the demo for ``run``, keeping its output lines and wall time."""
    tic = time.perf_counter()
    run_demo(command, run.env, run.log, run.lines, echo)
    run.wall = time.perf_counter() - tic


def paths_table(rows: list[dict], target: int | None = None) -> list[str]:
    """The lines comparing the runs of ``--penalties`` (``report``'s figures of each), with
    the iterations' mean, least and most (and the ``target`` of iterations, if given)."""
    lines = ["paths (one run per penalty; the rounding parts them):",
             "  penalty      iterations  converged  steps  cuts  at limit  stalled  "
             "penetration  wall"]  # fmt: skip
    for row in rows:
        lines.append(
            f"  {row['penalty']:<12s} {row['iterations']:10d} {row['converged']:10d} "
            f"{row['steps']:6d} {row['cuts']:5d} {row['at_limit']:9d} {row['stalled']:8d}  "
            f"{row['penetration']:9.3f} h {row['wall']:5.0f} s"
        )
    counts = [row["iterations"] for row in rows]
    if counts:
        goal = f" (target <= {target})" if target is not None else ""
        lines.append(f"  iterations: mean {sum(counts) / len(counts):.0f}, least {min(counts)}, "
                     f"most {max(counts)}{goal}")  # fmt: skip
    return lines


def main() -> None:
    args = arguments()
    runs = planned_runs(args, dict(os.environ))
    command = [sys.executable, str(DEMO)]
    if args.processes > 1:
        command = ["mpirun", "-n", str(args.processes), *command]
    if args.from_log:
        (run,) = runs
        run.lines = Path(args.from_log).read_text().splitlines()
    else:
        echo = len(runs) == 1 or args.jobs == 1
        with concurrent.futures.ThreadPoolExecutor(max_workers=args.jobs) as pool:
            for done in [pool.submit(execute, run, command, echo) for run in runs]:
                done.result()
    rows = [report(args, run) for run in runs]
    if args.penalties is not None:
        print()
        target = TARGET_150_ITERATIONS if args.degrees == 150.0 else None
        print("\n".join(paths_table(rows, target)))


def report(args: argparse.Namespace, run: Run) -> dict:
    """Print the figures of one run; return those ``paths_table`` compares."""
    env, output, lines, wall = run.env, run.output, run.lines, run.wall
    if (output / "knee.json").exists():
        summary = json.loads((output / "knee.json").read_text())
    else:  # the demo was killed: the iterations from its monitor lines only
        print(f"\n(no {output / 'knee.json'}: the demo did not finish; figures from its output)")
        nan = float("nan")
        summary = dict(
            max_newton_iterations=int(env.get("MATDEPTH_KNEE_MAX_IT", 200)),  # the demo's default
            reached_degrees=nan, completed=False, steps=[], seconds=nan, solve_seconds=nan,
            time_split=dict(force_stiffness=nan, contact_update=nan, linear_solve=nan),
        )  # fmt: skip

    if args.from_log:  # the run's own time, not the reading's
        wall = summary["seconds"]
    steps = parse(lines)
    per_step = [sum(len(a.iterations) for a in attempts) for attempts in steps]
    converged_only = [len(attempts[-1].iterations) for attempts in steps]
    total = sum(per_step)
    causes = attribute(steps)
    limit = summary["max_newton_iterations"]
    at_limit = sum(
        1
        for attempts in steps
        for a in attempts
        if not a.converged and len(a.iterations) >= limit
    )  # fmt: skip
    cuts = sum(len(a) - 1 for a in steps)
    worst_pen = max((m["penetration_over_h"] for m in summary["steps"]), default=float("nan"))
    print()
    print(f"knee {args.degrees:g} deg in {args.steps} steps on {args.processes} process(es); "
          f"predictor {env.get('MATDEPTH_KNEE_PREDICTOR', '0')}; step control: target "
          f"{summary.get('target_iterations', 0)}, stop at {summary.get('stop_iterations')} "
          f"iterations; augmented Lagrangian to {summary.get('augmented_tol_h')} h, penalty "
          f"{summary.get('penalty')} MPa/mm; fibre toe "
          f"{summary.get('fibre_toe', 0.0)}; pairs that left kept in the Jacobian: "
          f"{summary.get('keep_left_pairs', False)}; Newton atol "
          f"{summary.get('newton_atol', 1e-8):g} N; pseudo-transient sigma0 "
          f"{summary.get('pseudo_transient', 0.0):g}")  # fmt: skip
    print(f"  reached {summary['reached_degrees']:.1f} deg, completed {summary['completed']}, "
          f"{len(steps)} steps, {cuts} cuts")  # fmt: skip
    print(f"  Newton iterations: {total} in all (failed attempts included), per step "
          f"{per_step}")  # fmt: skip
    print(f"  converged attempts only: {sum(converged_only)}, per step {converged_only}")
    stopped = [len(a.iterations) for s in steps for a in s if a.stopped_early]
    print(
        f"  attempts reaching the limit of {limit}: {at_limit}; stopped early by the step "
        f"control's rate test: {len(stopped)} (after {stopped} iterations); linear-solver "
        f"failures (GMRES on a kept factorisation): "
        f"{sum(a.linear_failures for s in steps for a in s)} "
        f"({sum(a.linear_failed_iterations for s in steps for a in s)} GMRES iterations; "
        f"{sum(a.linear_rate_stops for s in steps for a in s)} stopped by their rate)"
    )
    print("  iterations by cause:")
    for cause, count in causes.items():
        print(f"    {cause:32s} {count:5d}  ({100 * count / max(total, 1):.0f} %)")
    off = [m.get("steps_off_dirichlet") for m in summary["steps"]]
    if off and None not in off:
        attempts = sum(len(a) for a in steps)
        print(f"  Newton steps begun with a Dirichlet dof off its value: {sum(off)}, "
              f"{sum(off) - attempts} after the first of each of the {attempts} attempts; per "
              f"step {off}")  # fmt: skip
    if "shift_factorisations" in summary:
        print(f"  factorisations of shifted Jacobians (J + mu I, every rung tried): "
              f"{summary['shift_factorisations']}")  # fmt: skip
    if "reversed_steps" in summary:
        print(f"  Newton steps reversed at a saddle (uphill_step {summary['uphill_step']}): "
              f"{summary['reversed_steps']}")  # fmt: skip
    if "stalled_steps" in summary:
        stalled = [
            round(m["degrees"], 1) for m in summary["steps"] if m.get("pressure_updates_stalled")
        ]
        print(f"  steps ended on stalled pressure updates (the overlap left above the "
              f"tolerance): {summary['stalled_steps']}, at {stalled} deg")  # fmt: skip
    lambdas = [it.step_length for s in steps for a in s for it in a.iterations]
    rejected = sum(it.nan_cuts for s in steps for a in s for it in a.iterations)
    print(f"  inadmissible trial states rejected: {rejected}; median step length "
          f"{sorted(lambdas)[len(lambdas) // 2] if lambdas else float('nan'):.3g}")  # fmt: skip
    last = summary["steps"][-1] if summary["steps"] else {}
    if last:
        lowest = min(m["min_det_F"] for m in summary["steps"])
        print(f"  checks: penetration at most {worst_pen:.3f} h over the steps (target 0.1 h; "
              f"{last['penetration_over_h']:.3f} h at the last step), lowest det F "
              f"{lowest:.3f}, patella turned "
              f"{last['patella_rotation_degrees']:.1f} deg, displaced "
              f"{[round(x, 1) for x in last['patella_displacement']]} mm (x lateral), fold "
              f"vertices in self-contact {last['fold_skin_vertices_in_contact']}")  # fmt: skip
    print(f"  wall {wall:.1f} s (demo's own figure {summary['seconds']:.1f} s, steps "
          f"{summary['solve_seconds']:.1f} s)")  # fmt: skip
    split = summary["time_split"]
    print(f"  time split: force + stiffness {100 * split['force_stiffness']:.0f} % (paper 63 %), "
          f"contact update {100 * split['contact_update']:.0f} % (paper 22 %), linear solve "
          f"{100 * split['linear_solve']:.0f} % (paper 15 %) of "
          f"{split.get('seconds', float('nan')):.1f} s, every solve")  # fmt: skip
    if args.degrees == 30.0 and args.steps == 10:
        print(f"  target: <= {TARGET_30_ITERATIONS} iterations, no step over "
              f"{TARGET_30_STEP_MAX}: {total} and {max(per_step, default=0)}")  # fmt: skip
    if args.degrees == 150.0:
        print(f"  target: <= {TARGET_150_ITERATIONS} iterations, none at the limit, <= "
              f"{TARGET_150_SECONDS:.0f} s, penetration <= 0.1 h at every step: {total}, "
              f"{at_limit}, {wall:.0f} s, {worst_pen:.3f} h")  # fmt: skip
    return dict(
        penalty=run.penalty or str(summary.get("penalty")), iterations=total,
        converged=sum(converged_only), steps=len(steps), cuts=cuts, at_limit=at_limit,
        stalled=int(summary.get("stalled_steps") or 0), penetration=worst_pen, wall=wall,
    )  # fmt: skip


if __name__ == "__main__":
    main()
