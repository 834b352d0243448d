"""Candidate (contact element, tetrahedron) pairs and the vertex couplings of the sparsity
pattern, from what a rank holds (a :class:`~fenics_matdepth.contact.surface.ContactSurface`),
and :class:`PairSearch`, the candidate pairs an operator keeps from one search to the next.

Contact elements are the boundary triangles this rank owns (area integration) or the boundary
vertices it owns (collocation), so every pair is found, and evaluated, by exactly one rank.
Pairs sharing a vertex (a triangle against the tetrahedra around it) are not contacts and are
left out by vertex number, which is one-to-one with the global vertex numbers.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse

from fenics_matdepth._constants import INDEX
from fenics_matdepth.contact.kernels.drivers import intersecting
from fenics_matdepth.contact.surface import ContactSurface
from fenics_matdepth.geometry.boxes import element_boxes, overlapping_pairs
from fenics_matdepth.geometry.bvh import AABBTree
from fenics_matdepth.geometry.intersect import near_pairs

__all__ = [
    "PairSearch",
    "candidate_pairs",
    "coupling_keys",
    "pair_vertices",
    "pairs_holding",
    "pairs_touching",
    "pattern_keys",
    "search_order",
]

#: Default skin of the candidate pairs (area integration), in mean boundary edge lengths (see
#: :attr:`PairSearch.skin`).
PAIR_SKIN = 0.1

#: A :class:`PairSearch` update searches again only round the vertices that moved while their
#: contact elements and tetrahedra are at most this fraction of the rank's; past it, everywhere.
PARTIAL_SEARCH_SHARE = 0.25


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
        # a triangle's boxes overlap the tetrahedra round its own vertices, which are no
        # contacts: left out as the tree finds them (exclude_shared_vertex_pairs' answer)
        return surface.tree.query_boxes(lo, hi, margin=margin, apart=(surface.tri, tets))
    pts = x[surface.nodes]
    qa, qk = surface.tree.query_boxes(pts, pts, margin=margin)
    keep = np.all(tets[qk] != surface.nodes[qa, None], axis=1)
    return qa[keep], qk[keep]


def _round_pairs(
    x: np.ndarray,
    tri: np.ndarray,
    tets: np.ndarray,
    tri_near: np.ndarray,
    tet_near: np.ndarray,
    tet_tree: AABBTree,
    tri_tree: AABBTree,
    margin: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The (triangle, tetrahedron) pairs sharing no vertex whose boxes at ``x`` overlap within
    ``margin``, of the triangles marked in ``tri_near`` or the tetrahedra marked in
    ``tet_near``, each once (in no particular order). ``tet_tree`` and ``tri_tree`` are trees
    over ``tets`` and ``tri`` at ``x``."""
    ta, kb = np.flatnonzero(tri_near), np.flatnonzero(tet_near)
    lo, hi = element_boxes(x, tri[ta])
    qa, qk = tet_tree.query_boxes(lo, hi, margin=margin, apart=(tri[ta], tets))
    # the marked tetrahedra against the triangles not marked (the others were queried above)
    lo, hi = element_boxes(x, tets[kb])
    qk2, qa2 = tri_tree.query_boxes(lo, hi, margin=margin, apart=(tets[kb], tri))
    other = ~tri_near[qa2]
    return (
        np.concatenate((ta[qa], qa2[other])).astype(INDEX),
        np.concatenate((qk, kb[qk2[other]])).astype(INDEX),
    )


def search_order(surface: ContactSurface, pa: np.ndarray, pk: np.ndarray) -> np.ndarray:
    """The order in which a search of the whole surface lists the area pairs ``(pa, pk)``:
    by contact element, then by the tetrahedra's order in the surface's tree (the order of
    :func:`candidate_pairs`' answer, whatever order the pairs were found in)."""
    position = np.empty(surface.tets.shape[0], dtype=INDEX)
    position[surface.tree.order] = np.arange(surface.tets.shape[0], dtype=INDEX)
    keys = pa.astype(INDEX) * surface.tets.shape[0] + position[pk]
    return np.argsort(keys, kind="stable")


def pairs_touching(
    surface: ContactSurface, held: np.ndarray, margin: float
) -> tuple[np.ndarray, np.ndarray]:
    """The area pairs holding a vertex marked in ``held`` (a mask over the held vertices) whose
    boxes overlap within ``margin`` now: those of :func:`candidate_pairs` with that margin that
    hold such a vertex, in its order, found by a search round them only."""
    if surface.tree is None or surface.tri.shape[0] == 0:
        return np.empty(0, dtype=INDEX), np.empty(0, dtype=INDEX)
    x, tri, tets = surface.x, surface.tri, surface.tets
    pa, pk = _round_pairs(
        x, tri, tets, held[tri].any(axis=1), held[tets].any(axis=1), surface.tree,
        AABBTree(x, tri), margin,
    )  # fmt: skip
    order = search_order(surface, pa, pk)
    return pa[order], pk[order]


