# ---
# jupyter:
#   jupytext:
#     text_representation:
#       extension: .py
#       format_name: light
#       format_version: '1.5'
#       jupytext_version: 1.16.0
# ---

# # A hyperelastic bar sagging under its own weight
#
# This demo is implemented in {download}`demo_hyperelastic_bar.py`. It illustrates how to:
#
# - write the total potential energy of a hyperelastic body with the strain-energy densities of
#   {py:mod}`fenics_matdepth.materials` (neo-Hookean, Mooney-Rivlin, Veronda-Westmann and a
#   transversely isotropic fiber-reinforced model);
# - obtain the residual and the Jacobian by automatic differentiation of that energy;
# - solve the nonlinear problem with Newton's method and load stepping, on any supported
#   DOLFINx version, serially or in parallel;
# - save the results to XDMF (for ParaView) and render a picture off-screen with pyvista.
#
# No contact yet: this is the bulk physics on top of which the contact operator of
# `fenics_matdepth` adds its penalty forces.
#
# ## The physics
#
# A bar of length $L$ and square cross-section $b \times b$ is clamped at $x = 0$ and hangs
# horizontally under gravity $\mathbf{g} = -g\,\mathbf{e}_z$. With the displacement
# $\mathbf{u}$, the deformation gradient $F = I + \nabla\mathbf{u}$ and a strain-energy
# density $\psi(F)$ (energy per unit reference volume), the equilibrium state minimises the
# total potential energy
#
# $$
# \Pi(\mathbf{u}) = \int_\Omega \psi(F)\,\mathrm{d}X
#   - \int_\Omega \rho\,\mathbf{g}\cdot\mathbf{u}\,\mathrm{d}X,
# $$
#
# where $\rho$ is the density in the reference configuration. Its first variation is the weak
# form of equilibrium, $\int_\Omega P : \nabla\mathbf{v}\,\mathrm{d}X = \int_\Omega
# \rho\,\mathbf{g}\cdot\mathbf{v}\,\mathrm{d}X$, with $P = \partial\psi/\partial F$ the first
# Piola-Kirchhoff stress. UFL derives both the residual and its Jacobian from $\Pi$.
#
# Every model here is calibrated to the same small-strain behaviour (Young's modulus $E$,
# Poisson's ratio $\nu$), so the bars differ only through their nonlinear response:
#
# - **neo-Hookean**: $\psi = \frac{\mu}{2}(\bar I_1 - 3) + U(J)$;
# - **Mooney-Rivlin**: $\psi = c_{10}(\bar I_1 - 3) + c_{01}(\bar I_2 - 3) + U(J)$ with
#   $2(c_{10} + c_{01}) = \mu$;
# - **Veronda-Westmann**: $\psi = c_1(e^{c_2(\bar I_1 - 3)} - 1) - \frac{c_1 c_2}{2}(\bar I_2 - 3)
#   + U(J)$ with $c_1 c_2 = \mu$, stiffening exponentially with stretch;
# - **fiber-reinforced**: the neo-Hookean matrix plus fibers along the bar axis that resist
#   stretching only, $\psi_f = \frac{k_1}{2k_2}(e^{k_2(I_4 - 1)^2} - 1)$ for $I_4 > 1$. In a
#   sagging cantilever the upper half is stretched and the lower half compressed: the fibers
#   stiffen the upper half only, and the bar sags less.
#
# All share the volumetric energy $U(J) = \frac{\kappa}{4}(J^2 - 1 - 2\ln J)$, which tends to
# infinity as $J \to 0$ so that no element is turned inside out.
#
# ## Implementation
#
# We start with the imports.

# +
from __future__ import annotations

import time
from pathlib import Path

from mpi4py import MPI

import numpy as np
import ufl
from dolfinx import fem, io, mesh, plot

from fenics_matdepth import materials, solve_nonlinear
from fenics_matdepth.plotting import (
    gather_vtk_grid,
    offscreen_pyvista,
    output_folder,
    round_bands,
    show_image,
)

