"""The mesh split between the ranks: tets by a graph partitioner on their face adjacency
(METIS on rank 0 where pymetis is installed, else PETSc's), vertices to the lowest rank among
their tets, free DOFs numbered rank by rank over each rank's local free vector
(:func:`local_layout`).

METIS first because it is deterministic (its seed is fixed): the same mesh on as many ranks
is cut the same way in every run, so the same run twice sums in the same order and gives the
same bits. PT-Scotch, the partitioner Debian's PETSc has, cut a 1e5-tet box differently in
every run, also with its generator seeded (docs/parallel.md).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fem3d.parallel.ghosts import Ghosts
from fem3d.solve.linear.petsc import DofLayout, petsc_module

__all__ = ["PARTITIONERS", "dual_graph", "partition_tets", "local_layout"]

#: PETSc's graph partitioners in order of preference (the first one PETSc was built with).
PARTITIONERS = ("parmetis", "ptscotch", "chaco", "party")

#: The four faces of a tet (vertex positions in ``T``'s rows).
_FACES = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])


def dual_graph(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The tets' face adjacency as CSR arrays: ``indices[indptr[e]:indptr[e + 1]]`` are the
    tets sharing a face with tet ``e`` (sorted).

    Parameters
    ----------
    T : (m, n_nodes) int64

    Returns
    -------
    indptr : (m + 1,) int64
    indices : (2 * interior faces,) int64
    """
    m = T.shape[0]
    faces = np.sort(T[:, _FACES].reshape(-1, 3), axis=1)
    owner = np.repeat(np.arange(m, dtype=np.int64), 4)
    order = np.lexsort((faces[:, 2], faces[:, 1], faces[:, 0]))
    faces, owner = faces[order], owner[order]
    same = (faces[1:] == faces[:-1]).all(axis=1)  # a face shared by the tets i and i + 1
    a, b = owner[:-1][same], owner[1:][same]
    rows = np.concatenate([a, b])
    cols = np.concatenate([b, a])
    order = np.lexsort((cols, rows))
    rows, cols = rows[order], cols[order]
    indptr = np.zeros(m + 1, dtype=np.int64)
    np.cumsum(np.bincount(rows, minlength=m), out=indptr[1:])
    return indptr, cols


def _partitioner(PETSc: Any) -> str:
    for name in PARTITIONERS:
        if PETSc.Sys.hasExternalPackage(name):
            return name
    raise ImportError(f"PETSc has no graph partitioner ({', '.join(PARTITIONERS)}): "
                      "install a PETSc built with PT-Scotch or ParMETIS "
                      "(scripts/install_petsc.sh)")


def partition_tets(T: np.ndarray, n_parts: int) -> np.ndarray:
    """The part (rank) of each tet, cut on the one process that holds the mesh (rank 0):
    METIS (pymetis) on the tets' face adjacency; without pymetis, PETSc's graph partitioner
    (:data:`PARTITIONERS`) in this process (not the same from run to run with PT-Scotch: the
    module's docstring).

    Parameters
    ----------
    T : (m, n_nodes) int64
        The whole mesh.
    n_parts : int

    Returns
    -------
    (m,) int64
    """
    m = T.shape[0]
    if n_parts == 1:
        return np.zeros(m, dtype=np.int64)
    indptr, indices = dual_graph(T)
    try:
        import pymetis  # optional (fem3d[mpi]): the deterministic partition
    except ImportError:
        return _petsc_partition(indptr, indices, n_parts)
    cut = pymetis.part_graph(n_parts, adjacency=pymetis.CSRAdjacency(indptr, indices))
    return np.asarray(cut.vertex_part, dtype=np.int64)


def _petsc_partition(indptr: np.ndarray, indices: np.ndarray, n_parts: int) -> np.ndarray:
    """:func:`partition_tets` of the dual graph ``indptr, indices`` by PETSc's graph
    partitioner (:data:`PARTITIONERS`) in this process."""
    PETSc = petsc_module()
    m = indptr.size - 1
    # the graph as an AIJ matrix of ones (the partitioner converts it to MPIAdj)
    adj = PETSc.Mat().createAIJ((m, m), csr=(indptr.astype(PETSc.IntType),
                                             indices.astype(PETSc.IntType),
                                             np.ones(indices.size)), comm=PETSc.COMM_SELF)
    adj.assemble()
    part = PETSc.MatPartitioning().create(comm=PETSc.COMM_SELF)
    prefix = f"fem3d_cut_{id(part)}_"
    part.setOptionsPrefix(prefix)
    opts = PETSc.Options(prefix)
    opts["mat_partitioning_nparts"] = n_parts
    part.setAdjacency(adj)
    part.setType(_partitioner(PETSc))
    part.setFromOptions()
    del opts["mat_partitioning_nparts"]  # the prefix is this call's: nothing left behind
    parts = PETSc.IS()
    part.apply(parts)
    out = parts.getIndices().astype(np.int64)
    for obj in (parts, part, adj):
        obj.destroy()
    return out


def local_layout(comm: Any, free_ids: np.ndarray) -> tuple[DofLayout, Ghosts]:
    """Collective: PETSc's numbering of the ranks' local free DOFs, from local information
    alone. Each free DOF is owned by the lowest rank holding it (:attr:`Ghosts.owner`); each
    rank numbers its owned free DOFs consecutively in increasing global id, after the lower
    ranks' (rank ``r``'s first row is the sum of the lower ranks' counts).

    Parameters
    ----------
    comm : mpi4py.MPI.Comm
    free_ids : (k,) int64
        The sorted global DOF ids (``3 * v + c``) of this rank's local free DOFs (those of
        its own tets' free vertices).

    Returns
    -------
    layout : DofLayout
        Over the local free vector (length ``k``): ``order`` (a ghost's row is its owner's),
        ``owned``, ``start``, ``counts``, ``n`` and ``ghosts``.
    ghosts : Ghosts
        Of ``free_ids``.
    """
    ghosts = Ghosts.build(comm, free_ids)
    size, rank = comm.Get_size(), comm.Get_rank()
    owned = np.flatnonzero(ghosts.owned).astype(np.int64)  # increasing global id
    counts = (np.array([owned.size], dtype=np.int64) if size == 1 else
              np.asarray(comm.allgather(int(owned.size)), dtype=np.int64))
    start = int(counts[:rank].sum())
    rows = np.full(ghosts.ids.size, -1, dtype=np.int64)
    rows[owned] = start + np.arange(owned.size, dtype=np.int64)
    order = ghosts.complete(rows)
    for a in (order, owned, counts):
        a.setflags(write=False)
    layout = DofLayout(comm=comm, order=order, owned=owned, start=start, counts=counts,
                       n=int(counts.sum()), ghosts=ghosts)
    return layout, ghosts
