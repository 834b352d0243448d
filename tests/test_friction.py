"""Coulomb friction over the intersection polygons: the law's input checks, the lagged
potential's exact derivatives (finite differences, one pair and the operator), and a block
pulled over a plane (stick, then sliding at mu N)."""

from __future__ import annotations

from mpi4py import MPI

import dolfinx
import dolfinx.fem.petsc
import numpy as np
import pytest
import ufl
from conftest import (
    assert_fd_derivatives,
    assert_operator_derivatives,
    clamped_and_moved,
    merged_mesh,
    neo_hookean_residual,
    operator_residual,
)

import fenics_matdepth as fm
from fenics_matdepth.contact.kernels.friction import (
    empty_reference,
    friction_blocks,
    friction_pairs,
    friction_points,
    friction_reference,
)
from fenics_matdepth.meshing import box_tetrahedra

# -- the law -----------------------------------------------------------------------------------


def test_coulomb_checks_its_input_and_looks_up_pairs():
    assert fm.Coulomb(0.3).pair_mu(np.array([0, 1]), np.array([1, 1])).tolist() == [0.3, 0.3]
    law = fm.Coulomb({(1, 0): 0.5, (2, 2): 0.01}, slip_tol=1e-3, default=0.1)
    got = law.pair_mu(np.array([0, 1, 2, 0]), np.array([1, 0, 2, 2]))
    assert got.tolist() == [0.5, 0.5, 0.01, 0.1]
    for bad in (-0.1, float("nan"), "x"):
        with pytest.raises(ValueError, match="mu must be a number >= 0"):
            fm.Coulomb(bad)
    with pytest.raises(ValueError, match="pairs of body indices"):
        fm.Coulomb({(0, 1, 2): 0.3})
    with pytest.raises(ValueError, match="slip_tol must be a positive length"):
        fm.Coulomb(0.3, slip_tol=0.0)
    with pytest.raises(ValueError, match="default must be"):
        fm.Coulomb({(0, 1): 0.3}, default=-1.0)


# -- one pair: the kernels against finite differences ------------------------------------------

_TRI = np.array([[-0.2, 0.1, 0.3], [0.9, -0.1, 0.2], [0.1, 0.9, 0.35]])
_TET = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])


def _one_pair(depth: np.ndarray, split: bool, penalty: float = 40.0, mu: float = 0.4):
    """The lagged data of one (triangle, tetrahedron) pair at its reference state."""
    x0 = np.vstack((_TRI, _TET))
    tri = np.array([[0, 1, 2]], dtype=np.int32)
    tet = np.array([[3, 4, 5, 6, 7 if split else -1]], dtype=np.int32)
    pair = np.zeros(1, dtype=np.int32)
    args = (x0, depth, tri, tet, pair, pair, np.array([penalty]), np.zeros((1, 3)), np.array([mu]))
    nq = friction_reference(*args, False, *empty_reference())
    qpair = np.empty(nq, dtype=np.int32)
    coef, normal, weight = np.empty((nq, 7)), np.empty((nq, 3)), np.empty(nq)
    assert friction_reference(*args, True, qpair, coef, normal, weight, np.empty(nq)) == nq
    return x0, np.array([0, nq], dtype=np.int32), coef, normal, weight