start = time.perf_counter()
comm = MPI.COMM_WORLD
try:
    here = Path(__file__).resolve().parent
except NameError:  # in a notebook
    here = Path.cwd()
output = output_folder(comm, here / "output")  # or $MATDEPTH_DEMO_OUTPUT
# -

# ### Geometry, mesh and material data
#
# SI units throughout: a rubber-like bar, 1 m long with a 10 cm square section. The mesh is
# deliberately coarse so that the demo runs in seconds. Linear tetrahedra are too stiff in
# bending on such a mesh (they "lock"), so the sag is underestimated: the picture is
# qualitative.

# +
length, width = 1.0, 0.1  # m
density, gravity = 1000.0, 9.81  # kg/m^3, m/s^2
youngs_modulus, poisson_ratio = 1.0e6, 0.3  # Pa, -
mu, kappa = materials.shear_bulk_from_youngs_poisson(youngs_modulus, poisson_ratio)

domain = mesh.create_box(
    comm, [np.zeros(3), np.array([length, width, width])], [16, 3, 3], mesh.CellType.tetrahedron
)
V = fem.functionspace(domain, ("Lagrange", 1, (3,)))
# -

# The material parameters are `fem.Constant`s: one compiled form per model serves every value.
# The fiber direction `a0` is the bar axis.


# +
def constant(value):
    return fem.Constant(domain, np.asarray(value, dtype=np.float64))


a0 = constant([1.0, 0.0, 0.0])
models = {
    "neo-Hookean": (materials.neo_hookean, {"mu": constant(mu), "kappa": constant(kappa)}),
    "Mooney-Rivlin": (
        materials.mooney_rivlin,
        {"c10": constant(0.35 * mu), "c01": constant(0.15 * mu), "kappa": constant(kappa)},
    ),
    "Veronda-Westmann": (
        materials.veronda_westmann,
        {"c1": constant(mu / 2.0), "c2": constant(2.0), "kappa": constant(kappa)},
    ),
    "fiber-reinforced": (
        materials.fiber_reinforced,
        {
            "mu": constant(mu),
            "kappa": constant(kappa),
            "a0": a0,
            "k1": constant(mu),
            "k2": constant(1.0),
        },
    ),
}
# -

# ### Boundary condition, energy and load stepping
#
# The end $x = 0$ is clamped. Gravity is applied in a few load steps, each solved by Newton's
# method from the previous equilibrium: a bar that sags by a good fraction of its length is too
# far from the undeformed state for a single Newton solve without a line search.
# `solve_nonlinear` raises if Newton does not converge, so reaching the end of the loop means
# every solve converged.

# +
clamped = mesh.locate_entities_boundary(
    domain, domain.topology.dim - 1, lambda x: np.isclose(x[0], 0.0)
)
clamped_dofs = fem.locate_dofs_topological(V, domain.topology.dim - 1, clamped)
bcs = [fem.dirichletbc(np.zeros(3), clamped_dofs, V)]

load_factor = constant(0.0)
body_force = load_factor * density * ufl.as_vector([0.0, 0.0, -gravity])  # N/m^3
load_steps = np.linspace(0.25, 1.0, 4)

solutions, tip_deflection = {}, {}
for name, (strain_energy, parameters) in models.items():
    u = fem.Function(V, name=name.replace("-", "_"))
    F = ufl.variable(ufl.Identity(3) + ufl.grad(u))
    energy = strain_energy(F, **parameters) * ufl.dx - ufl.dot(body_force, u) * ufl.dx
    residual = ufl.derivative(energy, u, ufl.TestFunction(V))
    iterations = []
    for factor in load_steps:
        load_factor.value = factor
        its, converged = solve_nonlinear(residual, u, bcs, petsc_options_prefix=f"bar_{u.name}_")
        assert converged
        iterations.append(its)
    solutions[name] = u
    tip_deflection[name] = comm.allreduce(u.x.array[2::3].min(initial=0.0), op=MPI.MIN)
    if comm.rank == 0:
        print(
            f"{name:>18}: tip deflection {tip_deflection[name]:+.4f} m, "
            f"Newton iterations per load step {iterations}"
        )
