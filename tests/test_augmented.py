"""Augmented Lagrangian (paper section 8.3): the pair kernel with nodal pressures, its exact
derivatives, the Uzawa moments, and the Uzawa driver on the contact patch test."""

from __future__ import annotations

import types

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import numpy as np
import pytest
import ufl
from conftest import assert_fd_derivatives
from test_kernels import polygon_mu, random_configs, split
from test_validation import PATCH_PRESSURE, _hyperelastic_energy, _report, _solve_patch

import fenics_matdepth as fm
from fenics_matdepth import AugmentedLagrangian
from fenics_matdepth._compat import create_tetrahedral_mesh
from fenics_matdepth.contact.kernels import (
    augmented_pair_energy,
    pair_energy,
    pressure_moments,
)
from fenics_matdepth.geometry.clip import (
    clip_shift,
)
from fenics_matdepth.meshing import box_tetrahedra
from fenics_matdepth.tolerances import looser_tolerances

EPS = 3.0
FD_RTOL = 1e-6


def _quadrature(x_tri, x_tet, depth, integrand):
    """``int_{T cap K} integrand(mu, g) dA`` by the edge-midpoint rule (exact for quadratics)
    on a fan of the intersection polygon; ``g`` from barycentric coordinates computed here, at
    the points of the triangle moved by the clipper's consistent shift (`clip_shift`)."""
    mu = polygon_mu(x_tri, x_tet)
    shifted = x_tri + clip_shift(x_tri)
    e = (x_tet[1:] - x_tet[0]).T

    def depth_at(y):
        lam123 = np.linalg.solve(e, y - x_tet[0])
        return depth @ np.concatenate(([1.0 - lam123.sum()], lam123))

    a2 = np.linalg.norm(np.cross(x_tri[1] - x_tri[0], x_tri[2] - x_tri[0]))
    total = 0.0
    for k in range(1, len(mu) - 1):
        tri = mu[[0, k, k + 1]]
        area = 0.5 * abs(
            (tri[1, 1] - tri[0, 1]) * (tri[2, 2] - tri[0, 2])
            - (tri[1, 2] - tri[0, 2]) * (tri[2, 1] - tri[0, 1])
        )
        for a, b in ((0, 1), (1, 2), (2, 0)):
            m = 0.5 * (tri[a] + tri[b])
            total += area / 3.0 * integrand(m, depth_at(m @ shifted)) * a2
    return total


def _pressures(seed):
    return np.random.default_rng(seed).uniform(0.5, 2.0, size=3)


def test_zero_pressure_is_the_penalty_kernel():
    """With all nodal pressures 0 the augmented kernel returns the plain kernel's numbers."""
    for x_tri, x_tet, depth in random_configs(11, 10):
        plain = pair_energy(x_tri, x_tet, depth, EPS)
        aug = augmented_pair_energy(x_tri, x_tet, depth, EPS, np.zeros(3))
        assert aug[0] == plain[0]
        assert np.array_equal(aug[1], plain[1]) and np.array_equal(aug[2], plain[2])


@pytest.mark.parametrize("seed", [4, 5])
def test_energy_against_quadrature(seed):
    """``int (p g + eps/2 g^2) dA`` with p linear on the triangle, against an independent
    quadrature over the intersection polygon."""
    for x_tri, x_tet, depth in random_configs(seed, 10):
        p = _pressures(seed)
        energy = augmented_pair_energy(x_tri, x_tet, depth, EPS, p)[0]
        reference = _quadrature(
            x_tri, x_tet, depth, lambda mu, g, p=p: (p @ mu) * g + 0.5 * EPS * g * g
        )
        assert energy == pytest.approx(reference, rel=1e-10)
        assert energy > pair_energy(x_tri, x_tet, depth, EPS)[0]  # p > 0 and g > 0


@pytest.mark.parametrize("seed", [2, 3])
def test_gradient_hessian_finite_differences(seed):
    for x_tri, x_tet, depth in random_configs(seed, 12):
        p = _pressures(seed)

        def f(x, p=p, depth=depth):
            return augmented_pair_energy(*split(x), depth, EPS, p)

        x0 = np.concatenate([x_tri.ravel(), x_tet.ravel()])
        assert_fd_derivatives(f, x0, FD_RTOL, symmetric=True)


