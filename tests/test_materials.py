"""Tests of the UFL hyperelastic models in fenics_matdepth.materials.

UFL expressions of a constant deformation gradient are evaluated with
``dolfinx.fem.Expression`` on a small mesh owned by each process (``MPI.COMM_SELF``), the
deformation gradient being a ``fem.Constant``. The reference values come from an independent
NumPy implementation of each energy, differentiated by the complex step (exact to rounding), and
from closed-form linear elasticity.
"""

from __future__ import annotations

import functools

from mpi4py import MPI
from petsc4py import PETSc

import numpy as np
import pytest
import ufl
from dolfinx import fem, mesh

from fenics_matdepth import materials
from fenics_matdepth._compat import solve_nonlinear

# Nondimensional parameters: every model has small-strain shear modulus 1 and bulk modulus 10.
MU, KAPPA = 1.0, 10.0
K1, K2 = 2.0, 1.0
PARAMETERS = {
    "neo_hookean": {"mu": MU, "kappa": KAPPA},
    "mooney_rivlin": {"c10": 0.3, "c01": 0.2, "kappa": KAPPA},
    "veronda_westmann": {"c1": 0.5, "c2": 2.0, "kappa": KAPPA},
    "fiber_reinforced": {"mu": MU, "kappa": KAPPA, "k1": K1, "k2": K2},
}
MODELS = list(PARAMETERS)
E1 = np.array([1.0, 0.0, 0.0])


# The material laws are pointwise formulas evaluated on COMM_SELF: one process says it all.
pytestmark = pytest.mark.serial


# --- Independent NumPy reference (complex-step differentiable) ----------------------------


def _det3(F):
    """Determinant written as a polynomial, so that it is complex-analytic."""
    return (
        F[0, 0] * (F[1, 1] * F[2, 2] - F[1, 2] * F[2, 1])
        - F[0, 1] * (F[1, 0] * F[2, 2] - F[1, 2] * F[2, 0])
        + F[0, 2] * (F[1, 0] * F[2, 1] - F[1, 1] * F[2, 0])
    )


def reference_psi(name: str, F: np.ndarray, a0: np.ndarray = E1):
    """Energy density of model ``name`` at the 3 x 3 (possibly complex) matrix ``F``."""
    p = PARAMETERS[name]
    C = F.T @ F
    J = _det3(F)
    I1, I2 = np.trace(C), (np.trace(C) ** 2 - np.trace(C @ C)) / 2
    I1b, I2b = J ** (-2 / 3) * I1, J ** (-4 / 3) * I2
    U = p["kappa"] / 4 * (J**2 - 1 - 2 * np.log(J))
    if name == "neo_hookean":
        return p["mu"] / 2 * (I1b - 3) + U
    if name == "mooney_rivlin":
        return p["c10"] * (I1b - 3) + p["c01"] * (I2b - 3) + U
    if name == "veronda_westmann":
        return p["c1"] * (np.exp(p["c2"] * (I1b - 3)) - 1) - p["c1"] * p["c2"] / 2 * (I2b - 3) + U
    I4 = a0 @ C @ a0
    fiber = p["k1"] / (2 * p["k2"]) * (np.exp(p["k2"] * (I4 - 1) ** 2) - 1)
    return p["mu"] / 2 * (I1b - 3) + U + (fiber if I4.real > 1 else 0.0)


def reference_piola(name: str, F: np.ndarray, a0: np.ndarray = E1) -> np.ndarray:
    """First Piola stress by complex-step differentiation of :func:`reference_psi`."""
    h = 1e-30
    P = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            Fc = F.astype(complex)
            Fc[i, j] += 1j * h
            P[i, j] = reference_psi(name, Fc, a0).imag / h
    return P


# --- Evaluation of UFL expressions of a constant F ----------------------------------------


