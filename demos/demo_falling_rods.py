# ---
# jupyter:
#   jupytext:
#     text_representation:
#       extension: .py
#       format_name: light
#       format_version: '1.5'
#       jupytext_version: 1.16.0
# ---

# # Falling rods: implicit dynamics with contact (Hirota, Fisher & State 2003, Fig. 24)
#
# This demo is implemented in {download}`demo_falling_rods.py`. It reproduces the paper's
# dynamic example: "a 7 x 5 array of rods mounted on a 45°-slanted foundation. At the beginning
# of the simulation, all the objects are stationary. Gravity then pulls the rods toward the
# ground and causes complex collisions and sliding contacts." It shows how to:
#
# - write the equation of motion in UFL with the time integrator's acceleration and velocity
#   ({py:class}`fenics_matdepth.Newmark`), and pass the step's incremental potential to
#   {py:class}`fenics_matdepth.ContactProblem` for its energy line search;
# - step in time with {py:func}`fenics_matdepth.solve_time_steps`: dt is halved when a step
#   fails and grows back, one line of progress per step, energies per step;
# - render frames off-screen with pyvista (gathered on rank 0 under MPI), join them into an
#   animation, and plot the energies.
#
# ## The physics
#
# Every body is a compressible neo-Hookean solid,
# $\psi = \frac{\mu}{2}(\bar I_1 - 3) + \frac{\kappa}{4}(J^2 - 1 - 2\ln J)$, of density $\rho$.
# The rods' bases are clamped to the foundation, which is clamped too (a rigid support that
# still has a material depth, so the rods feel it as an obstacle). Rods touch their neighbours
# and the foundation through the material-depth penalty energy $E_c(\mathbf u)$. With
# mass-proportional damping $c$ (an air drag that brings the scene to rest), the equation of
# motion is, for every test function $\mathbf v$,
#
# $$
# \int_\Omega \rho\, \ddot{\mathbf u} \cdot \mathbf v
# + c \rho\, \dot{\mathbf u} \cdot \mathbf v
# + \mathbf P(\mathbf u) : \nabla \mathbf v \,\mathrm{d}X
# + \frac{\partial E_c}{\partial \mathbf u} \cdot \mathbf v
# = \int_\Omega \rho\, \mathbf g \cdot \mathbf v \,\mathrm{d}X .
# $$
#
# Newmark's method ($\beta = 0.3025$, $\gamma = 0.6$: second-order accurate for the slow
# motion, dissipative for the stiff contact modes that a time step cannot resolve) turns
# each time step into a nonlinear problem for $\mathbf u_{n+1}$, solved by Newton's method with
# the contact force evaluated at $\mathbf u_{n+1}$ like every other internal force (the paper's
# "implicit dynamic analysis", §3.1).
#
# ## Implementation
#
# `MATDEPTH_DEMO_QUICK=1` runs a reduced scene (3 x 2 rods, a shorter time) for the test suite;
# `MATDEPTH_DEMO_OUTPUT` moves the output folder (default `demos/output`);
# `MATDEPTH_RODS_MU=0.3` adds Coulomb friction with that coefficient
# ({py:class}`fenics_matdepth.Coulomb`, {doc}`/friction`): the contact fields (pressure,
# penetration, traction, slip, stick/slip status) then go to the XDMF file with every step,
# and a last picture shows the status (`MATDEPTH_RODS_T_END` sets the end time);
# `MATDEPTH_RODS_ARRAY=7x1` runs that array of rods (rows downhill x columns) with the full
# scene's mesh sizes, `MATDEPTH_RODS_YOUNGS` sets the Young's modulus (Pa, default 20e3) and
# `MATDEPTH_RODS_PENALTY_FACTOR` the penalty's factor on it (default 10; {doc}`/friction`,
# "Demos", has the runs that use them);
# `MATDEPTH_RODS_GAMMA=0.5 MATDEPTH_RODS_CONTACT_FORCE=discrete_gradient` steps with average
# acceleration and the contact force whose work is the change of the contact energy
# ({doc}`/dynamics`, "Energy at impacts").

