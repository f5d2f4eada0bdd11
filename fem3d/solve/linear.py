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

:class:`PreconditionedCG` keeps one factorization and uses it as the preconditioner of conjugate
gradients on later matrices of the same pattern (the Hessian changes little between Newton
iterations or time steps); it reports iterations and says when CG stalls so the caller
refactorizes.
"""

from __future__ import annotations

import functools
import math
import os
import time
import warnings
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from fem3d.errors import Fem3dError

__all__ = [
    "AMG_AUTO_MIN_FREE_DOFS",
    "AMGPreconditioner",
    "BACKENDS",
    "CGResult",
    "NotPositiveDefinite",
    "PreconditionedCG",
    "SparseSPDSolver",
    "available_backends",
    "default_backend",
    "loaded_blas",
    "amg_available",
    "choose_backend",
    "iterations_per_decade",
    "rigid_body_modes",
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
    import pypardiso

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
        hint = {"cholmod": "pip install scikit-sparse (needs SuiteSparse headers)",
                "pardiso": "pip install pypardiso"}.get(name, "")
        raise ImportError(f"sparse solver back end {name!r} is not installed: {hint}")
    return name


def loaded_blas() -> list[str]:
    """Paths of the BLAS/LAPACK shared libraries mapped into this process (Linux; else [])."""
    try:
        with open("/proc/self/maps") as f:
            paths = {line.split()[-1] for line in f if "/" in line}
    except OSError:
        return []
    return sorted(p for p in paths if "blas" in os.path.basename(p) or "lapack" in p)


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
    A = sp.csr_matrix(A, dtype=np.float64)
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
                 *, cholmod_mode: str = "auto") -> None:
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

        Tries ``mu = 0, mu0, mu0 * growth, ...`` (``max_tries`` shifted attempts) and keeps the
        first positive-definite one. With ``S = |diag(A)|`` (default) the shifted matrix tends to
        the positive diagonal as ``mu`` grows, so the ladder ends in an SPD matrix; the resulting
        solve is a damped (Levenberg-Marquardt-like) Newton direction, still a descent direction.

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
        last: NotPositiveDefinite | None = None
        mus = [0.0] * try_unshifted + [mu0 * growth**k for k in range(max_tries)]
        for mu in mus:
            try:
                self._factorize_data(data + mu * s_data if mu else data)
            except NotPositiveDefinite as err:
                last = err
                continue
            self.shift = mu
            return mu
        raise NotPositiveDefinite(
            f"still not positive definite with shift mu = {mus[-1]:g} ({last})",
            backend=self.backend,
        )

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
        from sksparse import cholmod

        _warn_reference_blas()
        self._cholmod = cholmod
        pattern = self._csc_view(np.ones(len(self._indices)))
        if self.cholmod_mode == "auto":
            cheap = self.n <= SIMPLICIAL_MAX_N and \
                self._factor_cost_per_entry() < SIMPLICIAL_MAX_FLOPS_PER_ENTRY
            self.cholmod_mode = "simplicial" if cheap else "supernodal"
        self._factor = cholmod.analyze(pattern, mode=self.cholmod_mode)

    def _factor_cost_per_entry(self) -> float:
        """Flops per entry of ``L`` (``sum c_j^2 / sum c_j``) for this pattern, from one
        simplicial factorization of a diagonally dominant matrix on it (``L``'s structure does
        not depend on the values)."""
        data = np.full(len(self._indices), -1.0)
        data[self._diag_pos] = np.diff(self._indptr)  # row count > |off-diagonal sum|: SPD
        probe = self._cholmod.analyze(self._csc_view(data), mode="simplicial")
        probe.cholesky_inplace(self._csc_view(data))
        counts = np.diff(probe.L().indptr).astype(np.float64)
        return float((counts * counts).sum() / counts.sum())

    def _factor_cholmod(self, data: np.ndarray) -> None:
        try:
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
        return self._factor.solve_A(b)

    # ------------------------------------------------------------------ PARDISO
    def _analyze_pardiso(self) -> None:
        from pypardiso.pardiso_wrapper import PyPardisoError

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
        import ctypes

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


@dataclass(frozen=True)
class CGResult:
    """Outcome of :meth:`PreconditionedCG.solve`.

    Attributes
    ----------
    x : (n,) float64
        The solution (the direct solution when ``refactorized``).
    iterations : int
        CG iterations run (0 when solved directly).
    residual : float
        Final relative residual ``|b - A x| / |b|``.
    converged : bool
        CG reached ``rtol`` (or the direct solve was used).
    stalled : bool
        CG failed: not converged within ``maxiter``, too slow a residual decrease, or a
        non-positive curvature ``p^T A p`` (``A`` indefinite). The caller should refactorize.
    negative_curvature : bool
        CG stopped on ``p^T A p <= 0``: ``A`` is not positive definite.
    refactorized : bool
        The solver refactorized ``A`` and solved directly (``refactorize_on_stall=True``).
    """

    x: np.ndarray
    iterations: int
    residual: float
    converged: bool
    stalled: bool
    refactorized: bool
    negative_curvature: bool = False


class PreconditionedCG:
    """Conjugate gradients preconditioned by an older factorization of the same pattern.

    Newton iterations and neighbouring time steps produce matrices that differ little; a
    Cholesky factor of one of them is an excellent preconditioner for the others, so a few CG
    iterations (each one sparse mat-vec plus two triangular solves) replace a refactorization.

    The CG loop is written out (rather than calling ``scipy.sparse.linalg.cg``) to see the
    residual and the curvature ``p^T A p`` at every iteration: a non-positive curvature means
    ``A`` is indefinite, which the Newton solver must know about.

    Parameters
    ----------
    solver : SparseSPDSolver
        Holds (or will hold) the factorization used as preconditioner.
    rtol : float
        Relative residual target ``|b - A x| <= rtol |b|``.
    maxiter : int
        CG iterations before giving up (a good preconditioner needs a handful).
    stall_window, stall_factor : int, float
        Stalled when the residual has not dropped by ``stall_factor`` over ``stall_window``
        iterations.
    refactorize_on_stall : bool
        When CG stalls, refactorize the current ``A`` (it becomes the new preconditioner) and
        return the direct solution; otherwise return the CG iterate with ``stalled=True``.
    """

    def __init__(
        self,
        solver: SparseSPDSolver,
        *,
        rtol: float = 1e-8,
        maxiter: int = 50,
        stall_window: int = 10,
        stall_factor: float = 0.5,
        refactorize_on_stall: bool = True,
    ) -> None:
        self.solver = solver
        self.rtol = rtol
        self.maxiter = maxiter
        self.stall_window = stall_window
        self.stall_factor = stall_factor
        self.refactorize_on_stall = refactorize_on_stall
        self.n_refactorizations = 0

    def refactorize(self, A: sp.spmatrix | sp.sparray) -> None:
        """Make ``A``'s factorization the preconditioner (may raise NotPositiveDefinite)."""
        self.solver.factorize(A)
        self.n_refactorizations += 1

    def solve(
        self, A: sp.spmatrix | sp.sparray, b: np.ndarray, x0: np.ndarray | None = None
    ) -> CGResult:
        """Solve ``A x = b`` by preconditioned CG.

        Parameters
        ----------
        A : (n, n) scipy.sparse matrix, symmetric, same pattern as the solver's
        b : (n,) float64
        x0 : (n,) float64, optional
            Initial guess (default: the preconditioner's solution ``M^{-1} b``).

        Returns
        -------
        CGResult
        """
        if not self.solver._factored:
            self.refactorize(A)
        b = np.asarray(b, dtype=np.float64)
        A = _as_csr(A)
        bnorm = float(np.linalg.norm(b))
        if bnorm == 0.0:
            return CGResult(np.zeros_like(b), 0, 0.0, True, False, False)
        x = self.solver.solve(b) if x0 is None else np.array(x0, dtype=np.float64)
        r = b - A @ x
        history = [float(np.linalg.norm(r)) / bnorm]
        it = 0
        stalled = negative = False
        p: np.ndarray | None = None
        rz = 0.0
        while history[-1] > self.rtol:
            if it >= self.maxiter:
                stalled = True
                break
            # preconditioning only when another iteration follows (a solve is the costly part)
            z = self.solver.solve(r)
            rz_new = float(r @ z)
            p = z if p is None else z + (rz_new / rz) * p
            rz = rz_new
            Ap = A @ p
            curv = float(p @ Ap)
            if not curv > 0.0:  # indefinite A (or NaN)
                stalled = negative = True
                break
            alpha = rz / curv
            x += alpha * p
            r -= alpha * Ap
            it += 1
            history.append(float(np.linalg.norm(r)) / bnorm)
            w = self.stall_window
            if len(history) > w and history[-1] > self.stall_factor * history[-1 - w]:
                stalled = True
                break
        if stalled and self.refactorize_on_stall:
            self.refactorize(A)
            x = self.solver.solve(b)
            res = float(np.linalg.norm(b - A @ x)) / bnorm
            return CGResult(x, it, res, True, True, True, negative)
        return CGResult(x, it, history[-1], not stalled, stalled, False, negative)


