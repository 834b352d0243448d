"""Spatial core figures: AABB tree build/refit/candidate pairs and material depth (one core).

Prints each figure with its ratio to the target (ratio < 1 meets it); never asserts time.
Times are the best of a few repetitions after a JIT warm-up.

    scripts/fenicsx python3 benchmarks/bench_spatial.py [--depth-cells 99] [--skip-dolfinx]
"""

from __future__ import annotations

import argparse
import time

from mpi4py import MPI

import numpy as np

from fenics_matdepth.depth import distance_to_triangles
from fenics_matdepth.geometry.boxes import element_boxes, exclude_shared_vertex_pairs
from fenics_matdepth.geometry.bvh import AABBTree

#: Targets (seconds) from issue #3.
TARGET_DEPTH_1M_VERTICES = 5.0
TARGET_BUILD_1M_TETS = 1.0
TARGET_REFIT_1M_TETS = 0.050
TARGET_PAIRS_100K_TRI_1M_TETS = 0.5


def box_tets(n, lo=(0.0, 0.0, 0.0), h=1.0):
    """Structured box of n = (nx, ny, nz) cubes of side h, 6 tetrahedra per cube (Kuhn split)."""
    _, ny, nz = n
    axes = [lo[d] + h * np.arange(n[d] + 1) for d in range(3)]
    x = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    i, j, k = (a.ravel() for a in np.meshgrid(*(np.arange(m) for m in n), indexing="ij"))

    def vid(a, b, c):
        return ((i + a) * (ny + 1) + (j + b)) * (nz + 1) + (k + c)

    v = [vid(a, b, c) for a in (0, 1) for b in (0, 1) for c in (0, 1)]
    paths = [(4, 6), (4, 5), (2, 6), (2, 3), (1, 5), (1, 3)]
    tets = np.concatenate([np.stack([v[0], v[p], v[q], v[7]], axis=1) for p, q in paths])
    return x, tets.astype(np.int64)


def boundary_faces(tets):
    """Triangles that belong to exactly one tetrahedron."""
    faces = np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 2, 3]], tets[:, [0, 1, 3]],
                            tets[:, [0, 1, 2]]])  # fmt: skip
    key = np.sort(faces, axis=1)
    _, first, count = np.unique(key, axis=0, return_index=True, return_counts=True)
    return faces[first[count == 1]]


def best_of(fn, repeat):
    times = []
    out = None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return min(times), out


def report(name, seconds, target, scale=1.0, note=""):
    """Print a figure, its value scaled to the target's size, and the ratio to the target."""
    scaled = seconds * scale
    extra = f"  ({note})" if note else ""
    print(
        f"{name:<48s} {seconds:9.4f} s   scaled {scaled:8.4f} s   target {target:7.3f} s   "
        f"ratio {scaled / target:5.2f}{extra}",
        flush=True,
    )


def bench_tree():
    x, tets = box_tets((55, 55, 55))
    n = len(tets)
    print(f"tree: structured box, {n} tetrahedra, {len(x)} vertices")
    AABBTree(x[:20], tets[:5] % 20)  # JIT warm-up (cache=True makes it a load after 1st run)
    t, tree = best_of(lambda: AABBTree(x, tets), 3)
    report("tree build", t, TARGET_BUILD_1M_TETS, 1e6 / n, f"{tree.num_nodes} nodes")
    rng = np.random.default_rng(0)
    y = x + rng.normal(scale=0.05, size=x.shape)
    t, _ = best_of(lambda: tree.refit(y), 5)
    report("tree refit", t, TARGET_REFIT_1M_TETS, 1e6 / n, f"growth {tree.quality_growth:.3f}")


def bench_pairs():
    # Two slabs (104 x 104 x 8 cubes each), the upper one pushed 0.3 cells into the lower one.
    xa, ta = box_tets((104, 104, 8))
    xb, tb = box_tets((104, 104, 8), lo=(0.5, 0.5, 8.0 - 0.3))
    x = np.concatenate([xa, xb])
    tets = np.concatenate([ta, tb + len(xa)])
    tri = np.concatenate([boundary_faces(ta), boundary_faces(tb) + len(xa)])
    print(
        f"pairs: two slabs in contact, {len(tets)} tetrahedra, {len(tri)} boundary triangles, "
        f"penetration 0.3 cell"
    )
    tree = AABBTree(x, tets)

    def candidates():
        lo, hi = element_boxes(x, tri)
        q, e = tree.query_boxes(lo, hi)
        return q, e, exclude_shared_vertex_pairs(tri, tets, q, e)

    candidates()  # warm-up
    t_all, (q, e, (kt, _)) = best_of(candidates, 3)
    # the query cost grows with the number of triangles, only logarithmically with the tets
    scale = 1e5 / len(tri)
    report(
        "candidate pairs (boxes + query + filter)",
        t_all,
        TARGET_PAIRS_100K_TRI_1M_TETS,
        scale,
        f"{q.size} box overlaps, {kt.size} pairs without shared vertex",
    )
    lo, hi = element_boxes(x, tri)
    t_q, _ = best_of(lambda: tree.query_boxes(lo, hi), 3)
    t_f, _ = best_of(lambda: exclude_shared_vertex_pairs(tri, tets, q, e), 3)
    print(f"  of which: tree query {t_q:.4f} s, shared-vertex filter {t_f:.4f} s")
    # the library's search: the shared-vertex pairs left out during the traversal
    t_a, (at, _) = best_of(lambda: tree.query_boxes(lo, hi, apart=(tri, tets)), 3)
    print(
        f"  query leaving them out as found (apart=): {t_a:.4f} s, {at.size} pairs; "
        f"against query + filter {t_q + t_f:.4f} s: ratio {t_a / (t_q + t_f):.2f}"
    )


