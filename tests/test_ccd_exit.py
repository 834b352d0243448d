"""Continuous collision detection of pass-through: a vertex inside a body leaving it through
the far side (``fenics_matdepth.geometry.ccd``, "pass-through").

The exit cap is checked against an independent reference that samples the vertex's signed
height over the moving triangle's plane finely (plain numpy) and bisects the first rise through
zero at which the vertex projects into the triangle: the cap is never later than that crossing,
leaves the vertex behind the plane, and is close to it; trajectories that do not cross are not
capped. The sweep over triangle pairs applies it only where the vertex's surface faces the way
the triangle does (a vertex leaving through the face it came in by is free).
"""

from __future__ import annotations

import numpy as np
import pytest

from fenics_matdepth.geometry.ccd import (
    EXIT_DEPTH,
    EXIT_MARGIN,
    exit_fraction,
    sweep_caps,
    sweep_topology,
    triangle_bodies,
)

# pure numba/numpy: every rank would run the same computation, so the serial pass runs it
pytestmark = pytest.mark.serial


def _height_and_inside(p, tri, slack=0.0):
    """Signed heights (k,) of points p (k, 3) over the planes of triangles tri (k, 3, 3)
    (positive on the right-hand normal's side) and whether each projects into its triangle
    grown by ``slack`` (barycentric coordinates >= -slack)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    n = np.cross(b - a, c - a)
    nn = np.linalg.norm(n, axis=1)
    h = np.einsum("ij,ij->i", n, p - a) / nn
    v0, v1, v2 = b - a, c - a, p - a
    d00, d01 = np.einsum("ij,ij->i", v0, v0), np.einsum("ij,ij->i", v0, v1)
    d11, d20 = np.einsum("ij,ij->i", v1, v1), np.einsum("ij,ij->i", v2, v0)
    d21 = np.einsum("ij,ij->i", v2, v1)
    den = d00 * d11 - d01 * d01
    lb = (d11 * d20 - d01 * d21) / den
    lc = (d00 * d21 - d01 * d20) / den
    inside = (lb >= -slack) & (lc >= -slack) & (1.0 - lb - lc >= -slack)
    return h, inside


def _reference_exit(p0, tri0, p1, tri1, slack=0.0, samples=4000):
    """First time (inf: none) the point rises through the triangle's plane while projecting
    into it: sampled, then bisected."""
    t = np.linspace(0.0, 1.0, samples + 1)

    def at(s):
        s = np.atleast_1d(s)
        return p0 + s[:, None] * (p1 - p0), tri0 + s[:, None, None] * (tri1 - tri0)

    h, _ = _height_and_inside(*at(t))
    for i in np.flatnonzero((h[:-1] < 0.0) & (h[1:] >= 0.0)):
        lo, hi = t[i], t[i + 1]
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            if _height_and_inside(*at(mid))[0][0] < 0.0:
                lo = mid
            else:
                hi = mid
        if _height_and_inside(*at(hi), slack=slack)[1][0]:
            return hi
    return np.inf


def _random_trajectories(rng, n):
    """Unit-size triangles moving and turning, with a point starting behind each, moving up
    through or beside it."""
    tri0 = rng.uniform(-0.5, 0.5, (n, 3, 3))
    tri0[:, :, 2] *= 0.2
    tri0[:, 1, 0] += 1.0
    tri0[:, 2, 1] += 1.0
    tri1 = tri0 + rng.uniform(-0.3, 0.3, (n, 3, 3))
    centre = tri0.mean(axis=1)
    p0 = centre + np.column_stack((rng.uniform(-0.5, 0.5, (n, 2)), rng.uniform(-0.6, -0.05, n)))
    p1 = p0 + np.column_stack((rng.uniform(-0.3, 0.3, (n, 2)), rng.uniform(0.2, 1.5, n)))
    return p0, tri0, p1, tri1


def test_exit_cap_is_never_later_than_the_crossing_and_keeps_the_vertex_behind():
    """200 random trajectories: where the reference finds a crossing, the cap is not after it,
    the vertex is behind the plane at the cap, and the cap is within 1e-3 of the crossing; where
    the vertex stays clear of the triangle grown by 1 %, there is no cap."""
    rng = np.random.default_rng(7)
    p0, tri0, p1, tri1 = _random_trajectories(rng, 200)
    depth = 1e-6
    caps = exit_fraction(p0, tri0, p1, tri1, depth)
    crossed = clear = 0
    for i in range(p0.shape[0]):
        if _height_and_inside(p0[i : i + 1], tri0[i : i + 1])[0][0] >= -depth:
            assert caps[i] == 1.0
            continue
        true = _reference_exit(p0[i], tri0[i], p1[i], tri1[i])
        if np.isfinite(true):
            crossed += 1
            assert caps[i] <= true + 1e-12, (i, caps[i], true)
            assert caps[i] >= true - 1e-3, (i, caps[i], true)
            s = caps[i]
            h, _ = _height_and_inside(
                (p0[i] + s * (p1[i] - p0[i]))[None], (tri0[i] + s * (tri1[i] - tri0[i]))[None]
            )
            assert h[0] < 0.0, (i, h[0])
        elif not np.isfinite(_reference_exit(p0[i], tri0[i], p1[i], tri1[i], slack=0.01)):
            clear += 1
            assert caps[i] == 1.0, (i, caps[i])
    assert crossed > 60 and clear > 60, (crossed, clear)


def test_exit_cap_analytical_cases():
    """A vertex 0.1 under a fixed unit triangle rising 0.4, depth m = 1e-4 (margin m): stopped
    2 m under the plane, at 0.25 - 2 m / 0.4; sliding along under it, or leaving beside it,
    not capped; a vertex in front, or behind by less than m (on the plane of a flush face),
    not tested; a vertex 1.5 m behind stops 1.25 m behind (half its height beyond m); a
    triangle tilting down onto the point caps where its plane reaches it."""
    tri = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    p = np.array([0.2, 0.2, -0.1])
    m = 1e-4
    up = np.array([0.0, 0.0, 0.4])
    assert np.isclose(exit_fraction(p, tri, p + up, tri, m)[0], 0.25 - 2 * m / 0.4, atol=1e-12)
    assert exit_fraction(p, tri, p + [0.5, 0.0, 0.0], tri, m)[0] == 1.0  # sliding under it
    beside = np.array([1.5, 1.5, -0.1])
    assert exit_fraction(beside, tri, beside + up, tri, m)[0] == 1.0
    assert exit_fraction(-p * [1, 1, -1], tri, -p * [1, 1, -1] + up, tri, m)[0] == 1.0
    flush = np.array([0.2, 0.2, -0.5 * m])
    assert exit_fraction(flush, tri, flush + up, tri, m)[0] == 1.0
    near = np.array([0.2, 0.2, -1.5 * m])
    cap = exit_fraction(near, tri, near + up, tri, m)[0]
    assert np.isclose(cap, 0.25 * m / 0.4, rtol=1e-9), cap
    # the third vertex goes 2 down: the plane over (0.25, 0.25) is at -2 t * 0.25, the point's
    # height -0.05, reached at t = 0.1
    q = np.array([0.25, 0.25, -0.05])
    tri1 = tri + [[0, 0, 0], [0, 0, 0], [0, 0, -2.0]]
    cap = exit_fraction(q, tri, q, tri1, 1e-9)[0]
    assert np.isclose(cap, 0.1, atol=1e-6), cap


def _two_layer_surface():
    """A slab's bottom triangle (normal -z) under vertices of another body's surface (rows 3,
    4: normal down, it came in from above; rows 5, 6: normal up)."""
    x0 = np.array([
        [-1.0, -1.0, 0.0], [-1.0, 2.0, 0.0], [2.0, -1.0, 0.0],  # slab bottom, seen from below
        [0.2, 0.2, 0.05], [0.2, 0.3, 0.05], [0.3, 0.2, 0.05],  # a triangle facing down
        [0.2, 0.2, 0.3], [0.3, 0.2, 0.3], [0.2, 0.3, 0.3],  # a triangle facing up
    ])  # fmt: skip
    tri = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8]], dtype=np.int64)
    return x0, tri


def _sweep(x0, x1, tri, exits=True, entry=0.01, pairs=None, bodies=None):
    tri_edge, edges, vertex_owner, edge_owner = sweep_topology(tri, x0.shape[0])
    entry = np.full(tri.shape[0], entry)
    if pairs is None:
        pa, pb = np.array([0, 0, 1, 2], dtype=np.int64), np.array([1, 2, 0, 0], dtype=np.int64)
    else:
        pa, pb = pairs
    return sweep_caps(
        x0, x1, tri, tri_edge, edges, vertex_owner, edge_owner, entry, pa, pb, exits, bodies
    )


def test_sweep_caps_a_vertex_leaving_through_the_far_side_only():
    """The facing-down triangle's vertices (inside the slab above its bottom face) moved 0.1
    down, through the bottom face: capped (kind 2, the pass-through) before the crossing, the
    exit depth and margin short of it; without ``exits`` not capped. The facing-up triangle's
    vertices moved down through it the same way (their surface faces the other way: leaving
    by the face they came in by): not capped."""
    x0, tri = _two_layer_surface()
    x1 = x0.copy()
    x1[3:6, 2] -= 0.1
    best, capped, kind, v, t = _sweep(x0, x1, tri)
    assert kind == 2 and t == 0 and v in (3, 4, 5) and capped == 3, (kind, t, v, capped)
    assert np.isclose(best, 0.5 - (EXIT_DEPTH + EXIT_MARGIN) * 0.01 / 0.1, atol=1e-12), best
    assert _sweep(x0, x1, tri, exits=False)[0] == 1.0
    x1 = x0.copy()
    x1[6:9, 2] -= 0.4
    assert _sweep(x0, x1, tri)[0] == 1.0


def _box_surface(lo, hi, n=2):
    """The boundary of the box [lo, hi] as triangles, n x n squares a face, outward: (points,
    triangles)."""
    lo, hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
    points, tris = [], []
    s = np.linspace(0.0, 1.0, n + 1)
    for axis in range(3):
        u, w = (axis + 1) % 3, (axis + 2) % 3
        for side in (0, 1):
            grid = np.empty((n + 1, n + 1, 3))
            grid[..., axis] = hi[axis] if side else lo[axis]
            grid[..., u] = lo[u] + s[:, None] * (hi[u] - lo[u])
            grid[..., w] = lo[w] + s[None, :] * (hi[w] - lo[w])
            k = sum(len(q) for q in points)
            points.append(grid.reshape(-1, 3))
            idx = k + np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
            for i in range(n):
                for j in range(n):
                    a, b, c, d = idx[i, j], idx[i + 1, j], idx[i + 1, j + 1], idx[i, j + 1]
                    # (u, w, axis) is right-handed: u x w points along +axis
                    quad = [(a, b, c), (a, c, d)] if side else [(a, c, b), (a, d, c)]
                    tris.extend(quad)
    x = np.vstack(points)
    _, first, inverse = np.unique(np.round(x, 12), axis=0, return_index=True, return_inverse=True)
    return x[first], inverse.ravel()[np.asarray(tris)]


def _two_boxes(lower, upper):
    """Two box surfaces in one numbering, and every ordered pair of a triangle of one with a
    triangle of the other."""
    xa, ta = _box_surface(*lower)
    xb, tb = _box_surface(*upper)
    x0 = np.vstack((xa, xb))
    tri = np.vstack((ta, tb + xa.shape[0])).astype(np.int64)
    i, j = np.meshgrid(np.arange(ta.shape[0]), ta.shape[0] + np.arange(tb.shape[0]))
    pairs = (np.concatenate((i.ravel(), j.ravel())), np.concatenate((j.ravel(), i.ravel())))
    return x0, tri, pairs, xa.shape[0]


def test_box_surface_is_closed_and_outward():
    """The test's box surface: every edge in two triangles, the enclosed volume the box's."""
    x, tri = _box_surface((0.0, 0.0, 0.0), (1.0, 4.0, 0.5))
    edges = np.sort(np.stack((tri, tri[:, [1, 2, 0]]), axis=2).reshape(-1, 2), axis=1)
    assert (np.unique(edges, axis=0, return_counts=True)[1] == 2).all()
    p = x[tri]
    volume = np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0
    assert np.isclose(volume, 2.0)


def test_an_edge_sliding_off_a_body_through_its_side_face_is_free():
    """A box lying on another, its lower edge 0.05 inside the lower box's side face and 0.02
    under its top face, slides 0.3 sideways off it: that edge's vertices (their normals at 45
    degrees between their faces, so facing the way the side face does) leave through the
    side face while in contact with the top face, which faces them and is not the other side
    of a layer: not capped. With every triangle a body of its own (no other face to be in
    contact with: the rule before) the side face caps them (kind 2)."""
    x0, tri, pairs, n_lower = _two_boxes(((0.0, 0.0, 0.0), (1.0, 4.0, 1.0)),
                                         ((0.05, 1.0, 0.98), (1.05, 3.0, 1.98)))  # fmt: skip
    x1 = x0.copy()
    x1[n_lower:, 0] -= 0.3
    best, capped, kind, v, t = _sweep(x0, x1, tri, entry=0.1, pairs=pairs)
    assert best == 1.0 and capped == 0, (best, capped, kind)
    alone = triangle_bodies(tri, np.arange(tri.shape[0]))
    best, capped, kind, v, t = _sweep(x0, x1, tri, entry=0.1, pairs=pairs, bodies=alone)
    assert kind == 2 and best < 1.0 and np.allclose(x0[v, [0, 2]], (0.05, 0.98)), (kind, v)
    assert np.isclose(x0[tri[t], 0], 0.0).all()


def test_an_edge_through_a_thin_layer_is_held():
    """A box whose lower face went through a plate's top face (0.25 thick) to 0.1 over its
    bottom face moves on down by 0.3: its vertices, the lower edges' too (their normals at 45
    degrees), are capped at the bottom face (kind 2): the only face facing them within reach,
    the top face, is the layer's other side."""
    x0, tri, pairs, n_lower = _two_boxes(((0.0, 0.0, 0.0), (4.0, 4.0, 0.25)),
                                         ((1.0, 1.0, 0.1), (3.0, 3.0, 1.1)))  # fmt: skip
    x1 = x0.copy()
    x1[n_lower:, 2] -= 0.3
    best, capped, kind, v, t = _sweep(x0, x1, tri, entry=0.1, pairs=pairs)
    assert kind == 2 and np.isclose(x0[v, 2], 0.1) and np.isclose(x0[tri[t], 2], 0.0).all()
    assert np.isclose(best, (0.1 - (EXIT_DEPTH + EXIT_MARGIN) * 0.1) / 0.3, atol=1e-9), best
    assert capped >= 9, capped  # the lower face's nine vertices, each by a bottom triangle or more
    # every bottom vertex of the upper box is held, the 8 on its edges as well as the middle
    held = {int(v)}
    for q in range(pairs[0].size):
        one = (pairs[0][q : q + 1], pairs[1][q : q + 1])
        out = _sweep(x0, x1, tri, entry=0.1, pairs=one)
        if out[2] == 2:
            held.add(int(out[3]))
    assert len(held) == 9, sorted(held)
