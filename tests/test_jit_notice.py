"""The notice printed while numba compiles (fenics_matdepth/_jit.py)."""

from __future__ import annotations

import time

from mpi4py import MPI

import numba
import numpy as np

from fenics_matdepth import _jit


def test_notice_while_compiling(monkeypatch, capsys):
    """A first call that compiles longer than the delay says so on rank 0, and how long it
    took; other ranks stay silent, and so does the second call. (Every rank runs every test:
    a test skipped on some ranks only would leave the others in the collective clean-up.)"""
    monkeypatch.setattr(_jit, "NOTICE_AFTER_S", 0.0)
    monkeypatch.setattr(_jit, "POLL_S", 0.01)
    monkeypatch.delenv("MATDEPTH_QUIET_JIT", raising=False)

    @numba.njit  # not cached: compiled at the first call
    def kernel(a):
        s = 0.0
        for v in a:
            s += np.sin(v) * np.cos(v)
        return s

    @_jit.announces_compilation("a test kernel")
    def entry(a):
        value = kernel(a) + kernel(a)
        time.sleep(0.2)  # the watcher looks every 0.01 s
        return value

    entry(np.ones(3))
    err = capsys.readouterr().err
    if MPI.COMM_WORLD.rank == 0:
        assert "fenics_matdepth: compiling the numba kernels of a test kernel" in err
        assert "a test kernel: compiled in" in err
    else:
        assert err == ""
    entry(np.ones(3))
    assert capsys.readouterr().err == ""


def test_no_notice_without_compiling(monkeypatch, capsys):
    """A call that is slow for another reason than compiling prints nothing."""
    monkeypatch.setattr(_jit, "NOTICE_AFTER_S", 0.01)
    monkeypatch.setattr(_jit, "POLL_S", 0.01)

    @_jit.announces_compilation("nothing")
    def entry():
        time.sleep(0.2)

    entry()
    assert capsys.readouterr().err == ""
