"""Self-contact: a strip whose end is turned through a full turn curls up and folds onto itself.

A strip (length 4, width 0.8, thickness 0.2, neo-Hookean E = 1, nu = 0.3) is clamped at
x = 0. Its other end face is turned rigidly about its own centre line (parallel to y) through
2 pi while the centre moves 1.5 towards the clamp (slack for the loop). The strip rolls into a
loop whose end comes down onto the strip itself: contact within one body, the case that
needs the material depth (each side is the other's "inside").

Checks: every load step converges (with automatic step cutting); contact is active at the end
and the mesh is one body; the deepest point of the contact surface lies less than 15 % of the
element size h = 0.1 (along the strip and through its thickness) inside the strip (penalty
from ``propose_penalty`` with factor 30: eps = 30 E_p / h_b, E_p the p-wave modulus, h_b the
median boundary edge, 0.14); no tetrahedron is inverted (det F > 0 in every
cell).
"""

from __future__ import annotations

from mpi4py import MPI

import dolfinx
import numpy as np
import ufl
from conftest import clamped_and_moved, min_det_F, neo_hookean_residual

import fenics_matdepth as fm
from fenics_matdepth._compat import create_tetrahedral_mesh
from fenics_matdepth.meshing import box_tetrahedra

LENGTH, WIDTH, THICKNESS = 4.0, 0.8, 0.2
CELLS = (40, 4, 2)  # 0.1 along the strip and through the thickness, 0.2 across
SLACK = 1.5
#: Largest penetration allowed, as a fraction of the element size.
PENETRATION_FRACTION = 0.15


def _end_motion(t: float):
    """Displacement of the end face at load t: turned by 2 pi t about its centre line, which
    moves t * SLACK towards the clamp."""
    angle = 2.0 * np.pi * t
    c, s = np.cos(angle), np.sin(angle)

    def displacement(x):
        dx, dz = x[0] - LENGTH, x[2] - THICKNESS / 2
        return np.vstack(
            (
                LENGTH - t * SLACK + c * dx - s * dz - x[0],
                np.zeros_like(x[0]),
                THICKNESS / 2 + s * dx + c * dz - x[2],
            )
        )

    return displacement


def test_strip_folds_onto_itself():
    comm = MPI.COMM_WORLD
    X, cells = box_tetrahedra(CELLS, (0.0, 0.0, 0.0), (LENGTH, WIDTH, THICKNESS))
    mesh = create_tetrahedral_mesh(comm, cells, X)
    h = LENGTH / CELLS[0]
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    residual, psi = neo_hookean_residual(u)

    bcs, g = clamped_and_moved(
        V, lambda x: np.isclose(x[0], 0.0), lambda x: np.isclose(x[0], LENGTH)
    )
    mu, kappa = fm.materials.shear_bulk_from_youngs_poisson(1.0, 0.3)
    moduli = fm.materials.small_strain_moduli(fm.materials.neo_hookean, mu=mu, kappa=kappa)
    penalty = fm.propose_penalty(mesh, moduli.stiffest, factor=30.0)
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=penalty)
    assert contact.num_bodies == 1
    problem = fm.ContactProblem(residual, u, contact, bcs=bcs, energy=psi * ufl.dx)

    steps = fm.solve_load_steps(problem, lambda t: g.interpolate(_end_motion(t)), num_steps=20)
    assert np.isclose(steps[-1].load, 1.0)
    final = steps[-1].diagnostics
    assert final["active_pairs"] > 0, "the strip did not reach itself"
    assert final["max_penetration"] < PENETRATION_FRACTION * h, final["max_penetration"] / h
    # one body: its contact forces cancel
    forces = np.abs(contact.gradient_array()[1])  # may be empty on a rank
    scale = comm.allreduce(forces.max() if forces.size else 0.0, op=MPI.MAX)
    assert np.abs(final["force_resultant"]).max() <= 1e-8 * scale

    assert min_det_F(u) > 0.0
