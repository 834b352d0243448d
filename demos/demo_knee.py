# ---
# jupyter:
#   jupytext:
#     text_representation:
#       extension: .py
#       format_name: light
#       format_version: '1.5'
#       jupytext_version: 1.16.0
# ---

# # The knee: a leg flexed 150°, the patella sliding unprescribed, the skin folding onto itself
#
# This demo is implemented in {download}`demo_knee.py`. It is the headline application of
# Hirota, Fisher & State (2003), section 6 (their Figs. 18-22), on a synthetic right leg
# (`meshes/leg.py`) instead of the Visible Human data: the femur is fixed, the thigh's cut
# section may only slide in its plane, and the tibia is rotated about the knee's flexion axis,
# 150° in 50 steps of 3°. Nothing prescribes the patella: it is pulled by the tibia through the
# patellar ligament, held by the quadriceps through its tendon, and pressed onto the femur, over
# which it has to slide by contact. Behind the knee the skin-fat layer is compressed and folds
# onto itself. It shows how to:
#
# - assign a material per body through the mesh's cell tags (`dx(tag)`): neo-Hookean bone,
#   Mooney-Rivlin muscle, Veronda-Westmann skin-fat, fibre-reinforced tendon and ligament;
# - prescribe a rigid rotation as Dirichlet data with {py:class}`fenics_matdepth.RigidRotation`,
#   and a sliding plane with a Dirichlet condition on one component (`V.sub(2)`);
# - run a long quasi-static load history with {py:func}`fenics_matdepth.solve_load_steps`
#   (automatic step cutting), with diagnostics per step and VTX output for ParaView.
#
# ## The physics
#
# All bodies share one mesh; glued interfaces are shared faces, sliding interfaces are gaps
# (`meshes/leg.py` lists them). The total potential energy is
#
# $$
# \Pi(\mathbf{u}) = \sum_{b} \int_{\Omega_b} \psi_b(\mathbf{F})\,\mathrm{d}X + E_c(\mathbf{u}),
# \qquad
# E_c = \frac{\varepsilon}{2} \sum_{(T, K)} \int_{T \cap K} g_K^2 \,\mathrm{d}A,
# $$
#
# with $g_K$ the material depth interpolated in the tetrahedron $K$ that a boundary triangle $T$
# has entered: skin entering skin behind the knee, the patella entering the femur, muscle
# entering bone. Each load step solves $\partial\Pi/\partial\mathbf{u} = 0$ by Newton's method.
#
# ## Implementation
#
# `MATDEPTH_DEMO_QUICK=1` runs two steps (for the test suite);
# `MATDEPTH_KNEE_RESOLUTION` (`coarse`, the demo's default, `default`, `fine` or a number),
# `MATDEPTH_KNEE_DEGREES` and `MATDEPTH_KNEE_STEPS` override the resolution, the total flexion
# and the number of steps,
# `MATDEPTH_KNEE_PREDICTOR` the step predictor (`0`, the default: none; `extrapolate` or
# `rotation`; below),
# `MATDEPTH_KNEE_BULK_RATIO` sets the soft tissues' bulk-to-shear modulus ratio (default 50),
# `MATDEPTH_KNEE_FIBRE_TOE` the width in I4 of the tendon's toe region (default 0.04; 0: fibres
# that switch on at their slack length; below),
# `MATDEPTH_KNEE_MAX_IT` the Newton iterations before a step is cut (default 200),
# `MATDEPTH_KNEE_TARGET_IT` the step control's target Newton iterations per step (default 0:
# off, steps halve only after a failure and double back after it; 10 is FEBio's choice;
# below), `MATDEPTH_KNEE_STOP_IT` the iterations its rate test lets an attempt be predicted to
# need (default three times the target), `MATDEPTH_KNEE_MIN_SCALE` the smallest factor from a
# converged step to the next (default: the step control's, 1 / 2; 1: a hard step does not
# shrink the next),
# `MATDEPTH_KNEE_ATOL` the residual norm (N) at which a Newton solve has converged (default
# 1e-2; below), `MATDEPTH_KNEE_PSEUDO_TRANSIENT` the shift of pseudo-transient continuation
# (`fm.PseudoTransient`'s `sigma0`; default 0: plain Newton; below),
# `MATDEPTH_KNEE_STOP_DEGREES` stops the flexion at the first step at or past this angle (as
# `knee_stop` does),
# `MATDEPTH_KNEE_PENALTY` the contact penalty (default 2 MPa/mm),
# `MATDEPTH_KNEE_AL_TOL_H` the overlap the augmented Lagrangian accepts, relative to the
# boundary's median edge (default 0.1; 0 turns it off: plain penalty),
# `MATDEPTH_KNEE_AL_RESET=1` starts every step's pressures from zero instead of the last step's,
# `MATDEPTH_KNEE_AL_CARRY` from this fraction of the last step's (default 1; see
# docs/measurements.md),
# `MATDEPTH_KNEE_AL_TERM` the pressure term (`quadratic`, the default, or `linear`; below),
# `MATDEPTH_KNEE_AL_MAX_IT` the Newton iterations of one step's augmented-Lagrangian solves
# together, after which the step is cut (default twice `MATDEPTH_KNEE_MAX_IT`; 0: no limit),
# `MATDEPTH_KNEE_AL_STALL` the augmented Lagrangian's `stall_rtol` (default 0.1; 0: off; below),
# `MATDEPTH_KNEE_KEEP_LEFT=1` keeps each contact pair that left in the next Newton iteration's
# Jacobian (active-set damping; below),
# `MATDEPTH_KNEE_STEP_LIMIT` the longest move of a vertex coordinate in one Newton step, in
# median boundary edges (default 2; 0: no limit; below),
# `MATDEPTH_KNEE_UPHILL` how a Newton step that climbs the energy is replaced (`reverse`, the
# default, or `shift`; below),
# `MATDEPTH_KNEE_RELAX=0` turns off the relaxation of a concentrated residual before each Newton
# step (below),
# `MATDEPTH_KNEE_FRICTION=1` adds Coulomb friction, bone on bone 0.01 and skin on skin 0.5
# (below; the contact fields of every step go to `knee_contact.xdmf` either way);
# `MATDEPTH_DEMO_OUTPUT` moves the output folder (default `demos/output`). Each converged step
# is saved to `knee_checkpoint.npz` in the output folder; `python3 demo_knee.py --resume` (or
# `MATDEPTH_KNEE_RESUME=1`) continues a stopped run from the last step saved there, with the
# same resolution, flexion and number of steps (and the augmented Lagrangian's nodal
# pressures, saved next to it in `knee_pressure.npz`).

# +
from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import dolfinx.fem.petsc
import numpy as np
import ufl
from dolfinx import fem, io, plot
from dolfinx.mesh import entities_to_geometry

import fenics_matdepth as fm
from fenics_matdepth.meshing import interpolation_points
from fenics_matdepth.plotting import (
    gather_vtk_grid,
    offscreen_pyvista,
    output_folder,
    round_bands,
    show_image,
    write_animation,
)

# the model builders of meshes/: run with the repository on PYTHONPATH
from meshes import leg

start = time.perf_counter()
comm = MPI.COMM_WORLD
quick = os.environ.get("MATDEPTH_DEMO_QUICK", "0") not in ("", "0")
# the coarse leg (7.8k vertices, 33.6k tetrahedra) is the paper's size (10k nodes, 40k
# tetrahedra) and the one flexed to 150 deg in docs/demos.md; `default` is finer (63.5k)
resolution = os.environ.get("MATDEPTH_KNEE_RESOLUTION", "coarse")
total_degrees = float(os.environ.get("MATDEPTH_KNEE_DEGREES", 6.0 if quick else 150.0))
num_steps = int(os.environ.get("MATDEPTH_KNEE_STEPS", 2 if quick else 50))
predictor = os.environ.get("MATDEPTH_KNEE_PREDICTOR", "0")
predictor = {"1": "extrapolate", "": "0"}.get(predictor, predictor)
if predictor not in ("extrapolate", "rotation", "0"):
    raise ValueError(f"MATDEPTH_KNEE_PREDICTOR is extrapolate, rotation or 0, not {predictor!r}")