def test_derivatives_split_tetrahedron():
    """A tetrahedron split around its centroid (thin layers): derivatives still exact."""
    x_tet = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    depth = np.zeros(4)
    x_tri = np.array([[-0.3, 0.2, 0.3], [0.8, -0.2, 0.1], [0.1, 0.9, 0.2]])
    p = np.array([1.0, 0.4, 2.0])

    def f(x):
        return augmented_pair_energy(*split(x), depth, EPS, p, centroid_depth=0.15)

    x0 = np.concatenate([x_tri.ravel(), x_tet.ravel()])
    energy, _, _ = assert_fd_derivatives(f, x0, FD_RTOL)
    assert energy > 0.0


def test_pressure_moments():
    """``int mu_i g dA`` is the derivative of the energy with respect to p_i (the energy is
    linear in p), and ``int mu_i dA`` sums to the polygon's area; both against quadrature."""
    for x_tri, x_tet, depth in random_configs(7, 10):
        gmom, amom = pressure_moments(x_tri, x_tet, depth)
        for i in range(3):
            ref_g = _quadrature(x_tri, x_tet, depth, lambda mu, g, i=i: mu[i] * g)
            ref_a = _quadrature(x_tri, x_tet, depth, lambda mu, g, i=i: mu[i])
            assert gmom[i] == pytest.approx(ref_g, rel=1e-10)
            assert amom[i] == pytest.approx(ref_a, rel=1e-10)
            dp = np.zeros(3)
            dp[i] = 0.5
            base = np.full(3, 1.0)
            slope = (
                augmented_pair_energy(x_tri, x_tet, depth, EPS, base + dp)[0]
                - augmented_pair_energy(x_tri, x_tet, depth, EPS, base - dp)[0]
            )
            assert slope == pytest.approx(gmom[i], rel=1e-8)
        area = 2.0 * pair_energy(x_tri, x_tet, np.ones(4), EPS)[0] / EPS
        assert amom.sum() == pytest.approx(area, rel=1e-12)


WIDTH = 0.05


@pytest.mark.parametrize("seed", [4, 5])
def test_quadratic_pressure_term(seed):
    """With a width w the pressure term is ``p_mean g^2 / (2 w)``: the plain kernel at the
    penalty ``eps + p_mean / w`` (against an independent quadrature), derivatives exact."""
    for x_tri, x_tet, depth in random_configs(seed, 8):
        p = _pressures(seed)
        stiffness = EPS + p.mean() / WIDTH
        energy, grad, hess = augmented_pair_energy(x_tri, x_tet, depth, EPS, p, width=WIDTH)
        reference = _quadrature(x_tri, x_tet, depth, lambda mu, g, k=stiffness: 0.5 * k * g * g)
        assert energy == pytest.approx(reference, rel=1e-10)
        plain = pair_energy(x_tri, x_tet, depth, stiffness)
        assert np.allclose(grad, plain[1], rtol=1e-12, atol=1e-12 * np.abs(grad).max())

        def f(x, p=p, depth=depth):
            return augmented_pair_energy(*split(x), depth, EPS, p, width=WIDTH)

        x0 = np.concatenate([x_tri.ravel(), x_tet.ravel()])
        assert_fd_derivatives(f, x0, FD_RTOL, exact=(grad, hess))


def _flat_on_face(s):
    """A triangle parallel to the boundary face z = 0 of the unit tetrahedron (depth z), at
    height s (outside for s < 0)."""
    x_tet = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    depth = np.array([0.0, 0.0, 0.0, 1.0])
    x_tri = np.array([[0.1, 0.1, s], [0.6, 0.1, s], [0.1, 0.6, s]])
    return x_tri, x_tet, depth