@pytest.mark.parametrize(
    "case", ["stick_and_slip", "at_rest", "normal_motion_only", "split_tetrahedron"]
)
def test_pair_derivatives_match_finite_differences(case):
    rng = np.random.default_rng(7)
    split = case == "split_tetrahedron"
    # depths of the tetrahedron's vertices (then the centroid's, used when split)
    depth = np.array([0, 0, 0, 0.0, 0.0, 0.0, 0.0, 0.15]) if split else np.zeros(7)
    if not split:
        depth[3:7] = [0.3, 0.1, 0.05, 0.0]
    x0, qptr, coef, normal, weight = _one_pair(depth, split)
    assert qptr[1] >= 9 and np.all(weight > 0.0)
    # the lagged data: the slip is a relative displacement (coefficients sum to 0), unit normals
    assert np.allclose(coef.sum(axis=1), 0.0) and np.allclose(np.linalg.norm(normal, axis=1), 1)
    verts = np.arange(7, dtype=np.int32)[None]
    tol = 0.02
    du = {
        "stick_and_slip": 0.03 * rng.standard_normal((7, 3)),
        "at_rest": np.zeros((7, 3)),
        "normal_motion_only": np.outer(np.r_[np.ones(3), np.zeros(4)], normal[0]) * 0.1,
        "split_tetrahedron": 0.03 * rng.standard_normal((7, 3)),
    }[case]

    def f(z):
        e, g, h = friction_pairs(
            z.reshape(7, 3), verts, x0[None], qptr, coef, normal, weight, tol, True, True
        )
        return e[0], g[0], h[0]

    z0 = (x0 + du).ravel()
    if case in ("at_rest", "normal_motion_only"):
        # no slip: f0(|s|) has a |s|^3 term, so no finite differences across s = 0
        energy, grad, hess = f(z0)
    else:
        energy, grad, hess = assert_fd_derivatives(f, z0, rtol=1e-6, symmetric=True)
    slip, ratio, _, _ = friction_points(x0 + du, verts, x0[None], qptr, coef, normal, weight, tol)
    if case == "stick_and_slip" or split:
        assert np.any(slip < tol) and np.any(slip > tol)  # both branches of the mollifier
    if case in ("at_rest", "normal_motion_only"):
        assert energy <= 1e-28 and np.abs(grad).max() < 1e-14
        # the stick stiffness 2 c / e in the tangent plane, along each point's slip map
        b = np.stack([np.kron(c[None, :], np.eye(3)) for c in coef])  # (nq, 3, 21)
        proj = np.eye(3) - normal[:, :, None] * normal[:, None, :]
        expect = np.einsum("q,qia,qij,qjb->ab", 2.0 * weight / tol, b, proj, b)
        assert np.abs(hess - expect).max() <= 1e-12 * np.abs(expect).max()
    if case == "normal_motion_only":
        # a triangle moving along the (common) normal does not slip at points of that normal
        same = np.all(np.isclose(normal, normal[0]), axis=1)
        assert same.all() and np.allclose(slip, 0.0, atol=1e-14)
    # the Hessian is positive semi-definite (the potential is convex in the positions)
    assert np.linalg.eigvalsh(hess).min() >= -1e-10 * np.abs(hess).max()
    assert np.all(ratio <= 1.0)


def test_blocks_sum_the_pair_hessians():
    """friction_blocks, which sums each point's Hessian into 3 x 3 vertex blocks without
    forming the pair Hessians, equals the pair Hessians of friction_pairs summed into a dense
    matrix: two pairs sharing vertices (one pair's points twice, mapped onto other vertices),
    a Dirichlet dof's row and column left out, a coupling outside the pattern left out."""
    rng = np.random.default_rng(3)
    depth = np.zeros(7)
    depth[3:7] = [0.3, 0.1, 0.05, 0.0]
    x0, qptr1, coef1, normal1, weight1 = _one_pair(depth, False)
    nq = qptr1[1]
    # pair 1 the same points on vertices 0, 1, 2 (shared), 7, 8, 9, 10
    verts = np.array([[0, 1, 2, 3, 4, 5, 6], [0, 1, 2, 7, 8, 9, 10]], dtype=np.int32)
    xv = np.vstack((x0, x0[3:] + 0.01))
    xref = xv[verts]
    qptr = np.array([0, nq, 2 * nq], dtype=np.int32)
    coef, normal = np.vstack((coef1, coef1)), np.vstack((normal1, normal1))
    weight = np.concatenate((weight1, 0.5 * weight1))
    x = xv + 0.03 * rng.standard_normal(xv.shape)  # slips on both branches at tol 0.02
    tol = 0.02
    bc = np.zeros(3 * 11, dtype=bool)
    bc[3 * 4 + 1] = True  # vertex 4's y dof
    _, _, hess = friction_pairs(x, verts, xref, qptr, coef, normal, weight, tol, True, True)
    dense = np.zeros((33, 33))
    for p in range(2):
        dofs = (3 * verts[p][:, None] + np.arange(3)).ravel()
        dense[np.ix_(dofs, dofs)] += hess[p]
    dense[bc, :] = dense[:, bc] = 0.0
    # the pattern: every coupling of the two pairs except (5, 6), which is left out
    pairs_vv = sorted({(a, b) for v in verts for a in v for b in v} - {(5, 6)})
    index = {ab: k for k, ab in enumerate(pairs_vv)}
    slot = np.array([[[index.get((a, b), -1) for b in v] for a in v] for v in verts])
    blocks = np.zeros((len(pairs_vv), 3, 3))
    friction_blocks(x, verts, xref, qptr, coef, normal, weight, tol, slot, bc, blocks)
    assert np.abs(dense[15:18, 18:21]).max() > 0.0
    dense[15:18, 18:21] = 0.0  # the coupling (5, 6) outside the pattern
    summed = np.zeros((33, 33))
    for (a, b), k in index.items():
        summed[3 * a : 3 * a + 3, 3 * b : 3 * b + 3] = blocks[k]
    assert np.abs(summed - dense).max() <= 1e-13 * np.abs(dense).max()


