"""Continuous collision detection in self-contact: a strip one element thick folded onto itself in
large quasi-static load steps must not pass through itself.

A strip 1 x 0.1 x 0.05 (one element, 0.05, thick; neo-Hookean E = 1, nu = 0.3) lies on a table:
its bottom face is held for x <= 0.45 (the lower layer). Its end face is turned rigidly through
180° about a line parallel to y at x = 0.6, in two load steps of 90°, so that the end comes down
over the lower layer, a gap 0.05 above it. Then, in one load step (``solve_load_steps`` cuts the
steps it cannot converge), a weight (body force 3 per volume, down) pulls the upper layer onto
the lower one: free, it would sag far more than the gap (about 0.9 by the linear estimate for a
beam of length 0.4 held at both ends), so the only equilibrium on this side has the upper layer
resting on the lower one. Nothing moves across the strip (y): a weighted layer on a parallel one
of the same width otherwise slides off its side, which is no passing through. Without the
collision detection the Newton steps of that load step carry the upper layer straight through
the lower one (no pair is in contact at the step's start, so nothing resists) and the solve
converges with the layers crossed; with it (the default) they are capped where the upper layer
meets the lower one, and it comes to rest there.
"""

from __future__ import annotations

from mpi4py import MPI

import dolfinx
import numpy as np
import pytest
import ufl
from conftest import neo_hookean_residual

import fenics_matdepth as fm
from fenics_matdepth._compat import create_tetrahedral_mesh
from fenics_matdepth.meshing import box_tetrahedra

pytestmark = pytest.mark.filterwarnings("ignore::fenics_matdepth.DepthDeficiencyWarning")

LENGTH, WIDTH, THICKNESS = 1.0, 0.1, 0.05
CELLS = (20, 2, 1)
TABLE = 0.45  # the bottom face is held for x <= TABLE
FOLD_X = 0.6  # the fold's axis; the end lands at x = 2 FOLD_X - LENGTH = 0.2
GAP = 0.05  # between the layers once folded
WEIGHT = 3.0  # body force per volume, down, in the last load step
FOLD_STEPS = 2  # load steps of the fold (90° each); then one for the weight


def _end_motion(angle: float):
    """The end face's displacement turned by ``angle`` about the line x = FOLD_X,
    z = THICKNESS + GAP / 2."""
    c, sn = np.cos(angle), np.sin(angle)
    cx, cz = FOLD_X, THICKNESS + 0.5 * GAP

    def displacement(x):
        dx, dz = x[0] - cx, x[2] - cz
        return np.vstack(
            (cx + c * dx - sn * dz - x[0], np.zeros_like(x[0]), cz + sn * dx + c * dz - x[2])
        )

    return displacement


def _fold(ccd: bool):
    """Folds the strip and loads it; returns (the upper layer's lowest point over the table,
    ``_lowest_over_the_table``; the load steps)."""
    comm = MPI.COMM_WORLD
    X, cells = box_tetrahedra(CELLS, (0.0, 0.0, 0.0), (LENGTH, WIDTH, THICKNESS))
    mesh = create_tetrahedral_mesh(comm, cells, X)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    v = ufl.TestFunction(V)
    elastic, psi = neo_hookean_residual(u)
    weight = dolfinx.fem.Constant(mesh, np.zeros(3))
    residual = elastic - ufl.inner(weight, v) * ufl.dx
    table = dolfinx.mesh.locate_entities_boundary(
        mesh, 2, lambda x: np.isclose(x[2], 0.0) & (x[0] <= TABLE + 1e-9)
    )
    end = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[0], LENGTH))
    g = dolfinx.fem.Function(V)
    # no motion across the strip (it bends in the xz plane): a weighted layer on a parallel
    # one of the same width otherwise slides off its side, which is no passing through
    vertices = np.arange(
        mesh.topology.index_map(0).size_local + mesh.topology.index_map(0).num_ghosts
    )
    across = dolfinx.fem.locate_dofs_topological(V.sub(1), 0, vertices)
    bcs = [
        dolfinx.fem.dirichletbc(np.zeros(3), dolfinx.fem.locate_dofs_topological(V, 2, table), V),
        dolfinx.fem.dirichletbc(g, dolfinx.fem.locate_dofs_topological(V, 2, end)),
        dolfinx.fem.dirichletbc(dolfinx.default_scalar_type(0.0), across, V.sub(1)),
    ]
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=fm.propose_penalty(mesh, 1.0))
    problem = fm.ContactProblem(
        residual, u, contact, bcs=bcs, energy=(psi - ufl.inner(weight, u)) * ufl.dx,
        petsc_options_prefix="ccd_fold_", ccd=ccd,
    )  # fmt: skip

    def set_load(s):
        # s in [0, 1]: the fold over the first FOLD_STEPS of FOLD_STEPS + 1 steps, then the weight
        fold = min(s * (FOLD_STEPS + 1) / FOLD_STEPS, 1.0)
        g.interpolate(_end_motion(np.pi * fold))
        weight.value[2] = -WEIGHT * max(s * (FOLD_STEPS + 1) - FOLD_STEPS, 0.0)

    steps = fm.solve_load_steps(problem, set_load, num_steps=FOLD_STEPS + 1, progress=False)
    n = V.dofmap.index_map.size_local
    X = V.tabulate_dof_coordinates()[:n]
    x = X + u.x.array[: 3 * n].reshape(-1, 3)
    rows = np.vstack(comm.allgather(np.hstack((X, x))))
    problem.destroy()
    return _lowest_over_the_table(rows[:, :3], rows[:, 3:]), steps


