"""DOLFINx version differences (0.9, 0.10, 0.11), and what petsc4py lacks, kept in this one module.

Everything else in the package calls these helpers instead of testing versions itself.
"""

from __future__ import annotations

import ctypes
import functools
import logging
import warnings

import dolfinx

__all__ = [
    "DOLFINX_VERSION",
    "NewtonSolverProblemBase",
    "bc_constrains_space",
    "create_tetrahedral_mesh",
    "geometry_cmap",
    "geometry_dofmap",
    "gmsh_model_to_mesh",
    "integral_domains",
    "interpolation_points",
    "set_lag_preconditioner",
    "show_warnings",
    "solve_nonlinear",
]

#: (major, minor) of the DOLFINx in use.
DOLFINX_VERSION: tuple[int, int] = tuple(int(p) for p in dolfinx.__version__.split(".")[:2])


def show_warnings() -> bool:
    """Show warnings on stderr again where FFCx captured them into a logging set up nowhere.

    FFCx 0.9 calls ``logging.captureWarnings(True)`` on import: every warning then goes to the
    ``py.warnings`` logger, which (with no handler anywhere) gets a ``NullHandler`` at the
    first warning, so nothing is printed. Where the root logger and ``py.warnings`` have no
    handler of their own (no logging was set up by the script), Python's display is restored;
    a script that configured logging keeps its choice.

    Returns:
        Whether the display was restored.
    """
    if warnings.showwarning is not getattr(logging, "_showwarning", None):
        return False  # not captured (DOLFINx 0.10 on), or redirected by someone else
    captured = logging.getLogger("py.warnings")
    own = [h for h in captured.handlers if not isinstance(h, logging.NullHandler)]
    if logging.getLogger().handlers or own:
        return False
    logging.captureWarnings(False)
    return True


def _newton_problem_base():
    import dolfinx.fem.petsc

    # 0.10 renamed the NewtonSolver's problem class (NonlinearProblem became the SNES wrapper)
    if DOLFINX_VERSION >= (0, 10):
        return dolfinx.fem.petsc.NewtonSolverNonlinearProblem
    return dolfinx.fem.petsc.NonlinearProblem


#: The problem class that ``dolfinx.nls.petsc.NewtonSolver`` drives: ``NonlinearProblem`` on
#: DOLFINx 0.9, ``NewtonSolverNonlinearProblem`` from 0.10 on (same methods: F, J, form).
NewtonSolverProblemBase = _newton_problem_base()

#: Newton defaults of :func:`solve_nonlinear`: full steps, direct solve with MUMPS (works in
#: serial and in parallel), tight tolerances.
_NEWTON_DEFAULTS: dict[str, object] = {
    "snes_type": "newtonls",
    "snes_linesearch_type": "basic",
    "snes_atol": 1e-10,
    "snes_rtol": 1e-10,
    "snes_stol": 0.0,
    "snes_max_it": 25,
    "ksp_type": "preonly",
    "pc_type": "lu",
    "pc_factor_mat_solver_type": "mumps",
}


def solve_nonlinear(
    F,
    u,
    bcs=(),
    petsc_options: dict | None = None,
    petsc_options_prefix: str = "fenics_matdepth_nonlinear_",
) -> tuple[int, bool]:
    """Solve ``F(u; v) = 0`` for ``u`` by Newton's method, on any supported DOLFINx.

    DOLFINx >= 0.10: ``dolfinx.fem.petsc.NonlinearProblem`` (PETSc SNES) with ``petsc_options``
    pushed under ``petsc_options_prefix``. DOLFINx 0.9: ``dolfinx.nls.petsc.NewtonSolver`` with
    the residual convergence criterion; ``snes_atol``, ``snes_rtol`` and ``snes_max_it`` are
    mapped onto it, ``ksp_*``/``pc_*``/``mat_*`` options go to its Krylov solver, other
    ``snes_*`` options (line search, ...) have no 0.9 counterpart and are ignored.

    Args:
        F: UFL residual form (linear in the test function).
        u: The unknown ``dolfinx.fem.Function``; holds the initial guess and, on return, the
            solution.
        bcs: Dirichlet boundary conditions.
        petsc_options: PETSc options overriding the defaults (Newton with full steps, LU with
            MUMPS, absolute and relative residual tolerances 1e-10, at most 25 iterations).
        petsc_options_prefix: Options prefix of the PETSc objects (DOLFINx >= 0.10).

    Returns:
        ``(iterations, converged)``; ``converged`` is always True on return.

    Raises:
        RuntimeError: If Newton's method (or its linear solver) did not converge.
    """
    from petsc4py import PETSc

    import dolfinx.fem.petsc

    options = {**_NEWTON_DEFAULTS, **(petsc_options or {})}
    bcs = list(bcs)
    if DOLFINX_VERSION >= (0, 10):
        problem = dolfinx.fem.petsc.NonlinearProblem(
            F, u, petsc_options_prefix=petsc_options_prefix, bcs=bcs, petsc_options=options
        )
        problem.solve()
        reason = problem.solver.getConvergedReason()
        iterations = problem.solver.getIterationNumber()
        if reason <= 0:
            raise RuntimeError(
                f"Newton (SNES) did not converge: reason {reason} after {iterations} iterations"
            )
        return iterations, True

    import dolfinx.nls.petsc

    problem = dolfinx.fem.petsc.NonlinearProblem(F, u, bcs=bcs)
    solver = dolfinx.nls.petsc.NewtonSolver(u.function_space.mesh.comm, problem)
    solver.convergence_criterion = "residual"
    solver.atol = float(options["snes_atol"])
    solver.rtol = float(options["snes_rtol"])
    solver.max_it = int(options["snes_max_it"])
    # Raise below with our own message, the same as on DOLFINx >= 0.10.
    solver.error_on_nonconvergence = False
    ksp = solver.krylov_solver
    ksp.setOptionsPrefix(petsc_options_prefix)
    petsc_opts = PETSc.Options()
    ksp_keys = [k for k in options if k.split("_")[0] in ("ksp", "pc", "mat")]
    for key in ksp_keys:
        petsc_opts[f"{petsc_options_prefix}{key}"] = options[key]
    ksp.setFromOptions()
    for key in ksp_keys:
        del petsc_opts[f"{petsc_options_prefix}{key}"]
    iterations, converged = solver.solve(u)
    if not converged:
        raise RuntimeError(f"Newton did not converge after {iterations} iterations")
    return int(iterations), True


