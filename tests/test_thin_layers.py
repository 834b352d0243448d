"""Thin layers and coarse meshes: tetrahedra whose four vertices all lie on the boundary.

Their P1 material depth is 0 everywhere, so a surface entering them feels no force. The
contact operator splits each such tetrahedron into four sub-tetrahedra around its centroid,
which carries its exact distance to the boundary (``split_deficient=True``, the default); see
``docs/kernels.md`` ("Thin layers"). Checked here: the split pair against an independent sum
over the sub-tetrahedra and against finite differences; the operator's derivatives on a mesh
of split tetrahedra; a plate one element thick pressed onto another (falls through without
the split) and onto a thick block; a strip one element thick folded onto itself; and the
symmetry of the overlap under a block whose footprint edges meet split tetrahedra on two
sides only. Run with ``pytest -s`` to see the measured numbers.
"""

from __future__ import annotations

import warnings

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import numpy as np
import pytest
import ufl
from conftest import (
    assert_operator_derivatives,
    clamped_and_moved,
    merged_mesh,
    min_det_F,
    neo_hookean,
)
from test_self_contact import LENGTH, THICKNESS, WIDTH, _end_motion

import fenics_matdepth as fm
from fenics_matdepth._compat import create_tetrahedral_mesh
from fenics_matdepth.contact.kernels import collocation_energy, pair_energy
from fenics_matdepth.contact.kernels.drivers import area_pairs, area_pairs_into
from fenics_matdepth.contact.kernels.polygon import area_pairs_max_depth
from fenics_matdepth.contact.operator import ContactOperator, DepthDeficiencyWarning
from fenics_matdepth.depth import count_depth_deficient, depth_deficient_tets
from fenics_matdepth.meshing import box_tetrahedra

#: Newton tolerance as in tests/test_validation.py (contact residual rounding floor).
NEWTON_OPTIONS = {"snes_rtol": 1e-8}


def _report(text: str) -> None:
    if MPI.COMM_WORLD.rank == 0:
        print(text, flush=True)


# ------------------------------------------------------------------------------------------
# one pair
# ------------------------------------------------------------------------------------------

#: A triangle cutting a tetrahedron through its interior, away from degenerate incidences.
X_TRI = np.array([[-0.3, 0.2, 0.35], [1.1, 0.1, 0.25], [0.2, 1.2, 0.3]])
X_TET = np.array([[0.0, 0.0, 0.0], [1.0, 0.05, 0.02], [0.1, 0.9, 0.0], [0.15, 0.1, 0.8]])
CENTROID_DEPTH = 0.17
EPS = 7.0


def _sub_tets(x_tet: np.ndarray) -> list[np.ndarray]:
    """The four sub-tetrahedra around the centroid: vertex s replaced by the centroid."""
    out = []
    for s in range(4):
        sub = x_tet.copy()
        sub[s] = x_tet.mean(axis=0)
        out.append(sub)
    return out


def _centroid_map(first: int) -> list[np.ndarray]:
    """For each sub-tetrahedron s, the matrix T_s with x_sub = T_s x_parent (xyz interleaved)."""
    n = first + 4
    maps = []
    for s in range(4):
        T = np.eye(n)
        T[first + s, :] = 0.0
        T[first + s, first:] = 0.25
        maps.append(np.kron(T, np.eye(3)))
    return maps


def test_split_pair_is_the_sum_over_sub_tetrahedra():
    """Energy, gradient and Hessian of a split pair equal the sums over the four sub-pairs,
    each computed by the unsplit kernel and mapped back with T^T g and T^T H T in numpy."""
    depth = np.zeros(4)
    e, g, h = pair_energy(X_TRI, X_TET, depth, EPS, centroid_depth=CENTROID_DEPTH)
    e_ref, g_ref, h_ref = 0.0, np.zeros(21), np.zeros((21, 21))
    for s, (sub, T) in enumerate(zip(_sub_tets(X_TET), _centroid_map(3), strict=True)):
        d = depth.copy()
        d[s] = CENTROID_DEPTH
        es, gs, hs = pair_energy(X_TRI, sub, d, EPS)
        e_ref += es
        g_ref += T.T @ gs
        h_ref += T.T @ hs @ T
    assert e > 0.0
    assert e == pytest.approx(e_ref, rel=1e-13)
    assert np.allclose(g, g_ref, rtol=0.0, atol=1e-13 * np.abs(g_ref).max())
    assert np.allclose(h, h_ref, rtol=0.0, atol=1e-13 * np.abs(h_ref).max())
    # without the split the tetrahedron has depth 0 everywhere
    assert pair_energy(X_TRI, X_TET, depth, EPS)[0] == 0.0


