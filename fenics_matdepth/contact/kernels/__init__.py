"""Numba pair kernels of the material-depth penalty contact energy, with exact derivatives.

Two integrations of the same penalty energy density ``(eps/2) g^2`` (``g`` = material depth,
P1-interpolated in the current tetrahedron):

* area integration (the paper's method), one (boundary triangle T, tetrahedron K) pair:
  ``E = (eps/2) int_{T cap K} g_K^2 dA = eps * A_T * Phi(Lam)``, with ``A_T`` the current area of
  T, ``Lam[i, j] = lambda_j(x_i)`` the barycentric coordinates of the triangle vertices in K and
  ``Phi = int_P (G . mu)^2 dxi`` over the clipped polygon P of the parameter simplex
  (``G = Lam @ d``). 21 dofs: triangle vertices 0..2 then tetrahedron vertices 0..3, xyz
  interleaved.
* point collocation (baseline), one (boundary vertex a, tetrahedron K) pair:
  ``E = (eps/2) W_a g_K(x_a)^2`` if ``x_a`` is in K (all barycentrics >= 0), else 0. 15 dofs.

Gradients and Hessians are the exact derivatives of these per-pair energies (including the
motion of polygon edges that lie on tetrahedron faces); see ``docs/kernels.md`` for the
derivation: ``Phi`` is differentiated with respect to the 12 numbers ``Lam`` through the
polygon vertices (each the meeting point of two lines whose coefficients are columns of
``Lam``), then the chain rule through ``Lam(x)`` and ``A_T(x)`` uses the closed forms
``d lambda_j / d y = grad lambda_j`` and ``d lambda_j / d X_k = -lambda_k grad lambda_j``.

Units: coordinates in length, depths in length, penalty in pressure / length, energies in
energy; gradients in energy / length, Hessians in energy / length^2.

Modules, one concept each:

* `area`: one area pair (`area.area_pair`) and its named work arrays; its derivative helpers
  in `area_derivatives`;
* `split`: tetrahedra split around their centroid (thin layers);
* `drivers`: the area kernel over many pairs (plain, into preallocated arrays, summed into
  per-dof sums and pattern blocks) and the exact intersection test over pairs;
* `polygon`: the intersection polygon without derivatives (largest depth reached on it);
* `augmented`: augmented-Lagrangian pair energies and the pressure moments;
* `collocation`: point collocation and the depth at points;
* `one_pair`: the numpy one-pair helpers re-exported here;
* `fastmath`: the kernels' floating-point licence.
"""

from __future__ import annotations

from fenics_matdepth.contact.kernels.one_pair import (
    augmented_pair_energy,
    collocation_energy,
    pair_energy,
    pressure_moments,
)

__all__ = [
    "augmented_pair_energy",
    "collocation_energy",
    "pair_energy",
    "pressure_moments",
]
