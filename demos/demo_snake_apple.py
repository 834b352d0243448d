# ---
# jupyter:
#   jupytext:
#     text_representation:
#       extension: .py
#       format_name: light
#       format_version: '1.5'
#       jupytext_version: 1.16.0
# ---

# # A snake swallows an apple: contact inside a soft tube stretched several-fold
#
# This demo is implemented in {download}`demo_snake_apple.py`. It redoes the animation of
# Hirota, Fisher & State (2003), section 7, Fig. 23: a snake swallows an apple. It shows how to
#
# - mesh two bodies of different materials in one DOLFINx mesh with gmsh
#   (`meshes/snake.py`) and give each its own strain energy through cell tags, `dx(tag)`;
# - drive one body by prescribing the motion of a region well inside it, with
#   {py:func}`fenics_matdepth.solve_load_steps` cutting the load steps automatically;
# - follow large-stretch contact on the inner surface of a soft tube: per step the Newton
#   iterations, the active contact pairs, the penetration, the smallest $\det F$ and the tube's
#   circumferential stretch;
# - render frames off-screen with pyvista (opaque, and with the snake translucent so that the
#   apple shows inside), join them into a row picture and an animation, and write the motion
#   for ParaView (VTX).
#
# ## The physics
#
# The snake is a soft hyperelastic tube: its lumen (3.5 mm in radius) is much narrower than the
# apple (10 mm in radius), so where the apple passes, the wall has to stretch around it by a
# factor of 2.9 at its inner surface. Its head is a funnel that opens wider than the apple (a
# snake's jaws open very wide), its tail is closed. The apple is a ball twenty times stiffer than
# the snake. Both are neo-Hookean,
# $\psi = \frac{\mu}{2}(\bar I_1 - 3) + \frac{\kappa}{4}(J^2 - 1 - 2\ln J)$.
#
# Contact is the material-depth penalty of the paper: every vertex carries its distance to the
# boundary in the reference configuration, $d$, interpolated linearly in each tetrahedron; where
# a boundary triangle of one body has entered a tetrahedron of the other, the energy
# $\frac{\varepsilon}{2}\int_{T \cap K} g_K^2\,\mathrm{d}A$ pushes it back out. Here both
# directions act: the apple's surface triangles entering the snake's wall, and the wall's inner
# triangles entering the apple. The contact is frictionless, so the apple can only push the wall
# outwards and along the axis: it opens the throat like a wedge.
#
# **The motion.** Seen from the snake's head, swallowing moves the prey into the body. The
# snake's mouth (the annular end face of the funnel) is held; the apple's core, a ball of 4 mm
# radius at its centre, is moved along the snake's axis, from in front of the throat to deep in
# the body, in quasi-static load steps. The rest of the apple and the whole snake (its tail
# included) follow from equilibrium. Holding the head rather than the tail keeps the wall
# between the mouth and the apple in tension; pushing the apple into a tube held at the tail would
# compress the tube ahead of the apple, which a soft tube escapes by buckling.
#
# At each load step the apple is first moved rigidly to its new position (the initial guess of
# Newton's method: a stiff body follows its core), then Newton's method finds the equilibrium.
# Moving only the core's vertices would squeeze the apple's elements next to the core in the
# initial guess instead.
#
# ## Implementation
#
# `MATDEPTH_DEMO_QUICK=1` selects a coarser mesh, a shorter snake and a shorter path (for the
# test suite); `MATDEPTH_DEMO_OUTPUT` moves the output folder (default `demos/output`);
# `MATDEPTH_SNAKE_MU=0.3` adds Coulomb friction with that coefficient between the apple and the
# snake ({py:class}`fenics_matdepth.Coulomb`, {doc}`/friction`): the wall is then dragged along
# with the apple, and each step records the force that pushes the core and the friction's
# dissipation and stick/slip counts.

# +
from __future__ import annotations

import json
import os
import time
from pathlib import Path