@pytest.mark.parametrize("which", ["area", "collocation"])
def test_split_pair_derivatives_match_finite_differences(which):
    """Central differences of the split pair's energy and gradient (4th order), rel. 1e-6."""
    rng = np.random.default_rng(3)
    # collocation: a vertex inside the tetrahedron, clear of the sub-tetrahedra's faces
    first = X_TRI if which == "area" else (np.array([0.3, 0.2, 0.15, 0.35]) @ X_TET)[None]
    x0 = np.vstack((first, X_TET)).ravel()
    nf = first.shape[0]

    def f(x):
        x = x.reshape(-1, 3)
        if which == "area":
            return pair_energy(x[:nf], x[nf:], np.zeros(4), EPS, CENTROID_DEPTH)
        return collocation_energy(x[0], x[nf:], np.zeros(4), 0.3, EPS, CENTROID_DEPTH)

    e0, g0, h0 = f(x0)
    assert e0 > 0.0
    v = rng.standard_normal(x0.size)
    step = 1e-4
    stencil = [(-2, 1 / 12), (-1, -8 / 12), (1, 8 / 12), (2, -1 / 12)]
    de = sum(c * f(x0 + k * step * v)[0] for k, c in stencil) / step
    dg = sum(c * f(x0 + k * step * v)[1] for k, c in stencil) / step
    assert de == pytest.approx(g0 @ v, rel=1e-6)
    assert np.linalg.norm(dg - h0 @ v) <= 1e-6 * np.linalg.norm(h0 @ v)


def test_batch_drivers_with_split_tetrahedra():
    """Mixed batches (split and plain tetrahedra): the compact driver `area_pairs_into`
    (also when its arrays are too short) and `area_pairs_max_depth` agree with the
    one-pair results and with the sub-tetrahedra evaluated as plain tetrahedra."""
    rng = np.random.default_rng(5)
    n = 12
    x_tri = X_TRI[None] + 0.3 * rng.standard_normal((n, 3, 3))
    x = np.vstack((x_tri.reshape(-1, 3), X_TET))
    nt = 3 * n
    depth = np.concatenate((np.zeros(nt + 4), [0.0, CENTROID_DEPTH]))  # 4 vertices, 2 extra
    depth[nt + 3] = 0.05  # the plain tetrahedron has one vertex inside the body
    tri = np.arange(nt, dtype=np.int64).reshape(n, 3)
    tet = np.array([[nt, nt + 1, nt + 2, nt + 3, -1], [nt, nt + 1, nt + 2, nt + 3, nt + 5]])
    pair_tri = np.arange(n, dtype=np.int64)
    pair_tet = np.arange(n, dtype=np.int64) % 2
    e_ref = np.array([
        pair_energy(x_tri[p], X_TET, depth[tet[pair_tet[p], :4]], EPS,
                    CENTROID_DEPTH if pair_tet[p] else None)[0]
        for p in range(n)
    ])  # fmt: skip
    energy, grad, hess = area_pairs(x, depth, tri, tet, pair_tri, pair_tet, EPS, True, True)
    assert np.allclose(energy, e_ref, rtol=1e-13, atol=0.0)
    assert np.count_nonzero(energy[pair_tet == 1] > 0) >= 2
    m_full = None
    for cap in (n, 2):
        out = (np.empty(cap, np.int64), np.empty(cap), np.empty((cap, 21)), np.empty((cap, 21, 21)))
        m = area_pairs_into(x, depth, tri, tet, pair_tri, pair_tet, EPS, True, True, *out)
        m_full = m if m_full is None else m_full
        assert m == m_full
        rows = out[0][: min(m, cap)]
        assert np.array_equal(out[1][: rows.size], energy[rows])
        assert np.array_equal(out[2][: rows.size], grad[rows])
        assert np.array_equal(out[3][: rows.size], hess[rows])
    # max depth: the largest over the sub-tetrahedra, each evaluated as a plain tetrahedron
    subs = _sub_tets(X_TET)
    xs = np.vstack((x_tri.reshape(-1, 3), *subs))
    sub_depth = np.zeros(xs.shape[0])
    sub_tet = np.arange(nt, nt + 16, dtype=np.int64).reshape(4, 4)
    for s in range(4):
        sub_depth[nt + 4 * s : nt + 4 * s + 4] = depth[nt : nt + 4]
        sub_depth[nt + 4 * s + s] = CENTROID_DEPTH
    split_pairs = pair_tri[pair_tet == 1]
    g = area_pairs_max_depth(x, depth, tri, tet, split_pairs, np.ones_like(split_pairs))
    g_sub = np.max(
        [
            area_pairs_max_depth(
                xs, sub_depth, tri, sub_tet, split_pairs, np.full_like(split_pairs, s)
            )
            for s in range(4)
        ],
        axis=0,
    )
    assert g.max() > 0.0
    assert np.allclose(g, g_sub, rtol=1e-14, atol=0.0)


