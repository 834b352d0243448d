"""Contact pair kernels: energies against exact integrals, derivatives against finite
differences, invariances, continuity of the force along a sliding path, degenerate inputs."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest
from conftest import assert_fd_derivatives, rel_err
from hypothesis import given, settings
from hypothesis import strategies as st
from test_clip import exact_barycentrics

from fenics_matdepth.contact.kernels import collocation_energy, pair_energy
from fenics_matdepth.contact.kernels.area_derivatives import clip_shift_jacobian
from fenics_matdepth.contact.kernels.augmented import area_pairs_augmented
from fenics_matdepth.contact.kernels.collocation import collocation_pairs
from fenics_matdepth.contact.kernels.drivers import area_pairs, area_pairs_into, intersecting
from fenics_matdepth.geometry.clip import MAX_POLYGON_VERTICES, _intersection_polygon, clip_shift

# pure numba/numpy: every rank would run the same computation, so the serial pass runs it
pytestmark = pytest.mark.serial

EPS = 3.0  # penalty (pressure / length)
# Relative errors (max-norm, relative to the largest entry) allowed against 4th-order central
# differences with h = 1e-4: truncation ~ h^4 |f^(5)| ~ 1e-15 and rounding ~ 1e-16 / h ~ 1e-12
# on the well-conditioned configurations used, so 1e-6 leaves a wide margin yet catches any
# missing term (which shows up at the 1e-2 .. 1 level).
FD_RTOL = 1e-6


# ---------------------------------------------------------------- helpers
def split(x):
    return x[:9].reshape(3, 3), x[9:].reshape(4, 3)


def area_fun(depth, penalty=EPS):
    def f(x):
        return pair_energy(*split(x), depth, penalty)

    return f


def polygon_mu(x_tri, x_tet):
    mu = np.empty((2, MAX_POLYGON_VERTICES, 3))
    vlab = np.empty((2, MAX_POLYGON_VERTICES, 2), dtype=np.int64)
    elab = np.empty((2, MAX_POLYGON_VERTICES), dtype=np.int64)
    n = _intersection_polygon(x_tri, x_tet, mu, vlab, elab)
    return mu[0, :n].copy()


def well_conditioned(x_tri, x_tet, margin=2e-2):
    """Non-empty polygon whose combinatorics cannot change within a 4e-4 stencil: edges not
    short, corners not near face planes, well-shaped tetrahedron."""
    e = x_tet[1:] - x_tet[0]
    h = max(np.linalg.norm(x_tet[a] - x_tet[b]) for a in range(4) for b in range(a))
    if abs(np.linalg.det(e)) < 5e-2 * h**3:
        return False
    mu = polygon_mu(x_tri, x_tet)
    if len(mu) < 3:
        return False
    if min(np.linalg.norm(mu[k] - mu[k - 1]) for k in range(len(mu))) < margin:
        return False
    lam = np.linalg.solve(np.vstack([x_tet.T, np.ones(4)]), np.vstack([x_tri.T, np.ones(3)]))
    return np.abs(lam).min() > margin


def random_configs(seed, count, spread=0.8):
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < count:
        x_tet = rng.normal(size=(4, 3))
        x_tri = x_tet.mean(axis=0) + spread * rng.normal(size=(3, 3))
        depth = rng.uniform(0.0, 1.0, size=4)
        if well_conditioned(x_tri, x_tet):
            out.append((x_tri, x_tet, depth))
    return out


def _det3(a, b, c):
    return (
        a[0] * (b[1] * c[2] - b[2] * c[1])
        - a[1] * (b[0] * c[2] - b[2] * c[0])
        + a[2] * (b[0] * c[1] - b[1] * c[0])
    )


def exact_phi(x_tri, x_tet, depth):
    """Exact int_P g^2 dxi over the clipped parameter polygon (rational arithmetic), of the
    triangle moved by the clipper's consistent shift (`clip_shift`, added exactly)."""
    lam = exact_barycentrics(x_tri, x_tet, clip_shift(x_tri))
    d = [Fraction(float(v)) for v in depth]
    poly = [(Fraction(1), Fraction(0), Fraction(0))]
    poly += [(Fraction(0), Fraction(1), Fraction(0)), (Fraction(0), Fraction(0), Fraction(1))]
    for j in range(4):
        out = []
        for k in range(len(poly)):
            p, q = poly[k], poly[(k + 1) % len(poly)]
            lp = sum(p[i] * lam[i][j] for i in range(3))
            lq = sum(q[i] * lam[i][j] for i in range(3))
            if lp >= 0:
                out.append(p)
            if (lp > 0 > lq) or (lp < 0 < lq):
                t = lp / (lp - lq)
                out.append(tuple(p[i] + t * (q[i] - p[i]) for i in range(3)))
        poly = out
        if not poly:
            return Fraction(0)
    g_corner = [sum(lam[i][j] * d[j] for j in range(4)) for i in range(3)]

    def g(mu):
        return sum(mu[i] * g_corner[i] for i in range(3))

    phi = Fraction(0)
    for k in range(1, len(poly) - 1):
        a, b, c = poly[0], poly[k], poly[k + 1]
        area = _det3(a, b, c) / 2  # the parameter simplex has area 1/2
        ga, gb, gc = g(a), g(b), g(c)
        phi += area / 6 * (ga * ga + gb * gb + gc * gc + ga * gb + gb * gc + gc * ga)
    return phi