def gmsh_model_to_mesh(model, comm, rank: int = 0, gdim: int = 3):
    """Convert a gmsh model to a DOLFINx mesh on any supported DOLFINx.

    DOLFINx 0.9 has ``dolfinx.io.gmshio.model_to_mesh`` returning a plain tuple; 0.10+ has
    ``dolfinx.io.gmsh.model_to_mesh`` returning a named tuple with more fields.

    Args:
        model: The gmsh model (``gmsh.model``), meshed on ``rank``.
        comm: MPI communicator of the mesh.
        rank: Rank holding the gmsh model.
        gdim: Geometric dimension.

    Returns:
        ``(mesh, cell_tags, facet_tags)``.
    """
    if DOLFINX_VERSION >= (0, 10):
        from dolfinx.io import gmsh as _gmsh_io

        data = _gmsh_io.model_to_mesh(model, comm, rank, gdim=gdim)
        return data.mesh, data.cell_tags, data.facet_tags
    from dolfinx.io import gmshio as _gmsh_io

    mesh, cell_tags, facet_tags = _gmsh_io.model_to_mesh(model, comm, rank, gdim=gdim)[:3]
    return mesh, cell_tags, facet_tags


def gmsh_build_to_mesh(build, comm, gdim: int = 3):
    """Mesh a gmsh model built by ``build`` on rank 0 and distribute it (collective).

    gmsh is initialised if it is not already (and finalised again then), quiet and on one
    thread (the same mesh on every run); ``build(gmsh.model)`` runs on rank 0 only, and the
    model is removed afterwards, also when ``build`` raises.

    Args:
        build: callable taking ``gmsh.model``: adds the geometry, physical groups, sizes and
            generates the mesh.
        comm: MPI communicator of the mesh.
        gdim: geometric dimension.

    Returns:
        ``(mesh, cell_tags, facet_tags)``.
    """
    import gmsh

    initialized_here = not gmsh.isInitialized()
    if initialized_here:
        gmsh.initialize()
    gmsh.option.setNumber("General.Terminal", 0)
    try:
        if comm.rank == 0:
            gmsh.option.setNumber("General.NumThreads", 1)
            build(gmsh.model)
        return gmsh_model_to_mesh(gmsh.model, comm, 0, gdim=gdim)
    finally:
        if comm.rank == 0:
            gmsh.model.remove()
        if initialized_here:
            gmsh.finalize()


def geometry_cmap(mesh):
    """The (single) coordinate element of ``mesh.geometry``.

    DOLFINx 0.11 supports mixed-topology geometry and deprecates ``geometry.cmap`` in favour of
    ``geometry.cmaps[0]``; 0.9 only has ``geometry.cmap``.
    """
    geometry = mesh.geometry
    cmaps = getattr(geometry, "cmaps", None)
    return cmaps[0] if cmaps is not None else geometry.cmap


def geometry_dofmap(mesh):
    """The (num_cells, num_nodes) geometry dofmap of a single-cell-type mesh.

    ``geometry.dofmaps[0]`` where it exists (0.11 deprecates ``geometry.dofmap``), else
    ``geometry.dofmap``.
    """
    geometry = mesh.geometry
    dofmaps = getattr(geometry, "dofmaps", None)
    return dofmaps[0] if dofmaps is not None else geometry.dofmap


