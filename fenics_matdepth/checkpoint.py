"""Checkpoints of vertex-based (P1) fields, for resuming long runs.

:class:`Checkpoint` saves named arrays of a P1 (Lagrange degree 1, scalar or vector) function
space together with a few scalars, and reads them back on any number of processes:
:func:`fenics_matdepth.solve_load_steps` uses it (``checkpoint=``, ``resume=``), and a time
stepper can use it the same way (save displacement and velocity with the time).

File format (one NumPy ``.npz`` file, written by rank 0, replaced atomically so that a run
killed while writing leaves the previous checkpoint intact):

* ``format``: the string ``"fenics_matdepth.checkpoint/1"``;
* ``vertex``: (n,) int64, the *original input* index of each vertex (the row of the vertex in
  the coordinates given to ``create_mesh`` or read from the mesh file), sorted;
* ``coordinates``: (n, 3) float64 reference coordinates of those vertices (a resumed run
  checks that it has the same mesh);
* ``field/<name>``: (n, bs) float64 values of each array, one row per vertex;
* ``meta``: a JSON string with the scalars.

Values are stored bit for bit, and keyed by input vertex index rather than by the
partition-dependent dof numbering: a checkpoint written on one partition resumes exactly on
any other.
"""

from __future__ import annotations

import json
import os
import typing
from pathlib import Path

from mpi4py import MPI

import dolfinx
import numpy as np

from fenics_matdepth._compat import geometry_dofmap
from fenics_matdepth._mpi import collective_error

__all__ = ["Checkpoint"]

FORMAT = "fenics_matdepth.checkpoint/1"


def _vertex_keys(V: dolfinx.fem.FunctionSpace) -> tuple[np.ndarray, np.ndarray]:
    """Original input vertex index and reference coordinates of every local dof block."""
    from fenics_matdepth.boundary import p1_dof_coordinates

    mesh = V.mesh
    imap = V.dofmap.index_map
    n_local = imap.size_local + imap.num_ghosts
    dofs = np.asarray(V.dofmap.list).reshape(-1)
    nodes = np.asarray(geometry_dofmap(mesh)).reshape(-1)
    node_of_dof = np.full(n_local, -1, dtype=np.int64)
    node_of_dof[dofs] = nodes
    keys = np.asarray(mesh.geometry.input_global_indices, dtype=np.int64)[node_of_dof]
    return keys, p1_dof_coordinates(V)


class Checkpoint:
    """Save and restore arrays of one P1 function space with scalars (collective).

    Args:
        path: the checkpoint file (``.npz`` is appended if missing).
        V: a P1 space (scalar or vector) on an affine mesh; the arrays saved are local arrays of
            Functions on ``V`` (``u.x.array``, owned and ghost values).
    """

    def __init__(self, path: str | os.PathLike, V: dolfinx.fem.FunctionSpace):
        element = V.ufl_element()
        if element.degree != 1 or np.asarray(geometry_dofmap(V.mesh)).shape[1] != 4:
            raise ValueError(
                "Checkpoint stores P1 fields on affine tetrahedral meshes: pass a "
                'functionspace(mesh, ("Lagrange", 1, ...))'
            )
        path = Path(path)
        self.path = path if path.suffix == ".npz" else path.with_name(path.name + ".npz")
        self.V = V
        self.comm: MPI.Comm = V.mesh.comm
        self._bs = V.dofmap.index_map_bs
        self._n_owned = V.dofmap.index_map.size_local
        self._keys, self._X = _vertex_keys(V)

    def exists(self) -> bool:
        """Whether the checkpoint file exists (collective: rank 0 looks)."""
        return bool(self.comm.bcast(self.path.exists() if self.comm.rank == 0 else None))

    def save(self, arrays: dict[str, np.ndarray], **meta: typing.Any) -> None:
        """Write ``arrays`` (local arrays on ``V``) and the JSON-serialisable scalars ``meta``,
        replacing the previous checkpoint (collective).

        Raises:
            RuntimeError: on every rank, if the file cannot be written (the message says why).
        """
        owned = slice(0, self._n_owned)
        keys = self.comm.gather(self._keys[owned], root=0)
        coords = self.comm.gather(self._X[owned], root=0)
        gathered = {
            name: self.comm.gather(
                np.asarray(a).reshape(-1, self._bs)[owned].astype(np.float64), root=0
            )
            for name, a in arrays.items()
        }
        message = None
        if self.comm.rank == 0:
            keys = np.concatenate(keys)
            order = np.argsort(keys)
            content = {
                "format": np.array(FORMAT),
                "vertex": keys[order],
                "coordinates": np.concatenate(coords)[order],
                "meta": np.array(json.dumps(meta)),
            }
            for name, parts in gathered.items():
                content[f"field/{name}"] = np.concatenate(parts)[order]
            partial = self.path.with_name(self.path.name + ".partial.npz")
            try:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                np.savez(partial, **content)
                os.replace(partial, self.path)
            except OSError as err:
                message = (
                    f"cannot write the checkpoint {self.path}: {err}. Choose a writable path "
                    "(checkpoint=...) with free space"
                )
        collective_error(self.comm, self.comm.bcast(message, root=0), RuntimeError)

    def load(self) -> tuple[dict[str, np.ndarray], dict[str, typing.Any]]:
        """Read the checkpoint: (local arrays on ``V``, owned and ghost values; meta scalars).

        Raises:
            RuntimeError: on every rank, if the file is missing, not a checkpoint, or written
                for another mesh.
        """
        message, data = None, None
        try:
            with np.load(self.path, allow_pickle=False) as f:
                data = {key: f[key] for key in f.files}
            if str(data.get("format")) != FORMAT:
                message = f"{self.path} is not a fenics_matdepth checkpoint"
        except (OSError, ValueError) as err:
            message = f"cannot read the checkpoint {self.path}: {err}"
        collective_error(self.comm, message, RuntimeError)
        vertex = data["vertex"]
        pos = np.searchsorted(vertex, self._keys)
        pos = np.minimum(pos, max(vertex.size - 1, 0))
        found = vertex.size > 0 and np.array_equal(vertex[pos], self._keys)
        scale = float(np.abs(self._X).max()) if self._X.size else 1.0
        same = found and np.allclose(
            data["coordinates"][pos], self._X, rtol=0.0, atol=1e-12 * scale
        )
        if not same:
            message = (
                f"the checkpoint {self.path} was written for another mesh (its vertices or their "
                "coordinates differ): resume with the mesh of the run that wrote it"
            )
        collective_error(self.comm, message, RuntimeError)
        arrays = {
            key[len("field/") :]: np.ascontiguousarray(value[pos]).reshape(-1)
            for key, value in data.items()
            if key.startswith("field/")
        }
        return arrays, json.loads(str(data["meta"]))