# +
from __future__ import annotations

import json
import os
import time
from pathlib import Path

from mpi4py import MPI

import numpy as np
import ufl
from dolfinx import fem, io, plot

import fenics_matdepth as fm
from fenics_matdepth.plotting import (
    gather_vtk_grid,
    offscreen_pyvista,
    output_folder,
    show_image,
    write_animation,
)

# the model builders of meshes/: run with the repository on PYTHONPATH
from meshes import rods

start = time.perf_counter()
comm = MPI.COMM_WORLD
quick = os.environ.get("MATDEPTH_DEMO_QUICK", "0") not in ("", "0")
try:
    here = Path(__file__).resolve().parent
except NameError:  # in a notebook
    here = Path.cwd()
output = output_folder(comm, here / "output")  # or $MATDEPTH_DEMO_OUTPUT


def report(message: str) -> None:
    if comm.rank == 0:
        print(message, flush=True)


# -

# ### The scene
#
# SI units. The mesh script `meshes/rods.py` builds the scene with gmsh: square rods of side
# 1 cm and length 8 cm, 2.5 cm apart, on a 4 cm thick foundation; then tilts everything by
# 45° about the $y$ axis. Each rod is a structured mesh, 2 x 2 cells across (so it has interior
# vertices, where its material depth is positive) and 6 layers along; the foundation is
# meshed freely with 20 mm elements (15 mm in the reduced run).

# +
if quick:
    geometry = rods.RodsGeometry(rows=2, columns=1, layers=6, foundation_size=0.015)
    t_end = 0.2  # s
else:
    geometry = rods.RodsGeometry(layers=6, foundation_size=0.02)
    t_end = 0.3  # s
if os.environ.get("MATDEPTH_RODS_ARRAY"):  # e.g. "7x1": one column of the full scene's rows
    rows, columns = (int(n) for n in os.environ["MATDEPTH_RODS_ARRAY"].lower().split("x"))
    geometry = rods.RodsGeometry(rows=rows, columns=columns, layers=6, foundation_size=0.02)
t_end = float(os.environ.get("MATDEPTH_RODS_T_END", t_end))
friction_mu = float(os.environ.get("MATDEPTH_RODS_MU", "0"))
domain, cell_tags = rods.rods_mesh(comm, geometry)
V = fem.functionspace(domain, ("Lagrange", 1, (3,)))
num_tets = domain.topology.index_map(3).size_global
num_vertices = V.dofmap.index_map.size_global
h = geometry.side / geometry.across  # the rods' element size across
report(
    f"mesh: {geometry.rows} x {geometry.columns} rods, {num_tets} tetrahedra, "
    f"{num_vertices} vertices"
)
# -

# ### Material, gravity, damping and supports
#
# A soft gel: $E = 20$ kPa, $\nu = 0.3$, $\rho = 1000$ kg/m³. Under its own weight a rod
# bends like a cantilever with a tip deflection of the order of its length, so the rods fall
# over onto their downhill neighbours and the foundation. Mass-proportional damping
# $c = 2\ \mathrm{s}^{-1}$. The foundation and the rods' bases, 1 mm above its top face, are
# clamped.

# +
youngs_modulus, poisson_ratio, density = 20e3, 0.3, 1000.0  # Pa, -, kg/m^3
youngs_modulus = float(os.environ.get("MATDEPTH_RODS_YOUNGS", youngs_modulus))
gravity = np.array([0.0, 0.0, -9.81])  # m/s^2
damping = 2.0  # 1/s
mu, kappa = fm.materials.shear_bulk_from_youngs_poisson(youngs_modulus, poisson_ratio)

normal = geometry.rotation()[:, 2]  # the foundation's top-face normal, the rods' axis


def height(x: np.ndarray) -> np.ndarray:
    """Height of reference points (3, n) above the foundation's top face."""
    return normal @ x


