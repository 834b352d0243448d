"""Continuous collision detection on thin layers: a plate falling edge-first onto a plate.

A plate one element (0.05) thick, tilted 45° about x so that an edge leads, falls at 30 per
second (0.3 a step of 0.01) onto a clamped plate one element thick, 0.05 below; no gravity,
``solve_time_steps`` defaults. Without collision detection the leading edge ends below the
lower plate after two steps; with it (the default, with either solver) the step that reaches
the plate is truncated at the impact. NonlinearContactProblem's Newton update is capped by the
collision detection as ContactProblem's line search is.
"""

from __future__ import annotations

import types
import warnings

from mpi4py import MPI

import dolfinx
import numpy as np
import pytest
import ufl
from conftest import merged_mesh, neo_hookean_residual

import fenics_matdepth as fm
from fenics_matdepth.meshing import box_tetrahedra

pytestmark = pytest.mark.filterwarnings("ignore::fenics_matdepth.DepthDeficiencyWarning")

E, NU, RHO = 1000.0, 0.3, 1.0
THICKNESS = 0.05  # both plates: one element
GAP = 0.05
DT = 0.01
SPEED = 30.0


def _tilted_plate():
    """The falling plate (0.2 x 0.05 x 0.2, 2 x 1 x 2 boxes) turned 45° about x, its
    leading edge GAP above the lower plate's top face (z = 0)."""
    X, cells = box_tetrahedra((2, 1, 2), (-0.1, -0.5 * THICKNESS, 0.0), (0.2, THICKNESS, 0.2))
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)
    y, z = X[:, 1].copy(), X[:, 2].copy()
    X[:, 1], X[:, 2] = c * y - s * z, s * y + c * z
    X[:, 2] += GAP - X[:, 2].min()
    return X, cells


def _scene(comm, ccd: bool, solver: str = "snes", penalty_factor: float = 1.0):
    """The two plates, the falling one at SPEED; returns (problem, integrator, strain energy,
    owned reference z of the vertices, mask of the falling plate's, of the top face's)."""
    plate = box_tetrahedra((6, 6, 1), (-0.15, -0.15, -THICKNESS), (0.3, 0.3, THICKNESS))
    mesh = merged_mesh(comm, plate, _tilted_plate())
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    v = ufl.TestFunction(V)
    elastic, psi = neo_hookean_residual(u, E, NU)
    rim = dolfinx.mesh.locate_entities_boundary(
        mesh, 2, lambda x: np.isclose(np.abs(x[0]), 0.15) | np.isclose(np.abs(x[1]), 0.15)
    )
    bcs = [dolfinx.fem.dirichletbc(np.zeros(3), dolfinx.fem.locate_dofs_topological(V, 2, rim), V)]
    penalty = penalty_factor * fm.propose_penalty(mesh, E)
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty)
    integrator = fm.Newmark(u, DT, rho=RHO)
    residual = integrator.inertia(v) + elastic
    v0 = dolfinx.fem.Function(V)
    v0.interpolate(lambda x: np.vstack((0 * x[0], 0 * x[0], np.where(x[2] > 0.01, -SPEED, 0.0))))
    integrator.initial(None, v0, residual=residual, contact=contact, bcs=bcs)
    if solver == "snes":
        problem = fm.ContactProblem(
            residual, u, contact, bcs=bcs, petsc_options_prefix="ccd_thin_", ccd=ccd
        )
    else:
        problem = fm.NonlinearContactProblem(residual, u, contact, bcs, ccd=ccd)
        # the truncated step's first try (dt 2.1e-3) does not converge and is halved: given up
        # after 15 iterations, not 50 (CI time)
        problem.newton_solver(max_it=15)
    X_z = V.tabulate_dof_coordinates()[: V.dofmap.index_map.size_local, 2]
    return problem, integrator, psi * ufl.dx, X_z, X_z > 0.01, np.isclose(X_z, 0.0)


