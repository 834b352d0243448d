"""A word on screen while numba compiles the kernels.

The kernels are compiled by numba on first use and cached on disk (``cache=True``, in the
package's ``__pycache__`` folders or ``NUMBA_CACHE_DIR``): the first run after installing (or
after changing) the package compiles for a minute or two, later runs load them in seconds. So
that the first run does not sit silent, the entry points that may compile are wrapped by
:func:`announces_compilation`: when such a call has been compiling for ``NOTICE_AFTER_S``
seconds (numba's ``numba:compile`` events, emitted only on a cache miss), rank 0 prints what it
is doing to standard error, and how long it took once done. Calls that are slow for another
reason (a large mesh) print nothing. ``MATDEPTH_QUIET_JIT=1`` silences it.
"""

from __future__ import annotations

import functools
import os
import sys
import threading
import time

from mpi4py import MPI

from numba.core import event as _event

__all__ = ["announces_compilation"]

#: seconds of compilation before the notice is printed
NOTICE_AFTER_S = 2.0
#: seconds between two looks at whether a call is compiling
POLL_S = 0.25


class _CompileCounter(_event.Listener):
    """Counts numba compilations (cache misses) started in this process."""

    def __init__(self):
        self.started = 0

    def on_start(self, event):
        self.started += 1

    def on_end(self, event):
        pass


_counter = _CompileCounter()
_event.register("numba:compile", _counter)
_announced = False


def _say(message: str) -> None:
    print(f"fenics_matdepth: {message}", file=sys.stderr, flush=True)


def announces_compilation(what: str):
    """Decorator of an entry point whose first call may compile numba kernels for ``what``."""

    def decorate(fn):
        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            if (
                wrapper.__dict__.get("_warm")
                or MPI.COMM_WORLD.rank != 0
                or os.environ.get("MATDEPTH_QUIET_JIT") == "1"
            ):
                return fn(*args, **kwargs)
            before, start = _counter.started, time.perf_counter()
            done, told = threading.Event(), threading.Event()

            def watch():
                global _announced
                while not done.wait(POLL_S):
                    if _counter.started > before and time.perf_counter() - start >= NOTICE_AFTER_S:
                        told.set()
                        tail = "" if _announced else (
                            " (once: the compiled kernels are cached on disk and load in seconds "
                            "in later runs; the first run after installing takes a minute or two)"
                        )  # fmt: skip
                        _announced = True
                        _say(f"compiling the numba kernels of {what}{tail} ...")
                        return

            watcher = threading.Thread(target=watch, daemon=True)
            watcher.start()
            try:
                return fn(*args, **kwargs)
            finally:
                done.set()
                watcher.join()
                wrapper._warm = True
                if told.is_set():
                    _say(f"{what}: compiled in {time.perf_counter() - start:.0f} s")

        return wrapper

    return decorate
