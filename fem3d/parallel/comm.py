"""The MPI side of a distributed run: is this process one of several ranks, and sums that
every rank agrees on bit for bit (so every rank's Newton takes the same decisions)."""

from __future__ import annotations

import os
import sys
from typing import Any

import numpy as np

__all__ = ["RANK_VARIABLES", "launched_rank", "launched_ranks", "leave_together", "world",
           "sum_scalar", "sum_array", "mpi_started", "abort"]

#: Environment variables the common MPI launchers set to the number of ranks (Open MPI,
#: MPICH/Hydra, PMI and PMIx: srun's too; not ``SLURM_NTASKS``, which a batch script that runs
#: fem3d without a launcher also sees).
RANK_VARIABLES = ("OMPI_COMM_WORLD_SIZE", "PMI_SIZE", "PMIX_SIZE", "MPI_LOCALNRANKS")


def launched_ranks() -> int:
    """How many ranks the MPI launcher started this process among (1 without ``mpiexec``),
    read from the launcher's environment without importing MPI."""
    for name in RANK_VARIABLES:
        value = os.environ.get(name, "")
        if value.isdigit() and int(value) > 0:
            return int(value)
    return 1

#: The launchers' variables of this process's rank, in :data:`RANK_VARIABLES`' order.
_RANK_OF = ("OMPI_COMM_WORLD_RANK", "PMI_RANK", "PMIX_RANK", "MPI_LOCALRANKID")


def launched_rank() -> int:
    """This process's rank among :func:`launched_ranks` (0 without ``mpiexec``)."""
    for name in _RANK_OF:
        value = os.environ.get(name, "")
        if value.isdigit():
            return int(value)
    return 0


def world() -> Any:
    """``mpi4py.MPI.COMM_WORLD`` (PETSc initialised first, on the same communicator)."""
    from fem3d.solve.linear.petsc import petsc_module

    petsc_module()
    from mpi4py import MPI  # optional (fem3d[mpi]): imported for mpiexec runs

    return MPI.COMM_WORLD


def leave_together(timeout: float = 30.0) -> None:
    """Under ``mpiexec``, wait (at most ``timeout`` seconds) until every rank has come here.

    A failed run exits non-zero on every rank, and Open MPI's ``mpiexec`` kills the ranks
    still running as soon as one exits non-zero: a rank that is quick to fail would take rank
    0's one-line message with it before rank 0 had printed it. A non-blocking barrier with a
    deadline, so a rank that never arrives (a failure of one rank alone) delays the exit and
    cannot hang it. Nothing happens in one process or without mpi4py.
    """
    import sys
    import time

    if launched_ranks() < 2:
        return
    sys.stdout.flush()
    sys.stderr.flush()
    try:
        request = world().Ibarrier()
    except Exception:  # noqa: BLE001 - no MPI to wait with: leave at once
        return
    deadline = time.monotonic() + timeout
    while not request.Test() and time.monotonic() < deadline:
        time.sleep(0.005)


def sum_scalar(comm: Any, value: float) -> float:
    """``sum`` of one float over the ranks, added in rank order: the same bits on every rank
    (an ``MPI_Allreduce`` may associate differently per rank)."""
    return _in_rank_order(comm.allgather(float(value)), 0.0)


def sum_array(comm: Any, value: np.ndarray) -> np.ndarray:
    """:func:`sum_scalar` of a small array, entry by entry (every rank's whole array sent to
    every rank: for a few numbers per rank, not for vectors over the mesh)."""
    parts = comm.allgather(np.asarray(value, dtype=np.float64))
    return _in_rank_order(parts, np.zeros_like(parts[0]))


def _in_rank_order(parts: list, total: Any) -> Any:
    """``total + parts[0] + parts[1] + ...``, left to right."""
    for part in parts:
        total += part
    return total


def mpi_started() -> bool:
    """Whether this process has started MPI (and not finished it): from then on a rank that
    stops alone leaves the others waiting in their next collective call."""
    mpi = sys.modules.get("mpi4py.MPI")
    return mpi is not None and mpi.Is_initialized() and not mpi.Is_finalized()


def abort(code: int) -> None:
    """Stop every rank with exit status ``code`` (``MPI_Abort``; Open MPI's ``mpiexec``
    exits with it) when :func:`mpi_started`; nothing otherwise. For an error one rank may
    meet alone (a file it cannot write, a bug)."""
    if mpi_started():
        sys.stderr.flush()
        sys.modules["mpi4py.MPI"].COMM_WORLD.Abort(code)