def test_quadratic_pressure_term_has_no_kink():
    """A face lying flat on the other body's boundary enters with its whole area at once: the
    linear pressure term's energy then grows like ``p A s`` with the overlap s (a kink at
    s = 0, where the energy is 0 outside), the quadratic one's like ``s^2`` (C1)."""
    p = np.array([1.0, 2.0, 1.5])
    area = 0.125
    s = 1e-6

    def slope(width):
        e1 = augmented_pair_energy(*_flat_on_face(s), EPS, p, width=width)[0]
        e2 = augmented_pair_energy(*_flat_on_face(2 * s), EPS, p, width=width)[0]
        outside = augmented_pair_energy(*_flat_on_face(-s), EPS, p, width=width)[0]
        assert outside == 0.0
        return (e2 - e1) / s

    assert slope(0.0) == pytest.approx(p.mean() * area, rel=1e-4)  # the kink
    assert abs(slope(WIDTH)) < 1e-3 * p.mean() * area


# ------------------------------------------------------------------------------------------
# Uzawa driver: the contact patch test (tests/test_validation.py) with a soft penalty
# ------------------------------------------------------------------------------------------


def test_patch_augmented_lagrangian():
    """A soft penalty (eps h / E ~ 1.4) leaves an overlap of p / (2 eps) and a pressure a few %
    off uniform; the augmented Lagrangian brings the overlap below the tolerance everywhere
    (``max_penetration``: over every intersection polygon, the footprint's edges included) and
    the pressure to uniform within 1 % over every column of the upper mesh."""
    penalty = 10.0
    plain = _solve_patch(penalty)
    tol = 0.1 * PATCH_PRESSURE / (2.0 * penalty)  # 10 % of the penalty's overlap
    out = _solve_patch(penalty, augmented={"tol": tol, "max_updates": 10})
    solver = out["solver"]
    p = PATCH_PRESSURE
    diag = solver.diagnostics()
    overlap_plain = plain["contact"].max_penetration()
    _report(
        f"\npatch, eps = {penalty}: penalty overlap {overlap_plain:.3e}, columns "
        f"[{plain['pressure'].min() / p:.4f}, {plain['pressure'].max() / p:.4f}] p, "
        f"{plain['iterations']} Newton it; augmented: {diag['updates']} updates, "
        f"{diag['newton_iterations']} Newton it, overlap {diag['overlap']:.3e} "
        f"({diag['overlap_tol']:.2f} tol, {diag['overlap_h']:.2e} h), columns "
        f"[{out['pressure'].min() / p:.5f}, {out['pressure'].max() / p:.5f}] p, "
        f"interior [{out['interior_pressure'].min() / p:.5f}, "
        f"{out['interior_pressure'].max() / p:.5f}]"
    )
    for r in solver.history:
        _report(f"  {r}")
    assert diag["overlap"] <= tol
    assert out["contact"].max_penetration() <= tol
    assert overlap_plain > 10 * tol  # the penalty alone is far off
    assert out["total_force"] == pytest.approx(p, rel=1e-6)
    assert np.all(np.abs(out["pressure"] / p - 1.0) < 0.01)
    # the multipliers carry the load: nodal pressures near p on each surface's share
    assert diag["updates"] >= 1


def test_patch_augmented_lagrangian_quadratic():
    """The quadratic pressure term on the same patch: the overlap below the tolerance (its
    fixed point is below half of it), the pressure uniform within 1 %, and the nodal pressures
    the contact pressure (on each surface its own share of the load)."""
    penalty = 10.0
    tol = 0.1 * PATCH_PRESSURE / (2.0 * penalty)
    out = _solve_patch(
        penalty, augmented={"tol": tol, "max_updates": 10, "pressure_term": "quadratic"}
    )
    solver = out["solver"]
    p = PATCH_PRESSURE
    diag = solver.diagnostics()
    _report(
        f"\npatch, quadratic pressure term: {diag['updates']} updates, "
        f"{diag['newton_iterations']} Newton it, overlap {diag['overlap_tol']:.3f} tol, "
        f"columns [{out['pressure'].min() / p:.5f}, {out['pressure'].max() / p:.5f}] p, "
        f"largest nodal pressure {diag['max_pressure'] / p:.3f} p"
    )
    assert solver.width == pytest.approx(0.5 * tol)
    assert out["contact"].max_penetration() <= tol
    assert diag["updates"] >= 1
    assert out["total_force"] == pytest.approx(p, rel=1e-6)
    assert np.all(np.abs(out["pressure"] / p - 1.0) < 0.01)
    # each surface carries part of p: the nodal pressures are of order p, not beyond it
    assert 0.2 * p < diag["max_pressure"] < 1.5 * p


