"""A snake and an apple (gmsh OCC): a soft tube with a flared mouth and a closed tail, and a ball.

Two disjoint bodies in one gmsh model (not glued), so the DOLFINx mesh holds both:

- the snake (cell tag :data:`SNAKE`): a solid of revolution about the x axis. Its wall is a
  tube of inner radius ``inner_radius`` and outer radius ``outer_radius`` from
  ``x = mouth_length`` to ``x = body_end``; towards the head (``x = 0``) the wall flares as a
  cone to a mouth of inner radius ``mouth_radius`` (wider than the apple: a snake's jaws open
  wide), with the same radial wall thickness; behind ``body_end`` the lumen ends in a
  hemisphere and the body in a half-ellipsoid tail of length ``tail_length``. The mouth's
  annular end face ``x = 0`` has facet tag :data:`LIP`.
- the apple (cell tags :data:`APPLE` and :data:`CORE`): a ball of radius ``apple_radius``
  centred at ``(apple_x, 0, 0)`` on the axis, in front of or inside the mouth. Its inner ball of
  radius ``core_radius`` is a separate volume glued conformingly to the rest of the apple
  (one body), so that the demo can prescribe the apple's motion on the core's vertices, well
  inside the apple.

Mesh sizes: ``snake_size`` in the snake; ``apple_size`` on the apple's surface, growing to
``2 * apple_size`` in the core. ``resolution`` scales all sizes (2 halves them). The wall is
``outer_radius - inner_radius`` thick: the default sizes put 2 to 3 elements across it.

Run ``python3 meshes/snake.py`` to write the default mesh to ``output/snake.xdmf`` and print
its size.
"""

from __future__ import annotations

import math

from mpi4py import MPI

import dolfinx

from fenics_matdepth.meshing import gmsh_build_to_mesh

__all__ = ["APPLE", "CORE", "LIP", "SNAKE", "build_snake_model", "snake_mesh"]

#: Cell tags: the snake, the apple's outer part, the apple's core.
SNAKE, APPLE, CORE = 1, 2, 3
#: Facet tag of the mouth's annular end face (x = 0).
LIP = 1


