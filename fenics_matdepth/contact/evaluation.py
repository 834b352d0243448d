"""The pair kernels run over a rank's evaluated pairs, as the contact operator asks for them.

* :func:`pair_arrays`: per pair, the energy and, on request, its gradient and Hessian over the
  pair's vertices (area integration, with or without the augmented Lagrangian's nodal
  pressures, or collocation);
* :class:`SummedPass`: area integration with plain penalty, the gradient summed per held dof
  and the Hessian per 3 x 3 block of the sparsity pattern as the kernel makes them, into
  buffers kept from one state to the next.

Which pairs, and what is kept between calls, is the operator's business
(:class:`~fenics_matdepth.ContactOperator`).
"""

from __future__ import annotations

import numpy as np

from fenics_matdepth._constants import FLOAT, INDEX
from fenics_matdepth.contact.kernels.augmented import area_pairs_augmented
from fenics_matdepth.contact.kernels.collocation import collocation_pairs
from fenics_matdepth.contact.kernels.drivers import area_pairs, area_pairs_summed
from fenics_matdepth.contact.surface import ContactSurface

__all__ = ["SummedPass", "pair_arrays"]


def pair_arrays(
    surface: ContactSurface,
    integration: str,
    pair_a: np.ndarray,
    pair_k: np.ndarray,
    penalty: float,
    pressure: np.ndarray | None,
    width: float,
    want_grad: bool,
    want_hess: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pair kernel's (energy, gradient, Hessian) arrays of the pairs ``(pair_a, pair_k)``.

    Args:
        surface: what the rank holds.
        integration: ``"area"`` or ``"collocation"``.
        pair_a, pair_k: the pairs: rows of ``surface.tri`` (area) or positions in
            ``surface.nodes`` (collocation), and rows of ``surface.tets``.
        penalty: the penalty parameter eps (pressure / length).
        pressure: the augmented Lagrangian's nodal pressures (global vertex numbering), or
            ``None`` (area integration only).
        width: the width of its quadratic pressure term (L; 0: none).
        want_grad, want_hess: whether to compute the gradients and the Hessians.
    """
    s = surface
    if integration == "area":
        # the kernel arrays carry the split of depth-deficient tetrahedra; each pair
        # still comes out over its 7 original vertices
        if pressure is None:
            return area_pairs(
                s.x, s.kernel_depth, s.tri, s.kernel_tets, pair_a, pair_k, penalty,
                want_grad, want_hess,
            )  # fmt: skip
        # the pressures of the held vertices (the numbering changes with the halo)
        held_pressure = np.ascontiguousarray(pressure[s.global_vertex])
        return area_pairs_augmented(
            s.x, s.kernel_depth, s.tri, s.kernel_tets, pair_a, pair_k, penalty,
            held_pressure, width, want_grad, want_hess,
        )  # fmt: skip
    return collocation_pairs(
        s.x, s.kernel_depth, s.weight, s.kernel_tets, s.nodes[pair_a], pair_k, penalty,
        want_grad, want_hess,
    )  # fmt: skip


class SummedPass:
    """Area pairs with plain penalty, summed as the kernel makes them
    (``kernels.drivers.area_pairs_summed``), into output buffers reused from state to state.

    The sums are those of :func:`~fenics_matdepth.contact.assembly.gradient_array` and
    :func:`~fenics_matdepth.contact.assembly.add_jacobian_blocks` on the arrays of
    :func:`pair_arrays`, in the same order, but the (n, 21, 21) Hessians (36 MB on 10k pairs)
    are never written: each chunk of pairs is summed while in the cache.
    """

    def __init__(self):
        self._grad_sum = np.empty(0, dtype=FLOAT)
        self._reached = np.empty(0, dtype=bool)
        self._blocks = np.empty((0, 3, 3), dtype=FLOAT)
        self._touched = np.empty(0, dtype=bool)

    def __call__(
        self,
        surface: ContactSurface,
        pair_a: np.ndarray,
        pair_k: np.ndarray,
        penalty: float,
        positions: np.ndarray | None = None,
        keys: np.ndarray | None = None,
    ) -> dict[str, np.ndarray]:
        """The pairs' energies, their gradient summed per held dof and, given the pattern,
        their Hessians summed into its 3 x 3 blocks.

        Args:
            surface: what the rank holds (its Dirichlet mask ``bc`` leaves rows and columns
                out of the blocks).
            pair_a, pair_k: the intersecting area pairs.
            penalty: the penalty parameter eps (pressure / length).
            positions: the pattern index of every vertex coupling of the pairs
                (:func:`~fenics_matdepth.contact.assembly.coupling_positions`), or ``None``
                for no Hessian.
            keys: the pattern's couplings in the held numbering (with ``positions``).

        Returns:
            ``energy`` (n,), ``grad_sum`` and ``reached`` (per held dof) and, with the
            Hessian, ``blocks`` and ``touched`` (per pattern key): the buffers, valid until
            the next call.
        """
        want_hess = positions is not None
        n_dofs = 3 * surface.num_held
        if self._grad_sum.shape[0] != n_dofs:
            self._grad_sum = np.empty(n_dofs, dtype=FLOAT)
            self._reached = np.empty(n_dofs, dtype=bool)
        self._grad_sum.fill(0.0)
        self._reached.fill(False)
        if want_hess:
            nk = keys.size
            if self._blocks.shape[0] != nk:
                self._blocks = np.empty((nk, 3, 3), dtype=FLOAT)
                self._touched = np.empty(nk, dtype=bool)
            self._blocks.fill(0.0)
            self._touched.fill(False)
        else:
            positions = np.empty((0, 7, 7), dtype=INDEX)
            keys = np.empty(0, dtype=INDEX)
        s = surface
        energy = np.empty(pair_a.size, dtype=FLOAT)
        area_pairs_summed(
            s.x, s.kernel_depth, s.tri, s.kernel_tets, pair_a, pair_k, penalty, want_hess,
            positions, keys, s.bc, energy, self._grad_sum, self._reached, self._blocks,
            self._touched,
        )  # fmt: skip
        out = {"energy": energy, "grad_sum": self._grad_sum, "reached": self._reached}
        if want_hess:
            out["blocks"], out["touched"] = self._blocks, self._touched
        return out
