"""Continuous collision detection: the kernels against an independent reference.

The reference samples the distance along the trajectories finely (plain numpy: the distance
of a point to a triangle by projection onto its plane or its nearest edge; of two segments
by their end points and the common perpendicular) and refines the first sign
change of ``distance - min_distance`` by bisection (min_distance > 0, so a crossing shows in
the samples; exact contact, distance 0, is checked on analytical cases).
"""

from __future__ import annotations

import numpy as np
import pytest

from fenics_matdepth.geometry.ccd import (
    STILL_REACH,
    edge_edge_time_of_impact,
    entry_fraction,
    sweep_caps,
    sweep_topology,
    vertex_triangle_time_of_impact,
)

# pure numba/numpy: every rank would run the same computation, so the serial pass runs it
pytestmark = pytest.mark.serial


def _point_segment(p, q0, q1):
    """Distances (k,) of points p (k, 3) to segments [q0, q1] (k, 3)."""
    d = q1 - q0
    dd = np.einsum("ij,ij->i", d, d)
    t = np.einsum("ij,ij->i", p - q0, d) / np.where(dd > 0.0, dd, 1.0)
    t = np.clip(np.where(dd > 0.0, t, 0.0), 0.0, 1.0)
    return np.linalg.norm(p - q0 - t[:, None] * d, axis=1)