# ---------------------------------------------------------------------------------------------
# algebraic multigrid


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
AMG_OPTIONS: dict = dict(max_coarse=500, max_levels=10, omega=4.0 / 3.0, rho_iterations=6)


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


def _block_inverses(A: sp.bsr_matrix) -> np.ndarray:
    """``(nb, k, k)`` inverses of the diagonal blocks of a square-blocked BSR matrix:
    pseudo-inverses where a block is singular (coarse levels: a candidate dropped in an
    aggregate leaves a zero row and column). 3x3 blocks by their adjugates (vectorized)."""
    from pyamg import amg_core

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


def _spectral_radius(A: sp.bsr_matrix, Dinv: np.ndarray, iterations: int) -> float:
    """Largest eigenvalue of ``D^-1 A`` (Arnoldi from a fixed start vector)."""
    n = A.shape[0]
    Dinv = _block_diagonal(Dinv)
    v = np.random.default_rng(12345).random(n)
    V = [v / np.linalg.norm(v)]
    H = np.zeros((iterations + 1, iterations))
    m = iterations
    for j in range(iterations):
        w = Dinv @ (A @ V[j])
        for i in range(j + 1):
            H[i, j] = float(w @ V[i])
            w -= H[i, j] * V[i]
        H[j + 1, j] = float(np.linalg.norm(w))
        if H[j + 1, j] <= 1e-12 * abs(H[j, j]):
            m = j + 1
            break
        V.append(w / H[j + 1, j])
    return float(np.abs(np.linalg.eigvals(H[:m, :m])).max())


