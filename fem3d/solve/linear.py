"""Sparse symmetric positive-definite solves for the implicit integrators.

Backward Euler solves ``(M + dt^2 K) dv = -g`` once per Newton iteration, restricted to the free
DOFs. The sparsity pattern of that matrix is fixed for a mesh and a constraint set, so the
expensive symbolic analysis (fill-reducing ordering, elimination tree, supernodes) is done ONCE
per pattern and only the numeric factorization is repeated.

Back ends (``backend=``, or the ``FEM3D_SOLVER`` environment variable, which wins):

``"cholmod"``
    CHOLMOD Cholesky through scikit-sparse (``sksparse.cholmod``): supernodal, or simplicial
    ``LDL^T`` for small factors with short columns (the classic scenes), where the supernodal
    code's dense-block overhead costs more than it saves
    (:data:`SIMPLICIAL_MAX_FLOPS_PER_ENTRY`).
    Link it against an optimized BLAS (OpenBLAS): with the reference BLAS the supernodal
    factorization is ~20x slower.
``"pardiso"``
    Intel MKL PARDISO through pypardiso, real SPD matrix type (``mtype=2``), analysis phase 11
    once, numeric phase 22 per ``factorize``, solve phase 33.
``"superlu"``
    ``scipy.sparse.linalg.splu`` with diagonal pivoting (``SymmetricMode``): the first
    factorization computes the fill-reducing ordering (``MMD_AT_PLUS_A``, SuperLU has no
    separate analysis), later ones run on the symmetrically pre-permuted matrix with
    ``permc_spec="NATURAL"``. Needs only SciPy; several times slower than CHOLMOD or PARDISO
    on large meshes (no supernodal BLAS-3 Cholesky, LU stores both triangles).
``"auto"``
    The first of cholmod, pardiso, superlu that imports.

A matrix that is not positive definite (the stiffness away from rest may be indefinite) makes
:meth:`SparseSPDSolver.factorize` raise :class:`NotPositiveDefinite`; the caller can then use
:meth:`SparseSPDSolver.factorize_shifted`, which retries with ``A + mu S`` for increasing ``mu``
(``S = |diag(A)|`` by default, or a mass matrix), or fall back to a safe direction.

Iterative solvers live next door: :mod:`fem3d.solve.krylov` (conjugate gradients preconditioned
by an older factorization) and :mod:`fem3d.solve.amg` (smoothed-aggregation AMG).
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import os
import time
import warnings
from collections.abc import Callable, Iterator

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from fem3d.errors import Fem3dError

__all__ = [
    "AMG_AUTO_MIN_FREE_DOFS",
    "BACKENDS",
    "NotPositiveDefinite",
    "SparseSPDSolver",
    "available_backends",
    "default_backend",
    "loaded_blas",
    "amg_available",
    "choose_backend",
]

#: Back ends in the order ``"auto"`` tries them.
BACKENDS: tuple[str, ...] = ("cholmod", "pardiso", "superlu")

#: CHOLMOD runs simplicial (not supernodal) when the matrix has at most
#: :data:`SIMPLICIAL_MAX_N` rows and its factor costs fewer than this many flops per stored
#: entry (``sum c_j^2 / sum c_j`` over the column counts ``c_j`` of ``L``). Measured on this
#: project's 2-core machine with OpenBLAS (one thread, CPU time, best of 9): simplicial is
#: 1.2-1.6x faster on the armadillo (ratio 32), as fast or 1.7x faster on the bunny (66) and
#: as fast on a 300-DOF box (55); supernodal is 2.4x faster on a 540-DOF box (83), 3.0x on
#: the armadillo refined x8 (3,813 DOFs, 102), 2.4x on an 880-DOF box (118) and 7x on the
#: bunny refined x8 (266). The simplicial code slows down sharply once ``L`` leaves the cache.
#: CHOLMOD's own switch (40) sends the bunny to the supernodal code.
SIMPLICIAL_MAX_FLOPS_PER_ENTRY = 75.0
#: Above this size the pattern is not probed: the factorization is supernodal.
SIMPLICIAL_MAX_N = 5000


class NotPositiveDefinite(Fem3dError, np.linalg.LinAlgError):
    """The matrix handed to a Cholesky-type factorization is not positive definite.

    Parameters
    ----------
    message : str
        What failed.
    backend : str
        The back end that detected it.
    """

    def __init__(self, message: str, *, backend: str) -> None:
        self.backend = backend
        super().__init__(f"{backend}: {message}")


_MKL_RT: str | None = None


def _pardiso_solver():
    """A new ``pypardiso.PyPardisoSolver`` (real SPD), finding libmkl_rt only once.

    pypardiso searches ``sys.prefix`` for ``mkl_rt`` on every construction (seconds); the path
    found the first time is handed to later ones through ``PYPARDISO_MKL_RT``.
    """
    global _MKL_RT
    import pypardiso  # optional back end (fem3d[bench]): imported when chosen

    if _MKL_RT is None or "PYPARDISO_MKL_RT" in os.environ:
        solver = pypardiso.PyPardisoSolver(mtype=2)
        _MKL_RT = solver.libmkl._name
        return solver
    os.environ["PYPARDISO_MKL_RT"] = _MKL_RT
    try:
        return pypardiso.PyPardisoSolver(mtype=2)
    finally:
        del os.environ["PYPARDISO_MKL_RT"]


@functools.cache
def _backend_importable(name: str) -> bool:
    try:
        if name == "cholmod":
            import sksparse.cholmod  # noqa: F401
        elif name == "pardiso":
            _pardiso_solver()  # raises ImportError when mkl_rt is missing
        elif name != "superlu":
            return False
    except (ImportError, OSError):
        return False
    return True


@functools.cache
def amg_available() -> bool:
    """Whether pyamg (the ``"amg"`` back end) imports."""
    try:
        import pyamg  # noqa: F401
    except ImportError:
        return False
    return True


#: ``"auto"`` takes AMG-preconditioned CG (``"amg"``) for Newton systems with at least this many
#: free DOFs, a direct factorization below. Measured with ``python -m bench.newton_step --mesh
#: box --tets N --steps 3 --swing 4 --modes direct,reuse,amg`` (one thread, the project's
#: shared 2-core machine, load ~10; speed-ups over refactorizing every Newton iteration):
#: 882 free DOFs: amg 1.9x, reuse 3.7x; 2,700: amg 1.4x, reuse 1.1x; 6,084: amg 2.3x, reuse
#: 2.8x; 16,524: amg 4.7x, reuse 2.6x. AMG beats both direct modes from about 1e4 free DOFs.
AMG_AUTO_MIN_FREE_DOFS = 10000


def choose_backend(backend: str | None, n_free_dofs: int) -> str:
    """The linear back end a :class:`fem3d.solve.integrators.System` uses.

    Parameters
    ----------
    backend : {"auto", "amg", "cholmod", "pardiso", "superlu"} or None
        ``"auto"``/None: ``"amg"`` from :data:`AMG_AUTO_MIN_FREE_DOFS` free DOFs up when
        pyamg is installed, else the first direct back end that imports. ``FEM3D_SOLVER``
        (a direct back end) wins over ``"auto"``.
    n_free_dofs : int

    Returns
    -------
    str
        ``"amg"`` or a direct back end name.
    """
    name = (backend or "auto").lower()
    if name == "amg":
        if not amg_available():
            raise ImportError("linear solver 'amg' needs pyamg: pip install pyamg")
        return "amg"
    if name == "auto" and not os.environ.get("FEM3D_SOLVER", "").strip() and \
            n_free_dofs >= AMG_AUTO_MIN_FREE_DOFS and amg_available():
        return "amg"
    return _resolve_backend(name)


def available_backends() -> list[str]:
    """Back ends that can be used in this environment, in ``"auto"`` preference order."""
    return [b for b in BACKENDS if _backend_importable(b)]


def default_backend() -> str:
    """The back end ``"auto"`` resolves to (``FEM3D_SOLVER`` is honoured by the solver)."""
    return available_backends()[0]


def _resolve_backend(backend: str | None) -> str:
    env = os.environ.get("FEM3D_SOLVER", "").strip().lower()
    name = env or (backend or "auto").lower()
    if name == "auto":
        return default_backend()
    if name not in BACKENDS:
        src = "FEM3D_SOLVER" if env else "backend"
        raise ValueError(f"unknown sparse solver {name!r} ({src}); choose from auto, {BACKENDS}")
    if not _backend_importable(name):
        hint = {"cholmod": "pip install 'fem3d[cholmod]' (after the SuiteSparse headers: "
                           "sudo bash scripts/install_cholmod.sh)",
                "pardiso": "pip install pypardiso"}.get(name, "")
        src = " (FEM3D_SOLVER)" if env else ""
        raise ImportError(f"sparse solver back end {name!r}{src} is not installed: {hint}")
    return name


def _mapped_libraries() -> set[str]:
    """Paths of the shared libraries mapped into this process (Linux; else empty)."""
    try:
        with open("/proc/self/maps") as f:
            return {line.split()[-1] for line in f if "/" in line}
    except OSError:
        return set()


def loaded_blas() -> list[str]:
    """Paths of the BLAS/LAPACK shared libraries mapped into this process (Linux; else [])."""
    return sorted(p for p in _mapped_libraries()
                  if "blas" in os.path.basename(p) or "lapack" in p)


@functools.cache
def _openmp_runtimes() -> tuple[ctypes.CDLL, ...]:
    """The GNU OpenMP runtimes (``libgomp``) mapped into this process once CHOLMOD is loaded."""
    runtimes = []
    for path in sorted(p for p in _mapped_libraries() if "libgomp" in os.path.basename(p)):
        try:
            lib = ctypes.CDLL(path)
            lib.omp_get_max_active_levels.restype = ctypes.c_int
            lib.omp_set_max_active_levels.argtypes = [ctypes.c_int]
        except (OSError, AttributeError):
            continue
        runtimes.append(lib)
    return tuple(runtimes)


@contextlib.contextmanager
def _serial_openmp_regions() -> Iterator[None]:
    """Run the OpenMP parallel regions entered inside on one thread.

    CHOLMOD 3's supernodal code (Debian's ``libcholmod3``) opens a parallel region of a
    fixed 4 threads per supernode, whatever ``OMP_NUM_THREADS`` says; on a 2-core machine
    the threads wait for each other's cores at every supernode. Measured on the pile's 15k-DOF
    Newton matrix: 93 ms per factorization as shipped, 24 ms with those regions on one thread,
    the same bits (the loops in them are independent scatters; the BLAS keeps its own
    threads). A zero ``max-active-levels`` makes every region inactive: ``libgomp`` has no
    call that caps a ``num_threads`` clause (``OMP_THREAD_LIMIT`` is read once, at load).
    """
    runtimes = _openmp_runtimes()
    saved = [lib.omp_get_max_active_levels() for lib in runtimes]
    for lib in runtimes:
        lib.omp_set_max_active_levels(0)
    try:
        yield
    finally:
        for lib, levels in zip(runtimes, saved, strict=True):
            lib.omp_set_max_active_levels(levels)


@functools.cache
def _warn_reference_blas() -> None:
    """Warn once when CHOLMOD runs on Debian's reference BLAS (5-20x slower factorization)."""
    ref = [p for p in loaded_blas() if "/blas/libblas.so" in p]
    if ref:
        warnings.warn(
            f"CHOLMOD uses the reference BLAS ({ref[0]}): its supernodal factorization is "
            "5-20x slower than with OpenBLAS (apt-get install libopenblas0-pthread)",
            RuntimeWarning,
            stacklevel=4,
        )


