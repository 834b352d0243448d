"""Hertz contact geometry: a hemisphere resting on a block (gmsh), a quarter of each by default.

Two separate volumes in one gmsh model, not glued (no boolean fragment between them), so the
DOLFINx mesh holds two disjoint bodies that touch at one point, the origin:

- the block ``[0, W] x [0, W] x [-H, 0]`` (cell tag :data:`BLOCK`), top face ``z = 0``;
- the lower half of the sphere of radius ``R`` centred at ``(0, 0, R)``, cut by the planes
  ``x = 0`` and ``y = 0`` (cell tag :data:`SPHERE`); its flat face is ``z = R``.

The planes ``x = 0`` and ``y = 0`` are symmetry planes of the full problem. With
``full=True`` the model is the full problem instead, as dolfinx_contact's Hertz demo meshes it
(``create_halfsphere_box_mesh``): the block ``[-W, W] x [-W, W] x [-H, 0]`` and the whole lower
half of the sphere, without symmetry planes; the block's top face then has no vertex at the
origin (the sphere's pole has one). The mesh size is ``contact_size`` within
``refine_radius`` of the origin and grows linearly to ``far_size`` at distance
``coarsen_radius``, through a gmsh Distance + Threshold background field.

Run ``python3 meshes/hertz.py`` to write the default mesh to ``output/hertz.xdmf``.
"""

from __future__ import annotations

from mpi4py import MPI

import dolfinx

from fenics_matdepth.meshing import gmsh_build_to_mesh

__all__ = [
    "BLOCK",
    "BLOCK_BOTTOM",
    "SPHERE",
    "SPHERE_TOP",
    "SYMMETRY_X",
    "SYMMETRY_Y",
    "build_hertz_model",
    "hertz_mesh",
]

#: Cell tags of the two bodies.
BLOCK, SPHERE = 1, 2
#: Facet tags: the block's bottom face ``z = -H``, the sphere's flat face ``z = R``, and the
#: symmetry planes ``x = 0`` and ``y = 0`` (both bodies).
BLOCK_BOTTOM, SPHERE_TOP, SYMMETRY_X, SYMMETRY_Y = 1, 2, 3, 4


