"""Cattaneo-Mindlin: a tangential force T < mu N on a Hertz contact; the stick radius against
``c / a = (1 - T / (mu N))^(1/3)``.

The full Hertz model of ``bench_hertz.py`` (``meshes/hertz.py``, ``full=True``: a hemisphere
of radius R = 8 on a 20 x 20 x 20 block, mesh size ``res`` within R/2 of the contact point,
``2 res`` from R on), both bodies linearly elastic with E = 200, nu = 0.3 (equal materials:
Dundurs' beta is 0, so the tangential load leaves the normal pressure as it is, Mindlin's
assumption). The block's bottom is clamped and the hemisphere's flat face is held and moved as
a rigid plate: pressed down by ``--press`` in two load steps (friction on, ``mu = 0.3``), then,
from that pressed state (the friction's reference), moved sideways by a prescribed ``dx`` in
one step, once per ``dx`` of ``--shifts`` (each from the pressed state again). One step from
the reference measures the whole slip since the pressed state, as Mindlin's monotone loading.

Measured per shift: T, the x force the contact puts on the hemisphere; N, the normal force at
the reference (so ``mu N`` is the friction's bound, the pressure being lagged); the contact
area ``A`` (the quadrature weights of the friction points, both surfaces, so ``2 pi a^2``) and
the stick area ``A_stick`` (those of the points that slip less than the slip tolerance: the
status the contact fields show), ``c / a = sqrt(A_stick / A)``; the same from the vertices'
status field on the block's top face (the share of its contact vertices that stick; the
refined mesh is about uniform there); and c / a from the traction along the load, averaged
over rings about the contact's centre (:func:`traction_stick_radius`: where the ratio of the
x traction to ``mu p`` falls below 0.95 coming in from the edge; with 20 rings, and 10 and 30
for the measure's own spread), which does not depend on the slip tolerance as the status
does. Theory: ``(1 - T / (mu N))^(1/3)`` at the measured T.

Run: ``scripts/fenicsx python3 benchmarks/bench_mindlin.py --res 0.5 [--press 1.0] [--shifts
0.1 0.2 0.3 0.4] [--slip-tol 1e-3 1e-4] [--save prefix]`` (61k cells at res 0.5, about 5
minutes for three shifts); each shift is solved once per slip tolerance; ``--save`` writes the
friction points of every shift to ``prefix_res<res>.npz``. Prints figures; asserts nothing.
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
from meshes import hertz

RADIUS, WIDTH, DEPTH = 8.0, 20.0, 20.0
YOUNGS, POISSON = 200.0, 0.3
MU = 0.3
RINGS = (20, 10, 30)  # ring counts of the traction's stick radius: the first is the figure


def run(
    res: float,
    press: float,
    shifts: list[float],
    slip_tol: float | list[float],
    radius: float = RADIUS,
    width: float = WIDTH,
    depth: float = DEPTH,
    press_steps: int = 2,
    factor: float = 10.0,
    increments: int = 1,
    comm: MPI.Comm = MPI.COMM_WORLD,
) -> dict:
    """Press, then shift sideways from the pressed state once per ``shifts``; the figures.

    Returns:
        ``N`` (the normal force at the reference), ``a`` (from the contact area), ``a_hertz``
        (from N), ``cells``, ``newton`` (press), and per shift (lists): ``dx``, ``T``, ``ratio``
        (T / mu N), ``c_points``, ``c_vertices`` (c / a measured both ways), ``c_theory``,
        ``newton``.
    """
    mesh, _, facet_tags = hertz.hertz_mesh(
        comm, radius=radius, block_width=width / 2, block_depth=depth, contact_size=res,
        far_size=2 * res, refine_radius=radius / 2, coarsen_radius=radius, full=True,
    )  # fmt: skip
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    mu = YOUNGS / (2 * (1 + POISSON))
    lmbda = YOUNGS * POISSON / ((1 + POISSON) * (1 - 2 * POISSON))
    eps_u = ufl.sym(ufl.grad(u))
    energy = (mu * ufl.inner(eps_u, eps_u) + 0.5 * lmbda * ufl.tr(eps_u) ** 2) * ufl.dx
    residual = ufl.derivative(energy, u, ufl.TestFunction(V))
    bottom = dolfinx.fem.locate_dofs_topological(V, 2, facet_tags.find(hertz.BLOCK_BOTTOM))
    top = dolfinx.fem.locate_dofs_topological(V, 2, facet_tags.find(hertz.SPHERE_TOP))
    plate = dolfinx.fem.Constant(mesh, np.zeros(3, dtype=PETSc.ScalarType))
    bcs = [
        dolfinx.fem.dirichletbc(np.zeros(3, dtype=PETSc.ScalarType), bottom, V),
        dolfinx.fem.dirichletbc(plate, top, V),
    ]
    penalty = fm.propose_penalty(mesh, YOUNGS, factor=factor)
    slip_tols = [slip_tol] if np.isscalar(slip_tol) else list(slip_tol)
    first = slip_tols[0] or None  # 0: the default, Coulomb's slip_tol=None
    contact = fm.ContactOperator(
        u, fm.material_depth(mesh), penalty=penalty, friction=fm.Coulomb(MU, slip_tol=first)
    )
    default_tol = contact.slip_tol if first is None else None
    slip_tols = [tol or default_tol for tol in slip_tols]
    if None in slip_tols:
        raise ValueError("slip_tol 0 (the default) must come first: it is the press's")
    problem = fm.ContactProblem(
        residual, u, contact, bcs=bcs, energy=energy, petsc_options={"snes_rtol": 1e-8}
    )
    pressed = fm.solve_load_steps(
        problem, lambda t: setattr(plate, "value", (0.0, 0.0, -press * t)),
        num_steps=press_steps, progress=False,
    )  # fmt: skip
    bulk = dolfinx.fem.form(residual)
    owned = top[top < V.dofmap.index_map.size_local]

    def plate_force() -> np.ndarray:
        """The force the contact puts on the hemisphere: minus the plate's reaction, the bulk
        residual at the plate's dofs (the elastic forces of a body sum to 0)."""
        r = dolfinx.fem.assemble_vector(bulk)
        r.scatter_reverse(dolfinx.la.InsertMode.add)
        local = r.array.reshape(-1, 3)[owned].sum(axis=0)
        return -comm.allreduce(local, op=MPI.SUM)

    normal_force = float(plate_force()[2])
    u_pressed = u.x.array.copy()
    area_total = _point_areas(contact)[0]
    a = np.sqrt(area_total / (2 * np.pi))
    e_star = YOUNGS / (2 * (1 - POISSON**2))
    out = {
        "cells": mesh.topology.index_map(3).size_global,
        "N": normal_force,
        "a": a,
        "a_hertz": (3 * normal_force * radius / (4 * e_star)) ** (1 / 3),
        "newton_press": sum(r.iterations for r in pressed),
        "bound": contact.comm.allreduce(
            float(np.sum(contact.friction_points()["weight"])), op=MPI.SUM
        ),
        "rows": [],
    }
    nodes = _node_coordinates(V)
    for dx, tol in ((dx, tol) for dx in shifts for tol in slip_tols):
        # the press used the first tolerance; the shift's stick/slip branch uses this one
        contact.slip_tol = tol
        u.x.array[:] = u_pressed
        plate.value = (dx, 0.0, -press)
        tic = time.perf_counter()
        if increments == 1:
            result = problem.solve()
            iterations = result.iterations
        else:  # load steps, the friction's reference advanced after each but the last
            steps = fm.solve_load_steps(
                problem, lambda t, dx=dx: setattr(plate, "value", (dx * t, 0.0, -press)),
                num_steps=increments - 1, end=(increments - 1) / increments, progress=False,
            )  # fmt: skip
            plate.value = (dx, 0.0, -press)
            result = problem.solve()  # measured before an advance() zeroes the slips
            iterations = sum(r.iterations for r in steps) + result.iterations
        seconds = time.perf_counter() - tic
        tangential = -float(plate_force()[0])  # friction holds the hemisphere back
        total, stick = _point_areas(contact)
        ratio = tangential / (MU * normal_force)
        points = _point_profile(contact, nodes, _node_coordinates(V, u))
        out["rows"].append(
            {
                "dx": dx,
                "slip_tol": tol,
                "T": tangential,
                "ratio": ratio,
                "ratio_bound": tangential / out["bound"],
                "c_points": float(np.sqrt(stick / total)),
                "c_vertices": _vertex_stick_share(contact, mesh) ** 0.5,
                "c_traction": {n: traction_stick_radius(points, a, rings=n) for n in RINGS},
                "c_theory": float(max(1.0 - ratio, 0.0) ** (1 / 3)),
                "newton": iterations,
                "seconds": seconds,
                "points": points,
            }
        )
        if increments > 1:  # the pressed state the friction's reference again
            u.x.array[:] = u_pressed
            contact.advance()
    return out


