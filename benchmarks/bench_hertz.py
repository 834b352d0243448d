"""The 3D Hertz problem of dolfinx_contact's demo (python/demos/demo_hertzian_contact.py,
``--3D --problem 1``): penalty and augmented Lagrangian against Hertz theory.

Set-up as the peer's demo: a hemisphere of radius R = 8 (lower half of a ball) rests on a
20 x 20 x 20 block, both linearly elastic with E = 200, nu = 0.3; a body force of density
``3 L / (4 pi R^3)`` (L = 2 R 0.625 = 10) acts on the hemisphere, applied in 4 load steps; the
block's bottom is clamped. The mesh size is ``res`` within R/2 of the contact point and grows
to ``2 res`` at distance R (the peer's gmsh Threshold field). ``--model full`` solves the
peer's full model: its mesh (``meshes/hertz.py``, ``full=True``: 1959 vertices and 8304 cells
at res 1.0, where the peer's has 1962 and 8323) and its supports, the block's bottom clamped and
x and y held at the three sphere vertices nearest to the sphere's centre (0, 0, R), to
(0, 0, R/2) and to (0, R/2, R/2) (the peer pins the mesh nodes nearest to those points); this
is the default. ``--model quarter`` solves a quarter of it (symmetry planes x = 0, y = 0 on
rollers, material depth of the full bodies), about a quarter of the vertices. Either way the
hemisphere is held vertically only by contact, as in the peer's demo.

The body force on the hemisphere (volume 2 pi R^3 / 3) totals ``L / 2 = 5``; the Hertz values
are those of the force the contact transmits, which equilibrium makes equal to it (printed).
(The peer's script evaluates its Hertz formulas with ``L = 10``, twice the force it applies.)

Measured: the overlap (largest material depth reached by a contact surface) relative to the
Hertz approach delta = a^2 / R; p_max, the largest nodal pressure on the block's top (nodal
contact force / tributary area), also against Hertz's pressure measured the same way (weighted
by the pole's hat function, which alone puts it below p0 by about 3 h^2 / (20 a^2)); the
contact radius from the second moment of the block's
nodal contact forces (``<r^2> = 2 a^2 / 5`` for the Hertz pressure); Newton iterations; wall
time of the load stepping (mesh, forms and compilation excluded).

Also measured: the *pointwise* contact pressure at the pole, the pressure the model itself
applies at a surface point: a penetrating surface point y gets the force density
``(p(y) + eps g(y)) grad g`` per unit area, ``g`` the material depth of the other body at y
(``ContactOperator.vertex_penetration``) and ``p`` the augmented Lagrangian's nodal pressure (0
for the penalty), so the pressure there is ``eps g + p`` (times ``|grad g|``, which is
1 + O(strain) since g is the reference depth: 1.02 at the pole at res 0.5). Both surfaces enter the
other body, so the pressure transmitted at the pole is the sum of the block's pole vertex's
value and the sphere's. The check of that sum: ``int (p + eps g) dA`` over every intersection
polygon of each surface (``ContactOperator.pressure_moments``, exact) against the transmitted
force, and the same integral from the vertex values alone (each times a third of the area of
its boundary triangles off the symmetry planes), which agrees only where the vertex values
represent the field.

Also measured, the peer's own measure, like for like: the normal traction of the bulk stress,
``p = -sigma(u) n . n`` (``sigma = 2 mu eps(u) + lambda tr(eps(u)) I``, constant per P1 cell),
``n`` the outward normal of a contact facet, in the cell under each facet; p_max from the
stress is its largest value over the block's top face (n = +z, so ``p = -sigma_zz``), over all
ranks, and the same over the sphere's curved surface (its own outward normal). dolfinx_contact
(``python/dolfinx_contact/output.py``) evaluates ``sigma(u) n_x . n_contact`` at the contact
facets' quadrature points, ``n_contact = -n_x`` with ray-tracing and the other surface's normal
with closest-point search, in the reference configuration: with P1 one value per facet, the
same as here with ray-tracing; an older version of its Hertz demo took, commented out, the
maximum over the second surface's (the block's top face) values.

With ``--pressure-term quadratic`` the augmented Lagrangian's pressure term is the C1 one
(``AugmentedLagrangian(..., pressure_term="quadratic")``: stiffness ``eps + p_T / w``, ``p_T``
a penetrating triangle's mean nodal pressure, ``w`` half the tolerance); the pointwise
pressure is then ``(eps + p / w) g`` and its integral ``int (eps + p / w) g dA``, each with
the vertex's nodal pressure in place of ``p_T`` (approximate).

Run: ``scripts/fenicsx python3 benchmarks/bench_hertz.py --res 1.0 0.5 [--method both]
[--model quarter|full] [--pressure-term quadratic] [--petsc pc_type=cholesky ...]``.
Prints figures; asserts nothing.
"""