bulk_ratio = float(os.environ.get("MATDEPTH_KNEE_BULK_RATIO", 50.0))
max_newton = int(os.environ.get("MATDEPTH_KNEE_MAX_IT", 200))
newton_atol = float(os.environ.get("MATDEPTH_KNEE_ATOL", 1e-2))
pseudo_transient = float(os.environ.get("MATDEPTH_KNEE_PSEUDO_TRANSIENT", 0.0))
stop_degrees = float(os.environ.get("MATDEPTH_KNEE_STOP_DEGREES", "inf"))
target_iterations = int(os.environ.get("MATDEPTH_KNEE_TARGET_IT", 0))
stop_iterations = int(os.environ.get("MATDEPTH_KNEE_STOP_IT", 3 * target_iterations))
min_scale = float(os.environ.get("MATDEPTH_KNEE_MIN_SCALE", 0.0)) or None
al_tol_h = float(os.environ.get("MATDEPTH_KNEE_AL_TOL_H", 0.1))
fibre_toe = float(os.environ.get("MATDEPTH_KNEE_FIBRE_TOE", 0.04))
al_reset = os.environ.get("MATDEPTH_KNEE_AL_RESET", "0") not in ("", "0")
al_carry = float(os.environ.get("MATDEPTH_KNEE_AL_CARRY", 1.0))
al_term = os.environ.get("MATDEPTH_KNEE_AL_TERM", "quadratic")
al_max_it = int(os.environ.get("MATDEPTH_KNEE_AL_MAX_IT", 2 * max_newton))
al_stall = float(os.environ.get("MATDEPTH_KNEE_AL_STALL", 0.1))
keep_left = os.environ.get("MATDEPTH_KNEE_KEEP_LEFT", "0") not in ("", "0")
step_limit = float(os.environ.get("MATDEPTH_KNEE_STEP_LIMIT", 2.0))
uphill_step = os.environ.get("MATDEPTH_KNEE_UPHILL", "reverse")
relax = os.environ.get("MATDEPTH_KNEE_RELAX", "1") not in ("", "0")
resume = "--resume" in sys.argv or os.environ.get("MATDEPTH_KNEE_RESUME", "0") not in ("", "0")
try:
    here = Path(__file__).resolve().parent
except NameError:  # in a notebook
    here = Path.cwd()
output = output_folder(comm, here / "output")  # or $MATDEPTH_DEMO_OUTPUT
if comm.rank == 0:
    (output / "knee_stop").unlink(missing_ok=True)  # a stop request of an earlier run
comm.barrier()


def report(message: str) -> None:
    if comm.rank == 0:
        print(message, flush=True)


# -

# ### The leg
#
# Units: millimetres, megapascals (N/mm²), newtons. The flexion axis is the $x$ axis through
# the centres of the femoral condyles; $y$ points forwards, $z$ upwards.
#
# Where the leg's shape comes from a measured failure. An earlier version of the leg reached
# only 43.5° (min det F 0.15). Rendering det F cell by cell showed what crushed the tissue,
# one thing after another as each was removed:
#
# - *a ledge on the femur*: the femoral shaft, a straight cylinder down to the condyles, stood
#   7 mm proud of the trochlear groove; the tissue under its flat end was crushed by the
#   descending patella and the pull of the ligament (det F 0.61 after the first 3°, 0.30 at
#   12°). A real anterior cortex runs into the trochlea without a step, so the shaft's lowest
#   24 mm now sweep back into the condyles (`metaphysis_offset`, `metaphysis_height`);
# - *soft tissue between patella and femur*: the patella sat 4 mm off the femur with a 2 mm
#   layer of tissue glued to its back, which carried the patellofemoral pressure (det F 0.58
#   at 21°). In a real knee cartilage meets cartilage there; the patella now sits 1.5 mm off
#   the femur, across the joint space (`patellofemoral_space`);
# - *bulk behind the knee*: a real knee has the popliteal fossa, a hollow between the
#   hamstrings and the heads of gastrocnemius into which the skin folds as the knee bends.
#   The back of the leg is now hollowed there (`fossa_depth` 14 mm, `fossa_radius` 40 mm) and
#   the popliteal crease cuts 10 mm deeper at its floor;
# - *the plateau's rim*: the tibial plateau sits 1.5 mm further forward (`plateau_offset`),
#   which keeps its posterior rim, swinging up behind the condyles about the fixed axis, a
#   little further from the femoral shaft at full flexion;
# - *tissue on the plateau's posterior rim* (the lowest det F of the leg, 0.28 at 54°, under
#   the lateral condyle): not a misplaced axis (the condyles' surface is 22.00 mm from their
#   centres on the axis, so the rim keeps its 5.3 mm from the femur as it turns), but 3.3 mm of
#   tissue glued to the rim and pressed onto the femur by the tissue behind it. The joint space
#   now reaches 4 mm past the posterior rim (`joint_space_semi_axes`, `joint_space_offset`);
# - *tissue glued round the patella's lower rim and under its lower pole*: carried down onto
#   the trochlea (penetration 0.28 h at 52°) and pressed onto the femur by the ligament. The
#   patella's lower half now sits in a 2 mm recess swept back into the femur's clearance
#   (`patella_recess`). Leaving out the tissue between the ligament and the femur as well
#   (the infrapatellar fat pad's place, `fat_pad_half_width`) made it worse
#   (`docs/measurements.md`);
# - *the tissue behind the knee at x = 0*: with muscle filling the whole back of the knee,
#   the coarse leg stopped at 135.8°. The calf tissue behind the tibial plateau, swung round
#   the fixed axis, arrived at the back of the femoral shaft (tissue more than 30° behind the
#   shank's axis is rotated into the shaft's place by 150°), pressed the thigh tissue between
#   the condyles into the femur and was itself crushed at the hinge (det F 0.047 at
#   (0, -32, -5)). A real knee has the popliteal space there, between the heads of
#   gastrocnemius and the hamstrings, holding fat, vessels and the tibial nerve; it is now
#   left empty under the skin (`popliteal_space_half_width` 14 mm and its companions);
# - *slivers*: the lowest det F sat in single flat tetrahedra (a tetrahedron whose vertices are
#   nearly coplanar changes its volume by a large fraction for a small motion). The mesh is
#   optimised harder (`Mesh.OptimizeThreshold` 0.45, three passes, then vertex relocation):
#   tetrahedra of quality below 0.05 went from 270 to about 100 on the coarse leg.

# +
geometry = leg.LegGeometry()
tic = time.perf_counter()
resolution_value = resolution if resolution in leg.RESOLUTIONS else float(resolution)
domain, cell_tags, facet_tags = leg.leg_mesh(comm, resolution_value, geometry)
stats = leg.mesh_statistics(domain)
report(
    f"leg mesh ({resolution}): {stats['vertices']} vertices, {stats['tetrahedra']} tetrahedra, "
    f"{stats['boundary_triangles']} boundary triangles, {stats['zero_depth_tetrahedra']} "
    f"tetrahedra with all four vertices on the boundary, median edge "
    f"{stats['median_edge']:.2f} mm ({time.perf_counter() - tic:.1f} s)"
)
V = fem.functionspace(domain, ("Lagrange", 1, (3,)))
depth = fm.material_depth(domain)
depth.name = "material_depth"
# -

# ### Materials
#
# Moduli in MPa. Soft-tissue figures are small-strain shear moduli of the orders reported for
# passive tissue. Their bulk moduli are fifty times the shear moduli (Poisson's ratio 0.49,
# `MATDEPTH_KNEE_BULK_RATIO` changes the factor): tissue is mostly water, and nearly
# incompressible. An earlier choice of ten times (Poisson's ratio 0.45) made the tissue a
# sponge: the pressure the joint puts on it (0.05 to 0.1 MPa next to the patella and on the
# tibial plateau's rim) is a sizeable fraction of a bulk modulus of 0.15 MPa, so the tissue
# there lost a third of its volume in the first 20° instead of flowing aside (measured: det F
# fell by 0.06 per 3° step on the plateau's rim with ten times, by 0.035 with fifty). Fifty is
# still far from water's ratio (about 1e5); with first-order tetrahedra a larger one locks.
#
# - femur, tibia: neo-Hookean, mu = 40, kappa = 90 (E about 100). Both are prescribed entirely
#   (fixed, rotated), so the values do not matter.
# - patella: neo-Hookean, mu = 40, kappa = 90 (E about 100): four orders of magnitude stiffer
#   than the tissue around it, rigid in effect; real bone (E about 1e4) only worsens the
#   conditioning.
# - quadriceps, thigh and calf soft tissue: Mooney-Rivlin, c10 = 5e-3, c01 = 2.5e-3
#   (mu = 15 kPa), kappa = 0.75: passive skeletal muscle, mu of 5 to 20 kPa in indentation and
#   elastography.
# - skin-fat layer: Veronda-Westmann, c1 = 2.5e-3, c2 = 4 (mu = 10 kPa), kappa = 0.5:
#   dominated by subcutaneous fat (mu of a few kPa), stiffening at large stretch (the dermis).
# - quadriceps tendon, patellar ligament: fibre-reinforced, matrix mu = 0.5, kappa = 5, fibres
#   k1 = 100 (fibre modulus 4 k1 = 400 MPa) along the tendon's axis: tendon has a modulus of
#   several hundred MPa along its fibres and is soft across them. The fibres stiffen over a toe
#   region, I4 from 1 to 1.04 (about 2 % strain, where tendon's crimped collagen straightens):
#   fibres that switch on at their slack length make the energy only once differentiable
#   there, and hundreds of the tendon's cells crossing it in each Newton iteration kept
#   Newton's method from converging quadratically (docs/measurements.md).
#
# The fibre direction $\mathbf{a}_0$ is a piecewise-constant field: along $z$ in the quadriceps
# tendon, from the patella to the tibial tuberosity in the patellar ligament.