def traction_stick_radius(
    points: dict[str, np.ndarray], a: float, rings: int = 20, level: float = 0.95
) -> float:
    """The stick radius over ``a`` from the traction along the load, averaged over rings.

    Each friction point's tangential force is taken along x with the sign of its body's total
    (so both surfaces count the traction that resists the shift); over rings of width
    ``a / rings`` about the contact's centre (the points' centroid weighted by their bound),
    the ratio ``sum q_x / sum mu p w``. In Mindlin's solution that ratio is
    ``1 - sqrt((c^2 - r^2) / (a^2 - r^2))`` inside the stick zone and 1 outside: the radius
    where it last falls below ``level`` coming in from the edge (linear between the rings'
    middles) is c (0.95 places Mindlin's own profile within 0.3 % of c). Unlike a point's
    status (its slip below the slip tolerance), this does not count as slipping the stick
    zone's points whose discrete creep exceeds the tolerance in some other direction: such
    creep, in varying directions, makes ``|t_T|`` reach ``mu p`` while the traction along the
    load stays below it on average.

    Args:
        points: the friction points of ``_point_profile``: ``x``, ``weight``, ``force``,
            ``body``.
        a: the contact radius.
        rings: the number of rings over ``[0, a]``.
        level: the traction ratio that marks the edge of the stick zone.

    Returns:
        c / a.
    """
    x, weight, force, body = (points[k] for k in ("x", "weight", "force", "body"))
    sign = np.zeros(len(weight))
    for b in np.unique(body):
        mine = body == b
        sign[mine] = np.sign(force[mine, 0].sum())
    centre = (weight[:, None] * x).sum(axis=0) / weight.sum()
    r = np.hypot(x[:, 0] - centre[0], x[:, 1] - centre[1])
    ring = np.minimum((r / a * rings).astype(int), rings)  # beyond a: an extra ring, unused
    q = np.bincount(ring, force[:, 0] * sign, minlength=rings + 1)[:rings]
    bound = np.bincount(ring, weight, minlength=rings + 1)[:rings]
    profile = np.where(bound > 0, q / np.where(bound > 0, bound, 1.0), 1.0)
    middle = (np.arange(rings) + 0.5) / rings
    below = np.flatnonzero(profile < level)
    if below.size == 0:
        return 0.0
    j = below[-1]
    if j == rings - 1:
        return 1.0
    step = (level - profile[j]) / (profile[j + 1] - profile[j])
    return float(middle[j] + step * (middle[j + 1] - middle[j]))