def _point_triangle_distance(p, tri):
    """Exact distances (k,) of points p (k, 3) to triangles tri (k, 3, 3): by projection onto
    the plane where it falls inside, else the nearest edge (numpy, independent of the
    package)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    n = np.cross(b - a, c - a)
    nn = np.einsum("ij,ij->i", n, n)
    q = p - (np.einsum("ij,ij->i", n, p - a) / np.where(nn > 0.0, nn, 1.0))[:, None] * n
    # barycentric coordinates of the projection
    v0, v1, v2 = b - a, c - a, q - a
    d00, d01 = np.einsum("ij,ij->i", v0, v0), np.einsum("ij,ij->i", v0, v1)
    d11, d20 = np.einsum("ij,ij->i", v1, v1), np.einsum("ij,ij->i", v2, v0)
    d21 = np.einsum("ij,ij->i", v2, v1)
    den = np.where(nn > 0.0, d00 * d11 - d01 * d01, 1.0)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    inside = (nn > 0.0) & (v >= 0) & (w >= 0) & (v + w <= 1)
    edges = np.minimum.reduce(
        [_point_segment(p, a, b), _point_segment(p, b, c), _point_segment(p, c, a)]
    )
    return np.where(inside, np.linalg.norm(p - q, axis=1), edges)


def _segment_distance(p0, p1, q0, q1):
    """Distances (k,) between segments [p0, p1] and [q0, q1] (each (k, 3)): the smaller of
    the four end-point-to-segment distances and, where the lines' common perpendicular meets
    both segments inside, its length."""
    best = np.minimum.reduce([
        _point_segment(p0, q0, q1), _point_segment(p1, q0, q1),
        _point_segment(q0, p0, p1), _point_segment(q1, p0, p1),
    ])  # fmt: skip
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a11, a12 = np.einsum("ij,ij->i", d1, d1), np.einsum("ij,ij->i", d1, d2)
    a22 = np.einsum("ij,ij->i", d2, d2)
    b1, b2 = -np.einsum("ij,ij->i", d1, r), -np.einsum("ij,ij->i", d2, r)
    # the 2 x 2 system [[a11, -a12], [a12, -a22]] (s, t) = (b1, b2), by Cramer's rule
    det = -a11 * a22 + a12 * a12
    regular = np.abs(det) > 1e-12 * a11 * a22
    det = np.where(regular, det, 1.0)
    s = (-b1 * a22 + a12 * b2) / det
    t = (a11 * b2 - a12 * b1) / det
    inside = regular & (s >= 0.0) & (s <= 1.0) & (t >= 0.0) & (t <= 1.0)
    perpendicular = np.linalg.norm(p0 + s[:, None] * d1 - q0 - t[:, None] * d2, axis=1)
    return np.where(inside, np.minimum(best, perpendicular), best)


def _reference_toi(distance, min_distance, samples=2000):
    """First time in [0, 1] with distance(t) <= min_distance (sampled, then bisected), inf for
    none."""
    t = np.linspace(0.0, 1.0, samples + 1)
    d = distance(t)
    below = np.flatnonzero(d <= min_distance)
    if below.size == 0:
        return np.inf, d.min()
    k = below[0]
    if k == 0:
        return 0.0, d.min()
    lo, hi = t[k - 1], t[k]
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        if distance(np.array([mid]))[0] <= min_distance:
            hi = mid
        else:
            lo = mid
    return hi, d.min()


def _vt_distance(p0, tri0, p1, tri1):
    """The distance at an array of times (k,)."""
    return lambda t: _point_triangle_distance(
        p0 + t[:, None] * (p1 - p0), tri0 + t[:, None, None] * (tri1 - tri0)
    )


def _ee_distance(a0, b0, a1, b1):
    def distance(t):
        a = a0 + t[:, None, None] * (a1 - a0)
        b = b0 + t[:, None, None] * (b1 - b0)
        return _segment_distance(a[:, 0], a[:, 1], b[:, 0], b[:, 1])

    return distance


def _random_vt(rng):
    tri0 = rng.uniform(-1.0, 1.0, (3, 3))
    p0 = rng.uniform(-1.0, 1.0, 3) + 1.5 * np.cross(tri0[1] - tri0[0], tri0[2] - tri0[0])
    # aimed at a random point of the triangle, overshooting or falling short
    w = rng.dirichlet(np.ones(3))
    target = w @ tri0
    p1 = p0 + rng.uniform(0.8, 2.0) * (target - p0) + 0.05 * rng.normal(size=3)
    tri1 = tri0 + 0.1 * rng.normal(size=(3, 3))
    return p0, tri0, p1, tri1


def test_vertex_triangle_random_trajectories_are_never_late():
    """60 random vertex-triangle trajectories, min distance 0.01 and 0.05: the CCD time is
    never later than the reference (within the reference's bisection accuracy 1e-9) and,
    where the reference finds an impact, earlier by less than 2e-3 of the step."""
    rng = np.random.default_rng(7)
    hits = 0
    for min_distance in (0.01, 0.05):
        for _ in range(30):
            p0, tri0, p1, tri1 = _random_vt(rng)
            ref, dmin = _reference_toi(_vt_distance(p0, tri0, p1, tri1), min_distance)
            got = vertex_triangle_time_of_impact(p0, tri0, p1, tri1, min_distance)[0]
            if np.isfinite(ref):
                hits += 1
                assert got <= ref + 1e-9, (got, ref)
                assert got >= ref - 2e-3, (got, ref)
            else:
                # the sampling misses only impacts of grazing trajectories
                assert not np.isfinite(got) or dmin - min_distance < 1e-2, (got, dmin)
    assert hits > 30  # most trajectories hit: the check has teeth


def test_edge_edge_random_trajectories_are_never_late():
    """60 random crossing edge pairs, min distance 0.01: never later than the reference, at
    most 2e-3 early."""
    rng = np.random.default_rng(11)
    hits = 0
    for _ in range(60):
        # an edge along x below one along y (crossing in projection), each tilted at random
        a0 = np.array([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]) + 0.3 * rng.normal(size=(2, 3))
        b0 = np.array([[0.0, -1.0, 2.0], [0.0, 1.0, 2.0]]) + 0.3 * rng.normal(size=(2, 3))
        a1 = a0 + 0.2 * rng.normal(size=(2, 3))
        b1 = b0 + np.array([0.0, 0.0, -rng.uniform(1.0, 4.0)]) + 0.2 * rng.normal(size=(2, 3))
        ref, _ = _reference_toi(_ee_distance(a0, b0, a1, b1), 0.01)
        got = edge_edge_time_of_impact(a0, b0, a1, b1, 0.01)[0]
        if np.isfinite(ref):
            hits += 1
            assert got <= ref + 1e-9, (got, ref)
            assert got >= ref - 2e-3, (got, ref)
    assert hits > 36


def test_degenerate_trajectories():
    """Parallel edges falling onto each other, a vertex sliding in the triangle's plane onto
    it, a vertex aimed at an edge, a vertex aimed at a vertex: exact impact times (analytical)
    within the tolerance, never later."""
    tol = 1e-9
    # parallel edges 1 apart closing at 2 per step: contact at t = 0.5
    a = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    b = np.array([[0.2, 0.0, 1.0], [1.2, 0.0, 1.0]])
    t = edge_edge_time_of_impact(a, b, a, b - [0.0, 0.0, 2.0], tol=tol)[0]
    assert 0.5 - 1e-6 <= t <= 0.5, t
    # collinear edges (overlapping lines) closing along the line: contact at t = 0.25
    b = np.array([[2.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    t = edge_edge_time_of_impact(a, b, a, b - [4.0, 0.0, 0.0], tol=tol)[0]
    assert 0.25 - 1e-6 <= t <= 0.25, t
    tri = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    # coplanar motion: vertex in the plane, from x = -1 toward the triangle's edge at x = 0
    p0, p1 = np.array([-1.0, 0.3, 0.0]), np.array([1.0, 0.3, 0.0])
    t = vertex_triangle_time_of_impact(p0, tri, p1, tri, tol=tol)[0]
    assert 0.5 - 1e-6 <= t <= 0.5, t
    # vertex onto the middle of an edge (from above): contact at t = 0.5
    p0, p1 = np.array([0.5, 0.0, 1.0]), np.array([0.5, 0.0, -1.0])
    t = vertex_triangle_time_of_impact(p0, tri, p1, tri, tol=tol)[0]
    assert 0.5 - 1e-6 <= t <= 0.5, t
    # vertex onto a vertex, the triangle moving up to meet it: contact at t = 0.4
    p0, p1 = np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -0.5])
    t = vertex_triangle_time_of_impact(p0, tri, p1, tri + [0.0, 0.0, 1.0], tol=tol)[0]
    assert 0.4 - 1e-6 <= t <= 0.4, t
    # sliding past, never closer than 0.5: no impact; a pair not moving: none
    p0, p1 = np.array([-1.0, -0.5, 0.5]), np.array([2.0, -0.5, 0.5])
    assert np.isinf(vertex_triangle_time_of_impact(p0, tri, p1, tri)[0])
    assert np.isinf(vertex_triangle_time_of_impact(p0, tri, p0, tri)[0])


def test_entry_cap_bounds_the_depth_past_first_contact():
    """The entry cap: at the capped fraction no pair is deeper than the entry tolerance past
    the plane it crossed (head-on: exactly entry / speed after contact, up to the
    advancement's tolerance); pairs starting within the entry tolerance, or missing, are not
    capped."""
    tri = np.array([[-1.0, -1.0, 0.0], [2.0, -1.0, 0.0], [-1.0, 2.0, 0.0]])
    entry = 0.01
    # a vertex from z = 0.5 to z = -0.5: contact at 0.5, depth 0.01 at 0.51
    cap = entry_fraction([0.2, 0.2, 0.5], tri, [0.2, 0.2, -0.5], tri, entry)[0]
    assert 0.5 < cap <= 0.51 + 1e-12, cap
    assert cap > 0.5 + 0.5 * entry  # not needlessly early: at least half the entry taken
    # already within the entry tolerance: free
    assert entry_fraction([0.2, 0.2, 0.005], tri, [0.2, 0.2, -0.5], tri, entry)[0] == 1.0
    # missing the triangle: free
    assert entry_fraction([5.0, 5.0, 0.5], tri, [5.0, 5.0, -0.5], tri, entry)[0] == 1.0
    # random head-on and oblique trajectories: the depth at the cap is at most entry
    rng = np.random.default_rng(3)
    for _ in range(50):
        p0 = np.array([*rng.uniform(0.0, 0.5, 2), rng.uniform(0.05, 1.0)])
        p1 = np.array([*rng.uniform(0.0, 0.5, 2), rng.uniform(-2.0, -0.05)])
        cap = entry_fraction(p0, tri, p1, tri, entry)[0]
        depth = -(p0 + cap * (p1 - p0))[2]
        assert depth <= entry * (1 + 1e-9), (cap, depth)
    # edge-edge: crossing edges from 1 apart at 2 per step: contact 0.5, cap <= 0.505
    a = np.array([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    b = np.array([[0.0, -1.0, 1.0], [0.0, 1.0, 1.0]])
    cap = entry_fraction(a, b, a, b - [0.0, 0.0, 2.0], entry, kind="edge_edge")[0]
    assert 0.5 < cap <= 0.505 + 1e-12, cap


def _crumpled_sheets(rng, sheets=3, n=5, spacing=0.08):
    """Triangulated unit square sheets (n x n squares, each cut in two), crumpled (by 0.05)
    and stacked ``spacing`` apart: positions, triangles (outward by the right-hand rule), each
    triangle's edges and the owner triangle of every edge and vertex (the first holding it),
    as ``sweep_caps`` takes them."""
    g = np.linspace(0.0, 1.0, n + 1)
    X, Y = np.meshgrid(g, g, indexing="ij")
    grid = np.stack((X.ravel(), Y.ravel(), np.zeros(X.size)), axis=1)
    k = np.arange(n + 1) * (n + 1)
    corner = (k[:-1, None] + np.arange(n)[None, :]).ravel()
    cells = np.concatenate(
        (
            np.stack((corner, corner + n + 1, corner + 1), axis=1),
            np.stack((corner + 1, corner + n + 1, corner + n + 2), axis=1),
        )
    )
    x, tri = [], []
    for s in range(sheets):
        sheet = grid + [0.0, 0.0, spacing * s] + rng.normal(0.0, 0.05, grid.shape)
        tri.append(cells + s * grid.shape[0])
        x.append(sheet)
    x, tri = np.concatenate(x), np.concatenate(tri).astype(np.int64)
    return x, tri, *sweep_topology(tri, x.shape[0])


@pytest.mark.parametrize("exits", [False, True])
def test_sweep_skips_only_pairs_that_cannot_reach_their_entry_tolerance(exits):
    """Three crumpled sheets 0.08 apart (the entry tolerance is about 0.05), each vertex
    moved by a random vector (half the steps each sheet at a scale of its own, from 0.01 to
    10 entry tolerances; half 0.8 to 1.6 of them): the sweep that skips the pairs whose two
    triangles' largest vertex moves sum to at most ``STILL_REACH`` entry tolerances gives the
    same cap, the same count of capped pairs and the same smallest pair as the sweep of every
    pair, step after step; and the steps skip many pairs and cap some. A triangle falling
    head-on from just beyond the entry tolerance by just over twice it is capped, and swept:
    a larger bound would skip it."""
    rng = np.random.default_rng(11)
    x0, tri, tri_edge, edges, vertex_owner, edge_owner = _crumpled_sheets(rng)
    edge = np.linalg.norm(x0[tri[:, [1, 2, 0]]] - x0[tri], axis=2).mean(axis=1)
    entry = np.ascontiguousarray(0.25 * edge)
    m = tri.shape[0]
    a, b = np.divmod(np.arange(m * m), m)
    skipped = capped = 0
    for k in range(24):
        if k % 2:
            # each sheet moves at a scale of its own, each vertex by half to all of it
            sheet = 10.0 ** rng.uniform(-2.0, 1.0, 3)[np.arange(x0.shape[0]) * 3 // x0.shape[0]]
            scale = entry.mean() * sheet[:, None] * rng.uniform(0.5, 1.0, (x0.shape[0], 1))
        else:  # about the bound: 0.8 to 1.6 entry tolerances each
            scale = entry.mean() * rng.uniform(0.8, 1.6, (x0.shape[0], 1))
        step = rng.normal(size=x0.shape)
        x1 = x0 + scale * step / np.linalg.norm(step, axis=1, keepdims=True)
        args = (x0, x1, tri, tri_edge, edges, vertex_owner, edge_owner, entry, a, b, exits)
        every = sweep_caps(*args, skip_still=False)
        assert sweep_caps(*args) == every
        travel = np.linalg.norm(x1 - x0, axis=1)[tri].max(axis=1)
        still = travel[a] + travel[b] <= STILL_REACH * np.minimum(entry[a], entry[b])
        skipped += int(still[a != b].sum())
        capped += every[1]
    assert skipped > 0.1 * 24 * m * (m - 1), skipped
    assert capped > 0, capped
    # a triangle falling head-on onto another from 1.05 entry tolerances by 2.1: its lowest
    # vertex 1.05 past first contact, capped (a bound above 2.1 would skip it)
    e = 0.01
    x0 = np.array([[-1, -1, 0], [2, -1, 0], [-1, 2, 0], [0, 0, 1.05 * e], [1, 0, 1], [0, 1, 1]])
    x1 = x0 - np.outer(np.arange(6) >= 3, [0.0, 0.0, 2.1 * e])
    tri = np.array([[0, 1, 2], [3, 5, 4]])
    pair = np.array([0, 1]), np.array([1, 0])
    args = (x0, x1, tri, *sweep_topology(tri, 6), np.full(2, e), *pair, exits)
    assert sweep_caps(*args) == sweep_caps(*args, skip_still=False)
    assert sweep_caps(*args)[0] < 1.0