def pair_vertices(
    surface: ContactSurface, integration: str, pa: np.ndarray, pk: np.ndarray
) -> np.ndarray:
    """The (held) vertices of each pair: (n, 7) for area pairs, (n, 5) for collocation."""
    if integration == "area":
        return np.hstack((surface.tri[pa], surface.tets[pk]))
    return np.hstack((surface.nodes[pa, None], surface.tets[pk]))


def pairs_holding(
    surface: ContactSurface, integration: str, pa: np.ndarray, pk: np.ndarray, held: np.ndarray
) -> np.ndarray:
    """Whether each pair holds one of the vertices marked in ``held`` (a mask over the
    surface's held vertices), without :func:`pair_vertices`' table of every pair."""
    if integration == "area":
        element = held[surface.tri[pa]].any(axis=1)
    else:
        element = held[surface.nodes[pa]]
    return element | held[surface.tets[pk]].any(axis=1)


def pattern_keys(
    surface: ContactSurface,
    integration: str,
    margin: float,
    search: PairSearch | None = None,
) -> np.ndarray:
    """Sorted global vertex-coupling keys ``vi * num_vertices + vj`` of the pairs within
    ``margin`` (the contact part of the matrix sparsity pattern on this rank).

    The candidates are ``search``'s where they are those of a search with ``margin`` at the
    surface's state (:meth:`PairSearch.searched_now`: the same pairs in the same order, so the
    same keys; 20 of 41 rebuilds in the knee's last three steps), else searched here."""
    found = search.searched_now(surface, margin) if search is not None else None
    pa, pk = found if found is not None else candidate_pairs(surface, integration, margin)
    if integration == "area":
        # boxes inflated by the margin overlap for far more pairs than come within the
        # margin (7x more than the active pairs on a flat interface); the couplings of the
        # others would be explicit zeros that the factorisation treats as nonzeros
        pa, pk = near_pairs(surface.x, surface.tri, surface.tets, pa, pk, margin)
    verts = surface.global_vertex[pair_vertices(surface, integration, pa, pk)]
    return coupling_keys(verts, surface.num_vertices)


def coupling_keys(verts: np.ndarray, num_vertices: int) -> np.ndarray:
    """Sorted unique keys ``vi * num_vertices + vj`` of every two vertices (each with itself
    too) in one row of ``verts`` ((n, m) global vertex numbers below ``num_vertices``).

    As the pattern of ``P^T P``, ``P`` the rows' incidence matrix: SciPy's sparse product
    marks each row's couplings without sorting them all (on 50k rows of 7 vertices within 60
    of one another, 0.07 s where the unique of the n m^2 keys took 0.22 s)."""
    verts = np.asarray(verts, dtype=INDEX)
    n, m = verts.shape
    if n == 0:
        return np.empty(0, dtype=INDEX)
    rows = np.repeat(np.arange(n, dtype=INDEX), m)
    # int32 counts: the product sums them, and a sum that wrapped to 0 would drop an entry
    P = scipy.sparse.csr_matrix(
        (np.ones(n * m, dtype=np.int32), (rows, verts.ravel())), shape=(n, num_vertices)
    )
    G = (P.T @ P).tocsr()
    G.sort_indices()
    first = np.repeat(np.arange(num_vertices, dtype=INDEX), np.diff(G.indptr))
    return first * num_vertices + G.indices.astype(INDEX)


