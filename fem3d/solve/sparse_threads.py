"""Threaded sparse kernels of the AMG-preconditioned CG, the same bits on any thread count.

The C extension (``fem3d._ckernels``, rendered from ``templates/c/amg.c.jinja``) provides
BSR mat-vecs, block Gauss-Seidel sweeps, a CSR mat-vec, a dot product and BSR x BSR products
(:func:`bsr_product`: the Galerkin products of a setup), all on OpenMP threads. Every row's sum
runs in storage order whichever thread computes it, and a dot product adds fixed chunks in
order, so the results do not depend on the number of threads.

How many threads: every kernel takes ``n_threads`` (0: OpenMP's count, ``OMP_NUM_THREADS``;
else that many, capped at OpenMP's). An AMG setup asks :mod:`fem3d.kernels.threads` for one
count per family, measured on its own data the first time in a process
(:func:`product_threads`: a sample of a product; the solve's kernels together, on a few PCG
rounds: :meth:`fem3d.solve.linear.amg.AMGPreconditioner.setup`), or forced by ``FEM3D_THREADS``.

A Gauss-Seidel sweep cannot run its rows in parallel as they are: row ``i`` reads the rows
updated before it. :func:`sweep_schedule` cuts the rows into blocks of consecutive rows and
colours the blocks so that no two blocks of one colour couple; a sweep then runs the colours
one after the other and the blocks of a colour in parallel. It is the exact Gauss-Seidel
sweep of the rows taken in that order (colour by colour, block by block), on the triangles of
that order (:func:`split_triangles`: ``L`` the blocks whose columns come earlier, ``rank[j] <
rank[i]``, ``U`` the later ones). Blocks, colours and order depend on the sparsity pattern
alone (not the thread count).

:func:`reference_sweep` is the NumPy statement of a sweep (slow: for checks); SciPy's ``@``
that of the mat-vecs.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import ModuleType

import numpy as np
import scipy.sparse as sp

from fem3d.kernels.backend import c_extension
from fem3d.kernels.threads import measure

__all__ = ["PRODUCT_SAMPLE_ROWS", "SweepSchedule", "bsr_product", "c_kernels",
           "product_threads", "reference_sweep", "split_triangles",
           "sweep_schedule"]

#: A schedule cuts the rows into ``MAX_BLOCKS``, ``MAX_BLOCKS / 2``, ... (at least 2) blocks of
#: at least ``MIN_BLOCK_ROWS`` rows each and keeps the cut whose colouring needs the fewest
#: colours (the most blocks among those), as long as every colour has two blocks on average:
#: fewer colours, fewer barriers, and an order closer to the row order (on the 1e5-tet box: 16
#: blocks in 2 colours, the CG iterations of pyamg's row-order sweeps). Else one block.
MIN_BLOCK_ROWS = 256
MAX_BLOCKS = 64
#: The Galerkin products' thread count is measured on the product of this many block rows of
#: the finest matrix (the whole matrix when smaller) with the matrix itself: as dense a product
#: per row as the setup's ``A P`` and ``R (A P)`` (``A T`` is far lighter); 2048 rows: the
#: fewest the C products split over threads (FEM3D_AMG_PARALLEL_ROWS).
PRODUCT_SAMPLE_ROWS = 2048


def c_kernels() -> ModuleType | None:
    """The C extension when it has the AMG kernels, else None (NumPy/SciPy fallback)."""
    ext = c_extension()
    return ext if ext is not None and hasattr(ext, "block_sweep") else None


@dataclass(frozen=True, eq=False)
class SweepSchedule:
    """The order of a threaded Gauss-Seidel sweep over the block rows of a square matrix.

    Attributes
    ----------
    rank : (nb,) int32 or None
        Position of every block row in the sweep (None: the row order itself).
    order : (nb,) int32 or None
        The rows in sweep order (``order[rank[i]] == i``; None: ``0 .. nb-1``).
    blocks : (n_blocks + 1,) int64
        Offsets into ``order``: block ``s`` is ``order[blocks[s]:blocks[s + 1]]``.
    colours : (n_colours + 1,) int64
        Offsets into the blocks: colour ``c`` is blocks ``colours[c] .. colours[c + 1] - 1``,
        no two of which couple.
    """

    rank: np.ndarray | None
    order: np.ndarray | None
    blocks: np.ndarray
    colours: np.ndarray

    @property
    def n_colours(self) -> int:
        """Number of colours (one after the other in a sweep)."""
        return int(self.colours.size - 1)

    @property
    def n_blocks(self) -> int:
        """Number of blocks."""
        return int(self.blocks.size - 1)

    def sequence(self) -> np.ndarray:
        """``(nb,) int64``: the rows in sweep order."""
        n = int(self.blocks[-1])
        return np.arange(n) if self.order is None else self.order.astype(np.int64)


def _block_adjacency(indptr: np.ndarray, indices: np.ndarray, n_blocks: int) -> np.ndarray:
    """``(n_blocks, n_blocks) bool``: which blocks of rows ``(s n) // n_blocks ...`` couple."""
    n = indptr.size - 1
    starts = (np.arange(n_blocks + 1, dtype=np.int64) * n) // n_blocks
    block_of = np.repeat(np.arange(n_blocks), np.diff(starts))
    rows = np.repeat(block_of, np.diff(indptr))
    adjacency = np.zeros((n_blocks, n_blocks), dtype=bool)
    adjacency[rows, block_of[indices]] = True
    return adjacency