# -- the operator: residual and Jacobian of the friction potential -----------------------------


def _two_boxes_with_friction(comm: MPI.Comm, friction: fm.Coulomb):
    """Two boxes in one mesh, the upper one sunk 0.2 into the lower one (the operator's
    reference state), as in test_operator."""
    mesh = merged_mesh(
        comm,
        box_tetrahedra(3, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)),
        box_tetrahedra(4, (0.23, 0.11, 0.8), (0.9, 0.8, 1.0)),
    )
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    op = fm.ContactOperator(
        u, fm.material_depth(mesh), penalty=50.0, friction=friction,
        allow_reference_overlap=True,  # the boxes overlap in the mesh on purpose
    )  # fmt: skip
    return V, u, op


def test_operator_friction_derivatives_match_finite_differences():
    comm = MPI.COMM_WORLD
    V, u, op = _two_boxes_with_friction(comm, fm.Coulomb(0.4, slip_tol=0.002))
    x = V.tabulate_dof_coordinates()
    # slips of a few slip tolerances: points on both branches of the mollifier
    u.x.array[:] = (0.02 * np.sin([3.1, 2.3, 1.7] * x + np.array([0.3, 0.1, 0.7]))).ravel()
    op.update()
    d = op.friction_diagnostics()
    assert d["stick_points"] > 0 and d["slip_points"] > 0
    assert 0.0 < d["friction_dissipation"] and d["max_traction_ratio"] == pytest.approx(1.0)
    assert_operator_derivatives(op, u, h=1e-6, rtol=1e-6)
    # advance: the current state is the reference, the friction potential is 0 there
    e_before = op.energy()
    op.advance()
    assert op.friction_diagnostics()["friction_dissipation"] == 0.0
    assert op.energy() < e_before


def test_friction_takes_the_augmented_lagrangians_pressure():
    """With the augmented Lagrangian's nodal pressures P the friction's normal traction is
    ``(eps g + P) |grad g|``: the friction force of a sliding state is affine in a uniform P,
    and larger with it; with the quadratic pressure term (width w) the penalty is
    ``eps + P / w``, so P = w eps doubles the force of P = 0."""
    comm = MPI.COMM_WORLD
    V, u, op = _two_boxes_with_friction(comm, fm.Coulomb(0.4, slip_tol=1e-6))
    x = V.tabulate_dof_coordinates()
    slide = (0.05 * np.sin([3.1, 2.3, 1.7] * x + np.array([0.3, 0.1, 0.7]))).ravel()

    def friction_force(pressure, width=0.0):
        u.x.array[:] = 0.0
        op.set_pressure(np.full(op.num_vertices, pressure), width)
        op.advance()
        u.x.array[:] = slide
        op.update()
        return op.friction_diagnostics()["friction_dissipation"]

    f0, f1, f2 = friction_force(0.0), friction_force(1.0), friction_force(2.0)
    assert f1 > f0 > 0.0 and f2 - f1 == pytest.approx(f1 - f0, rel=1e-9)
    width = 0.01
    assert friction_force(width * op.penalty, width) == pytest.approx(2.0 * f0, rel=1e-9)


# -- a block pulled over a plane ---------------------------------------------------------------

#: the block's top: pressed down by PRESS, then pulled along x to PULL[i] in the steps after
PRESS = 0.02
PULL = [0.002, 0.004, 0.04, 0.07, 0.1]
MU = 0.3


def _block_on_slab(comm: MPI.Comm):
    """A 0.6 x 0.6 x 0.4 block standing on a 1.5 x 1.5 x 0.5 slab, one mesh of two bodies."""
    return merged_mesh(
        comm,
        box_tetrahedra((6, 6, 2), (0.0, 0.0, 0.0), (1.5, 1.5, 0.5)),
        box_tetrahedra((4, 4, 2), (0.3, 0.45, 0.5), (0.6, 0.6, 0.4)),
    )


