"""What each rank holds and sends with the distributed contact operator, on any number of ranks.

The model of ``bench_newton.py`` (a 1.5 x 1.5 x 0.5 block, a 1 x 1 x 0.5 block resting on it,
about 40k tetrahedra), partitioned by dolfinx, with the upper block pressed 0.01 into the
lower one. Prints, per rank: held vertices and tetrahedra (owned plus halo) against the global
counts, halo tetrahedra, neighbours and displacement bytes sent per update; then the seconds of
an update (a small change of u: neighbour exchange, refit, pair search) and of an update that
rebuilds the halo (a rigid motion of one boundary edge). Prints figures; asserts nothing.

Run: ``scripts/fenicsx mpirun -n 4 --oversubscribe python3 benchmarks/bench_halo.py``.
"""

from __future__ import annotations

import time

from mpi4py import MPI

import dolfinx
import numpy as np
from bench_newton import build

import fenics_matdepth as fm
from fenics_matdepth.boundary import p1_dof_coordinates

REPEATS = 5


def _timed(comm, fn) -> float:
    comm.Barrier()
    tic = time.perf_counter()
    fn()
    return comm.allreduce(time.perf_counter() - tic, op=MPI.MAX)


def main():
    comm = MPI.COMM_WORLD
    mesh, num_tets = build(comm, (24, 24, 8), (16, 16, 8))
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    X = p1_dof_coordinates(V)
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=200.0)
    n_local = X.shape[0]
    glob = V.dofmap.index_map.local_to_global(np.arange(n_local, dtype=np.int32))
    body = contact.body_of_vertex[glob]
    upper = body == contact.body_of_vertex[np.argmax(contact.surface.gathered()["X"][:, 2])]
    press = np.zeros_like(X)
    press[upper, 2] = -0.01  # the upper block moved 0.01 into the lower one
    u.x.array[:] = press.ravel()
    contact.update()
    d = contact.diagnostics()
    keys = ("held_vertices", "held_tets", "halo_tets", "neighbours", "update_bytes_sent")
    rows = comm.gather([d[k] for k in keys], root=0)

    def small_step(k):
        u.x.array[:] = (press * (1.0 + 1e-3 * (k + 1))).ravel()
        contact.update()

    update = np.mean([_timed(comm, lambda k=k: small_step(k)) for k in range(REPEATS)])
    refreshes = contact.diagnostics()["halo_refreshes"]
    shift = np.zeros_like(X)
    shift[:, 0] = contact.surface.mean_edge  # moves every vertex one boundary edge
    rebuild = []
    for k in range(REPEATS):
        u.x.array[:] = (press + (k + 1) * shift).ravel()
        rebuild.append(_timed(comm, contact.update))
    rebuilt = contact.diagnostics()["halo_refreshes"] - refreshes
    if comm.rank != 0:
        return
    n_vertices = V.dofmap.index_map.size_global
    print(f"{num_tets} tets, {n_vertices} vertices, {comm.size} rank(s); active pairs "
          f"{d['active_pairs']}")  # fmt: skip
    for rank, row in enumerate(rows):
        sizes = dict(zip(keys, row, strict=True))
        print(
            f"  rank {rank}: held {sizes['held_vertices']} vertices "
            f"({sizes['held_vertices'] / n_vertices:.1%}), {sizes['held_tets']} tets "
            f"({sizes['held_tets'] / num_tets:.1%}), halo {sizes['halo_tets']} tets, "
            f"{sizes['neighbours']} neighbours, {sizes['update_bytes_sent']} bytes sent per update"
        )
    print(f"update (no halo rebuild): {update * 1e3:.1f} ms; update with halo rebuild: "
          f"{np.mean(rebuild) * 1e3:.1f} ms ({rebuilt} rebuilds in {REPEATS} updates)")  # fmt: skip


if __name__ == "__main__":
    main()