def triangle_area(x_tri):
    return 0.5 * np.linalg.norm(np.cross(x_tri[1] - x_tri[0], x_tri[2] - x_tri[0]))


# ---------------------------------------------------------------- energies
def test_energy_triangle_inside_analytical():
    """Triangle inside K: E = eps/2 * A/6 * (a^2 + b^2 + c^2 + ab + bc + ca), a, b, c = g at
    the corners (g is affine on the triangle)."""
    x_tet = np.array([[0.0, 0, 0], [2, 0, 0], [0, 2, 0], [0, 0, 2]])
    depth = np.array([0.3, 0.0, 0.5, 1.2])
    x_tri = np.array([[0.2, 0.3, 0.4], [0.9, 0.2, 0.3], [0.3, 0.6, 0.8]])
    y = x_tri + clip_shift(x_tri)  # the corners as the clipper sees them
    lam = np.linalg.solve(np.vstack([x_tet.T, np.ones(4)]), np.vstack([y.T, np.ones(3)]))
    a, b, c = depth @ lam
    expected = EPS / 2 * triangle_area(x_tri) / 6 * (a * a + b * b + c * c + a * b + b * c + c * a)
    energy, _, _ = pair_energy(x_tri, x_tet, depth, EPS)
    assert energy == pytest.approx(expected, rel=1e-13)


def test_energy_constant_depth_is_area():
    """Constant depth d: E = eps/2 d^2 * area(T cap K); a triangle through the middle of a cube
    corner tetrahedron cut by the plane z = 0.25 gives a known area."""
    x_tet = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    x_tri = np.array([[-1.0, -1.0, 0.25], [3.0, -1.0, 0.25], [-1.0, 3.0, 0.25]])
    # the section z = 1/4 is a right triangle with legs 3/4, at the plane moved by the clip
    # shift (4e-9 along +z): legs 3/4 - shift
    dz = clip_shift(x_tri)[2]
    assert 0.0 < dz < 1e-8
    energy, _, _ = pair_energy(x_tri, x_tet, np.full(4, 0.7), EPS)
    assert energy == pytest.approx(EPS / 2 * 0.49 * 0.5 * (0.75 - dz) ** 2, rel=1e-13)


def test_energy_against_exact_rational_random():
    for x_tri, x_tet, depth in random_configs(1, 60):
        expected = EPS * triangle_area(x_tri) * float(exact_phi(x_tri, x_tet, depth))
        energy, _, _ = pair_energy(x_tri, x_tet, depth, EPS)
        assert energy == pytest.approx(expected, rel=1e-9)


grid = st.integers(-2, 2).map(float)
half_grid = st.integers(-4, 4).map(lambda v: 0.5 * v)


