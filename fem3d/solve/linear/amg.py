"""Algebraic multigrid: smoothed-aggregation V-cycles preconditioning conjugate gradients.

The hierarchy behind the ``"amg"`` linear solver
(:class:`fem3d.solve.linear.amg_cg.AMGCGSolver`; ``"auto"`` picks it by size):
:func:`rigid_body_modes` gives the near-nullspace, :class:`AMGPreconditioner` aggregates
a sparsity pattern once, builds a numeric hierarchy per matrix and runs V-cycle
preconditioned CG. pyamg provides the aggregation, the candidate fitting and the block
Gauss-Seidel kernel; the rest is fem3d's own. Large systems (``threads_min_rows``) run the
setup's products, the V-cycles and CG on the threaded C kernels of
:mod:`fem3d.solve.sparse_threads` instead (Gauss-Seidel in a colour/block order; the same bits
on any number of threads).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse as sp

from fem3d.kernels import threads
from fem3d.solve import sparse_threads
from fem3d.solve.linear.base import as_csr
from fem3d.solve.linear.krylov import CGResult

__all__ = ["AMG_OPTIONS", "AMGPreconditioner", "rigid_body_modes"]


def rigid_body_modes(points: np.ndarray) -> np.ndarray:
    """The six rigid-body modes of a point set, the near-nullspace of elasticity.

    Parameters
    ----------
    points : (k, 3) float64

    Returns
    -------
    (3 k, 6) float64
        Vertex-major DOF vectors: translations along x, y, z, then infinitesimal rotations
        about x, y, z through the centroid (scaled to the translations' magnitude).
    """
    x = np.asarray(points, dtype=np.float64)
    y = x - x.mean(axis=0)
    scale = float(np.abs(y).max()) or 1.0
    y = y / scale
    B = np.zeros((3 * x.shape[0], 6))
    for a in range(3):
        B[a::3, a] = 1.0
    B[1::3, 3], B[2::3, 3] = -y[:, 2], y[:, 1]  # about x: (0, -z, y)
    B[0::3, 4], B[2::3, 4] = y[:, 2], -y[:, 0]  # about y: (z, 0, -x)
    B[0::3, 5], B[1::3, 5] = -y[:, 1], y[:, 0]  # about z: (-y, x, 0)
    return B


#: Smoothed aggregation as used for the Newton systems (pyamg's building blocks, fem3d's own
#: setup and V-cycle):
#:
#: ``max_coarse``
#:     Coarsen until a level has at most this many block rows (vertices, then aggregates of
#:     six DOFs: pyamg's rule); it is solved densely (Cholesky, or a pseudo-inverse when it is
#:     not positive definite).
#: ``max_levels``
#:     Cap on the hierarchy's depth.
#: ``omega``
#:     Jacobi prolongation smoothing ``P = (I - omega / rho(D^-1 A) D^-1 A) T`` with the block
#:     diagonal ``D`` (pyamg's ``weighting="block"``: at 1e5 tets 17 CG iterations to 1e-6
#:     instead of 21 with the scalar diagonal).
#: ``rho_iterations``
#:     Arnoldi iterations estimating ``rho(D^-1 A)`` from a fixed start vector (so a hierarchy
#:     is a function of its matrix alone: a checkpoint rebuilds the same one).
#:
#: Fixed choices: strength of connection without a threshold (every block couples: the vector
#: problem is not M-matrix-like), so the aggregation depends on the sparsity pattern alone and
#: is computed once per pattern (:meth:`AMGPreconditioner.analyze`, like a direct solver's
#: symbolic analysis); no candidate improvement (the rigid modes are exact near-nullspace
#: vectors); one forward block Gauss-Seidel sweep before the coarse correction and one
#: backward sweep after (a symmetric V-cycle at half the cost of symmetric sweeps, same
#: iterations).
#:
#: ``threads_min_rows``
#:     Systems of at least this many vertices (3-DOF block rows) run the V-cycles and CG on
#:     the threaded C kernels of :mod:`fem3d.solve.sparse_threads` (the sweeps in a
#:     colour/block order: the same bits on any number of threads); smaller ones, or any
#:     without the C extension, keep pyamg's Gauss-Seidel in row order and SciPy's mat-vecs
#:     (the classic scenes' bits). 6144 vertices: about 3e4 tets, where the fused assemblies
#:     start their threads too. How many threads each family of those kernels gets (the
#:     solve's sweeps, mat-vecs and dot products together; the products) is measured at the
#:     first such setup of a process, or forced by ``FEM3D_THREADS``
#:     (:mod:`fem3d.kernels.threads`).
AMG_OPTIONS: dict = dict(max_coarse=500, max_levels=10, omega=4.0 / 3.0, rho_iterations=6,
                         threads_min_rows=6144)


@dataclass(frozen=True, eq=False)
class _AMGPlan:
    """The structural part of a hierarchy (:meth:`AMGPreconditioner.analyze`).

    ``indptr``/``indices`` are the CSR pattern analysed; ``bsr_indptr``/``bsr_indices`` its
    3x3 block pattern and ``bsr_slot`` the BSR data slot of every CSR entry; ``T`` the
    tentative prolongators (BSR) of levels ``0 .. L-2``.
    """

    indptr: np.ndarray
    indices: np.ndarray
    bsr_indptr: np.ndarray
    bsr_indices: np.ndarray
    bsr_slot: np.ndarray
    T: tuple
    seconds: float


@dataclass(frozen=True, eq=False)
class _AMGLevel:
    """One non-coarsest level of the hierarchy.

    Its matrix ``A = L + D + U`` (strictly lower blocks, diagonal blocks, strictly upper) is
    kept as ``L`` and ``U`` in BSR (block Gauss-Seidel reads the diagonal blocks only through
    their inverses ``Dinv``, ``(nb, k, k)``), ``U`` with the block order reversed (``U_rev =
    J U J``, ``J`` reversing the blocks: a forward sweep on it is a backward sweep on ``U``,
    and pyamg's Gauss-Seidel runs 1.8x slower backward; ``Dinv_rev`` likewise); P and
    R = P^T.
    """

    L: sp.bsr_matrix
    U_rev: sp.bsr_matrix
    Dinv: np.ndarray
    Dinv_rev: np.ndarray
    P: sp.bsr_matrix
    R: sp.bsr_matrix

    @staticmethod
    def make(A: sp.bsr_matrix, Dinv: np.ndarray, P: sp.bsr_matrix, R: sp.bsr_matrix
             ) -> _AMGLevel:
        """Split ``A`` (BSR, sorted indices) into its triangles."""
        k = A.blocksize[0]
        nb = A.shape[0] // k
        rows = np.repeat(np.arange(nb), np.diff(A.indptr))

        def part(keep: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            indptr = np.zeros(nb + 1, dtype=A.indptr.dtype)
            np.cumsum(np.bincount(rows[keep], minlength=nb), out=indptr[1:])
            return A.data[keep], A.indices[keep], indptr

        def bsr(data, indices, indptr) -> sp.bsr_matrix:
            M = sp.bsr_matrix((data, indices, indptr), shape=A.shape)
            M.has_sorted_indices = True
            return M

        data, indices, indptr = part(A.indices > rows)
        # reversing the block sequence reverses the rows and the order within each row
        u_rev = bsr(np.ascontiguousarray(data[::-1]),
                    (nb - 1 - indices[::-1]).astype(indices.dtype),
                    (indptr[-1] - indptr[::-1]).astype(indptr.dtype))
        return _AMGLevel(bsr(*part(A.indices < rows)), u_rev, Dinv,
                         np.ascontiguousarray(Dinv[::-1]), P, R)


@dataclass(frozen=True, eq=False)
class _ThreadedLevel:
    """One non-coarsest level of a hierarchy on the threaded kernels: the order of its
    Gauss-Seidel sweeps (:func:`~fem3d.solve.sparse_threads.sweep_schedule`), its matrix
    ``A = L + D + U`` split in that order (:func:`~fem3d.solve.sparse_threads.split_triangles`)
    as ``L``, ``U`` and the inverses ``Dinv`` of the diagonal blocks, P and R = P^T (BSR with
    int32 indices)."""

    L: sp.bsr_matrix
    U: sp.bsr_matrix
    Dinv: np.ndarray
    sweep: sparse_threads.SweepSchedule
    P: sp.bsr_matrix
    R: sp.bsr_matrix


def _c_bsr(M: sp.bsr_matrix) -> sp.bsr_matrix:
    """``M`` with int32 indices and contiguous data (what the C kernels take)."""
    return sp.bsr_matrix((np.ascontiguousarray(M.data), M.indices.astype(np.int32, copy=False),
                          M.indptr.astype(np.int32, copy=False)), shape=M.shape)


def _reversed_blocks(x: np.ndarray, k: int) -> np.ndarray:
    """``J x``: the ``k``-blocks of ``x`` in reverse order (a new contiguous array)."""
    return np.ascontiguousarray(x.reshape(-1, k)[::-1]).reshape(-1)


def _slot_dtype(slot: np.ndarray) -> type:
    return np.int32 if slot.size == 0 or slot.max() < 2**31 else np.int64


def _block_pattern(indptr: np.ndarray, indices: np.ndarray, n: int
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """3x3 block pattern of a CSR pattern and the BSR data slot of every CSR entry."""
    nb = n // 3
    rows = np.repeat(np.arange(n, dtype=np.int64), np.diff(indptr))
    cols = np.asarray(indices, dtype=np.int64)
    # the block pattern: rows of the blocks' columns, summed over each block row's 3 rows
    E = sp.csr_matrix((np.ones(cols.size), cols // 3, np.array(indptr)), shape=(n, nb))
    E.sum_duplicates()  # in place: on a copy of indptr
    G = sp.csr_matrix((np.ones(n), np.arange(n) // 3, np.arange(n + 1)), shape=(n, nb)).T @ E
    G = G.tocsr()
    G.sort_indices()
    bsr_indptr = G.indptr.astype(np.int32)
    bsr_indices = G.indices.astype(np.int32)
    keys = (rows // 3) * nb + cols // 3
    if cols.size == 9 * bsr_indices.size:  # full blocks: the slots follow arithmetically
        t = np.arange(cols.size, dtype=np.int64) - np.asarray(indptr, dtype=np.int64)[rows]
        block = bsr_indptr[rows // 3].astype(np.int64) + t // 3
        if np.array_equal(bsr_indices[block].astype(np.int64) * 3 + t % 3, cols):
            slot = block * 9 + (rows % 3) * 3 + t % 3
            return bsr_indptr, bsr_indices, slot.astype(_slot_dtype(slot))
    block_rows = np.repeat(np.arange(nb, dtype=np.int64), np.diff(bsr_indptr))
    block = np.searchsorted(block_rows * nb + bsr_indices, keys)
    slot = block * 9 + (rows % 3) * 3 + cols % 3
    return bsr_indptr, bsr_indices, slot.astype(_slot_dtype(slot))


def _full_block_pattern(indptr: np.ndarray, indices: np.ndarray, n: int
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """:func:`_block_pattern` of a CSR pattern made of whole 3x3 blocks (a finite-element
    pattern: every vertex pair couples all 3 x 3 DOFs) in int32 arithmetic over its column
    triples; None when the pattern is not made of whole blocks.

    Triple ``u`` of the CSR (entries ``3 u .. 3 u + 2``) is the ``k``-th of row ``3 i + c``,
    ``u = 3 bp_i + c deg_i + k`` (``bp_i`` the first block of block row ``i``, ``deg_i`` its
    block count), and its entries land in BSR slots ``9 (bp_i + k) + 3 c + (0, 1, 2)``.
    """
    nb = n // 3
    indptr = np.asarray(indptr)
    nnz = int(indptr[-1])
    if nnz == 0 or nnz % 9 or nnz > np.iinfo(np.int32).max:
        return None
    length = np.diff(indptr)
    if (length % 3).any() or not ((length[1::3] == length[0::3]).all()
                                  and (length[2::3] == length[0::3]).all()):
        return None
    deg = (length[0::3] // 3).astype(np.int32)  # blocks per block row
    triple = np.asarray(indices).reshape(-1, 3)  # rows hold whole triples: they start at 3 k
    first = triple[:, 0]
    if (first % 3).any() or not ((triple[:, 1] == first + 1).all()
                                 and (triple[:, 2] == first + 2).all()):
        return None
    block_col = (first // 3).astype(np.int32)  # one per triple, in CSR order
    del triple, first
    bsr_indptr = np.zeros(nb + 1, dtype=np.int32)
    np.cumsum(deg, out=bsr_indptr[1:])
    row_of_triple = np.repeat(np.arange(3 * nb, dtype=np.int32), np.repeat(deg, 3))
    c = row_of_triple % 3
    bsr_indices = block_col[c == 0]
    # rows 3 i + 1 and 3 i + 2 must repeat row 3 i's block columns
    if not (np.array_equal(block_col[c == 1], bsr_indices)
            and np.array_equal(block_col[c == 2], bsr_indices)):
        return None
    del block_col
    i = row_of_triple // 3
    del row_of_triple
    u = np.arange(c.size, dtype=np.int32)
    u -= 2 * bsr_indptr[i] + c * deg[i]  # bp_i + k
    u *= 9
    u += 3 * c
    slot = (u[:, None] + np.arange(3, dtype=np.int32)).reshape(-1)
    return bsr_indptr, bsr_indices, slot


def _block_inverses(A: sp.bsr_matrix) -> np.ndarray:
    """``(nb, k, k)`` inverses of the diagonal blocks of a square-blocked BSR matrix:
    pseudo-inverses where a block is singular (coarse levels: a candidate dropped in an
    aggregate leaves a zero row and column). 3x3 blocks by their adjugates (vectorized)."""
    from pyamg import amg_core  # pyamg is imported when AMG runs (0.3 s at every start else)

    k = A.blocksize[0]
    nb = A.shape[0] // k
    rows = np.repeat(np.arange(nb), np.diff(A.indptr))
    diag = np.flatnonzero(A.indices == rows)
    D = np.zeros((nb, k, k))
    D[rows[diag]] = A.data[diag]
    if k != 3:
        amg_core.pinv_array(D.ravel(), nb, k, "T")  # in place, robust to singular blocks
        return D
    # adjugate / determinant; ill-conditioned blocks go to the pseudo-inverse
    adj = np.empty_like(D)
    for i in range(3):
        for j in range(3):
            r0, r1 = (j + 1) % 3, (j + 2) % 3
            c0, c1 = (i + 1) % 3, (i + 2) % 3
            adj[:, i, j] = D[:, r0, c0] * D[:, r1, c1] - D[:, r0, c1] * D[:, r1, c0]
    det = np.einsum("bj,bj->b", D[:, 0, :], adj[:, :, 0])
    scale = np.abs(D).reshape(nb, -1).max(axis=1)
    bad = ~(np.abs(det) > 1e-10 * scale ** 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        Dinv = adj / det[:, None, None]
    if bad.any():
        Db = np.ascontiguousarray(D[bad])
        amg_core.pinv_array(Db.ravel(), Db.shape[0], 3, "T")
        Dinv[bad] = Db
    return Dinv


def _block_diagonal(blocks: np.ndarray) -> sp.bsr_matrix:
    """The BSR block-diagonal matrix of ``(nb, k, k)`` blocks."""
    nb, k = blocks.shape[:2]
    return sp.bsr_matrix((blocks, np.arange(nb, dtype=np.int32),
                          np.arange(nb + 1, dtype=np.int32)), shape=(nb * k, nb * k))


def _block_rows_times(Dinv: np.ndarray, M: sp.bsr_matrix) -> sp.bsr_matrix:
    """``blockdiag(Dinv) @ M`` for a BSR ``M`` whose block rows match ``Dinv``'s blocks."""
    rows = np.repeat(np.arange(Dinv.shape[0]), np.diff(M.indptr))
    return sp.bsr_matrix((np.matmul(Dinv[rows], M.data), M.indices, M.indptr), shape=M.shape)


def _spectral_radius(A: sp.bsr_matrix, Dinv: np.ndarray, iterations: int,
                     ext: object = None, n_threads: int = 0) -> float:
    """Largest eigenvalue of ``D^-1 A`` (Arnoldi from a fixed start vector); NumPy's inner
    products and SciPy's mat-vecs, or the C extension's ``ext`` (on ``n_threads``)."""
    n = A.shape[0]
    Dinv = _block_diagonal(Dinv)
    dot = None
    if ext is None:
        def operator(v):
            return Dinv @ (A @ v)
    else:
        A, Dinv = _c_bsr(A), _c_bsr(Dinv)

        def operator(v):
            Av, w = np.empty(n), np.empty(n)
            ext.bsr_matvec(A.indptr, A.indices, A.data, *A.blocksize, v, None, 1.0, Av,
                           n_threads)
            ext.bsr_matvec(Dinv.indptr, Dinv.indices, Dinv.data, *Dinv.blocksize, Av, None, 1.0,
                           w, n_threads)
            return w

        def dot(x, y):
            return ext.dot(x, y, n_threads)
    v = np.random.default_rng(12345).random(n)
    if dot is None:
        def dot(x, y):
            return x @ y

        def norm(x):
            return np.linalg.norm(x)
    else:
        def norm(x):
            return np.sqrt(dot(x, x))
    V = [v / norm(v)]
    H = np.zeros((iterations + 1, iterations))
    m = iterations
    for j in range(iterations):
        w = operator(V[j])
        for i in range(j + 1):
            H[i, j] = float(dot(w, V[i]))
            w -= H[i, j] * V[i]
        H[j + 1, j] = float(norm(w))
        if H[j + 1, j] <= 1e-12 * abs(H[j, j]):
            m = j + 1
            break
        V.append(w / H[j + 1, j])
    return float(np.abs(np.linalg.eigvals(H[:m, :m])).max())


def _galerkin(A: sp.bsr_matrix, T: sp.bsr_matrix, Dinv: np.ndarray, scale: float,
              ext: object, n_threads: int = 0
              ) -> tuple[sp.bsr_matrix, sp.bsr_matrix, sp.bsr_matrix]:
    """``P = T - scale D^-1 A T``, ``R = P^T`` and the coarse matrix ``R A P`` (sorted
    indices): SciPy's products, or the threaded C ones (on ``n_threads``) when ``ext`` is the
    C extension."""
    if ext is None:
        P = T - scale * _block_rows_times(Dinv, A @ T)
        P = sp.bsr_matrix(P, blocksize=T.blocksize)
        R = sp.bsr_matrix(P.T)
        Ac = sp.bsr_matrix(R @ (A @ P))  # (the product A P is the largest transient)
        Ac.sort_indices()
        return P, R, Ac
    def product(X: sp.bsr_matrix, Y: sp.bsr_matrix) -> sp.bsr_matrix:
        return sparse_threads.bsr_product(ext, X, Y, n_threads)

    P = T - scale * _block_rows_times(Dinv, product(A, T))
    P = _c_bsr(sp.bsr_matrix(P, blocksize=T.blocksize))
    R = _c_bsr(sp.bsr_matrix(P.T))
    return P, R, product(R, product(A, P))


class AMGPreconditioner:
    """Smoothed-aggregation AMG V-cycles preconditioning conjugate gradients.

    Two phases, like a direct solver's: :meth:`analyze` aggregates the vertices of a sparsity
    pattern (once per pattern: the strength of connection keeps every block, so the
    aggregates, the tentative prolongators and the coarse near-nullspace depend on the
    pattern and the rigid-body modes alone); :meth:`setup` builds the numeric hierarchy of one
    matrix (smoothed prolongators, Galerkin coarse matrices, smoother data, coarsest
    factorization), reused for later matrices of the same pattern (Newton iterations, time
    steps) until the caller decides it has aged
    (:func:`~fem3d.solve.linear.krylov.iterations_per_decade` of the last solve above its budget).
    pyamg provides the aggregation, the candidate fitting and the block Gauss-Seidel kernel.

    Parameters
    ----------
    near_nullspace : (n, k) float64
        ``B``: the rigid-body modes of the free DOFs (:func:`rigid_body_modes`).
    options : dict, optional
        Overrides of :data:`AMG_OPTIONS`.

    Attributes
    ----------
    setups : int
        Hierarchies built.
    analyze_seconds, setup_seconds, cg_seconds : float
        Wall time of the last analysis, and total wall time in setups and in CG.
    iterations : int
        Total CG iterations.
    level_sizes : list of int
        DOFs per level of the current hierarchy, finest first.
    thread_counts : dict
        Threads per kernel family (``"products"``, ``"solve"``) of a hierarchy on the
        threaded kernels (:mod:`fem3d.kernels.threads`); empty otherwise.
    """

    def __init__(self, near_nullspace: np.ndarray, options: dict | None = None) -> None:
        self.B = np.asarray(near_nullspace, dtype=np.float64)
        unknown = set(options or {}) - set(AMG_OPTIONS)
        if unknown:
            raise ValueError(f"unknown AMG options {sorted(unknown)}; known: "
                             f"{sorted(AMG_OPTIONS)}")
        self.options = AMG_OPTIONS | dict(options or {})
        self._plan: _AMGPlan | None = None
        self._levels: list = []  # _AMGLevel, or _ThreadedLevel when threaded
        self._coarse: tuple | None = None
        self._threads = None  # the C kernels while the hierarchy runs on them
        self.thread_counts: dict[str, int] = {}  # per kernel family, while threaded
        self._sweeps: list[tuple[np.ndarray, np.ndarray, sparse_threads.SweepSchedule]] = []
        self.pattern_key: object = None
        self.setups = 0
        self.analyze_seconds = 0.0
        self.setup_seconds = 0.0
        self.cg_seconds = 0.0
        self.iterations = 0
        self.level_sizes: list[int] = []

    @property
    def ready(self) -> bool:
        """A hierarchy exists."""
        return self._coarse is not None

    def _planned(self, A: sp.csr_matrix) -> bool:
        plan = self._plan
        return plan is not None and (
            (plan.indptr is A.indptr and plan.indices is A.indices) or
            (np.array_equal(plan.indptr, A.indptr) and np.array_equal(plan.indices, A.indices)))

    def analyze(self, pattern: sp.spmatrix | sp.sparray) -> None:
        """Aggregate the DOFs of ``pattern`` level by level (structure only; its values are
        ignored). :meth:`setup` runs it when it meets a new pattern.

        Parameters
        ----------
        pattern : (n, n) scipy.sparse matrix
            Symmetric pattern of whole 3-DOF vertices (n divisible by 3), diagonal included.
        """
        from pyamg.aggregation.aggregate import standard_aggregation  # see amg_core above
        from pyamg.aggregation.tentative import fit_candidates

        t0 = time.perf_counter()
        P = as_csr(pattern)
        n = P.shape[0]
        if n % 3 or P.shape != (n, n):
            raise ValueError("AMG needs a square matrix of whole 3-DOF vertices")
        if self.B.shape[0] != n:
            raise ValueError(f"near-nullspace has {self.B.shape[0]} rows, the matrix {n}")
        blocks = _full_block_pattern(P.indptr, P.indices, n)
        bsr_indptr, bsr_indices, slot = blocks if blocks is not None else \
            _block_pattern(P.indptr, P.indices, n)
        nb = n // 3
        G = sp.csr_matrix((np.ones(bsr_indices.size), bsr_indices, bsr_indptr), shape=(nb, nb))
        B = self.B
        T = []
        size = n
        while G.shape[0] > self.options["max_coarse"] and \
                len(T) + 1 < self.options["max_levels"]:
            agg, _ = standard_aggregation(sp.csr_array(G))
            agg = sp.csr_matrix(agg)
            if agg.shape[1] == 0 or agg.shape[1] * B.shape[1] >= size:
                break  # no coarsening left
            Tl, B = fit_candidates(sp.csr_array(agg), B)
            T.append(sp.bsr_matrix(Tl))
            # the next level's block pattern: P^T A P with P's pattern that of A T
            GP = G @ agg
            G = (GP.T @ G @ GP).tocsr()
            G.data[:] = 1.0
            G.sort_indices()
            size = B.shape[0]
        self._plan = _AMGPlan(P.indptr, P.indices, bsr_indptr, bsr_indices, slot, tuple(T),
                              time.perf_counter() - t0)
        self._coarse = None
        self.analyze_seconds = self._plan.seconds

    def setup(self, A: sp.csr_matrix, pattern_key: object = None) -> None:
        """Build the hierarchy from ``A`` (symmetric, 3x3-blocked DOFs; analysed first when
        its pattern is new)."""
        t0 = time.perf_counter()
        A = as_csr(A)
        if not self._planned(A):
            self.analyze(A)
        plan = self._plan
        n = A.shape[0]
        data = np.zeros(plan.bsr_indices.size * 9)
        data[plan.bsr_slot] = A.data
        Al = sp.bsr_matrix((data.reshape(-1, 3, 3), plan.bsr_indices, plan.bsr_indptr),
                           shape=(n, n))
        omega, iters = self.options["omega"], self.options["rho_iterations"]
        ext = sparse_threads.c_kernels() if n // 3 >= self.options["threads_min_rows"] else None
        counts = self._setup_thread_counts(ext, Al)
        levels = []
        for T in plan.T:
            Dinv = _block_inverses(Al)
            rho = _spectral_radius(Al, Dinv, iters, ext, counts.get("solve", 0))
            P, R, Ac = _galerkin(Al, T, Dinv, omega / rho, ext, counts.get("products", 0))
            if ext is None:
                levels.append(_AMGLevel.make(Al, Dinv, P, R))
            else:
                sweep = self._sweep_schedule(len(levels), Al)
                L, U = sparse_threads.split_triangles(Al, sweep.rank)
                levels.append(_ThreadedLevel(L, U, np.ascontiguousarray(Dinv), sweep, P, R))
            Al = Ac
        Ac = Al.toarray()
        Ac = 0.5 * (Ac + Ac.T)
        try:
            self._coarse = ("cholesky", scipy.linalg.cho_factor(Ac, lower=True))
        except np.linalg.LinAlgError:  # not positive definite: a symmetric pseudo-inverse
            self._coarse = ("pinv", scipy.linalg.pinvh(Ac))
        self._levels = levels
        self._threads = ext
        self.thread_counts = counts
        if ext is not None and levels:
            self._measure_solve(A)
        self.level_sizes = [lvl.P.shape[0] for lvl in levels] + [Ac.shape[0]]
        self.pattern_key = pattern_key
        self.setups += 1
        self.setup_seconds += time.perf_counter() - t0

    def _setup_thread_counts(self, ext: object, Al: sp.bsr_matrix) -> dict[str, int]:
        """Threads of the products on the threaded kernels (``ext``; none without), measured
        on ``Al`` (the setup matrix in BSR) the first time in a process
        (:mod:`fem3d.kernels.threads`), and of the setup's mat-vecs: the solve's count once
        it is chosen (:meth:`_measure_solve`), one thread before."""
        if ext is None:
            return {}
        counts = {"solve": threads.settled_threads("solve") or 1}
        if self._plan.T:
            counts["products"] = sparse_threads.product_threads(ext, _c_bsr(Al))
        return counts

    def _measure_solve(self, A: sp.csr_matrix) -> None:
        """The solve's thread count (sweeps, mat-vecs and dot products together), measured
        the first time in a process on PCG rounds of the new hierarchy: a V-cycle, a mat-vec
        with ``A`` and a dot product, all on the count tried (their vectors pass from kernel
        to kernel as in CG, so a count that moves them between cores pays for it here)."""
        b = np.ones(A.shape[0])
        counts = self.thread_counts

        def pcg_round(n_threads: int) -> None:
            counts["solve"] = n_threads
            dot, matvec = self._cg_operations(A)
            z = self._apply_threaded(b)
            dot(matvec(z), z)

        counts["solve"] = threads.measure("solve", pcg_round)

    def _sweep_schedule(self, level: int, A: sp.bsr_matrix) -> sparse_threads.SweepSchedule:
        """The sweep order of level ``level``'s pattern (cached while the pattern stays: a
        pattern with a new block needs a new colouring)."""
        if level < len(self._sweeps):
            indptr, indices, schedule = self._sweeps[level]
            if np.array_equal(indptr, A.indptr) and np.array_equal(indices, A.indices):
                return schedule
        del self._sweeps[level:]
        self._sweeps.append((A.indptr, A.indices, sparse_threads.sweep_schedule(A.indptr,
                                                                                A.indices)))
        return self._sweeps[level][2]

    def _coarse_solve(self, b: np.ndarray) -> np.ndarray:
        kind, f = self._coarse
        # the factor was checked at setup; checking it again (a dense copy's isfinite) each
        # V-cycle cost a third of the coarse solve on the 16k-tet pile (same result, bit for bit)
        return scipy.linalg.cho_solve(f, b, check_finite=False) if kind == "cholesky" else f @ b

    def apply(self, b: np.ndarray) -> np.ndarray:
        """One V-cycle from zero on ``A x = b`` (``A`` the setup matrix): ``x ~ A^-1 b``,
        symmetric positive definite when ``A`` is."""
        from pyamg import amg_core  # imported when AMG runs

        if self._coarse is None:
            raise RuntimeError("setup() must run before apply()")
        if self._threads is not None:
            return self._apply_threaded(np.ascontiguousarray(b, dtype=np.float64))
        # Forward Gauss-Seidel from x = 0 never reads the upper triangle (x is still 0 there)
        # and leaves the residual b - A x = -U x; the backward sweep on x is one on U + D
        # with b - L x (L x of the old x throughout). So each sweep touches half the blocks
        # and each residual costs half a product: the same V-cycle as full sweeps on A.
        gs = amg_core.block_gauss_seidel
        xs, bs = [], []
        for lvl in self._levels:
            L, k = lvl.L, lvl.Dinv.shape[1]
            x = np.zeros_like(b)
            gs(L.indptr, L.indices, L.data.reshape(-1), x, b, lvl.Dinv.reshape(-1),
               0, L.shape[0] // k, 1, k)
            xs.append(x)
            bs.append(b)
            b = lvl.R @ _reversed_blocks(lvl.U_rev @ _reversed_blocks(x, k), k)
            np.negative(b, out=b)
        x = self._coarse_solve(b)
        for lvl, xf, bf in zip(reversed(self._levels), reversed(xs), reversed(bs), strict=True):
            U, k = lvl.U_rev, lvl.Dinv.shape[1]
            xf += lvl.P @ x
            c = bf - lvl.L @ xf
            x = _reversed_blocks(xf, k)
            gs(U.indptr, U.indices, U.data.reshape(-1), x, _reversed_blocks(c, k),
               lvl.Dinv_rev.reshape(-1), 0, U.shape[0] // k, 1, k)
            x = _reversed_blocks(x, k)
        return x

    def _apply_threaded(self, b: np.ndarray) -> np.ndarray:
        """:meth:`apply` on the threaded kernels: the same V-cycle, the sweeps in each level's
        schedule order on its triangles in that order (the backward sweep reads ``L`` of the
        old ``x`` itself: one pass for ``b - L x`` and the sweep)."""
        ext = self._threads
        n_threads = self.thread_counts.get("solve", 0)
        xs, bs = [], []
        for lvl in self._levels:
            L, U, s, R = lvl.L, lvl.U, lvl.sweep, lvl.R
            x = np.zeros_like(b)
            ext.block_sweep(L.indptr, L.indices, L.data, None, None, None, lvl.Dinv, s.order,
                            s.blocks, s.colours, x, b, n_threads)
            xs.append(x)
            bs.append(b)
            r = np.empty_like(b)  # b - A x = -U x after a forward sweep from zero
            ext.bsr_matvec(U.indptr, U.indices, U.data, *U.blocksize, x, None, -1.0, r, n_threads)
            b = np.empty(R.shape[0])
            ext.bsr_matvec(R.indptr, R.indices, R.data, *R.blocksize, r, None, 1.0, b, n_threads)
        x = self._coarse_solve(b)
        for lvl, xf, bf in zip(reversed(self._levels), reversed(xs), reversed(bs), strict=True):
            L, U, s, P = lvl.L, lvl.U, lvl.sweep, lvl.P
            ext.bsr_matvec(P.indptr, P.indices, P.data, *P.blocksize, x, xf, 1.0, xf, n_threads)
            ext.block_sweep(L.indptr, L.indices, L.data, U.indptr, U.indices, U.data, lvl.Dinv,
                            s.order, s.blocks, s.colours, xf, bf, n_threads)
            x = xf
        return x

    def _cg_operations(self, A: sp.csr_matrix) -> tuple:
        """CG's inner product and ``p -> A p``: NumPy's and SciPy's, or the threaded C kernels
        (the same bits on any thread count) with a threaded hierarchy."""
        ext = self._threads
        if ext is None:
            # bitwise the classic float(r @ z), np.linalg.norm(r) (its square root of r @ r)
            return (lambda x, y: float(x @ y)), (lambda p: A @ p)
        n_threads = self.thread_counts["solve"]

        def dot(x: np.ndarray, y: np.ndarray) -> float:
            return ext.dot(x, y, n_threads)

        if A.indptr.dtype != np.int32 or A.indices.dtype != np.int32:
            return dot, (lambda p: A @ p)
        data = np.ascontiguousarray(A.data, dtype=np.float64)

        def matvec(p: np.ndarray) -> np.ndarray:
            y = np.empty(A.shape[0])
            ext.csr_matvec(A.indptr, A.indices, data, p, y, n_threads)
            return y

        return dot, matvec

    def solve(self, A: sp.spmatrix | sp.sparray, b: np.ndarray, *, rtol: float,
              maxiter: int) -> CGResult:
        """CG on ``A x = b`` from ``x = 0``, V-cycle preconditioned, to ``|r| <= rtol |b|``.

        From ``x = 0`` every CG iterate of an SPD system is a descent direction of the
        quadratic model (``b . x > 0``). A non-positive curvature ``p^T A p`` stops CG with
        ``negative_curvature`` (``A`` indefinite); ``stalled`` means ``maxiter`` was reached.
        """
        if self._coarse is None:
            raise RuntimeError("setup() must run before solve()")
        t0 = time.perf_counter()
        A = as_csr(A)
        b = np.asarray(b, dtype=np.float64)
        dot, matvec = self._cg_operations(A)
        bnorm = math.sqrt(dot(b, b))
        if bnorm == 0.0:
            return CGResult(np.zeros_like(b), 0, 0.0, True, False, False)
        x = np.zeros_like(b)
        r = b.copy()
        res = 1.0
        it = 0
        negative = stalled = False
        p: np.ndarray | None = None
        rz = 0.0
        while res > rtol:
            if it >= maxiter:
                stalled = True
                break
            z = self.apply(r)
            rz_new = dot(r, z)
            if not rz_new > 0.0:  # the V-cycle is not SPD (hierarchy of an indefinite matrix)
                negative = stalled = True
                break
            if p is None:
                p = z
            else:
                p *= rz_new / rz
                p += z
            rz = rz_new
            Ap = matvec(p)
            curv = dot(p, Ap)
            if not curv > 0.0:
                negative = stalled = True
                break
            alpha = rz / curv
            x += alpha * p
            r -= alpha * Ap
            it += 1
            res = math.sqrt(dot(r, r)) / bnorm
        self.iterations += it
        self.cg_seconds += time.perf_counter() - t0
        return CGResult(x, it, res, not stalled, stalled, False, negative)
