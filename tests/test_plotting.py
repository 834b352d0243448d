"""Plotting helpers that need no renderer: the GIF writer, the colour bands."""

from __future__ import annotations

import numpy as np
import pytest

from fenics_matdepth.plotting import output_folder, round_bands, write_animation


@pytest.mark.serial
def test_write_animation_keeps_frames_in_order(tmp_path):
    """Three frames of distinct colours come back as three frames of those colours, in order."""
    from PIL import Image

    colours = [(255, 0, 0), (0, 255, 0), (0, 0, 255)]
    paths = []
    for i, c in enumerate(colours):
        frame = np.zeros((24, 32, 3), dtype=np.uint8) + np.array(c, dtype=np.uint8)
        Image.fromarray(frame).save(tmp_path / f"f{i}.png")
        paths.append(tmp_path / f"f{i}.png")
    out = write_animation(paths, tmp_path / "a.gif", fps=5)
    with Image.open(out) as gif:
        assert gif.n_frames == 3
        assert gif.size == (32, 24)
        for i, c in enumerate(colours):
            gif.seek(i)
            pixel = np.asarray(gif.convert("RGB"))[12, 16]
            assert np.abs(pixel.astype(int) - c).max() <= 8
            assert gif.info["duration"] == 200


@pytest.mark.serial
def test_write_animation_rejects_bad_frames(tmp_path):
    with pytest.raises(ValueError, match="at least one frame"):
        write_animation([], tmp_path / "a.gif")
    frames = [np.zeros((4, 4, 3), np.uint8), np.zeros((5, 4, 3), np.uint8)]
    with pytest.raises(ValueError, match="same size"):
        write_animation(frames, tmp_path / "b.gif")


@pytest.mark.serial
def test_output_folder(tmp_path, monkeypatch):
    """$MATDEPTH_DEMO_OUTPUT (made absolute) when set, else the default; made if missing."""
    from mpi4py import MPI

    monkeypatch.delenv("MATDEPTH_DEMO_OUTPUT", raising=False)
    default = tmp_path / "beside" / "output"
    assert output_folder(MPI.COMM_WORLD, default) == default
    assert default.is_dir()
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MATDEPTH_DEMO_OUTPUT", "run/1")
    got = output_folder(MPI.COMM_WORLD, default)
    assert got == tmp_path.resolve() / "run" / "1"
    assert got.is_dir()


@pytest.mark.parametrize(
    ("largest", "most", "width", "count"),
    [
        (0.648, 7, 0.1, 7),  # the hyperelastic bar's displacement
        (38.2, 12, 5.0, 8),  # the knee's cut-away depth
        (11.8, 12, 1.0, 12),  # the fold's
        (12.0, 12, 1.0, 12),  # a largest value on a band edge needs no further band
        (12.5, 12, 2.0, 7),
        (3.0e-4, 5, 1e-4, 3),
        (0.0, 5, 1.0, 1),  # nothing to show: one band
    ],
)
def test_round_bands(largest, most, width, count):
    """The narrowest width of 1, 2 or 5 times a power of ten with at most ``most`` bands."""
    got_width, got_count = round_bands(largest, most)
    assert got_width == pytest.approx(width, rel=1e-12)
    assert got_count == count
    assert got_count <= most and got_count * got_width >= largest
