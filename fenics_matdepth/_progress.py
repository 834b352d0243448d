"""Progress of long runs (load steps, time steps): a bar when someone watches, lines otherwise.

In a terminal or a Jupyter notebook the steps advance a tqdm progress bar whose postfix carries
the step's one-line summary; when the output goes to a file or a CI log (not a terminal), or
when tqdm is missing, each step prints its line instead, so logs stay readable. Only MPI rank 0
reports.
"""

from __future__ import annotations

import os
import sys

__all__ = ["StepProgress"]


def _interactive(comm) -> bool:
    """Whether a person is watching: a notebook kernel, or standard output on a terminal.

    Under MPI (more than one rank) the answer is no: mpirun hands its ranks a pseudo-terminal,
    so standard output looks like a terminal even when the job's output goes to a log file.
    """
    if os.environ.get("MATDEPTH_PROGRESS") in ("bar", "lines"):
        return os.environ["MATDEPTH_PROGRESS"] == "bar"
    if comm.size > 1:
        return False
    try:
        from IPython import get_ipython

        shell = get_ipython()
        if shell is not None and "IPKernelApp" in getattr(shell, "config", {}):
            return True
    except ImportError:
        pass
    return bool(getattr(sys.stdout, "isatty", lambda: False)())


class StepProgress:
    """Reports the steps of a run from ``start`` to ``end`` (load factor or time).

    Args:
        comm: the communicator of the run; ranks other than 0 stay silent.
        start, end: the range the run covers (the bar's 0 and 100 %).
        label: what is counted, e.g. ``"load"`` or ``"t"`` (the bar's description).
        enabled: False silences everything (``progress=False`` of the solvers).

    Set ``MATDEPTH_PROGRESS=lines`` (or ``bar``) to force one mode.
    """

    def __init__(self, comm, start: float, end: float, label: str, enabled: bool = True):
        self._on = enabled and comm.rank == 0
        self._start, self._span = float(start), float(end) - float(start)
        self._bar = None
        if self._on and _interactive(comm):
            try:
                from tqdm.auto import tqdm
            except ImportError:
                return
            self._bar = tqdm(total=1000, desc=label, unit="‰", leave=True, dynamic_ncols=True)

    @property
    def uses_bar(self) -> bool:
        """Whether steps advance a progress bar (else they print lines)."""
        return self._bar is not None

    def step(self, reached: float, line: str) -> None:
        """A converged step: the bar advances to ``reached`` and shows ``line``; or the line is
        printed."""
        if not self._on:
            return
        if self._bar is None:
            print(line, flush=True)
            return
        done = 1.0 if self._span == 0.0 else (reached - self._start) / self._span
        self._bar.n = round(1000 * min(max(done, 0.0), 1.0))
        self._bar.set_postfix_str(line, refresh=True)

    def message(self, line: str) -> None:
        """A line that is not a step (a cut, a warning): printed above the bar."""
        if not self._on:
            return
        if self._bar is None:
            print(line, flush=True)
        else:
            self._bar.write(line)

    def close(self) -> None:
        """Finish the bar (call once, also after a failure)."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None