def test_split_collocation_depth_is_four_centroid_depths_times_min_barycentric():
    """A vertex in a split tetrahedron lies in the sub-tetrahedron of its smallest barycentric
    coordinate lambda_min, where the depth is 4 lambda_min d_c (analytical)."""
    lam = np.array([0.3, 0.2, 0.15, 0.35])
    x = lam @ X_TET
    weight = 0.4
    e, _, _ = collocation_energy(x, X_TET, np.zeros(4), weight, EPS, CENTROID_DEPTH)
    g = 4.0 * lam.min() * CENTROID_DEPTH
    assert e == pytest.approx(0.5 * EPS * weight * g**2, rel=1e-12)


# ------------------------------------------------------------------------------------------
# meshes
# ------------------------------------------------------------------------------------------


def _stack(comm, *boxes) -> dolfinx.mesh.Mesh:
    """One mesh of several structured boxes ``(cells, origin, size)``."""
    return merged_mesh(comm, *(box_tetrahedra(n, origin, size) for n, origin, size in boxes))


def test_deficiency_counts_and_warning():
    """A plate one element thick: every tetrahedron is deficient; a 3 x 3 x 3 box: the
    tetrahedra with four boundary vertices are counted as in an independent numpy count."""
    comm = MPI.COMM_WORLD
    plate = _stack(comm, ((4, 3, 1), (0, 0, 0), (1, 1, 0.1)))
    d = fm.material_depth(plate)
    counts = fm.depth_deficiency(d)
    assert counts.deficient == counts.boundary_adjacent == 6 * 4 * 3
    assert counts.fraction == 1.0

    # box: vertices on the boundary counted from the structured grid
    X, cells = box_tetrahedra(3, (0, 0, 0), (1, 1, 1))
    on_boundary = np.any((np.abs(X) < 1e-12) | (np.abs(X - 1) < 1e-12), axis=1)
    expected = count_depth_deficient(cells, np.where(on_boundary, 0.0, 1.0))
    assert 0 < expected.deficient < expected.boundary_adjacent
    box = create_tetrahedral_mesh(comm, cells, X)
    assert fm.depth_deficiency(fm.material_depth(box)) == expected
    assert np.array_equal(
        depth_deficient_tets(cells, np.where(on_boundary, 0.0, 1.0)),
        np.all(on_boundary[cells], axis=1),
    )

    V = dolfinx.fem.functionspace(box, ("Lagrange", 1, (3,)))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        op = ContactOperator(dolfinx.fem.Function(V), fm.material_depth(box), penalty=1.0)
    ours = [w for w in caught if issubclass(w.category, DepthDeficiencyWarning)]
    assert len(ours) == (1 if comm.rank == 0 else 0)
    if ours:
        assert "split around its centroid" in str(ours[0].message)
    diag = op.diagnostics()
    assert diag["deficient_tets"] == expected.deficient
    assert diag["boundary_adjacent_tets"] == expected.boundary_adjacent
    assert diag["deficient_fraction"] == pytest.approx(expected.fraction)
    assert diag["split_tets"] == expected.deficient
    # without the split, the warning says what that means
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        op = ContactOperator(dolfinx.fem.Function(V), fm.material_depth(box), penalty=1.0,
                             split_deficient=False)  # fmt: skip
    assert op.diagnostics()["split_tets"] == 0
    if comm.rank == 0:
        assert any("feel no contact force" in str(w.message) for w in caught)