def build_snake_model(
    gmsh_model,
    inner_radius: float = 3.5,
    outer_radius: float = 8.0,
    mouth_radius: float = 12.5,
    mouth_length: float = 15.0,
    body_end: float = 50.0,
    tail_length: float = 12.0,
    apple_radius: float = 10.0,
    apple_x: float = -1.0,
    core_radius: float = 4.0,
    snake_size: float = 1.8,
    apple_size: float = 1.8,
    resolution: float = 1.0,
) -> None:
    """Build and mesh the snake and the apple in ``gmsh_model`` (the calling process only).

    Lengths in mm (any unit works; the defaults are an apple 20 mm across and a snake 62 mm long).

    Args:
        gmsh_model: ``gmsh.model`` of an initialised gmsh session; a new model is added.
        inner_radius: the body's inner (lumen) radius.
        outer_radius: the body's outer radius.
        mouth_radius: inner radius of the mouth at ``x = 0``.
        mouth_length: length of the flared part (the head), from the mouth to the body.
        body_end: x where the cylindrical body ends and the tail begins.
        tail_length: length of the half-ellipsoidal tail behind ``body_end``.
        apple_radius: the apple's radius.
        apple_x: x of the apple's centre.
        core_radius: radius of the apple's core (the driven region).
        snake_size: mesh size in the snake.
        apple_size: mesh size on the apple's surface (twice that in the core).
        resolution: divides every mesh size.

    Raises:
        ValueError: if the dimensions are inconsistent (the apple not wider than the lumen, the
            mouth not wider than the apple, the core not inside the apple, ...).
    """
    import gmsh

    if not 0.0 < inner_radius < outer_radius:
        raise ValueError(
            f"need 0 < inner_radius < outer_radius, got {inner_radius}, {outer_radius}"
        )
    if not inner_radius < apple_radius < mouth_radius:
        raise ValueError(
            "the apple must be wider than the lumen and narrower than the mouth: need "
            f"inner_radius < apple_radius < mouth_radius, got {inner_radius}, {apple_radius}, "
            f"{mouth_radius}"
        )
    if not 0.0 < core_radius < apple_radius:
        raise ValueError(f"need 0 < core_radius < apple_radius, got {core_radius}")
    if not (0.0 < mouth_length < body_end and tail_length > outer_radius):
        raise ValueError("need 0 < mouth_length < body_end and tail_length > outer_radius")
    if resolution <= 0.0:
        raise ValueError(f"resolution must be positive, got {resolution}")

    occ = gmsh_model.occ
    gmsh_model.add("snake")
    wall = outer_radius - inner_radius
    # The wall's meridian section in the (x, y >= 0) plane, revolved about the x axis.
    p = [
        occ.addPoint(0.0, mouth_radius, 0.0),  # 0 mouth, inner lip
        occ.addPoint(mouth_length, inner_radius, 0.0),  # 1 throat
        occ.addPoint(body_end, inner_radius, 0.0),  # 2 end of the lumen's cylinder
        occ.addPoint(body_end + inner_radius, 0.0, 0.0),  # 3 end of the lumen, on the axis
        occ.addPoint(body_end + tail_length, 0.0, 0.0),  # 4 tip of the tail
        occ.addPoint(body_end, outer_radius, 0.0),  # 5 start of the tail, outside
        occ.addPoint(mouth_length, outer_radius, 0.0),  # 6 neck, outside
        occ.addPoint(0.0, mouth_radius + wall, 0.0),  # 7 mouth, outer lip
    ]
    centre = occ.addPoint(body_end, 0.0, 0.0)
    curves = [
        occ.addLine(p[0], p[1]),
        occ.addLine(p[1], p[2]),
        occ.addCircleArc(p[2], centre, p[3]),
        occ.addLine(p[3], p[4]),
        occ.addEllipseArc(p[4], centre, p[4], p[5]),
        occ.addLine(p[5], p[6]),
        occ.addLine(p[6], p[7]),
        occ.addLine(p[7], p[0]),
    ]
    section = occ.addPlaneSurface([occ.addCurveLoop(curves)])
    snake = [
        tag for dim, tag in occ.revolve([(2, section)], 0, 0, 0, 1, 0, 0, 2 * math.pi) if dim == 3
    ]
    occ.remove([(0, centre)])

    apple = occ.addSphere(apple_x, 0.0, 0.0, apple_radius)
    core = occ.addSphere(apple_x, 0.0, 0.0, core_radius)
    pieces, _ = occ.fragment([(3, apple)], [(3, core)])
    occ.synchronize()
    core_vols, apple_vols = [], []
    for dim, tag in pieces:
        box = gmsh_model.getBoundingBox(dim, tag)
        (core_vols if box[3] - box[0] < apple_radius + core_radius else apple_vols).append(tag)
    if len(core_vols) != 1 or len(apple_vols) != 1:
        raise RuntimeError(f"snake geometry: the apple did not split into shell and core: {pieces}")

    gmsh_model.addPhysicalGroup(3, snake, SNAKE, name="snake")
    gmsh_model.addPhysicalGroup(3, apple_vols, APPLE, name="apple")
    gmsh_model.addPhysicalGroup(3, core_vols, CORE, name="core")
    tol = 1e-5 * outer_radius
    reach = 2.0 * (mouth_radius + wall)
    at_mouth = gmsh_model.getEntitiesInBoundingBox(-tol, -reach, -reach, tol, reach, reach, 2)
    # the lip's faces, not any of the apple's (which would lie inside the mouth's opening)
    lip = [tag for _, tag in at_mouth if gmsh_model.getBoundingBox(2, tag)[4] > mouth_radius]
    if not lip:
        raise RuntimeError("snake geometry: no face found at the mouth (x = 0)")
    gmsh_model.addPhysicalGroup(2, lip, LIP, name="lip")

    # Sizes: one per body, through the points of each body (OCC geometry, no size field).
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 1)
    snake_points = gmsh_model.getBoundary([(3, t) for t in snake], recursive=True)
    gmsh_model.mesh.setSize(snake_points, snake_size / resolution)
    apple_points = gmsh_model.getBoundary([(3, t) for t in apple_vols], recursive=True)
    gmsh_model.mesh.setSize(apple_points, apple_size / resolution)
    core_points = gmsh_model.getBoundary([(3, t) for t in core_vols], recursive=True)
    gmsh_model.mesh.setSize(core_points, 2 * apple_size / resolution)
    gmsh.option.setNumber("Mesh.MeshSizeMax", max(snake_size, 2 * apple_size) / resolution)
    gmsh.option.setNumber("General.NumThreads", 1)  # the same mesh on every run
    gmsh_model.mesh.generate(3)
    gmsh_model.mesh.optimize()


def snake_mesh(
    comm: MPI.Comm = MPI.COMM_WORLD, **kwargs
) -> tuple[dolfinx.mesh.Mesh, dolfinx.mesh.MeshTags, dolfinx.mesh.MeshTags]:
    """The snake-and-apple mesh, meshed by gmsh on rank 0 and distributed over ``comm``.

    Args:
        comm: MPI communicator of the mesh (collective).
        **kwargs: geometry and mesh sizes, see :func:`build_snake_model`.

    Returns:
        ``(mesh, cell_tags, facet_tags)`` with the tags of this module.
    """
    return gmsh_build_to_mesh(lambda model: build_snake_model(model, **kwargs), comm)


if __name__ == "__main__":
    import sys
    from pathlib import Path

    import numpy as np
    from dolfinx.io import XDMFFile

    resolution = float(sys.argv[1]) if len(sys.argv) > 1 else 1.0
    mesh, cell_tags, facet_tags = snake_mesh(MPI.COMM_WORLD, resolution=resolution)
    counts = {
        name: mesh.comm.allreduce(int(np.count_nonzero(cell_tags.values == tag)))
        for name, tag in (("snake", SNAKE), ("apple", APPLE), ("core", CORE))
    }
    n_cells = mesh.topology.index_map(3).size_global
    n_vertices = mesh.topology.index_map(0).size_global
    if MPI.COMM_WORLD.rank == 0:
        print(f"snake mesh: {n_cells} tetrahedra ({counts}), {n_vertices} vertices")
    out = Path(__file__).resolve().parents[1] / "output"
    out.mkdir(exist_ok=True)
    with XDMFFile(mesh.comm, out / "snake.xdmf", "w") as xdmf:
        xdmf.write_mesh(mesh)
        mesh.topology.create_connectivity(2, 3)
        xdmf.write_meshtags(cell_tags, mesh.geometry)
        xdmf.write_meshtags(facet_tags, mesh.geometry)