def test_quadratic_pressures_fall_where_the_contact_relaxes():
    """Carried pressures far above the contact pressure: the linear term keeps them (its
    update only adds), the quadratic one brings them down to the contact pressure."""
    penalty = 10.0
    tol = 0.1 * PATCH_PRESSURE / (2.0 * penalty)
    out = _solve_patch(
        penalty, augmented={"tol": tol, "max_updates": 10, "pressure_term": "quadratic"}
    )
    solver = out["solver"]
    before = solver.pressure.copy()
    solver.pressure = 5.0 * before
    solver.solve()  # the overlap shrinks under the stiffer contact: no update needed
    assert solver.diagnostics()["updates"] == 0
    solver.update_pressure()
    _report(
        f"\ncarried pressures x5: largest {5 * before.max() / PATCH_PRESSURE:.3f} p, after one "
        f"update {solver.pressure.max() / PATCH_PRESSURE:.3f} p "
        f"(before {before.max() / PATCH_PRESSURE:.3f} p)"
    )
    assert solver.pressure.max() < 1.5 * before.max()


def test_rigid_mode_damping_floating_cube():
    """The patch test's upper cube held only by contact, started touching (no initial sink):
    the damped proximal solves plus the final undamped solve reach the plain solution."""
    penalty = 10.0
    plain = _solve_patch(penalty)
    # a free cube moves p / k in the first damped solve: half the penalty's overlap p / (2 eps)
    # (with a fixed k giving a motion of h / 10, 28 times that overlap, the cube sank so deep
    # that the second damped solve stopped in the line search; with this k fixed, the proximal
    # solves crept, each reducing the residual by 10 %)
    damped = _solve_patch(penalty, damping=PATCH_PRESSURE / (0.25 * PATCH_PRESSURE / penalty))
    _report(
        f"\nfloating cube: {damped['solver'].damped_solves} damped solves, "
        f"{damped['iterations']} Newton it (plain from a sunk start: {plain['iterations']}); "
        f"overlap {damped['overlap']:.6e} vs {plain['overlap']:.6e}"
    )
    assert damped["solver"].damped_solves >= 2
    assert damped["total_force"] == pytest.approx(PATCH_PRESSURE, rel=1e-6)
    assert np.allclose(damped["pressure"], plain["pressure"], rtol=1e-5, atol=0.0)
    assert damped["overlap"] == pytest.approx(plain["overlap"], rel=1e-4)


def test_max_iterations_bounds_a_solve_with_its_updates():
    """``max_iterations`` bounds the Newton iterations of one solve, its inner solves after the
    pressure updates included: from a state that needs updates, a budget of the first inner
    solve's iterations fails (within the budget, the pressures restored, the message naming
    ``max_iterations``), a budget above what the solve takes changes nothing, and a budget below
    1 is refused."""
    penalty = 10.0
    tol = 0.1 * PATCH_PRESSURE / (2.0 * penalty)
    # (without ContactProblem's damping of the upper cube, which only contact holds: its damped
    # solves are several SNES solves in one inner solve, each bounded by what is left)
    out = _solve_patch(penalty, augmented={"tol": tol, "max_updates": 10}, damp_free_bodies=False)
    solver = out["solver"]
    # from the solution with the pressures dropped, the overlap is the penalty's again, and
    # the solve needs updates and more than one inner solve
    state, zero = solver.u.x.array.copy(), np.zeros_like(solver.pressure)

    def solve_from_state(max_iterations, raise_on_failure=False):
        solver.u.x.array[:] = state
        solver.u.x.scatter_forward()
        solver.pressure = zero
        solver.max_iterations = max_iterations
        return solver.solve(raise_on_failure=raise_on_failure)

    free = solve_from_state(None)
    inner = [r.newton_iterations for r in solver.history]
    _report(f"\nfrom the solution without pressures: {free.iterations} Newton it, inner {inner}")
    assert free.converged and len(inner) >= 2 and sum(inner[1:]) >= 1

    budget = inner[0]
    short = solve_from_state(budget)
    assert not short.converged
    assert short.iterations <= budget
    assert np.all(solver.pressure == 0.0)  # restored to the start
    message = solver.failure_message(short)
    assert "max_iterations" in message and f"the {budget} Newton iterations" in message
    with pytest.raises(RuntimeError, match="max_iterations"):
        solve_from_state(budget, raise_on_failure=True)

    enough = solve_from_state(10 * free.iterations)
    assert enough.converged
    assert solver.contact.max_penetration() <= tol
    with pytest.raises(ValueError, match="max_iterations"):
        AugmentedLagrangian(solver.problem, tol=1.0, max_iterations=0)


