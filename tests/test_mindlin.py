"""Cattaneo-Mindlin: a tangential force T < mu N on a Hertz contact leaves a stick zone of
radius ``c = a (1 - T / (mu N))^(1/3)``.

The model and its measures are ``benchmarks/bench_mindlin.py``'s (run here on the coarse
mesh, res 1.0, a / h = 2.6; the benchmark's figures are at res 0.5): the stick radius is read
from the traction along the load, averaged over rings, where its ratio to ``mu p`` falls below
0.95 (``traction_stick_radius``). That measure is checked first on Mindlin's own traction.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

from mpi4py import MPI

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bench():
    """``benchmarks/bench_mindlin.py`` as a module (it imports ``meshes`` from the root)."""
    added = str(ROOT) not in sys.path
    if added:
        sys.path.insert(0, str(ROOT))
    try:
        spec = importlib.util.spec_from_file_location(
            "bench_mindlin", ROOT / "benchmarks" / "bench_mindlin.py"
        )
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    finally:
        if added:
            sys.path.remove(str(ROOT))
    return module


def _mindlin_points(c_over_a: float, a: float = 2.0, n: int = 60) -> dict[str, np.ndarray]:
    """Friction points on both faces of a Hertz contact carrying Mindlin's traction: on a
    polar grid of the disc of radius ``a`` (the centre at (1, -2)), ``p = sqrt(1 - r^2/a^2)``,
    ``q = mu p - mu (c/a) sqrt(1 - r^2/c^2)`` inside ``c``, ``mu p`` outside; the lower face
    carries the opposite force."""
    mu = 0.3
    r = (np.arange(n) + 0.5) / n * a
    theta = (np.arange(2 * n) + 0.5) / (2 * n) * 2 * np.pi
    rr, tt = (v.ravel() for v in np.meshgrid(r, theta))
    area = rr * (a / n) * (2 * np.pi / (2 * n))
    p = np.sqrt(1.0 - (rr / a) ** 2)
    c = c_over_a * a
    q = mu * p - mu * c_over_a * np.sqrt(np.clip(1.0 - (rr / c) ** 2, 0.0, None))
    x = np.column_stack([1.0 + rr * np.cos(tt), -2.0 + rr * np.sin(tt), np.zeros_like(rr)])
    force = np.zeros((len(rr), 3))
    force[:, 0] = q * area
    both = lambda v: np.concatenate([v, v])  # noqa: E731
    return {
        "x": both(x),
        "weight": both(mu * p * area),
        "force": np.concatenate([force, -force]),
        "body": np.repeat([0, 1], len(rr)),
    }


@pytest.mark.parametrize("c_over_a", [0.3, 0.6, 0.9])
def test_the_traction_measure_reads_mindlins_stick_radius(bench, c_over_a):
    measured = bench.traction_stick_radius(_mindlin_points(c_over_a), 2.0)
    assert measured == pytest.approx(c_over_a, rel=0.03)
    # the ratio's level decides: a point of the stick zone's traction is below 0.95
    assert bench.traction_stick_radius(_mindlin_points(c_over_a), 2.0, level=0.5) < measured


def test_stick_radius_follows_mindlin_under_a_tangential_load(bench):
    """Pressed, then shifted sideways by 0.2 and 0.4 (T / mu N about 0.36 and 0.67): the
    stick radius from the traction within 10 % of Mindlin's. (The share of points whose
    slip is below the slip tolerance, the status the contact fields show, reads -18 % at
    0.67 on this mesh: it counts the stick zone's creep as slip.)"""
    out = bench.run(res=1.0, press=1.0, shifts=[0.2, 0.4], slip_tol=0.0, comm=MPI.COMM_WORLD)
    ratios = [row["ratio"] for row in out["rows"]]
    assert 0.3 < ratios[0] < 0.45 and 0.6 < ratios[1] < 0.75, ratios
    # the normal force is the press's: Hertz's a from N close to the measured contact radius
    assert out["a"] == pytest.approx(out["a_hertz"], rel=0.2)
    for row in out["rows"]:
        c = row["c_traction"][20]
        assert c == pytest.approx(row["c_theory"], rel=0.10), (row["ratio"], c, row["c_theory"])
        assert c < 0.95  # a stick zone inside the contact, not the whole of it
