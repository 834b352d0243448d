"""The package's warnings reach a plain script's stderr.

FFCx 0.9 (DOLFINx 0.9's form compiler) calls ``logging.captureWarnings(True)`` when it is
imported, which routes every warning to the ``py.warnings`` logger; with no logging set up,
the first warning gives that logger a ``NullHandler`` and nothing is printed — a
``DepthDeficiencyWarning`` or the penalty raise's ``RuntimeWarning`` would go unseen.
Importing ``fenics_matdepth`` shows warnings again unless the script set up logging itself.
"""

from __future__ import annotations

import subprocess
import sys

from mpi4py import MPI

import pytest

pytestmark = pytest.mark.skipif(
    MPI.COMM_WORLD.size > 1, reason="runs one plain script in a subprocess (serial lane)"
)

SCRIPT = """
import warnings
{setup}
import fenics_matdepth
warnings.warn("a warning the user must see", RuntimeWarning)
"""


def _stderr(setup: str = "") -> str:
    done = subprocess.run(
        [sys.executable, "-c", SCRIPT.format(setup=setup)],
        capture_output=True, text=True, timeout=600, check=True,
    )  # fmt: skip
    return done.stderr


def test_a_warning_reaches_stderr_after_the_import():
    assert "a warning the user must see" in _stderr()


def test_a_script_that_set_up_logging_keeps_it():
    """With logging configured (a handler on the root logger) and warnings captured by the
    script itself, the warning goes through logging, as the script asked: formatted by its
    handler."""
    setup = (
        "import logging; logging.basicConfig(format='LOGGED %(message)s'); "
        "logging.captureWarnings(True)"
    )
    err = _stderr(setup)
    assert "LOGGED" in err and "a warning the user must see" in err, err
