"""Pseudo-transient continuation (fm.PseudoTransient): the Jacobian shift of ContactProblem's
Newton steps, which must leave the converged equilibrium that of plain Newton."""

from __future__ import annotations

from mpi4py import MPI

import dolfinx
import numpy as np
import pytest
import ufl
from conftest import clamped_and_moved, merged_mesh, neo_hookean, neo_hookean_residual

import fenics_matdepth as fm
from fenics_matdepth._compat import create_tetrahedral_mesh
from fenics_matdepth.meshing import box_tetrahedra
from fenics_matdepth.pseudo_transient import PseudoTransient

E, NU = 1.0, 0.3
WELL, HALF_WIDTH, PIN = 1000.0, 0.1, 10.0
#: the load at which the left well of c (u_x^2 - a^2)^2 - f u_x ends (a limit point)
LIMIT_LOAD = 8.0 * WELL * HALF_WIDTH**3 / (3.0 * np.sqrt(3.0))


def _tilted_well(load: float, sigma0: float | None):
    """A soft block (no contact) in the tilted double well c (u_x^2 - a^2)^2 - f u_x + k (u_y^2
    + u_z^2), started in the left well u_x = -a, which the load f (past the limit load) has
    removed: the solution snaps to the right well, the root of 4 c x (x^2 - a^2) = f with x > a.
    Every iterate stays a uniform translation (the elastic energy's null mode), so the solve is
    the one-degree-of-freedom problem's. Returns the solve's result and ``u``."""
    comm = MPI.COMM_WORLD
    x, c = box_tetrahedra(2, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    mesh = create_tetrahedral_mesh(comm, c, x)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    psi, _ = neo_hookean(u, E, NU)
    a = HALF_WIDTH
    psi += WELL * (u[0] ** 2 - a**2) ** 2 - load * u[0] + PIN * (u[1] ** 2 + u[2] ** 2)
    energy = psi * ufl.dx
    residual = ufl.derivative(energy, u, ufl.TestFunction(V))
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=1.0)
    problem = fm.ContactProblem(
        residual, u, contact, energy=energy, petsc_options={"snes_max_it": 200}
    )
    if sigma0 is not None:
        problem.pseudo_transient = fm.PseudoTransient(sigma0=sigma0)
    u.x.array[0::3] = -a
    result = problem.solve(raise_on_failure=False)
    if sigma0 is not None:
        problem.pseudo_transient.destroy()
    problem.destroy()
    return result, u


def _right_root(load: float) -> float:
    roots = np.roots([4.0 * WELL, 0.0, -4.0 * WELL * HALF_WIDTH**2, -load])
    return float(max(r.real for r in roots if abs(r.imag) < 1e-12))


@pytest.mark.parametrize(("over_limit", "sigma0"), [(1.1, 1.0), (3.0, 0.3)])
def test_the_snap_converges_to_plain_newtons_equilibrium_in_fewer_iterations(over_limit, sigma0):
    """Past the limit load the left well is gone; plain Newton crawls through the flat region
    its ghost leaves (long steps the energy line search cuts), the shifted steps less. Both
    end at the right well's root (to 1e-10), the shifted solve in fewer iterations (measured,
    DOLFINx 0.9: 21 and 11 at 1.1 times the limit load with sigma0 = 1; 13 and 6 at 3 times
    with 0.3; sigma0 = 3 took 24 and 13: too large a shift is a slow gradient flow)."""
    load = over_limit * LIMIT_LOAD
    plain, u_plain = _tilted_well(load, None)
    shifted, u_shifted = _tilted_well(load, sigma0)
    root = _right_root(load)
    assert plain.converged and shifted.converged
    assert np.allclose(u_plain.x.array[0::3], root, rtol=1e-10)
    assert np.allclose(u_shifted.x.array[0::3], root, rtol=1e-10)
    assert np.allclose(u_shifted.x.array[1::3], 0.0, atol=1e-10)
    print(f"iterations: plain Newton {plain.iterations}, shifted "
          f"{shifted.iterations}")  # fmt: skip
    assert shifted.iterations < plain.iterations


