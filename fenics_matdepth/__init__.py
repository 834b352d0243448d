"""fenics_matdepth: material-depth penalty contact for FEniCSx (DOLFINx).

Frictionless penalty contact and self-contact between nonlinearly elastic bodies, with the
contact model of Hirota, Fisher & State (2003): every vertex carries its material depth
(distance to the boundary in the reference configuration), interpolated linearly in each
tetrahedron, and the penalty energy (eps/2) g^2 is integrated exactly over the polygons
where boundary triangles cut tetrahedra.
"""

from __future__ import annotations

__version__ = "0.1.0"

# _cache first: numba's cache stamps of the kernels then cover all the package's sources
from fenics_matdepth import (
    _cache,  # noqa: F401
    checkpoint,
    contact,
    geometry,
    kinematics,
    materials,
    meshing,
)
from fenics_matdepth._compat import solve_nonlinear
from fenics_matdepth.augmented import (
    AugmentedLagrangian,
    RigidModeDamping,
    UzawaUpdate,
    damping_energy,
)
from fenics_matdepth.checkpoint import Checkpoint
from fenics_matdepth.contact.operator import ContactOperator, propose_penalty
from fenics_matdepth.continuation import ContinuationStage, PenaltyContinuation
from fenics_matdepth.depth import depth_deficiency, material_depth
from fenics_matdepth.dynamics import BackwardEuler, Newmark, TimeStep, solve_time_steps
from fenics_matdepth.kinematics import RigidRotation, rotation_displacement, rotation_matrix
from fenics_matdepth.solvers import (
    ContactAssembler,
    ContactProblem,
    LoadStep,
    NonlinearContactProblem,
    SolveResult,
    StopRequested,
    rigid_body_modes,
    solve_load_steps,
)

__all__ = [
    "AugmentedLagrangian",
    "BackwardEuler",
    "Checkpoint",
    "ContactAssembler",
    "ContactOperator",
    "ContactProblem",
    "ContinuationStage",
    "LoadStep",
    "Newmark",
    "NonlinearContactProblem",
    "PenaltyContinuation",
    "RigidModeDamping",
    "RigidRotation",
    "SolveResult",
    "StopRequested",
    "TimeStep",
    "UzawaUpdate",
    "__version__",
    "checkpoint",
    "contact",
    "damping_energy",
    "depth_deficiency",
    "geometry",
    "kinematics",
    "material_depth",
    "materials",
    "meshing",
    "propose_penalty",
    "rotation_displacement",
    "rotation_matrix",
    "rigid_body_modes",
    "solve_load_steps",
    "solve_nonlinear",
    "solve_time_steps",
]
