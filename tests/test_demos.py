"""Run every demo (demos/demo_*.py) in a subprocess, serially and with `mpirun -n 2`.

The demos assert their own convergence; a demo fails this test if it exits with an error.
Demos with a reduced-size mode run reduced (the environment in ``REDUCED``), write to a
temporary folder, and the claims they make are checked from the summary they write there.
These tests start their own MPI jobs, so they run in the serial pass of the suite only
(an mpirun nested inside an MPI run does not work).
"""

from __future__ import annotations

import itertools
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

DEMO_DIR = Path(__file__).resolve().parents[1] / "demos"
DEMOS = sorted(DEMO_DIR.glob("demo_*.py"))
#: Seconds allowed to one demo run before it is declared hung.
TIMEOUT = 600
#: Extra environment of the demos that have a reduced-size mode.
REDUCED = {
    "demo_concave_corner.py": {"MATDEPTH_DEMO_QUICK": "1"},
    "demo_falling_rods.py": {"MATDEPTH_DEMO_QUICK": "1"},
    "demo_snake_apple.py": {"MATDEPTH_DEMO_QUICK": "1"},
    "demo_knee.py": {"MATDEPTH_DEMO_QUICK": "1"},
}


def _run(command: list[str], demo: Path, output: Path, extra: dict | None = None) -> None:
    """Run a demo, failing the test with the tail of its output if it exits with an error
    (``extra``: more environment, and the claims of its reduced run are not checked)."""
    env = dict(os.environ)
    # The demos import fenics_matdepth from this checkout, wherever pytest runs from.
    repo = str(DEMO_DIR.parent)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (repo, env.get("PYTHONPATH")) if p)
    env.update(REDUCED.get(demo.name, {}))
    env.update(extra or {})
    env["MATDEPTH_DEMO_OUTPUT"] = str(output)
    result = subprocess.run(
        command, cwd=DEMO_DIR, env=env, capture_output=True, text=True, timeout=TIMEOUT
    )
    if result.returncode != 0:
        tail = "\n".join((result.stdout + "\n" + result.stderr).splitlines()[-40:])
        pytest.fail(f"{' '.join(command)} exited with {result.returncode}:\n{tail}")
    if demo.name in CLAIMS and not extra:
        CLAIMS[demo.name](output)


def _mpiexec() -> str:
    for name in ("mpirun", "mpiexec"):
        if (path := shutil.which(name)) is not None:
            return path
    pytest.skip("no mpirun/mpiexec on PATH")


def _concave_corner_claims(output: Path) -> None:
    """The paper's section 5 (Fig. 16-17), as the demo's summary reports it.

    Area integration converges to a relative residual of 1e-10 in a modest number of Newton
    iterations, with full steps at the end; point collocation, from the same state with the same
    solver, stalls far above the tolerance. As the wedge slides across the corner, the
    collocated force on a vertex jumps while the area-integrated one changes by small steps.
    """
    summary = json.loads((output / "concave_corner.json").read_text())
    area, collocation = summary["area"], summary["collocation"]

    r = np.asarray(area["residual_norms"])
    assert area["converged"], r
    assert r[-1] <= 1e-10 * r[0], r
    # a modest count: the reduced demo takes 19 iterations, serially and on 2 ranks (the full
    # one 11)
    assert area["iterations"] <= 30, r
    assert area["step_lengths"][-1] == pytest.approx(1.0, abs=1e-6)  # Newton's own steps

    r = np.asarray(collocation["residual_norms"])
    assert not collocation["converged"], r
    assert r[-1] >= 1e-4 * r[0], f"collocation did not stall: {r}"

    jumps = summary["jumps"]
    assert jumps["area"]["largest"] < 0.05 * jumps["area"]["span"], jumps
    assert jumps["collocation"]["largest"] > 5 * jumps["area"]["largest"], jumps

    for picture in ("concave_corner_convergence.png", "concave_corner_slide.png"):
        assert (output / picture).stat().st_size > 0