@settings(max_examples=300, deadline=None)
@given(
    st.lists(st.tuples(half_grid, half_grid, half_grid), min_size=3, max_size=3),
    st.lists(st.tuples(grid, grid, grid), min_size=4, max_size=4),
    st.lists(st.integers(0, 4).map(lambda v: 0.25 * v), min_size=4, max_size=4),
)
def test_energy_against_exact_rational_adversarial(tri, tet, depth):
    """Integer grids: coplanar faces, vertices on faces, edges through edges, flat tets."""
    x_tri, x_tet, depth = np.array(tri), np.array(tet), np.array(depth)
    energy, grad, hess = pair_energy(x_tri, x_tet, depth, EPS)
    assert np.isfinite(energy) and np.all(np.isfinite(grad)) and np.all(np.isfinite(hess))
    # integer data: the determinant is an integer, rounding cannot hide a flat tetrahedron
    if round(np.linalg.det(x_tet[1:] - x_tet[0])) == 0 or triangle_area(x_tri) == 0.0:
        assert energy == 0.0
        return
    expected = EPS * triangle_area(x_tri) * float(exact_phi(x_tri, x_tet, depth))
    assert energy == pytest.approx(expected, rel=1e-9, abs=1e-13)


# ---------------------------------------------------------------- derivatives
@pytest.mark.parametrize("seed", [2, 3])
def test_gradient_hessian_finite_differences(seed):
    for x_tri, x_tet, depth in random_configs(seed, 15):
        x0 = np.concatenate([x_tri.ravel(), x_tet.ravel()])
        assert_fd_derivatives(area_fun(depth), x0, FD_RTOL, symmetric=True)


def test_gradient_hessian_edge_on_face_boundary_terms():
    """Polygon edges on tetrahedron faces with non-zero depth there: the boundary terms that
    only cancel in sums over neighbours must be in the per-pair derivatives."""
    x_tet = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    depth = np.array([0.9, 0.4, 0.6, 0.8])  # g != 0 on every face
    x_tri = np.array([[-0.3, 0.2, 0.3], [0.8, -0.2, 0.1], [0.1, 0.9, 0.2]])
    x0 = np.concatenate([x_tri.ravel(), x_tet.ravel()])
    assert len(polygon_mu(x_tri, x_tet)) >= 5
    assert_fd_derivatives(area_fun(depth), x0, FD_RTOL)


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])
def test_clip_shift_jacobian_against_differences(scale):
    """The kernels' exact Jacobian of the clip shift equals 4th-order central differences of
    `clip_shift`, on random triangles, slivers and triangles far from the origin. (The pair
    derivatives cannot check it: the shift is 1e-9 of the element size.)"""
    rng = np.random.default_rng(7)
    triangles = [rng.normal(size=(3, 3)) for _ in range(20)]
    sliver = np.array([[0.0, 0, 0], [1, 0, 0], [0.5, 1e-3, 0]])
    needle = np.array([[0.0, 0, 0], [1e-2, 0, 0], [0.3, 1, 0.2]])
    far = rng.normal(size=(3, 3)) + 100.0
    for x_tri in [*triangles, sliver, needle, far]:
        x_tri = scale * x_tri
        ds = np.empty((3, 9))
        clip_shift_jacobian(x_tri, ds)
        h = 1e-5 * scale
        fd = np.empty((3, 9))
        for col in range(9):
            e = np.zeros(9)
            e[col] = h
            e = e.reshape(3, 3)
            fd[:, col] = (
                8.0 * (clip_shift(x_tri + e) - clip_shift(x_tri - e))
                - (clip_shift(x_tri + 2 * e) - clip_shift(x_tri - 2 * e))
            ) / (12.0 * h)
        assert rel_err(ds, fd) < 1e-6