@pytest.mark.parametrize("integration", ["area", "collocation"])
def test_operator_derivatives_with_split_tetrahedra(integration):
    """Residual and Jacobian against central differences on two overlapping plates one
    element thick (every tetrahedron split), as tests/test_operator.py does for boxes."""
    comm = MPI.COMM_WORLD
    mesh = _stack(
        comm, ((3, 3, 1), (0, 0, 0), (1, 1, 0.25)), ((4, 3, 1), (0.13, 0.07, 0.2), (0.8, 0.9, 0.25))
    )
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    x = V.tabulate_dof_coordinates()
    u.x.array[:] = (0.02 * np.sin([3.1, 2.3, 1.7] * x + np.array([0.3, 0.1, 0.7]))).ravel()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DepthDeficiencyWarning)
        op = ContactOperator(
            u, fm.material_depth(mesh), penalty=50.0, integration=integration,
            allow_reference_overlap=True,
        )  # fmt: skip
    assert op.num_split_tets == mesh.topology.index_map(3).size_global
    assert op.energy() > 0.0
    assert_operator_derivatives(op, u, h=1e-6, rtol=1e-6)


# ------------------------------------------------------------------------------------------
# a plate one element thick pressed onto another plate or onto a block
# ------------------------------------------------------------------------------------------

PLATE = 0.1  # thickness of one element layer
PRESSURE = 0.01
PENALTY = 100.0  # = 10 E / PLATE


def _plane_bc(V, axis: int, value: float, component: int) -> dolfinx.fem.DirichletBC:
    mesh = V.mesh
    facets = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[axis], value))
    dofs = dolfinx.fem.locate_dofs_topological(V.sub(component), 2, facets)
    return dolfinx.fem.dirichletbc(PETSc.ScalarType(0.0), dofs, V.sub(component))


def _upper_body(op: ContactOperator) -> int:
    return int(op.body_of_vertex[np.argmax(op.surface.gathered()["X"][:, 2])])


def _sink_upper_body(op: ContactOperator, u: dolfinx.fem.Function, sink: float) -> int:
    """Move the upper body of ``op``'s mesh down by ``sink`` (in ``u``); returns its number."""
    upper = _upper_body(op)
    imap = u.function_space.dofmap.index_map
    n_owned = imap.size_local
    glob = imap.local_to_global(np.arange(n_owned, dtype=np.int32))
    is_upper = op.body_of_vertex[glob] == upper
    u.x.array[: 3 * n_owned].reshape(-1, 3)[is_upper, 2] = -sink
    u.x.scatter_forward()
    return upper


