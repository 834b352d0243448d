"""Candidate pairs and the contact sparsity pattern (fenics_matdepth/contact/pairs.py) against a
brute-force test of every (boundary element, tetrahedron) box pair of a small model: two boxes,
the upper one sunk into the lower one, displaced by a smooth field. On several ranks, the
ranks' pairs together are the whole model's, each found once."""

from __future__ import annotations

import warnings

from mpi4py import MPI

import dolfinx
import numpy as np
import pytest
from test_operator import _two_boxes

import fenics_matdepth as fm
from fenics_matdepth.contact.pairs import (
    PairSearch,
    candidate_pairs,
    coupling_keys,
    pair_vertices,
    pairs_holding,
    pairs_touching,
    pattern_keys,
)
from fenics_matdepth.contact.surface import ContactSurface, DepthDeficiencyWarning
from fenics_matdepth.geometry import intersection_polygon


def two_box_surface(integration: str, perturbed: bool = True) -> ContactSurface:
    """The surface of two overlapping boxes (tests/test_operator.py), at its current state:
    displaced by a smooth, partition-independent field (no pair on a degenerate case) if
    ``perturbed``, else at the reference state."""
    mesh = _two_boxes(MPI.COMM_WORLD)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    if perturbed:
        x = V.tabulate_dof_coordinates()
        u.x.array[:] = (0.02 * np.sin([3.1, 2.3, 1.7] * x + np.array([0.3, 0.1, 0.7]))).ravel()
    with warnings.catch_warnings():  # tetrahedra with four boundary vertices are split
        warnings.simplefilter("ignore", DepthDeficiencyWarning)
        surface = ContactSurface(u, fm.material_depth(mesh), integration)
    surface.update()
    return surface


def _rows(a: np.ndarray) -> set[tuple]:
    return {tuple(int(v) for v in row) for row in a}


def _gathered_pairs(surface: ContactSurface, integration: str, margin: float) -> np.ndarray:
    """Every rank's candidate pairs as rows of global vertices (element's, then the sorted
    tetrahedron's), on every rank."""
    pa, pk = candidate_pairs(surface, integration, margin)
    verts = surface.global_vertex[pair_vertices(surface, integration, pa, pk)]
    m = 3 if integration == "area" else 1
    rows = np.hstack((verts[:, :m], np.sort(verts[:, m:], axis=1)))
    return np.vstack(surface.comm.allgather(rows))


def _brute_force_pairs(surface: ContactSurface, integration: str, margin: float) -> np.ndarray:
    """All (element, tetrahedron) pairs of the whole model whose boxes overlap when the
    element's is inflated by ``margin`` (closed boxes), sharing no vertex; rows of global
    vertices as in :func:`_gathered_pairs`."""
    comm = surface.comm
    model = surface.gathered()
    x, tets = model["x"], np.sort(model["tets"], axis=1)
    if integration == "area":
        elements = np.vstack(comm.allgather(surface.global_vertex[surface.tri]))
    else:
        elements = np.concatenate(comm.allgather(surface.global_vertex[surface.nodes]))[:, None]
    lo_e, hi_e = x[elements].min(axis=1) - margin, x[elements].max(axis=1) + margin
    lo_k, hi_k = x[tets].min(axis=1), x[tets].max(axis=1)
    overlap = np.all((lo_e[:, None] <= hi_k[None, :]) & (lo_k[None, :] <= hi_e[:, None]), axis=2)
    shared = np.zeros_like(overlap)
    for j in range(elements.shape[1]):
        shared |= np.any(tets[None, :, :] == elements[:, None, j, None], axis=2)
    e, k = np.nonzero(overlap & ~shared)
    return np.hstack((elements[e], tets[k]))


