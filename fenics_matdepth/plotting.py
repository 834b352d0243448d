"""Pictures from demos and scripts: the folder they go to, off-screen pyvista, also on a headless
Linux machine (CI, clusters), and distributed meshes gathered on rank 0 for it."""

from __future__ import annotations

import atexit
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

__all__ = [
    "gather_vtk_grid",
    "offscreen_pyvista",
    "output_folder",
    "round_bands",
    "show_image",
    "start_virtual_display",
    "write_animation",
]


def output_folder(comm, default: str | os.PathLike) -> Path:
    """The folder a script writes its pictures and results to, made if missing (collective).

    ``$MATDEPTH_DEMO_OUTPUT`` when it is set (the demos' tests and the docs build send each
    run's output to a folder of their own), else ``default``. Rank 0 makes the folder; every
    rank returns once it exists.

    Args:
        comm: the script's communicator.
        default: the folder to use when ``$MATDEPTH_DEMO_OUTPUT`` is not set, e.g. ``output/``
            beside the script.

    Returns:
        The folder, as an absolute path when it comes from ``$MATDEPTH_DEMO_OUTPUT``.
    """
    if os.environ.get("MATDEPTH_DEMO_OUTPUT"):
        output = Path(os.environ["MATDEPTH_DEMO_OUTPUT"]).resolve()
    else:
        output = Path(default)
    if comm.rank == 0:
        output.mkdir(parents=True, exist_ok=True)
    comm.barrier()
    return output


def round_bands(largest: float, most: int) -> tuple[float, int]:
    """Colour bands of a round width for values from 0 to ``largest``: the narrowest width of 1,
    2 or 5 times a power of ten that needs at most ``most`` bands, and how many it needs (the
    band edges, and so a colour key's labels, are then round numbers).

    Returns:
        ``(width, count)``: the scale runs from 0 to ``count * width >= largest``.
    """
    if not largest > 0.0:  # nothing to show: one band of unit width
        return 1.0, 1
    exponent = np.floor(np.log10(largest / most))
    for step in (1.0, 2.0, 5.0, 10.0):  # the last always fits: 10^(exponent+1) > largest / most
        width = step * 10.0**exponent
        if largest / width <= most * (1.0 + 1e-12):
            break
    return width, max(1, int(np.ceil(largest / width - 1e-9)))


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


def gather_vtk_grid(comm, cells, types, points, *point_data):
    """The pieces of a distributed VTK grid joined on rank 0 (None on other ranks).

    Args:
        comm: the mesh's communicator.
        cells, types, points: this rank's ``dolfinx.plot.vtk_mesh`` arrays.
        point_data: arrays with one row per point of this rank.

    Returns:
        ``(cells, types, points, *point_data)`` of the whole mesh, cell connectivity renumbered
        into the concatenated points (collective).
    """
    parts = comm.gather((cells, types, points, *point_data), root=0)
    if comm.rank != 0:
        return None
    offset, all_cells = 0, []
    for part_cells, _, part_points, *_ in parts:
        # VTK cell arrays are [n, i_0, ..., i_{n-1}, n, ...]; all cells have the same n here.
        block = part_cells.reshape(-1, part_cells[0] + 1).copy()
        block[:, 1:] += offset
        all_cells.append(block.ravel())
        offset += part_points.shape[0]
    joined = (np.concatenate([p[i] for p in parts]) for i in range(1, len(parts[0])))
    return (np.concatenate(all_cells), *joined)


def write_animation(frames, path, fps: float = 10.0, loop: bool = True) -> str:
    """Join rendered frames (PNG files or RGB(A) arrays, all the same size) into an animated GIF.

    Pillow (a dependency of matplotlib) writes the GIF, so no video codec is needed. Render
    every frame with one fixed colour scale and camera, so that the animation compares like
    with like.

    Args:
        frames: a sequence of PNG paths or ``(height, width, 3|4)`` uint8 arrays, in time order.
        path: the GIF to write (``.gif``).
        fps: frames per second.
        loop: repeat forever (else play once).

    Returns:
        ``path`` as a string.

    Raises:
        ValueError: if there are no frames or they differ in size.
    """
    from PIL import Image

    images = [
        Image.open(f) if isinstance(f, str | os.PathLike) else Image.fromarray(f) for f in frames
    ]
    if not images:
        raise ValueError("write_animation needs at least one frame")
    sizes = {im.size for im in images}
    if len(sizes) != 1:
        raise ValueError(f"all frames must have the same size, got {sorted(sizes)}")
    rgb = [im.convert("RGB") for im in images]
    rgb[0].save(
        str(path), save_all=True, append_images=rgb[1:], duration=round(1000.0 / fps),
        loop=0 if loop else 1, optimize=False,
    )  # fmt: skip
    return str(path)


def show_image(path) -> None:
    """Show a rendered picture inline when running in a notebook; do nothing in a script.

    Demos save their pyvista screenshots to files (scripts, CI) and call this after each, so
    the same demo executed as a notebook (``make notebooks``, the docs) shows them in place.
    """
    try:
        from IPython import get_ipython
    except ImportError:
        return
    shell = get_ipython()
    if shell is None or "IPKernelApp" not in getattr(shell, "config", {}):
        return
    from IPython.display import Image, display

    display(Image(filename=str(path)))