def create_tetrahedral_mesh(
    comm, cells, x, degree: int = 1, all_cells_on_rank0: bool = False, cell_ranks=None
):
    """A tetrahedral mesh from node coordinates and cells (rank 0's data is used).

    ``dolfinx.mesh.create_mesh`` takes ``(comm, cells, x, element)`` on 0.9 and
    ``(comm, cells, element, x)`` from 0.10 on; a custom partitioner must return the C++
    adjacency list from 0.10 on.

    Args:
        comm: communicator of the mesh.
        cells: (n, 4) vertex indices (degree 1) or (n, 10) node indices (degree 2, DOLFINx
            node order).
        x: (m, 3) node coordinates.
        degree: degree of the coordinate element.
        all_cells_on_rank0: keep every cell on rank 0 (the other ranks get none).
        cell_ranks: (n,) rank that owns each cell (rank 0's array is used), instead of the
            graph partitioner's choice.
    """
    import basix.ufl
    import numpy as np
    import ufl

    element = ufl.Mesh(basix.ufl.element("Lagrange", "tetrahedron", degree, shape=(3,)))
    nodes_per_cell = np.asarray(cells).shape[1]
    if comm.rank != 0:
        cells = np.empty((0, nodes_per_cell), dtype=np.int64)
        x = np.empty((0, 3), dtype=np.float64)
    cells = np.asarray(cells, dtype=np.int64)
    x = np.asarray(x, dtype=np.float64)
    kwargs = {}
    if all_cells_on_rank0:

        def to_rank0(comm, nparts, cell_types, local_cells):
            # the partitioner sees the topology (4 vertices per cell), whatever the degree
            n = np.asarray(local_cells[0]).size // 4 if local_cells else 0
            dest = dolfinx.graph.adjacencylist(np.zeros(n, dtype=np.int32))
            return getattr(dest, "_cpp_object", dest)

        kwargs["partitioner"] = to_rank0
    elif cell_ranks is not None:
        ranks = np.asarray(cell_ranks, dtype=np.int32) if comm.rank == 0 else None

        def to_given_ranks(comm, nparts, cell_types, local_cells):
            n = np.asarray(local_cells[0]).size // 4 if local_cells else 0
            dest = ranks if n else np.empty(0, dtype=np.int32)
            dest = dolfinx.graph.adjacencylist(np.ascontiguousarray(dest, dtype=np.int32))
            return getattr(dest, "_cpp_object", dest)

        kwargs["partitioner"] = to_given_ranks
    if DOLFINX_VERSION >= (0, 10):
        return dolfinx.mesh.create_mesh(comm, cells, element, x, **kwargs)
    return dolfinx.mesh.create_mesh(comm, cells, x, element, **kwargs)


def interpolation_points(V):
    """Reference interpolation points of a function space's element.

    A method of ``V.element`` on DOLFINx 0.9, a property from 0.10 on.
    """
    points = V.element.interpolation_points
    return points() if callable(points) else points


def integral_domains(form, kind) -> list[tuple[int, object]]:
    """``(subdomain id, integration entities)`` of each of the compiled ``form``'s integrals of
    type ``kind`` (cell or exterior facet), in the order DOLFINx assembles them (ids ascending,
    -1 first: over every cell or facet). DOLFINx 0.9 looks an integral's entities up by its
    id, 0.10 and later by its position."""
    ufcx = form.ufcx_form
    k = {dolfinx.fem.IntegralType.cell: 0, dolfinx.fem.IntegralType.exterior_facet: 1}[kind]
    start, stop = ufcx.form_integral_offsets[k], ufcx.form_integral_offsets[k + 1]
    out = []
    for position in range(stop - start):
        ident = int(ufcx.form_integral_ids[start + position])
        key = ident if DOLFINX_VERSION < (0, 10) else position
        out.append((ident, form._cpp_object.domains(kind, key)))
    return out


def bc_constrains_space(bc, V) -> bool:
    """Whether the Dirichlet condition ``bc`` constrains ``V`` or one of its subspaces.

    ``DirichletBC.function_space`` is a C++ space on DOLFINx 0.9 and a Python one later; the
    comparison goes through the C++ objects.
    """
    space = bc.function_space
    space = getattr(space, "_cpp_object", space)
    return bool(V._cpp_object.contains(space))


def set_lag_preconditioner(snes, lag: int) -> None:
    """``SNESSetLagPreconditioner(snes, lag)``: -2 factorise (set up the preconditioner of) the
    next Jacobian, -1 keep the last one (logically collective).

    petsc4py (3.22 to 3.25 at least) does not wrap it; the C function is called through ctypes,
    from the PETSc library petsc4py's extension module is linked with.
    """
    method = getattr(snes, "setLagPreconditioner", None)
    if method is not None:
        method(lag)
        return
    err = _petsc_c().SNESSetLagPreconditioner(ctypes.c_void_p(snes.handle), _petsc_int()(lag))
    if err != 0:
        raise RuntimeError(f"SNESSetLagPreconditioner({lag}) failed with PETSc error {err}")


def _petsc_int():
    from petsc4py import PETSc

    import numpy as np

    return ctypes.c_int64 if np.dtype(PETSc.IntType).itemsize == 8 else ctypes.c_int32


@functools.cache
def _petsc_c():
    from petsc4py import PETSc

    # dlsym on the extension module also searches the libraries it was linked with (libpetsc)
    lib = ctypes.CDLL(PETSc.__file__)
    lib.SNESSetLagPreconditioner.restype = ctypes.c_int
    return lib