@pytest.mark.parametrize("integration", ["area", "collocation"])
def test_candidate_pairs_match_brute_force(integration):
    surface = two_box_surface(integration)
    margin = surface.margin
    assert margin > 0.0
    found = _gathered_pairs(surface, integration, margin)
    expected = _brute_force_pairs(surface, integration, margin)
    assert expected.shape[0] > 100  # the boxes overlap: a real test
    # each pair found once, on one rank, and exactly the brute-force ones
    assert np.unique(found, axis=0).shape[0] == found.shape[0]
    assert _rows(found) == _rows(expected)
    # no margin: fewer pairs, still exactly the brute-force ones
    tight = _gathered_pairs(surface, integration, 0.0)
    assert _rows(tight) == _rows(_brute_force_pairs(surface, integration, 0.0))
    assert tight.shape[0] < found.shape[0]


def test_pair_vertices_are_the_pairs_elements():
    """The held vertices of area pairs: the triangle's three, then the tetrahedron's four, all
    distinct (no pair shares a vertex); collocation pairs: the node, then the tetrahedron's."""
    for integration, m in (("area", 3), ("collocation", 1)):
        surface = two_box_surface(integration)
        pa, pk = candidate_pairs(surface, integration, surface.margin)
        verts = pair_vertices(surface, integration, pa, pk)
        assert verts.shape == (pa.size, m + 4)
        element = surface.tri[pa] if m == 3 else surface.nodes[pa, None]
        assert np.array_equal(verts[:, :m], element)
        assert np.array_equal(verts[:, m:], surface.tets[pk])
        assert all(len(set(row)) == m + 4 for row in verts.tolist())


