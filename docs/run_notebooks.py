"""Convert every demo (demos/demo_*.py, jupytext light) to a notebook and execute it headless.

``make notebooks`` runs this; the executed notebooks land in ``docs/demos/`` (with a copy of
each script, for the pages' download links), where ``make docs`` renders them with their
outputs. Demos run in their reduced size unless ``MATDEPTH_DOCS_FULL=1``.

Usage: ``python3 docs/run_notebooks.py [demo_name.py ...]`` (default: every demo).
"""

from __future__ import annotations

import os
import shutil
import sys
import time
from pathlib import Path

import jupytext
import nbclient
import nbformat

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
OUT = HERE / "demos"
#: Seconds one demo may run before its execution is declared hung.
TIMEOUT = 1800


def main(names: list[str]) -> int:
    demos = sorted((REPO / "demos").glob("demo_*.py"))
    if names:
        demos = [d for d in demos if d.name in names]
        missing = set(names) - {d.name for d in demos}
        if missing:
            print(f"no such demo: {', '.join(sorted(missing))}", file=sys.stderr)
            return 2
    OUT.mkdir(exist_ok=True)
    if os.environ.get("MATDEPTH_DOCS_FULL", "0") in ("", "0"):
        os.environ["MATDEPTH_DEMO_QUICK"] = "1"
    os.environ.setdefault("MATDEPTH_DEMO_OUTPUT", str(HERE / "_build" / "demo_output"))
    os.environ["MPLBACKEND"] = "module://matplotlib_inline.backend_inline"
    # the kernels import fenics_matdepth and the model builders (`from meshes import leg`)
    # from this checkout
    os.environ["PYTHONPATH"] = os.pathsep.join(
        p for p in (str(REPO), os.environ.get("PYTHONPATH")) if p
    )
    for demo in demos:
        tic = time.perf_counter()
        print(f"executing {demo.name} ...", flush=True)
        notebook = jupytext.read(demo, fmt="py:light")
        notebook.metadata["kernelspec"] = {
            "name": "python3", "display_name": "Python 3", "language": "python",
        }  # fmt: skip
        client = nbclient.NotebookClient(
            notebook, timeout=TIMEOUT, kernel_name="python3",
            # run where the script lives, as a user opening it there would: the demos write
            # to output/ beside themselves unless MATDEPTH_DEMO_OUTPUT says otherwise
            resources={"metadata": {"path": str(REPO / "demos")}},
        )  # fmt: skip
        try:
            client.execute()
        except nbclient.exceptions.CellExecutionError as err:
            print(f"{demo.name} failed:\n{err}", file=sys.stderr)
            return 1
        nbformat.write(notebook, OUT / f"{demo.stem}.ipynb")
        shutil.copy2(demo, OUT / demo.name)
        print(f"  {demo.stem}.ipynb written ({time.perf_counter() - tic:.0f} s)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