def _as_csr(A: sp.spmatrix | sp.sparray) -> sp.csr_matrix:
    if not sp.issparse(A):
        raise TypeError(f"expected a scipy.sparse matrix, got {type(A).__name__}")
    if not (type(A) is sp.csr_matrix and A.dtype == np.float64):
        A = sp.csr_matrix(A, dtype=np.float64)
    # the same object when it is already a float64 CSR matrix: scipy caches its
    # canonical-format check on the object (an O(nnz) scan), so a Newton matrix that CG and
    # the factorization both see is scanned once
    if not A.has_canonical_format:
        A = A.copy()
        A.sum_duplicates()  # also sorts the indices
    return A


class SparseSPDSolver:
    """Cholesky-type solver for SPD matrices that share one sparsity pattern.

    Create it once per pattern (mesh + constraint set); it runs the fill-reducing symbolic
    analysis once. Then ``factorize(A)`` per matrix and ``solve(b)`` per right-hand side.

    Parameters
    ----------
    pattern : (n, n) scipy.sparse matrix
        A matrix with the sparsity pattern of every later ``A`` (its values are ignored). It must
        be structurally symmetric and hold the whole diagonal.
    backend : {"auto", "cholmod", "pardiso", "superlu"}, optional
        Overridden by the ``FEM3D_SOLVER`` environment variable when that is set.
    cholmod_mode : {"auto", "supernodal", "simplicial"}, optional
        CHOLMOD's factorization; ``"auto"`` (default) probes small patterns and takes
        simplicial when their factor is cheap per entry (see
        :data:`SIMPLICIAL_MAX_FLOPS_PER_ENTRY`), supernodal otherwise. Ignored by the other
        back ends.
    symmetric : bool, optional
        The caller vouches that ``pattern`` is structurally symmetric (a
        :class:`~fem3d.solve.system.System`'s patterns are, by construction), so it is not
        checked (4 ms of each of the pile's 292 analyses). Default False: checked.

    Attributes
    ----------
    backend : str
        The back end in use.
    n : int
        Matrix size.
    analyze_seconds, factor_seconds, solve_seconds : float
        Wall time of the analysis and of the last factorization and solve.
    shift : float
        The ``mu`` of the last :meth:`factorize_shifted` (0.0 after a plain ``factorize``).
    cholmod_mode : {"supernodal", "simplicial"} or None
        CHOLMOD's factorization (None for the other back ends).

    Examples
    --------
    >>> solver = SparseSPDSolver(A)            # analysis once
    >>> solver.factorize(A)                    # numeric factorization
    >>> x = solver.solve(b)
    """

    def __init__(self, pattern: sp.spmatrix | sp.sparray, backend: str | None = "auto",
                 *, cholmod_mode: str = "auto", symmetric: bool = False) -> None:
        if cholmod_mode not in ("auto", "supernodal", "simplicial"):
            raise ValueError(f"cholmod_mode must be 'auto', 'supernodal' or 'simplicial', got "
                             f"{cholmod_mode!r}")
        P = _as_csr(pattern)
        n, m = P.shape
        if n != m:
            raise ValueError(f"pattern must be square, got shape {P.shape}")
        self.n = n
        self.backend = _resolve_backend(backend)
        self._indptr = P.indptr.copy()
        self._indices = P.indices.copy()
        rows = np.repeat(np.arange(n), np.diff(P.indptr))
        diag_pos = np.flatnonzero(rows == P.indices)
        if len(diag_pos) != n:
            raise ValueError("pattern must contain every diagonal entry")
        if not symmetric:
            ones = sp.csr_matrix((np.ones(len(P.indices)), P.indices, P.indptr), shape=P.shape)
            if (ones != ones.T).nnz:
                raise ValueError("pattern must be structurally symmetric")
        self._rows = rows
        self._keys: np.ndarray | None = None
        self._diag_pos = diag_pos
        self._factored = False
        self.shift = 0.0
        self.factor_seconds = 0.0
        self.solve_seconds = 0.0
        self.cholmod_mode: str | None = cholmod_mode if self.backend == "cholmod" else None
        t0 = time.perf_counter()
        getattr(self, f"_analyze_{self.backend}")()
        self.analyze_seconds = time.perf_counter() - t0

    # ------------------------------------------------------------------ pattern handling
    def _data_on_pattern(self, A: sp.spmatrix | sp.sparray) -> np.ndarray:
        """Values of ``A`` in the order of the analysed pattern, (nnz,) float64."""
        A = _as_csr(A)
        if A.shape != (self.n, self.n):
            raise ValueError(f"matrix shape {A.shape} differs from the pattern's {(self.n,) * 2}")
        if np.array_equal(A.indptr, self._indptr) and np.array_equal(A.indices, self._indices):
            return A.data
        # A's pattern may be a subset (entries that cancelled, dropped zeros): embed it.
        a_rows = np.repeat(np.arange(self.n, dtype=np.int64), np.diff(A.indptr))
        keys = a_rows * self.n + A.indices
        if self._keys is None:
            self._keys = self._rows.astype(np.int64) * self.n + self._indices
        pos = np.searchsorted(self._keys, keys)
        pos = np.minimum(pos, len(self._keys) - 1)
        inside = self._keys[pos] == keys
        if not np.all(inside | (A.data == 0.0)):  # stored zeros outside are harmless
            raise ValueError("matrix has entries outside the sparsity pattern given to the solver")
        data = np.zeros(len(self._keys))
        data[pos[inside]] = A.data[inside]
        return data

    def _matrix(self, data: np.ndarray) -> sp.csr_matrix:
        return sp.csr_matrix((data, self._indices, self._indptr), shape=(self.n, self.n))

    # ------------------------------------------------------------------ public API
    def factorize(self, A: sp.spmatrix | sp.sparray) -> None:
        """Numeric factorization of ``A`` (same pattern as the one analysed).

        Parameters
        ----------
        A : (n, n) scipy.sparse matrix, symmetric

        Raises
        ------
        NotPositiveDefinite
            When ``A`` is not (numerically) positive definite. The previous factorization is
            no longer valid then.
        """
        data = self._data_on_pattern(A)
        self._factorize_data(data)
        self.shift = 0.0

    def _factorize_data(self, data: np.ndarray) -> None:
        if not np.all(np.isfinite(data)):
            self._factored = False
            raise NotPositiveDefinite("matrix has non-finite entries", backend=self.backend)
        t0 = time.perf_counter()
        self._factored = False
        getattr(self, f"_factor_{self.backend}")(data)
        self._factored = True
        self.factor_seconds = time.perf_counter() - t0

    def factorize_shifted(
        self,
        A: sp.spmatrix | sp.sparray,
        shift: np.ndarray | sp.spmatrix | sp.sparray | None = None,
        *,
        mu0: float = 1e-4,
        growth: float = 10.0,
        max_tries: int = 10,
        try_unshifted: bool = True,
    ) -> float:
        """Factorize ``A``, or ``A + mu S`` with the smallest ``mu`` in a geometric ladder.

        The rungs are ``mu0, mu0 * growth, ...`` (``max_tries`` of them), tried after ``A``
        itself (``try_unshifted``); the factorization kept is that of the smallest rung whose
        matrix is positive definite. With ``S = |diag(A)|`` (default) the shifted matrix tends
        to the positive diagonal as ``mu`` grows, so the ladder ends in an SPD matrix; the
        resulting solve is a damped (Levenberg-Marquardt-like) Newton direction, still a
        descent direction.

        The rungs are searched upward from ``mu0`` when the unshifted matrix was not tried
        (``mu0`` is a hint: the rung needed is usually ``mu0`` or the next one), and by
        bisection when it was tried and failed: then nothing is known of the rung needed, which
        an indefinite contact Hessian puts anywhere from ``1e-4`` to ``1e6`` (a failed attempt
        costs up to a whole factorization; bisection takes about ``log2(max_tries)`` of them
        where climbing takes as many as the rung's index). ``S`` is positive definite, so a
        rung above a positive-definite one is positive definite too: both searches find the
        same rung.

        Parameters
        ----------
        A : (n, n) scipy.sparse matrix, symmetric
        shift : (n,) float64 or (n, n) scipy.sparse matrix, optional
            ``S``: a diagonal (e.g. lumped mass) or an SPD matrix inside ``A``'s pattern (e.g.
            the consistent mass matrix). Default ``|diag(A)|``.
        mu0 : float
            First non-zero shift factor.
        growth : float
            Factor between successive shifts.
        max_tries : int
            Number of shifted attempts after the unshifted one.
        try_unshifted : bool
            Try ``mu = 0`` first (default). False when ``A`` is known to be indefinite (a
            failed attempt costs a whole factorization).

        Returns
        -------
        float
            The ``mu`` used (0.0 when ``A`` itself was positive definite); also ``self.shift``.

        Raises
        ------
        NotPositiveDefinite
            When even the largest shift fails.
        """
        data = self._data_on_pattern(A)
        if shift is None:
            s_data = np.zeros_like(data)
            s_data[self._diag_pos] = np.abs(data[self._diag_pos])
            if np.any(s_data[self._diag_pos] == 0.0):
                s_data[self._diag_pos] = np.maximum(
                    s_data[self._diag_pos], np.abs(data[self._diag_pos]).max() or 1.0
                )
        elif sp.issparse(shift):
            s_data = self._data_on_pattern(shift)
        else:
            s = np.asarray(shift, dtype=np.float64)
            if s.shape != (self.n,):
                raise ValueError(f"shift must be (n,) = ({self.n},) or sparse, got {s.shape}")
            s_data = np.zeros_like(data)
            s_data[self._diag_pos] = s
        rungs = [mu0 * growth**k for k in range(max_tries)]
        failures: list[NotPositiveDefinite] = []

        def attempt(mu: float) -> bool:
            try:
                self._factorize_data(data + mu * s_data if mu else data)
            except NotPositiveDefinite as err:
                failures.append(err)
                return False
            return True

        if try_unshifted and attempt(0.0):
            self.shift = 0.0
            return 0.0
        if try_unshifted:
            k = self._lowest_rung(rungs, attempt)
        else:
            k = next((i for i, mu in enumerate(rungs) if attempt(mu)), None)
        if k is None:
            raise NotPositiveDefinite(
                f"still not positive definite with shift mu = {rungs[-1] if rungs else 0.0:g} "
                f"({failures[-1] if failures else 'no shift tried'})",
                backend=self.backend,
            )
        self.shift = rungs[k]
        return rungs[k]

    def _lowest_rung(self, rungs: list[float], attempt: Callable[[float], bool]) -> int | None:
        """Bisection for the lowest rung whose attempt succeeds (None: not even the top one);
        leaves that rung's factorization in place."""
        lo, hi = 0, len(rungs)  # the rung needed is in [lo, hi]; hi: none found yet
        last_ok = False
        while lo < hi:
            mid = (lo + hi) // 2
            last_ok = attempt(rungs[mid])
            if last_ok:
                hi = mid
            else:
                lo = mid + 1
        if hi == len(rungs):
            return None
        if not last_ok:  # the last attempt was the rung below: factorize this one again
            if not attempt(rungs[hi]):
                raise NotPositiveDefinite(
                    f"shift mu = {rungs[hi]:g} was positive definite and is not now",
                    backend=self.backend)
        return hi

    def solve(self, b: np.ndarray) -> np.ndarray:
        """Solve ``A x = b`` with the last factorization.

        Parameters
        ----------
        b : (n,) or (n, k) float64

        Returns
        -------
        x : same shape as ``b``
        """
        if not self._factored:
            raise RuntimeError("factorize() must succeed before solve()")
        b = np.asarray(b, dtype=np.float64)
        if b.shape[0] != self.n:
            raise ValueError(f"right-hand side has {b.shape[0]} rows, matrix has {self.n}")
        t0 = time.perf_counter()
        x = getattr(self, f"_solve_{self.backend}")(b)
        self.solve_seconds = time.perf_counter() - t0
        return x

    __call__ = solve

    def as_linear_operator(self) -> spla.LinearOperator:
        """``A^{-1}`` of the current factorization as a LinearOperator (a preconditioner)."""
        return spla.LinearOperator((self.n, self.n), matvec=self.solve, dtype=np.float64)

    # ------------------------------------------------------------------ CHOLMOD
    def _csc_view(self, data: np.ndarray) -> sp.csc_matrix:
        # For a symmetric matrix the CSR arrays are also its CSC arrays.
        return sp.csc_matrix((data, self._indices, self._indptr), shape=(self.n, self.n))

    def _analyze_cholmod(self) -> None:
        from sksparse import cholmod  # optional (fem3d[cholmod]): imported when chosen

        _warn_reference_blas()
        self._cholmod = cholmod
        pattern = self._csc_view(np.ones(len(self._indices)))
        if self.cholmod_mode == "auto":
            cheap = self.n <= SIMPLICIAL_MAX_N and \
                self._factor_cost_per_entry() < SIMPLICIAL_MAX_FLOPS_PER_ENTRY
            self.cholmod_mode = "simplicial" if cheap else "supernodal"
        with _serial_openmp_regions():
            self._factor = cholmod.analyze(pattern, mode=self.cholmod_mode)

    def _factor_cost_per_entry(self) -> float:
        """Flops per entry of ``L`` (``sum c_j^2 / sum c_j``) for this pattern, from one
        simplicial factorization of a diagonally dominant matrix on it (``L``'s structure does
        not depend on the values)."""
        data = np.full(len(self._indices), -1.0)
        data[self._diag_pos] = np.diff(self._indptr)  # row count > |off-diagonal sum|: SPD
        with _serial_openmp_regions():
            probe = self._cholmod.analyze(self._csc_view(data), mode="simplicial")
            probe.cholesky_inplace(self._csc_view(data))
        counts = np.diff(probe.L().indptr).astype(np.float64)
        return float((counts * counts).sum() / counts.sum())

    def _factor_cholmod(self, data: np.ndarray) -> None:
        try:
            with _serial_openmp_regions():
                self._factor.cholesky_inplace(self._csc_view(data))
        except self._cholmod.CholmodNotPositiveDefiniteError as err:
            raise NotPositiveDefinite(str(err), backend="cholmod") from err
        if self.cholmod_mode == "simplicial":
            # simplicial CHOLMOD computes LDL^T, which exists for indefinite matrices too:
            # positive definite <=> every pivot of D is positive
            pivots = self._factor.D()
            if not np.all(pivots > 0.0):
                bad = int(np.count_nonzero(~(pivots > 0.0)))
                raise NotPositiveDefinite(
                    f"matrix not positive definite ({bad} non-positive pivots of LDL^T)",
                    backend="cholmod")

    def _solve_cholmod(self, b: np.ndarray) -> np.ndarray:
        with _serial_openmp_regions():
            return self._factor.solve_A(b)

    # ------------------------------------------------------------------ PARDISO
    def _analyze_pardiso(self) -> None:
        from pypardiso.pardiso_wrapper import PyPardisoError  # optional back end

        self._pardiso_error = PyPardisoError
        solver = _pardiso_solver()  # holds the MKL handle (pt) and iparm
        iparm = solver.iparm
        iparm[:] = 0
        iparm[0] = 1  # iparm given here, not defaults
        iparm[1] = 2  # METIS nested dissection ordering
        iparm[9] = 8  # pivot perturbation 1e-8 (only used by the indefinite types)
        iparm[17] = -1  # report nnz(L) in iparm[17]
        iparm[34] = 1  # zero-based ia/ja: no index conversion per call
        upper = self._indices >= self._rows
        self._upper = np.flatnonzero(upper)
        counts = np.bincount(self._rows[upper], minlength=self.n)
        self._ia = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)
        self._ja = self._indices[upper].astype(np.int32)
        self._pardiso = solver
        self._a_upper = np.ones(len(self._ja))
        self._pardiso_call(11, np.zeros((self.n, 1)))

    def _pardiso_call(self, phase: int, b: np.ndarray) -> np.ndarray:
        """One MKL ``pardiso`` call on the stored upper triangle (real SPD, ``mtype = 2``)."""
        import ctypes  # the optional PARDISO back end's calls only

        s = self._pardiso
        i32 = ctypes.c_int32
        i32p = ctypes.POINTER(i32)
        f64p = ctypes.POINTER(ctypes.c_double)
        b = np.asfortranarray(b, dtype=np.float64)
        x = np.zeros_like(b)
        err = i32(0)
        s._mkl_pardiso(
            s.pt.ctypes.data_as(ctypes.POINTER(s._pt_type[0])),
            ctypes.byref(i32(1)), ctypes.byref(i32(1)), ctypes.byref(i32(2)),
            ctypes.byref(i32(phase)), ctypes.byref(i32(self.n)),
            self._a_upper.ctypes.data_as(f64p), self._ia.ctypes.data_as(i32p),
            self._ja.ctypes.data_as(i32p), s.perm.ctypes.data_as(i32p),
            ctypes.byref(i32(b.shape[1])), s.iparm.ctypes.data_as(i32p), ctypes.byref(i32(0)),
            b.ctypes.data_as(f64p), x.ctypes.data_as(f64p), ctypes.byref(err),
        )
        if err.value != 0:
            # -4: zero pivot (for mtype 2: the matrix is not positive definite)
            if phase == 22 and err.value == -4:
                raise NotPositiveDefinite("PARDISO error -4 (zero or negative pivot)",
                                          backend="pardiso")
            raise RuntimeError(f"PARDISO phase {phase} failed with error {err.value}")
        return x

    def _factor_pardiso(self, data: np.ndarray) -> None:
        self._a_upper = np.ascontiguousarray(data[self._upper])
        self._pardiso_call(22, np.zeros((self.n, 1)))

    def _solve_pardiso(self, b: np.ndarray) -> np.ndarray:
        x = self._pardiso_call(33, b.reshape(self.n, -1))
        return np.ascontiguousarray(x).reshape(b.shape)

    def __del__(self) -> None:
        # release PARDISO's internal memory (phase -1)
        if getattr(self, "_pardiso", None) is not None:
            try:
                self._pardiso_call(-1, np.zeros((self.n, 1)))
            except Exception:  # noqa: BLE001 - interpreter shutdown
                pass

    # ------------------------------------------------------------------ SuperLU
    def _analyze_superlu(self) -> None:
        # SuperLU cannot order without factorizing: the first factorization orders (MMD on
        # A^T + A, pattern only) and records the permutation; later ones reuse it.
        self._perm = None
        self._lu_permuted = False

    def _set_superlu_ordering(self, perm_c: np.ndarray) -> None:
        # SuperLU moves column j to position perm_c[j]: the new order lists argsort(perm_c).
        perm = np.argsort(np.asarray(perm_c))
        self._perm = perm
        self._iperm = np.asarray(perm_c)
        # Position map: data of P A P^T (CSC, canonical) = data[self._pmap]
        nnz = len(self._indices)
        tagged = self._matrix(np.arange(1, nnz + 1, dtype=np.float64))
        PAPt = tagged[perm][:, perm].tocsc()
        PAPt.sort_indices()
        self._p_indptr, self._p_indices = PAPt.indptr, PAPt.indices
        self._pmap = PAPt.data.astype(np.int64) - 1

    def _factor_superlu(self, data: np.ndarray) -> None:
        first = self._perm is None
        if first:
            Ap = self._csc_view(data)  # symmetric: CSR arrays are the CSC arrays
        else:
            Ap = sp.csc_matrix(
                (data[self._pmap], self._p_indices, self._p_indptr), shape=(self.n, self.n)
            )
        try:
            lu = spla.splu(
                Ap,
                permc_spec="MMD_AT_PLUS_A" if first else "NATURAL",
                diag_pivot_thresh=0.0,
                options={"SymmetricMode": True},
            )
        except RuntimeError as err:  # "Factor is exactly singular"
            raise NotPositiveDefinite(str(err), backend="superlu") from err
        if first:
            self._set_superlu_ordering(lu.perm_c)  # depends on the pattern only
        # With diagonal pivoting the pivots are the D of A = L D L^T: SPD <=> all > 0.
        d = lu.U.diagonal()
        if not np.array_equal(lu.perm_r, lu.perm_c) or not np.all(d > 0):
            raise NotPositiveDefinite(
                f"{int(np.sum(d <= 0))} non-positive pivot(s)", backend="superlu"
            )
        self._lu = lu
        self._lu_permuted = not first

    def _solve_superlu(self, b: np.ndarray) -> np.ndarray:
        if not self._lu_permuted:
            return self._lu.solve(b)
        return self._lu.solve(b[self._perm])[self._iperm]
