"""fenics_matdepth: material-depth penalty contact for FEniCSx (DOLFINx).

Frictionless penalty contact and self-contact between nonlinearly elastic bodies, with the
contact model of Hirota, Fisher & State (2003): every vertex carries its material depth
(distance to the boundary in the reference configuration), interpolated linearly in each
tetrahedron, and the penalty energy (eps/2) g^2 is integrated exactly over the polygons
where boundary triangles cut tetrahedra.
"""

from __future__ import annotations

__version__ = "0.1.0"

# _cache first: numba's cache stamps of the kernels then cover all the package's sources.
# linear_solver fixes PETSc's summation order (linear_solver.MDOT_GEMV_OPTION) on import,
# which must come before anything creates a PETSc vector.
from fenics_matdepth import (
    _cache,  # noqa: F401
    checkpoint,
    contact,
    geometry,
    kinematics,
    linear_solver,  # noqa: F401
    materials,
    meshing,
)
from fenics_matdepth._compat import show_warnings, solve_nonlinear
from fenics_matdepth.augmented import (
    AugmentedLagrangian,
    RigidModeDamping,
    UzawaUpdate,
    damping_energy,
)
from fenics_matdepth.checkpoint import Checkpoint
from fenics_matdepth.contact.friction import Coulomb
from fenics_matdepth.contact.operator import ContactOperator, propose_penalty
from fenics_matdepth.contact.surface import DepthDeficiencyWarning
from fenics_matdepth.continuation import ContinuationStage, PenaltyContinuation
from fenics_matdepth.depth import depth_deficiency, material_depth
from fenics_matdepth.dynamics import BackwardEuler, Newmark
from fenics_matdepth.free_bodies import FreeBody, FreeBodyDamping, find_free_bodies
from fenics_matdepth.kinematics import RigidRotation, rotation_displacement, rotation_matrix
from fenics_matdepth.problems import ContactProblem, NonlinearContactProblem, rigid_body_modes
from fenics_matdepth.pseudo_transient import PseudoTransient
from fenics_matdepth.relaxation import LocalRelaxation
from fenics_matdepth.results import LoadStep, Solvable, SolveResult, StopRequested, TimeStep
from fenics_matdepth.step_control import StepControl
from fenics_matdepth.stepping import solve_load_steps
from fenics_matdepth.system_assembler import SystemAssembler
from fenics_matdepth.time_stepping import solve_time_steps

__all__ = [
    "AugmentedLagrangian",
    "BackwardEuler",
    "Checkpoint",
    "ContactOperator",
    "ContactProblem",
    "ContinuationStage",
    "Coulomb",
    "DepthDeficiencyWarning",
    "FreeBody",
    "FreeBodyDamping",
    "LoadStep",
    "LocalRelaxation",
    "Newmark",
    "NonlinearContactProblem",
    "PenaltyContinuation",
    "PseudoTransient",
    "RigidModeDamping",
    "RigidRotation",
    "Solvable",
    "SolveResult",
    "StepControl",
    "StopRequested",
    "SystemAssembler",
    "TimeStep",
    "UzawaUpdate",
    "__version__",
    "checkpoint",
    "contact",
    "damping_energy",
    "depth_deficiency",
    "find_free_bodies",
    "geometry",
    "kinematics",
    "material_depth",
    "materials",
    "meshing",
    "propose_penalty",
    "rigid_body_modes",
    "rotation_displacement",
    "rotation_matrix",
    "solve_load_steps",
    "solve_nonlinear",
    "solve_time_steps",
]

# FFCx 0.9 (imported with DOLFINx above) captures warnings into logging that prints nothing:
# the package's warnings (DepthDeficiencyWarning, the penalty raise's) must be seen
show_warnings()


def __getattr__(name: str):
    """``fenics_matdepth.ContactAssembler``, the former name of :class:`SystemAssembler`, with
    a DeprecationWarning."""
    if name == "ContactAssembler":
        import warnings

        warnings.warn(
            "fenics_matdepth.ContactAssembler is deprecated: it is "
            "fenics_matdepth.SystemAssembler now (fenics_matdepth.system_assembler)",
            DeprecationWarning,
            stacklevel=2,
        )
        return SystemAssembler
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