def _falling_rods_claims(output: Path) -> None:
    """Paper Fig. 24, reduced: the rods fall over onto each other and the foundation.

    Every step converged (the demo stops otherwise) to the reduced run's end; the rods' tips
    moved by more than half a rod's length; they came into contact (contact energy well above
    the round-off of the bases resting on the foundation), with a penetration below a third of
    the element size; the damped, dissipative scheme never gains energy.
    """
    summary = json.loads((output / "falling_rods.json").read_text())
    assert summary["t_end"] == pytest.approx(0.2, rel=1e-9)
    assert summary["steps"] >= 20
    assert summary["max_displacement"] > 0.5 * summary["length"]
    scale = max(summary["gravity_work"])  # J
    contact = np.asarray(summary["contact"])
    assert contact.max() > 1e-6 * scale, contact.max()  # resting bases: about 1e-17 J
    penetration = np.asarray(summary["max_penetration"]) / summary["element_size"]
    assert 0.0 < penetration.max() < 1.0 / 3.0
    total = np.asarray(summary["total"])
    assert np.all(np.diff(total) <= 1e-6 * scale), np.diff(total)
    assert total[-1] < -0.01 * scale  # damping took its share
    for picture in ("falling_rods_energy.png", "falling_rods.gif"):
        assert (output / picture).stat().st_size > 0
    assert summary["frames"]


def _snake_apple_claims(output: Path) -> None:
    """The snake swallows the apple (paper Fig. 23), as the demo's summary reports it.

    Every load step converged to the solver's tolerance and the path was completed; the apple
    ends behind the mouth (fully inside the snake), having stretched the wall more than twice
    around it (the apple's radius is 2.9 times the lumen's); the contact surfaces overlap by
    less than a third of the wall's element size (penalty ten times the snake's modulus over
    that size); no element inverted.
    """
    summary = json.loads((output / "snake_apple.json").read_text())
    steps = summary["steps"]
    assert steps[-1]["load"] == pytest.approx(1.0), [s["load"] for s in steps]
    for step in steps[1:]:
        r = np.asarray(step["residual_norms"])
        assert r[-1] <= max(1e-10 * r[0], 1e-11), (step["load"], r)
    assert steps[-1]["apple_back"] > 0.0, steps[-1]
    assert max(s["max_stretch"] for s in steps) > 2.0, [s["max_stretch"] for s in steps]
    assert steps[-1]["active_pairs"] > 0
    assert max(s["relative_penetration"] for s in steps) < 1.0 / 3.0, steps
    assert min(s["min_det_F"] for s in steps) > 0.1, [s["min_det_F"] for s in steps]
    for picture in summary["pictures"]:
        assert (output / picture).stat().st_size > 0