from mpi4py import MPI

import numpy as np
import ufl
from dolfinx import fem, io, la, plot

import fenics_matdepth as fm
from fenics_matdepth.meshing import interpolation_points
from fenics_matdepth.plotting import (
    gather_vtk_grid,
    offscreen_pyvista,
    output_folder,
    show_image,
    write_animation,
)

# the model builders of meshes/: run with the repository on PYTHONPATH
from meshes.snake import APPLE, CORE, LIP, SNAKE, snake_mesh

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

# ### Geometry and mesh
#
# Units: millimetres, megapascals (N/mm²), newtons. The snake lies along the $x$ axis with its
# mouth at $x = 0$; `meshes/snake.py` builds it as a solid of revolution: the funnel of the head
# (inner radius 12.5 mm at the mouth, 3.5 mm at the throat 15 mm behind it), the body (inner
# radius 3.5 mm, outer 8 mm: a wall 4.5 mm thick, 35 mm long) and a half-ellipsoidal tail
# 12 mm long. The apple (radius 10 mm) starts with its centre 1 mm in front of the mouth, inside
# the funnel's opening but not touching it, and ends with its centre 30 mm behind the mouth.
# The wall is meshed with elements of 1.8 mm, two to three across its thickness (the quick run:
# 2.6 mm, a shorter body, the apple's centre ending at 16 mm, 8 steps instead of 31).

# +
geometry = {
    "inner_radius": 3.5,
    "outer_radius": 8.0,
    "mouth_radius": 12.5,
    "mouth_length": 15.0,
    "body_end": 28.0 if quick else 50.0,
    "tail_length": 12.0,
    "apple_radius": 10.0,
    "apple_x": -1.0,
    "core_radius": 4.0,
    "snake_size": 2.6 if quick else 1.8,
    "apple_size": 3.5 if quick else 1.8,
}
apple_end = 16.0 if quick else 30.0  # mm: x of the apple's centre at the end
friction_mu = float(os.environ.get("MATDEPTH_SNAKE_MU", "0"))
domain, cell_tags, facet_tags = snake_mesh(comm, **geometry)
V = fem.functionspace(domain, ("Lagrange", 1, (3,)))
num_tets = domain.topology.index_map(3).size_global
num_vertices = V.dofmap.index_map.size_global
tets_per_body = {
    name: comm.allreduce(int(np.count_nonzero(cell_tags.values == tag)))
    for name, tag in (("snake", SNAKE), ("apple", APPLE), ("core", CORE))
}
report(f"mesh: {num_tets} tetrahedra {tets_per_body}, {num_vertices} vertices")
# -

# Material depth, once, in the reference configuration. A tetrahedron whose four vertices all
# lie on the boundary has depth zero everywhere inside and so feels no contact: a thin wall
# meshed one element thick would let the apple through. We count them per body.

# +
depth = fm.material_depth(domain)
depth.name = "material_depth"
num_owned_cells = domain.topology.index_map(3).size_local
depth_cells = depth.function_space.dofmap.list[:num_owned_cells]
flat = np.all(depth.x.array[depth_cells] == 0.0, axis=1)
owned_tags = np.zeros(num_owned_cells, dtype=np.int32)
local_tags = cell_tags.values[cell_tags.indices < num_owned_cells]
owned_tags[cell_tags.indices[cell_tags.indices < num_owned_cells]] = local_tags
zero_depth = {
    name: comm.allreduce(int(np.count_nonzero(flat & (owned_tags == tag))))
    for name, tag in (("snake", SNAKE), ("apple", APPLE))
}
thickness = geometry["outer_radius"] - geometry["inner_radius"]
snake_depth_dofs = depth.function_space.dofmap.list[cell_tags.find(SNAKE)]
snake_max_depth = comm.allreduce(float(depth.x.array[snake_depth_dofs].max(initial=0.0)), MPI.MAX)
report(
    f"tetrahedra with all four vertices on the boundary (zero depth): {zero_depth}; largest "
    f"depth in the snake {snake_max_depth:.3g} mm (its solid tail included; half the wall: "
    f"{thickness / 2:.3g} mm)"
)
# -

