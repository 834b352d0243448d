"""Shared pytest set-up: collective clean-up after each test, serial-only marker."""

from __future__ import annotations

import gc
import os
import sys

from mpi4py import MPI

import pytest
from hypothesis import settings

# Property tests draw the same examples on every run and every rank (a CI run must not pass or
# fail by chance, and MPI ranks must agree); HYPOTHESIS_PROFILE=explore draws new ones.
settings.register_profile("deterministic", derandomize=True, database=None)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "deterministic"))


@pytest.fixture(autouse=True)
def _collective_cleanup():
    """Collect garbage and wait for every rank: PETSc destructors are collective."""
    yield
    gc.collect()
    MPI.COMM_WORLD.Barrier()


@pytest.fixture
def child_env() -> dict[str, str]:
    """The environment for a fresh serial child process: without the MPI launcher's
    variables (a child inheriting them would try to join this run and hang)."""
    launcher = ("OMPI_", "PMIX_", "PRTE_", "MPI_")
    return {k: v for k, v in os.environ.items() if not k.startswith(launcher)}


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """Under MPI, a test that fails on some ranks only leaves the others waiting in a
    collective (and the failed rank in the barrier above): print the failure and abort the
    job instead of hanging until the timeout."""
    outcome = yield
    report = outcome.get_result()
    if report.failed and MPI.COMM_WORLD.size > 1:
        rank = MPI.COMM_WORLD.rank
        sys.stderr.write(f"\n[rank {rank}] {item.nodeid} failed:\n{report.longreprtext}\n")
        sys.stderr.write(f"[rank {rank}] aborting the MPI job (the other ranks may be stuck)\n")
        sys.stderr.flush()
        MPI.COMM_WORLD.Abort(1)


def pytest_collection_modifyitems(config, items):
    """Skip tests marked ``serial`` when running on more than one MPI process."""
    if MPI.COMM_WORLD.size == 1:
        return
    skip = pytest.mark.skip(reason="serial test (runs in the serial pass of `make test`)")
    for item in items:
        if "serial" in item.keywords:
            item.add_marker(skip)
