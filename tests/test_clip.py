"""Triangle-tetrahedron intersection polygon against exact rational clipping."""

from __future__ import annotations

import subprocess
import sys
from fractions import Fraction

from mpi4py import MPI

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fenics_matdepth.geometry.clip import (
    CLIP_SHIFT,
    CLIP_TOL,
    MAX_POLYGON_VERTICES,
    SHIFT_TANGENT,
    _snap,
    clip_nonempty,
    clip_shift,
    intersection_polygon,
    tet_gradients,
    triangle_area2,
    triangle_rows,
)
from fenics_matdepth.geometry.intersect import _BLOCK, _decide_block, intersect_pairs, near_pairs

# pure numba/numpy: every rank would run the same computation, so the serial pass runs it
pytestmark = pytest.mark.serial

# Float clipping works on barycentrics computed in floating point (error ~ 1e-16 times the
# tetrahedron's condition number, at most ~1e3 for the configurations drawn here; values within
# CLIP_TOL of zero are snapped to zero): on configurations that are not near-coplanar the area
# error is a few times 1e-13 of the triangle area, far below this relative tolerance.
AREA_RTOL = 1e-9


def _det3(a, b, c):
    return (
        a[0] * (b[1] * c[2] - b[2] * c[1])
        - a[1] * (b[0] * c[2] - b[2] * c[0])
        + a[2] * (b[0] * c[1] - b[1] * c[0])
    )


def exact_barycentrics(x_tri, x_tet, shift=(0.0, 0.0, 0.0)):
    """Exact ``lam[i][j] = lambda_j(x_tri[i] + shift)`` (Fractions, the float ``shift`` added
    exactly), None for a flat tetrahedron."""
    xs = [
        [Fraction(float(v)) + Fraction(float(d)) for v, d in zip(row, shift, strict=True)]
        for row in x_tri
    ]
    xt = [[Fraction(float(v)) for v in row] for row in x_tet]
    e = [[xt[k][r] - xt[0][r] for r in range(3)] for k in (1, 2, 3)]
    det = _det3(*e)
    if det == 0:
        return None
    lam = []
    for y in xs:
        d = [y[r] - xt[0][r] for r in range(3)]
        # Cramer's rule for (l1, l2, l3) in sum_k l_k e_k = d
        l1 = _det3(d, e[1], e[2]) / det
        l2 = _det3(e[0], d, e[2]) / det
        l3 = _det3(e[0], e[1], d) / det
        lam.append([1 - l1 - l2 - l3, l1, l2, l3])
    return lam


def exact_polygon(x_tri, x_tet):
    """Exact clipped polygon in triangle barycentrics (list of 3-tuples of Fractions), of the
    triangle moved by the clipper's consistent shift (`clip_shift`, rounded to float)."""
    lam = exact_barycentrics(x_tri, x_tet, clip_shift(x_tri))
    if lam is None:
        return []
    poly = [
        (Fraction(1), Fraction(0), Fraction(0)),
        (Fraction(0), Fraction(1), Fraction(0)),
        (Fraction(0), Fraction(0), Fraction(1)),
    ]
    for j in range(4):
        out = []
        for k in range(len(poly)):
            p = poly[k]
            q = poly[(k + 1) % len(poly)]
            lp = sum(p[i] * lam[i][j] for i in range(3))
            lq = sum(q[i] * lam[i][j] for i in range(3))
            if lp >= 0:
                out.append(p)
            if (lp > 0 and lq < 0) or (lp < 0 and lq > 0):
                t = lp / (lp - lq)
                out.append(tuple(p[i] + t * (q[i] - p[i]) for i in range(3)))
        poly = out
        if not poly:
            return []
    return poly


def exact_area_ratio(poly):
    """Polygon area over the parameter simplex area (shoelace in (mu_1, mu_2))."""
    s = Fraction(0)
    for k in range(len(poly)):
        p = poly[k]
        q = poly[(k + 1) % len(poly)]
        s += p[1] * q[2] - p[2] * q[1]
    return s