# ### Materials, penalty and boundary conditions
#
# The snake is soft tissue, $E = 0.1$ MPa, the apple twenty times stiffer, $E = 2$ MPa; both
# $\nu = 0.4$. Each body's strain energy is integrated over its cells only, `dx(tag)`. The
# penalty is ten times the snake's modulus over its element size: it is the snake's wall that
# gives way, so its stiffness sets how hard the contact must be.

# +
E_snake, E_apple, nu = 0.1, 2.0, 0.4  # MPa, MPa, -
mu_s, kappa_s = fm.materials.shear_bulk_from_youngs_poisson(E_snake, nu)
mu_a, kappa_a = fm.materials.shear_bulk_from_youngs_poisson(E_apple, nu)
u = fem.Function(V, name="displacement")
F = ufl.variable(ufl.Identity(3) + ufl.grad(u))
dx = ufl.Measure("dx", domain=domain, subdomain_data=cell_tags)
psi_snake = fm.materials.neo_hookean(F, mu_s, kappa_s)
psi_apple = fm.materials.neo_hookean(F, mu_a, kappa_a)
energy = psi_snake * dx(SNAKE) + psi_apple * (dx(APPLE) + dx(CORE))
residual = ufl.derivative(energy, u, ufl.TestFunction(V))
h_snake = geometry["snake_size"]
penalty = fm.propose_penalty(domain, E_snake, factor=10.0, h=h_snake)  # MPa/mm

lip_dofs = fem.locate_dofs_topological(V, 2, facet_tags.find(LIP))
core_cells = cell_tags.find(CORE)
domain.topology.create_connectivity(3, 3)
core_dofs = fem.locate_dofs_topological(V, 3, core_cells)
core_translation = fem.Constant(domain, np.zeros(3))
bcs = [
    fem.dirichletbc(np.zeros(3), lip_dofs, V),
    fem.dirichletbc(core_translation, core_dofs, V),
]
friction = fm.Coulomb(friction_mu) if friction_mu > 0.0 else None
contact = fm.ContactOperator(u, depth, penalty, friction=friction)
problem = fm.ContactProblem(
    residual, u, contact, bcs=bcs, energy=energy, petsc_options_prefix="snake_apple_",
    petsc_options={"snes_max_it": 30},
)  # fmt: skip
report(f"penalty {penalty:.3g} MPa/mm; wall elements {h_snake} mm")
# -

# The load factor $t \in [0, 1]$ moves the core's centre from $x = -1$ mm to its end position.
# `set_load` also sets the initial guess of the step's Newton solve. Once two steps have
# converged it extrapolates them linearly (the displacement of the whole model, snake included:
# in steady swallowing the next state looks like the last one moved on by the same amount, as
# load-stepping codes such as FEBio predict it). Before that, it moves the whole apple rigidly by
# the increment (a stiff body follows its core); the shift is measured from the core's current
# displacement in `u`, so it is right both after a converged step and after `solve_load_steps`
# has restored the last converged state to retry a shorter step.

# +
apple_cells = np.concatenate((cell_tags.find(APPLE), core_cells))
apple_blocks = np.unique(V.dofmap.list[apple_cells].ravel())
n_owned = V.dofmap.index_map.size_local
owned_core = core_dofs[core_dofs < n_owned]
num_core = comm.allreduce(owned_core.size)
apple_start = geometry["apple_x"]
converged_states: list[tuple[float, np.ndarray]] = []  # the last two converged (t, u)


def core_x_displacement() -> float:
    """The apple core's current x displacement in ``u`` (mm; collective)."""
    local = float(u.x.array.reshape(-1, 3)[owned_core, 0].sum())
    return comm.allreduce(local) / num_core