@pytest.mark.parametrize("integration", ["area", "collocation"])
def test_pairs_holding_are_the_pairs_with_a_marked_vertex(integration):
    """The pairs holding one of a set of vertices, from a mask over the held vertices, are
    those of whose pair_vertices row one is in the set: for one vertex of a pair (its element's
    or its tetrahedron's), ten random held vertices, and none."""
    surface = two_box_surface(integration)
    pa, pk = candidate_pairs(surface, integration, surface.margin)
    verts = pair_vertices(surface, integration, pa, pk)
    rng = np.random.default_rng(3)
    sets = [np.empty(0, dtype=int), rng.choice(surface.global_vertex.size, 10, replace=False)]
    if pa.size:
        sets += [verts[pa.size // 2, :1], verts[pa.size // 3, -1:]]
    for chosen in sets:
        held = np.zeros(surface.global_vertex.size, dtype=bool)
        held[chosen] = True
        expected = np.isin(verts, chosen).any(axis=1)
        assert np.array_equal(pairs_holding(surface, integration, pa, pk, held), expected)
    assert pa.size == 0 or expected.any()


def test_pairs_touching_are_a_whole_search_round_the_marked_vertices():
    """The area pairs holding a marked vertex, searched round those vertices only, are the
    pairs of a whole search holding one, in that search's order: for one vertex of a pair's
    triangle, one of its tetrahedron's only, ten random held vertices, all and none; at the
    surface's margin and at 0."""
    surface = two_box_surface("area")
    rng = np.random.default_rng(5)
    n = surface.global_vertex.size
    for margin in (surface.margin, 0.0):
        pa, pk = candidate_pairs(surface, "area", margin)
        assert pa.size > 0
        verts = pair_vertices(surface, "area", pa, pk)
        tet_only = np.setdiff1d(verts[pa.size // 3, 3:], verts[pa.size // 3, :3])[:1]
        marks = [verts[pa.size // 2, :1], tet_only, rng.choice(n, 10, replace=False)]
        marks += [np.arange(n), np.empty(0, dtype=int)]
        for chosen in marks:
            held = np.zeros(n, dtype=bool)
            held[chosen] = True
            want = pairs_holding(surface, "area", pa, pk, held)
            ta, tk = pairs_touching(surface, held, margin)
            np.testing.assert_array_equal(ta, pa[want])
            np.testing.assert_array_equal(tk, pk[want])
            assert chosen.size == 0 or chosen.size == n or 0 < ta.size < pa.size


@pytest.mark.parametrize("seed", [0, 1])
def test_coupling_keys_are_every_two_vertices_of_a_row(seed):
    """``coupling_keys`` against the unique of every (row, vi, vj) key written out: rows of 7
    vertices each within 9 of one another (so that rows share vertices and some repeat one,
    and many rows couple the same two vertices), up to the last vertex; no rows, none."""
    rng = np.random.default_rng(seed)
    n = 60
    verts = rng.integers(0, n - 8, (300, 1)) + rng.integers(0, 9, (300, 7))  # neighbours
    verts[0, :] = n - 1
    expected = np.unique((verts[:, :, None] * n + verts[:, None, :]).ravel())
    keys = coupling_keys(verts, n)
    assert keys.dtype == np.int64 and np.array_equal(keys, expected)
    assert expected.size < 0.9 * n * n  # not simply every coupling
    assert coupling_keys(np.empty((0, 7), dtype=np.int64), n).size == 0


def test_pattern_keys_hold_the_touching_pairs():
    """The contact pattern's vertex couplings: sorted, distinct, symmetric; every coupling of
    a pair whose triangle meets its tetrahedron (a non-empty intersection polygon) is in it,
    and nothing outside the couplings of the pairs whose boxes overlap within the margin."""
    surface = two_box_surface("area")
    n = surface.num_vertices
    keys = pattern_keys(surface, "area", surface.margin)
    assert np.all(np.diff(keys) > 0)
    vi, vj = keys // n, keys % n
    assert np.all(np.isin(vj * n + vi, keys))

    def couplings(verts: np.ndarray) -> np.ndarray:
        g = surface.global_vertex[verts]
        return np.unique((g[:, :, None] * n + g[:, None, :]).ravel())

    pa, pk = candidate_pairs(surface, "area", surface.margin)
    verts = pair_vertices(surface, "area", pa, pk)
    assert np.all(np.isin(keys, couplings(verts)))
    touching = [
        p
        for p in range(pa.size)
        if len(intersection_polygon(surface.x[verts[p, :3]], surface.x[verts[p, 3:]])) >= 3
    ]
    assert surface.comm.allreduce(len(touching)) > 20
    if touching:
        assert np.all(np.isin(couplings(verts[touching]), keys))
    # pairs far apart (within the boxes' margin, not within the margin of the triangle) were
    # left out: the pattern is smaller than the boxes' couplings
    total = surface.comm.allreduce(keys.size)
    assert total < surface.comm.allreduce(couplings(verts).size)


def test_the_pattern_takes_the_pair_search_only_when_it_searched_this_state():
    """``pattern_keys(..., search)`` takes the search's candidates exactly when they are a
    whole search with the pattern's margin at the surface's current coordinates; then the keys
    are those of a search of its own. After a move, or a search round the moved vertices
    only, or with another skin, the search's pairs are not offered."""
    s = two_box_surface("area")
    margin = s.margin
    search = PairSearch("area", margin)
    search.update(s)  # the first update searches the whole surface
    found = search.searched_now(s, margin)
    assert found is not None
    expected = candidate_pairs(s, "area", margin)
    assert all(np.array_equal(f, e) for f, e in zip(found, expected, strict=True))
    assert np.array_equal(pattern_keys(s, "area", margin, search), pattern_keys(s, "area", margin))
    assert search.searched_now(s, 2.0 * margin) is None  # another margin
    # a move of one vertex by more than half the skin: the search goes round it only
    x0 = s.x.copy()
    s.x[0] += 0.6 * margin
    assert search.searched_now(s, margin) is None  # the coordinates changed
    search.update(s)
    assert search.partial_searches == 1 and search.searched_now(s, margin) is None
    s.x[:] = x0
    assert search.searched_now(s, margin) is None  # the pairs are no whole search's now
    assert np.array_equal(pattern_keys(s, "area", margin, search), pattern_keys(s, "area", margin))