class ConstantF:
    """Evaluates UFL expressions of a constant deformation gradient ``F`` (a fem.Constant)."""

    def __init__(self):
        self.mesh = mesh.create_unit_cube(MPI.COMM_SELF, 1, 1, 1)
        self.F = fem.Constant(self.mesh, np.eye(3))
        self.a0 = fem.Constant(self.mesh, E1)
        self._point = np.zeros((1, 3))

    def compile(self, expr: ufl.core.expr.Expr):
        """Return ``f(F_value) -> ndarray`` evaluating ``expr`` at ``F = F_value``."""
        compiled = fem.Expression(expr, self._point)
        shape = expr.ufl_shape

        def evaluate(F_value: np.ndarray, a0: np.ndarray = E1) -> np.ndarray:
            self.F.value[:] = F_value
            self.a0.value[:] = a0
            values = compiled.eval(self.mesh, np.array([0], dtype=np.int32))
            return np.asarray(values).reshape(shape)

        return evaluate


@pytest.fixture(scope="module")
def evaluator() -> ConstantF:
    return ConstantF()


def _psi_of(name: str, F, a0) -> ufl.core.expr.Expr:
    model = getattr(materials, name)
    if name == "fiber_reinforced":
        return model(F, a0=a0, **PARAMETERS[name])
    return model(F, **PARAMETERS[name])


@functools.cache
def _compiled(evaluator: ConstantF, name: str, what: str):
    """Compiled psi, P or the tangent dP/dF of model ``name`` (cached: FFCx compiles once)."""
    if what == "psi":
        return evaluator.compile(_psi_of(name, evaluator.F, evaluator.a0))
    F = ufl.variable(evaluator.F)
    P = ufl.diff(_psi_of(name, F, evaluator.a0), F)
    return evaluator.compile(P if what == "P" else ufl.diff(P, F))


def _random_deformation(rng: np.random.Generator) -> np.ndarray:
    """A random F with det F > 0 (moderate: up to ~30% strain)."""
    while True:
        F = np.eye(3) + 0.3 * rng.uniform(-1, 1, (3, 3))
        if np.linalg.det(F) > 0.3:
            return F


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    Q, R = np.linalg.qr(rng.standard_normal((3, 3)))
    Q = Q @ np.diag(np.sign(np.diag(R)))
    return Q if np.linalg.det(Q) > 0 else -Q


def _linear_elasticity(mu: float, kappa: float) -> np.ndarray:
    """C_ijkl = lambda d_ij d_kl + mu (d_ik d_jl + d_il d_jk), lambda = kappa - 2 mu / 3."""
    d = np.eye(3)
    lam = kappa - 2 * mu / 3
    return lam * np.einsum("ij,kl->ijkl", d, d) + mu * (
        np.einsum("ik,jl->ijkl", d, d) + np.einsum("il,jk->ijkl", d, d)
    )


# --- Tests --------------------------------------------------------------------------------


@pytest.mark.parametrize("name", MODELS)
def test_reference_state_is_stress_free(evaluator, name):
    P = _compiled(evaluator, name, "P")(np.eye(3))
    assert np.abs(P).max() < 1e-12 * MU
    assert abs(_compiled(evaluator, name, "psi")(np.eye(3))) < 1e-12 * MU


@pytest.mark.parametrize("name", MODELS)
def test_small_strain_tangent_is_linear_elasticity(evaluator, name):
    """d2 psi / dF2 at F = I equals the isotropic elasticity tensor of small_strain_moduli."""
    moduli = materials.small_strain_moduli(getattr(materials, name), **PARAMETERS[name])
    assert (moduli.shear, moduli.bulk) == pytest.approx((MU, KAPPA), rel=1e-14)
    A = _compiled(evaluator, name, "A")(np.eye(3))
    C = _linear_elasticity(moduli.shear, moduli.bulk)
    assert np.abs(A - C).max() < 1e-10 * KAPPA


def test_fiber_tangent_in_small_tension(evaluator):
    """Just past I4 = 1 the fiber adds fiber = 4 k1 to the a0 a0 a0 a0 tangent component."""
    moduli = materials.small_strain_moduli(
        materials.fiber_reinforced, **PARAMETERS["fiber_reinforced"]
    )
    assert moduli.fiber == pytest.approx(4 * K1)
    t = 1e-7
    F = np.eye(3) + t * np.outer(E1, E1)
    A = _compiled(evaluator, "fiber_reinforced", "A")(F)
    A_matrix = _compiled(evaluator, "neo_hookean", "A")(F)
    expected = np.zeros((3, 3, 3, 3))
    expected[0, 0, 0, 0] = moduli.fiber
    # O(t) terms of the fiber tangent: 12 k1 t + ... -> tolerance 1e-5.
    assert np.abs(A - A_matrix - expected).max() < 1e-5 * moduli.fiber