def _node_coordinates(V, u=None) -> np.ndarray:
    """The coordinates of every node by its global number, reference or moved by ``u``
    (gathered to all ranks)."""
    imap = V.dofmap.index_map
    n = imap.size_local
    X = np.zeros((imap.size_global, 3))
    x = V.tabulate_dof_coordinates()[:n]
    if u is not None:
        x = x + u.x.array.reshape(-1, 3)[:n]
    X[imap.local_to_global(np.arange(n, dtype=np.int32))] = x
    return V.mesh.comm.allreduce(X, op=MPI.SUM)


def _point_profile(
    contact: fm.ContactOperator, nodes: np.ndarray, moved: np.ndarray
) -> dict[str, np.ndarray]:
    """Per friction point (gathered): its triangle point, reference ``X`` and current ``x``
    (nq, 3), its area, friction bound ``mu p w``, slip length, traction ratio
    ``|t_T| / (mu p)``, tangential force and slip vectors (on the triangle's side) and the
    triangle's body."""
    p = contact.friction_points()
    bary, verts = p["coef"][:, :3], p["verts"][:, :3]
    local = {
        "X": np.einsum("qk,qkd->qd", bary, nodes[verts]),
        "x": np.einsum("qk,qkd->qd", bary, moved[verts]),
        "area": p["area"],
        "weight": p["weight"],
        "slip_length": p["slip_length"],
        "ratio": p["ratio"],
        "force": p["force"],
        "slip": p["slip"],
        "body": contact.body_of_vertex[p["verts"][:, 0]],
    }
    return {k: np.concatenate(contact.comm.allgather(v)) for k, v in local.items()}