# +
bone = {"mu": 40.0, "kappa": 90.0}
muscle = {"c10": 5e-3, "c01": 2.5e-3, "kappa": 0.015 * bulk_ratio}
skin_fat = {"c1": 2.5e-3, "c2": 4.0, "kappa": 0.01 * bulk_ratio}
tendon = {"mu": 0.5, "kappa": 5.0, "k1": 100.0, "toe": fibre_toe}

u = fem.Function(V, name="displacement")
F = ufl.variable(ufl.Identity(3) + ufl.grad(u))
W = fem.functionspace(domain, ("DG", 0, (3,)))
fibre = fem.Function(W, name="fibre_direction")
fibre_of = {leg.TENDON: np.asarray(geometry.tendon_axis), leg.LIGAMENT: geometry.ligament_axis}
for tag, direction in fibre_of.items():
    cells = cell_tags.find(tag)
    fibre.x.array.reshape(-1, 3)[W.dofmap.list[cells, 0]] = direction
fibre.x.scatter_forward()

psi = {
    leg.FEMUR: fm.materials.neo_hookean(F, **bone),
    leg.TIBIA: fm.materials.neo_hookean(F, **bone),
    leg.PATELLA: fm.materials.neo_hookean(F, **bone),
    leg.QUADRICEPS: fm.materials.mooney_rivlin(F, **muscle),
    leg.THIGH: fm.materials.mooney_rivlin(F, **muscle),
    leg.CALF: fm.materials.mooney_rivlin(F, **muscle),
    leg.SKIN: fm.materials.veronda_westmann(F, **skin_fat),
    leg.TENDON: fm.materials.fiber_reinforced(F, a0=fibre, **tendon),
    leg.LIGAMENT: fm.materials.fiber_reinforced(F, a0=fibre, **tendon),
}
# P1 displacements and piecewise-constant fibres make every energy density constant on each
# tetrahedron, so one quadrature point integrates it exactly; UFL's estimate (a high degree for
# these invariants) gave the same Newton iterations (the quick run's 2 steps of 18) with a
# Jacobian 2.5 to 3.5 times slower to assemble (coarse leg: 0.35 s against 0.10 to 0.15 s).
dx = ufl.Measure("dx", domain=domain, subdomain_data=cell_tags, metadata={"quadrature_degree": 1})
energy = sum(density * dx(tag) for tag, density in psi.items())
# -

# ### Boundary conditions
#
# The femur is fixed (all its vertices); the tibia's vertices follow a rigid rotation about
# the flexion axis (the $-x$ axis: the foot moves backwards); the thigh's proximal cut plane
# $z = $ `thigh_length` may only move in its plane: its $z$ component is zero, a Dirichlet
# condition on the sub-space `V.sub(2)`.
#
# Except for the quadriceps. It does not end at the cut: it runs on for another 25 cm or so to
# the hip and the proximal femur, and in passive flexion the whole muscle lengthens as the
# patella is pulled 5-8 cm down over the femur. Pinned at the cut, the 2 cm of muscle between
# the cut and the tendon's end would have to take that whole excursion (several hundred per cent
# of strain, crushing the muscle beside the stiff tendon's end: the lowest det F of the leg
# after 10° in an earlier run). So the quadriceps' share of the cut carries the muscle left out
# instead: a spring of stiffness $k = E / L_0$ per unit area on the $z$ displacement, with
# $E = 3\mu = 45$ kPa the muscle's small-strain modulus and $L_0 = 250$ mm the omitted length,
# energy $\frac{k}{2}\int u_z^2\,\mathrm{d}A$ over that part of the cut.

# +
tdim = domain.topology.dim
fdim = tdim - 1
domain.topology.create_connectivity(fdim, tdim)
cell_tag_of = np.zeros(
    domain.topology.index_map(tdim).size_local + domain.topology.index_map(tdim).num_ghosts,
    dtype=np.int32,
)
cell_tag_of[cell_tags.indices] = cell_tags.values
cut_facets = facet_tags.find(leg.PROXIMAL_CUT)
f2c = domain.topology.connectivity(fdim, tdim)
on_quadriceps = np.array(
    [cell_tag_of[f2c.links(f)[0]] == leg.QUADRICEPS for f in cut_facets], dtype=bool
)
QUADRICEPS_CUT = 1
quadriceps_cut = dolfinx.mesh.meshtags(
    domain, fdim, cut_facets[on_quadriceps], np.full(on_quadriceps.sum(), QUADRICEPS_CUT, np.int32)
)
ds = ufl.Measure("ds", domain=domain, subdomain_data=quadriceps_cut)
omitted_muscle = 250.0  # mm
spring = 3.0 * 2.0 * (muscle["c10"] + muscle["c01"]) / omitted_muscle  # MPa/mm
energy = energy + 0.5 * spring * u[2] ** 2 * ds(QUADRICEPS_CUT)
residual = ufl.derivative(energy, u, ufl.TestFunction(V))

domain.topology.create_connectivity(tdim, tdim)
femur_dofs = fem.locate_dofs_topological(V, tdim, cell_tags.find(leg.FEMUR))
tibia_dofs = fem.locate_dofs_topological(V, tdim, cell_tags.find(leg.TIBIA))
cut_dofs = fem.locate_dofs_topological(V.sub(2), fdim, cut_facets[~on_quadriceps])
tibia_rotation = fm.RigidRotation(V, center=(0.0, 0.0, 0.0), axis=(-1.0, 0.0, 0.0))
bcs = [
    fem.dirichletbc(np.zeros(3, dtype=PETSc.ScalarType), femur_dofs, V),
    fem.dirichletbc(tibia_rotation.function, tibia_dofs),
    fem.dirichletbc(PETSc.ScalarType(0.0), cut_dofs, V.sub(2)),
]
total_angle = np.radians(total_degrees)
# -

# ### A predictor for each step
#
# By default there is none: each step starts from the last converged state, and the tibia's new
# values come through the first Newton step, which extends them into the tissue by one linear
# solve at the current tangent. Measured with `benchmarks/bench_knee.py` (serially, the same
# machine and hour): the first 30° in 10 steps took 93 Newton iterations (11, 11, 10, 7, 8, 7,
# 12, 10, 11, 6) without a predictor against 159 (29, 9, 23, 16, 11, 12, 13, 16, 16, 14) with
# the extrapolating one below, the final states alike (penetration 0.077 h, lowest det F 0.527);
# the first 3° step alone 11 against 29. With the extrapolation 24 of the 159 iterations had
# a full step that inverted elements behind the knee (45 trial states rejected), none without.
# The full 150° without a predictor: 53 steps, 1,296 Newton iterations in the
# converged attempts and 4 failed attempts (the last run with the extrapolation: 57 steps,
# 1,625 and 9). The predictors are kept as options:
#
# `ContactProblem` imposes the new Dirichlet values through the first Newton step, so the tibia's
# 3° increment reaches the tissue glued to it through the linearised step and no element is
# inverted before Newton starts. Newton still starts far from the answer: the shank has to turn
# with the tibia. The options start each step from a prediction. Once two converged states are
# known, the last increment is extrapolated (scaled to the new step): it carries what the tissue
# did in the last step, the skin sliding and folding behind the knee included. The first step (and
# the first after `--resume`) spreads the increment of rotation over the leg instead: vertices of
# the shank turn with the tibia, the thigh stays, and across the knee the share of the rotation
# falls linearly from 1 at the tibial plateau to 0 at the flexion axis. Measured from 96° (coarse
# leg), a 3° step: rotated, Newton started at |F| = 1.6e4 with the calf's skin pushed into the
# thigh's and failed after 50 iterations; extrapolated, it started at 1.3e3 and converged in 28.
# Either way the constrained dofs are then put on their values (the femur's condyles reach below
# the axis, and the shared rotation moved them up to 0.5 mm off their fixed place): while a
# Dirichlet dof is off its value the line search cannot use the energy, and a step from such a
# start crawled (1.5° at 94° failed after 50 iterations at |F| = 1.5e3; with the dofs put on
# their values it converged in 25). Newton corrects the rest. A prediction that inverts an
# element is not used: that step starts from the last converged state, and the tibia's new values
# come through the first Newton step (in the full run this happened 11 times past 110°; before,
# each such start failed with a NaN residual and the step was cut: 18 of 21 cuts).
# (`MATDEPTH_KNEE_PREDICTOR=rotation` always rotates; `0` starts each step from the last
# converged state.)

# +
X_all = V.tabulate_dof_coordinates()
share = np.clip((0.0 - X_all[:, 2]) / (0.0 - geometry.plateau_top), 0.0, 1.0)
last = {"u": u.x.array.copy(), "angle": 0.0, "before": None}  # before: (u, angle) one step back