def _fall(
    ccd: bool,
    steps: int,
    solver: str = "snes",
    penalty_factor: float = 1.0,
    heights=None,
    contact_force=None,
):
    """Steps of the fall; returns the falling plate's lowest point, relative to the lower
    plate's top face under it, after each step, the records, and the entry tolerance."""
    comm = MPI.COMM_WORLD
    problem, integrator, strain, X_z, falling, top = _scene(comm, ccd, solver, penalty_factor)
    u, n = problem.u, X_z.size

    def lowest(mask):
        z = X_z + u.x.array[: 3 * n].reshape(-1, 3)[:, 2]
        return comm.allreduce(float(z[mask].min()) if mask.any() else np.inf, op=MPI.MIN)

    heights = [] if heights is None else heights
    records = []

    def track(record):
        heights.append(lowest(falling) - lowest(top))
        records.append(record)
        if record.step >= steps:
            raise fm.StopRequested("enough steps")

    try:
        fm.solve_time_steps(
            problem,
            integrator,
            1.0,
            DT,
            on_step=track,
            strain_energy=strain,
            progress=False,
            contact_force=contact_force,
        )
    except fm.StopRequested:
        pass
    entry = problem.collisions.entry.min() if problem.collisions is not None else 0.0
    problem.destroy()
    return np.asarray(heights), records, entry


def test_newton_update_is_capped_by_the_collision_detection():
    """NonlinearContactProblem's update: a Newton step moving the falling plate 0.3 down (the
    lower plate's full thickness past it) is shortened to the entry cap, which lets the
    leading edge go just past the top face: (gap + entry) / 0.3 up to the advancement's
    tolerance; with ``ccd=False`` the whole step is taken."""
    comm = MPI.COMM_WORLD
    for ccd in (True, False):
        problem, _, _, X_z, falling, _ = _scene(comm, ccd, "newton")
        x = problem.u.x.petsc_vec
        x.set(0.0)
        dx = x.duplicate()
        step = np.zeros((X_z.size, 3))
        step[falling, 2] = 0.3  # the update is x - dx
        dx.getArray()[: step.size] = step.ravel()
        problem._update(types.SimpleNamespace(relaxation_parameter=1.0), dx, x)
        moved = -x.getArray(readonly=True)[: step.size].reshape(-1, 3)[falling, 2]
        if ccd:
            entry = problem.collisions.entry.min()
            assert problem.ccd_caps == 1
            fraction = moved / 0.3
            assert np.allclose(fraction, fraction[0] if fraction.size else 0.0, rtol=1e-12)
            if fraction.size:
                low, high = (GAP + 0.5 * entry) / 0.3, (GAP + entry) / 0.3 + 1e-12
                assert low <= fraction[0] <= high, (fraction[0], low, high)
        else:
            assert np.allclose(moved, 0.3, rtol=1e-12)
        dx.destroy()
        problem.destroy()


@pytest.mark.parametrize("solver", ["snes", "newton"])
def test_newton_step_is_bounded_in_travel_before_the_sweep(solver):
    """A Newton step moving the falling plate 100 up (away from everything; 500 plate
    thicknesses) is shortened to ``collisions.max_travel`` (NEWTON_TRAVEL_EDGES median boundary
    edges) before the collision detection sweeps it: ContactProblem's line-search pre-check
    scales the step, NonlinearContactProblem's update moves the plate that far; ``travel``
    is the largest vertex displacement. A step within the bound is left whole."""
    comm = MPI.COMM_WORLD
    problem, _, _, X_z, falling, _ = _scene(comm, True, solver)
    collisions = problem.collisions
    edge = np.linalg.norm(
        collisions.X[collisions.tri[:, [1, 2, 0]]] - collisions.X[collisions.tri], axis=2
    ).mean(axis=1)
    assert collisions.max_travel == pytest.approx(
        fm.contact.ccd.NEWTON_TRAVEL_EDGES * np.median(edge), rel=1e-12
    )
    for distance in (100.0, 0.5 * collisions.max_travel):
        x = problem.u.x.petsc_vec
        x.set(0.0)
        dx = x.duplicate()
        step = np.zeros((X_z.size, 3))
        step[falling, 2] = -distance  # the update is x - dx: up
        dx.getArray()[: step.size] = step.ravel()
        moving = comm.allreduce(int(falling.sum()))
        if moving:
            end = -dx.getArray(readonly=True)
            assert collisions.travel(x.getArray(readonly=True), end) == pytest.approx(distance)
        if solver == "snes":
            problem._precheck(x, dx)
            moved = -dx.getArray(readonly=True)[: step.size].reshape(-1, 3)[falling, 2]
        else:
            problem._update(types.SimpleNamespace(relaxation_parameter=1.0), dx, x)
            moved = x.getArray(readonly=True)[: step.size].reshape(-1, 3)[falling, 2]
        expected = min(distance, collisions.max_travel)
        assert np.allclose(moved, expected, rtol=1e-12), (moved[:3], expected)
        assert problem.ccd_caps == (1 if distance > collisions.max_travel else 0)
        problem.ccd_caps = 0
        dx.destroy()
    problem.destroy()


