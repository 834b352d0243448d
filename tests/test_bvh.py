"""AABB tree and point-triangle distance against brute force and independent formulas."""

from __future__ import annotations

import numpy as np
import pytest

from fenics_matdepth.geometry.boxes import element_boxes, exclude_shared_vertex_pairs
from fenics_matdepth.geometry.bvh import AABBTree
from fenics_matdepth.geometry.distance import (
    nearest_triangle_bruteforce,
    point_triangle_distance,
)

# pure numba/numpy: every rank would run the same computation, so the serial pass runs it
pytestmark = pytest.mark.serial

# ------------------------------------------------------------------------------------------
# independent references (plain numpy, a different algorithm from the kernels)
# ------------------------------------------------------------------------------------------


def _segment_distance(p, a, b):
    ab = b - a
    t = np.clip(np.sum((p - a) * ab, axis=-1) / np.sum(ab * ab, axis=-1), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[..., None] * ab), axis=-1)


def _triangle_distance_reference(p, tri):
    """Distance by projection onto the plane (if inside) or else the nearest edge.

    p (n, 3), tri (n, 3, 3) non-degenerate.
    """
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1)[:, None]
    h = np.sum((p - a) * n, axis=1)
    q = p - h[:, None] * n
    # inside test: q on the same side of all three edges as the triangle normal
    s0 = np.sum(np.cross(b - a, q - a) * n, axis=1)
    s1 = np.sum(np.cross(c - b, q - b) * n, axis=1)
    s2 = np.sum(np.cross(a - c, q - c) * n, axis=1)
    inside = (s0 >= 0) & (s1 >= 0) & (s2 >= 0)
    edge = np.minimum(
        np.minimum(_segment_distance(p, a, b), _segment_distance(p, b, c)),
        _segment_distance(p, c, a),
    )
    return np.where(inside, np.abs(h), edge)


def _overlap_bruteforce(lo, hi, blo, bhi, margin):
    ov = np.all((lo[:, None] - margin <= bhi[None]) & (blo[None] <= hi[:, None] + margin), axis=2)
    return set(zip(*(a.tolist() for a in np.nonzero(ov)), strict=True))


def _jittered_box_tets(n, rng, jitter=0.25):
    """Tetrahedral mesh of [0, 1]^3 (n^3 cubes, 6 tets each) with randomly moved vertices."""
    g = np.linspace(0.0, 1.0, n + 1)
    x = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    x += rng.uniform(-jitter, jitter, x.shape) / n

    def vid(i, j, k):
        return (i * (n + 1) + j) * (n + 1) + k

    i, j, k = (a.ravel() for a in np.meshgrid(*(np.arange(n),) * 3, indexing="ij"))
    v = [vid(i + a, j + b, k + c) for a in (0, 1) for b in (0, 1) for c in (0, 1)]
    paths = [(4, 6), (4, 5), (2, 6), (2, 3), (1, 5), (1, 3)]
    tets = np.concatenate([np.stack([v[0], v[p], v[q], v[7]], axis=1) for p, q in paths])
    return x, tets


def _random_triangles(n, rng):
    """Triangle soup: small random triangles in [0, 1]^3 (not degenerate)."""
    centre = rng.uniform(0.0, 1.0, (n, 1, 3))
    tri = centre + rng.uniform(-0.1, 0.1, (n, 3, 3))
    return tri.reshape(-1, 3), np.arange(3 * n).reshape(n, 3)


# ------------------------------------------------------------------------------------------
# point-triangle distance
# ------------------------------------------------------------------------------------------


def test_point_triangle_distance_analytic():
    tri = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    # above the face: the height
    assert point_triangle_distance([0.5, 0.5, 3.0], tri) == pytest.approx(3.0, abs=1e-15)
    # on a vertex: exactly zero (material depth relies on it)
    for v in tri:
        assert point_triangle_distance(v, tri) == 0.0
    # beyond vertex b along x: distance to b
    assert point_triangle_distance([5.0, -1.0, 0.0], tri) == pytest.approx(np.hypot(3, 1))
    # facing the hypotenuse b-c, off the plane: sqrt(edge offset^2 + height^2)
    p = np.array([1.0, 1.0, 0.0]) + np.array([1.0, 1.0, 0.0]) / np.sqrt(2) * 0.5
    p[2] = 1.2
    assert point_triangle_distance(p, tri) == pytest.approx(np.hypot(0.5, 1.2), rel=1e-14)
    # degenerate triangle (repeated vertex): distance to the segment, finite
    seg = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    assert point_triangle_distance([0.5, 2.0, 0.0], seg) == pytest.approx(2.0, rel=1e-15)