def test_taylor_remainder():
    """|E(x + h v) - E - h g.v| ~ h^2 and, with the Hessian term, ~ h^3."""
    x_tri, x_tet, depth = random_configs(4, 1)[0]
    x0 = np.concatenate([x_tri.ravel(), x_tet.ravel()])
    f = area_fun(depth)
    e0, g0, h0 = f(x0)
    v = np.random.default_rng(5).normal(size=21)
    hs = 1e-3 * 0.5 ** np.arange(6)
    r1, r2 = [], []
    for h in hs:
        e = f(x0 + h * v)[0]
        r1.append(abs(e - e0 - h * g0 @ v))
        r2.append(abs(e - e0 - h * g0 @ v - 0.5 * h * h * v @ h0 @ v))
    rate1 = np.log2(np.array(r1[:-1]) / np.array(r1[1:]))
    rate2 = np.log2(np.array(r2[:-1]) / np.array(r2[1:]))
    assert np.all(np.abs(rate1 - 2.0) < 0.1)
    assert np.all(np.abs(rate2 - 3.0) < 0.2)


def test_translation_and_rotation_invariance():
    rng = np.random.default_rng(6)
    for x_tri, x_tet, depth in random_configs(7, 10):
        energy, grad, hess = pair_energy(x_tri, x_tet, depth, EPS)
        # translation: the 7 vertex forces sum to zero, and so do the Hessian's vertex blocks
        scale = np.abs(grad).max()
        assert np.abs(grad.reshape(7, 3).sum(axis=0)).max() < 1e-12 * scale
        assert np.abs(hess.reshape(21, 7, 3).sum(axis=1)).max() < 1e-11 * np.abs(hess).max()
        shift = rng.normal(size=3)
        e_shift = pair_energy(x_tri + shift, x_tet + shift, depth, EPS)[0]
        assert e_shift == pytest.approx(energy, rel=1e-12)
        # rotation: E(Rx) = E(x), grad(Rx) = R grad(x), hess(Rx) = R hess R^T
        rot, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        rot *= np.sign(np.linalg.det(rot))
        e_rot, g_rot, h_rot = pair_energy(x_tri @ rot.T, x_tet @ rot.T, depth, EPS)
        assert e_rot == pytest.approx(energy, rel=1e-12)
        big = np.kron(np.eye(7), rot)
        np.testing.assert_allclose(g_rot, big @ grad, rtol=0, atol=1e-12 * scale)
        np.testing.assert_allclose(h_rot, big @ hess @ big.T, atol=1e-11 * np.abs(hess).max())


# ---------------------------------------------------------------- collocation
def test_collocation_value_and_derivatives():
    rng = np.random.default_rng(8)
    x_tet = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]) + 0.1 * rng.normal(size=(4, 3))
    depth = np.array([0.2, 0.5, 0.1, 0.9])
    weight = 0.37
    checked = 0
    for _ in range(20):
        x_node = x_tet.mean(axis=0) + 0.1 * rng.normal(size=3)
        lam = np.linalg.solve(np.vstack([x_tet.T, np.ones(4)]), np.append(x_node, 1.0))
        energy, grad, hess = collocation_energy(x_node, x_tet, depth, weight, EPS)
        if lam.min() < 0:
            assert energy == 0.0 and not grad.any() and not hess.any()
            continue
        checked += 1
        assert energy == pytest.approx(0.5 * EPS * weight * (lam @ depth) ** 2, rel=1e-13)
        x0 = np.concatenate([x_node, x_tet.ravel()])

        def f(x):
            return collocation_energy(x[:3], x[3:].reshape(4, 3), depth, weight, EPS)

        assert_fd_derivatives(f, x0, FD_RTOL, exact=(grad, hess))
    assert checked > 5
    outside = collocation_energy(np.array([2.0, 2.0, 2.0]), x_tet, depth, weight, EPS)
    assert outside[0] == 0.0


# ---------------------------------------------------------------- continuity along a path
def _ridge_setup():
    """Two tetrahedra sharing the face z = 0 (vertices 1, 2, 3); the depth peaks on the shared
    face (0 above, 0.5 on it, 0.1 below): the depth gradient turns, as at a concave corner."""
    x_mesh = np.array(
        [[0.0, 0.0, 1.5], [-1.0, -1.0, 0.0], [2.0, -1.0, 0.0], [-1.0, 2.0, 0.0], [0.0, 0.0, -1.5]]
    )
    depth_mesh = np.array([0.0, 0.5, 0.5, 0.5, 0.1])
    tets = np.array([[0, 1, 2, 3], [4, 1, 2, 3]])
    x_tri = np.array([[0.05, 0.1, 0.0], [0.35, 0.05, 0.07], [0.1, 0.4, -0.05]])
    direction = np.array([0.05, 0.03, -1.0])
    return x_mesh, depth_mesh, tets, x_tri, direction / np.linalg.norm(direction)