def _pulled_block(comm: MPI.Comm) -> list[dict]:
    """A 0.6 x 0.6 x 0.4 block on a 1.5 x 1.5 x 0.5 slab (neo-Hookean, E = 1, nu = 0.3):
    the slab's bottom clamped, the block's top pressed down by PRESS and then pulled along x.
    Per converged step: the friction force T and the normal force N on the block (from the
    residuals with and without friction), the work of the friction forces over the step's
    displacement and the operator's friction diagnostics."""
    mesh = _block_on_slab(comm)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    residual, psi = neo_hookean_residual(u)
    bcs, g = clamped_and_moved(V, lambda x: np.isclose(x[2], 0.0), lambda x: np.isclose(x[2], 0.9))
    depth = fm.material_depth(mesh)
    eps = fm.propose_penalty(mesh, 1.0)
    contact = fm.ContactOperator(u, depth, penalty=eps, friction=fm.Coulomb(MU))
    normal = fm.ContactOperator(u, depth, penalty=eps)  # the same contact, frictionless
    problem = fm.ContactProblem(
        residual, u, contact, bcs=bcs, energy=psi * ufl.dx, petsc_options_prefix="friction_"
    )
    table = np.array([[0.0, 0.0], [0.0, PRESS]] + [[p, PRESS] for p in PULL])

    def set_load(t):
        i = min(int(t), len(table) - 2)
        ux, uz = table[i] + (t - i) * (table[i + 1] - table[i])
        g.interpolate(
            lambda x: np.vstack((np.full(x.shape[1], ux), 0 * x[0], np.full(x.shape[1], -uz)))
        )

    n_owned = V.dofmap.index_map.size_local
    lo = V.dofmap.index_map.local_range[0]
    body = contact.body_of_vertex[lo + np.arange(n_owned)]
    z = V.tabulate_dof_coordinates()[:n_owned, 2]
    block = comm.allreduce(int(body[z > 0.6].max()) if np.any(z > 0.6) else -1, op=MPI.MAX)
    on_block = body == block
    steps, last = [], {"u": u.x.array[: 3 * n_owned].copy()}

    def measure(load):
        contact.update()
        normal.update()
        b_all = operator_residual(contact, V).array.reshape(-1, 3)
        b_normal = operator_residual(normal, V).array.reshape(-1, 3)
        b_friction = b_all - b_normal
        du = u.x.array[: 3 * n_owned] - last["u"]
        last["u"] = u.x.array[: 3 * n_owned].copy()
        if load == len(table) - 1.0:  # the last (sliding) step: the fields, on u's space
            fields = contact.fields()
            for name in ("pressure", "penetration", "status"):
                carrier = dolfinx.fem.Function(V)
                carrier.sub(0).interpolate(fields[name])
                fields[name] = carrier.x.array.reshape(-1, 3)[:n_owned, 0].copy()
            for name in ("traction", "slip"):
                fields[name] = fields[name].x.array.reshape(-1, 3)[:n_owned].copy()
            last["fields"] = fields
        steps.append({
            "load": load,
            "T": -comm.allreduce(float(b_friction[on_block, 0].sum())),
            "N": -comm.allreduce(float(b_normal[on_block, 2].sum())),
            "work": comm.allreduce(float(b_friction.ravel() @ du)),
        })  # fmt: skip

    # the writer sees each converged state before the friction's reference moves on
    records = fm.solve_load_steps(
        problem, set_load, num_steps=len(table) - 1, end=len(table) - 1.0, writer=measure,
        progress=False,
    )  # fmt: skip
    out = [
        {**s, **r.diagnostics, "iterations": r.iterations}
        for s, r in zip(steps, records, strict=True)
    ]
    bottom = on_block & np.isclose(z, 0.5)  # the block's face on the slab
    return out, {name: values[bottom] for name, values in last["fields"].items()}


_PULLED: dict = {}


def _pulled_block_once() -> tuple[list[dict], dict]:
    """:func:`_pulled_block` on COMM_WORLD, solved once for the tests that look at it."""
    if not _PULLED:
        _PULLED["run"] = _pulled_block(MPI.COMM_WORLD)
    return _PULLED["run"]