def set_load(t: float) -> None:
    target = t * (apple_end - apple_start)
    core_translation.value[:] = (target, 0.0, 0.0)
    if len(converged_states) == 2:
        (t0, u0), (t1, u1) = converged_states
        u.x.array[:] = u1 + (t - t1) / (t1 - t0) * (u1 - u0)
    else:
        shift = target - core_x_displacement()
        u.x.array.reshape(-1, 3)[apple_blocks, 0] += shift


# -

# ### What is measured at each step
#
# - the **circumferential stretch** of the snake's wall, $\lambda_\theta = |F\,\mathbf{e}_\theta|$
#   with $\mathbf{e}_\theta$ the reference circumferential direction about the axis; $F$ is
#   constant in each P1 tetrahedron, so it is interpolated cell by cell (DG0). Stretching the
#   lumen's 3.5 mm radius over the apple's 10 mm takes 2.9 at the inner surface;
# - the smallest $\det F$ over all tetrahedra (an inverted element would have $\det F \le 0$);
# - the contact operator's diagnostics: active pairs and the largest material depth reached by
#   a contact surface (the penetration), relative to the wall's element size;
# - where the apple is: the smallest $x$ over its current vertices (behind the mouth, $x > 0$,
#   it is fully inside).

# +
DG0 = fem.functionspace(domain, ("DG", 0))
X = ufl.SpatialCoordinate(domain)
radial = ufl.sqrt(X[1] ** 2 + X[2] ** 2)
e_theta = ufl.as_vector((0.0, -X[2] / radial, X[1] / radial))
hoop = fem.Function(DG0, name="circumferential_stretch")
hoop_expr = fem.Expression(ufl.sqrt(ufl.dot(F * e_theta, F * e_theta)), interpolation_points(DG0))
jacobian = fem.Function(DG0, name="det_F")
jacobian_expr = fem.Expression(ufl.det(F), interpolation_points(DG0))
snake_cells = cell_tags.find(SNAKE)
bulk_residual = fem.form(residual)
snake_cell_dofs = DG0.dofmap.list[snake_cells[snake_cells < num_owned_cells], 0]
num_owned_dg0 = DG0.dofmap.index_map.size_local  # one per owned cell
X_blocks = V.tabulate_dof_coordinates()


def measure() -> dict:
    """Circumferential stretch, det F and where the apple is (collective)."""
    hoop.interpolate(hoop_expr)
    jacobian.interpolate(jacobian_expr)
    x_now = X_blocks + u.x.array.reshape(-1, 3)
    mine = apple_blocks[apple_blocks < n_owned]
    # the force that moves the core along the axis: the bulk residual at its (prescribed)
    # dofs, which contact does not reach (the core lies 6 mm inside the apple's surface)
    forces = fem.assemble_vector(bulk_residual)
    forces.scatter_reverse(la.InsertMode.add)  # the ghosts' shares onto their owners
    forces = forces.array.reshape(-1, 3)
    return {
        "push_force": comm.allreduce(float(forces[owned_core, 0].sum())),
        "max_stretch": comm.allreduce(
            float(hoop.x.array[snake_cell_dofs].max(initial=0.0)), MPI.MAX
        ),
        "min_det_F": comm.allreduce(
            float(jacobian.x.array[:num_owned_dg0].min(initial=np.inf)), MPI.MIN
        ),
        "apple_back": comm.allreduce(float(x_now[mine, 0].min(initial=np.inf)), MPI.MIN),
        "apple_front": comm.allreduce(float(x_now[mine, 0].max(initial=-np.inf)), MPI.MAX),
    }


# -

# ### Frames
#
# Each converged step is drawn off-screen with pyvista on rank 0 (every process sends its cells
# there): the snake's surface opaque in green, and again translucent over the red apple, as in the
# paper's bottom row. The camera and colours are fixed for the whole sequence.