support = fem.locate_dofs_geometrical(
    V, lambda x: height(x) <= geometry.base_gap + 1e-9 * geometry.length
)
bcs = [fem.dirichletbc(np.zeros(3), support, V)]
# -

# ### The equation of motion in UFL
#
# The integrator holds the last converged displacement, velocity and acceleration; its
# `acceleration` and `velocity` are UFL expressions of the unknown `u`. The incremental
# potential (inertia, damping, strain energy, gravity; the contact energy is added by the
# problem) has the residual as its derivative, so the line search can work on the energy
# (`energy=`, as the tests of `tests/test_dynamics.py` do). This demo judges steps by the
# residual norm, as the concave-corner demo does; `MATDEPTH_RODS_ENERGY_LINE_SEARCH=1` passes
# the incremental potential instead. (A first version of the scene, with the rods' base faces
# lying in the foundation's top face, failed its first steps with either merit function; the
# failures went away when the bases were lifted 1 mm above the face (coplanar faces). The
# energy merit has not been measured again on the full scene.) The penalty is proposed
# from the stiffness and the rods' element size.

# +
u = fem.Function(V, name="displacement")
v = ufl.TestFunction(V)
dt = float(os.environ.get("MATDEPTH_RODS_DT", "0.01"))  # s: the nominal step
# MATDEPTH_RODS_GAMMA = 0.5 (average acceleration, no numerical damping) with
# MATDEPTH_RODS_CONTACT_FORCE = discrete_gradient: contact that creates no energy at impacts
gamma = float(os.environ.get("MATDEPTH_RODS_GAMMA", "0.6"))
integrator = fm.Newmark(u, dt, beta=(gamma + 0.5) ** 2 / 4, gamma=gamma, rho=density)
contact_force = os.environ.get("MATDEPTH_RODS_CONTACT_FORCE") or None
F_def = ufl.variable(ufl.Identity(3) + ufl.grad(u))
psi = fm.materials.neo_hookean(F_def, mu, kappa)
g = fem.Constant(domain, gravity)
dx = ufl.dx(domain=domain)
strain_energy = psi * dx
gravity_work = density * ufl.inner(g, u) * dx
residual = (
    integrator.inertia(v, damping=damping)
    + ufl.inner(ufl.diff(psi, F_def), ufl.grad(v)) * dx
    - density * ufl.inner(g, v) * dx
)
incremental = integrator.incremental_energy(strain_energy - gravity_work, damping=damping)

depth = fm.material_depth(domain)
depth.name = "material_depth"
penalty_factor = float(os.environ.get("MATDEPTH_RODS_PENALTY_FACTOR", "10"))
penalty = fm.propose_penalty(domain, youngs_modulus, factor=penalty_factor, h=h)
friction = fm.Coulomb(friction_mu) if friction_mu > 0.0 else None
contact = fm.ContactOperator(u, depth, penalty, friction=friction)
use_energy = os.environ.get("MATDEPTH_RODS_ENERGY_LINE_SEARCH", "0") not in ("", "0")
problem = fm.ContactProblem(
    residual, u, contact, bcs=bcs, energy=incremental if use_energy else None,
    petsc_options_prefix="falling_rods_", petsc_options={"snes_rtol": 1e-6, "snes_atol": 1e-9},
    ccd=os.environ.get("MATDEPTH_RODS_CCD", "1") not in ("", "0"),
)  # fmt: skip
report(f"penalty {penalty:.3g} Pa/m; {contact.num_bodies} bodies")
# -

# ### Pictures
#
# Every few steps the deformed mesh is gathered on rank 0 and rendered off-screen: the
# foundation in grey, the rods coloured by how far they have moved. One camera and one colour
# scale for every frame, so that the frames make an animation.

