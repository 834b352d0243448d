"""Prescribed rigid motions as Dirichlet data (a bone rotated about a joint axis, a clamp turned)
and the deformation gradient's determinant per cell.

* :func:`rotation_matrix`: the 3 x 3 matrix of a rotation about an axis (Rodrigues' formula).
* :func:`rotation_displacement`: the displacement ``u = R (X - c) + c - X`` of reference points
  ``X`` rotated about the axis through the centre ``c``.
* :class:`RigidRotation`: a ``dolfinx.fem.Function`` holding that displacement at every dof of a
  vector space, updated for a new angle with :meth:`RigidRotation.set_angle`; hand it to
  ``dolfinx.fem.dirichletbc`` once and change the angle at each load step::

      tibia = fm.RigidRotation(V, center=(0, 0, 0), axis=(-1, 0, 0))
      bc = dolfinx.fem.dirichletbc(tibia.function, tibia_dofs)
      fm.solve_load_steps(problem, lambda t: tibia.set_angle(t * np.radians(150)), 50)

Angles are in radians; the sense of rotation is right-handed about ``axis``.

And what the solvers check of a displacement:

* :func:`check_function_space`: ``u`` lives on a P1 vector space of dimension 3;
* :class:`CellDeterminants`: the smallest ``det F`` over the cells of a P1 displacement, a cheap
  per-cell evaluation used to reject trial states that invert elements.
"""

from __future__ import annotations

import typing

from mpi4py import MPI

import dolfinx
import numpy as np
from numba import njit

from fenics_matdepth.boundary import p1_dof_coordinates
from fenics_matdepth.geometry.clip import tet_frame

__all__ = [
    "CellDeterminants",
    "RigidRotation",
    "check_function_space",
    "rotation_displacement",
    "rotation_matrix",
]


def _unit(axis: typing.Sequence[float]) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64).reshape(-1)
    norm = float(np.linalg.norm(axis)) if axis.shape == (3,) else 0.0
    if not (np.isfinite(norm) and norm > 0.0):
        raise ValueError(f"the rotation axis must be a non-zero 3-vector, got {axis!r}")
    return axis / norm


def rotation_matrix(axis: typing.Sequence[float], angle: float) -> np.ndarray:
    """Matrix of the right-handed rotation by ``angle`` (radians) about ``axis`` (any length).

    Rodrigues' formula ``R = I + sin(a) K + (1 - cos(a)) K^2`` with ``K`` the cross-product
    matrix of the unit axis.
    """
    k = _unit(axis)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * (K @ K)


def rotation_displacement(
    points: np.ndarray,
    center: typing.Sequence[float],
    axis: typing.Sequence[float],
    angle: float,
) -> np.ndarray:
    """Displacement of ``points`` (n, 3) rotated by ``angle`` about the axis through ``center``.

    Args:
        points: reference coordinates (n, 3) (length L).
        center: a point of the rotation axis (L).
        axis: direction of the axis (right-handed sense of rotation).
        angle: rotation angle (radians).

    Returns:
        ``R (X - c) + c - X``, shape (n, 3) (L).
    """
    X = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    c = np.asarray(center, dtype=np.float64).reshape(3)
    R = rotation_matrix(axis, angle)
    return (X - c) @ (R - np.eye(3)).T


class RigidRotation:
    """A displacement Function that rotates a vector space's dofs rigidly about an axis.

    The Function holds the rotation's displacement at *every* dof of ``V`` (a blocked Lagrange
    space of value size 3, any degree); a Dirichlet condition built on it applies the rotation
    on the dofs it is given (a bone's vertices, a clamped face).

    Args:
        V: vector function space (value shape (3,)) of the displacement.
        center: a point of the rotation axis (L).
        axis: direction of the axis (right-handed sense of rotation).
        angle: initial angle (radians); default 0 (zero displacement).

    Attributes:
        function: the displacement Function (name ``"rigid_rotation"``).
        angle: the angle it currently holds (radians).
    """

    def __init__(
        self,
        V: dolfinx.fem.FunctionSpace,
        center: typing.Sequence[float],
        axis: typing.Sequence[float],
        angle: float = 0.0,
    ):
        if V.dofmap.index_map_bs != 3:
            raise ValueError(
                "RigidRotation needs a vector space of value size 3, e.g. "
                'functionspace(mesh, ("Lagrange", 1, (3,)))'
            )
        self.center = np.asarray(center, dtype=np.float64).reshape(3)
        self.axis = _unit(axis)
        self.function = dolfinx.fem.Function(V, name="rigid_rotation")
        # one row per block (owned and ghost), the block's reference coordinates
        self._X = V.tabulate_dof_coordinates()[:, :3].copy()
        self.angle = float("nan")
        self.set_angle(angle)

    def set_angle(self, angle: float) -> None:
        """Set the Function to the rotation by ``angle`` (radians), owned and ghost dofs."""
        self.angle = float(angle)
        values = rotation_displacement(self._X, self.center, self.axis, self.angle)
        self.function.x.array[:] = values.reshape(-1)

    def __call__(self, angle: float) -> None:
        """Same as :meth:`set_angle` (so the object can be a ``set_load`` callback)."""
        self.set_angle(angle)