def _path_forces(kind, steps=10_000, length=3.2):
    """Global force (8 vertices: triangle, then mesh) and d(force)/ds along the path."""
    x_mesh, depth_mesh, tets, x_tri0, v = _ridge_setup()
    nv = 3 + len(x_mesh)
    x_all = np.vstack([x_tri0, x_mesh])
    depth = np.concatenate([np.zeros(3), depth_mesh])
    tri = np.array([[0, 1, 2]])
    tet = tets + 3
    weight = np.full(nv, triangle_area(x_tri0) / 3.0)
    ds = length / steps
    start = 1.6 / v[2] * v  # z = +1.6: above both tetrahedra
    forces = np.empty((steps + 1, 3 * nv))
    slopes = np.empty(steps + 1)
    move = np.zeros((nv, 3))
    move[:3] = v
    for k in range(steps + 1):
        x = x_all.copy()
        x[:3] += start + k * ds * v
        force = np.zeros((nv, 3))
        hess = np.zeros((3 * nv, 3 * nv))
        if kind == "area":
            _, g, h = area_pairs(
                x, depth, tri, tet, np.zeros(2, np.int64), np.arange(2), EPS, True, True
            )
            dofs = [np.concatenate([tri[0], tet[p]]) for p in range(2)]
        else:
            nodes = np.repeat(np.arange(3), 2)
            kk = np.tile(np.arange(2), 3)
            _, g, h = collocation_pairs(x, depth, weight, tet, nodes, kk, EPS, True, True)
            dofs = [np.concatenate([[nodes[p]], tet[kk[p]]]) for p in range(len(nodes))]
        for p, vert in enumerate(dofs):
            idx = (3 * vert[:, None] + np.arange(3)).ravel()
            force[vert] += g[p].reshape(-1, 3)
            hess[np.ix_(idx, idx)] += h[p]
        forces[k] = force.ravel()
        slopes[k] = np.abs(hess @ move.ravel()).max()
    return forces, slopes, ds


def test_force_continuity_area_vs_collocation():
    """Slide a triangle through the two tetrahedra in 10^4 steps (it enters across exterior
    faces, crosses the shared face where grad g turns, leaves): every per-step change of the
    area-integrated force is bounded by step * max |dF/ds| (F is continuous, piecewise C1);
    the collocation force jumps by orders of magnitude more than that bound."""
    f_area, s_area, ds = _path_forces("area")
    jumps = np.abs(np.diff(f_area, axis=0)).max(axis=1)
    assert np.abs(f_area).max() > 0.0
    assert jumps.max() <= 2.0 * ds * s_area.max() + 1e-12 * np.abs(f_area).max()

    f_col, s_col, ds = _path_forces("collocation")
    jumps_col = np.abs(np.diff(f_col, axis=0)).max(axis=1)
    assert jumps_col.max() > 50.0 * ds * s_col.max()