# +
cells, types, points = plot.vtk_mesh(V)  # the points are V's local vertices, in dof order
n_points = points.shape[0]
# the foundation is the body (connected component) of the vertices below its top face
local = V.dofmap.index_map.local_to_global(np.arange(n_points, dtype=np.int32))
body = contact.body_of_vertex[local]
below = height(points.T) < -1e-9 * geometry.length
foundation_body = comm.allreduce(int(body[below].max(initial=-1)), op=MPI.MAX)
is_rod = (body != foundation_body).astype(float)
pyvista = offscreen_pyvista() if comm.rank == 0 else None
frames: list[str] = []
frame_every = 2 if quick else 4
x0, x1, y0, y1 = geometry.foundation_box
span = max(x1 - x0, y1 - y0)
centre = geometry.rotation() @ np.array([0.5 * (x0 + x1), 0.5 * (y0 + y1), 0.3 * geometry.length])
view = np.array([-0.2, -1.0, 0.45])
# far enough for the upright rods at t = 0 and the foundation's lowest corner, with a margin
camera = centre + 2.6 * span * view / np.linalg.norm(view)


def render(path: Path, t: float) -> None:
    """Render the current state to ``path`` (collective: every rank sends its part)."""
    displacement = u.x.array.reshape(-1, 3)[:n_points]
    grid = gather_vtk_grid(comm, cells, types, points + displacement, displacement, is_rod)
    if comm.rank != 0 or pyvista is None:
        return
    all_cells, all_types, all_points, all_displacement, rod_points = grid
    mesh = pyvista.UnstructuredGrid(all_cells, all_types, all_points)
    mesh.point_data["displacement (m)"] = np.linalg.norm(all_displacement, axis=1)
    rods_part = mesh.extract_points(rod_points > 0.5, adjacent_cells=False)
    base = mesh.extract_points(rod_points < 0.5, adjacent_cells=False)
    plotter = pyvista.Plotter(window_size=(960, 720), off_screen=True)
    plotter.set_background("white")
    plotter.add_mesh(base.extract_surface(), color="#b9b4aa", show_edges=True, edge_color="#8d877c")
    plotter.add_mesh(
        rods_part.extract_surface(), scalars="displacement (m)", cmap="plasma",
        clim=[0.0, geometry.length], show_edges=False,
        scalar_bar_args={"title": "displacement (m)", "color": "black", "vertical": True,
                         "position_x": 0.05, "position_y": 0.3, "width": 0.05, "height": 0.45,
                         "title_font_size": 16, "label_font_size": 16, "fmt": "%g"},
    )  # fmt: skip
    # upright at the left, where the scene leaves room: lying at the bottom, the bar covered
    # the foundation and its title the labels
    plotter.scalar_bar.SetVerticalTitleSeparation(10)
    plotter.add_text(f"t = {t:.3f} s", font_size=12, color="black")
    plotter.camera.focal_point = tuple(centre)
    plotter.camera.position = tuple(camera)
    plotter.camera.up = (0.0, 0.0, 1.0)
    plotter.screenshot(str(path))
    plotter.close()


def frame(record: fm.TimeStep | None) -> None:
    step = 0 if record is None else record.step
    if step % frame_every:
        return
    path = output / f"falling_rods_{step:04d}.png"
    render(path, 0.0 if record is None else record.t)
    if comm.rank == 0 and pyvista is not None:
        frames.append(str(path))


# -

# ### Time stepping
#
# From rest, with gravity on at $t = 0$ (the initial acceleration is computed from the
# equation of motion: gravity against the clamped supports). Steps of 10 ms; a step that
# fails, or that lets a surface sink deeper than a third of the rods' element size into
# another body, is retried from the last converged state with half the step, and the step
# grows back after two clean steps. The displacement and velocity go to an XDMF file that
# ParaView opens.

# +
integrator.initial(residual=residual, contact=contact, bcs=bcs)
velocity = integrator.v_prev
xdmf = io.XDMFFile(comm, output / "falling_rods.xdmf", "w")
xdmf.write_mesh(domain)
xdmf.write_function(depth)
last_status = fem.Function(V)  # the last step's stick/slip status (in component 0)