def _press_plate(lower_layers: int, split: bool) -> dict:
    """A unit-square plate one element thick (4 x 4 x 1 cubes) under a dead pressure on its
    top, resting on a unit-square plate or block of ``lower_layers`` element layers (5 x 5
    cubes) whose bottom is held (u_z = 0); rollers on x = 0 and y = 0 for both, so the exact
    state is uniform. Starts from the upper plate sunk by p / (2 eps)."""
    comm = MPI.COMM_WORLD
    top_lower = PLATE * lower_layers
    mesh = _stack(
        comm,
        ((5, 5, lower_layers), (0, 0, 0), (1, 1, top_lower)),
        ((4, 4, 1), (0, 0, top_lower), (1, 1, PLATE)),
    )
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    top = dolfinx.mesh.locate_entities_boundary(
        mesh, 2, lambda x: np.isclose(x[2], top_lower + PLATE)
    )
    ds = ufl.Measure(
        "ds", domain=mesh, subdomain_data=dolfinx.mesh.meshtags(mesh, 2, top, np.ones_like(top))
    )
    energy = neo_hookean(u)[0] * ufl.dx + PRESSURE * u[2] * ds(1)
    residual = ufl.derivative(energy, u, ufl.TestFunction(V))
    bcs = [_plane_bc(V, 0, 0.0, 0), _plane_bc(V, 1, 0.0, 1), _plane_bc(V, 2, 0.0, 2)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DepthDeficiencyWarning)
        op = ContactOperator(u, fm.material_depth(mesh), penalty=PENALTY, split_deficient=split)
    upper = _sink_upper_body(op, u, PRESSURE / (2.0 * PENALTY))
    op.update()
    out = {"initial_force": op.force_resultants()[upper, 2], "diagnostics": op.diagnostics()}
    problem = fm.ContactProblem(
        residual, u, op, bcs=bcs, energy=energy, petsc_options=NEWTON_OPTIONS
    )
    result = problem.solve()
    op.update()
    g = op.surface.gathered()
    X = g["X"]
    U = g["x"] - g["X"]
    inner = np.all((X[:, :2] > 0.2 - 1e-9) & (X[:, :2] < 0.8 + 1e-9), axis=1)
    face = np.isclose(X[:, 2], top_lower) & inner
    up = op.body_of_vertex == upper
    out.update(
        converged=result.converged,
        iterations=result.iterations,
        force=op.force_resultants()[upper, 2],
        overlap=float(np.mean(U[face & ~up, 2]) - np.mean(U[face & up, 2])),
        diagnostics=op.diagnostics(),
    )
    return out


@pytest.mark.parametrize("lower_layers", [1, 3])
def test_plate_one_element_thick_pressed(lower_layers):
    """Plate on plate (both one element thick) and plate on a block three elements thick.

    Without the split, the upper plate's tetrahedra all have depth 0, so nothing can push out
    of it: the operator refuses the mesh with an error naming the remedy. With the split
    (default), sunk by p / (2 eps), the plates push back, the solve converges, the contact
    force balances the load (1e-8), and the overlap is below p / eps: about p / (2 eps) on the
    block (both surfaces penetrate; the depth gradient is 1 in the plate's top-face
    sub-tetrahedra and in the block).
    """
    p, eps = PRESSURE, PENALTY
    with pytest.raises(ValueError, match=r"no vertex inside them.*keep split_deficient=True"):
        _press_plate(lower_layers, split=False)
    after = _press_plate(lower_layers, split=True)
    d = after["diagnostics"]
    _report(
        f"\nplate (1 layer) on {lower_layers} layer(s): deficient {d['deficient_tets']} of "
        f"{d['boundary_adjacent_tets']} boundary tets; force at overlap p/(2 eps) "
        f"{after['initial_force']:.4g} (load {p}); "
        f"converged in {after['iterations']} its, force {after['force']:.10g}, overlap "
        f"{after['overlap'] * eps / p:.3f} p/eps, max depth {d['max_penetration'] * eps / p:.3f} "
        "p/eps"
    )
    if lower_layers == 1:
        assert d["deficient_tets"] == d["boundary_adjacent_tets"] == 6 * (25 + 16)
    assert after["initial_force"] > 0.0
    assert after["converged"]
    assert after["force"] == pytest.approx(p * 1.0, rel=1e-8)
    assert 0.0 < after["overlap"] < p / eps
    if lower_layers > 1:
        assert after["overlap"] == pytest.approx(p / (2.0 * eps), rel=0.2)


# ------------------------------------------------------------------------------------------
# self-contact of a strip one element thick
# ------------------------------------------------------------------------------------------


