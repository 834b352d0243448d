"""The notice printed while numba compiles (fenics_matdepth/_jit.py), and numba's cache
following edits of any module of the package (fenics_matdepth/_cache.py)."""

from __future__ import annotations

import shutil
import subprocess
import sys
import time
from pathlib import Path

from mpi4py import MPI

import numba
import numpy as np

import fenics_matdepth as fm
from fenics_matdepth import _cache, _jit


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


_PROBE_A = """
from numba import njit

VALUE = {value}


@njit(inline="always")
def value():
    return VALUE
"""
_PROBE_B = """
from numba import njit

from fenics_matdepth import _probe_a


@njit(cache=True)
def value():
    return _probe_a.value()
"""


def test_cached_kernel_follows_an_edit_of_another_module(tmp_path, child_env):
    """A cached kernel that inlines a function of another module of the package is recompiled
    when only that other module changes (numba's own stamp covers the defining file only: the
    old machine code would be loaded, as happened with ``geometry/clip.py``)."""
    if MPI.COMM_WORLD.rank != 0:  # one process writes the package copy
        return
    package = Path(fm.__file__).resolve().parent
    copy = tmp_path / "fenics_matdepth"
    shutil.copytree(package, copy, ignore=shutil.ignore_patterns("__pycache__"))
    (copy / "_probe_b.py").write_text(_PROBE_B)
    # a fresh process, not an MPI rank of this run, with numba's default cache location
    env = {k: v for k, v in child_env.items() if k != "NUMBA_CACHE_DIR"}
    env.update(PYTHONPATH=str(tmp_path), MATDEPTH_QUIET_JIT="1")
    script = "import fenics_matdepth._probe_b as b; print(b.value())"

    def run(value):
        (copy / "_probe_a.py").write_text(_PROBE_A.format(value=value))
        out = subprocess.run(
            [sys.executable, "-c", script],
            env=env,
            cwd=tmp_path,
            capture_output=True,
            text=True,
            check=True,
        )
        return float(out.stdout.strip())

    assert run(1.0) == 1.0
    assert list((copy / "__pycache__").glob("_probe_b*.nbi"))  # cached on disk
    assert run(2.0) == 2.0
    assert run(2.0) == 2.0  # and loaded from the cache again


def test_package_stamp_changes_with_any_source(tmp_path):
    (tmp_path / "a.py").write_text("x = 1\n")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "b.py").write_text("y = 1\n")
    before = _cache.package_stamp(tmp_path)
    assert _cache.package_stamp(tmp_path) == before
    (tmp_path / "sub" / "b.py").write_text("y = 2\n")
    assert _cache.package_stamp(tmp_path) != before
    assert _cache.INSTALLED
