"""Progress reporting: lines when nobody watches, a bar that reaches its end when someone does."""

from __future__ import annotations

import io

from mpi4py import MPI

import pytest

from fenics_matdepth._progress import StepProgress


def test_lines_when_not_interactive(capsys, monkeypatch):
    monkeypatch.setenv("MATDEPTH_PROGRESS", "lines")
    progress = StepProgress(MPI.COMM_WORLD, 0.0, 1.0, "load")
    assert not progress.uses_bar
    progress.step(0.5, "step 1 half")
    progress.message("a cut")
    progress.close()
    out = capsys.readouterr().out
    if MPI.COMM_WORLD.rank == 0:
        assert out.splitlines() == ["step 1 half", "a cut"]
    else:
        assert out == ""


@pytest.mark.serial
def test_bar_advances_to_the_reached_fraction(monkeypatch):
    pytest.importorskip("tqdm")
    monkeypatch.setenv("MATDEPTH_PROGRESS", "bar")
    progress = StepProgress(MPI.COMM_WORLD, 2.0, 4.0, "t")
    assert progress.uses_bar
    stream = io.StringIO()
    progress._bar.fp = stream  # keep the test's output clean; check the bar's state
    progress.step(2.5, "t 2.5")
    assert progress._bar.n == 250
    progress.step(4.0, "t 4")
    assert progress._bar.n == 1000
    assert "t 4" in str(progress._bar)
    progress.close()
    assert not progress.uses_bar


def test_lines_under_mpi_even_on_a_terminal(monkeypatch):
    """mpirun gives its ranks a pseudo-terminal; a run on several ranks prints lines (a bar in
    a log file is unreadable); serially, a terminal gets the bar."""
    pytest.importorskip("tqdm")
    monkeypatch.delenv("MATDEPTH_PROGRESS", raising=False)
    monkeypatch.setattr("sys.stdout.isatty", lambda: True, raising=False)
    progress = StepProgress(MPI.COMM_WORLD, 0.0, 1.0, "load")
    if progress.uses_bar:
        progress._bar.fp = io.StringIO()
    expected = MPI.COMM_WORLD.size == 1 and MPI.COMM_WORLD.rank == 0
    assert progress.uses_bar == expected
    progress.close()


def test_silent_when_disabled(capsys):
    progress = StepProgress(MPI.COMM_WORLD, 0.0, 1.0, "load", enabled=False)
    progress.step(1.0, "never shown")
    progress.message("nor this")
    progress.close()
    assert capsys.readouterr().out == ""