@pytest.mark.parametrize("name", MODELS)
def test_objectivity(evaluator, name):
    """psi(Q F) = psi(F) and P(Q F) = Q P(F) for random rotations Q."""
    rng = np.random.default_rng(7)
    psi, P = _compiled(evaluator, name, "psi"), _compiled(evaluator, name, "P")
    for _ in range(5):
        F, Q = _random_deformation(rng), _random_rotation(rng)
        scale = abs(psi(F)) + MU
        assert abs(psi(Q @ F) - psi(F)) < 1e-12 * scale
        assert np.abs(P(Q @ F) - Q @ P(F)).max() < 1e-11 * scale


@pytest.mark.parametrize("name", MODELS)
def test_energy_and_stress_match_independent_reference(evaluator, name):
    """UFL psi and P = diff(psi, F) against a NumPy energy and its complex-step derivative."""
    rng = np.random.default_rng(11)
    psi, P = _compiled(evaluator, name, "psi"), _compiled(evaluator, name, "P")
    tension = np.diag([1.3, 0.9, 0.95])  # I4 > 1: the fiber term is active
    for F in [tension] + [_random_deformation(rng) for _ in range(4)]:
        ref = reference_psi(name, F)
        assert abs(psi(F) - ref) < 1e-12 * (abs(ref) + MU)
        P_ref = reference_piola(name, F)
        assert np.abs(P(F) - P_ref).max() < 1e-11 * (np.abs(P_ref).max() + MU)


def test_first_piola_kirchhoff_helper(evaluator):
    P_helper = materials.first_piola_kirchhoff(
        materials.mooney_rivlin, evaluator.F, **PARAMETERS["mooney_rivlin"]
    )
    F = _random_deformation(np.random.default_rng(3))
    P_ref = reference_piola("mooney_rivlin", F)
    assert np.abs(evaluator.compile(P_helper)(F) - P_ref).max() < 1e-11 * np.abs(P_ref).max()


@pytest.mark.parametrize("name", MODELS)
def test_energy_blows_up_as_volume_vanishes(evaluator, name):
    """psi(diag(s, 1, 1)) >= U(s) = kappa/4 (s^2 - 1 - 2 ln s), which -> inf as s -> 0."""
    psi = _compiled(evaluator, name, "psi")
    stretches = [1e-1, 1e-2, 1e-3]
    values = [float(psi(np.diag([s, 1.0, 1.0]))) for s in stretches]
    for s, value in zip(stretches, values, strict=True):
        assert value >= KAPPA / 4 * (s**2 - 1 - 2 * np.log(s))
    assert values[0] < values[1] < values[2]
    assert np.isfinite(values[2]) and values[2] > 3 * KAPPA


@pytest.mark.parametrize(
    "F, a0",
    [
        (np.diag([0.8, 1.1, 1.1]), E1),  # fiber compression
        (np.eye(3) + 0.4 * np.outer([1, 0, 0], [0, 1, 0]), np.array([0.0, 0.0, 1.0])),
        (np.eye(3) + 0.4 * np.outer([1, 0, 0], [0, 1, 0]), E1),  # shear along the fiber
    ],
    ids=["compression", "shear-perpendicular", "shear-along-fiber"],
)
def test_fiber_term_vanishes_without_fiber_stretch(evaluator, F, a0):
    """Where the fiber does not lengthen, fiber_reinforced is exactly the neo-Hookean matrix."""
    assert a0 @ F.T @ F @ a0 <= 1.0
    for what in ("psi", "P"):
        fiber = _compiled(evaluator, "fiber_reinforced", what)(F, a0)
        matrix = _compiled(evaluator, "neo_hookean", what)(F, a0)
        assert np.abs(fiber - matrix).max() <= 1e-14 * (np.abs(matrix).max() + MU)


def test_fiber_term_in_tension(evaluator):
    F = np.diag([1.2, 0.95, 0.95])
    I4 = 1.2**2
    fiber = K1 / (2 * K2) * (np.exp(K2 * (I4 - 1) ** 2) - 1)
    difference = _compiled(evaluator, "fiber_reinforced", "psi")(F) - _compiled(
        evaluator, "neo_hookean", "psi"
    )(F)
    assert abs(difference - fiber) < 1e-13 * fiber


