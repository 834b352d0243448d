"""One-pair helpers over the batch kernels (numpy in and out; vertex order: triangle or
vertex first, then the tetrahedron, xyz interleaved), re-exported by
`fenics_matdepth.contact.kernels`."""

from __future__ import annotations

import numpy as np

from fenics_matdepth._constants import FLOAT, INDEX
from fenics_matdepth.contact.kernels.augmented import (
    area_pairs_augmented,
    area_pairs_pressure_moments,
)
from fenics_matdepth.contact.kernels.collocation import collocation_pairs
from fenics_matdepth.contact.kernels.drivers import area_pairs

__all__ = [
    "augmented_pair_energy",
    "collocation_energy",
    "pair_energy",
    "pressure_moments",
]

# triangle of the single-pair helper (its tetrahedron is 3..6)
_ONE_TRI = np.array([[0, 1, 2]], dtype=INDEX)


def _one_pair_arrays(
    x_first: np.ndarray, x_tet: np.ndarray, depth_tet: np.ndarray, centroid_depth: float | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertex, depth and tetrahedron arrays of a single pair: the first points, then the
    tetrahedron's four vertices, then (when ``centroid_depth`` is given) the centroid's depth
    as the fifth column of the tetrahedron."""
    xt = np.ascontiguousarray(x_tet, dtype=FLOAT).reshape(4, 3)
    dt = np.ascontiguousarray(depth_tet, dtype=FLOAT).reshape(4)
    nf = x_first.shape[0]
    x = np.vstack([x_first, xt])
    depth = np.concatenate([np.zeros(nf, dtype=FLOAT), dt])
    tet = np.arange(nf, nf + 4, dtype=INDEX).reshape(1, 4)
    if centroid_depth is not None:
        centroid_depth = float(centroid_depth)
        if not (np.isfinite(centroid_depth) and centroid_depth > 0.0):
            raise ValueError(f"centroid_depth must be a positive length, got {centroid_depth}")
        depth = np.append(depth, centroid_depth)
        tet = np.array([[nf, nf + 1, nf + 2, nf + 3, nf + 4]], dtype=INDEX)
    return x, depth, tet


def pair_energy(
    x_tri: np.ndarray,
    x_tet: np.ndarray,
    depth_tet: np.ndarray,
    penalty: float,
    centroid_depth: float | None = None,
) -> tuple[float, np.ndarray, np.ndarray]:
    """Area-integrated penalty energy of one (triangle, tetrahedron) pair, exact derivatives.

    Args:
        x_tri: (3, 3) current triangle vertex coordinates (length).
        x_tet: (4, 3) current tetrahedron vertex coordinates (length).
        depth_tet: (4,) material depths of the tetrahedron vertices (length).
        penalty: eps (pressure / length).
        centroid_depth: if given (length, > 0), the tetrahedron is split into four
            sub-tetrahedra around its centroid, which carries this depth (the remedy the
            contact operator applies to tetrahedra whose four vertices have depth 0); the
            derivatives are still over the 7 vertices.

    Returns:
        ``(E, grad, hess)``: energy ``(eps/2) int_{T cap K} g^2 dA`` (energy), gradient (21,)
        and Hessian (21, 21) over the triangle then tetrahedron vertex coordinates, xyz
        interleaved.
    """
    xs = np.ascontiguousarray(x_tri, dtype=FLOAT).reshape(3, 3)
    x, depth, tet = _one_pair_arrays(xs, x_tet, depth_tet, centroid_depth)
    one = np.zeros(1, dtype=INDEX)
    energy, grad, hess = area_pairs(x, depth, _ONE_TRI, tet, one, one, penalty, True, True)
    return float(energy[0]), grad[0], hess[0]


def collocation_energy(
    x_node: np.ndarray,
    x_tet: np.ndarray,
    depth_tet: np.ndarray,
    weight: float,
    penalty: float,
    centroid_depth: float | None = None,
) -> tuple[float, np.ndarray, np.ndarray]:
    """Point-collocation penalty energy of one (vertex, tetrahedron) pair, exact derivatives.

    Args:
        x_node: (3,) current vertex coordinates (length).
        x_tet: (4, 3) current tetrahedron vertex coordinates (length).
        depth_tet: (4,) material depths of the tetrahedron vertices (length).
        weight: W_a, the area the vertex represents (length^2).
        penalty: eps (pressure / length).
        centroid_depth: as in :func:`pair_energy` (split around the centroid).

    Returns:
        ``(E, grad, hess)``: ``(eps/2) W g(x_a)^2`` if the vertex is in the tetrahedron, else 0;
        gradient (15,) and Hessian (15, 15) over the vertex then tetrahedron coordinates.
    """
    xa = np.ascontiguousarray(x_node, dtype=FLOAT).reshape(1, 3)
    x, depth, tet = _one_pair_arrays(xa, x_tet, depth_tet, centroid_depth)
    weights = np.full(5, weight, dtype=FLOAT)
    zero = np.zeros(1, dtype=INDEX)
    energy, grad, hess = collocation_pairs(x, depth, weights, tet, zero, zero, penalty, True, True)
    return float(energy[0]), grad[0], hess[0]


def augmented_pair_energy(
    x_tri: np.ndarray,
    x_tet: np.ndarray,
    depth_tet: np.ndarray,
    penalty: float,
    pressure_tri: np.ndarray,
    centroid_depth: float | None = None,
    width: float = 0.0,
) -> tuple[float, np.ndarray, np.ndarray]:
    """Augmented-Lagrangian energy of one (triangle, tetrahedron) pair, exact derivatives.

    Args:
        x_tri, x_tet, depth_tet, penalty, centroid_depth: as :func:`pair_energy`.
        pressure_tri: (3,) nodal contact pressures of the triangle's vertices (pressure).
        width: 0: the linear pressure term; ``w > 0``: the quadratic one (see ``width`` of
            `area_pairs_augmented`).

    Returns:
        ``(E, grad, hess)``: ``int_{T cap K} (p g + (eps/2) g^2) dA`` with ``p`` interpolated
        linearly on the triangle, or ``((eps + p_mean / w) / 2) int_{T cap K} g^2 dA`` (energy),
        gradient (21,) and Hessian (21, 21) as :func:`pair_energy`.
    """
    xs = np.ascontiguousarray(x_tri, dtype=FLOAT).reshape(3, 3)
    x, depth, tet = _one_pair_arrays(xs, x_tet, depth_tet, centroid_depth)
    pressure = np.zeros(depth.shape[0], dtype=FLOAT)
    pressure[:3] = np.asarray(pressure_tri, dtype=FLOAT).reshape(3)
    one = np.zeros(1, dtype=INDEX)
    energy, grad, hess = area_pairs_augmented(
        x, depth, _ONE_TRI, tet, one, one, penalty, pressure, float(width), True, True
    )
    return float(energy[0]), grad[0], hess[0]


def pressure_moments(
    x_tri: np.ndarray,
    x_tet: np.ndarray,
    depth_tet: np.ndarray,
    centroid_depth: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """``int_{T cap K} mu_i g dA`` and ``int_{T cap K} mu_i dA`` for the 3 triangle vertices.

    Args:
        x_tri, x_tet, depth_tet, centroid_depth: as :func:`pair_energy`.

    Returns:
        ``(gmom (3,), amom (3,))`` (length^3, length^2).
    """
    xs = np.ascontiguousarray(x_tri, dtype=FLOAT).reshape(3, 3)
    x, depth, tet = _one_pair_arrays(xs, x_tet, depth_tet, centroid_depth)
    one = np.zeros(1, dtype=INDEX)
    gmom, amom = area_pairs_pressure_moments(x, depth, _ONE_TRI, tet, one, one)
    return gmom[0], amom[0]
