"""What the contact state looks like: penetration, forces and pressures per vertex and body.

Functions of a contact operator's state at its last update: what a rank holds (a
:class:`~fenics_matdepth.contact.surface.ContactSurface`) and the pairs its kernels evaluated.
:class:`~fenics_matdepth.ContactOperator` calls them from its methods of the same names, which
document what the values mean; all are collective and return the same values on every rank.

Each pair is evaluated on one rank (its contact element's owner), so sums and maxima over the
ranks of the per-pair values are those of the whole mesh.
"""

from __future__ import annotations

import typing

from mpi4py import MPI

import numpy as np

from fenics_matdepth._constants import FLOAT
from fenics_matdepth.contact.kernels.augmented import area_pairs_pressure_moments
from fenics_matdepth.contact.kernels.collocation import point_depths
from fenics_matdepth.contact.kernels.polygon import area_pairs_max_depth
from fenics_matdepth.contact.surface import ContactSurface

__all__ = [
    "deepest_contact",
    "force_resultants",
    "max_penetration",
    "pair_depths",
    "peak_pressure",
    "pressure_moments",
    "vertex_penetration",
]


def pair_depths(
    surface: ContactSurface,
    integration: str,
    penalty: float,
    pair_a: np.ndarray,
    pair_k: np.ndarray,
    energy: np.ndarray,
) -> np.ndarray:
    """The deepest material depth (L) of each evaluated pair (this rank's).

    Args:
        surface: what the rank holds.
        integration: ``"area"`` or ``"collocation"``.
        penalty: the penalty parameter eps the energies were evaluated with.
        pair_a, pair_k: the evaluated pairs: area integration, the intersecting ones (the
            depth is the maximum of ``g_K`` over each polygon); collocation, every candidate
            (the depth of its vertex, from its energy).
        energy: (n,) the pairs' energies (used with collocation only).
    """
    s = surface
    if integration == "area":
        return area_pairs_max_depth(s.x, s.kernel_depth, s.tri, s.kernel_tets, pair_a, pair_k)
    w = s.weight[s.nodes[pair_a]]
    return np.sqrt(2.0 * energy / (penalty * w))


def max_penetration(surface: ContactSurface, g: np.ndarray) -> float:
    """The largest of the pairs' depths ``g`` (:func:`pair_depths`) over the ranks, 0 without
    pairs (L)."""
    local = float(g.max()) if g.size else 0.0
    return surface.comm.allreduce(local, op=MPI.MAX)


def vertex_penetration(surface: ContactSurface, integration: str) -> np.ndarray:
    """Material depth reached by each boundary vertex, ``(num_vertices,)`` in the global vertex
    numbering (L; see :meth:`fenics_matdepth.ContactOperator.vertex_penetration`)."""
    s = surface
    local = np.zeros(s.num_vertices, dtype=FLOAT)
    # the boundary vertices of this rank's contact elements: the halo holds every
    # tetrahedron near them
    verts = np.unique(s.tri) if integration == "area" else s.nodes
    if verts.size and s.tree is not None:
        points = np.ascontiguousarray(s.x[verts])
        # a hair of margin: a point on a tetrahedron's face stays a candidate whatever
        # the rounding of the boxes
        qa, qk = s.tree.query_boxes(points, points, margin=1e-12 * s.mean_edge)
        keep = np.all(s.tets[qk] != verts[qa, None], axis=1)
        qa, qk = qa[keep], qk[keep]
        g = point_depths(s.x, s.kernel_depth, s.kernel_tets, points, qa, qk)
        np.maximum.at(local, s.global_vertex[verts[qa]], g)
    out = np.empty_like(local)
    s.comm.Allreduce(local, out, op=MPI.MAX)
    return out