# +
body_of_point = fem.Function(fem.functionspace(domain, ("Lagrange", 1)))  # 1 on the snake
body_of_point.x.array[np.unique(body_of_point.function_space.dofmap.list[snake_cells])] = 1.0
pyvista = offscreen_pyvista() if comm.rank == 0 else None
window = (800, 380)
# A fixed camera, from the side and a little above, framing the apple's start and the snake,
# with room for the body to lengthen (the apple pushes it towards the tail).
reach = (
    apple_start - geometry["apple_radius"] - 2.0,
    geometry["body_end"] + geometry["tail_length"] + 6.0,
)
view_centre = np.array([0.5 * sum(reach), 0.0, 0.0])
view_direction = np.array([0.0, -0.96, 0.28])
view_angle = 20.0  # degrees, vertical
# the height must also hold the mouth, which the apple widens
mouth_outer = geometry["mouth_radius"] + geometry["outer_radius"] - geometry["inner_radius"]
visible_height = max(1.05 * (reach[1] - reach[0]) * window[1] / window[0], 2.5 * mouth_outer)
view_distance = visible_height / (2.0 * np.tan(np.radians(view_angle / 2)))
frames: dict[str, list[np.ndarray]] = {"opaque": [], "translucent": []}


def render_frame(t: float) -> None:
    """Append the current state's two pictures to ``frames`` (rank 0; collective gather)."""
    Q = body_of_point.function_space
    cells, types, points = plot.vtk_mesh(Q)
    moved = np.empty_like(points)
    component = fem.Function(Q)
    for i in range(3):
        component.interpolate(u.sub(i))
        moved[:, i] = points[:, i] + component.x.array[: points.shape[0]]
    grid = gather_vtk_grid(
        comm, cells[: 5 * num_owned_cells], types[:num_owned_cells], moved,
        body_of_point.x.array[: points.shape[0]],
    )  # fmt: skip
    if comm.rank != 0 or pyvista is None:
        return
    cells, types, points, is_snake = grid
    whole = pyvista.UnstructuredGrid(cells, types, points)
    whole.point_data["snake"] = is_snake
    snake = whole.threshold(0.5, scalars="snake").extract_surface().compute_normals()
    apple = whole.threshold(0.5, scalars="snake", invert=True).extract_surface()
    apple = apple.compute_normals()
    for style in ("opaque", "translucent"):
        plotter = pyvista.Plotter(window_size=window, off_screen=True)
        plotter.set_background("white")
        plotter.add_mesh(apple, color="#c0262d", smooth_shading=True, specular=0.4)
        opacity = 1.0 if style == "opaque" else 0.25
        plotter.add_mesh(snake, color="#5b8c2a", smooth_shading=True, specular=0.3, opacity=opacity)
        plotter.camera.focal_point = view_centre
        plotter.camera.position = view_centre + view_distance * view_direction
        plotter.camera.up = (0.0, 0.0, 1.0)
        plotter.camera.view_angle = view_angle
        # large enough to read in the row of five frames (snake_apple_row.png, 4000 px wide)
        plotter.add_text(
            f"apple's centre at x = {apple_start + t * (apple_end - apple_start):.0f} mm",
            position="upper_edge", font_size=22, color="black",
        )  # fmt: skip
        frames[style].append(plotter.screenshot(return_img=True))
        plotter.close()


# -

# ### The swallowing, in load steps
#
# `solve_load_steps` solves the steps one after the other (each from the last converged state)
# and halves a step that fails. After each converged step, the writer callback measures, writes
# the displacement to a VTX file (open `snake_apple.bp` in ParaView and *Warp By Vector*) and
# renders the frames.

# +
num_steps = 8 if quick else 31
records: list[dict] = []
vtx = io.VTXWriter(comm, output / "snake_apple.bp", [u])


