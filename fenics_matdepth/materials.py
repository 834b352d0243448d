"""Hyperelastic strain-energy densities written in UFL (Hirota, Fisher & State 2003, §3.2).

Every model is a function ``psi(F, *parameters)`` returning the strain energy per unit
*reference* volume (J/m^3 = Pa when the parameters are in Pa) as a UFL expression of the
deformation gradient ``F = I + grad(u)``. The parameters may be Python floats or UFL
expressions (``dolfinx.fem.Constant``, ``Function``); using Constants lets one compiled form
serve every parameter value.

All models share three properties the contact method relies on:

* the reference state is stress free: ``P(I) = 0``;
* the energy grows without bound as ``J = det F -> 0+``, so that an element is never turned
  inside out by a finite load (the volumetric term below);
* at small strain they reduce to isotropic linear elasticity with the shear modulus ``mu`` and
  bulk modulus ``kappa`` returned by :func:`small_strain_moduli` (plus, for
  :func:`fiber_reinforced`, a fiber stiffness that acts in fiber tension only).

The isotropic models use the decoupled form ``psi = psi_iso(C_bar) + U(J)`` with
``C_bar = J^(-2/3) C`` and the volumetric energy

    U(J) = kappa / 4 * (J^2 - 1 - 2 ln J),

which has ``U(1) = U'(1) = 0``, ``U''(1) = kappa`` and ``U -> +inf`` both as ``J -> 0+`` and as
``J -> inf``. Two-dimensional ``F`` (2 x 2) is treated as plane strain: the out-of-plane
stretch is 1.

The first Piola-Kirchhoff stress is obtained by differentiation of the energy with respect to
``F`` made a :func:`ufl.variable` (:func:`first_piola_kirchhoff`).

Example:
    >>> import ufl
    >>> import fenics_matdepth as fm
    >>> F = ufl.variable(ufl.Identity(3) + ufl.grad(u))
    >>> psi = fm.materials.mooney_rivlin(F, c10=0.4e3, c01=0.1e3, kappa=1e5)
    >>> P = ufl.diff(psi, F)  # first Piola-Kirchhoff stress (Pa)

    or, equivalently, ``P = fm.materials.first_piola_kirchhoff(fm.materials.mooney_rivlin,
    F, c10=0.4e3, c01=0.1e3, kappa=1e5)``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import ufl
from ufl.core.expr import Expr
from ufl.variable import Variable

__all__ = [
    "SmallStrainModuli",
    "fiber_reinforced",
    "first_piola_kirchhoff",
    "mooney_rivlin",
    "neo_hookean",
    "shear_bulk_from_youngs_poisson",
    "small_strain_moduli",
    "veronda_westmann",
    "volumetric_energy",
    "youngs_poisson_from_shear_bulk",
]

#: A material parameter: a number or a UFL expression (e.g. a ``dolfinx.fem.Constant``).
Scalar = float | Expr


# --- Kinematics ---------------------------------------------------------------------------


def _invariants(F: Expr) -> tuple:
    """Return ``(J, I1, I2, C)`` of the right Cauchy-Green tensor ``C = F^T F`` in 3-D.

    A 2 x 2 ``F`` is read as plane strain (``F_33 = 1``): then ``I1 = tr C + 1`` and
    ``I2 = det C + tr C``.
    """
    dim = F.ufl_shape[0]
    if F.ufl_shape != (dim, dim) or dim not in (2, 3):
        raise ValueError(f"F must be a 2 x 2 or 3 x 3 tensor, got shape {F.ufl_shape}")
    C = F.T * F
    J = ufl.det(F)
    trC = ufl.tr(C)
    if dim == 3:
        return J, trC, (trC**2 - ufl.tr(C * C)) / 2, C
    return J, trC + 1, ufl.det(C) + trC, C


def _isochoric_invariants(F: Expr) -> tuple:
    """Return ``(J, I1_bar, I2_bar, C)``, invariants of ``C_bar = J^(-2/3) C``."""
    J, I1, I2, C = _invariants(F)
    return J, J ** (-2.0 / 3.0) * I1, J ** (-4.0 / 3.0) * I2, C


def volumetric_energy(J: Expr, kappa: Scalar) -> Expr:
    """Volumetric energy ``U(J) = kappa/4 (J^2 - 1 - 2 ln J)`` shared by every model.

    It is zero with zero slope at ``J = 1``, has curvature ``kappa`` there (so ``kappa`` is the
    small-strain bulk modulus), and tends to ``+inf`` as ``J -> 0+``: compressing an element to
    zero volume costs infinite energy, which keeps Newton iterates from inverting elements.

    Args:
        J: Volume ratio ``det F`` (dimensionless, > 0).
        kappa: Bulk modulus (Pa).

    Returns:
        Energy per unit reference volume (Pa).
    """
    return kappa / 4 * (J**2 - 1 - 2 * ufl.ln(J))


# --- Models -------------------------------------------------------------------------------


def neo_hookean(F: Expr, mu: Scalar, kappa: Scalar) -> Expr:
    """Compressible (decoupled) neo-Hookean energy.

    ``psi = mu/2 (I1_bar - 3) + U(J)``.

    Args:
        F: Deformation gradient (3 x 3, or 2 x 2 for plane strain).
        mu: Shear modulus (Pa). Small-strain shear modulus: ``mu``.
        kappa: Bulk modulus (Pa). Small-strain bulk modulus: ``kappa``.

    Returns:
        Strain energy per unit reference volume (Pa).
    """
    J, I1_bar, _, _ = _isochoric_invariants(F)
    return mu / 2 * (I1_bar - 3) + volumetric_energy(J, kappa)


def mooney_rivlin(F: Expr, c10: Scalar, c01: Scalar, kappa: Scalar) -> Expr:
    """Compressible (decoupled) Mooney-Rivlin energy.

    ``psi = c10 (I1_bar - 3) + c01 (I2_bar - 3) + U(J)``.

    Args:
        F: Deformation gradient (3 x 3, or 2 x 2 for plane strain).
        c10: First Mooney-Rivlin constant (Pa).
        c01: Second Mooney-Rivlin constant (Pa). Small-strain shear modulus:
            ``mu = 2 (c10 + c01)``.
        kappa: Bulk modulus (Pa). Small-strain bulk modulus: ``kappa``.

    Returns:
        Strain energy per unit reference volume (Pa).
    """
    J, I1_bar, I2_bar, _ = _isochoric_invariants(F)
    return c10 * (I1_bar - 3) + c01 * (I2_bar - 3) + volumetric_energy(J, kappa)


def veronda_westmann(F: Expr, c1: Scalar, c2: Scalar, kappa: Scalar) -> Expr:
    """Compressible Veronda-Westmann energy (the form used for soft tissue, e.g. in FEBio).

    ``psi = c1 (exp(c2 (I1_bar - 3)) - 1) - c1 c2 / 2 (I2_bar - 3) + U(J)``.

    The exponential in ``I1_bar`` stiffens the material at large stretch.

    Args:
        F: Deformation gradient (3 x 3, or 2 x 2 for plane strain).
        c1: Stress scale (Pa).
        c2: Exponential stiffening coefficient (dimensionless). Small-strain shear modulus:
            ``mu = c1 c2``.
        kappa: Bulk modulus (Pa). Small-strain bulk modulus: ``kappa``.

    Returns:
        Strain energy per unit reference volume (Pa).
    """
    J, I1_bar, I2_bar, _ = _isochoric_invariants(F)
    return (
        c1 * (ufl.exp(c2 * (I1_bar - 3)) - 1)
        - c1 * c2 / 2 * (I2_bar - 3)
        + volumetric_energy(J, kappa)
    )


def fiber_reinforced(
    F: Expr,
    mu: Scalar,
    kappa: Scalar,
    a0: Expr,
    k1: Scalar,
    k2: Scalar = 0.0,
    toe: float = 0.0,
) -> Expr:
    """Transversely isotropic fiber-reinforced energy: neo-Hookean matrix + tension-only fibers.

    ``psi = neo_hookean(F, mu, kappa) + psi_f(I4)``, with ``I4 = a0 . C a0`` the squared fiber
    stretch and (Holzapfel-Gasser-Ogden fiber term)

        psi_f = k1 / (2 k2) (exp(k2 (I4 - 1)^2) - 1)   if I4 > 1,   0 otherwise

    (``psi_f = k1/2 (I4 - 1)^2`` in tension when ``k2`` is the number 0). Fibers resist stretch
    only: under fiber compression, and under any deformation that leaves the fiber length
    unchanged (e.g. shear in a plane perpendicular to the fiber), the term is exactly zero.
    ``I4`` is built from the full ``C`` (not the isochoric one), so that fiber stretch, and not
    only fiber distortion, is penalised.

    With ``toe = d > 0`` (and ``k2 = 0``) the fibers stiffen over a toe region instead of
    switching on at ``I4 = 1``, as tendon does while its crimped collagen straightens (the
    first 2 to 4 % of strain): with ``s = I4 - 1``,

        psi_f = k1 s^3 / (6 d)                   for 0 < s <= d,
        psi_f = k1 / 2 (s - d / 2)^2 + k1 d^2 / 24   for s > d,

    so the fiber's second derivative ``d2 psi_f / ds2`` rises linearly from 0 to ``k1`` over
    the toe and the energy is twice continuously differentiable. Without it (``toe = 0``) the
    second derivative jumps from 0 to ``k1`` at ``I4 = 1``: Newton's method converges only
    linearly while fibers cross the slack length (measured on the knee demo's tendon,
    docs/measurements.md).

    Args:
        F: Deformation gradient (3 x 3, or 2 x 2 for plane strain).
        mu: Shear modulus of the matrix (Pa).
        kappa: Bulk modulus of the matrix (Pa).
        a0: Fiber direction in the reference configuration, a unit vector (UFL expression,
            ``Constant`` or vector ``Function``; not normalised here; where it is zero the fiber
            term is off).
        k1: Fiber stiffness (Pa). At small fiber tension the fiber adds ``4 k1`` to the
            uniaxial tangent modulus along ``a0``.
        k2: Fiber stiffening coefficient (dimensionless, >= 0).
        toe: Width ``d`` of the toe region in ``I4`` (dimensionless, >= 0; about twice the
            toe's strain): 0 for fibers that switch on at their slack length. Only with
            ``k2 = 0``.

    Returns:
        Strain energy per unit reference volume (Pa).
    """
    J, I1_bar, _, C = _isochoric_invariants(F)
    if a0.ufl_shape != (F.ufl_shape[0],):
        raise ValueError(f"a0 must be a vector of size {F.ufl_shape[0]}, got {a0.ufl_shape}")
    I4 = ufl.dot(a0, C * a0)
    stretch = I4 - 1
    quadratic = isinstance(k2, int | float) and k2 == 0
    if not (isinstance(toe, int | float) and toe >= 0.0):
        raise ValueError(f"toe must be a number >= 0, got {toe!r}")
    if toe > 0.0 and not quadratic:
        raise ValueError(
            f"the toe region is defined for the quadratic fiber term only (k2 = 0), got k2={k2}"
        )
    if quadratic:
        fiber = k1 / 2 * stretch**2
    else:
        fiber = k1 / (2 * k2) * (ufl.exp(k2 * stretch**2) - 1)
    matrix = mu / 2 * (I1_bar - 3) + volumetric_energy(J, kappa)
    if toe > 0.0:
        past = k1 / 2 * (stretch - toe / 2) ** 2 + k1 * toe**2 / 24
        within = k1 * stretch**3 / (6 * toe)
        fiber = ufl.conditional(ufl.gt(stretch, toe), past, within)
    return matrix + ufl.conditional(ufl.gt(I4, 1), fiber, 0)


# --- Stress -------------------------------------------------------------------------------


def first_piola_kirchhoff(
    strain_energy: Callable[..., Expr],
    F: Expr,
    *args,
    **kwargs,
) -> Expr:
    """First Piola-Kirchhoff stress ``P = d psi / d F`` by UFL differentiation.

    ``F`` is wrapped in a :func:`ufl.variable` (unless it already is one), the energy is built
    on it and differentiated with :func:`ufl.diff`.

    Args:
        strain_energy: A model of this module (or any ``psi(F, *args, **kwargs)``).
        F: Deformation gradient, e.g. ``ufl.Identity(3) + ufl.grad(u)``.
        *args: Material parameters passed on to ``strain_energy``.
        **kwargs: Material parameters passed on to ``strain_energy``.

    Returns:
        The stress tensor (Pa, force per unit reference area), same shape as ``F``.
    """
    F_var = F if isinstance(F, Variable) else ufl.variable(F)
    return ufl.diff(strain_energy(F_var, *args, **kwargs), F_var)


# --- Small-strain moduli ------------------------------------------------------------------


class SmallStrainModuli(NamedTuple):
    """Linear-elastic moduli a model reduces to at small strain (all in Pa).

    Attributes:
        shear: Shear modulus ``mu``.
        bulk: Bulk modulus ``kappa``.
        fiber: Extra uniaxial tangent modulus along the fiber, in fiber tension only
            (``4 k1`` for :func:`fiber_reinforced`, 0 for isotropic models).
    """

    shear: float
    bulk: float
    fiber: float = 0.0

    @property
    def youngs_modulus(self) -> float:
        """Young's modulus ``E = 9 kappa mu / (3 kappa + mu)`` (Pa) of the isotropic part."""
        return youngs_poisson_from_shear_bulk(self.shear, self.bulk)[0]

    @property
    def poisson_ratio(self) -> float:
        """Poisson's ratio (dimensionless) of the isotropic part."""
        return youngs_poisson_from_shear_bulk(self.shear, self.bulk)[1]

    @property
    def p_wave_modulus(self) -> float:
        """Constrained (uniaxial-strain) modulus ``kappa + 4 mu / 3`` (Pa) of the isotropic part."""
        return self.bulk + 4 * self.shear / 3

    @property
    def stiffest(self) -> float:
        """Largest uniaxial-strain tangent modulus over all directions (Pa).

        ``kappa + 4 mu / 3 + fiber``: the stiffness a penalty parameter has to be compared
        with.
        """
        return self.p_wave_modulus + self.fiber


def small_strain_moduli(
    strain_energy: Callable[..., Expr], **parameters: float
) -> SmallStrainModuli:
    """Small-strain shear and bulk moduli implied by a model's parameters.

    Args:
        strain_energy: One of :func:`neo_hookean`, :func:`mooney_rivlin`,
            :func:`veronda_westmann`, :func:`fiber_reinforced`.
        **parameters: The model's parameters by name, as numbers (``a0`` may be given or
            omitted for :func:`fiber_reinforced`).

    Returns:
        The moduli (Pa).

    Example:
        >>> small_strain_moduli(mooney_rivlin, c10=0.4e3, c01=0.1e3, kappa=1e5)
        SmallStrainModuli(shear=1000.0, bulk=100000.0, fiber=0.0)
    """
    p = parameters
    if strain_energy is neo_hookean:
        return SmallStrainModuli(float(p["mu"]), float(p["kappa"]))
    if strain_energy is mooney_rivlin:
        return SmallStrainModuli(2.0 * (p["c10"] + p["c01"]), float(p["kappa"]))
    if strain_energy is veronda_westmann:
        return SmallStrainModuli(float(p["c1"] * p["c2"]), float(p["kappa"]))
    if strain_energy is fiber_reinforced:
        return SmallStrainModuli(float(p["mu"]), float(p["kappa"]), 4.0 * p["k1"])
    raise ValueError(f"unknown strain-energy function {strain_energy!r}")


def shear_bulk_from_youngs_poisson(E: float, nu: float) -> tuple[float, float]:
    """Convert Young's modulus and Poisson's ratio to shear and bulk moduli.

    Args:
        E: Young's modulus (Pa).
        nu: Poisson's ratio (dimensionless, -1 < nu < 1/2).

    Returns:
        ``(mu, kappa)`` in Pa: ``mu = E / (2 (1 + nu))``, ``kappa = E / (3 (1 - 2 nu))``.
    """
    if not -1.0 < nu < 0.5:
        raise ValueError(f"Poisson's ratio must lie in (-1, 1/2), got {nu}")
    return E / (2 * (1 + nu)), E / (3 * (1 - 2 * nu))


def youngs_poisson_from_shear_bulk(mu: float, kappa: float) -> tuple[float, float]:
    """Convert shear and bulk moduli to Young's modulus and Poisson's ratio.

    Args:
        mu: Shear modulus (Pa, > 0).
        kappa: Bulk modulus (Pa, > 0).

    Returns:
        ``(E, nu)``: ``E = 9 kappa mu / (3 kappa + mu)`` (Pa) and
        ``nu = (3 kappa - 2 mu) / (2 (3 kappa + mu))``.
    """
    if not (mu > 0 and kappa > 0 and math.isfinite(mu) and math.isfinite(kappa)):
        raise ValueError(f"moduli must be positive and finite, got mu={mu}, kappa={kappa}")
    return 9 * kappa * mu / (3 * kappa + mu), (3 * kappa - 2 * mu) / (2 * (3 * kappa + mu))