def set_flexion(t: float) -> None:
    """Load factor t in [0, 1]: the tibia rotated by t * total_angle; u predicted from the last
    converged states (extrapolated, or the rotation increment shared out, as described above)
    with the Dirichlet dofs on their values."""
    angle = t * total_angle
    tibia_rotation.set_angle(angle)
    if predictor == "0":
        return
    if predictor == "extrapolate" and last["before"] is not None:
        u_before, angle_before = last["before"]
        scale = (angle - last["angle"]) / (last["angle"] - angle_before)
        u.x.array[:] = last["u"] + scale * (last["u"] - u_before)
    else:
        x = X_all + last["u"].reshape(-1, 3)
        step = np.empty_like(x)
        for fraction in np.unique(share):
            rows = share == fraction
            step[rows] = fm.rotation_displacement(
                x[rows], (0.0, 0.0, 0.0), (-1.0, 0.0, 0.0), fraction * (angle - last["angle"])
            )
        u.x.array[:] = last["u"] + step.reshape(-1)
    dolfinx.fem.petsc.set_bc(u.x.petsc_vec, bcs)
    u.x.scatter_forward()
    if problem.min_det_F() <= 0.0:
        # the prediction inverts an element (its residual would be NaN and the step cut):
        # start from the last converged state, the Dirichlet values reached through the first
        # Newton step instead
        u.x.array[:] = last["u"]
        u.x.scatter_forward()
        report(f"    the prediction for {np.degrees(angle):.2f} deg inverts an element: starting "
               "from the last converged state")  # fmt: skip


# -

# ### Contact
#
# One penalty for every contact in the leg. The largest pressure is between patella and femur:
# the quadriceps and the ligament press the patella onto the trochlea with a pressure of order
# 0.1-1 MPa; $\varepsilon = 2$ MPa/mm lets that penetrate 0.05-0.5 mm, a tenth of an element or
# less. Skin on skin (pressures of kPa) then penetrates micrometres.

# +
penalty = float(os.environ.get("MATDEPTH_KNEE_PENALTY", 2.0))  # MPa/mm
# MATDEPTH_KNEE_FRICTION=1: Coulomb friction by pair of cell tags (docs/friction.md), cartilage
# on cartilage (bone on bone: femur, patella, tibia) mu = 0.01, skin on skin mu = 0.5, the rest
# (soft tissue sliding on bone) frictionless
knee_friction = None
if os.environ.get("MATDEPTH_KNEE_FRICTION", "0") not in ("", "0"):
    bones = (leg.FEMUR, leg.PATELLA, leg.TIBIA)
    knee_mu = {(a, b): 0.01 for a in bones for b in bones} | {(leg.SKIN, leg.SKIN): 0.5}
    knee_friction = fm.Coulomb(knee_mu, cell_tags=cell_tags)
contact = fm.ContactOperator(u, depth, penalty, friction=knee_friction)
problem = fm.ContactProblem(
    residual,
    u,
    contact,
    bcs=bcs,
    energy=energy,
    petsc_options_prefix="knee_",
    # |F| below 1e-2 N is converged (MATDEPTH_KNEE_ATOL): the forces in the leg are of order 1 to
    # 1000 N, and 1e-2 N left the first 30 deg's checks the same to 5 digits (penetration,
    # det F, the patella's turn and displacement, the fold) where 1e-8 N, the earlier
    # tolerance, took 21 more Newton iterations, one or two a step in the quadratic range
    # (docs/measurements.md). (An absolute tolerance also keeps a small step's relative one,
    # 1e-10 of its first residual, from lying below the residual's rounding floor, 2e-9 to
    # 4e-9 N at 121 deg, where steps were cut to nothing.)
    # 200 iterations: past 148 deg a solve's residual fell to about 3e-2 N and jumped back to
    # about 10 N several times as faces entered the contact (with their carried pressures), and
    # with 50 the steps were cut to 0.1 deg and less; with 100 they converged. The attempts
    # that then reached 100 were converging: with 200 they took 112 and 132 iterations, and of
    # six paths to 150 deg none reached 200 (docs/measurements.md, "Where the late steps creep")
    petsc_options={"snes_max_it": max_newton, "snes_atol": newton_atol},
    # MATDEPTH_KNEE_CCD=0: without the collision detection of the Newton steps (to measure
    # what it costs here)
    ccd=os.environ.get("MATDEPTH_KNEE_CCD", "1") not in ("", "0"),
    # MATDEPTH_KNEE_CCD_ENTRY: the collision detection's entry tolerance, a fraction of the
    # local boundary edge (default 0.25; docs/measurements.md)
    ccd_entry=float(os.environ.get("MATDEPTH_KNEE_CCD_ENTRY", fm.contact.ccd.ENTRY_FRACTION)),
)
# MATDEPTH_KNEE_KEEP_LEFT=1: a pair that left the contact over a Newton step keeps its Hessian
# in the next Jacobian (fm.contact.active_set.LaggedPairs; measured in docs/measurements.md)
problem.assembler.keep_left_pairs(keep_left)
# MATDEPTH_KNEE_PSEUDO_TRANSIENT=sigma0: each Jacobian shifted by sigma |diag J|, sigma falling
# with the residual (pseudo-transient continuation, fm.PseudoTransient; docs/solvers.md)
if pseudo_transient > 0.0:
    problem.pseudo_transient = fm.PseudoTransient(sigma0=pseudo_transient)
# MATDEPTH_KNEE_STEP_LIMIT=edges: a Newton step moving a vertex coordinate further than that
# many median boundary edges (default 2) becomes a Levenberg-Marquardt step within it
# (ContactProblem.step_limit). Past 100 deg the pinched soft tissue behind the knee makes the
# Jacobian nearly singular and half the Newton steps move a vertex further than an edge, up to
# metres, along that soft mode; the limit of 2 edges took 873 to 1,103 Newton iterations to
# 150 deg in five runs, against 1,153 to 1,384 without it (docs/measurements.md)
if step_limit > 0.0:
    problem.step_limit = step_limit * stats["median_edge"]
# MATDEPTH_KNEE_UPHILL: near a saddle of the energy (the fold's tissue about to buckle one way
# or the other) the Newton step climbs the energy. Reversed (the default), it is a direction
# of negative curvature and leaves the saddle in a few iterations; shifted (J + mu I, the
# library's default), solves crept at |F| of 0.01 to 0.1 N for up to 31 iterations, and 150
# deg took 525 to 751 Newton iterations on four paths (mean 609) against 554 to 640 reversed
# (mean 594), with no solve creeping (ContactProblem.uphill_step; docs/measurements.md)
problem.uphill_step = uphill_step
# Before each Newton step, where a few vertices hold most of the residual, their patch is
# brought to equilibrium with the rest of the leg held (fm.LocalRelaxation; off with friction,
# which a patch leaves out). Past 100 deg the residual sits on two or three vertices behind the
# knee, and the Newton step answers their force by moving a soft region elsewhere; relaxed,
# 150 deg took 613 to 706 Newton iterations on three paths of this machine against 884 to 1,136
# without, and on 2 processes 633 to 1,423 against 842 to 1,102, fewer on two paths of three
# (docs/measurements.md).
if relax and knee_friction is None:
    problem.relaxation = fm.LocalRelaxation(energy)
elif relax:
    report("local relaxation: off (it leaves friction out)")
# -

# ### The augmented Lagrangian
#
# Bone on bone the penalty is too soft: from about 33° the patella bears on the femur's
# trochlea with a force that grows past 250 N, which $\varepsilon = 2$ MPa/mm carried only with
# an overlap of a third of an element (measured: 0.33 h at 73°). A penalty a hundred times
# larger would make Newton's matrix correspondingly worse conditioned. Instead
# {py:class}`fenics_matdepth.AugmentedLagrangian` keeps the penalty and adds nodal contact
# pressures, raised by Uzawa updates after each converged Newton solve until the deepest point
# of every contact surface is within `al_tol_h` (a tenth) of the boundary's median edge. Its
# solve replaces the problem's in `solve_load_steps`; a step that fails restores the pressures
# it started from, and the pressures carry over from one step to the next.
#
# The pressure term is the quadratic one (`pressure_term="quadratic"`): the pressures stiffen
# the penalty of each penetrating triangle, `eps + p / w` with `w` half the tolerance, and each
# update sets them to the peak contact pressure the solve produced. With the linear term
# (`p g`, Lagrange multipliers; `MATDEPTH_KNEE_AL_TERM=linear`) the pressures carried from the
# last step held faces of thigh tissue lying flat on the femur at the energy's kink, and Newton's
# method stalled at 58° whatever the step (docs/measurements.md); the quadratic term has no
# kink, and its pressures fall where a contact relaxes.
#
# A step's solves and pressure updates together get twice the Newton iterations one solve
# may take (`max_iterations`, `MATDEPTH_KNEE_AL_MAX_IT`; the step to 147° takes 126 with its
# two updates); where they are spent the step is cut, as after any failed attempt. Without
# the bound, the step to 144° of an earlier run spent 46 minutes in its updates and in the
# halvings of the updates whose solves failed (docs/measurements.md).
#
# Where an update raised the pressures round a vertex and its overlap stayed above the
# tolerance, lowered by less than a tenth (`stall_rtol=0.1`), the pressures cannot move it: on
# one path a triangle of the femur (prescribed) stayed 1.72 tolerances deep in a tetrahedron of
# the calf's tissue while eleven updates raised the pressures there to 1.0e6 MPa. Such a vertex
# is held for the rest of the step, its pressure back to its value before that update; the step
# ends once the overlap elsewhere is within the tolerance (accepted up to twice it,
# `stall_accept`; beyond, it is cut), and its line says "stalled".