#: T and N of each step as measured serially (DOLFINx 0.9): any partition gives them
SERIAL_T_N = [
    (-3.62693e-10, 0.0130063), (-0.000433391, 0.0130354), (-0.000862712, 0.0130638),
    (-0.00393401, 0.0132368), (-0.00399034, 0.0133295), (-0.00401892, 0.0133203),
]  # fmt: skip


def test_block_pulled_over_a_plane_sticks_then_slides_at_mu_n():
    """While the pull is small the friction holds the block: every point sticks, and the
    tangential force is linear in the pull (the elastic branch: twice the pull, twice the force,
    within 1 %) and below mu N. Once every point slides the friction force is mu N within
    1 %. Each step's friction dissipation is positive and equals the work of the friction
    forces over the step's displacement (the assembled friction residual dotted with it), and
    the forces are those of the serial run on any number of processes."""
    steps, _ = _pulled_block_once()
    for s in steps:
        print(
            f"load {s['load']:.3f}: T {s['T']:+.6g} N {s['N']:.6g} T/(mu N) "
            f"{s['T'] / (MU * s['N']):+.5f} dissipation {s['friction_dissipation']:.4g} "
            f"work {s['work']:.4g} stick {s['stick_points']} slip {s['slip_points']} "
            f"max ratio {s['max_traction_ratio']:.4f} iterations {s['iterations']}"
        )
    assert [s["load"] for s in steps] == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]  # no cut
    stick, slide = steps[1:3], [s for s in steps[3:] if s["stick_points"] == 0]
    for s in stick:
        assert s["slip_points"] == 0 and s["max_traction_ratio"] < 1.0
        assert 0.0 < -s["T"] < MU * s["N"]
    assert stick[1]["T"] / stick[0]["T"] == pytest.approx(PULL[1] / PULL[0], rel=0.01)
    assert len(slide) >= 2
    for s in slide:
        assert -s["T"] == pytest.approx(MU * s["N"], rel=0.01)
    for s in steps:
        assert s["friction_dissipation"] >= 0.0
        assert s["work"] == pytest.approx(s["friction_dissipation"], rel=1e-8, abs=1e-15)
    measured = np.array([(s["T"], s["N"]) for s in steps])
    assert np.allclose(measured, SERIAL_T_N, rtol=1e-4, atol=1e-9)


def test_contact_fields_of_the_sliding_block():
    """fields() on the block's face in its last, sliding step: every vertex slips (status 2),
    by the step's pull along x (within 2 %: the block moves rigidly over the slab); the
    traction's normal part is the pressure (within 5 %, the face stays flat) and its
    tangential part opposes the slip at mu times the pressure (within 10 % per vertex: the
    friction's pressure is lagged by one step, and near the edges the depth's gradient
    bends)."""
    _, f = _pulled_block_once()
    comm = MPI.COMM_WORLD
    f = {k: np.concatenate(comm.allgather(v)) for k, v in f.items()}
    assert f["status"].size == 25 and np.all(f["status"] == 2)  # 5 x 5 vertices
    p, t, slip = f["pressure"], f["traction"], f["slip"]
    assert np.all(p > 0.0) and np.all(f["penetration"] > 0.0)
    assert np.allclose(slip[:, 0], PULL[-1] - PULL[-2], rtol=0.02)
    assert np.abs(slip[:, 1:]).max() < 0.05 * (PULL[-1] - PULL[-2])
    assert np.allclose(t[:, 2], p, rtol=0.05)
    assert np.allclose(-t[:, 0] / p, MU, rtol=0.1)


# -- a block on an incline under gravity (dynamics) --------------------------------------------

RHO, YOUNGS, GRAVITY, SLIP_TOL = 1.0, 1.0e3, 10.0, 5e-5


