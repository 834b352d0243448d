"""Pair kernel throughput on one core (after JIT): intersection test, energy + gradient, energy +
gradient + Hessian, on a mix of candidate pairs of which about half intersect (each pair its own
triangle); the intersection test also on candidates grouped by triangle (20 a triangle).

Run: ``scripts/fenicsx python3 benchmarks/bench_kernels.py [--pairs N] [--profile]``.
Prints figures; asserts nothing about time.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from fenics_matdepth.contact.kernels.collocation import collocation_pairs
from fenics_matdepth.contact.kernels.drivers import area_pairs, area_pairs_into
from fenics_matdepth.geometry.intersect import intersect_pairs

TARGETS = {
    "intersection": 20e6,
    "intersection, grouped": 20e6,
    "energy+gradient": 3e6,
    "energy+gradient+hessian": 0.5e6,
}


def candidate_pairs(npairs: int, seed: int = 0):
    """Independent (triangle, tetrahedron) pairs: unit-size tetrahedra of random shape and
    orientation, and random triangles of similar size placed around each tetrahedron (as a broad
    phase would deliver them); the offset is tuned so that about half intersect."""
    rng = np.random.default_rng(seed)
    ref = np.array([[1.0, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]]) / np.sqrt(8.0)
    rot, _ = np.linalg.qr(rng.normal(size=(npairs, 3, 3)))
    x_tet = ref[None] @ rot + 0.15 * rng.normal(size=(npairs, 4, 3))
    centre = x_tet.mean(axis=1, keepdims=True)
    x_tri = centre + 0.25 * rng.normal(size=(npairs, 1, 3)) + 0.5 * rng.normal(size=(npairs, 3, 3))
    x = np.concatenate([x_tri, x_tet], axis=1).reshape(-1, 3)
    base = 7 * np.arange(npairs)
    tri = base[:, None] + np.arange(3)
    tet = base[:, None] + 3 + np.arange(4)
    depth = rng.uniform(0.0, 0.5, size=len(x))
    pairs = np.arange(npairs)
    return x, depth, tri, tet, pairs


def grouped_pairs(npairs: int, per: int = 20, seed: int = 1):
    """Candidate pairs as a broad phase delivers them, grouped by triangle: random triangles of
    unit size, each with ``per`` unit-size tetrahedra of random shape and orientation around it
    (the triangles far apart); about 40 % of the pairs intersect.

    Returns:
        x, tri, tet, pair_tri, pair_tet.
    """
    rng = np.random.default_rng(seed)
    ntri = npairs // per
    nk = ntri * per
    ref = np.array([[1.0, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]]) / np.sqrt(8.0)
    rot, _ = np.linalg.qr(rng.normal(size=(nk, 3, 3)))
    centre = 10.0 * rng.normal(size=(ntri, 1, 3))
    x_tri = centre + 0.5 * rng.normal(size=(ntri, 3, 3))
    x_tet = ref[None] @ rot + 0.15 * rng.normal(size=(nk, 4, 3))
    x_tet += np.repeat(centre, per, axis=0) + 0.3 * rng.normal(size=(nk, 1, 3))
    x = np.concatenate([x_tri.reshape(-1, 3), x_tet.reshape(-1, 3)])
    tri = np.arange(3 * ntri).reshape(ntri, 3)
    tet = 3 * ntri + np.arange(4 * nk).reshape(nk, 4)
    return x, tri, tet, np.repeat(np.arange(ntri), per), np.arange(nk)


def best_rate(fun, npairs: int, repeat: int) -> float:
    fun()  # JIT (or load from cache) outside the timing
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fun()
        best = min(best, time.perf_counter() - t0)
    return npairs / best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--pairs", type=int, default=200_000)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    npairs = args.pairs
    x, depth, tri, tet, pairs = candidate_pairs(npairs)
    flags = np.empty(npairs, dtype=bool)
    hit = intersect_pairs(x, tri, tet, pairs, pairs, flags)
    print(f"pairs: {npairs}, intersecting: {hit} ({100.0 * hit / npairs:.1f} %)")
    gx, gtri, gtet, gpair_tri, gpair_tet = grouped_pairs(npairs)
    gflags = np.empty(len(gpair_tri), dtype=bool)
    ghit = intersect_pairs(gx, gtri, gtet, gpair_tri, gpair_tet, gflags)
    print(
        f"grouped: {len(gpair_tri)} pairs of {len(gtri)} triangles, intersecting: {ghit} "
        f"({100.0 * ghit / len(gpair_tri):.1f} %)"
    )
    print("one core: the drivers loop serially (no prange)")

    # Newton-loop use: outputs preallocated once and reused (area_pairs_into writes the
    # contributing pairs compactly); the Hessian output is 3.5 kB per pair, so that figure is
    # taken on a slice to keep memory modest
    nh = min(npairs, 50_000)
    active = np.empty(npairs, dtype=np.int64)
    energy = np.empty(npairs)
    grad = np.empty((npairs, 21))
    hess = np.empty((nh, 21, 21))
    no_hess = np.empty((0, 21, 21))
    rates = {
        "intersection": best_rate(
            lambda: intersect_pairs(x, tri, tet, pairs, pairs, flags), npairs, args.repeat
        ),
        # the same test on candidates grouped by triangle (per-triangle work done once a group)
        "intersection, grouped": best_rate(
            lambda: intersect_pairs(gx, gtri, gtet, gpair_tri, gpair_tet, gflags),
            len(gpair_tri),
            args.repeat,
        ),
        "energy+gradient": best_rate(
            lambda: area_pairs_into(
                x, depth, tri, tet, pairs, pairs, 1.0, True, False, active, energy, grad, no_hess
            ),
            npairs,
            args.repeat,
        ),
        "energy+gradient+hessian": best_rate(
            lambda: area_pairs_into(
                x,
                depth,
                tri,
                tet,
                pairs[:nh],
                pairs[:nh],
                1.0,
                True,
                True,
                active[:nh],
                energy[:nh],
                grad[:nh],
                hess,
            ),
            nh,
            args.repeat,
        ),
    }
    energy_only = best_rate(
        lambda: area_pairs_into(
            x, depth, tri, tet, pairs, pairs, 1.0, False, False, active, energy, grad, no_hess
        ),
        npairs,
        args.repeat,
    )
    # the allocating driver (fresh zeroed (np, 21, 21) output each call: page faults included)
    alloc_h = best_rate(
        lambda: area_pairs(x, depth, tri, tet, pairs[:nh], pairs[:nh], 1.0, True, True),
        nh,
        args.repeat,
    )
    print(f"{'kernel':<26}{'pairs/s':>14}{'target':>12}{'ratio':>8}")
    for name, rate in rates.items():
        target = TARGETS[name]
        print(f"{name:<26}{rate:>14.3e}{target:>12.1e}{rate / target:>8.2f}")
    print(f"{'energy only':<26}{energy_only:>14.3e}")
    print(f"{'e+g+h, allocating driver':<26}{alloc_h:>14.3e}")

    # collocation baseline: every triangle vertex against its tetrahedron
    node = tri.ravel()
    ktet = np.repeat(pairs, 3)
    weight = np.full(len(x), 0.1)
    col_g = best_rate(
        lambda: collocation_pairs(x, depth, weight, tet, node, ktet, 1.0, True, False),
        len(node),
        args.repeat,
    )
    col_h = best_rate(
        lambda: collocation_pairs(x, depth, weight, tet, node[:nh], ktet[:nh], 1.0, True, True),
        nh,
        args.repeat,
    )
    print(f"{'collocation grad':<26}{col_g:>14.3e}")
    print(f"{'collocation grad+hess':<26}{col_h:>14.3e}")


if __name__ == "__main__":
    main()