def _point_areas(contact: fm.ContactOperator) -> tuple[float, float]:
    """The friction points' area, all and sticking (summed over the ranks)."""
    p = contact.friction_points()
    stick = p["slip_length"] < contact.slip_tol
    comm = contact.comm
    return (
        comm.allreduce(float(p["area"].sum()), op=MPI.SUM),
        comm.allreduce(float(p["area"][stick].sum()), op=MPI.SUM),
    )


def _vertex_stick_share(contact: fm.ContactOperator, mesh) -> float:
    """The share of the block's top-face vertices in contact (status 1 or 2) that stick
    (status 1), from the contact fields (owned dofs, summed over the ranks)."""
    status = contact.fields()["status"]
    Q = status.function_space
    n = Q.dofmap.index_map.size_local
    X = Q.tabulate_dof_coordinates()[:n]
    values = status.x.array[:n]
    face = np.abs(X[:, 2]) < 1e-9 * RADIUS  # the block's top face (the sphere: only the pole)
    in_contact = int(np.count_nonzero(face & (values > 0.5)))
    sticking = int(np.count_nonzero(face & (np.abs(values - 1.0) < 0.5)))
    comm = mesh.comm
    in_contact, sticking = comm.allreduce(in_contact), comm.allreduce(sticking)
    return sticking / max(in_contact, 1)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--res", type=float, nargs="+", default=[0.5])
    parser.add_argument("--press", type=float, default=1.0, help="the plate's descent (L)")
    parser.add_argument(
        "--shifts", type=float, nargs="+", default=[0.1, 0.2, 0.3, 0.4], help="sideways (L)"
    )
    parser.add_argument(
        "--slip-tol", type=float, nargs="+", default=[1e-4],
        help="slip tolerances: each shift is solved with each (the press with the first; "
        "0 first: Coulomb's default)",
    )  # fmt: skip
    parser.add_argument(
        "--increments", type=int, default=1,
        help="load steps per shift (the friction's reference advanced after each)",
    )  # fmt: skip
    parser.add_argument("--save", help="save the friction points per shift to this .npz")
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    for res in args.res:
        tic = time.perf_counter()
        r = run(res, args.press, args.shifts, args.slip_tol, increments=args.increments)
        if comm.rank == 0:
            print(
                f"res {res}: {r['cells']} cells, press {args.press} ({r['newton_press']} Newton "
                f"iterations), N = {r['N']:.4g} (mu N = {MU * r['N']:.4g}, sum of the friction "
                f"points' bound {r['bound']:.4g}), a = {r['a']:.4f} from the contact area "
                f"(Hertz from N: {r['a_hertz']:.4f}), a / h = {r['a'] / res:.1f}, slip_tol "
                f"{args.slip_tol}, {args.increments} load step(s) per shift"
            )
            for row in r["rows"]:
                err = row["c_points"] / row["c_theory"] - 1 if row["c_theory"] > 0 else np.nan
                c_t = row["c_traction"]
                err_t = c_t[RINGS[0]] / row["c_theory"] - 1 if row["c_theory"] > 0 else np.nan
                others = ", ".join(f"{c_t[n]:.4f} with {n}" for n in RINGS[1:])
                print(
                    f"  dx {row['dx']:.3f}, slip_tol {row['slip_tol']:g}: T = {row['T']:.4g}, "
                    f"T / mu N = {row['ratio']:.4f} "
                    f"(over the points' bound {row['ratio_bound']:.4f}); c / a: points "
                    f"{row['c_points']:.4f}, vertex status {row['c_vertices']:.4f}, Mindlin "
                    f"{row['c_theory']:.4f} (points {err:+.1%}); traction along the load "
                    f"{c_t[RINGS[0]]:.4f} ({err_t:+.1%}; {RINGS[0]} rings, {others}); "
                    f"{row['newton']} Newton iterations, {row['seconds']:.1f} s"
                )
            print(f"  {time.perf_counter() - tic:.0f} s in all", flush=True)
            if args.save:
                arrays = {"N": r["N"], "a": r["a"]}
                for i, row in enumerate(r["rows"]):
                    arrays |= {f"{i}_{k}": v for k, v in row["points"].items()}
                    arrays |= {f"{i}_row_{k}": row[k] for k in ("dx", "slip_tol", "T", "ratio")}
                np.savez(f"{args.save}_res{res}.npz", **arrays)


if __name__ == "__main__":
    main()