def deepest_contact(
    surface: ContactSurface,
    integration: str,
    g: np.ndarray,
    pair_a: np.ndarray,
    pair_k: np.ndarray,
) -> dict[str, typing.Any] | None:
    """Where the contact surface reaches deepest: the pair of largest depth ``g`` over the
    ranks, described as :meth:`fenics_matdepth.ContactOperator.deepest_contact` says, or
    ``None`` where nothing penetrates.

    Args:
        surface: what the rank holds.
        integration: ``"area"`` or ``"collocation"``.
        g: (n,) the pairs' depths (:func:`pair_depths`).
        pair_a, pair_k: the pairs of ``g``.
    """
    s = surface
    best = (0.0, None)
    if g.size and g.max() > 0.0:
        p = int(np.argmax(g))
        if integration == "area":
            surf = s.tri[pair_a[p]]
            edges = s.X[surf[[1, 2, 0]]] - s.X[surf]
            local_h = float(np.linalg.norm(edges, axis=1).mean())
        else:
            surf, local_h = s.nodes[pair_a[p]][None], None
        tet = s.tets[pair_k[p], :4]
        best = (
            float(g[p]),
            {
                "depth": float(g[p]),
                "surface_vertices": s.global_vertex[surf].tolist(),
                "tetrahedron_vertices": s.global_vertex[tet].tolist(),
                "surface_reference": s.X[surf].mean(axis=0).tolist(),
                "tetrahedron_reference": s.X[tet].mean(axis=0).tolist(),
                "surface_position": s.x[surf].mean(axis=0).tolist(),
                "local_h": local_h,
            },
        )
    # the deepest over the ranks, the lowest rank's on a tie
    return max(s.comm.allgather(best), key=lambda b: b[0])[1]


def force_resultants(surface: ContactSurface, verts: np.ndarray, grad: np.ndarray) -> np.ndarray:
    """Net contact force ``-dE/dx`` summed over each body's vertices, ``(num_bodies, 3)``
    (force units).

    Args:
        surface: what the rank holds.
        verts: (n, m) the held vertices of the evaluated pairs.
        grad: (n, 3 m) their energy gradients.
    """
    out = np.zeros((surface.num_bodies, 3), dtype=FLOAT)
    if verts.size:
        body = np.repeat(surface.body[verts.ravel()], 3)
        comp = np.tile(np.arange(3), verts.size)
        np.add.at(out, (body, comp), -grad.ravel())
    return surface.comm.allreduce(out)


def peak_pressure(
    surface: ContactSurface,
    g: np.ndarray,
    pair_a: np.ndarray,
    penalty: float,
    pressure: np.ndarray | None,
    width: float,
) -> np.ndarray:
    """Per vertex, the largest ``k g`` over the penetrating boundary triangles around it,
    ``k`` the pair's stiffness (``penalty``, plus ``p_T / width`` with the quadratic pressure
    term), 0 elsewhere; ``(num_vertices,)`` in the global vertex numbering (pressure units).

    Args:
        surface: what the rank holds.
        g: (n,) the depths of the intersecting area pairs (:func:`pair_depths`).
        pair_a: (n,) their triangles.
        penalty: the penalty parameter eps.
        pressure: the nodal pressures of the augmented Lagrangian, or ``None``.
        width: the width of its quadratic pressure term (0: none).
    """
    s = surface
    verts = s.global_vertex[s.tri[pair_a]]
    stiffness = np.full(g.shape, penalty)
    if pressure is not None and width > 0.0:
        stiffness += pressure[verts].mean(axis=1) / width
    peak = np.zeros(s.num_vertices)
    for c in range(3):
        np.maximum.at(peak, verts[:, c], stiffness * g)
    s.comm.Allreduce(MPI.IN_PLACE, peak, op=MPI.MAX)
    return peak


def pressure_moments(
    surface: ContactSurface, pair_a: np.ndarray, pair_k: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per vertex, ``int mu_i g dA`` (L^3) and ``int mu_i dA`` (L^2) summed over the
    intersection polygons of the pairs (the Uzawa update's data), global vertex numbering.

    Args:
        surface: what the rank holds.
        pair_a, pair_k: the intersecting area pairs.
    """
    s = surface
    gmom, amom = area_pairs_pressure_moments(
        s.x, s.kernel_depth, s.tri, s.kernel_tets, pair_a, pair_k
    )
    # each pair is evaluated on one rank (its triangle's owner): the sums over ranks are
    # the moments
    verts = s.global_vertex[s.tri[pair_a].ravel()]
    n = s.num_vertices
    local = np.vstack(
        (
            np.bincount(verts, weights=gmom.ravel(), minlength=n),
            np.bincount(verts, weights=amom.ravel(), minlength=n),
        )
    )
    total = np.empty_like(local)
    s.comm.Allreduce(local, total, op=MPI.SUM)
    return total[0], total[1]