def polygon_area_3d(poly):
    if len(poly) < 3:
        return 0.0
    s = np.zeros(3)
    for k in range(len(poly)):
        s += np.cross(poly[k], poly[(k + 1) % len(poly)])
    return 0.5 * np.linalg.norm(s)


def triangle_area(x_tri):
    return 0.5 * np.linalg.norm(np.cross(x_tri[1] - x_tri[0], x_tri[2] - x_tri[0]))


def check_area(x_tri, x_tet):
    poly = intersection_polygon(x_tri, x_tet)
    assert np.all(np.isfinite(poly))
    area = polygon_area_3d(poly)
    expected = float(exact_area_ratio(exact_polygon(x_tri, x_tet))) * triangle_area(x_tri)
    assert area == pytest.approx(expected, rel=0, abs=AREA_RTOL * max(triangle_area(x_tri), 1e-300))
    return poly


coords = st.floats(-2.0, 2.0, allow_nan=False, allow_subnormal=False)
point = st.tuples(coords, coords, coords)
# adversarial: small integer grid -> coplanar faces, vertices on faces, edges through edges
grid = st.integers(-2, 2).map(float)
grid_point = st.tuples(grid, grid, grid)
half_grid = st.integers(-4, 4).map(lambda v: 0.5 * v)
half_point = st.tuples(half_grid, half_grid, half_grid)


def well_shaped(x_tet):
    e = x_tet[1:] - x_tet[0]
    h = max(np.linalg.norm(x_tet[a] - x_tet[b]) for a in range(4) for b in range(a))
    return abs(np.linalg.det(e)) > 1e-3 * h**3