def test_thin_plate_passes_through_without_collision_detection():
    """The failure: with ``ccd=False`` the leading edge is below the lower plate's bottom
    face after two steps (with the end-of-step contact force, as measured when the collision
    detection was built)."""
    heights, _, _ = _fall(ccd=False, steps=2, contact_force="endpoint")
    assert heights[-1] < -THICKNESS, heights


@pytest.mark.parametrize("solver", ["snes", "newton"])
def test_thin_plate_falling_edge_first_is_stopped_at_the_impact(solver):
    """With the collision detection (default; ContactProblem's line search or
    NonlinearContactProblem's update, and the time step's truncation): the first step is
    truncated once, at the predicted impact, not again and again after converging; the edge
    ends it no deeper than the entry tolerance below the lower plate's top face, and the
    total energy has not grown beyond the initial kinetic energy (by more than 1 %). (Stopping
    the plate after that is the penalty's work: see the next tests.)"""
    heights, records, entry = _fall(ccd=True, steps=1, solver=solver)
    first = records[0]
    assert first.truncations == 1 and first.dt < DT, (first.truncations, first.dt)
    assert -entry * (1 + 1e-6) <= heights[0] < GAP, (heights[0], entry)
    kinetic = 0.5 * RHO * 0.2 * 0.2 * THICKNESS * SPEED**2
    assert first.total_energy <= 1.01 * kinetic, (first.total_energy, kinetic)
    if MPI.COMM_WORLD.rank == 0:
        print(f"{solver}: first step dt {first.dt:.3g}, {first.truncations} truncation(s), "
              f"height {heights[0]:.4f} (entry {entry:.4f}), energy {first.total_energy:.4g} "
              f"of {kinetic:.4g}")  # fmt: skip


def test_thin_plate_too_fast_for_the_penalty_stops_with_the_penalty_needed():
    """With the proposed penalty the lower plate cannot take the falling plate's momentum
    (without the exit cap the edge went out through its bottom face in the third step). Now a
    vertex inside a plate cannot leave it through its far side: the steps shrink while it is
    held there, and at the smallest step the time stepping stops with an error that names a
    penalty that would hold the plate (between 2 and 50 times the proposed one; a run with 10
    times holds it, below), never with the edge through the lower plate. (NonlinearContactProblem
    the same, measured, not tested: CI time.)"""
    heights = []
    with pytest.raises(RuntimeError, match="pass through a body") as failure:
        _fall(ccd=True, steps=50, heights=heights)
    assert len(heights) >= 2 and min(heights) > -THICKNESS, heights
    message = str(failure.value)
    needed = float(message.split("a penalty of about ")[1].split(" ")[0])
    proposed = float(message.split("(now ")[1].split(";")[0])
    assert 2.0 * proposed < needed < 50.0 * proposed, (needed, proposed)
    if MPI.COMM_WORLD.rank == 0:
        print(f"heights {np.round(heights, 4)}: {message}")


