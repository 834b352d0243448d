"""The contact state as DOLFINx P1 Functions (for VTX/XDMF files and pyvista): contact
pressure, penetration, traction vector, slip vector and status.

The pressure and traction are the surface densities of the model's forces, averaged on each
boundary vertex's hat function over the boundary triangles around it (a lumped projection:
``sum_q w_q t_q xi_a / (area around a / 3)`` over the quadrature points q of the intersection
polygons, ``xi_a`` the triangle's barycentric coordinate of vertex a). Where two bodies meet,
both surfaces enter the other, and each surface's vertices carry the traction that acts on
that surface.
"""

from __future__ import annotations

import typing

from mpi4py import MPI

import dolfinx
import numpy as np

from fenics_matdepth._constants import FLOAT

__all__ = ["OPEN", "SLIP", "STICK", "contact_fields"]

#: The status of a vertex with no contact.
OPEN = 0
#: The status of a vertex in contact and sticking (most of its friction points slip less than
#: the slip tolerance).
STICK = 1
#: The status of a vertex in contact and slipping (frictionless contact always slips).
SLIP = 2


def _vertex_sums(comm: MPI.Comm, n: int, verts: np.ndarray, xi: np.ndarray, values: np.ndarray):
    """``sum_q xi[q, a] values[q]`` onto the global vertices ``verts[q, a]`` (``(n, k)``,
    summed over the ranks)."""
    local = np.zeros((n, values.shape[1]), dtype=FLOAT)
    for a in range(verts.shape[1]):  # the triangle's 3 corners
        np.add.at(local, verts[:, a], xi[:, a, None] * values)
    out = np.empty_like(local)
    comm.Allreduce(local, out, op=MPI.SUM)
    return out


def contact_fields(operator: typing.Any) -> dict[str, dolfinx.fem.Function]:
    """The contact fields of ``operator`` (a :class:`~fenics_matdepth.ContactOperator` with
    area integration) at its last update; see :meth:`~fenics_matdepth.ContactOperator.fields`."""
    op = operator
    s, comm, n = op.surface, op.comm, op.num_vertices
    # the area around each boundary vertex, a third of each triangle's (current) area
    xt = s.x[s.tri]
    tri_area = 0.5 * np.linalg.norm(np.cross(xt[:, 1] - xt[:, 0], xt[:, 2] - xt[:, 0]), axis=1)
    third = np.repeat(tri_area[:, None] / 3.0, 3, axis=1)
    around = _vertex_sums(comm, n, s.global_vertex[s.tri], third, np.ones((s.tri.shape[0], 1)))
    around = around[:, 0]
    safe = np.where(around > 0.0, around, 1.0)
    # normal traction at the current state: -p n on the triangle's side
    pts = op.contact_points()
    tri_verts = pts["verts"][pts["pair"], :3]
    xi = pts["coef"][:, :3]
    force_n = -pts["weight"][:, None] * pts["normal"]
    sums = _vertex_sums(comm, n, tri_verts, xi, np.column_stack((pts["weight"], force_n)))
    pressure = sums[:, 0] / safe
    traction = sums[:, 1:] / safe[:, None]
    status = np.where(pressure > 0.0, SLIP, OPEN)
    slip = np.zeros((n, 3), dtype=FLOAT)
    fp = op.friction_points() if op.friction is not None else None
    if fp is not None:
        y, force_t, vector = fp["slip_length"], fp["force"], fp["slip"]
        f_verts = fp["verts"][:, :3]
        f_xi = fp["coef"][:, :3]
        area = fp["area"][:, None]
        sliding = (y >= op.slip_tol).astype(FLOAT)[:, None]
        f_sums = _vertex_sums(
            comm, n, f_verts, f_xi, np.hstack((force_t, area * vector, area, area * sliding))
        )
        traction += f_sums[:, :3] / safe[:, None]
        touched = f_sums[:, 6] > 0.0
        weight = np.where(touched, f_sums[:, 6], 1.0)
        slip = f_sums[:, 3:6] / weight[:, None]
        sticking = touched & (f_sums[:, 7] <= 0.5 * f_sums[:, 6]) & (pressure > 0.0)
        status = np.where(sticking, STICK, status)
    return _functions(
        op.u.function_space,
        {
            "pressure": pressure,
            "penetration": op.vertex_penetration(),
            "status": status.astype(FLOAT),
            "traction": traction,
            "slip": slip,
        },
    )


def _functions(V: dolfinx.fem.FunctionSpace, values: dict[str, np.ndarray]) -> dict:
    """P1 Functions (scalars on a collapsed component space of ``V``, vectors on ``V``) from
    per-vertex values in the global vertex numbering of ``V``'s index map."""
    imap = V.dofmap.index_map
    n_local = imap.size_local + imap.num_ghosts
    glob = imap.local_to_global(np.arange(n_local, dtype=np.int32))
    out = {}
    scalars = [k for k, v in values.items() if v.ndim == 1]
    carrier = dolfinx.fem.Function(V)
    for c, name in enumerate(scalars):
        carrier.x.array.reshape(-1, 3)[:, c] = values[name][glob]
        f = carrier.sub(c).collapse()
        f.name = name
        out[name] = f
    for name in (k for k, v in values.items() if v.ndim == 2):
        f = dolfinx.fem.Function(V, name=name)
        f.x.array.reshape(-1, 3)[:] = values[name][glob]
        out[name] = f
    return out