def build_hertz_model(
    gmsh_model,
    radius: float = 1.0,
    block_width: float = 1.0,
    block_depth: float = 1.0,
    contact_size: float = 0.015,
    far_size: float = 0.15,
    refine_radius: float = 0.15,
    coarsen_radius: float = 1.0,
    full: bool = False,
) -> None:
    """Build and mesh the Hertz geometry in ``gmsh_model`` (the calling process only).

    Args:
        gmsh_model: ``gmsh.model`` of an initialised gmsh session; a new model is added.
        radius: sphere radius R (length unit L).
        block_width: block width W in x and y (L): the quarter block's, half the full one's.
        block_depth: block depth H (L).
        contact_size: mesh size within ``refine_radius`` of the contact point (L).
        far_size: mesh size at distance ``coarsen_radius`` and beyond (L).
        refine_radius: radius of the finely meshed ball around the contact point (L).
        coarsen_radius: distance at which the size reaches ``far_size`` (L).
        full: the full model (no symmetry planes) instead of the quarter.
    """
    import gmsh

    occ = gmsh_model.occ
    gmsh_model.add("hertz")
    lo = -1.0 if full else 0.0  # the bodies' extent in x and y, in units of their width
    sphere = occ.addSphere(0.0, 0.0, radius, radius)
    cut = occ.addBox(lo * radius, lo * radius, 0.0, (1 - lo) * radius, (1 - lo) * radius, radius)
    (sphere_vol,), _ = occ.intersect([(3, sphere)], [(3, cut)])
    width = (1 - lo) * block_width
    corner = lo * block_width
    block_vol = (3, occ.addBox(corner, corner, -block_depth, width, width, block_depth))
    occ.synchronize()

    gmsh_model.addPhysicalGroup(3, [block_vol[1]], BLOCK, name="block")
    gmsh_model.addPhysicalGroup(3, [sphere_vol[1]], SPHERE, name="sphere")
    # OCC bounding boxes are padded by about 1e-7: compare with a looser tolerance.
    tol = 1e-5 * radius
    groups = {BLOCK_BOTTOM: [], SPHERE_TOP: [], SYMMETRY_X: [], SYMMETRY_Y: []}
    for dim, tag in gmsh_model.getEntities(2):
        _, _, z0, x1, y1, z1 = gmsh_model.getBoundingBox(dim, tag)
        if abs(x1) < tol:
            groups[SYMMETRY_X].append(tag)
        elif abs(y1) < tol:
            groups[SYMMETRY_Y].append(tag)
        elif abs(z1 + block_depth) < tol:
            groups[BLOCK_BOTTOM].append(tag)
        elif abs(z0 - radius) < tol:
            groups[SPHERE_TOP].append(tag)
    names = {BLOCK_BOTTOM: "block_bottom", SPHERE_TOP: "sphere_top"}
    names |= {SYMMETRY_X: "symmetry_x", SYMMETRY_Y: "symmetry_y"}
    if full:
        for group in (SYMMETRY_X, SYMMETRY_Y):
            groups.pop(group)
    for group, tags in groups.items():
        if not tags:
            raise RuntimeError(f"hertz geometry: no surface found for {names[group]}")
        gmsh_model.addPhysicalGroup(2, tags, group, name=names[group])

    # Size field: fine around the contact point (the sphere's pole, and the block's corner in
    # the quarter model).
    origin = gmsh_model.getEntitiesInBoundingBox(-tol, -tol, -tol, tol, tol, tol, 0)
    if len(origin) != (1 if full else 2):
        raise RuntimeError(f"hertz geometry: unexpected points at the origin: {origin}")
    field = gmsh_model.mesh.field
    distance = field.add("Distance")
    field.setNumbers(distance, "PointsList", [tag for _, tag in origin])
    threshold = field.add("Threshold")
    field.setNumber(threshold, "InField", distance)
    field.setNumber(threshold, "SizeMin", contact_size)
    field.setNumber(threshold, "SizeMax", far_size)
    field.setNumber(threshold, "DistMin", refine_radius)
    field.setNumber(threshold, "DistMax", coarsen_radius)
    field.setAsBackgroundMesh(threshold)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    gmsh_model.mesh.generate(3)


def hertz_mesh(
    comm: MPI.Comm = MPI.COMM_WORLD, **kwargs
) -> tuple[dolfinx.mesh.Mesh, dolfinx.mesh.MeshTags, dolfinx.mesh.MeshTags]:
    """The Hertz mesh (quarter or full), meshed by gmsh on rank 0 and distributed over ``comm``.

    Args:
        comm: MPI communicator of the mesh (collective).
        **kwargs: geometry and mesh sizes, see :func:`build_hertz_model`.

    Returns:
        ``(mesh, cell_tags, facet_tags)`` with the tags of this module.
    """
    return gmsh_build_to_mesh(lambda model: build_hertz_model(model, **kwargs), comm)


if __name__ == "__main__":
    from pathlib import Path

    from dolfinx.io import XDMFFile

    mesh, cell_tags, facet_tags = hertz_mesh(MPI.COMM_WORLD)
    n_cells = mesh.topology.index_map(3).size_global
    n_vertices = mesh.topology.index_map(0).size_global
    if MPI.COMM_WORLD.rank == 0:
        print(f"hertz mesh: {n_cells} tetrahedra, {n_vertices} vertices")
    out = Path(__file__).resolve().parents[1] / "output"
    out.mkdir(exist_ok=True)
    with XDMFFile(mesh.comm, out / "hertz.xdmf", "w") as xdmf:
        xdmf.write_mesh(mesh)
        mesh.topology.create_connectivity(2, 3)
        xdmf.write_meshtags(cell_tags, mesh.geometry)
        xdmf.write_meshtags(facet_tags, mesh.geometry)