def check_function_space(u: dolfinx.fem.Function, what: str = "u") -> None:
    """``u`` must be a Function on a P1 (Lagrange degree 1) vector space of dimension 3.

    Raises:
        TypeError: if ``u`` is not a dolfinx Function.
        ValueError: for another element, naming it and the space to use.
    """
    if not isinstance(u, dolfinx.fem.Function):
        raise TypeError(
            f"{what} must be a dolfinx.fem.Function, got {type(u).__name__}: create it with "
            'dolfinx.fem.Function(functionspace(mesh, ("Lagrange", 1, (3,))))'
        )
    V = u.function_space
    element = V.ufl_element()
    if V.dofmap.index_map_bs != 3 or element.degree != 1 or len(element.reference_value_shape) != 1:
        raise ValueError(
            f"{what} must live on a P1 vector space of dimension 3, got a space of degree "
            f"{element.degree} with {V.dofmap.index_map_bs} component(s): use "
            'functionspace(mesh, ("Lagrange", 1, (3,)))'
        )


@njit(cache=True, error_model="numpy", fastmath=False)
def _signed_volumes6(X: np.ndarray, u: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Six times the signed volume of each tetrahedron ``cells`` (n, 4) of the points ``X + u``
    (``X`` (m, 3); ``u`` flat, 3 values per point), as the clipping kernels compute it
    (:func:`~fenics_matdepth.geometry.clip.tet_frame`)."""
    out = np.empty(cells.shape[0])
    for c in range(cells.shape[0]):
        i, j, k, m = cells[c, 0], cells[c, 1], cells[c, 2], cells[c, 3]
        out[c] = tet_frame(
            X[i, 0] + u[3 * i], X[i, 1] + u[3 * i + 1], X[i, 2] + u[3 * i + 2],
            X[j, 0] + u[3 * j], X[j, 1] + u[3 * j + 1], X[j, 2] + u[3 * j + 2],
            X[k, 0] + u[3 * k], X[k, 1] + u[3 * k + 1], X[k, 2] + u[3 * k + 2],
            X[m, 0] + u[3 * m], X[m, 1] + u[3 * m + 1], X[m, 2] + u[3 * m + 2],
        )[0]  # fmt: skip
    return out


class CellDeterminants:
    """Smallest ``det F = det(I + grad u)`` over the cells of a P1 vector displacement.

    On affine tetrahedra ``F`` is constant per cell: ``det F = V_current / V_reference`` with
    signed volumes from the vertex positions. The reference volumes are kept; each call is one
    compiled loop over the cells (the solvers call it at every trial state; collective).

    Args:
        V: the P1 vector space (dimension 3) of the displacement.
    """

    def __init__(self, V: dolfinx.fem.FunctionSpace):
        mesh = V.mesh
        self._comm = mesh.comm
        num_owned = mesh.topology.index_map(3).size_local
        self._cells = np.asarray(V.dofmap.list).reshape(-1, 4)[:num_owned]
        self._X = np.ascontiguousarray(p1_dof_coordinates(V), dtype=np.float64)
        self._vol6 = _signed_volumes6(self._X, np.zeros(self._X.size), self._cells)

    def local_values(self, u_local: np.ndarray) -> np.ndarray:
        """det F of each of this rank's owned cells for the local (owned + ghost) displacement
        values."""
        u = np.ascontiguousarray(u_local, dtype=np.float64).reshape(-1)
        return _signed_volumes6(self._X, u, self._cells) / self._vol6

    def local_min(self, u_local: np.ndarray) -> float:
        """This rank's smallest det F for the local (owned + ghost) displacement values."""
        if self._cells.shape[0] == 0:
            return np.inf
        value = float(self.local_values(u_local).min())
        return value if np.isfinite(value) else -np.inf

    def min(self, u: dolfinx.fem.Function | np.ndarray) -> float:
        """Smallest det F over all cells (collective); NaN displacements give ``-inf``.

        Args:
            u: the displacement Function (ghost values current), or its local array.
        """
        values = u.x.array if isinstance(u, dolfinx.fem.Function) else u
        return self._comm.allreduce(self.local_min(values), op=MPI.MIN)
