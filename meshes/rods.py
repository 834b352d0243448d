"""Rods standing on a slanted foundation (Hirota, Fisher & State 2003, Fig. 24), gmsh OCC.

In the foundation's own frame (primed): the foundation is the block
``[x0, x1] x [y0, y1] x [-depth, 0]``, and a ``rows x columns`` array of square rods (side
``side``, length ``length``) stands over its top face ``z' = 0``, rod ``(i, j)`` centred at
``(i pitch, j pitch)``, its base ``base_gap`` above the top face. The foundation reaches
``overhang`` beyond the rods on every side and ``length`` further on the downhill side
(``x' < 0``), where the rods fall.

Each rod is a transfinite
square of ``across`` x ``across`` cells (each cut into 2 triangles), extruded along the rod in
``layers`` layers of tetrahedra (each prism cut into 3). So the rods have interior vertices
(the material depth is positive inside them) at a low cost. The foundation is meshed
unstructured with size ``foundation_size``. The rods are separate volumes, not glued to the
foundation: clamp their bases (see :func:`rods_mesh`).

:func:`rods_mesh` then rotates the mesh by ``tilt`` about the y axis: the foundation's top face
slopes down towards ``-x``, the rods lean the same way, and gravity along ``-z`` pulls them over
onto their downhill neighbours and the foundation.

Run ``python3 meshes/rods.py`` to write the default mesh to ``output/rods.xdmf``.
"""

from __future__ import annotations

import dataclasses

from mpi4py import MPI

import dolfinx
import numpy as np

from fenics_matdepth.meshing import gmsh_build_to_mesh

__all__ = ["FOUNDATION", "ROD", "RodsGeometry", "build_rods_model", "rods_mesh"]

#: Cell tags: the foundation, and the rods (all rods share one tag).
FOUNDATION, ROD = 1, 2


@dataclasses.dataclass(frozen=True)
class RodsGeometry:
    """Sizes of the scene (length unit L) and its mesh resolution.

    Attributes:
        rows, columns: rods along x' (downhill) and along y.
        side: side of a rod's square section.
        length: length of a rod.
        pitch: distance between neighbouring rods' axes.
        depth: thickness of the foundation.
        overhang: foundation beyond the outer rods (besides the extra ``length`` downhill).
        across: cells across a rod's side (>= 2 for interior vertices).
        layers: layers of cells along a rod.
        foundation_size: mesh size in the foundation.
        tilt: rotation of the scene about y (degrees): the foundation's slope.
        base_gap: height of the rods' bases above the foundation's top face. The rods are
            clamped there rather than standing on the face: a base face lying in the plane of
            the foundation's top face makes coplanar triangle-tetrahedron intersections whose
            area (and contact stiffness, ``eps int grad g grad g dA`` even at zero depth)
            flickers with round-off from one Newton iterate to the next.
    """

    rows: int = 7
    columns: int = 5
    side: float = 0.01
    length: float = 0.08
    pitch: float = 0.025
    depth: float = 0.04
    overhang: float = 0.015
    across: int = 2
    layers: int = 12
    foundation_size: float = 0.012
    tilt: float = 45.0
    base_gap: float = 0.001

    @property
    def foundation_box(self) -> tuple[float, float, float, float]:
        """``(x0, x1, y0, y1)`` of the foundation in its own frame."""
        half = self.side / 2 + self.overhang
        return (
            -half - self.length,
            (self.rows - 1) * self.pitch + half,
            -half,
            (self.columns - 1) * self.pitch + half,
        )

    def rotation(self) -> np.ndarray:
        """The 3 x 3 rotation from the foundation's frame to the world frame."""
        a = np.radians(self.tilt)
        # about y, taking the rod axis e_z' to (-sin a, 0, cos a): the rods lean towards -x
        return np.array(
            [[np.cos(a), 0.0, -np.sin(a)], [0.0, 1.0, 0.0], [np.sin(a), 0.0, np.cos(a)]]
        )


def build_rods_model(gmsh_model, geometry: RodsGeometry = RodsGeometry()) -> None:
    """Build and mesh the scene, in the foundation's frame, in ``gmsh_model`` (this process).

    Args:
        gmsh_model: ``gmsh.model`` of an initialised gmsh session; a new model is added.
        geometry: sizes and resolution.
    """
    import gmsh

    g = geometry
    if g.across < 2:
        raise ValueError("rods need at least 2 cells across (interior vertices), got across < 2")
    occ = gmsh_model.occ
    gmsh_model.add("rods")
    x0, x1, y0, y1 = g.foundation_box
    foundation = occ.addBox(x0, y0, -g.depth, x1 - x0, y1 - y0, g.depth)
    squares = []
    for i in range(g.rows):
        for j in range(g.columns):
            cx, cy = i * g.pitch, j * g.pitch
            squares.append(
                occ.addRectangle(cx - g.side / 2, cy - g.side / 2, g.base_gap, g.side, g.side)
            )
    occ.synchronize()
    # structured squares (the extrusion copies their mesh layer by layer)
    for square in squares:
        for _, curve in gmsh_model.getBoundary([(2, square)], oriented=False):
            gmsh_model.mesh.setTransfiniteCurve(curve, g.across + 1)
        gmsh_model.mesh.setTransfiniteSurface(square)
    rods = []
    for square in squares:
        out = occ.extrude([(2, square)], 0.0, 0.0, g.length, numElements=[g.layers])
        rods += [tag for dim, tag in out if dim == 3]
    occ.synchronize()
    gmsh_model.addPhysicalGroup(3, [foundation], FOUNDATION, name="foundation")
    gmsh_model.addPhysicalGroup(3, rods, ROD, name="rods")
    gmsh_model.mesh.setSize(
        gmsh_model.getBoundary([(3, foundation)], recursive=True), g.foundation_size
    )
    gmsh.option.setNumber("Mesh.MeshSizeMax", g.foundation_size)
    gmsh_model.mesh.generate(3)


def rods_mesh(
    comm: MPI.Comm = MPI.COMM_WORLD, geometry: RodsGeometry = RodsGeometry()
) -> tuple[dolfinx.mesh.Mesh, dolfinx.mesh.MeshTags]:
    """The scene meshed by gmsh on rank 0, distributed over ``comm`` and tilted (world frame).

    The foundation's frame maps to the world frame by ``geometry.rotation()``; a point's height
    above the foundation's top face is ``x . R[:, 2]`` (``R`` the rotation): zero on the top
    face, ``base_gap`` at the rods' bases, negative inside the foundation.

    Args:
        comm: MPI communicator of the mesh (collective).
        geometry: sizes and resolution.

    Returns:
        ``(mesh, cell_tags)`` with the tags :data:`FOUNDATION` and :data:`ROD`.
    """
    mesh, cell_tags, _ = gmsh_build_to_mesh(lambda model: build_rods_model(model, geometry), comm)
    x = mesh.geometry.x
    x[:] = x @ geometry.rotation().T
    return mesh, cell_tags


if __name__ == "__main__":
    from pathlib import Path

    comm = MPI.COMM_WORLD
    mesh, cell_tags = rods_mesh(comm)
    output = Path(__file__).resolve().parent / "output"
    output.mkdir(exist_ok=True)
    with dolfinx.io.XDMFFile(comm, output / "rods.xdmf", "w") as xdmf:
        xdmf.write_mesh(mesh)
        xdmf.write_meshtags(cell_tags, mesh.geometry)
    if comm.rank == 0:
        print(
            f"rods: {mesh.topology.index_map(3).size_global} tetrahedra, "
            f"{mesh.geometry.index_map().size_global} vertices -> {output / 'rods.xdmf'}"
        )