def test_point_triangle_distance_random():
    rng = np.random.default_rng(1)
    n = 20000
    tri = rng.normal(size=(n, 3, 3))
    p = 2.0 * rng.normal(size=(n, 3))
    d = point_triangle_distance(p, tri)
    ref = _triangle_distance_reference(p, tri)
    np.testing.assert_allclose(d, ref, rtol=1e-10, atol=1e-12)


# ------------------------------------------------------------------------------------------
# box queries
# ------------------------------------------------------------------------------------------


def _check_box_queries(tree, points, cells, rng, n_query=60):
    lo = rng.uniform(-0.2, 1.1, (n_query, 3))
    hi = lo + rng.uniform(0.0, 0.35, (n_query, 3))
    blo, bhi = element_boxes(points, cells)
    for margin in (0.0, 0.03):
        q, e = tree.query_boxes(lo, hi, margin=margin)
        got = list(zip(q.tolist(), e.tolist(), strict=True))
        assert len(got) == len(set(got)), "duplicate pairs"
        assert set(got) == _overlap_bruteforce(lo, hi, blo, bhi, margin)
        assert np.all(np.diff(q) >= 0), "pairs not grouped by query"


@pytest.mark.parametrize("leaf_size", [1, 4, 7])
@pytest.mark.parametrize("seed", [0, 1])
def test_query_boxes_tets_refit_rebuild(leaf_size, seed):
    rng = np.random.default_rng(seed)
    x, tets = _jittered_box_tets(5, rng)
    tree = AABBTree(x, tets, leaf_size=leaf_size)
    assert tree.num_elements == len(tets)
    _check_box_queries(tree, x, tets, rng)
    # random displacement + refit: same answers as brute force on the moved mesh
    y = x + rng.normal(scale=0.05, size=x.shape)
    tree.refit(y)
    _check_box_queries(tree, y, tets, rng)
    lo, hi = tree.bounds
    np.testing.assert_array_equal(lo, y[tets].reshape(-1, 3).min(axis=0))
    np.testing.assert_array_equal(hi, y[tets].reshape(-1, 3).max(axis=0))
    # large scrambling displacement: refit stays correct, then rebuild stays correct
    z = x + rng.normal(scale=0.5, size=x.shape)
    tree.refit(z)
    _check_box_queries(tree, z, tets, rng)
    tree.rebuild()
    _check_box_queries(tree, z, tets, rng)


def test_query_boxes_triangle_soup():
    rng = np.random.default_rng(7)
    x, tri = _random_triangles(300, rng)
    tree = AABBTree(x, tri)
    _check_box_queries(tree, x, tri, rng)


def test_rebuild_criterion():
    rng = np.random.default_rng(3)
    x, tets = _jittered_box_tets(6, rng)
    tree = AABBTree(x, tets)
    assert tree.quality_growth == pytest.approx(1.0, abs=1e-15)
    # rigid translation and uniform scaling leave the quality ratio unchanged
    tree.refit(3.0 * x + np.array([1.0, -2.0, 0.5]))
    assert tree.quality_growth == pytest.approx(1.0, rel=1e-12)
    assert not tree.needs_rebuild()
    # scrambling vertices far beyond the element size makes boxes overlap: rebuild needed
    tree.refit(x + rng.uniform(-0.5, 0.5, x.shape))
    assert tree.quality_growth > 2.0
    assert tree.needs_rebuild()
    tree.rebuild()
    assert tree.quality_growth == 1.0
    assert not tree.needs_rebuild()