# +
h_boundary = stats["median_edge"]
solver = problem
augmented = None
if al_tol_h > 0.0:
    augmented = fm.AugmentedLagrangian(
        problem, tol_h=al_tol_h, h=h_boundary, pressure_term=al_term,
        max_iterations=al_max_it or None, stall_rtol=al_stall,
    )  # fmt: skip
    solver = augmented
# -

# ### What is measured at each step
#
# - penetration relative to the element size: the largest depth reached by a surface
#   (`contact.max_penetration()`) over the median edge of the boundary triangles;
# - the smallest $\det \mathbf{F}$ over the cells (an inverted element has $\det\mathbf{F} \le 0$),
#   and the five lowest cells with their body and reference centroid (one crushed cell or a
#   crushed region);
# - the patella's motion relative to the (fixed) femur: the displacement of its centroid and the
#   rotation of the best-fitting rigid motion of its vertices (Kabsch);
# - the contact force on the patella: minus the contact gradient summed over its vertices (the
#   femur's pull on it, through the penetrated surface);
# - the skin vertices behind the knee that carry a contact force (self-contact of the fold).

# +
Q = fem.functionspace(domain, ("DG", 0))
mesh_x = domain.geometry.x
n_cells_local = domain.topology.index_map(tdim).size_local
cell_body = np.zeros(n_cells_local + domain.topology.index_map(tdim).num_ghosts, dtype=np.int32)
cell_body[cell_tags.indices] = cell_tags.values
domain_centroids = mesh_x[
    np.asarray(entities_to_geometry(domain, tdim, np.arange(n_cells_local, dtype=np.int32), False))
].mean(axis=1)
det_F = fem.Function(Q, name="det_F")
det_F_expr = fem.Expression(ufl.det(F), interpolation_points(Q))
imap = V.dofmap.index_map
n_owned = imap.size_local
X = V.tabulate_dof_coordinates()[:n_owned]
global_ids = imap.local_to_global(np.arange(n_owned, dtype=np.int32))


def vertices_of(tag: int) -> np.ndarray:
    """Owned local vertex (block) indices of the cells with ``tag``."""
    blocks = np.unique(V.dofmap.list[cell_tags.find(tag)].ravel())
    return blocks[blocks < n_owned]


patella_blocks = vertices_of(leg.PATELLA)
skin_blocks = vertices_of(leg.SKIN)
# skin vertices behind the knee: the fold's side of the leg
fold_blocks = skin_blocks[(X[skin_blocks, 1] < 0.0) & (np.abs(X[skin_blocks, 2]) < 60.0)]
is_patella = np.zeros(imap.size_global, dtype=bool)
is_patella[np.concatenate(comm.allgather(global_ids[patella_blocks]))] = True
is_fold = np.zeros(imap.size_global, dtype=bool)
is_fold[np.concatenate(comm.allgather(global_ids[fold_blocks]))] = True
patella_X = np.concatenate(comm.allgather(X[patella_blocks]))


def patella_motion() -> tuple[np.ndarray, np.ndarray, float]:
    """(centroid displacement, current centroid, rotation angle in degrees) of the patella."""
    moved = np.concatenate(
        comm.allgather(X[patella_blocks] + u.x.array.reshape(-1, 3)[patella_blocks])
    )
    c0, c1 = patella_X.mean(axis=0), moved.mean(axis=0)
    H = (patella_X - c0).T @ (moved - c1)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    angle = np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))
    # sign: flexion-like rotation about -x is positive
    if R[2, 1] - R[1, 2] > 0.0:
        angle = -angle
    return c1 - c0, c1, float(angle)


# each vertex's body for the deepest contact's report: a bone where a bone's cells touch it
vertex_body = np.zeros(imap.size_local + imap.num_ghosts, dtype=np.int32)
for tag in sorted(leg.BODIES, key=lambda b: b in (leg.FEMUR, leg.TIBIA, leg.PATELLA)):
    vertex_body[np.unique(V.dofmap.list[cell_tags.find(tag)].ravel())] = tag
body_of_global = np.zeros(imap.size_global, dtype=np.int32)
all_ids = imap.local_to_global(np.arange(imap.size_local + imap.num_ghosts, dtype=np.int32))
body_of_global[all_ids] = vertex_body
comm.Allreduce(MPI.IN_PLACE, body_of_global, op=MPI.MAX)


def deepest_contact() -> dict:
    """The contact pair reaching deepest (collective): its depth, the penetrating triangle's
    and the penetrated tetrahedron's bodies (by their vertices, bones first) and reference
    centroids (mm), and the triangle's mean edge length, the local element size (mm)."""
    deepest = contact.deepest_contact()
    if deepest is None:
        return {}

    def body(vertices):
        return leg.BODIES[int(np.bincount(body_of_global[vertices]).argmax())]

    return {
        "depth": deepest["depth"],
        "triangle_body": body(deepest["surface_vertices"]),
        "triangle_at": np.round(deepest["surface_reference"], 1).tolist(),
        "tetrahedron_body": body(deepest["tetrahedron_vertices"]),
        "tetrahedron_at": np.round(deepest["tetrahedron_reference"], 1).tolist(),
        "local_h": deepest["local_h"],
    }