def test_thin_plate_is_held_by_a_penalty_ten_times_higher():
    """Ten times the proposed penalty (near the one the error above names): over the first four
    steps the edge goes no deeper than half the lower plate's thickness, turns back above its
    top face, and the total energy does not grow beyond the initial kinetic energy (by more
    than 1 %)."""
    heights, records, _ = _fall(ccd=True, steps=4, penalty_factor=10.0)
    assert heights.min() > -0.5 * THICKNESS, heights
    assert heights[2:].max() > 0.0, heights
    kinetic = 0.5 * RHO * 0.2 * 0.2 * THICKNESS * SPEED**2
    energies = np.array([r.total_energy for r in records])
    assert energies.max() <= 1.01 * kinetic, (energies, kinetic)
    if MPI.COMM_WORLD.rank == 0:
        print(f"penalty x 10: heights {np.round(heights, 4)}, energies {np.round(energies, 4)}")


def test_thin_plate_too_fast_for_the_penalty_is_held_with_max_penalty():
    """The run above with ``max_penalty`` (100 times the proposed penalty): where it stopped,
    the penalty is raised instead (to twice the one named, with a RuntimeWarning on rank 0)
    and the stepping goes back to the last state without contact, the start; from there the
    edge goes no deeper than half the lower plate's thickness, turns back above its top face
    within 4 steps, and the total energy never rises above the initial kinetic energy (by
    more than 1 %): the raise, made where nothing overlaps, created none."""
    comm = MPI.COMM_WORLD
    problem, integrator, strain, X_z, falling, top = _scene(comm, ccd=True)
    u, n = problem.u, X_z.size
    proposed = problem.contact.penalty

    def lowest(mask):
        z = X_z + u.x.array[: 3 * n].reshape(-1, 3)[:, 2]
        return comm.allreduce(float(z[mask].min()) if mask.any() else np.inf, op=MPI.MIN)

    steps = {}  # step number -> (t, height, total energy, penalty) of the kept records

    def track(record):
        height = lowest(falling) - lowest(top)
        for later in [k for k in steps if k >= record.step]:  # steps the rewind dropped
            del steps[later]
        steps[record.step] = (record.t, height, record.total_energy, problem.contact.penalty)
        if problem.contact.penalty > proposed and record.step >= 4:
            raise fm.StopRequested("enough steps")

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RuntimeWarning)
        try:
            fm.solve_time_steps(
                problem, integrator, 1.0, DT, on_step=track, strain_energy=strain,
                progress=False, max_penalty=100.0 * proposed,
            )  # fmt: skip
        except fm.StopRequested:
            pass
    raised = problem.contact.penalty
    problem.destroy()
    t, heights, energies, penalties = (np.array(c) for c in zip(*steps.values(), strict=True))
    assert 2.0 * proposed < raised <= 100.0 * proposed, (raised, proposed)
    assert np.all(penalties == raised), penalties  # every kept step is one of the new run's
    assert np.all(np.diff(t) > 0.0), t
    assert heights.min() > -0.5 * THICKNESS, heights
    assert heights[1:].max() > 0.0, heights  # above the top face again (it rocks after)
    kinetic = 0.5 * RHO * 0.2 * 0.2 * THICKNESS * SPEED**2
    assert energies.max() <= 1.01 * kinetic, (energies, kinetic)
    if comm.rank == 0:
        messages = [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
        assert any("penalty is raised" in m for m in messages), messages
        print(f"penalty {proposed:.3g} -> {raised:.3g}; heights {np.round(heights, 4)}, "
              f"energies {np.round(energies, 4)} of {kinetic:.4g}")  # fmt: skip


def test_max_penalty_needs_the_collision_detection():
    """``max_penalty`` acts where the collision detection finds a pass-through: without it
    (``ccd=False``) the option is refused with a message naming what it needs."""
    problem, integrator, strain, *_ = _scene(MPI.COMM_WORLD, ccd=False)
    with pytest.raises(ValueError, match="max_penalty needs the problem's collision detection"):
        fm.solve_time_steps(
            problem, integrator, DT, DT, strain_energy=strain, progress=False, max_penalty=1e6
        )
    problem.destroy()