def _knee_claims(output: Path) -> None:
    """The reduced knee (coarse leg, the first few degrees of flexion): every step converged,
    the contact surfaces penetrate less than a tenth of the boundary element size, no element
    is inverted, the patella is pulled distally by the ligament (nothing prescribes it), and
    the last step is in the checkpoint a resumed run starts from (with the augmented
    Lagrangian's nodal pressures, when it is on)."""
    summary = json.loads((output / "knee.json").read_text())
    assert summary["completed"], summary["failure"]
    steps = summary["steps"]
    assert len(steps) >= summary["num_steps"]
    assert steps[-1]["degrees"] == pytest.approx(summary["target_degrees"])
    for step in steps:
        assert step["penetration_over_h"] < 0.1, step
        assert step["min_det_F"] > 0.0, step
        # the five lowest cells, gathered over the ranks, start with the leg's minimum
        lowest = [cell[0] for cell in step["lowest_det_F_cells"]]
        assert len(lowest) == 5 and lowest == sorted(lowest), step
        assert lowest[0] == pytest.approx(step["min_det_F"], rel=1e-12), step
    # distal (-z) motion of the patella grows with flexion
    dz = [step["patella_displacement"][2] for step in steps]
    assert dz[-1] < 0.0, dz
    assert all(b <= a + 1e-9 for a, b in itertools.pairwise(dz)), dz
    assert summary["mesh"]["inverted"] == 0
    # the local relaxation is on by default, on any number of processes (fm.LocalRelaxation),
    # and relaxes patches in the first steps already
    relaxation = summary["relaxation"]
    assert relaxation is not None and relaxation["patches"] > 0, relaxation
    # each step's record holds the patches relaxed in it
    assert sum(step["relaxed_patches"] for step in steps) == relaxation["patches"], steps
    # and the Newton steps taken with the tibia's dofs off their values: at least the first of
    # each step (its rotation comes in through it)
    off = [step["steps_off_dirichlet"] for step in steps]
    assert sum(off) == summary["steps_off_dirichlet"] and min(off) >= 1, off
    # a Newton step that climbs the energy is reversed (ContactProblem.uphill_step)
    assert summary["uphill_step"] == "reverse" and summary["reversed_steps"] >= 0, summary
    with np.load(output / "knee_checkpoint.npz") as checkpoint:
        meta = json.loads(str(checkpoint["meta"]))
        assert meta["steps"] == len(steps) and meta["load"] == pytest.approx(1.0), meta
        assert np.isfinite(checkpoint["field/u"]).all()
    assert len(json.loads((output / "knee_steps.json").read_text())) == len(steps)
    if summary["augmented_tol_h"] > 0.0:
        # the augmented Lagrangian's nodal pressures are saved with the step, for --resume
        with np.load(output / "knee_pressure.npz") as saved:
            meta = json.loads(str(saved["meta"]))
            assert meta["load"] == pytest.approx(1.0), meta
            pressure = saved["field/pressure"]
            assert np.isfinite(pressure).all() and (pressure >= 0.0).all()
        for step in steps:
            assert step["penetration_over_h"] <= summary["augmented_tol_h"], step
    for picture in ("knee_skin.png", "knee_cutaway.png", "knee_flexion.gif"):
        assert (output / picture).stat().st_size > 0


#: Checks of what a demo claims, run on its output folder after it succeeded.
CLAIMS = {
    "demo_concave_corner.py": _concave_corner_claims,
    "demo_falling_rods.py": _falling_rods_claims,
    "demo_snake_apple.py": _snake_apple_claims,
    "demo_knee.py": _knee_claims,
}


@pytest.mark.serial
@pytest.mark.parametrize("demo", DEMOS, ids=[d.name for d in DEMOS])
def test_demo_serial(demo: Path, tmp_path: Path):
    _run([sys.executable, str(demo)], demo, tmp_path)


@pytest.mark.serial
@pytest.mark.parametrize("demo", DEMOS, ids=[d.name for d in DEMOS])
def test_demo_mpi(demo: Path, tmp_path: Path):
    _run([_mpiexec(), "-n", "2", sys.executable, str(demo)], demo, tmp_path)


@pytest.mark.serial
def test_falling_rods_slide_off_each_other(tmp_path: Path):
    """Two columns of the full scene's rods (7 x 2) to t = 0.25 s, past their second contact:
    an edge of one rod slides off another's edge. The collision detection's exit cap held
    that edge inside the other rod's side face (its mean normal between its two faces, so
    "facing the same way"), and the run stopped at t = 0.2369 s naming a pass-through (the
    full demo at 0.2366 s); the reduced run above ends at 0.2 s, before it."""
    demo = DEMO_DIR / "demo_falling_rods.py"
    extra = {"MATDEPTH_RODS_ARRAY": "7x2", "MATDEPTH_RODS_T_END": "0.25"}
    _run([sys.executable, str(demo)], demo, tmp_path, extra)
    summary = json.loads((tmp_path / "falling_rods.json").read_text())
    assert summary["t_end"] == pytest.approx(0.25, rel=1e-9)
    contact = np.asarray(summary["contact"])
    assert contact.max() > 1e-6 * max(summary["gravity_work"])
    penetration = np.asarray(summary["max_penetration"]) / summary["element_size"]
    assert penetration.max() < 1.0 / 3.0