from __future__ import annotations

import argparse
import time

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import numpy as np
import ufl

import fenics_matdepth as fm
from fenics_matdepth.boundary import owned_exterior_facets
from fenics_matdepth.depth import boundary_triangles, distance_to_triangles
from meshes import hertz

RADIUS, WIDTH, DEPTH = 8.0, 20.0, 20.0
YOUNGS, POISSON = 200.0, 0.3
LOAD = 2 * RADIUS * 0.625
#: the peer's errors of p_max against Hertz theory at res 1.0, 0.5, 0.35
PEER_PMAX_ERROR = {1.0: -0.73, 0.5: -0.16, 0.35: 0.001}


def _full_body_depth(mesh, tol):
    """Material depth of the full bodies: distance to the exterior facets off x = 0, y = 0."""
    triangles = boundary_triangles(mesh)
    on_plane = np.zeros(triangles.shape[0], dtype=bool)
    for axis in (0, 1):
        on_plane |= np.all(np.abs(triangles[:, :, axis]) < tol, axis=1)
    Q = dolfinx.fem.functionspace(mesh, ("Lagrange", 1))
    depth = dolfinx.fem.Function(Q)
    depth.x.array[:] = distance_to_triangles(Q.tabulate_dof_coordinates(), triangles[~on_plane])
    return depth


def _hertz_nodal_pressure(tri, key, n, p0, a, subdivisions=24):
    """Hertz's pressure ``p0 sqrt(1 - r^2 / a^2)`` seen as a nodal pressure is: at each vertex
    of the flat triangles ``tri`` (m, 3, 3) (``key``: rounded position -> index < n), the
    pressure weighted by the vertex's hat function, ``int p phi_i dA / int phi_i dA``, by the
    centroid rule on ``subdivisions**2`` sub-triangles of each triangle. A nodal force divided
    by its tributary area estimates that, not p0: at the pole it lies below p0 by about
    ``3 h^2 / (20 a^2)`` for hat functions reaching a distance h (a disc)."""
    k = subdivisions
    bary = []
    for i in range(k):
        for j in range(k - i):
            bary.append(((i + 1 / 3) / k, (j + 1 / 3) / k))  # upright sub-triangles
            if i + j < k - 1:
                bary.append(((i + 2 / 3) / k, (j + 2 / 3) / k))  # inverted ones
    lam = np.array([(1 - b1 - b2, b1, b2) for b1, b2 in bary])  # (q, 3), equal weights
    points = np.einsum("qc,mcd->mqd", lam, tri)
    r2 = points[..., 0] ** 2 + points[..., 1] ** 2
    p = p0 * np.sqrt(np.clip(1 - r2 / a**2, 0.0, None))
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    moments = area[:, None] * np.einsum("mq,qc->mc", p, lam) / lam.shape[0]
    weight = np.zeros(n)
    num = np.zeros(n)
    for corners, m_c, a_t in zip(tri, moments, area, strict=True):
        for c, m in zip(corners, m_c, strict=True):
            i = key.get(tuple(np.round(c, 9)))
            if i is not None:
                num[i] += m
                weight[i] += a_t / 3
    return np.where(weight > 0, num / np.maximum(weight, 1e-300), 0.0)