def write(t: float) -> None:
    xdmf.write_function(u, t)
    xdmf.write_function(velocity, t)
    if friction is not None:  # the converged step's contact fields (before advance())
        fields = contact.fields()
        for field in fields.values():
            xdmf.write_function(field, t)
        # kept for the picture: after the run's last advance() every slip is 0 again
        last_status.sub(0).interpolate(fields["status"])


frame(None)
history = fm.solve_time_steps(
    problem, integrator, t_end, dt, writer=write, on_step=frame, min_dt=dt / 64,
    strain_energy=strain_energy, external_work=gravity_work, max_penetration=h / 3,
    contact_force=contact_force,
)  # fmt: skip
xdmf.close()
steps = history[1:]
iterations = np.array([r.iterations for r in steps])
cuts = sum(r.cuts for r in steps)
max_penetration = max(r.max_penetration for r in steps)
report(
    f"{len(steps)} steps to t = {history[-1].t:.3f} s, {cuts} cuts; Newton iterations per step "
    f"median {np.median(iterations):.0f}, max {iterations.max()}; max penetration "
    f"{max_penetration:.3e} m = {max_penetration / h:.3f} h; most active pairs "
    f"{max(r.active_pairs for r in steps)}"
)
# -

# With friction, the stick/slip status of the last step on the deformed surfaces: 0 open,
# 1 stick, 2 slip (the rods at rest stick; the vertices of both surfaces of a contact show it).

# +
if friction is not None:
    values = last_status.x.array.reshape(-1, 3)[:n_points, 0]
    grid = gather_vtk_grid(comm, cells, types, points + u.x.array.reshape(-1, 3)[:n_points], values)
    if comm.rank == 0 and pyvista is not None:
        status_mesh = pyvista.UnstructuredGrid(*grid[:3])
        status_mesh.point_data["status"] = grid[3]
        plotter = pyvista.Plotter(window_size=(960, 720), off_screen=True)
        plotter.set_background("white")
        plotter.add_mesh(
            status_mesh.extract_surface(), scalars="status", cmap=["#d9d9d9", "#1f77b4", "#d62728"],
            clim=[0, 2], show_edges=False,
            scalar_bar_args={"title": "0 open, 1 stick, 2 slip", "color": "black", "n_labels": 3,
                             "fmt": "%.0f"},
        )  # fmt: skip
        plotter.add_text(f"mu = {friction_mu:g}, t = {history[-1].t:.3f} s", color="black")
        plotter.camera.focal_point = tuple(centre)
        plotter.camera.position = tuple(camera)
        plotter.camera.up = (0.0, 0.0, 1.0)
        plotter.screenshot(str(output / "falling_rods_status.png"))
        plotter.close()
        show_image(output / "falling_rods_status.png")
# -

# ### Energies
#
# Kinetic, strain and contact energy, the work done by gravity, and what the damping and the
# numerical dissipation took: the total $K + W_s + E_c - W_g$ decreases from 0.