def _block_on_incline(comm: MPI.Comm, tan_theta: float, t_end: float = 0.4, dt: float = 0.02):
    """The block of :func:`_pulled_block` resting on the clamped slab, gravity tilted by theta
    from -z towards +x (the incline), backward Euler from rest, the block sunk
    by the penetration that carries its weight. Returns the times, the block's mean x velocity
    and the number of slipping friction points of each step."""
    mesh = _block_on_slab(comm)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    v = ufl.TestFunction(V)
    elastic, psi = neo_hookean_residual(u, YOUNGS, 0.3)
    theta = np.arctan(tan_theta)
    g = ufl.as_vector((GRAVITY * np.sin(theta), 0.0, -GRAVITY * np.cos(theta)))
    bottom = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[2], 0.0))
    bcs = [
        dolfinx.fem.dirichletbc(np.zeros(3), dolfinx.fem.locate_dofs_topological(V, 2, bottom), V)
    ]
    eps = fm.propose_penalty(mesh, YOUNGS)
    law = fm.Coulomb(MU, slip_tol=SLIP_TOL)
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=eps, friction=law)
    integrator = fm.BackwardEuler(u, dt, rho=RHO)
    residual = integrator.inertia(v) + elastic - RHO * ufl.inner(g, v) * ufl.dx
    n_owned = V.dofmap.index_map.size_local
    lo = V.dofmap.index_map.local_range[0]
    body = contact.body_of_vertex[lo + np.arange(n_owned)]
    X = V.tabulate_dof_coordinates()
    top = body[X[:n_owned, 2] > 0.6]
    block = comm.allreduce(int(top.max()) if top.size else -1, op=MPI.MAX)
    # both faces enter the other body: each carries half the weight's pressure
    sink = RHO * 0.4 * GRAVITY * np.cos(theta) / (2.0 * eps)
    on_block = (
        contact.body_of_vertex[
            V.dofmap.index_map.local_to_global(np.arange(X.shape[0], dtype=np.int32))
        ]
        == block
    )
    u0 = np.zeros((X.shape[0], 3))
    u0[on_block, 2] = -sink
    integrator.initial(u0.ravel(), None, residual=residual, contact=contact, bcs=bcs)
    energy = integrator.incremental_energy(psi * ufl.dx - RHO * ufl.inner(g, u) * ufl.dx)
    problem = fm.ContactProblem(
        residual, u, contact, bcs=bcs, energy=energy, petsc_options_prefix="incline_"
    )
    mass = dolfinx.fem.form(RHO * ufl.inner(ufl.TrialFunction(V), v) * ufl.dx)
    M = dolfinx.fem.petsc.assemble_matrix(mass)
    M.assemble()
    p = M.createVecLeft()
    times, momentum, slipping = [], [], []

    def track(record):
        M.mult(integrator.v_prev.x.petsc_vec, p)
        times.append(record.t)
        slipping.append(record.diagnostics["slip_points"])
        momentum.append(comm.allreduce(float(p.array_r.reshape(-1, 3)[body == block, 0].sum())))

    fm.solve_time_steps(problem, integrator, t_end, dt, on_step=track, progress=False)
    M.destroy()
    p.destroy()
    return np.array(times), np.array(momentum) / (RHO * 0.6 * 0.6 * 0.4), np.array(slipping)


@pytest.mark.parametrize("tan_theta", [0.2, 0.5])
def test_block_on_an_incline_sticks_or_slides_with_coulombs_acceleration(tan_theta):
    """A stiff block (E = 1e4, so it moves nearly rigidly) released on an incline, backward
    Euler (its velocity update is exact for a constant acceleration, and it damps the contact's
    and the block's vibrations). For tan theta > mu it slides with the acceleration
    g (sin theta - mu cos theta): the slope of its velocity over the last half of the run within
    2 %. For tan theta < mu it sticks: once the block's shear vibration from the release has
    died out (the second half of the run), no friction point slips by more than the slip
    tolerance in a step, and the block's velocity is below 1 % of what it would reach without
    friction."""
    t, velocity, slipping = _block_on_incline(MPI.COMM_WORLD, tan_theta)
    theta = np.arctan(tan_theta)
    if MPI.COMM_WORLD.rank == 0:
        print(f"tan theta {tan_theta}: {t.size} steps, block velocity {velocity}, slipping "
              f"points {slipping}")  # fmt: skip
    if tan_theta > MU:
        expected = GRAVITY * (np.sin(theta) - MU * np.cos(theta))
        late = t >= 0.5 * t[-1]
        slope = np.polyfit(t[late], velocity[late], 1)[0]
        assert slope == pytest.approx(expected, rel=0.02)
    else:
        late = t >= 0.5 * t[-1]
        free = GRAVITY * np.sin(theta) * t[-1]
        assert np.all(slipping[late] == 0)
        assert np.abs(velocity[late]).max() < 0.01 * free