def _cell_stress(V, u, cells, mu, lmbda):
    """The Cauchy stress ``sigma(u) = 2 mu eps(u) + lambda tr(eps(u)) I`` of the P1
    displacement ``u`` in the local cells ``cells`` (constant on each), (n, 3, 3), from the
    reference vertex coordinates: ``grad u`` solves ``(x_i - x_0) . grad u_a = u_ia - u_0a``."""
    dofs = np.asarray(V.dofmap.list)[cells]
    x = V.tabulate_dof_coordinates()[dofs]
    values = u.x.array.reshape(-1, 3)[dofs]
    grad = np.linalg.solve(x[:, 1:] - x[:, :1], values[:, 1:] - values[:, :1]).transpose(0, 2, 1)
    strain = 0.5 * (grad + grad.transpose(0, 2, 1))
    trace = np.trace(strain, axis1=1, axis2=2)
    return 2 * mu * strain + lmbda * trace[:, None, None] * np.eye(3)


def _owned_boundary_facets(V):
    """The exterior facets this rank owns (each facet of the mesh on one rank): their cell
    (local index), vertex coordinates (n, 3, 3) and outward unit normal (n, 3), reference
    configuration. A tetrahedron's facet i is opposite its vertex i (the P1 dofs follow the
    reference vertex order)."""
    mesh = V.mesh
    facets = owned_exterior_facets(mesh)
    mesh.topology.create_connectivity(2, 3)
    mesh.topology.create_connectivity(3, 2)
    f2c = mesh.topology.connectivity(2, 3)
    cell = np.asarray(f2c.array)[np.asarray(f2c.offsets)[facets]]
    c2f = np.asarray(mesh.topology.connectivity(3, 2).array).reshape(-1, 4)
    opposite = np.argmax(c2f[cell] == facets[:, None], axis=1)
    others = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
    dofs = np.asarray(V.dofmap.list)[cell]
    X = V.tabulate_dof_coordinates()
    tri = X[np.take_along_axis(dofs, others[opposite], axis=1)]
    apex = X[dofs[np.arange(cell.size), opposite]]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    inward = np.einsum("ij,ij->i", normal, apex - tri[:, 0]) > 0.0
    normal[inward] *= -1.0
    return cell, tri, normal


def _stress_pressure_max(comm, V, u, mu, lmbda, cell, tri, normal, select):
    """The largest normal traction ``-sigma(u) n . n`` (compression positive) over the owned
    boundary facets ``select`` (a mask of ``_owned_boundary_facets``'s), ``n`` the facet's
    outward normal and sigma its cell's (constant for P1), over all ranks, and the radius
    ``sqrt(x^2 + y^2)`` of that facet's centroid: (p, r), (0, nan) without facets."""
    sigma = _cell_stress(V, u, cell[select], mu, lmbda)
    n = normal[select]
    p = -np.einsum("fi,fij,fj->f", n, sigma, n)
    local = (-np.inf, np.nan)
    if p.size:
        i = int(np.argmax(p))
        centroid = tri[select][i].mean(axis=0)
        local = (float(p[i]), float(np.hypot(centroid[0], centroid[1])))
    best = max(comm.allgather(local), key=lambda pr: pr[0])
    return best if np.isfinite(best[0]) else (0.0, np.nan)