@settings(max_examples=600, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(st.lists(point, min_size=3, max_size=3), st.lists(point, min_size=4, max_size=4))
def test_area_random(tri, tet):
    x_tri = np.array(tri)
    x_tet = np.array(tet)
    if not well_shaped(x_tet):
        return
    # A corner at a distance 0 < delta << 1 from a face plane is a near-coplanar configuration
    # whose cut points are only determined to rounding / delta (and corners within CLIP_TOL are
    # snapped onto the plane by design): exact incidences are covered by the grid test below.
    lam = exact_barycentrics(x_tri, x_tet)
    if any(0 < abs(v) < 1e-6 for row in lam for v in row):
        return
    check_area(x_tri, x_tet)


@settings(max_examples=800, deadline=None)
@given(st.lists(half_point, min_size=3, max_size=3), st.lists(grid_point, min_size=4, max_size=4))
def test_area_adversarial_grid(tri, tet):
    """Integer/half-integer coordinates: every kind of coplanarity and incidence occurs."""
    x_tri = np.array(tri)
    x_tet = np.array(tet)
    if np.linalg.det(x_tet[1:] - x_tet[0]) == 0.0:
        assert len(intersection_polygon(x_tri, x_tet)) == 0
        return
    check_area(x_tri, x_tet)


def test_triangle_in_face_plane_counts_on_its_normal_side():
    """A triangle in a face plane is moved off it by the consistent shift along its normal:
    it is the polygon (up to the shift) when the normal points into the tetrahedron, nothing
    when it points out."""
    x_tet = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    face = x_tet[[1, 2, 3]]  # normal (1, 1, 1): out of the tetrahedron
    assert len(check_area(face, x_tet)) == 0
    poly = check_area(face[[0, 2, 1]], x_tet)  # check_area: exact for the shifted triangle
    # moved into the tetrahedron by CLIP_SHIFT sqrt(2 A), the triangle loses strips of that width
    assert polygon_area_3d(poly) == pytest.approx(triangle_area(face), rel=10 * CLIP_SHIFT)
    inner = np.array([[0.1, 0.1, 0.0], [0.5, 0.1, 0.0], [0.1, 0.5, 0.0]])  # normal +z: in
    poly = check_area(inner, x_tet)
    assert polygon_area_3d(poly) == pytest.approx(triangle_area(inner), rel=10 * CLIP_SHIFT)
    assert len(check_area(inner[[0, 2, 1]], x_tet)) == 0


def test_clip_shift_size_and_direction():
    x_tri = np.array([[1.0, 2.0, 3.0], [3.0, 2.0, 3.0], [1.0, 2.0, 4.0]])  # normal -y, 2A = 2
    # normal part CLIP_SHIFT sqrt(2 A) along -y; in-plane parts along the first edge (+x) and
    # along n x t_1 = -y x x = +z
    a, b = SHIFT_TANGENT
    expected = CLIP_SHIFT * np.sqrt(2.0) * np.array([a, -1.0, b])
    np.testing.assert_allclose(clip_shift(x_tri), expected, rtol=1e-14)
    assert np.all(clip_shift(np.zeros((3, 3))) == 0.0)


def test_polygon_orientation_and_containment():
    """Vertices lie in the triangle plane and in the tetrahedron, counter-clockwise."""
    rng = np.random.default_rng(7)
    checked = 0
    for _ in range(200):
        x_tet = rng.normal(size=(4, 3))
        if not well_shaped(x_tet):
            continue
        x_tri = x_tet.mean(axis=0) + 0.8 * rng.normal(size=(3, 3))
        poly = check_area(x_tri, x_tet)
        if len(poly) < 3:
            continue
        checked += 1
        normal = np.cross(x_tri[1] - x_tri[0], x_tri[2] - x_tri[0])
        s = sum(np.cross(poly[k], poly[(k + 1) % len(poly)]) for k in range(len(poly)))
        assert s @ normal > 0.0
        plane = x_tri[0] + clip_shift(x_tri)  # the polygon lies in the shifted plane
        assert np.abs((poly - plane) @ normal).max() < 1e-12 * np.linalg.norm(normal)
        lam = np.linalg.solve(
            np.vstack([x_tet.T, np.ones(4)]), np.vstack([poly.T, np.ones(len(poly))])
        )
        assert lam.min() > -1e-10
    assert checked > 50


def test_area_continuous_under_perturbation():
    """Degenerate configurations: the area moves by O(perturbation)."""
    x_tet = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    cases = [
        np.array([[0.0, 0.0, 0.0], [0.5, -0.5, 0.5], [-0.5, 0.5, 0.5]]),  # vertex on a tet vertex
        np.array([[0.5, 0.5, -1.0], [0.5, 0.5, 1.0], [-1.0, -1.0, 0.0]]),  # edge through an edge
        np.array([[0.25, 0.25, 0.25], [2.0, 0.0, 0.0], [0.0, 0.0, 2.0]]),  # vertex inside, cut
    ]
    rng = np.random.default_rng(3)
    for x_tri in cases:
        a0 = polygon_area_3d(check_area(x_tri, x_tet))
        for scale in (1e-6, 1e-9, 1e-12):
            for _ in range(20):
                d = scale * rng.normal(size=(3, 3))
                a1 = polygon_area_3d(check_area(x_tri + d, x_tet))
                assert abs(a1 - a0) < 100 * scale + 1e-12


def test_area_in_face_plane_continuous_over_both_sides():
    """A triangle in the plane of a shared face counts in exactly one of the two tetrahedra
    (the one its normal points into); a tilt moves area from one to the other (each jumps),
    but the total over the two stays continuous."""
    x_tet = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    mirror = x_tet * np.array([1.0, 1.0, -1.0])
    x_tri = np.array([[0.2, 0.2, 0.0], [0.6, 0.2, 0.0], [0.2, 0.6, 0.0]])
    a_tri = triangle_area(x_tri)
    a0 = polygon_area_3d(check_area(x_tri, x_tet))
    assert a0 == pytest.approx(a_tri, rel=1e-12)  # normal +z, into x_tet
    # exactly in the plane the triangle is counted once, not on both sides
    assert len(check_area(x_tri, mirror)) == 0
    rng = np.random.default_rng(5)
    # a tilt by an angle ~ scale puts the cut points at rounding / scale: the total over both
    # sides is exact to ~ 1e-16 / scale (relative), so scale stays >= 1e-8 here
    for scale in (1e-4, 1e-6, 1e-8):
        for _ in range(20):
            d = scale * rng.normal(size=(3, 3))
            d[:, :2] = 0.0
            a_up = polygon_area_3d(intersection_polygon(x_tri + d, x_tet))
            a_down = polygon_area_3d(intersection_polygon(x_tri + d, mirror))
            assert a_up + a_down == pytest.approx(a_tri, rel=1e-6)
            assert min(a_up, a_down) < a_tri


def test_degenerate_inputs_finite():
    x_tet = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    flat = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    tri = np.array([[0.1, 0.1, -1.0], [0.1, 0.1, 1.0], [1.0, 1.0, 0.0]])
    assert len(intersection_polygon(tri, flat)) == 0
    line = np.array([[0.1, 0.1, 0.1], [0.2, 0.2, 0.2], [0.3, 0.3, 0.3]])
    assert len(intersection_polygon(line, x_tet)) == 0
    point = np.array([[0.1, 0.1, 0.1]] * 3)
    assert len(intersection_polygon(point, x_tet)) == 0
    huge = np.array([[-1e8, -1e8, 0.1], [1e8, 0.0, 0.1], [0.0, 1e8, 0.1]])
    poly = intersection_polygon(huge, x_tet)
    assert np.all(np.isfinite(poly)) and len(poly) >= 3


def test_batch_intersection_test_matches_polygon():
    """`intersect_pairs` flags exactly the pairs with a non-empty polygon."""
    rng = np.random.default_rng(11)
    nv = 60
    x = rng.normal(size=(nv, 3))
    tri = rng.integers(0, nv, size=(40, 3))
    tet = rng.integers(0, nv, size=(40, 4))
    pair_tri = rng.integers(0, 40, size=500)
    pair_tet = rng.integers(0, 40, size=500)
    flags = np.empty(500, dtype=bool)
    count = intersect_pairs(x, tri, tet, pair_tri, pair_tet, flags)
    expected = np.array(
        [
            len(intersection_polygon(x[tri[a]], x[tet[b]])) >= 3
            for a, b in zip(pair_tri, pair_tet, strict=True)
        ]
    )
    assert count == expected.sum() > 20
    np.testing.assert_array_equal(flags, expected)


def _clip_keeps_polygon(lam) -> bool:
    """Sutherland-Hodgman of the parameter simplex on the four barycentric values of each
    vertex, all of them carried along: the plain form of the test `intersect_pairs` makes
    (Python floats, the same operations in the same order)."""
    poly = [list(row) for row in lam]
    for j in range(4):
        out = []
        for k in range(len(poly)):
            p, q = poly[k], poly[(k + 1) % len(poly)]
            if p[j] >= 0.0:
                out.append(p)
            if (p[j] > 0.0 and q[j] < 0.0) or (p[j] < 0.0 and q[j] > 0.0):
                t = p[j] / (p[j] - q[j])
                out.append([p[r] + t * (q[r] - p[r]) for r in range(4)])
        if len(out) < 3:
            return False
        poly = out
    return True


def test_clip_nonempty_on_exact_zeros():
    """The clip decision on barycentric rows with many exact zeros and ties (small integers:
    vertices on face lines, edges along them, polygons shrunk to an edge or a point), where the
    count of vertices left, not the signs alone, decides."""
    rng = np.random.default_rng(17)
    buf = np.empty((2, MAX_POLYGON_VERTICES, 4))
    decided = [0, 0]
    for _ in range(20000):
        lam = rng.integers(-2, 3, size=(3, 4)).astype(float)
        lam[:, 0] = rng.integers(-1, 2, size=3)
        expected = _clip_keeps_polygon(lam.tolist())
        assert clip_nonempty(lam, buf) == expected
        decided[expected] += 1
    assert min(decided) > 2000


def _reference_flags(x, tri, tet, pair_tri, pair_tet):
    """The intersection test pair by pair from the clipper's parts: flat tetrahedron, shifted
    and snapped corner rows, separating face plane, corner strictly inside, clip, area."""
    flags = np.zeros(len(pair_tri), dtype=bool)
    grads = np.empty((4, 3))
    lam = np.empty((3, 4))
    for p, (a, b) in enumerate(zip(pair_tri, pair_tet, strict=True)):
        xs = np.ascontiguousarray(x[tri[a]])
        xt = np.ascontiguousarray(x[tet[b]])
        if tet_gradients(xt, grads) == 0.0 or triangle_area2(xs) == 0.0:
            continue
        triangle_rows(xs, xt, grads, lam)
        _snap(lam)
        if np.any(np.all(lam < 0.0, axis=0)):
            continue
        flags[p] = bool(np.any(np.all(lam > 0.0, axis=1))) or _clip_keeps_polygon(lam.tolist())
    return flags


def _degenerate_mesh(seed):
    """Vertices on a small (half-)integer grid: corners on face planes, triangles in face planes,
    edges through edges, flat tetrahedra and zero-area triangles (repeated or collinear
    vertices) all occur; a quarter of the triangles are tetrahedron faces, a quarter the same
    faces reversed."""
    rng = np.random.default_rng(seed)
    x = rng.integers(-2, 3, size=(40, 3)).astype(float)
    x[:20] *= 0.5
    tri = rng.integers(0, 40, size=(120, 3))
    tet = rng.integers(0, 40, size=(120, 4))
    tri[:30] = tet[rng.integers(0, 120, size=30)][:, [1, 2, 3]]
    tri[30:60] = tet[rng.integers(0, 120, size=30)][:, [0, 2, 1]]
    # a rotated and shifted copy: the same incidences up to rounding of the coordinates
    rot, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return x, tri, tet, x @ rot + 0.37


@pytest.mark.parametrize("seed", [0, 1])
def test_batch_intersection_test_degenerate_pairs(seed):
    """`intersect_pairs` decides degenerate pairs exactly as the clipper's parts do (the
    shift, the snapping, the flat and zero-area cases), with candidates in random order and
    grouped by triangle (the per-triangle values it reuses along a group)."""
    x, tri, tet, x_rot = _degenerate_mesh(seed)
    rng = np.random.default_rng(100 + seed)
    pair_tri = rng.integers(0, len(tri), size=3000)
    pair_tet = rng.integers(0, len(tet), size=3000)
    for coords in (x, x_rot):
        expected = _reference_flags(coords, tri, tet, pair_tri, pair_tet)
        assert 300 < expected.sum() < 2700
        for order in (np.arange(3000), np.argsort(pair_tri, kind="stable")):
            flags = np.empty(3000, dtype=bool)
            count = intersect_pairs(coords, tri, tet, pair_tri[order], pair_tet[order], flags)
            np.testing.assert_array_equal(flags, expected[order])
            assert count == expected.sum()


def _mixed_pairs(n, seed):
    """Separate (triangle, tetrahedron) pairs of unit size around one another, as the kernel
    benchmark draws them: face-separated pairs, corners inside and pairs the clip decides."""
    rng = np.random.default_rng(seed)
    x_tet = rng.normal(size=(n, 4, 3))
    x_tri = x_tet.mean(axis=1, keepdims=True) + 0.3 * rng.normal(size=(n, 1, 3))
    x_tri = x_tri + 0.6 * rng.normal(size=(n, 3, 3))
    x = np.concatenate([x_tri, x_tet], axis=1).reshape(-1, 3)
    tri = 7 * np.arange(n)[:, None] + np.arange(3)
    tet = 7 * np.arange(n)[:, None] + 3 + np.arange(4)
    return x, tri, tet


@pytest.mark.parametrize("seed", [0, 1])
def test_decide_block_rows_and_decisions(seed):
    """`_decide_block` (the vectorised part of `intersect_pairs`) writes the clipper's snapped
    rows bit for bit and settles exactly the pairs the clipper's parts settle: empty for a flat
    tetrahedron, a zero-area triangle or a face plane with every corner strictly outside, a
    corner strictly inside, the clip for the rest; on degenerate grid pairs (exact zeros, ties,
    flat tetrahedra) and on a random mix."""
    grid, tri_g, tet_g, grid_rot = _degenerate_mesh(seed)
    x_mix, tri_m, tet_m = _mixed_pairs(400, seed)
    rng = np.random.default_rng(200 + seed)
    cases = [(coords, tri_g, tet_g) for coords in (grid, grid_rot)] + [(x_mix, tri_m, tet_m)]
    seen = np.zeros(3, dtype=int)
    grads = np.empty((4, 3))
    lam = np.empty((3, 4))
    for coords, tri, tet in cases:
        for _ in range(8):
            pair_tri = rng.integers(0, len(tri), size=_BLOCK)
            pair_tet = rng.integers(0, len(tet), size=_BLOCK)
            if tri is tri_m:
                pair_tet = pair_tri  # the mix's pairs are its triangles and tetrahedra in order
            w = np.full(34 * _BLOCK, np.nan)
            block = w.reshape(34, _BLOCK)
            block[:9] = coords[tri[pair_tri]].reshape(-1, 9).T
            block[9:21] = coords[tet[pair_tet]].reshape(-1, 12).T
            m = _BLOCK - int(rng.integers(0, 3))  # a short block leaves its tail alone
            _decide_block(w, m)
            assert np.all(np.isnan(block[21:, m:]))
            for k in range(m):
                xs = np.ascontiguousarray(coords[tri[pair_tri[k]]])
                xt = np.ascontiguousarray(coords[tet[pair_tet[k]]])
                if tet_gradients(xt, grads) == 0.0 or triangle_area2(xs) == 0.0:
                    expected = 0
                else:
                    triangle_rows(xs, xt, grads, lam)
                    _snap(lam)
                    np.testing.assert_array_equal(block[21:33, k].reshape(3, 4), lam)
                    if np.any(np.all(lam < 0.0, axis=0)):
                        expected = 0
                    elif np.any(np.all(lam > 0.0, axis=1)):
                        expected = 1
                    else:
                        expected = 2
                assert block[33, k] == expected
                seen[expected] += 1
    assert np.all(seen > 100)


@pytest.mark.parametrize("n", [0, 1, _BLOCK - 1, _BLOCK, _BLOCK + 1, 3 * _BLOCK + 5])
def test_batch_intersection_test_block_sizes(n):
    """Runs of pairs shorter, as long and longer than a block (a partial last block): the flags
    of the clipper's parts, pair by pair."""
    x, tri, tet = _mixed_pairs(max(n, 1), 5)
    pairs = np.arange(n)
    flags = np.ones(n, dtype=bool)
    count = intersect_pairs(x, tri, tet, pairs, pairs, flags)
    expected = _reference_flags(x, tri, tet, pairs, pairs)
    np.testing.assert_array_equal(flags, expected)
    assert count == expected.sum()


def test_clip_tolerance_is_small():
    """The documented band is far below the area tolerance used above."""
    assert CLIP_TOL * 1e3 < AREA_RTOL


def _sampled_distance(x_tri, x_tet, n=24) -> float:
    """An upper bound of the triangle-tetrahedron distance: the least distance between points
    sampled on the triangle and on the tetrahedron's faces (exact as n grows)."""
    t = np.linspace(0.0, 1.0, n + 1)
    a, b = np.meshgrid(t, t, indexing="ij")
    inside = a + b <= 1.0
    w = np.stack((1.0 - a[inside] - b[inside], a[inside], b[inside]), axis=1)
    on_tri = w @ x_tri
    faces = [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]
    on_tet = np.vstack([w @ x_tet[f] for f in faces])
    diff = on_tri[:, None, :] - on_tet[None, :, :]
    return float(np.sqrt((diff**2).sum(axis=2).min()))


def _one_pair_near(x_tri, x_tet, gap) -> bool:
    x = np.vstack((x_tri, x_tet)).astype(float)
    kept, _ = near_pairs(
        x, np.array([[0, 1, 2]]), np.array([[3, 4, 5, 6]]), np.zeros(1, np.int64),
        np.zeros(1, np.int64), gap,
    )  # fmt: skip
    return kept.size == 1


REFERENCE_TET = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])