def test_looser_tolerances_lowers_the_iteration_limit_and_restores_it():
    """The stage's iteration limit applies where it is below the problem's own, on a SNES and on
    a DOLFINx NewtonSolver alike; the problem's own tolerances come back afterwards."""
    snes = PETSc.SNES().create(MPI.COMM_SELF)
    snes.setTolerances(rtol=1e-10, atol=1e-12, stol=0.0, max_it=100)
    problem = types.SimpleNamespace(snes=snes)
    with looser_tolerances(problem, 1e-6, None, 30):
        assert snes.getTolerances() == (1e-6, 1e-12, 0.0, 30)
    with looser_tolerances(problem, None, None, 300):  # above its own: unchanged
        assert snes.getTolerances() == (1e-10, 1e-12, 0.0, 100)
    assert snes.getTolerances() == (1e-10, 1e-12, 0.0, 100)
    snes.destroy()
    newton = types.SimpleNamespace(rtol=1e-8, atol=1e-10, max_it=50)
    holder = types.SimpleNamespace(_solver=newton)
    with looser_tolerances(holder, None, 1e-6, 20):
        assert (newton.rtol, newton.atol, newton.max_it) == (1e-8, 1e-6, 20)
    assert (newton.rtol, newton.atol, newton.max_it) == (1e-8, 1e-10, 50)


def _locked_press(sink: float, **augmented) -> AugmentedLagrangian:
    """Two unit cubes (3 x 3 x 3 boxes of tetrahedra), the upper one prescribed ``sink`` into
    the lower one (``solver.sink``, a Constant), which is held but for the interior vertices
    of its top face: the deepest point sits at the held rim, where no pressure can move it
    (the overlap is ``sink``). Returns the augmented Lagrangian (tolerance 0.01, quadratic
    term) after one solve (``solver.result``)."""
    comm = MPI.COMM_WORLD
    x_lower, c_lower = box_tetrahedra(3, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    x_upper, c_upper = box_tetrahedra(3, (0.0, 0.0, 1.0), (1.0, 1.0, 1.0))
    mesh = create_tetrahedral_mesh(
        comm, np.vstack((c_lower, c_upper + x_lower.shape[0])), np.vstack((x_lower, x_upper))
    )
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    energy = _hyperelastic_energy(u, ufl.dx, [(ufl.dx, (1.0, 0.3))])
    cmap = mesh.topology.index_map(3)
    cells = np.arange(cmap.size_local + cmap.num_ghosts, dtype=np.int32)
    upper_cell = dolfinx.mesh.compute_midpoints(mesh, 3, cells)[:, 2] > 1.0
    blocks = np.asarray(V.dofmap.list)[cells]
    upper = np.unique(blocks[upper_cell].ravel())
    lower = np.setdiff1d(np.unique(blocks[~upper_cell].ravel()), upper)
    at = V.tabulate_dof_coordinates()[lower]
    inside = (at[:, :2] > 1e-9) & (at[:, :2] < 1.0 - 1e-9)
    top_interior = np.isclose(at[:, 2], 1.0) & inside.all(axis=1)
    value = dolfinx.fem.Constant(mesh, np.array([0.0, 0.0, -sink]))
    bcs = [
        dolfinx.fem.dirichletbc(value, upper.astype(np.int32), V),
        dolfinx.fem.dirichletbc(np.zeros(3), lower[~top_interior].astype(np.int32), V),
    ]
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=10.0)
    residual = ufl.derivative(energy, u, ufl.TestFunction(V))
    problem = fm.ContactProblem(residual, u, contact, bcs=bcs, energy=energy)
    solver = AugmentedLagrangian(problem, tol=0.01, pressure_term="quadratic", **augmented)
    solver.sink = value
    solver.result = solver.solve(raise_on_failure=False)
    return solver