class AMGPreconditioner:
    """Smoothed-aggregation AMG V-cycles preconditioning conjugate gradients.

    Two phases, like a direct solver's: :meth:`analyze` aggregates the vertices of a sparsity
    pattern (once per pattern: the strength of connection keeps every block, so the
    aggregates, the tentative prolongators and the coarse near-nullspace depend on the
    pattern and the rigid-body modes alone); :meth:`setup` builds the numeric hierarchy of one
    matrix (smoothed prolongators, Galerkin coarse matrices, smoother data, coarsest
    factorization), reused for later matrices of the same pattern (Newton iterations, time
    steps) until the caller decides it has aged (:func:`iterations_per_decade` of the last
    solve above its budget). pyamg provides the aggregation, the candidate fitting and the
    block Gauss-Seidel kernel.

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
    """

    def __init__(self, near_nullspace: np.ndarray, options: dict | None = None) -> None:
        self.B = np.asarray(near_nullspace, dtype=np.float64)
        unknown = set(options or {}) - set(AMG_OPTIONS)
        if unknown:
            raise ValueError(f"unknown AMG options {sorted(unknown)}; known: "
                             f"{sorted(AMG_OPTIONS)}")
        self.options = AMG_OPTIONS | dict(options or {})
        self._plan: _AMGPlan | None = None
        self._levels: list[_AMGLevel] = []
        self._coarse: tuple | None = None
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
        from pyamg.aggregation.aggregate import standard_aggregation
        from pyamg.aggregation.tentative import fit_candidates

        t0 = time.perf_counter()
        P = _as_csr(pattern)
        n = P.shape[0]
        if n % 3 or P.shape != (n, n):
            raise ValueError("AMG needs a square matrix of whole 3-DOF vertices")
        if self.B.shape[0] != n:
            raise ValueError(f"near-nullspace has {self.B.shape[0]} rows, the matrix {n}")
        bsr_indptr, bsr_indices, slot = _block_pattern(P.indptr, P.indices, n)
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
        A = _as_csr(A)
        if not self._planned(A):
            self.analyze(A)
        plan = self._plan
        n = A.shape[0]
        data = np.zeros(plan.bsr_indices.size * 9)
        data[plan.bsr_slot] = A.data
        Al = sp.bsr_matrix((data.reshape(-1, 3, 3), plan.bsr_indices, plan.bsr_indptr),
                           shape=(n, n))
        omega, iters = self.options["omega"], self.options["rho_iterations"]
        levels = []
        for T in plan.T:
            Dinv = _block_inverses(Al)
            rho = _spectral_radius(Al, Dinv, iters)
            P = T - (omega / rho) * _block_rows_times(Dinv, Al @ T)
            P = sp.bsr_matrix(P, blocksize=T.blocksize)
            R = sp.bsr_matrix(P.T)
            Ac = sp.bsr_matrix(R @ (Al @ P))  # (the product A P is the largest transient)
            Ac.sort_indices()
            levels.append(_AMGLevel.make(Al, Dinv, P, R))
            Al = Ac
        Ac = Al.toarray()
        Ac = 0.5 * (Ac + Ac.T)
        try:
            self._coarse = ("cholesky", scipy.linalg.cho_factor(Ac, lower=True))
        except np.linalg.LinAlgError:  # not positive definite: a symmetric pseudo-inverse
            self._coarse = ("pinv", scipy.linalg.pinvh(Ac))
        self._levels = levels
        self.level_sizes = [lvl.P.shape[0] for lvl in levels] + [Ac.shape[0]]
        self.pattern_key = pattern_key
        self.setups += 1
        self.setup_seconds += time.perf_counter() - t0

    def _coarse_solve(self, b: np.ndarray) -> np.ndarray:
        kind, f = self._coarse
        return scipy.linalg.cho_solve(f, b) if kind == "cholesky" else f @ b

    def apply(self, b: np.ndarray) -> np.ndarray:
        """One V-cycle from zero on ``A x = b`` (``A`` the setup matrix): ``x ~ A^-1 b``,
        symmetric positive definite when ``A`` is."""
        from pyamg import amg_core

        if self._coarse is None:
            raise RuntimeError("setup() must run before apply()")
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
        A = _as_csr(A)
        b = np.asarray(b, dtype=np.float64)
        bnorm = float(np.linalg.norm(b))
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
            rz_new = float(r @ z)
            if not rz_new > 0.0:  # the V-cycle is not SPD (hierarchy of an indefinite matrix)
                negative = stalled = True
                break
            if p is None:
                p = z
            else:
                p *= rz_new / rz
                p += z
            rz = rz_new
            Ap = A @ p
            curv = float(p @ Ap)
            if not curv > 0.0:
                negative = stalled = True
                break
            alpha = rz / curv
            x += alpha * p
            r -= alpha * Ap
            it += 1
            res = float(np.linalg.norm(r)) / bnorm
        self.iterations += it
        self.cg_seconds += time.perf_counter() - t0
        return CGResult(x, it, res, not stalled, stalled, False, negative)


def iterations_per_decade(result: CGResult) -> float:
    """CG iterations per factor 10 of residual reduction (``inf`` when it did not reduce)."""
    if result.iterations == 0:
        return 0.0
    if not 0.0 < result.residual < 1.0:
        return math.inf
    return result.iterations / -math.log10(result.residual)
