"""The pairs of a time step and their discrete gradients, over what a rank holds.

A step from the held coordinates ``x0`` to ``x1`` needs every (triangle, tetrahedron) pair
whose energy or midpoint gradient is not zero: the pairs that intersect at the start, the
midpoint or the end. They are found among the pairs whose *swept* boxes overlap (each
element's box over its positions at both ends, which holds its midpoint position too), then
tested exactly at the three states. The pair kernel runs at the three states and
`fenics_matdepth.contact.kernels.discrete_gradient` combines its values.
"""

from __future__ import annotations

import numpy as np

from fenics_matdepth._constants import FLOAT, INDEX
from fenics_matdepth.contact.kernels.discrete_gradient import (
    discrete_gradient_jacobians,
    discrete_gradients,
)
from fenics_matdepth.contact.kernels.drivers import area_pairs, intersecting
from fenics_matdepth.contact.pairs import pair_vertices
from fenics_matdepth.contact.surface import ContactSurface
from fenics_matdepth.geometry.boxes import element_boxes, exclude_shared_vertex_pairs
from fenics_matdepth.geometry.bvh import AABBTree

__all__ = ["StepPairs", "step_pairs"]


def step_pairs(
    surface: ContactSurface, x0: np.ndarray, x1: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The (triangle, tetrahedron) pairs that intersect at ``x0``, ``(x0 + x1) / 2`` or ``x1``.

    Args:
        surface: what the rank holds (its ``tri``, ``tets`` and ``kernel_tets``).
        x0, x1: (num_held, 3) held vertex coordinates at the step's start and end (L).

    Returns:
        The (triangle, tetrahedron) index arrays, rows of ``surface.tri`` and ``surface.tets``.
    """
    tets = surface.tets
    if tets.shape[0] == 0 or surface.tri.shape[0] == 0:
        return np.empty(0, dtype=INDEX), np.empty(0, dtype=INDEX)
    nh = x0.shape[0]
    both = np.ascontiguousarray(np.vstack((x0, x1)))
    # an element of 2k vertices, its k at both ends: its box is the swept box
    tree = AABBTree(both, np.hstack((tets, tets + nh)))
    lo, hi = element_boxes(both, np.hstack((surface.tri, surface.tri + nh)))
    qa, qk = tree.query_boxes(lo, hi)
    qa, qk = exclude_shared_vertex_pairs(surface.tri, tets, qa, qk)
    hit = np.zeros(qa.size, dtype=bool)
    for x in (x0, 0.5 * (x0 + x1), x1):
        hit[intersecting(x, surface.tri, surface.kernel_tets, qa, qk)] = True
    return qa[hit], qk[hit]


class StepPairs:
    """The discrete gradients of a step's pairs (:func:`step_pairs`), plain penalty with area
    integration, and on request their Jacobians with respect to the end state.

    Args:
        surface: what the rank holds, updated at the step's end (``surface.x`` is ``x1``).
        x0: (num_held, 3) held coordinates at the step's start, in the same numbering (L).
        penalty: eps (pressure / length).

    Attributes:
        verts: (n, 7) held vertices of each pair.
        energy0: (n,) pair energies at the step's start.
        energy_mid: (n,) pair energies at its midpoint.
        energy1: (n,) pair energies at its end.
        grad_mid: (n, 21) pair gradients at the midpoint.
        gradient: (n, 21) pair discrete gradients.
        coefficient: (n,) their ``c``.
    """

    def __init__(self, surface: ContactSurface, x0: np.ndarray, penalty: float):
        self.surface, self.penalty = surface, penalty
        self.x0 = np.ascontiguousarray(x0, dtype=FLOAT)
        self.x1 = surface.x
        self.pair_a, self.pair_k = step_pairs(surface, self.x0, self.x1)
        self.verts = pair_vertices(surface, "area", self.pair_a, self.pair_k)
        self.energy0 = self._pass(self.x0, False, False)[0]
        self.energy1 = self._pass(self.x1, False, False)[0]
        self.energy_mid, self.grad_mid, _ = self._pass(0.5 * (self.x0 + self.x1), True, False)
        n = self.verts.shape[0]
        self.gradient = np.empty((n, 21), dtype=FLOAT)
        self.coefficient = np.empty(n, dtype=FLOAT)
        discrete_gradients(
            self.x0, self.x1, self.verts, self.energy0, self.energy1, self.grad_mid,
            self.gradient, self.coefficient,
        )  # fmt: skip
        self._jacobian: np.ndarray | None = None

    def _pass(
        self, x: np.ndarray, want_grad: bool, want_hess: bool
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        s = self.surface
        return area_pairs(
            x, s.kernel_depth, s.tri, s.kernel_tets, self.pair_a, self.pair_k, self.penalty,
            want_grad, want_hess,
        )  # fmt: skip

    def jacobian(self) -> np.ndarray:
        """(n, 21, 21) derivatives of the discrete gradients with respect to the end state
        (computed once: the midpoint Hessians and the end gradients)."""
        if self._jacobian is None:
            _, _, hess_mid = self._pass(0.5 * (self.x0 + self.x1), True, True)
            _, grad1, _ = self._pass(self.x1, True, False)
            self._jacobian = np.empty((self.verts.shape[0], 21, 21), dtype=FLOAT)
            discrete_gradient_jacobians(
                self.x0, self.x1, self.verts, self.grad_mid, grad1, hess_mid, self.coefficient,
                self._jacobian,
            )  # fmt: skip
        return self._jacobian