def test_strip_one_element_thick_folds_onto_itself():
    """The strip of tests/test_self_contact.py (4 x 0.8 x 0.2, end turned through a full
    turn), meshed one element thick: every tetrahedron has four boundary vertices. Every load
    step converges, contact is active, the deepest point of the contact surface lies less
    than 0.2 of the thickness inside the strip, and no tetrahedron is inverted."""
    comm = MPI.COMM_WORLD
    length, width, thickness = LENGTH, WIDTH, THICKNESS
    X, cells = box_tetrahedra((40, 4, 1), (0.0, 0.0, 0.0), (length, width, thickness))
    mesh = create_tetrahedral_mesh(comm, cells, X)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    energy = neo_hookean(u)[0] * ufl.dx
    residual = ufl.derivative(energy, u, ufl.TestFunction(V))
    bcs, g = clamped_and_moved(
        V, lambda x: np.isclose(x[0], 0.0), lambda x: np.isclose(x[0], length)
    )
    mu, kappa = fm.materials.shear_bulk_from_youngs_poisson(1.0, 0.3)
    moduli = fm.materials.small_strain_moduli(fm.materials.neo_hookean, mu=mu, kappa=kappa)
    penalty = fm.propose_penalty(mesh, moduli.stiffest, factor=30.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DepthDeficiencyWarning)
        contact = ContactOperator(u, fm.material_depth(mesh), penalty=penalty)
    assert contact.num_split_tets == mesh.topology.index_map(3).size_global
    problem = fm.ContactProblem(residual, u, contact, bcs=bcs, energy=energy)
    steps = fm.solve_load_steps(problem, lambda t: g.interpolate(_end_motion(t)), num_steps=20)
    assert np.isclose(steps[-1].load, 1.0)
    final = steps[-1].diagnostics
    _report(
        f"\nstrip one element thick: {len(steps)} steps, "
        f"{sum(s.iterations for s in steps)} Newton iterations, eps = {penalty:.4g}, "
        f"{final['active_pairs']} active pairs, max penetration "
        f"{final['max_penetration'] / thickness:.3f} of the thickness"
    )
    assert final["active_pairs"] > 0, "the strip did not reach itself"
    assert final["max_penetration"] < 0.2 * thickness
    assert min_det_F(u) > 0.0


# ------------------------------------------------------------------------------------------
# symmetry of the overlap under a block
# ------------------------------------------------------------------------------------------

PATCH_UPPER = (5, 5, 3)  # 1 x 1 x 0.5 block
PATCH_LOWER = (8, 8, 4)  # 2 x 2 x 1 block


def _depth_at(points: np.ndarray, x: np.ndarray, tets: np.ndarray, depth: np.ndarray):
    """P1 material depth at each point, from the tetrahedron (current vertices ``x[tets]``)
    that contains it (points outside every tetrahedron get 0)."""
    corners = x[tets]
    edges = np.transpose(corners[:, 1:] - corners[:, :1], (0, 2, 1))  # (nk, 3, 3) columns
    out = np.zeros(points.shape[0])
    for i, q in enumerate(points):
        lam = np.linalg.solve(edges, (q - corners[:, 0])[:, :, None])[:, :, 0]
        lam = np.hstack((1.0 - lam.sum(axis=1, keepdims=True), lam))
        inside = np.flatnonzero(lam.min(axis=1) >= -1e-12)
        if inside.size:
            out[i] = lam[inside[0]] @ depth[tets[inside[0]]]
    return out