def test_stalled_updates_hold_their_vertices():
    """An overlap no pressure can move (``_locked_press``): without ``stall_rtol`` the updates
    raise the pressures there about ``g / w`` = 3-fold each, up to ``max_updates``, and the
    solve fails. With it, the vertices the first update raised in vain are held, their
    pressures back to their values before it: the solve ends there, accepted within
    ``stall_accept`` tolerances. The next solve tries once more and holds them again, so the
    pressures do not grow from solve to solve; once the overlap is within the tolerance nothing
    is held. Above ``stall_accept`` the solve fails (the pressures restored). Where the
    pressures do move the overlap (the patch test) nothing is held."""
    plain = _locked_press(0.015, max_updates=6)
    overlaps = [r.overlap_tol for r in plain.history]
    pressures = [r.max_pressure for r in plain.history]
    _report(f"\nlocked overlap, no stall test: overlaps {overlaps} tol, pressures {pressures}")
    assert not plain.result.converged and not plain.stalled and not plain.held.any()
    assert len(plain.history) == 7 and np.allclose(overlaps, 1.5, rtol=1e-6)
    assert pressures[-1] > 2.5**4 * pressures[2] > 0.0  # geometric growth, g / w = 3

    held = _locked_press(0.015, max_updates=6, stall_rtol=0.1)
    diag = held.diagnostics()
    _report(f"with stall_rtol 0.1: {[r.overlap_tol for r in held.history]} tol, {diag}")
    assert held.result.converged and held.stalled and held.total_stalls == 1
    assert len(held.history) == 2 and held.history[1].max_pressure > 0.0  # one update, in vain
    assert diag["stalled"] and diag["held_vertices"] == np.count_nonzero(held.held) > 0
    assert np.all(held.pressure[held.held] == 0.0)  # undone: the pressures before it
    assert held.contact.max_penetration() == pytest.approx(0.015, rel=1e-6)
    first = held.pressure.copy()
    for _ in range(2):  # the next load steps, the overlap still held there
        assert held.solve().converged and held.stalled and len(held.history) == 2
        assert np.array_equal(held.pressure, first)
    assert held.total_stalls == 3
    held.sink.value[:] = (0.0, 0.0, -0.005)  # half the tolerance
    held.solve()
    assert not held.stalled and not held.held.any()
    assert held.contact.max_penetration() <= 0.01

    # where the pressures do move the overlap (the patch test, linear term: it halves at each
    # update) nothing is held
    tol = 0.1 * PATCH_PRESSURE / (2.0 * 10.0)
    moving = _solve_patch(10.0, augmented={"tol": tol, "max_updates": 10, "stall_rtol": 0.1})
    assert not moving["solver"].held.any() and moving["solver"].diagnostics()["updates"] >= 3
    assert moving["contact"].max_penetration() <= tol

    beyond = _locked_press(0.03, max_updates=6, stall_rtol=0.1)  # 3 tolerances: not accepted
    assert not beyond.result.converged and beyond.stalled and len(beyond.history) == 2
    assert np.all(beyond.pressure == 0.0)  # restored
    assert "stalled" in beyond.failure_message(beyond.result)
    with pytest.raises(ValueError, match="stall_rtol"):
        AugmentedLagrangian(beyond.problem, tol=0.01, stall_rtol=1.0)
    with pytest.raises(ValueError, match="stall_accept"):
        AugmentedLagrangian(beyond.problem, tol=0.01, stall_accept=0.5)