TOE = 0.05


@functools.cache
def _compiled_toe(evaluator: ConstantF, toe: float, what: str):
    """The fiber part (fiber_reinforced minus its neo-Hookean matrix; k2 = 0) of psi, or of
    the tangent's a0 a0 a0 a0 component, with a toe region of width ``toe``."""
    F = ufl.variable(evaluator.F)
    p = {"mu": MU, "kappa": KAPPA, "k1": K1}
    psi = materials.fiber_reinforced(F, a0=evaluator.a0, toe=toe, **p)
    psi = psi - materials.neo_hookean(F, MU, KAPPA)
    if what == "psi":
        return evaluator.compile(psi)
    return evaluator.compile(ufl.diff(ufl.diff(psi, F), F)[0, 0, 0, 0])


def _fiber_toe_reference(s: float, toe: float) -> tuple[float, float, float]:
    """psi_f and its first two derivatives in s = I4 - 1 (the toe region as documented)."""
    if s <= 0.0:
        return 0.0, 0.0, 0.0
    if s <= toe:
        return K1 * s**3 / (6 * toe), K1 * s**2 / (2 * toe), K1 * s / toe
    return K1 / 2 * (s - toe / 2) ** 2 + K1 * toe**2 / 24, K1 * (s - toe / 2), K1


@pytest.mark.parametrize("s", [-0.02, 0.01, 0.03, 0.05, 0.2])
def test_fiber_toe_region_energy_and_tangent(evaluator, s):
    """Along F = diag(l, 1, 1) (I4 = l^2, s = I4 - 1) the fiber energy is the documented
    piecewise cubic / quadratic, and the a0 a0 a0 a0 tangent 4 l^2 psi_f'' + 2 psi_f'."""
    stretch = np.sqrt(1.0 + s)
    F = np.diag([stretch, 1.0, 1.0])
    psi, dpsi, d2psi = _fiber_toe_reference(s, TOE)
    assert abs(_compiled_toe(evaluator, TOE, "psi")(F) - psi) <= 1e-13 * (abs(psi) + K1 * TOE**2)
    tangent = 4 * stretch**2 * d2psi + 2 * dpsi
    assert abs(_compiled_toe(evaluator, TOE, "A")(F) - tangent) <= 1e-11 * K1


@pytest.mark.parametrize("at", [0.0, TOE])
def test_fiber_toe_region_tangent_is_continuous(evaluator, at):
    """The fiber tangent is continuous across I4 = 1 and the toe's end with a toe region (it
    changes by O(t) over +-t), and jumps by 4 k1 at I4 = 1 without one."""
    t = 1e-9

    def tangent(toe, s):
        return float(_compiled_toe(evaluator, toe, "A")(np.diag([np.sqrt(1.0 + s), 1, 1])))

    assert abs(tangent(TOE, at + t) - tangent(TOE, at - t)) < 1e-6 * K1
    if at == 0.0:
        assert tangent(0.0, t) - tangent(0.0, -t) == pytest.approx(4 * K1, rel=1e-6)


def test_fiber_toe_region_rejects_bad_input(evaluator):
    with pytest.raises(ValueError, match="k2 = 0"):
        materials.fiber_reinforced(evaluator.F, MU, KAPPA, evaluator.a0, K1, k2=1.0, toe=0.1)
    with pytest.raises(ValueError, match="toe must be a number >= 0"):
        materials.fiber_reinforced(evaluator.F, MU, KAPPA, evaluator.a0, K1, toe=-0.1)


def test_plane_strain_equals_3d_with_unit_out_of_plane_stretch(evaluator):
    F2 = np.array([[1.2, 0.3], [-0.1, 0.9]])
    F3 = np.eye(3)
    F3[:2, :2] = F2
    F2_const = fem.Constant(evaluator.mesh, F2)
    for name in ("neo_hookean", "mooney_rivlin", "veronda_westmann"):
        psi2 = float(evaluator.compile(_psi_of(name, F2_const, None))(np.eye(3)))
        assert abs(psi2 - reference_psi(name, F3)) < 1e-12 * abs(psi2)


