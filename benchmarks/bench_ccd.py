"""Seconds per continuous-collision query on two boxes whose boundaries close a gap in a step.

Two 1 x 1 x 0.1 boxes of ``n x n x 3`` cuboids (6 tetrahedra each), 0.01 apart; in the step
the upper box moves 0.02 down (through the gap) and every boundary vertex jitters by 1e-3.
One query: the swept-box tree over all boundary triangles, the query of every triangle's
swept box, and the entry caps of the vertex-triangle and edge-edge pairs
(`fenics_matdepth.geometry.ccd.sweep_caps`), as `ContinuousCollision.step_fraction` does on
one rank. Prints the figures (the first query compiles the kernels and is not timed).

Run: ``scripts/fenicsx python3 benchmarks/bench_ccd.py [n]`` (default n = 45: 18,360
boundary triangles).
"""

from __future__ import annotations

import sys
import time

import numpy as np

from fenics_matdepth.geometry.boxes import element_boxes
from fenics_matdepth.geometry.bvh import AABBTree
from fenics_matdepth.geometry.ccd import sweep_caps, sweep_topology, triangle_bodies
from fenics_matdepth.meshing import box_tetrahedra


def boundary_faces(x: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """The faces of the tetrahedra that belong to one tetrahedron only, oriented outwards
    (their normal away from the tetrahedron's fourth vertex: the exit caps need the sides)."""
    faces = np.concatenate(
        [cells[:, [1, 2, 3]], cells[:, [0, 3, 2]], cells[:, [0, 1, 3]], cells[:, [0, 2, 1]]]
    )
    opposite = np.concatenate([cells[:, 0], cells[:, 1], cells[:, 2], cells[:, 3]])
    _, first, count = np.unique(
        np.sort(faces, axis=1), axis=0, return_index=True, return_counts=True
    )
    keep = first[count == 1]
    faces, opposite = faces[keep], opposite[keep]
    a, b, c = x[faces[:, 0]], x[faces[:, 1]], x[faces[:, 2]]
    inward = np.einsum("ij,ij->i", np.cross(b - a, c - a), x[opposite] - a) > 0.0
    faces[inward] = faces[inward][:, [0, 2, 1]]
    return faces


def main(n: int) -> None:
    x1, c1 = box_tetrahedra((n, n, 3), (0.0, 0.0, 0.0), (1.0, 1.0, 0.1))
    x2, c2 = box_tetrahedra((n, n, 3), (0.01, 0.02, 0.11), (1.0, 1.0, 0.1))
    x = np.vstack((x1, x2))
    faces = boundary_faces(x, np.vstack((c1, c2 + x1.shape[0])))
    used = np.unique(faces)
    renumber = np.full(x.shape[0], -1, dtype=np.int64)
    renumber[used] = np.arange(used.size)
    tri = renumber[faces]
    x0 = x[used]
    rng = np.random.default_rng(0)
    x1_ = x0 + 1e-3 * rng.normal(size=x0.shape)
    x1_[x0[:, 2] > 0.105, 2] -= 0.02
    nb = x0.shape[0]
    tri_edge, edges, vertex_owner, edge_owner = sweep_topology(tri, nb)
    entry = np.full(tri.shape[0], 0.25 / n)
    cells6 = np.ascontiguousarray(np.hstack((tri, tri + nb)))
    points = np.vstack((x0, x1_))
    # the bodies once, as ContinuousCollision holds them (not in the timed query)
    bodies = triangle_bodies(tri)

    def query(exits):
        tic = time.perf_counter()
        tree = AABBTree(points, cells6)
        lo, hi = element_boxes(points, cells6)
        qa, qb = tree.query_boxes(lo, hi)
        out = sweep_caps(
            x0, x1_, tri, tri_edge, edges, vertex_owner, edge_owner, entry, qa, qb, exits, bodies
        )
        return time.perf_counter() - tic, out, qa.size

    for exits in (True, False):  # with and without the exit caps (pass-through)
        query(exits)
        seconds = []
        for _ in range(3):
            t, out, pairs = query(exits)
            seconds.append(t)
        print(
            f"exits={exits}: {tri.shape[0]} boundary triangles, {nb} vertices, "
            f"{edges.shape[0]} edges; {pairs} overlapping swept-box triangle pairs, {out[1]} "
            f"capped primitive pairs, cap {out[0]:.4f}; query {min(seconds):.3f} s (best of 3)"
        )


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 45)