def test_sigma_follows_the_residual_and_switches_off():
    """SER: sigma0 at the reference residual (the first iterate with the Dirichlet dofs on
    their values), proportional to the residual, capped at max_ratio times sigma0, 0 below
    off_rtol of the reference and before the Dirichlet dofs hold their values."""
    control = fm.PseudoTransient(sigma0=0.5, off_rtol=1e-3, max_ratio=4.0)
    control.start_solve()
    assert control.sigma(100.0, bcs_met=False) == 0.0
    assert control.sigma(10.0, bcs_met=True) == 0.5  # the reference
    assert control.sigma(1.0, bcs_met=True) == pytest.approx(0.05)
    assert control.sigma(1000.0, bcs_met=True) == pytest.approx(2.0)
    assert control.sigma(0.5e-2, bcs_met=True) == 0.0
    control.start_solve()
    assert control.sigma(1.0, bcs_met=True) == 0.5  # a new reference
    with pytest.raises(ValueError, match="sigma0"):
        fm.PseudoTransient(sigma0=-1.0)
    with pytest.raises(ValueError, match="off_rtol"):
        fm.PseudoTransient(off_rtol=1.0)


def _pressed_blocks(sigmas: tuple[float | None, ...]):
    """A block pressed onto another by its top face moved 0.03 down (the other's bottom
    clamped), solved from rest with contact once for each shift in ``sigmas`` (None: plain
    Newton), on one mesh (so that the solutions compare dof by dof on any number of ranks);
    returns each solve's result, displacement array and pseudo-transient control."""
    comm = MPI.COMM_WORLD
    mesh = merged_mesh(
        comm,
        box_tetrahedra(4, (0.0, 0.0, 0.0), (1.0, 1.0, 0.5)),
        box_tetrahedra(3, (0.25, 0.2, 0.5), (0.5, 0.55, 0.4)),
    )
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    residual, psi = neo_hookean_residual(u, E, NU)
    bcs, g = clamped_and_moved(V, lambda x: np.isclose(x[2], 0.0), lambda x: np.isclose(x[2], 0.9))
    g.x.array.reshape(-1, 3)[:, 2] = -0.03
    depth = fm.material_depth(mesh)
    solves = []
    for sigma0 in sigmas:
        u.x.array[:] = 0.0
        contact = fm.ContactOperator(u, depth, penalty=200.0)
        problem = fm.ContactProblem(residual, u, contact, bcs=bcs, energy=psi * ufl.dx)
        control = None
        if sigma0 is not None:
            control = problem.pseudo_transient = PseudoTransient(sigma0=sigma0)
        result = problem.solve()
        if control is not None:
            control.destroy()
        problem.destroy()
        solves.append((result, u.x.array.copy(), control))
    top = np.isclose(V.tabulate_dof_coordinates()[:, 2], 0.9)
    return solves, top


def test_with_contact_and_dirichlet_conditions_the_equilibrium_is_plain_newtons():
    """Two blocks pressed into contact by a prescribed displacement: with the shift the solve
    reaches plain Newton's equilibrium (to 1e-8 relative; both converge to rtol 1e-10) and the
    prescribed values exactly (the Dirichlet rows are not shifted); the shift was on in the
    solve's first iterations and off at its end."""
    ((plain, u_plain, _), (shifted, u_shifted, control)), top = _pressed_blocks((None, 0.3))
    assert plain.converged and shifted.converged
    difference = MPI.COMM_WORLD.allreduce(np.sum((u_shifted - u_plain) ** 2))
    assert np.sqrt(difference) <= 1e-8 * np.sqrt(MPI.COMM_WORLD.allreduce(np.sum(u_plain**2)))
    assert np.allclose(u_shifted.reshape(-1, 3)[top, 2], -0.03, rtol=1e-12)
    assert control.shifted >= 1
    assert control.last_sigma == 0.0
    print(f"iterations: plain {plain.iterations}, shifted {shifted.iterations}, "
          f"{control.shifted} shifted")  # fmt: skip