def test_modulus_conversions():
    mu, kappa = materials.shear_bulk_from_youngs_poisson(1.0, 0.25)
    assert (mu, kappa) == pytest.approx((0.4, 2.0 / 3.0), rel=1e-15)
    E, nu = materials.youngs_poisson_from_shear_bulk(3.0, 7.0)
    assert materials.shear_bulk_from_youngs_poisson(E, nu) == pytest.approx((3.0, 7.0))
    moduli = materials.SmallStrainModuli(shear=0.4, bulk=2.0 / 3.0, fiber=1.0)
    assert moduli.youngs_modulus == pytest.approx(1.0)
    assert moduli.poisson_ratio == pytest.approx(0.25)
    assert moduli.stiffest == pytest.approx(2.0 / 3.0 + 4 * 0.4 / 3 + 1.0)
    with pytest.raises(ValueError):
        materials.shear_bulk_from_youngs_poisson(1.0, 0.5)


# --- Homogeneous uniaxial stretch of a unit cube, solved with DOLFINx ----------------------


def _uniaxial_reference(name: str, stretch: float) -> tuple[float, float]:
    """Lateral stretch and P_11 of the uniaxial-stress state F = diag(stretch, l, l).

    ``l`` is the root of P_22(stretch, l, l) = 0 (bisection to rounding); the fiber lies along
    the loading axis, so the two lateral stretches are equal by symmetry.
    """

    def piola(lateral: float) -> np.ndarray:
        return reference_piola(name, np.diag([stretch, lateral, lateral]))

    low, high = 0.3, 1.5
    assert piola(low)[1, 1] < 0 < piola(high)[1, 1]
    for _ in range(200):
        mid = (low + high) / 2
        if mid in (low, high):
            break
        low, high = (mid, high) if piola(mid)[1, 1] < 0 else (low, mid)
    lateral = (low + high) / 2
    return lateral, piola(lateral)[0, 0]


@pytest.mark.parametrize("name", MODELS)
def test_uniaxial_stretch_of_unit_cube(name):
    """Roller supports on x=0, y=0, z=0 and u_x = stretch - 1 on x=1: homogeneous uniaxial stress.

    The exact displacement is linear, hence in the P1 space; the Newton solution must reproduce
    the 1-D reduced stress-stretch relation to 1e-8.
    """
    stretch = 1.25
    msh = mesh.create_unit_cube(MPI.COMM_WORLD, 2, 2, 2)
    V = fem.functionspace(msh, ("Lagrange", 1, (3,)))
    u = fem.Function(V)
    fdim = msh.topology.dim - 1
    bcs = []
    for axis, position, value in [
        (0, 0.0, 0.0),
        (1, 0.0, 0.0),
        (2, 0.0, 0.0),
        (0, 1.0, stretch - 1),
    ]:
        facets = mesh.locate_entities_boundary(
            msh, fdim, lambda x, a=axis, p=position: np.isclose(x[a], p)
        )
        dofs = fem.locate_dofs_topological(V.sub(axis), fdim, facets)
        bcs.append(fem.dirichletbc(PETSc.ScalarType(value), dofs, V.sub(axis)))

    F = ufl.variable(ufl.Identity(3) + ufl.grad(u))
    a0 = fem.Constant(msh, E1)
    P = ufl.diff(_psi_of(name, F, a0), F)
    residual = ufl.inner(P, ufl.grad(ufl.TestFunction(V))) * ufl.dx
    iterations, converged = solve_nonlinear(
        residual,
        u,
        bcs,
        {"snes_atol": 1e-12, "snes_rtol": 1e-12},
        petsc_options_prefix=f"test_uniaxial_{name}_",
    )
    assert converged and iterations > 0

    def mean(expr) -> float:
        """Average over the unit cube (volume 1)."""
        local = fem.assemble_scalar(fem.form(expr * ufl.dx))
        return msh.comm.allreduce(local, op=MPI.SUM)

    lateral_ref, P11_ref = _uniaxial_reference(name, stretch)
    assert abs(mean(F[1, 1]) - lateral_ref) < 1e-8
    assert abs(mean(F[2, 2]) - lateral_ref) < 1e-8
    assert abs(mean(P[0, 0]) - P11_ref) < 1e-8 * max(1.0, abs(P11_ref))
    assert abs(mean(P[1, 1])) < 1e-8