# ---------------------------------------------------------------- degenerate inputs
DEGENERATE = {
    "triangle is a face": (np.array([[1.0, 0, 0], [0, 1, 0], [0, 0, 1]]), None),
    "triangle in a face plane": (
        np.array([[0.2, 0.2, 0.0], [0.6, 0.2, 0.0], [0.2, 0.6, 0.0]]),
        None,
    ),
    "vertex on a face": (np.array([[0.2, 0.2, 0.0], [0.5, 0.3, -0.6], [0.1, 0.6, -0.4]]), None),
    "vertex on a tet vertex": (np.array([[0.0, 0, 0], [0.5, -0.5, 0.5], [-0.5, 0.5, 0.5]]), None),
    "edge through an edge": (
        np.array([[0.5, 0.5, -1.0], [0.5, 0.5, 1.0], [-1.0, -1.0, 0.0]]),
        None,
    ),
    "edge along an edge": (np.array([[-0.5, 0.0, 0.0], [1.5, 0.0, 0.0], [0.3, 0.4, 0.2]]), None),
    "zero-area triangle": (np.array([[0.1, 0.1, 0.1], [0.2, 0.2, 0.2], [0.4, 0.4, 0.4]]), None),
    "flat tetrahedron": (
        np.array([[0.1, 0.1, -1.0], [0.1, 0.1, 1.0], [1.0, 1.0, 0.0]]),
        np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]),
    ),
    "nearly flat tetrahedron": (
        np.array([[0.1, 0.1, -1.0], [0.1, 0.1, 1.0], [1.0, 1.0, 0.0]]),
        np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0.3, 0.3, 1e-13]]),
    ),
}


@pytest.mark.parametrize("name", list(DEGENERATE))
def test_degenerate_inputs_finite_and_continuous(name):
    x_tri, x_tet = DEGENERATE[name]
    if x_tet is None:
        x_tet = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    depth = np.array([0.9, 0.4, 0.6, 0.8])
    energy, grad, hess = pair_energy(x_tri, x_tet, depth, EPS)
    assert np.isfinite(energy) and np.all(np.isfinite(grad)) and np.all(np.isfinite(hess))
    if name in ("zero-area triangle", "flat tetrahedron"):
        assert energy == 0.0 and not grad.any() and not hess.any()
    for x_node in np.vstack([x_tri, x_tet]):  # on faces, edges, vertices of the tetrahedron
        e_c, g_c, h_c = collocation_energy(x_node, x_tet, depth, 0.5, EPS)
        assert np.isfinite(e_c) and np.all(np.isfinite(g_c)) and np.all(np.isfinite(h_c))
    if name in ("triangle in a face plane", "triangle is a face"):
        return  # in a face plane a tilt moves area to the neighbour (tested in test_clip.py)
    # continuity: small perturbations change the energy by O(perturbation)
    rng = np.random.default_rng(9)
    for scale in (1e-7, 1e-10):
        for _ in range(10):
            e1 = pair_energy(x_tri + scale * rng.normal(size=(3, 3)), x_tet, depth, EPS)[0]
            assert abs(e1 - energy) < 1e3 * scale + 1e-12