def after_step(t: float) -> None:
    diag = contact.diagnostics()
    record = {
        "load": t,
        "apple_x": apple_start + t * (apple_end - apple_start),
        "active_pairs": diag["active_pairs"],
        "max_penetration": diag["max_penetration"],
        "relative_penetration": diag["max_penetration"] / h_snake,
        **measure(),
    }
    for key in ("friction_dissipation", "stick_points", "slip_points"):
        if key in diag:
            record[key] = diag[key]
    records.append(record)
    converged_states.append((t, u.x.array.copy()))
    del converged_states[:-2]
    vtx.write(t)
    render_frame(t)
    report(
        f"    apple at x = {record['apple_x']:5.1f} mm: max circumferential stretch "
        f"{record['max_stretch']:.2f}, min det F {record['min_det_F']:.3f}, penetration "
        f"{record['relative_penetration']:.3f} h, push {record['push_force']:.3g} N"
    )


set_load(0.0)
after_step(0.0)
steps = fm.solve_load_steps(problem, set_load, num_steps=num_steps, writer=after_step)
vtx.close()
for record, step in zip(records[1:], steps, strict=True):
    record.update(iterations=step.iterations, cuts=step.cuts, seconds=step.seconds)
    record["residual_norms"] = step.residual_norms.tolist()
# -

# The apple ends behind the mouth, inside the snake, and no element inverted:

# +
final = records[-1]
iterations = np.array([s.iterations for s in steps])
report(
    f"{len(steps)} steps, {sum(s.cuts for s in steps)} cuts; Newton iterations median "
    f"{np.median(iterations):.0f}, max {iterations.max()}; max circumferential stretch "
    f"{max(r['max_stretch'] for r in records):.2f}; max penetration "
    f"{max(r['relative_penetration'] for r in records):.3f} h; min det F "
    f"{min(r['min_det_F'] for r in records):.3f}; apple from x = {final['apple_back']:.1f} to "
    f"{final['apple_front']:.1f} mm"
)
assert all(s.residual_norms[-1] <= 1e-10 * s.residual_norms[0] + 1e-12 for s in steps)
assert final["apple_back"] > 0.0, "the apple is not inside the snake"
assert min(r["min_det_F"] for r in records) > 0.0, "an element inverted"
# -

# ### Pictures
#
# A row of frames, opaque above and translucent below, and the animation (both rows per frame).

# +
pictures: list[str] = []
if comm.rank == 0 and frames["opaque"]:
    from PIL import Image

    picks = np.unique(np.linspace(0, len(frames["opaque"]) - 1, 5).round().astype(int))

    rows = [np.hstack([frames[s][i] for i in picks]) for s in ("opaque", "translucent")]
    Image.fromarray(np.vstack(rows)).save(output / "snake_apple_row.png")
    pictures.append("snake_apple_row.png")
    for i in picks:
        for style in ("opaque", "translucent"):
            name = f"snake_apple_{style}_{i:02d}.png"
            Image.fromarray(frames[style][i]).save(output / name)
            pictures.append(name)
    stacked = [
        np.vstack((a, b)) for a, b in zip(frames["opaque"], frames["translucent"], strict=True)
    ]
    write_animation(stacked, output / "snake_apple.gif", fps=4)
    pictures.append("snake_apple.gif")
    show_image(output / "snake_apple_row.png")
# -

# A short summary for the tests and the documentation:

# +
seconds = time.perf_counter() - start
summary = {
    "quick": quick,
    "processes": comm.size,
    "tetrahedra": num_tets,
    "tetrahedra_per_body": tets_per_body,
    "vertices": num_vertices,
    "zero_depth_tetrahedra": zero_depth,
    "snake_size": h_snake,
    "penalty": penalty,
    "mu": friction_mu,
    "seconds": seconds,
    "pictures": pictures,
    "steps": records,
}
if comm.rank == 0:
    (output / "snake_apple.json").write_text(json.dumps(summary, indent=1))
    print(f"pictures and results in {output}")
report(f"demo_snake_apple: {seconds:.1f} s on {comm.size} process(es)")
# -