def test_empty_tree_and_errors():
    tree = AABBTree(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    q, e = tree.query_boxes(np.zeros((2, 3)), np.ones((2, 3)))
    assert q.size == 0 and e.size == 0
    idx, d = tree.nearest(np.zeros((2, 3)))
    assert np.all(idx == -1) and np.all(np.isinf(d))
    x, tets = _jittered_box_tets(2, np.random.default_rng(0))
    tet_tree = AABBTree(x, tets)
    with pytest.raises(TypeError, match="triangles"):
        tet_tree.nearest(np.zeros((1, 3)))
    with pytest.raises(ValueError, match="margin"):
        tet_tree.query_boxes(np.zeros((1, 3)), np.ones((1, 3)), margin=-1.0)
    with pytest.raises(ValueError, match="points"):
        tet_tree.refit(x[:-1])
    with pytest.raises(ValueError, match="outside"):
        AABBTree(x[:3], tets)


# ------------------------------------------------------------------------------------------
# nearest triangle
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("leaf_size", [1, 4])
def test_nearest_triangle(leaf_size):
    rng = np.random.default_rng(11)
    x, tri = _random_triangles(400, rng)
    tree = AABBTree(x, tri, leaf_size=leaf_size)
    # sorted points (exercise the warm start) and shuffled points
    p = rng.uniform(-0.3, 1.3, (1500, 3))
    p = np.concatenate([p[np.argsort(p[:, 0])], p])

    def check(points_now):
        idx, d = tree.nearest(p)
        _, d_ref = nearest_triangle_bruteforce(p, points_now, tri)
        np.testing.assert_allclose(d, d_ref, rtol=0.0, atol=1e-14)
        # the returned triangle really is at that distance (independent formula)
        t = points_now[tri[idx]]
        np.testing.assert_allclose(_triangle_distance_reference(p, t), d, rtol=1e-10, atol=1e-13)

    check(x)
    y = x + rng.normal(scale=0.2, size=x.shape)
    tree.refit(y)
    check(y)
    tree.rebuild()
    check(y)


# ------------------------------------------------------------------------------------------
# shared-vertex filter
# ------------------------------------------------------------------------------------------


def test_exclude_shared_vertex_pairs():
    rng = np.random.default_rng(5)
    x, tets = _jittered_box_tets(4, rng)
    # boundary-like triangles: faces of random tets, so many pairs share vertices
    tri = tets[rng.integers(0, len(tets), 200)][:, :3]
    tree = AABBTree(x, tets)
    q, e = tree.query_boxes(*element_boxes(x, tri))
    assert q.size > 0
    kt, kk = exclude_shared_vertex_pairs(tri, tets, q, e)
    expected = [
        (t, k)
        for t, k in zip(q.tolist(), e.tolist(), strict=True)
        if not set(tri[t].tolist()) & set(tets[k].tolist())
    ]
    assert list(zip(kt.tolist(), kk.tolist(), strict=True)) == expected
    assert 0 < len(expected) < q.size  # both kinds of pairs were present


@pytest.mark.parametrize("margin", [0.0, 0.05])
def test_query_boxes_apart_leaves_out_the_shared_vertex_pairs_in_order(margin):
    """``query_boxes(..., apart=(tri, tets))`` answers what exclude_shared_vertex_pairs keeps
    of the whole answer, the same pairs in the same order; wrong cell counts are refused."""
    rng = np.random.default_rng(6)
    x, tets = _jittered_box_tets(4, rng)
    tri = tets[rng.integers(0, len(tets), 200)][:, 1:]
    tree = AABBTree(x, tets)
    lo, hi = element_boxes(x, tri)
    q, e = tree.query_boxes(lo, hi, margin=margin)
    kt, kk = exclude_shared_vertex_pairs(tri, tets, q, e)
    at, ak = tree.query_boxes(lo, hi, margin=margin, apart=(tri, tets))
    assert 0 < at.size < q.size
    assert np.array_equal(at, kt) and np.array_equal(ak, kk)
    assert at.dtype == kt.dtype and ak.dtype == kk.dtype
    with pytest.raises(ValueError, match="a cell per query box"):
        tree.query_boxes(lo, hi, apart=(tri[:-1], tets))
