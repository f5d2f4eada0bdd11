"""Run by tests/parallel/test_ghosts.py under ``mpiexec -n 3``: on a 4 x 4 x 4-cube box
(384 tets) cut by METIS, each rank builds :class:`~fem3d.parallel.ghosts.Ghosts` on its own
tets' vertices and DOFs and checks them against the whole mesh (which every rank has);
rank 0 writes the figures to the JSON file named by ``sys.argv[1]``.

Figures: ``assemble`` against one process's ``np.add.at`` (relative error, bits equal on
every holder, an entry held alone unchanged), ``complete`` (each ghost its owner's value),
``local_layout`` (the owned rows over all ranks are ``0..n-1`` once) and a PETSc solve of an
SPD system with local vectors (MUMPS, and CG + GAMG) against scipy's ``spsolve``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # bench, as run from any folder

import numpy as np  # noqa: E402
import scipy.sparse as sp  # noqa: E402
import scipy.sparse.linalg as spla  # noqa: E402
from mpi4py import MPI  # noqa: E402

from bench.meshes import box_mesh  # noqa: E402
from fem3d.parallel.ghosts import Ghosts  # noqa: E402
from fem3d.parallel.partition import local_layout, partition_tets  # noqa: E402
from fem3d.solve.linear.base import SolverOptions  # noqa: E402
from fem3d.solve.linear.petsc import PetscSolver  # noqa: E402

#: the PETSc options of the two solves: the default (MUMPS' Cholesky), and CG + GAMG (the
#: rigid-body modes of the local free vertices)
SOLVES = {"mumps": "", "gamg": "-ksp_type cg -pc_type gamg -ksp_rtol 1e-12"}


def _same_bits_on_holders(comm, ids: np.ndarray, values: np.ndarray) -> bool:
    """Whether every rank holding an id has the same bits for it (gathered on rank 0; the
    answer on every rank)."""
    got = comm.gather((ids, np.ascontiguousarray(values).view(np.uint64).reshape(ids.size, -1)))
    same = True
    if comm.Get_rank() == 0:
        seen: dict[int, bytes] = {}
        for rank_ids, bits in got:
            for i, row in zip(rank_ids.tolist(), bits, strict=True):
                same &= seen.setdefault(i, row.tobytes()) == row.tobytes()
    return bool(comm.bcast(same))


def _summed_in_rank_order(comm, ids: np.ndarray, partial: np.ndarray, total: np.ndarray
                          ) -> bool:
    """Whether every rank's ``total`` has the bits of its holders' ``partial`` rows added left
    to right in increasing rank order (gathered on rank 0; the answer on every rank)."""
    got = comm.gather((ids, partial, total))
    same = True
    if comm.Get_rank() == 0:
        sums: dict[int, np.ndarray] = {}
        for rank_ids, rank_partial, _ in got:  # the ranks in increasing order
            for i, row in zip(rank_ids.tolist(), rank_partial, strict=True):
                sums[i] = sums[i] + row if i in sums else row.copy()
        for rank_ids, _, rank_total in got:
            for i, row in zip(rank_ids.tolist(), rank_total, strict=True):
                same &= sums[i].tobytes() == row.tobytes()
    return bool(comm.bcast(same))


def _relative_error(got: np.ndarray, expected: np.ndarray) -> float:
    return float(np.max(np.abs(got - expected) / np.abs(expected), initial=0.0))


def _element_matrices(m: int, rng: np.random.Generator) -> np.ndarray:
    """(m, 12, 12) SPD-summing blocks: a weighted Laplacian of the tet's 4 vertices plus
    0.1 I, in 3 x 3 blocks (DOFs vertex by vertex)."""
    w = rng.uniform(0.5, 2.0, m)
    lap = 4.0 * np.eye(4) - np.ones((4, 4))
    k4 = w[:, None, None] * lap + 0.1 * np.eye(4)
    return np.einsum("eab,cd->eacbd", k4, np.eye(3)).reshape(m, 12, 12)


def _coo(T: np.ndarray, blocks: np.ndarray, index: np.ndarray, n: int) -> sp.csr_matrix:
    """The blocks of the tets ``T`` summed into an (n, n) matrix, DOF ``3 v + c`` at
    ``index[3 v + c]`` (``-1``: a pinned DOF, dropped)."""
    dofs = index[(3 * T[:, :, None] + np.arange(3)).reshape(len(T), 12)]
    rows = np.broadcast_to(dofs[:, :, None], blocks.shape).ravel()
    cols = np.broadcast_to(dofs[:, None, :], blocks.shape).ravel()
    keep = (rows >= 0) & (cols >= 0)
    A = sp.coo_matrix((blocks.ravel()[keep], (rows[keep], cols[keep])), shape=(n, n)).tocsr()
    A.sum_duplicates()
    return A


def main(out: Path) -> None:
    comm = MPI.COMM_WORLD
    rank, size = comm.Get_rank(), comm.Get_size()
    X, T = box_mesh(384)
    nv, m = len(X), len(T)
    tet_rank = partition_tets(T, comm.Get_size())  # METIS: the same cut on every rank
    mine = tet_rank == rank
    verts = np.unique(T[mine])
    dofs = (3 * verts[:, None] + np.arange(3)).ravel()
    report: dict[str, object] = {"ranks": size, "tets": m,
                                 "tets_per_rank": np.bincount(tet_rank, minlength=size).tolist()}

    # the lowest rank among each vertex's tets, and how many ranks hold it
    owner = np.full(nv, size, dtype=np.int64)
    np.minimum.at(owner, T, tet_rank[:, None])
    holds = np.zeros((nv, size), dtype=bool)
    holds[T, tet_rank[:, None]] = True
    holders = holds.sum(axis=1)

    # assemble: element "gradients" (positive: a relative error per entry means something)
    rng = np.random.default_rng(7)
    grads = rng.uniform(0.5, 1.5, (m, 4, 3))
    whole = np.zeros((nv, 3))
    np.add.at(whole, T, grads)
    part = np.zeros((verts.size, 3))
    np.add.at(part, np.searchsorted(verts, T[mine]), grads[mine])
    g_vertex = Ghosts.build(comm, verts.astype(np.int32))  # any integer dtype
    g_dof = Ghosts.build(comm, dofs)
    rows = g_vertex.assemble(part)
    flat = g_dof.assemble(part.reshape(-1))
    alone = holders[verts] == 1
    report |= {
        "owner_ok": bool(comm.allreduce(
            np.array_equal(g_vertex.owner, owner[verts])
            and np.array_equal(g_dof.owner, np.repeat(owner[verts], 3))
            and np.array_equal(g_vertex.owned, owner[verts] == rank), op=MPI.LAND)),
        "shared_entries": int(comm.allreduce(int((~alone).sum()))),
        "assemble_error_rows": comm.allreduce(_relative_error(rows, whole[verts]), op=MPI.MAX),
        "assemble_error_flat": comm.allreduce(
            _relative_error(flat, whole[verts].reshape(-1)), op=MPI.MAX),
        "rows_equal_flat_bits": bool(comm.allreduce(
            rows.reshape(-1).tobytes() == flat.tobytes(), op=MPI.LAND)),
        "alone_unchanged": bool(comm.allreduce(
            rows[alone].tobytes() == part[alone].tobytes(), op=MPI.LAND)),
        "rank_order_bits": _summed_in_rank_order(comm, verts, part, rows),
        "holders_same_bits": _same_bits_on_holders(comm, verts, rows)
        and _same_bits_on_holders(comm, dofs, flat),
        "assemble_is_copy": bool(comm.allreduce(
            not np.shares_memory(rows, part), op=MPI.LAND)),
    }

    # complete: every rank's own values; each ghost gets its owner's
    values = np.stack([verts * 10.0 + rank, -verts - 0.5 * rank, np.full(verts.size, rank)],
                      axis=1)
    done = g_vertex.complete(values)
    expected = np.stack([verts * 10.0 + owner[verts], -verts - 0.5 * owner[verts],
                         owner[verts].astype(float)], axis=1)
    done_dof = g_dof.complete(dofs * 4 + rank)  # an integer vector
    report |= {
        "complete_ok": bool(comm.allreduce(
            np.array_equal(done, expected)
            and np.array_equal(done_dof, dofs * 4 + np.repeat(owner[verts], 3)), op=MPI.LAND)),
    }

    # local_layout over the free DOFs (the vertices at x = 0 pinned)
    free_vertex = X[:, 0] > 1e-9
    local_free = verts[free_vertex[verts]]
    free_ids = (3 * local_free[:, None] + np.arange(3)).ravel()
    layout, ghosts = local_layout(comm, free_ids)
    all_free = (3 * np.flatnonzero(free_vertex)[:, None] + np.arange(3)).ravel()
    rows_owned = comm.allgather(layout.order[layout.owned])
    report |= {
        "n": layout.n, "n_expected": int(all_free.size), "counts": layout.counts.tolist(),
        "owned_rows_once": bool(np.array_equal(np.sort(np.concatenate(rows_owned)),
                                               np.arange(all_free.size))),
        "start_ok": bool(comm.allreduce(
            layout.start == int(layout.counts[:rank].sum())
            and np.array_equal(layout.order[layout.owned],
                               layout.start + np.arange(layout.owned.size)), op=MPI.LAND)),
        "order_same_on_holders": _same_bits_on_holders(comm, free_ids, layout.order),
        "layout_ghosts": layout.ghosts is ghosts,
    }

    # an SPD system: each rank's own tets into its local free pattern; scipy on the whole
    blocks = _element_matrices(m, np.random.default_rng(11))
    whole_index = np.full(3 * nv, -1, dtype=np.int64)
    whole_index[all_free] = np.arange(all_free.size)
    A = _coo(T, blocks, whole_index, all_free.size)
    b = np.random.default_rng(13).standard_normal(all_free.size)
    x_ref = spla.spsolve(A.tocsc(), b)
    local_index = np.full(3 * nv, -1, dtype=np.int64)
    local_index[free_ids] = np.arange(free_ids.size)
    A_local = _coo(T[mine], blocks[mine], local_index, free_ids.size)
    at = np.searchsorted(all_free, free_ids)  # the local entries in the whole free vector
    b_local = b[at]
    b_local[~ghosts.owned] = np.nan  # a ghost's right-hand side is not read
    for name, options in SOLVES.items():
        solver = PetscSolver(SolverOptions(points=X[local_free], petsc_options=options),
                             layout=layout)
        solver.analyse(A_local, symmetric=True)
        solver.factorize(A_local)
        x = solver.solve(b_local)
        err = np.linalg.norm(x - x_ref[at]) / np.linalg.norm(x_ref[at])
        report[f"solve_error_{name}"] = comm.allreduce(float(err), op=MPI.MAX)
        report[f"solve_ghosts_same_bits_{name}"] = _same_bits_on_holders(comm, free_ids, x)
        report[f"solve_pc_{name}"] = solver._ksp.getPC().getType()
    if rank == 0:
        out.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main(Path(sys.argv[1]))