def _greedy_colours(adjacency: np.ndarray) -> np.ndarray:
    """Colour of every block (greedy, in block order) so that no two coupled blocks share
    one."""
    n_blocks = adjacency.shape[0]
    colour = np.full(n_blocks, -1, dtype=np.int64)
    for s in range(n_blocks):
        taken = set(colour[adjacency[s] & (np.arange(n_blocks) != s)].tolist())
        c = 0
        while c in taken:
            c += 1
        colour[s] = c
    return colour


def sweep_schedule(indptr: np.ndarray, indices: np.ndarray, *,
                   min_block_rows: int = MIN_BLOCK_ROWS) -> SweepSchedule:
    """The threaded sweep order of a square block pattern (structurally symmetric).

    Parameters
    ----------
    indptr, indices : int arrays
        The BSR (block) pattern: ``nb + 1`` row offsets and the column of every block.
    min_block_rows : int, optional
        Rows per block at least; a pattern of fewer than twice as many rows gets one block
        (the row order, serially).

    Returns
    -------
    SweepSchedule
        Blocks of consecutive rows, taken colour by colour (blocks in row order within a
        colour): the cut of :data:`MAX_BLOCKS`, half as many, ... blocks whose colouring
        needs the fewest colours (at most half the blocks), else one block.
    """
    n = int(indptr.size - 1)
    indptr = np.asarray(indptr, dtype=np.int64)
    indices = np.asarray(indices, dtype=np.int64)
    n_blocks = 1
    while 2 * n_blocks <= min(MAX_BLOCKS, n // max(min_block_rows, 1)):
        n_blocks *= 2
    best: tuple[int, int, np.ndarray] | None = None
    if n_blocks >= 2:
        adjacency = _block_adjacency(indptr, indices, n_blocks)
        while n_blocks >= 2:  # the cuts nest: halving merges neighbouring pairs of blocks
            colour = _greedy_colours(adjacency)
            n_colours = int(colour.max()) + 1
            if 2 * n_colours <= n_blocks and (best is None or n_colours < best[0]):
                best = (n_colours, n_blocks, colour)
            adjacency = adjacency.reshape(n_blocks // 2, 2, n_blocks // 2, 2).any(axis=(1, 3))
            n_blocks //= 2
    if best is None:
        return SweepSchedule(None, None, np.array([0, n], dtype=np.int64),
                             np.array([0, 1], dtype=np.int64))
    n_colours, n_blocks, colour = best
    starts = (np.arange(n_blocks + 1, dtype=np.int64) * n) // n_blocks
    perm = np.argsort(colour, kind="stable")  # blocks colour by colour, row order within
    sizes = np.diff(starts)[perm]
    blocks = np.concatenate(([0], np.cumsum(sizes))).astype(np.int64)
    order = np.concatenate([np.arange(starts[s], starts[s + 1]) for s in perm]).astype(np.int32)
    rank = np.empty(n, dtype=np.int32)
    rank[order] = np.arange(n, dtype=np.int32)
    colours = np.concatenate(([0], np.cumsum(np.bincount(colour, minlength=n_colours))))
    return SweepSchedule(rank, order, blocks, colours.astype(np.int64))


def split_triangles(A: sp.bsr_matrix, rank: np.ndarray | None
                    ) -> tuple[sp.bsr_matrix, sp.bsr_matrix]:
    """``(L, U)``: the blocks of the square BSR matrix ``A`` whose columns come earlier
    (``rank[j] < rank[i]``) and later in a sweep order (``rank`` None: the row order), as BSR
    matrices with int32 indices, each row's blocks in ``A``'s storage order."""
    k = A.blocksize[0]
    nb = A.shape[0] // k
    rows = np.repeat(np.arange(nb), np.diff(A.indptr))
    r = np.arange(nb) if rank is None else np.asarray(rank)
    rank_rows, rank_cols = r[rows], r[A.indices]

    def part(keep: np.ndarray) -> sp.bsr_matrix:
        indptr = np.zeros(nb + 1, dtype=np.int32)
        np.cumsum(np.bincount(rows[keep], minlength=nb), out=indptr[1:])
        return sp.bsr_matrix((A.data[keep], A.indices[keep].astype(np.int32), indptr),
                             shape=A.shape)

    return part(rank_cols < rank_rows), part(rank_cols > rank_rows)


def bsr_product(ext: ModuleType, A: sp.bsr_matrix, B: sp.bsr_matrix, n_threads: int = 0
                ) -> sp.bsr_matrix:
    """``A @ B`` of two BSR matrices on the C kernels (``n_threads`` threads, 0: OpenMP's
    count, over the rows of the product, each row's blocks summed in ``A``'s then ``B``'s
    storage order: the same bits on any thread count); sorted int32 indices."""
    R, K = A.blocksize
    C = B.blocksize[1]
    if B.blocksize[0] != K or A.shape[1] != B.shape[0]:
        raise ValueError(f"cannot multiply {A.shape} ({R}x{K} blocks) by {B.shape} "
                         f"({B.blocksize[0]}x{C} blocks)")
    n_rows, n_cols = A.shape[0] // R, B.shape[1] // C
    if max(A.indices.size, B.indices.size, n_cols) >= 2**31:
        raise ValueError("bsr_product takes at most 2**31 - 1 blocks (int32 indices)")
    a = [np.ascontiguousarray(A.indptr, dtype=np.int32),
         np.ascontiguousarray(A.indices, dtype=np.int32), np.ascontiguousarray(A.data)]
    b = [np.ascontiguousarray(B.indptr, dtype=np.int32),
         np.ascontiguousarray(B.indices, dtype=np.int32), np.ascontiguousarray(B.data)]
    counts = np.empty(n_rows, dtype=np.int64)
    ext.bsr_matmat_count(a[0], a[1], b[0], b[1], n_cols, counts, n_threads)
    indptr = np.zeros(n_rows + 1, dtype=np.int64)
    np.cumsum(counts, out=indptr[1:])
    if indptr[-1] >= 2**31:
        raise ValueError("the product has more than 2**31 blocks")
    indices = np.empty(int(indptr[-1]), dtype=np.int32)
    data = np.empty((int(indptr[-1]), R, C))
    ext.bsr_matmat_fill(a[0], a[1], a[2], R, K, b[0], b[1], b[2], C, n_cols, indptr, indices,
                        data, n_threads)
    M = sp.bsr_matrix((data, indices, indptr.astype(np.int32)), shape=(A.shape[0], B.shape[1]))
    M.has_sorted_indices = True
    return M


def product_threads(ext: ModuleType, A: sp.bsr_matrix) -> int:
    """The thread count of the ``"products"`` family (:func:`bsr_product`), measured the first
    time in a process on the product of :data:`PRODUCT_SAMPLE_ROWS` block rows of the square
    BSR matrix ``A`` with ``A``."""
    R = A.blocksize[0]
    rows = min(A.shape[0] // R, PRODUCT_SAMPLE_ROWS)
    stop = int(A.indptr[rows])
    sample = sp.bsr_matrix((A.data[:stop], A.indices[:stop], A.indptr[:rows + 1]),
                           shape=(rows * R, A.shape[1]))
    return measure("products", lambda n: bsr_product(ext, sample, A, n))


def reference_sweep(L: sp.bsr_matrix, U: sp.bsr_matrix, Dinv: np.ndarray,
                    schedule: SweepSchedule, x: np.ndarray, b: np.ndarray, *,
                    backward: bool = False) -> np.ndarray:
    """One block Gauss-Seidel sweep in NumPy, row by row in the schedule's order (forward:
    ``x_i = Dinv_i (b_i - L_i x)``; backward, in reverse order: ``x_i = Dinv_i (b_i - L_i x -
    U_i x)``). Returns a new x (slow: for checks)."""
    k = L.blocksize[0]
    x = np.array(x, dtype=np.float64).reshape(-1, k)
    b = np.asarray(b, dtype=np.float64).reshape(-1, k)
    seq = schedule.sequence()
    for i in (seq[::-1] if backward else seq):
        acc = b[i].copy()
        for M in ((L, U) if backward else (L,)):
            lo, hi = M.indptr[i], M.indptr[i + 1]
            acc -= np.einsum("jab,jb->a", M.data[lo:hi], x[M.indices[lo:hi]])
        x[i] = Dinv[i] @ acc
    return x.reshape(-1)