class PairSearch:
    """The candidate pairs of the last pair search, kept while they cannot miss a contact.

    Args:
        integration: ``"area"`` or ``"collocation"`` (see
            :class:`~fenics_matdepth.ContactOperator`).
        skin: the initial :attr:`skin` (L).

    With area integration an update searches again only round the vertices that moved by more
    than 0.45 of the skin since they were last searched round (each vertex keeps the
    coordinates it had then), unless they hold more than ``PARTIAL_SEARCH_SHARE`` of the
    contact elements or tetrahedra: the pairs of their elements and tetrahedra are searched
    anew at those coordinates, the others kept. Every pair not listed then has boxes more than
    the skin apart at its vertices' kept coordinates, from which no vertex is more than 0.45 of
    it away, so no pair whose boxes overlap now is missed. The list is a superset of what a
    whole search finds, in another order: :meth:`intersecting` gives its pairs in the order of
    a whole search (:func:`search_order`), so the contact sums are the same to the bit.

    Attributes:
        skin: the skin of the candidate pairs, in L. The search inflates the contact element
            boxes by it, and its pairs serve later updates until some held vertex has moved by
            more than about half of it (no pair can then have come into contact unseen). With
            0 every update searches, as collocation always does, whose kernel evaluates every
            candidate. Assignable; the next update searches with a new value.
        searches: the number of pair searches of the whole surface so far.
        partial_searches: the updates that searched round the moved vertices only.
        pair_a: (n,) contact element of each candidate pair (a row of ``surface.tri``, or a
            position in ``surface.nodes`` with collocation).
        pair_k: (n,) tetrahedron of each candidate pair (a row of ``surface.tets``).
    """

    def __init__(self, integration: str, skin: float):
        self.integration = integration
        self.skin = skin
        self.searches = 0
        self.partial_searches = 0
        self.pair_a = np.empty(0, dtype=INDEX)
        self.pair_k = np.empty(0, dtype=INDEX)
        # per held vertex, its coordinates when last searched round (the last search's for
        # collocation, which does not search in part)
        self._x_at_search: np.ndarray | None = None
        self._trees: tuple[AABBTree, AABBTree] | None = None  # at _x_at_search (partial)
        self._search_refreshes = -1  # the halo build of the last search
        self._searched_skin = 0.0  # the skin of the last search
        self._in_search_order = True  # the pairs as a whole search lists them

    def _whole_search_needed(self, surface: ContactSurface) -> bool:
        """No skin or another skin than the last search's, no search yet, or a new halo."""
        return (
            self.skin <= 0.0
            or self.skin != self._searched_skin
            or self._x_at_search is None
            or surface.refreshes != self._search_refreshes
        )

    def _moved(self, surface: ContactSurface) -> np.ndarray:
        """Per held vertex, whether it moved by more than 0.45 of the skin since it was last
        searched round (two boxes that overlap now were then at most twice that apart per
        axis, within the skin the search inflated the boxes by; the tenth spared covers
        rounding)."""
        return ~(np.abs(surface.x - self._x_at_search).max(axis=1) <= 0.45 * self.skin)

    def update(self, surface: ContactSurface) -> None:
        """Search the candidate pairs again where they may miss a pair whose boxes now
        overlap (after ``surface.update()``): everywhere after a new halo or skin, round the
        vertices moved by more than 0.45 of the skin since they were last searched round."""
        if self._whole_search_needed(surface):
            self._search(surface)
            return
        moved = self._moved(surface)
        if not moved.any():
            return
        if self.integration != "area" or surface.tree is None:
            self._search(surface)
            return
        tri_near, tet_near = moved[surface.tri].any(axis=1), moved[surface.tets].any(axis=1)
        share = PARTIAL_SEARCH_SHARE
        if tri_near.sum() > share * tri_near.size or tet_near.sum() > share * tet_near.size:
            self._search(surface)
            return
        x = self._x_at_search
        x[moved] = surface.x[moved]
        if self._trees is None:
            self._trees = (AABBTree(x, surface.tets), AABBTree(x, surface.tri))
        else:
            for tree in self._trees:
                tree.refit(x)
                if tree.needs_rebuild():
                    tree.rebuild(x)
        kept = ~(tri_near[self.pair_a] | tet_near[self.pair_k])
        pa, pk = _round_pairs(
            x, surface.tri, surface.tets, tri_near, tet_near, *self._trees, self.skin
        )
        self.pair_a = np.concatenate((self.pair_a[kept], pa))
        self.pair_k = np.concatenate((self.pair_k[kept], pk))
        self._in_search_order = False
        self.partial_searches += 1

    def _search(self, surface: ContactSurface) -> None:
        """Search the whole surface; every vertex is searched round at its coordinates now."""
        self.pair_a, self.pair_k = candidate_pairs(surface, self.integration, self.skin)
        self._x_at_search = surface.x.copy()
        self._trees = None
        self._search_refreshes = surface.refreshes
        self._searched_skin = self.skin
        self._in_search_order = True
        self.searches += 1

    def searched_now(
        self, surface: ContactSurface, margin: float
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """The candidate pairs, where they are :func:`candidate_pairs` with ``margin`` at the
        surface's current state (the last search searched the whole surface with that skin,
        at these coordinates, on this halo), else None."""
        if not (
            self._in_search_order
            and self._searched_skin == margin
            and self._search_refreshes == surface.refreshes
            and self._x_at_search is not None
            and np.array_equal(self._x_at_search, surface.x)
        ):
            return None
        return self.pair_a, self.pair_k

    def intersecting(self, surface: ContactSurface) -> np.ndarray:
        """Indices of the candidate pairs whose intersection is not empty at the surface's
        current state, in the order of a whole search (area integration; not kept, see
        ``ContactOperator``)."""
        pa, pk = self.pair_a, self.pair_k
        if self._searched_skin > 0.0:
            # the pairs of the last search (boxes inflated by the skin) whose boxes overlap
            # now: those a search at this state would find (4 to 5.5 ms for 192k pairs on
            # bench_newton's press, against 34 ms for a search)
            near = overlapping_pairs(surface.x, surface.tri, surface.tets, pa, pk)
            hit = near[
                intersecting(surface.x, surface.tri, surface.kernel_tets, pa[near], pk[near])
            ]
            if not self._in_search_order:
                hit = hit[search_order(surface, pa[hit], pk[hit])]
            return hit
        return intersecting(surface.x, surface.tri, surface.kernel_tets, pa, pk)