def _nearest_nodes(V, cells, points):
    """Local P1 nodes (vertices) of ``cells`` nearest to each of ``points``, the nearest over
    all ranks (a rank holding it, owned or ghost, returns it; collective)."""
    nodes = np.unique(np.asarray(V.dofmap.list)[cells])
    X = V.tabulate_dof_coordinates()[nodes]
    found = [np.empty(0, dtype=nodes.dtype)]
    for point in points:
        d = np.linalg.norm(X - np.asarray(point), axis=1)
        nearest = V.mesh.comm.allreduce(float(d.min()) if d.size else np.inf, op=MPI.MIN)
        found.append(nodes[d <= nearest])
    return np.unique(np.concatenate(found))


def _gather(V, rows):
    n_owned = V.dofmap.index_map.size_local
    return np.concatenate(V.mesh.comm.allgather(np.asarray(rows)[:n_owned]))


def run(
    res: float,
    method: str,
    factor: float,
    tol_delta: float,
    steps: int,
    relaxation: float | None = None,
    max_updates: int = 20,
    start_factor: float = 10.0,
    growth: float = 10.0,
    damping: bool = True,
    pressure_term: str = "linear",
    model: str = "quarter",
    petsc_options: dict | None = None,
    damp_free_bodies: bool = True,
) -> dict:
    comm = MPI.COMM_WORLD
    full = model == "full"
    copies = 1 if full else 4  # of the meshed bodies in the full problem
    mesh, cell_tags, facet_tags = hertz.hertz_mesh(
        comm, radius=RADIUS, block_width=WIDTH / 2, block_depth=DEPTH, contact_size=res,
        far_size=2 * res, refine_radius=RADIUS / 2, coarsen_radius=RADIUS, full=full,
    )  # fmt: skip
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    mu = YOUNGS / (2 * (1 + POISSON))
    lmbda = YOUNGS * POISSON / ((1 + POISSON) * (1 - 2 * POISSON))
    eps_u = ufl.sym(ufl.grad(u))
    density = 3 * LOAD / (4 * np.pi * RADIUS**3)
    scale = dolfinx.fem.Constant(mesh, PETSc.ScalarType(0.0))
    dx = ufl.Measure("dx", domain=mesh, subdomain_data=cell_tags)
    energy = (mu * ufl.inner(eps_u, eps_u) + 0.5 * lmbda * ufl.tr(eps_u) ** 2) * dx
    energy = energy + scale * density * u[2] * dx(hertz.SPHERE)
    # the hemisphere is held only by contact: damp its rigid motion (a first proximal step of
    # a hundredth of the contact mesh size under the full body force), removed at each solve's
    # end (fm.RigidModeDamping)
    damping_term, stiffness, anchor = fm.damping_energy(u, dx(hertz.SPHERE), density / (0.01 * res))
    if damping:
        energy = energy + damping_term
    residual = ufl.derivative(energy, u, ufl.TestFunction(V))
    zero = PETSc.ScalarType(0.0)

    def roller(tag, component):
        dofs = dolfinx.fem.locate_dofs_topological(V.sub(component), 2, facet_tags.find(tag))
        return dolfinx.fem.dirichletbc(zero, dofs, V.sub(component))

    bottom = dolfinx.fem.locate_dofs_topological(V, 2, facet_tags.find(hertz.BLOCK_BOTTOM))
    bcs = [dolfinx.fem.dirichletbc(np.zeros(3, dtype=PETSc.ScalarType), bottom, V)]
    if full:
        # the peer's supports: x and y of three sphere vertices (which remove the sphere's
        # horizontal rigid motions and leave the vertical one to contact)
        points = [(0.0, 0.0, RADIUS), (0.0, 0.0, RADIUS / 2), (0.0, RADIUS / 2, RADIUS / 2)]
        pins = _nearest_nodes(V, cell_tags.find(hertz.SPHERE), points)
        bcs += [
            dolfinx.fem.dirichletbc(zero, (3 * pins + c).astype(np.int32), V.sub(c)) for c in (0, 1)
        ]
        depth = fm.material_depth(mesh)
    else:
        bcs += [roller(hertz.SYMMETRY_X, 0), roller(hertz.SYMMETRY_Y, 1)]
        depth = _full_body_depth(mesh, 1e-9 * RADIUS)
    penalty = fm.propose_penalty(mesh, YOUNGS, factor=factor)
    contact = fm.ContactOperator(u, depth, penalty=penalty)
    problem = fm.ContactProblem(
        residual, u, contact, bcs=bcs, energy=energy,
        petsc_options={"snes_rtol": 1e-8} | (petsc_options or {}),
        damp_free_bodies=damp_free_bodies,
    )  # fmt: skip
    force = LOAD / 2
    e_star = YOUNGS / (2 * (1 - POISSON**2))
    a_theory = (3 * force * RADIUS / (4 * e_star)) ** (1 / 3)
    delta = a_theory**2 / RADIUS
    p0 = 3 * force / (2 * np.pi * a_theory**2)
    solver = fm.RigidModeDamping(problem, stiffness, anchor) if damping else problem
    if method == "continuation":
        solver = fm.PenaltyContinuation(
            solver, start=fm.propose_penalty(mesh, YOUNGS, factor=start_factor), growth=growth
        )
    if method == "augmented":
        solver = fm.AugmentedLagrangian(
            solver, tol=tol_delta * delta, max_updates=max_updates, relaxation=relaxation,
            pressure_term=pressure_term,
        )  # fmt: skip
    stages = []  # continuation: (load, penalty, Newton iterations, converged) of every stage

    def converged_step(t):
        for s in getattr(solver, "history", []) if method == "continuation" else []:
            stages.append((t, s.penalty, s.newton_iterations, s.converged))

    tic = time.perf_counter()
    load_steps = fm.solve_load_steps(
        solver, lambda t: setattr(scale, "value", t), num_steps=steps, progress=False,
        writer=converged_step,
    )  # fmt: skip
    seconds = comm.allreduce(time.perf_counter() - tic, op=MPI.MAX)

    # nodal contact forces and the block's top-face tributary areas
    n = V.dofmap.index_map.size_global
    dofs, values = contact.gradient_array()
    dofs = np.concatenate(comm.allgather(dofs))
    values = np.concatenate(comm.allgather(values))
    f = -np.bincount(dofs, weights=values, minlength=3 * n).reshape(-1, 3)
    X = _gather(V, V.tabulate_dof_coordinates())
    imap = V.dofmap.index_map
    body = np.zeros(imap.size_local + imap.num_ghosts, dtype=np.int8)
    body[np.asarray(V.dofmap.list)[cell_tags.find(hertz.SPHERE)].ravel()] = 1
    sphere = _gather(V, body) == 1
    top = ~sphere & (np.abs(X[:, 2]) < 1e-9 * RADIUS)
    tri = boundary_triangles(mesh)
    flat = np.all(np.abs(tri[:, :, 2]) < 1e-9 * RADIUS, axis=1)
    areas = 0.5 * np.linalg.norm(
        np.cross(tri[flat, 1] - tri[flat, 0], tri[flat, 2] - tri[flat, 0]), axis=1
    )
    key = {tuple(np.round(x, 9)): i for i, x in enumerate(X[top])}
    tributary = np.zeros(int(top.sum()))
    for corners, area in zip(tri[flat], areas, strict=True):
        for c in corners:
            i = key.get(tuple(np.round(c, 9)))
            if i is not None:
                tributary[i] += area / 3
    fz = -f[top, 2]  # the block is pushed down
    # the sphere's only flat-face-down contact point is the pole: its top-face triangles at
    # z = 0 do not exist, so every flat triangle is the block's
    pressure = np.where(tributary > 0, fz / np.maximum(tributary, 1e-300), 0.0)
    r2 = X[top, 0] ** 2 + X[top, 1] ** 2
    # the same measure applied to Hertz's pressure on this mesh
    p_ref = _hertz_nodal_pressure(tri[flat], key, int(top.sum()), p0, a_theory)
    pole = int(np.argmin(r2))
    a_moment = np.sqrt(2.5 * np.sum(fz * r2) / np.sum(fz))
    transmitted = copies * np.sum(f[sphere, 2])
    overlap = contact.max_penetration()

    # the peer's measure: the normal traction -sigma(u) n . n of the bulk stress on the contact
    # facets, constant per facet for P1; the block's top face (n = +z) and the sphere's curved
    # surface (off the symmetry planes and the flat top z = R)
    u.x.scatter_forward()
    cell, facet_x, normal = _owned_boundary_facets(V)

    def on_plane(axis, value):
        return np.all(np.abs(facet_x[:, :, axis] - value) < 1e-9 * RADIUS, axis=1)

    block_face = on_plane(2, 0.0)  # the sphere touches z = 0 at its pole only
    # (z > 0 with a margin: the block's top face lies at z = 0 up to rounding)
    sphere_face = facet_x[:, :, 2].mean(axis=1) > 1e-9 * RADIUS
    sphere_face &= ~(on_plane(0, 0.0) | on_plane(1, 0.0) | on_plane(2, RADIUS))
    stress_block = _stress_pressure_max(comm, V, u, mu, lmbda, cell, facet_x, normal, block_face)
    stress_sphere = _stress_pressure_max(comm, V, u, mu, lmbda, cell, facet_x, normal, sphere_face)

    # pointwise contact pressure eps g + p at the penetrating boundary vertices, at the pole
    # the block's vertex plus the sphere's (both at the origin in the reference configuration)
    g = contact.vertex_penetration()
    nodal_p = np.zeros(n) if contact.pressure is None else contact.pressure
    width = getattr(solver, "width", 0.0)
    if width > 0.0:
        # the quadratic pressure term: stiffness eps + p_T / w, with the vertex's own nodal
        # pressure standing in for the triangle's mean p_T (approximate)
        pointwise = np.where(g > 0.0, (contact.penalty + nodal_p / width) * g, 0.0)
    else:
        pointwise = np.where(g > 0.0, contact.penalty * g + nodal_p, 0.0)
    block_pole = np.flatnonzero(top)[pole]
    on_sphere = np.flatnonzero(sphere)
    sphere_pole = on_sphere[np.argmin(np.linalg.norm(X[on_sphere], axis=1))]
    # int (p + eps g) dA over each surface's intersection polygons (the hat functions sum to 1)
    gmom, amom = contact.pressure_moments()
    if width > 0.0:
        carried = (contact.penalty + nodal_p / width) * gmom  # p_T as above: approximate
    else:
        carried = contact.penalty * gmom + nodal_p * amom
    # the same integral from the vertex values alone (each times a third of the current area
    # of its boundary triangles): it agrees with the exact one only if the vertex values
    # represent the field between them
    surface = contact.surface
    tri_v = np.concatenate(comm.allgather(surface.global_vertex[surface.tri]))
    # not the triangles on the symmetry planes, which the full bodies do not have
    tri_v = tri_v[~np.any(np.all(np.abs(X[tri_v, :2]) < 1e-9 * RADIUS, axis=1), axis=1)]
    x = X + _gather(V, u.x.array.reshape(-1, 3))
    e1, e2 = x[tri_v[:, 1]] - x[tri_v[:, 0]], x[tri_v[:, 2]] - x[tri_v[:, 0]]
    third = np.linalg.norm(np.cross(e1, e2), axis=1) / 6
    lumped = pointwise * np.bincount(tri_v.ravel(), weights=np.repeat(third, 3), minlength=n)
    out = {
        "res": res,
        "model": model,
        "method": method,
        "vertices": n,
        "cells": mesh.topology.index_map(3).size_global,
        "dofs": 3 * n,
        "penalty": penalty,
        "factor": factor,
        "newton": sum(s.iterations for s in load_steps),
        "cuts": sum(s.cuts for s in load_steps),
        "seconds": seconds,
        "force": transmitted,
        "force_block": copies * np.sum(fz),
        "delta": delta,
        "overlap_delta": overlap / delta,
        "p0": p0,
        "p_max": float(pressure.max()),
        "p_error": float(pressure.max()) / p0 - 1,
        "p_ref_pole": float(p_ref[pole]),
        "p_ref_error": float(pressure.max()) / float(p_ref[pole]) - 1,
        "p_stress": stress_block[0],
        "p_stress_r": stress_block[1],
        "p_stress_error": stress_block[0] / p0 - 1,
        "p_stress_sphere": stress_sphere[0],
        "p_stress_sphere_r": stress_sphere[1],
        "p_stress_sphere_error": stress_sphere[0] / p0 - 1,
        "p_point_block": float(pointwise[block_pole]),
        "p_point_sphere": float(pointwise[sphere_pole]),
        "p_point": float(pointwise[block_pole] + pointwise[sphere_pole]),
        "p_point_error": float(pointwise[block_pole] + pointwise[sphere_pole]) / p0 - 1,
        "carried_block": copies * float(carried[~sphere].sum()),
        "carried_sphere": copies * float(carried[sphere].sum()),
        "lumped_block": copies * float(lumped[~sphere].sum()),
        "lumped_sphere": copies * float(lumped[sphere].sum()),
        "a": a_theory,
        "a_moment": a_moment,
        "a_error": a_moment / a_theory - 1,
    }
    if method == "augmented":
        out["pressure_term"] = pressure_term
        out["updates"] = solver.total_updates
        out["overlap_tol"] = overlap / solver.tolerance
    if method == "continuation":
        out["stages"] = stages
        out["stage_solves"] = solver.total_stages
        out["retries"] = solver.total_retries
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--res", type=float, nargs="+", default=[1.0, 0.5])
    parser.add_argument(
        "--method", choices=["penalty", "augmented", "continuation", "both"], default="both"
    )
    parser.add_argument(
        "--factor",
        type=float,
        nargs="+",
        default=[None],
        help="propose_penalty factors, one run each (default 10; 100 for the augmented "
        "Lagrangian, which at 10 needs 520 pressure updates and 15 cuts at res 1.0)",
    )
    parser.add_argument(
        "--tol", type=float, default=0.05, help="augmented: overlap tolerance / delta"
    )
    parser.add_argument("--steps", type=int, default=4)
    parser.add_argument(
        "--model",
        choices=["quarter", "full"],
        default="full",
        help="full: the peer's full model and supports; quarter: a quarter of it on symmetry "
        "planes (about a quarter of the vertices)",
    )
    parser.add_argument("--petsc", nargs="*", default=[], help="extra PETSc options key=value")
    parser.add_argument(
        "--relaxation",
        type=float,
        default=None,
        help="augmented: Uzawa omega (default 0.5 with the linear pressure term, 1 quadratic)",
    )
    parser.add_argument(
        "--pressure-term",
        choices=["linear", "quadratic"],
        default="linear",
        help="augmented: the pressure term of AugmentedLagrangian (quadratic: C1, stiffness "
        "eps + p / w with w half the tolerance)",
    )
    parser.add_argument("--max-updates", type=int, default=20, help="augmented: per step")
    parser.add_argument(
        "--start-factor", type=float, default=10.0, help="continuation: first stage's factor"
    )
    parser.add_argument("--growth", type=float, default=10.0, help="continuation: per stage")
    parser.add_argument(
        "--no-damping",
        action="store_true",
        help="without RigidModeDamping and its term in the energy: the plain problem, whose "
        "automatic handling of bodies held only by contact (ContactProblem's damp_free_bodies) "
        "damps the hemisphere",
    )
    parser.add_argument(
        "--no-free-body-damping",
        action="store_true",
        help="ContactProblem(damp_free_bodies=False); with --no-damping the first step fails",
    )
    args = parser.parse_args()
    methods = ["penalty", "augmented"] if args.method == "both" else [args.method]

    def label(row):
        if row.get("pressure_term") == "quadratic":
            return "augmented (quadratic)"
        return row["method"]

    rows = []
    for res, method, given in [(r, m, f) for r in args.res for m in methods for f in args.factor]:
        try:
            factor = given or (100.0 if method == "augmented" else 10.0)
            row = run(
                res, method, factor, args.tol, args.steps, args.relaxation,
                args.max_updates, args.start_factor, args.growth, not args.no_damping,
                args.pressure_term, args.model, dict(o.split("=", 1) for o in args.petsc),
                not args.no_free_body_damping,
            )  # fmt: skip
        except RuntimeError as err:
            if MPI.COMM_WORLD.rank == 0:
                print(f"res {res} {method}: FAILED: {str(err)[:300]}", flush=True)
            continue
        rows.append(row)
        if MPI.COMM_WORLD.rank == 0:
            print(
                f"res {res:4.2f} {args.model} {label(row):9s} {row['vertices']:6d} vertices "
                f"{row['cells']:6d} cells  eps {row['penalty']:.4g} "
                f"({row['factor']:g} E/h)  newton {row['newton']:3d}"
                f"{'  updates ' + str(row['updates']) if 'updates' in row else ''}  "
                f"cuts {row['cuts']}  {row['seconds']:6.1f} s  F {row['force']:.4f} "
                f"(block {row['force_block']:.4f})  overlap/delta "
                f"{row['overlap_delta']:.3f}  p_max {row['p_max']:.3f} vs p0 {row['p0']:.3f}"
                f" ({row['p_error']:+.1%}, peer {PEER_PMAX_ERROR.get(res, np.nan):+.1%})  "
                f"p_max from the stress -sigma n.n: block {row['p_stress']:.3f} "
                f"({row['p_stress_error']:+.1%}, r {row['p_stress_r']:.3f}), sphere "
                f"{row['p_stress_sphere']:.3f} ({row['p_stress_sphere_error']:+.1%}, r "
                f"{row['p_stress_sphere_r']:.3f})  "
                f"a {row['a_moment']:.3f} vs {row['a']:.3f} ({row['a_error']:+.1%})  "
                f"Hertz as nodal pressure at the pole {row['p_ref_pole']:.3f} "
                f"({row['p_ref_pole'] / row['p0'] - 1:+.1%} of p0; p_max "
                f"{row['p_ref_error']:+.1%} of it)"
                + (
                    f"  stage solves {row['stage_solves']} (retries {row['retries']})"
                    if "stages" in row
                    else ""
                ),
                flush=True,
            )
            quadratic = row.get("pressure_term") == "quadratic"
            density = "(eps + p_i / w) g" if quadratic else "eps g + p"
            print(
                f"    pointwise pressure {density} at the pole {row['p_point']:.3f} (block "
                f"{row['p_point_block']:.3f} + sphere {row['p_point_sphere']:.3f}; "
                f"{row['p_point_error']:+.1%} of p0, peer "
                f"{PEER_PMAX_ERROR.get(res, np.nan):+.1%})  int ({density}) dA"
                f"{' (p_i for p_T: approximate)' if quadratic else ''}: block "
                f"{row['carried_block']:.4f} + sphere {row['carried_sphere']:.4f} = "
                f"{row['carried_block'] + row['carried_sphere']:.4f} (F {row['force']:.4f}); "
                f"from the vertex values: block {row['lumped_block']:.4f} + sphere "
                f"{row['lumped_sphere']:.4f}",
                flush=True,
            )
            for load, penalty, its, ok in row.get("stages", []):
                print(
                    f"    load {load:.4g}  penalty {penalty:.4g}  newton {its:3d}"
                    f"{'' if ok else '  failed'}",
                    flush=True,
                )


if __name__ == "__main__":
    main()