# +
t = np.array([r.t for r in history])
kinetic = np.array([r.kinetic_energy for r in history])
strain = np.array([r.strain_energy for r in history])
contact_energy = np.array([r.contact_energy for r in history])
work = np.array([r.external_work for r in history])
total = np.array([r.total_energy for r in history])
if comm.rank == 0:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FormatStrFormatter

    # dt, Newton iterations and active pairs have their own panels and axes: one log axis
    # shared by milliseconds and counts had no label, and could not show zero pairs
    fig, (top, middle, bottom) = plt.subplots(
        3, 1, figsize=(7, 7.5), sharex=True, height_ratios=(2.2, 1.0, 1.6)
    )
    top.plot(t, 1e3 * work, label="work of gravity")
    top.plot(t, 1e3 * strain, label="strain energy")
    top.plot(t, 1e3 * kinetic, label="kinetic energy")
    top.plot(t, 1e3 * contact_energy, label="contact energy")
    top.plot(t, 1e3 * -total, "k--", label="dissipated (damping, numerical)")
    top.set_ylabel("energy (mJ)")
    top.legend(fontsize=8)
    top.grid(alpha=0.3)
    step_ms = np.array([1e3 * r.dt for r in steps])
    middle.plot(t[1:], step_ms, ".-")
    # a log2 axis ticked at the halvings of the nominal step, which is what a cut does
    middle.set_yscale("log", base=2)
    halvings = np.arange(int(np.ceil(np.log2(1e3 * dt / step_ms.min()) - 1e-9)) + 1)
    middle.set_yticks(1e3 * dt / 2.0**halvings, [f"{1e3 * dt / 2.0**k:g}" for k in halvings])
    middle.minorticks_off()
    middle.set_ylim(step_ms.min() / 1.6, 1.6 * step_ms.max())
    middle.set_ylabel("time step (ms)")
    middle.grid(alpha=0.3)
    # symlog: linear from 0 to 1, so that a step without contact sits on the 0 tick
    bottom.plot(t[1:], iterations, "s", markersize=3, label="Newton iterations")
    pairs = [r.active_pairs for r in steps]
    bottom.plot(t[1:], pairs, ".-", label="active pairs")
    bottom.set_yscale("symlog", linthresh=1.0, linscale=0.5)
    # below 0 by a little, so that the markers at 0 are not cut by the frame, and up to the
    # next power of ten, so that the largest count lies below a labelled tick
    bottom.set_ylim(-0.4, 10.0 ** np.ceil(np.log10(max(10, *iterations, *pairs))))
    bottom.yaxis.set_major_formatter(FormatStrFormatter("%g"))
    bottom.set_ylabel("count per step")
    bottom.set_xlabel("time (s)")
    bottom.legend(fontsize=8)
    bottom.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(output / "falling_rods_energy.png", dpi=120)
    plt.close(fig)
    if frames:
        write_animation(frames, output / "falling_rods.gif", fps=10)
        show_image(frames[-1])
    show_image(output / "falling_rods_energy.png")
# -

# A summary for the tests and the documentation:

# +
seconds = time.perf_counter() - start
summary = {
    "quick": quick,
    "processes": comm.size,
    "rods": [geometry.rows, geometry.columns],
    "tetrahedra": num_tets,
    "vertices": num_vertices,
    "penalty": penalty,
    "element_size": h,
    "length": geometry.length,
    "steps": len(steps),
    "cuts": cuts,
    "truncations": sum(r.truncations for r in steps),
    "t_end": history[-1].t,
    "iterations": iterations.tolist(),
    "dt": [r.dt for r in steps],
    "active_pairs": [r.active_pairs for r in steps],
    "max_penetration": [r.max_penetration for r in steps],
    "time": t.tolist(),
    "kinetic": kinetic.tolist(),
    "strain": strain.tolist(),
    "contact": contact_energy.tolist(),
    "gravity_work": work.tolist(),
    "total": total.tolist(),
    "max_displacement": comm.allreduce(
        float(np.linalg.norm(u.x.array.reshape(-1, 3), axis=1).max(initial=0.0)), op=MPI.MAX
    ),
    "frames": [Path(f).name for f in frames],
    "mu": friction_mu,
    "friction": {
        k: [r.diagnostics.get(k) for r in steps]
        for k in ("friction_dissipation", "stick_points", "slip_points")
    },
    "rod_speed": comm.allreduce(
        float(
            np.linalg.norm(velocity.x.array.reshape(-1, 3)[:n_points][is_rod > 0.5], axis=1).max(
                initial=0.0
            )
        ),
        op=MPI.MAX,
    ),
    "seconds": seconds,
}
if comm.rank == 0:
    (output / "falling_rods.json").write_text(json.dumps(summary, indent=1))
    print(f"pictures and results in {output}")
report(f"demo_falling_rods: {seconds:.1f} s on {comm.size} process(es)")
# -