def _lowest_over_the_table(X, x):
    """The upper layer's lowest point over the table, where the lower layer is held (its
    bottom face at z = 0, its top at about THICKNESS): the lowest current z of the vertices of
    reference x >= 0.8 that are now over x < TABLE - 0.05. On the lower layer's top face it is
    about THICKNESS; below 0 it has passed through."""
    upper = (X[:, 0] >= 0.8 - 1e-9) & (x[:, 0] < TABLE - 0.05)
    return float(x[upper, 2].min()) if upper.any() else np.inf


@pytest.mark.serial
def test_strip_folded_in_large_load_steps_passes_through_without_collision_detection():
    """The failure: with ``ccd=False`` the upper layer ends below the lower one, which is held
    on the table (z = 0 its bottom). A run repeats to the bit (serially, five runs on DOLFINx
    0.9 ended at z = -0.2700 after 5 load steps, three on DOLFINx 0.11 at -0.2880 after 11
    load steps, each run's Newton iterates the same to the last bit). Until the scale of the shifted
    Jacobian's step (``SNESCallbacks._shifted_direction``) was summed in a fixed order
    (``linear_solver.abs_sum``) it was PETSc's 1-norm, whose rounding depends on where the
    vector lies in memory: runs parted at the first shifted step and ended anywhere from
    z = -0.30 to -0.006, or load stepping gave up, so this test accepted that too. Serial only:
    where the uncapped Newton steps end depends on the iterates' rounding, which differs with
    the partition (on 2 ranks the same set-up ended on the lower layer, 0.040 above the table,
    measured once): this test only shows the set-up can fail."""
    lowest, steps = _fold(ccd=False)
    assert np.isclose(steps[-1].load, 1.0)
    assert lowest < 0.0, lowest
    if MPI.COMM_WORLD.rank == 0:
        print(f"ccd=False: the upper layer's lowest point over the table at z = {lowest:.4f}; "
              f"{len(steps)} load steps, cuts {sum(s.cuts for s in steps)}")  # fmt: skip


@pytest.mark.serial
def test_strip_folded_in_large_load_steps_does_not_pass_through_itself():
    """With the collision detection (the default) the upper layer rests on the lower one: its
    lowest point over the table stays above the lower layer's mid-plane, past which the thin
    layer's penalty would push it on through (measured: 0.0411 serially, the top face at 0.05;
    without the collision detection -0.077, through).

    Serial only: in load steps only the entry caps act (a vertex that has entered within the
    entry tolerance is in contact and moves freely), and on 2 ranks, whose paths part in the
    last bits from run to run, some paths went through: 4 of 300 runs of this set-up ended at
    z = -0.31 (1 of 150 with the GMRES rate test, 3 of 150 without it; each time the weight's
    load step cut once, then 21 and 50 iterations), and of 100 with the
    penalty scaled by 1 + k 1e-6 (k = -50 to 49) one ended at -0.22 and one at 0.0208, past the
    mid-plane (that path serially too: 0.0208, the other 99 serial paths 0.0318 to 0.0411).
    Forcing the exit cap on (``problem.collisions.exits = True``) did not close it on 2 ranks
    (0.0208 again on one path) and, in the knee, stalls Newton at 140 deg (docs/dynamics.md)."""
    lowest, steps = _fold(ccd=True)
    assert np.isclose(steps[-1].load, 1.0)
    assert lowest > 0.5 * THICKNESS, lowest
    if MPI.COMM_WORLD.rank == 0:
        print(f"ccd=True: the upper layer's lowest point over the table at z = {lowest:.4f}; "
              f"{len(steps)} load steps, cuts {sum(s.cuts for s in steps)}")  # fmt: skip
