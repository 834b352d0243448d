"""Candidate (contact element, tetrahedron) pairs and the vertex couplings of the sparsity
pattern, from what a rank holds (a :class:`~fenics_matdepth.contact.surface.ContactSurface`).

Contact elements are the boundary triangles this rank owns (area integration) or the boundary
vertices it owns (collocation), so every pair is found, and evaluated, by exactly one rank.
Pairs sharing a vertex (a triangle against the tetrahedra around it) are not contacts and are
left out by vertex number, which is one-to-one with the global vertex numbers.
"""

from __future__ import annotations

import numpy as np

from fenics_matdepth.contact.surface import ContactSurface
from fenics_matdepth.geometry.boxes import element_boxes, exclude_shared_vertex_pairs
from fenics_matdepth.geometry.intersect import near_pairs as _near_pairs

__all__ = ["candidate_pairs", "pair_vertices", "pattern_keys"]


def candidate_pairs(
    surface: ContactSurface, integration: str, margin: float
) -> tuple[np.ndarray, np.ndarray]:
    """(contact element, tetrahedron) pairs whose current boxes overlap within ``margin``.

    Returns:
        (element index, tetrahedron index) arrays: rows of ``surface.tri`` (area) or positions
        in ``surface.nodes`` (collocation), and rows of ``surface.tets``.
    """
    x, tets = surface.x, surface.tets
    if surface.tree is None:  # no tetrahedra held
        return np.empty(0, dtype=tets.dtype), np.empty(0, dtype=tets.dtype)
    if integration == "area":
        lo, hi = element_boxes(x, surface.tri)
        qa, qk = surface.tree.query_boxes(lo, hi, margin=margin)
        return exclude_shared_vertex_pairs(surface.tri, tets, qa, qk)
    pts = x[surface.nodes]
    qa, qk = surface.tree.query_boxes(pts, pts, margin=margin)
    keep = np.all(tets[qk] != surface.nodes[qa, None], axis=1)
    return qa[keep], qk[keep]


def pair_vertices(
    surface: ContactSurface, integration: str, pa: np.ndarray, pk: np.ndarray
) -> np.ndarray:
    """The (held) vertices of each pair: (n, 7) for area pairs, (n, 5) for collocation."""
    if integration == "area":
        return np.hstack((surface.tri[pa], surface.tets[pk]))
    return np.hstack((surface.nodes[pa, None], surface.tets[pk]))


def pattern_keys(surface: ContactSurface, integration: str, margin: float) -> np.ndarray:
    """Sorted global vertex-coupling keys ``vi * num_vertices + vj`` of the pairs within
    ``margin`` (the contact part of the matrix sparsity pattern on this rank)."""
    pa, pk = candidate_pairs(surface, integration, margin)
    if integration == "area":
        # boxes inflated by the margin overlap for far more pairs than come within the
        # margin (7x more than the active pairs on a flat interface); the couplings of the
        # others would be explicit zeros that the factorisation treats as nonzeros
        pa, pk = _near_pairs(surface.x, surface.tri, surface.tets, pa, pk, margin)
    verts = surface.global_vertex[pair_vertices(surface, integration, pa, pk)]
    n = verts.shape[1]
    a = np.repeat(verts, n, axis=1).ravel()
    b = np.tile(verts, (1, n)).ravel()
    return np.unique(a * surface.num_vertices + b)