def fold_touching(dofs=None, values=None) -> np.ndarray:
    """The deformed positions of the fold's skin vertices with a contact force, one row per
    vertex, on every rank (collective; ``dofs, values``: the contact gradient if at hand)."""
    if dofs is None:
        contact.update()  # at u as it is (a resumed run stopped before its first solve)
        dofs, values = contact.gradient_array()
    touched = np.unique(dofs[(values != 0.0) & is_fold[dofs // 3]] // 3)
    # the contact surface holds every vertex of its pairs, with its position now
    s = contact.surface
    held = np.flatnonzero(np.isin(s.global_vertex, touched))
    ids = np.concatenate(comm.allgather(s.global_vertex[held]))
    positions = np.vstack(comm.allgather(s.x[held])).reshape(-1, 3)
    return positions[np.unique(ids, return_index=True)[1]]


def measure(t: float) -> dict:
    """Diagnostics of the converged state at load factor t (collective)."""
    det_F.interpolate(det_F_expr)
    n_cells = domain.topology.index_map(tdim).size_local
    local = det_F.x.array[Q.dofmap.list[:n_cells, 0]]  # cell order
    worst = int(np.argmin(local)) if n_cells else -1
    where = (
        (float(local[worst]), int(cell_body[worst]), domain_centroids[worst].tolist())
        if n_cells
        else (np.inf, 0, [0.0, 0.0, 0.0])
    )
    min_det, worst_body, worst_at = min(comm.allgather(where))
    # the five lowest cells of the leg, to tell one crushed cell from a crushed region
    lowest = np.argsort(local)[:5]
    candidates = [
        (float(local[c]), leg.BODIES[int(cell_body[c])], np.round(domain_centroids[c], 1).tolist())
        for c in lowest
    ]
    lowest_cells = sorted(c for part in comm.allgather(candidates) for c in part)[:5]
    dofs, values = contact.gradient_array()
    force = np.zeros(3)
    on_patella = is_patella[dofs // 3]
    np.add.at(force, dofs[on_patella] % 3, -values[on_patella])
    force = comm.allreduce(force)
    fold_contacts = len(fold_touching(dofs, values))
    shift, centroid, rotation = patella_motion()
    diag = contact.diagnostics()
    deepest = deepest_contact()
    return {
        "degrees": float(np.degrees(t * total_angle)),
        "active_pairs": int(diag["active_pairs"]),
        "max_penetration": float(diag["max_penetration"]),
        "penetration_over_h": float(diag["max_penetration"] / h_boundary),
        "deepest_contact": deepest,
        "min_det_F": min_det,
        "min_det_F_body": leg.BODIES.get(worst_body, "?"),
        "min_det_F_at": worst_at,
        "lowest_det_F_cells": lowest_cells,
        "patella_displacement": shift.tolist(),
        "patella_centroid": centroid.tolist(),
        "patella_rotation_degrees": rotation,
        "patella_contact_force": force.tolist(),
        "fold_skin_vertices_in_contact": fold_contacts,
        "friction": {
            k: float(diag[k])
            for k in ("friction_dissipation", "stick_points", "slip_points", "max_traction_ratio")
            if k in diag
        },
    }


# -

# ### Pictures
#
# The deformed mesh is gathered on rank 0 at every converged step (vertices moved by `u`, the
# material depth and each cell's body); pyvista renders a frame of the skin surface for the
# animation, and the last state is kept for the figures.

# +
cells, types, points = plot.vtk_mesh(V)
owned_cells = cells.reshape(-1, 5)[:n_cells_local].ravel()
pv = offscreen_pyvista() if comm.rank == 0 else None
frames: list[np.ndarray] = []
all_cell_bodies = comm.gather(cell_body[:n_cells_local], root=0)


def gathered_grid():
    """The deformed mesh on rank 0 as a pyvista grid (None elsewhere or without pyvista)."""
    n_points = points.shape[0]
    moved = points + u.x.array.reshape(-1, 3)[:n_points]
    data = gather_vtk_grid(
        comm, owned_cells, types[:n_cells_local], moved, depth.x.array[:n_points], points
    )
    if comm.rank != 0 or pv is None:
        return None
    c, t, x, d, x0 = data
    grid = pv.UnstructuredGrid(c, t, x)
    grid.point_data["material depth (mm)"] = d
    grid.point_data["reference"] = x0
    grid.cell_data["body"] = np.concatenate(all_cell_bodies)
    return grid


def add_title(plotter, text: str) -> None:
    """A subplot's title at its upper left, in one size: pyvista's corner text shrinks a long
    title, so that the two panels of a picture had titles of different sizes."""
    plotter.add_text(text, position=(0.01, 0.955), viewport=True, font_size=10)


def skin_view(plotter, grid, title: str) -> None:
    plotter.add_mesh(grid.extract_surface(), color="#e8b89a", smooth_shading=True)
    add_title(plotter, title)
    plotter.view_vector((1.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    plotter.camera.zoom(1.1)


straight = gathered_grid()


def add_frame(grid) -> None:
    plotter = pv.Plotter(window_size=(480, 480), off_screen=True)
    skin_view(plotter, grid, f"{frames_angles[-1]:.0f} deg")
    # one camera for every frame, far enough for the whole leg straight (210 mm tall) and the
    # shank swung back (to y = -155 mm at 90 deg); at 420 mm the straight leg's ends and the
    # folded shank's cut end at 150 deg were out of the frame
    plotter.camera.position = (600.0, -30.0, 0.0)
    plotter.camera.focal_point = (0.0, -30.0, 0.0)
    plotter.camera.up = (0.0, 0.0, 1.0)
    frames.append(plotter.screenshot(return_img=True))
    plotter.close()


# -

# ### The flexion
#
# 50 steps of 3° at most; a step that fails is retried from the last converged state with half
# the increment (`solve_load_steps`). With `MATDEPTH_KNEE_TARGET_IT` set, a step control
# ({py:class}`fenics_matdepth.StepControl`) aims at that many Newton iterations a step: each
# next step is scaled by the square root of the target over the last step's iterations (never
# beyond 3°), and an attempt whose residual, over its last four iterations, falls too slowly to
# converge within `stop_iterations` is stopped there and cut, instead of running on to the
# iteration limit; it stops at most one attempt of a step, the retries run to the limit (at
# 105.5° the load path has a limit point, where cutting on does not help). It is off by
# default: up to 60° it changed little (docs/measurements.md), and it has not been measured to
# 150° yet.
# After each converged step the writer hook measures, writes
# the VTX files and renders an animation frame; `solve_load_steps` then saves the step to the
# checkpoint. The measurements so far are kept in `knee_steps.json` next to it, so that a
# resumed run (`--resume`) reports the whole history; its VTX file and animation start at the
# resumed angle (`knee_from_<degrees>.bp`). Creating a file `knee_stop` in the output folder
# stops the flexion at the last converged step; the demo then goes on to the pictures and the
# summary of that state.

# +
checkpoint = output / "knee_checkpoint.npz"
pressure_checkpoint = fm.Checkpoint(output / "knee_pressure.npz", V)
local_ids = imap.local_to_global(np.arange(imap.size_local + imap.num_ghosts, dtype=np.int32))


def save_pressure(t: float) -> None:
    """The augmented Lagrangian's nodal pressures (global numbering) as the first component of
    a P1 vector field, which `fm.Checkpoint` keys by vertex (any number of ranks reads it)."""
    field = np.zeros((local_ids.size, 3))
    field[:, 0] = augmented.pressure[local_ids]
    pressure_checkpoint.save({"pressure": field.ravel()}, load=t)


def load_pressure(t: float) -> None:
    arrays, meta = pressure_checkpoint.load()
    if abs(meta["load"] - t) > 1e-12:
        raise RuntimeError(
            f"{pressure_checkpoint.path} holds the pressures at load {meta['load']}, the "
            f"checkpoint is at {t}: the run stopped between the two writes; restart from 0"
        )
    owned = arrays["pressure"].reshape(-1, 3)[:n_owned, 0]
    pressure = np.zeros(imap.size_global)
    pressure[global_ids] = owned
    comm.Allreduce(MPI.IN_PLACE, pressure, op=MPI.SUM)  # each vertex is owned once
    augmented.pressure = pressure


steps_file = output / "knee_steps.json"
per_step: list[dict] = []
# the local relaxation's patches and the problem's Newton steps off the Dirichlet values, as
# counted at the last converged step
counts_before = {"patches": 0, "off": 0}
frames_angles: list[float] = []
attempts = {"count": 0, "tic": time.perf_counter()}
if resume:
    arrays, meta = fm.Checkpoint(checkpoint, V).load()
    # the predictor starts from the saved state: set_flexion at the saved angle returns it
    last["u"], last["angle"] = arrays["u"], meta["load"] * total_angle
    u.x.array[:] = arrays["u"]
    if augmented is not None:
        load_pressure(meta["load"])
    per_step = json.loads(steps_file.read_text()) if comm.rank == 0 else None
    per_step = [m for m in comm.bcast(per_step, root=0) if m["load"] <= meta["load"] + 1e-12]
    attempts["count"] = -1  # solve_load_steps sets the saved load once before the first step
    report(f"resuming from {np.degrees(meta['load'] * total_angle):.1f} deg ({checkpoint})")
timing_totals = dict.fromkeys(fm.system_assembler.TIMING_KEYS, 0.0)
body_field = fem.Function(Q, name="body")
body_field.x.array[Q.dofmap.list[:, 0]] = cell_body
body_field.x.scatter_forward()
with io.VTXWriter(comm, output / "knee_tags.bp", [body_field]) as tags_file:
    tags_file.write(0.0)
start_degrees = per_step[-1]["degrees"] if per_step else 0.0
vtx_name = f"knee_from_{start_degrees:.0f}.bp" if per_step else "knee.bp"
vtx = io.VTXWriter(comm, output / vtx_name, [u, depth])
vtx.write(start_degrees)
# the contact fields of each converged step (pressure, penetration, traction, slip, status: see
# docs/friction.md), for ParaView and pyvista
contact_file = io.XDMFFile(comm, output / vtx_name.replace(".bp", "_contact.xdmf"), "w")
contact_file.write_mesh(domain)


def largest_residual(count: int = 5) -> list:
    """The vertices with the largest residual of the last Newton iterate: (norm of the
    vertex's residual, body, reference position), gathered over the ranks (collective)."""
    r = problem.snes.getFunction()[0].array_r.reshape(-1, 3)[:n_owned]
    norms = np.linalg.norm(r, axis=1)
    top = np.argsort(norms)[::-1][:count]
    local = [
        (float(norms[v]), leg.BODIES[int(vertex_body[v])], np.round(X[v], 1).tolist()) for v in top
    ]
    merged = [c for part in comm.allgather(local) for c in part]
    return sorted(merged, key=lambda c: -c[0])[:count]


class ReportFailures:
    """The solver, reporting each failed attempt (why; the augmented Lagrangian's inner solves)
    before `solve_load_steps` cuts the step."""

    def __init__(self, problem):
        # (`problem`: the step control's rate test finds the ContactProblem through it)
        self.problem, self.u, self.contact = problem, problem.u, problem.contact

    def solve(self, raise_on_failure: bool = True):
        try:
            result = self.problem.solve(raise_on_failure=False)
        except (RuntimeError, FloatingPointError, PETSc.Error) as err:
            # `solve_load_steps` cuts the step on these too (an error in a SNES callback
            # reaches it as a PETSc.Error)
            report(f"    the step to {np.degrees(last['try']):.2f} deg failed: {str(err)[:600]}")
            raise
        if not result.converged:
            why = result.failure_message()
            if augmented is not None:
                why = augmented.failure_message(result)
                why += "; inner solves (Newton its, overlap/h): " + ", ".join(
                    f"({r.newton_iterations}, {r.overlap_h:.3f})" for r in augmented.history
                )
            report(f"    the step to {np.degrees(last['try']):.2f} deg failed: {why[:600]}")
            report(f"    where the residual is largest: {largest_residual()}")
            if raise_on_failure:
                raise RuntimeError(why)
        return result


def counting_set_flexion(t: float) -> None:
    if (output / "knee_stop").exists():
        raise fm.StopRequested(f"{output}/knee_stop exists")
    if per_step and per_step[-1]["degrees"] >= stop_degrees - 1e-9:
        raise fm.StopRequested(f"reached MATDEPTH_KNEE_STOP_DEGREES={stop_degrees:g}")
    attempts["count"] += 1
    last["try"] = t * total_angle
    if augmented is not None and al_reset:
        augmented.pressure = np.zeros_like(augmented.pressure)
    elif augmented is not None and al_carry != 1.0:
        # a fraction of the pressures of the last converged step (kept for the retries)
        if last.get("carried_from") != last["angle"]:
            last["carried"] = augmented.pressure.copy()
            last["carried_from"] = last["angle"]
        augmented.pressure = al_carry * last["carried"]
    set_flexion(t)


def after_step(t: float) -> None:
    last["before"] = (last["u"], last["angle"])
    last["u"], last["angle"] = u.x.array.copy(), t * total_angle
    for key, value in problem.timings.items():
        timing_totals[key] += value
    m = measure(t)
    m["load"] = t
    m["newton_iterations"] = int(problem.snes.getIterationNumber())
    if augmented is not None:
        al = augmented.diagnostics()
        m["newton_iterations"] = int(al["newton_iterations"])
        m["pressure_updates"] = int(al["updates"])
        m["max_pressure"] = float(al["max_pressure"])
        m["pressure_updates_stalled"] = bool(al["stalled"])
        save_pressure(t)
    m["cuts"] = attempts["count"] - 1
    if problem.relaxation is not None:  # the patches relaxed in the step (its cut attempts too)
        m["relaxed_patches"] = problem.relaxation.uses - counts_before["patches"]
        counts_before["patches"] = problem.relaxation.uses
    # the Newton steps taken with the tibia's dofs off their values (each attempt's first is
    # one; those after it are judged by the residual norm alone, and the relaxation waits)
    m["steps_off_dirichlet"] = problem.steps_off_dirichlet - counts_before["off"]
    counts_before["off"] = problem.steps_off_dirichlet
    m["seconds"] = time.perf_counter() - attempts["tic"]
    attempts["count"], attempts["tic"] = 0, time.perf_counter()
    per_step.append(m)
    if comm.rank == 0:
        steps_file.write_text(json.dumps(per_step))
    vtx.write(m["degrees"])
    for field in contact.fields().values():  # before solve_load_steps' advance()
        contact_file.write_function(field, m["degrees"])
    frames_angles.append(m["degrees"])
    grid = gathered_grid()
    if grid is not None:
        add_frame(grid)
    fx, fy, fz = m["patella_contact_force"]
    dx_, dy_, dz_ = m["patella_displacement"]
    stalled = " (stalled: the overlap left above the tolerance)"
    pressures = (
        f", {m['pressure_updates']} pressure updates"
        f"{stalled if m['pressure_updates_stalled'] else ''}, max pressure "
        f"{m['max_pressure']:.3f} MPa"
        if augmented is not None
        else ""
    )
    report(
        f"    {m['degrees']:6.1f} deg: penetration/h {m['penetration_over_h']:.3f}, "
        f"min det F {m['min_det_F']:.3f} ({m['min_det_F_body']} at "
        f"{np.round(m['min_det_F_at'], 0).tolist()}), "
        f"patella moved ({dx_:+.1f}, {dy_:+.1f}, {dz_:+.1f}) mm "
        f"turned {m['patella_rotation_degrees']:+.1f} deg, patella contact force "
        f"({fx:+.1f}, {fy:+.1f}, {fz:+.1f}) N, fold skin vertices in contact "
        f"{m['fold_skin_vertices_in_contact']}{pressures}"
        + (
            f", friction: {m['friction']['stick_points']:.0f} stick / "
            f"{m['friction']['slip_points']:.0f} slip points, dissipated "
            f"{m['friction']['friction_dissipation']:.3g} N mm"
            if m["friction"]
            else ""
        )
        + f"; deepest {m['deepest_contact']}"
    )


report(
    f"flexion to {total_degrees:g} deg in {num_steps} steps; penalty {penalty} MPa/mm; "
    f"augmented Lagrangian to {al_tol_h:g} h ({'off' if augmented is None else 'on'}); "
    + (
        f"step control: target {target_iterations}, stop at {stop_iterations} Newton iterations; "
        if target_iterations > 0
        else "step control off; "
    )
    + f"{comm.size} process(es)"
)
step_control = (
    fm.StepControl(target_iterations, stop_iterations=stop_iterations, min_scale=min_scale)
    if target_iterations > 0
    else None
)
tic = time.perf_counter()
failure = None
try:
    fm.solve_load_steps(
        ReportFailures(solver),
        counting_set_flexion,
        num_steps,
        writer=after_step,
        checkpoint=checkpoint,
        resume=checkpoint if resume else None,
        step_control=step_control,
    )
except fm.StopRequested as err:  # on request: the checkpoint holds the last step
    failure = str(err)
except RuntimeError as err:  # the history stops at the last converged step: report it
    failure = str(err)
solve_seconds = time.perf_counter() - tic
vtx.close()
contact_file.close()
reached = per_step[-1]["degrees"] if per_step else 0.0
report(f"reached {reached:.1f} of {total_degrees:g} deg in {solve_seconds:.1f} s")
if failure is not None:
    report(f"stopped: {failure[:2000]}")
# -

# ### Cost
#
# The paper's split (§6.3, 376 min on a 300 MHz R12000): force and stiffness 63 %, collision
# detection 22 %, linear solve 15 %. Here "force + stiffness" is the bulk assembly plus the
# contact pair kernels and their insertion, "contact update" the gather, tree refit and pair
# search, and the continuous collision detection of the Newton steps, "linear solve" the MUMPS
# factorisation (LDLᵀ or LU) and solve. Every solve counts (`problem.assembler.run_timings`):
# the failed attempts and the augmented Lagrangian's repeated solves as well as the converged
# steps' last solves (`problem.timings`, summed in `timing_totals`). What the three leave out
# (the line search's energies, the step control, the checks and output) is the rest of the
# steps' time.

# +
run_timings = problem.assembler.run_timings
force_stiffness = run_timings["bulk_assembly"] + run_timings["contact_assembly"]
collision = run_timings["contact_update"] + run_timings["ccd"]
linear = run_timings["linear_solve"]
measured = force_stiffness + collision + linear
split = {
    "force_stiffness": force_stiffness / measured if measured else 0.0,
    "contact_update": collision / measured if measured else 0.0,
    "linear_solve": linear / measured if measured else 0.0,
    "ccd": run_timings["ccd"] / measured if measured else 0.0,
}
converged_part = sum(timing_totals.values())
split["seconds"], split["converged_last_solves_seconds"] = measured, converged_part
report(
    f"time split: force + stiffness {100 * split['force_stiffness']:.0f} % (paper 63 %), "
    f"contact update {100 * split['contact_update']:.0f} % (paper 22 %; the continuous collision "
    f"detection of the Newton steps {100 * split['ccd']:.1f} % of all), linear solve "
    f"{100 * split['linear_solve']:.0f} % (paper 15 %) of {measured:.1f} s, every solve "
    f"({converged_part:.1f} s in the converged steps' last solves)"
)
if problem.relaxation is not None:
    r = problem.relaxation
    report(
        f"local relaxation: {r.uses} patches relaxed in {r.local_iterations} local Newton "
        f"iterations, {r.seconds:.1f} s"
    )
report(
    f"contact pair searches: {comm.allreduce(contact.pair_searches)} of the whole surface, "
    f"{comm.allreduce(contact.pair_search.partial_searches)} round the moved vertices only "
    "(summed over the processes)"
)
# -

# ### Figures
#
# On rank 0, with pyvista: the leg straight and bent (skin surface, Fig. 19), the patella's
# path over the femur, a cut-away at the last state coloured by material depth (Fig. 20
# right), a close-up of the fold behind the knee (Figs. 21-22), and the animation.

# The bodies in matplotlib's tab10 colours without its purple (one colour a body, named in the
# key), the depth in bands of a round width; the keys stand in narrow columns beside the two
# panels of a picture, where they cover none of the mesh.

# +
BODY_COLOURS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#8c564b", "#e377c2", "#7f7f7f",
                "#bcbd22", "#17becf"]  # fmt: skip


def by_body(grid) -> dict:
    """The bodies of ``grid``, each in its colour (BODY_COLOURS, the same in every picture),
    keyed by name; the key lists the bodies ``grid`` holds only (a close-up shows a few of the
    nine). Adds the cell data it colours by ("body shown": 1, 2, ... over the bodies present)
    to ``grid``."""
    tags = np.unique(grid.cell_data["body"])
    grid.cell_data["body shown"] = np.searchsorted(tags, grid.cell_data["body"]) + 1
    return {
        "scalars": "body shown",
        "cmap": [BODY_COLOURS[tag - 1] for tag in tags],
        "clim": [0.5, len(tags) + 0.5],
        "n_colors": len(tags),
        "annotations": {i + 1.0: leg.BODIES[tag].replace("_", " ") for i, tag in enumerate(tags)},
        "show_scalar_bar": False,
    }


def by_depth(grid) -> dict:
    """Material depth in 5 to 12 bands of 1, 2 or 5 times a power of ten mm, from 0 to the
    first band edge above the largest depth in ``grid``: the key's labels are round numbers."""
    width, bands = round_bands(grid.point_data["material depth (mm)"].max(), 12)
    return {"scalars": "material depth (mm)", "cmap": "viridis", "n_colors": bands,
            "clim": [0.0, bands * width], "show_scalar_bar": False}  # fmt: skip


def keyed_plotter():
    """Two panels (columns 1 and 2) with a column for a colour key on either side."""
    return pv.Plotter(
        shape=(1, 4), col_weights=[1, 3, 3, 1], window_size=(1560, 640), off_screen=True
    )


def add_key(plotter, column: int, actor, title: str) -> None:
    """The colour key of ``actor`` (a mesh coloured by body or by depth) in ``column``: the
    bodies by name, the depth bands with a label at every edge."""
    plotter.subplot(0, column)
    lookup = actor.mapper.lookup_table
    named = lookup.GetNumberOfAnnotatedValues() > 0
    bar = plotter.add_scalar_bar(
        title, mapper=actor.mapper, vertical=True, position_x=0.06 if named else 0.35,
        position_y=0.1, width=0.15, height=0.75, title_font_size=16, label_font_size=14,
        fmt="%g", n_labels=0 if named else lookup.n_values + 1,
    )  # fmt: skip
    bar.SetVerticalTitleSeparation(10)  # else the title touches the top label
    if named:  # the names to the right of the bar, where VTK puts the tick labels
        bar.SetTextPositionToPrecedeScalarBar()


# -

# +
bent = gathered_grid()
touching = fold_touching()
if comm.rank == 0 and pv is not None and bent is not None:
    plotter = pv.Plotter(shape=(1, 2), window_size=(1200, 640), off_screen=True)
    plotter.subplot(0, 0)
    skin_view(plotter, straight, "straight (reference)")
    plotter.subplot(0, 1)
    skin_view(plotter, bent, f"flexed {reached:.0f} deg")
    plotter.link_views()
    # one camera that takes in both legs: fitted to the straight leg alone, it cut off the
    # shank folded back past the thigh
    plotter.reset_camera(bounds=pv.PolyData(np.vstack([straight.points, bent.points])).bounds)
    plotter.camera.zoom(1.1)
    plotter.screenshot(output / "knee_skin.png")
    plotter.close()

    # the patella's path over the femur (lateral and frontal views)
    path = np.array([patella_X.mean(axis=0)] + [m["patella_centroid"] for m in per_step])
    femur = bent.extract_cells(np.flatnonzero(bent.cell_data["body"] == leg.FEMUR))
    patella = bent.extract_cells(np.flatnonzero(bent.cell_data["body"] == leg.PATELLA))
    patella0 = straight.extract_cells(np.flatnonzero(straight.cell_data["body"] == leg.PATELLA))
    plotter = pv.Plotter(shape=(1, 2), window_size=(1200, 640), off_screen=True)
    for i, (view, title) in enumerate(
        (((1.0, 0.0, 0.0), "from the side"), ((0.0, 1.0, 0.0), "from the front"))
    ):
        plotter.subplot(0, i)
        plotter.add_mesh(femur.extract_surface(), color="ivory", smooth_shading=True)
        plotter.add_mesh(patella0.extract_surface(), color="lightblue", opacity=0.5)
        plotter.add_mesh(patella.extract_surface(), color="royalblue")
        if len(path) > 1:
            plotter.add_mesh(pv.lines_from_points(path), color="red", line_width=4)
        plotter.add_points(path, color="red", point_size=8, render_points_as_spheres=True)
        add_title(plotter, title)
        plotter.view_vector(view, (0.0, 0.0, 1.0))
        # centred on the path, looking along the view still (moving the focal point alone
        # turned the view)
        camera = plotter.camera
        shift = path.mean(axis=0) - np.array(camera.focal_point)
        camera.position = tuple(camera.position + shift)
        camera.focal_point = tuple(camera.focal_point + shift)
        plotter.renderer.reset_camera_clipping_range()
    plotter.subplot(0, 0)
    plotter.add_text(
        f"patella straight (pale) and at {reached:.0f} deg (blue),\nred: the path of its centroid",
        position=(0.01, 0.02), viewport=True, font_size=9,
    )  # fmt: skip
    plotter.screenshot(output / "knee_patella_path.png")
    plotter.close()

    # cut-away at the last state: the cells whose reference centroid lies at x < 0
    centres = bent.copy()
    centres.points = bent.point_data["reference"]
    half = bent.extract_cells(np.flatnonzero(centres.cell_centers().points[:, 0] < 0.0))
    plotter = keyed_plotter()
    plotter.subplot(0, 1)
    depth_actor = plotter.add_mesh(half, **by_depth(half))
    add_title(plotter, f"cut-away at {reached:.0f} deg: material depth")
    plotter.view_vector((1.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    plotter.subplot(0, 2)
    body_actor = plotter.add_mesh(half, show_edges=True, **by_body(half))
    add_title(plotter, "bodies")
    plotter.view_vector((1.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    plotter.link_views(views=[1, 2])
    add_key(plotter, 0, depth_actor, "material\ndepth (mm)")
    add_key(plotter, 3, body_actor, "body")
    plotter.screenshot(output / "knee_cutaway.png")
    plotter.close()

    # close-up of the fold behind the knee, cut at x = 0, mesh edges shown: the bodies (left)
    # and the material depth (right), the fold's skin vertices in self-contact within 6 mm of
    # the cut marked in red on it
    crease = np.array([0.0, -geometry.outer_radius(geometry.crease_level), geometry.crease_level])
    ref = centres.cell_centers().points
    near = np.linalg.norm(ref - crease, axis=1) < 45.0
    fold = bent.extract_cells(np.flatnonzero(near & (ref[:, 0] < 0.0)))
    touching = touching[np.abs(touching[:, 0]) < 6.0].copy()
    touching[:, 0] = fold.bounds[1] + 1.0  # in front of the cut
    print(f"the fold's skin vertices in self-contact within 6 mm of the cut: {len(touching)}")
    plotter = keyed_plotter()
    actors = []
    for i, (look, title) in enumerate(
        (
            (by_body(fold), f"the fold behind the knee at {reached:.0f} deg: bodies"),
            (by_depth(fold), "material depth; red: skin in self-contact"),
        )
    ):
        plotter.subplot(0, i + 1)
        actors.append(plotter.add_mesh(fold, show_edges=True, **look))
        if len(touching):
            plotter.add_points(touching, color="red", point_size=9, render_points_as_spheres=True)
        add_title(plotter, title)
        plotter.view_vector((1.0, 0.0, 0.0), (0.0, 0.0, 1.0))
        if len(touching):  # centred on the fold's contact, from as far as the whole cut
            camera = plotter.camera
            offset = np.subtract(camera.position, camera.focal_point)
            camera.focal_point = tuple(touching.mean(axis=0))
            camera.position = tuple(touching.mean(axis=0) + offset)
            plotter.renderer.reset_camera_clipping_range()
        plotter.camera.zoom(1.2)  # close, with the femur's end below it still in the frame
    plotter.link_views(views=[1, 2])
    add_key(plotter, 0, actors[0], "body")
    add_key(plotter, 3, actors[1], "material\ndepth (mm)")
    plotter.screenshot(output / "knee_fold.png")
    plotter.close()
    for name in ("knee_skin.png", "knee_patella_path.png", "knee_cutaway.png", "knee_fold.png"):
        show_image(output / name)
    if frames:
        write_animation(frames, output / "knee_flexion.gif", fps=8)
# -

# ### Summary
#
# Iterations, cuts and the per-step measurements, for the tests and the documentation.

# +
iterations = [m["newton_iterations"] for m in per_step]
summary = {
    "quick": quick,
    "resolution": resolution,
    "processes": comm.size,
    "mesh": stats,
    "penalty": penalty,
    "augmented_tol_h": al_tol_h,
    "augmented_max_iterations": al_max_it,
    "augmented_stall_rtol": al_stall,
    # the steps that ended on stalled pressure updates (their overlap above the tolerance)
    "stalled_steps": sum(bool(m.get("pressure_updates_stalled")) for m in per_step),
    "fibre_toe": fibre_toe,
    "keep_left_pairs": keep_left,
    "step_limit_edges": step_limit,
    "uphill_step": uphill_step,
    # the Newton steps reversed at a saddle, over every solve
    "reversed_steps": problem.reversed_steps,
    "steps_off_dirichlet": problem.steps_off_dirichlet,
    # the shifted Newton steps' factorisations (every rung tried), over every solve
    "shift_factorisations": problem.shift_factorisations,
    "relaxation": None
    if problem.relaxation is None
    else {
        "patches": problem.relaxation.uses,
        "local_iterations": problem.relaxation.local_iterations,
        "seconds": problem.relaxation.seconds,
    },
    "target_iterations": target_iterations,
    "stop_iterations": stop_iterations,
    "min_scale": min_scale,
    "max_newton_iterations": max_newton,
    "newton_atol": newton_atol,
    "pseudo_transient": pseudo_transient,
    "target_degrees": total_degrees,
    "num_steps": num_steps,
    "reached_degrees": reached,
    "completed": failure is None,
    "failure": failure,
    "resumed": resume,
    "steps": per_step,
    "iterations": iterations,
    "cuts": [m["cuts"] for m in per_step],
    "solve_seconds": solve_seconds,
    "time_split": split,
    "seconds": time.perf_counter() - start,
}
if comm.rank == 0:
    (output / "knee.json").write_text(json.dumps(summary, indent=1))
    print(f"pictures and results in {output}")
report(f"demo_knee: {summary['seconds']:.1f} s on {comm.size} process(es)")
if failure is not None:
    raise SystemExit(f"the flexion stopped at {reached:.1f} deg (see {output / 'knee.json'})")
# -