@pytest.mark.parametrize("d", [0.05, 0.0999, 0.1001, 0.3])
def test_near_pairs_face_parallel_triangle(d):
    """A triangle parallel to the face z = 0 of the reference tetrahedron, at distance d below
    it, is kept exactly when d <= gap (0.1): the face plane separates it otherwise."""
    tri = np.array([[0.2, 0.2, -d], [0.6, 0.2, -d], [0.2, 0.6, -d]])
    assert _one_pair_near(tri, REFERENCE_TET, 0.1) == (d <= 0.1)


def test_near_pairs_triangle_plane_separates():
    """A large triangle in the plane z = 1.2 lies 0.2 above the apex: dropped for gap 0.1
    (only the triangle's plane separates them: no face plane has all its corners outside),
    kept for gap 0.25."""
    tri = np.array([[-5.0, -5.0, 1.2], [5.0, -5.0, 1.2], [0.0, 5.0, 1.2]])
    assert not _one_pair_near(tri, REFERENCE_TET, 0.1)
    assert _one_pair_near(tri, REFERENCE_TET, 0.25)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(point, min_size=3, max_size=3), st.lists(point, min_size=4, max_size=4))
def test_near_pairs_never_drop_a_pair_within_gap(tri, tet):
    """Conservative: a pair whose (sampled, hence over-estimated) distance is within the gap
    is always kept."""
    x_tri, x_tet = np.array(tri, dtype=float), np.array(tet, dtype=float)
    gap = 0.3
    if _sampled_distance(x_tri, x_tet) <= gap:
        assert _one_pair_near(x_tri, x_tet, gap)