# -

# The fibers carry tension in the upper half of the bar: the fiber-reinforced bar, whose matrix
# is the neo-Hookean material, must sag less than the neo-Hookean bar.

assert tip_deflection["neo-Hookean"] < tip_deflection["fiber-reinforced"] < 0.0

# ### Output
#
# The displacements go to one XDMF file (open it in ParaView and use *Warp By Vector*).

with io.XDMFFile(comm, output / "hyperelastic_bar.xdmf", "w") as xdmf:
    xdmf.write_mesh(domain)
    for u in solutions.values():
        xdmf.write_function(u)

# The picture is drawn off-screen with pyvista, on rank 0 only: every process sends the cells it
# owns, with their displacements, to rank 0, which assembles one grid. pyvista is optional: the
# demo still runs without it.


# +
def gather_grid(u: fem.Function):
    """Return (cells, cell types, points, displacements) of the whole mesh on rank 0."""
    cells, types, points = plot.vtk_mesh(u.function_space)
    values = u.x.array.reshape(-1, 3)[: points.shape[0]]
    return gather_vtk_grid(comm, cells, types, points, values)


grids = {name: gather_grid(u) for name, u in solutions.items()}
if comm.rank == 0 and (pyvista := offscreen_pyvista()) is not None:
    largest = max(np.linalg.norm(values, axis=1).max() for *_, values in grids.values())
    # the colour scale ends on a round value, so that its labels are round and alike (they
    # mixed "0.648" with "0.00"): labelled bands of 1, 2 or 5 times a power of ten, at most 7
    band, count = round_bands(largest, 7)
    top = band * count
    bar = {
        "title": "displacement (m)", "vertical": True, "fmt": "%g", "color": "black",
        "n_labels": count + 1, "title_font_size": 16, "label_font_size": 16,
        "position_x": 0.8, "position_y": 0.1, "width": 0.08, "height": 0.6,
    }  # fmt: skip
    # one view for the four panels, fitted to every bar, so that their sags compare by eye
    corners = np.vstack([np.vstack((p, p + v)) for _, _, p, v in grids.values()])
    bounds = np.ravel(np.column_stack((corners.min(axis=0), corners.max(axis=0))))
    plotter = pyvista.Plotter(shape=(2, 2), window_size=(1200, 800), off_screen=True)
    for index, (name, (cells, types, points, values)) in enumerate(grids.items()):
        plotter.subplot(index // 2, index % 2)
        reference = pyvista.UnstructuredGrid(cells, types, points)
        deformed = pyvista.UnstructuredGrid(cells, types, points + values)
        deformed.point_data["displacement (m)"] = np.linalg.norm(values, axis=1)
        plotter.add_mesh(reference, style="wireframe", color="gray", opacity=0.3)
        plotter.add_mesh(
            deformed,
            scalars="displacement (m)",
            show_edges=True,
            clim=[0.0, top],
            scalar_bar_args=bar,
        )
        plotter.add_text(f"{name}: tip {tip_deflection[name]:+.3f} m", font_size=10)
        plotter.view_xz(bounds=bounds)
        plotter.camera.zoom(1.3)
    plotter.subplot(0, 0)
    # room between the title and the top label
    plotter.scalar_bar.SetVerticalTitleSeparation(10)
    plotter.screenshot(output / "hyperelastic_bar.png")
    plotter.close()
    show_image(output / "hyperelastic_bar.png")
    print(f"picture: {output / 'hyperelastic_bar.png'}")

if comm.rank == 0:
    print(f"demo_hyperelastic_bar: {time.perf_counter() - start:.1f} s on {comm.size} process(es)")
# -