def box_surface_triangles(n):
    """Boundary triangles of the unit cube, n x n squares per face, as (m, 3, 3) coordinates."""
    g = np.linspace(0.0, 1.0, n + 1)
    u, v = (a.ravel() for a in np.meshgrid(g[:-1], g[:-1], indexing="ij"))
    h = 1.0 / n
    tris = []
    for axis in range(3):
        others = [d for d in range(3) if d != axis]
        for side in (0.0, 1.0):

            def point(a, b, axis=axis, others=others, side=side):
                p = np.empty((a.size, 3))
                p[:, axis] = side
                p[:, others[0]] = a
                p[:, others[1]] = b
                return p

            p0, p1, p2, p3 = point(u, v), point(u + h, v), point(u + h, v + h), point(u, v + h)
            tris += [np.stack([p0, p1, p2], axis=1), np.stack([p0, p2, p3], axis=1)]
    return np.concatenate(tris)


def bench_depth_core(n):
    g = np.linspace(0.0, 1.0, n + 1)
    pts = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    # shuffle: the core must not rely on the caller's vertex order
    pts = pts[np.random.default_rng(0).permutation(len(pts))]
    tri = box_surface_triangles(n)
    distance_to_triangles(pts[:10], tri[:10])
    t, d = best_of(lambda: distance_to_triangles(pts, tri), 2)
    err = np.abs(d - np.minimum(pts, 1.0 - pts).min(axis=1)).max()
    report(
        "material depth core (plain arrays)",
        t,
        TARGET_DEPTH_1M_VERTICES,
        1e6 / len(pts),
        f"{len(pts)} points, {len(tri)} triangles, max error {err:.1e}",
    )


def bench_depth_dolfinx(n):
    import dolfinx

    from fenics_matdepth import material_depth
    from fenics_matdepth.boundary import boundary_triangles, p1_dof_coordinates

    t0 = time.perf_counter()
    mesh = dolfinx.mesh.create_box(
        MPI.COMM_WORLD, [np.zeros(3), np.ones(3)], [n, n, n], dolfinx.mesh.CellType.tetrahedron
    )
    t_mesh = time.perf_counter() - t0
    nv = mesh.topology.index_map(0).size_global
    print(f"depth: dolfinx create_box {n}^3 cells, {nv} vertices (mesh built in {t_mesh:.1f} s)")
    t0 = time.perf_counter()
    d = material_depth(mesh)
    t_total = time.perf_counter() - t0
    x = d.function_space.tabulate_dof_coordinates()
    err = np.abs(d.x.array - np.minimum(x, 1.0 - x).min(axis=1)).max()
    report(
        "material_depth(mesh), first call",
        t_total,
        TARGET_DEPTH_1M_VERTICES,
        1e6 / nv,
        f"max error {err:.1e}",
    )
    # where the time goes (second pass: the face table is kept with the mesh)
    t0 = time.perf_counter()
    tri = boundary_triangles(mesh)
    t1 = time.perf_counter()
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1))
    xd = p1_dof_coordinates(V)
    t2 = time.perf_counter()
    distance_to_triangles(xd, tri)
    t3 = time.perf_counter()
    print(
        f"  second pass: boundary triangles {t1 - t0:.3f} s, P1 space + dof coordinates "
        f"{t2 - t1:.3f} s, distance core {t3 - t2:.3f} s"
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--depth-cells", type=int, default=99, help="cells per side")
    parser.add_argument("--skip-dolfinx", action="store_true", help="skip the dolfinx mesh")
    args = parser.parse_args()
    if MPI.COMM_WORLD.size > 1:
        raise SystemExit("run serially: the targets are one-core figures")
    print("fenics_matdepth spatial benchmark (ratio = scaled time / target; < 1 meets it)")
    bench_tree()
    bench_pairs()
    bench_depth_core(args.depth_cells)
    if not args.skip_dolfinx:
        bench_depth_dolfinx(args.depth_cells)


if __name__ == "__main__":
    main()