_FAST_CALLER = """
import numpy as np
from numba import njit
from fenics_matdepth.geometry import clip, intersect

@njit(fastmath={"contract"})
def caller(x, tri, tet, pair_tri, pair_tet, out, a, b, c):
    return intersect.intersect_pairs(x, tri, tet, pair_tri, pair_tet, out), a * b + c

x = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
x[:3, 2] = 0.25
one = np.zeros(1, dtype=np.int64)
print(caller(x, np.array([[0, 1, 2]]), np.array([[3, 4, 5, 6]]), one, one,
             np.empty(1, dtype=np.bool_), 1.0, 2.0, 3.0)[0])

def ir(d):
    return " ".join(c.library.get_llvm_str() for c in d.overloads.values())

assert " contract " in ir(caller)
kernels = [getattr(m, n) for m in (clip, intersect) for n in dir(m)
           if hasattr(getattr(m, n), "overloads")]
assert any(k.overloads for k in kernels if k.py_func.__module__ == clip.__name__)
print(sorted(k.__name__ for k in kernels if k.overloads and " contract " in ir(k)))
"""


def test_clip_stays_exact_under_a_fast_math_caller(tmp_path, child_env):
    """numba compiles a function that has no fast-math setting of its own with the flags of
    the caller it is first compiled for, and keeps that machine code for every later call
    (and on disk). The pair kernels fuse multiply-adds; the clip's sign tests must not,
    whichever is compiled first. Compiled fresh (an empty cache) in a child process, first
    for a caller with fused multiply-adds: no clip function carries the flag."""
    if MPI.COMM_WORLD.rank != 0:  # one child is enough
        return
    env = dict(child_env, NUMBA_CACHE_DIR=str(tmp_path), MATDEPTH_QUIET_JIT="1")
    out = subprocess.run(
        [sys.executable, "-c", _FAST_CALLER], env=env, capture_output=True, text=True, check=True
    )
    hit, contracted = out.stdout.split("\n")[:2]
    assert hit == "1"  # the triangle at height 1/4 cuts the tetrahedron
    assert contracted == "[]"
