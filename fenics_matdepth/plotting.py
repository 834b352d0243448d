"""Off-screen rendering with pyvista, also on a headless Linux machine (CI, clusters)."""

from __future__ import annotations

import atexit
import os
import shutil
import subprocess
import sys

__all__ = ["offscreen_pyvista", "start_virtual_display"]


def start_virtual_display() -> bool:
    """Make sure VTK has an X server to render into; False if there is none to be had.

    Debian's VTK renders through X11 even off-screen, and aborts the process without an X
    server, so on a headless Linux machine this starts a private Xvfb (it picks a free display
    number and reports it on ``-displayfd``), stopped when the Python process exits.
    """
    if os.environ.get("DISPLAY") or not sys.platform.startswith("linux"):
        return True
    xvfb = shutil.which("Xvfb")
    if xvfb is None:
        return False
    read_end, write_end = os.pipe()
    server = subprocess.Popen(
        [xvfb, "-displayfd", str(write_end), "-screen", "0", "1280x1024x24", "-nolisten", "tcp"],
        pass_fds=(write_end,),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    os.close(write_end)
    with os.fdopen(read_end) as display_number:
        number = display_number.readline().strip()
    if not number:
        server.kill()
        return False
    os.environ["DISPLAY"] = f":{number}"
    atexit.register(server.wait)
    atexit.register(server.terminate)
    return True


def offscreen_pyvista():
    """The pyvista module set up for off-screen rendering, or None (with a printed reason) if
    pyvista is missing or there is no X server and no Xvfb."""
    try:
        import pyvista
    except ImportError:
        print("pyvista is not installed: no picture")
        return None
    if not start_virtual_display():
        print("no X server and no Xvfb: no picture")
        return None
    pyvista.OFF_SCREEN = True
    return pyvista