# ---------------------------------------------------------------- batch drivers
def test_batch_drivers_match_single_pairs():
    rng = np.random.default_rng(10)
    nv = 40
    x = rng.normal(size=(nv, 3))
    depth = rng.uniform(size=nv)
    tri = np.array([rng.choice(nv, 3, replace=False) for _ in range(15)])
    tet = np.array([rng.choice(nv, 4, replace=False) for _ in range(15)])
    pair_tri = rng.integers(0, 15, size=200)
    pair_tet = rng.integers(0, 15, size=200)
    energy, grad, hess = area_pairs(x, depth, tri, tet, pair_tri, pair_tet, EPS, True, True)
    for p in range(200):
        e1, g1, h1 = pair_energy(
            x[tri[pair_tri[p]]], x[tet[pair_tet[p]]], depth[tet[pair_tet[p]]], EPS
        )
        assert energy[p] == e1
        np.testing.assert_array_equal(grad[p], g1)
        np.testing.assert_array_equal(hess[p], h1)
    assert np.count_nonzero(energy) > 20
    e_only, g_none, h_none = area_pairs(x, depth, tri, tet, pair_tri, pair_tet, EPS, False, False)
    np.testing.assert_array_equal(e_only, energy)
    assert g_none.shape == (0, 21) and h_none.shape == (0, 21, 21)
    # the intersection test the operator runs first, then the pair kernel on those pairs
    active = intersecting(x, tri, tet, pair_tri, pair_tet)
    np.testing.assert_array_equal(active, np.flatnonzero(energy != 0.0))
    e_act, g_act, h_act = area_pairs(
        x, depth, tri, tet, pair_tri[active], pair_tet[active], EPS, True, True
    )
    np.testing.assert_array_equal(e_act, energy[active])
    np.testing.assert_array_equal(g_act, grad[active])
    np.testing.assert_array_equal(h_act, hess[active])

    # preallocated compact output; too small a capacity reports the count needed
    cap = len(active) + 3
    out = (np.empty(cap, np.int64), np.empty(cap), np.empty((cap, 21)), np.empty((cap, 21, 21)))
    m = area_pairs_into(x, depth, tri, tet, pair_tri, pair_tet, EPS, True, True, *out)
    assert m == len(active)
    np.testing.assert_array_equal(out[0][:m], active)
    np.testing.assert_array_equal(out[1][:m], e_act)
    np.testing.assert_array_equal(out[2][:m], g_act)
    np.testing.assert_array_equal(out[3][:m], h_act)
    small = (np.empty(5, np.int64), np.empty(5), np.empty((5, 21)), np.empty((5, 21, 21)))
    assert area_pairs_into(x, depth, tri, tet, pair_tri, pair_tet, EPS, True, True, *small) == m
    np.testing.assert_array_equal(small[3], h_act[:5])

    weight = rng.uniform(size=nv)
    pair_node = rng.integers(0, nv, size=200)
    e_c, g_c, h_c = collocation_pairs(x, depth, weight, tet, pair_node, pair_tet, EPS, True, True)
    for p in range(200):
        k = tet[pair_tet[p]]
        e1, g1, h1 = collocation_energy(x[pair_node[p]], x[k], depth[k], weight[pair_node[p]], EPS)
        assert e_c[p] == e1
        np.testing.assert_array_equal(g_c[p], g1)
        np.testing.assert_array_equal(h_c[p], h1)


def test_pairs_of_one_triangle_reuse_its_quantities_exactly():
    """The pair loops compute what depends on the triangle alone (its area's derivatives, the
    clip shift's Jacobian) once for consecutive pairs of one triangle: grouped by triangle,
    as the broad phase delivers them, every pair's energy, gradient and Hessian are bit for bit
    those of the same pairs in an order where no two consecutive pairs share a triangle, and
    of each pair on its own; for the plain and the augmented-Lagrangian drivers."""
    rng = np.random.default_rng(11)
    nv = 60
    x = rng.normal(size=(nv, 3))
    depth = rng.uniform(size=nv)
    ntri, ntet = 6, 40
    tri = np.array([rng.choice(nv, 3, replace=False) for _ in range(ntri)])
    tet = np.array([rng.choice(nv, 4, replace=False) for _ in range(ntet)])
    pair_tri = np.repeat(np.arange(ntri), ntet)  # grouped: 40 pairs a triangle
    pair_tet = np.tile(np.arange(ntet), ntri)
    mixed = np.arange(pair_tri.size).reshape(ntri, ntet).T.ravel()  # triangles alternate
    assert np.all(np.diff(pair_tri[mixed]) != 0)
    pressure = rng.uniform(size=nv)
    for run in (
        lambda pt, pk: area_pairs(x, depth, tri, tet, pt, pk, EPS, True, True),
        lambda pt, pk: area_pairs_augmented(
            x, depth, tri, tet, pt, pk, EPS, pressure, 0.0, True, True
        ),
    ):
        grouped = run(pair_tri, pair_tet)
        alone = run(pair_tri[mixed], pair_tet[mixed])
        for a, b in zip(grouped, alone, strict=True):
            np.testing.assert_array_equal(a[mixed], b)
        assert np.count_nonzero(grouped[0]) > 3 * ntri  # several contributing pairs a triangle
    energy, grad, hess = area_pairs(x, depth, tri, tet, pair_tri, pair_tet, EPS, True, True)
    for p in np.flatnonzero(energy)[::5]:
        k = tet[pair_tet[p]]
        e1, g1, h1 = pair_energy(x[tri[pair_tri[p]]], x[k], depth[k], EPS)
        assert energy[p] == e1
        np.testing.assert_array_equal(grad[p], g1)
        np.testing.assert_array_equal(hess[p], h1)
