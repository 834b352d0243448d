"""Run every demo (demos/demo_*.py) in a subprocess, serially and with `mpirun -n 2`.

The demos assert their own convergence; a demo fails this test if it exits with an error.
These tests start their own MPI jobs, so they run in the serial pass of the suite only
(an mpirun nested inside an MPI run does not work).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

DEMO_DIR = Path(__file__).resolve().parents[1] / "demos"
DEMOS = sorted(DEMO_DIR.glob("demo_*.py"))
#: Seconds allowed to one demo run before it is declared hung.
TIMEOUT = 600


def _run(command: list[str]) -> None:
    """Run a demo, failing the test with the tail of its output if it exits with an error."""
    env = dict(os.environ)
    # The demos import fenics_matdepth from this checkout, wherever pytest runs from.
    repo = str(DEMO_DIR.parent)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (repo, env.get("PYTHONPATH")) if p)
    result = subprocess.run(
        command, cwd=DEMO_DIR, env=env, capture_output=True, text=True, timeout=TIMEOUT
    )
    if result.returncode != 0:
        tail = "\n".join((result.stdout + "\n" + result.stderr).splitlines()[-40:])
        pytest.fail(f"{' '.join(command)} exited with {result.returncode}:\n{tail}")


def _mpiexec() -> str:
    for name in ("mpirun", "mpiexec"):
        if (path := shutil.which(name)) is not None:
            return path
    pytest.skip("no mpirun/mpiexec on PATH")


@pytest.mark.serial
@pytest.mark.parametrize("demo", DEMOS, ids=[d.name for d in DEMOS])
def test_demo_serial(demo: Path):
    _run([sys.executable, str(demo)])


@pytest.mark.serial
@pytest.mark.parametrize("demo", DEMOS, ids=[d.name for d in DEMOS])
def test_demo_mpi(demo: Path):
    _run([_mpiexec(), "-n", "2", sys.executable, str(demo)])