def _press_block(split: bool, penalty: float = 2.0) -> np.ndarray:
    """The 1 x 1 x 0.5 block (5 x 5 x 3 cubes) under a dead pressure on its top face (held
    laterally) on the middle of a 2 x 2 x 1 block (8 x 8 x 4 cubes, bottom held). Returns the
    overlap at the block's 6 x 6 bottom vertices, in units of p / eps: the depth the vertex
    reached in the lower block (whose depth under its flat top is the distance to it, with
    gradient 1 in the current configuration up to strains of 1e-2)."""
    comm = MPI.COMM_WORLD
    lower = ((PATCH_LOWER), (0.0, 0.0, 0.0), (2.0, 2.0, 1.0))
    upper = ((PATCH_UPPER), (0.5, 0.5, 1.0), (1.0, 1.0, 0.5))
    mesh = _stack(comm, lower, upper)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    top = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[2], 1.5))
    ds = ufl.Measure(
        "ds", domain=mesh, subdomain_data=dolfinx.mesh.meshtags(mesh, 2, top, np.ones_like(top))
    )
    energy = neo_hookean(u)[0] * ufl.dx + PRESSURE * u[2] * ds(1)
    residual = ufl.derivative(energy, u, ufl.TestFunction(V))
    zero = PETSc.ScalarType(0.0)
    bottom = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[2], 0.0))
    bcs = [
        dolfinx.fem.dirichletbc(np.zeros(3), dolfinx.fem.locate_dofs_topological(V, 2, bottom), V)
    ]
    for c in (0, 1):
        dofs = dolfinx.fem.locate_dofs_topological(V.sub(c), 2, top)
        bcs.append(dolfinx.fem.dirichletbc(zero, dofs, V.sub(c)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DepthDeficiencyWarning)
        op = ContactOperator(u, fm.material_depth(mesh), penalty=penalty, split_deficient=split)
    upper_body = _sink_upper_body(op, u, PRESSURE / (2.0 * penalty))
    problem = fm.ContactProblem(
        residual, u, op, bcs=bcs, energy=energy, petsc_options=NEWTON_OPTIONS
    )
    assert problem.solve().converged
    op.update()
    up = op.body_of_vertex == upper_body
    g = op.surface.gathered()
    lower_tets = g["tets"][~up[g["tets"][:, 0]]]
    n = PATCH_UPPER[0]
    bottom_v = np.flatnonzero(up & np.isclose(g["X"][:, 2], 1.0))
    overlap = _depth_at(g["x"][bottom_v], g["x"], lower_tets, g["depth"])
    grid = np.full((n + 1, n + 1), np.nan)
    ij = np.rint((g["X"][bottom_v, :2] - 0.5) * n).astype(int)
    grid[ij[:, 0], ij[:, 1]] = overlap * penalty / PRESSURE
    return grid


def _mirror_mismatch(grid: np.ndarray) -> float:
    """Largest relative difference of the overlap at vertices mirrored across the footprint's
    centre lines x = 1 and y = 1."""
    worst = 0.0
    for mirrored in (grid[::-1, :], grid[:, ::-1]):
        worst = max(worst, float(np.max(np.abs(grid - mirrored) / np.maximum(grid, mirrored))))
    return worst


def test_overlap_is_symmetric_under_a_block():
    """A 1 x 1 x 0.5 block (5 x 5 x 3 cubes of 6 Kuhn tetrahedra) pressed onto a 2 x 2 x 1
    block. On two sides of the footprint the block's side columns have tetrahedra with all
    four vertices on the boundary: without the split the overlap there is about twice that of
    the other two sides; with it, the overlap at vertices mirrored across the footprint's
    centre lines agrees within 10 %.

    Soft penalty (eps = 2 = 0.4 E / h): the contact pressure stays nearly uniform, so the
    overlap shows the contact stiffness the depth field gives each vertex rather than the
    elastic stress concentration at the footprint's edges (with stiffer penalties the latter
    dominates, and the Kuhn meshes are not mirror-symmetric themselves: measured mismatch
    before / after the split 50 % / 11 % at eps = 5, 67 % / 45 % at eps = 50).
    """
    before = _press_block(split=False)
    after = _press_block(split=True)
    np.set_printoptions(precision=3, suppress=True, linewidth=120)
    _report(
        f"\noverlap x eps / p at the block's bottom vertices\n"
        f"without split (mirror mismatch {_mirror_mismatch(before):.1%}):\n{before}\n"
        f"with split (mirror mismatch {_mirror_mismatch(after):.1%}):\n{after}"
    )
    assert not np.isnan(after).any()
    assert _mirror_mismatch(before) > 0.2  # the asymmetry the split removes
    assert _mirror_mismatch(after) < 0.1
