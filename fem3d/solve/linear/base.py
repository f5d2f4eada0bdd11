"""The linear-solver seam: what every solver of the Newton systems offers, and the direct
solvers' shared part.

A solver goes through three phases (:class:`LinearSolver`): :meth:`~LinearSolver.analyse` once
per sparsity pattern (fill-reducing ordering, elimination tree, AMG aggregates),
:meth:`~LinearSolver.factorize` per matrix (numeric factorization, AMG hierarchy; raises
:class:`NotPositiveDefinite` where it applies) and :meth:`~LinearSolver.solve` per right-hand
side; :attr:`~LinearSolver.report` says what the last phases did (:class:`SolveReport`).
:class:`DirectSolver` holds what CHOLMOD, PARDISO and SuperLU share: the analysed pattern,
matrices embedded into it, the shifted-retry ladder (:meth:`DirectSolver.factorize_shifted`)
and the timings; each back end supplies ``_analyse``, ``_factor`` and ``_solve``.
The registry of solvers by name is :mod:`fem3d.solve.linear.registry`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar, Protocol, runtime_checkable

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from fem3d.errors import Fem3dError

__all__ = ["DirectSolver", "IterativeSolver", "LinearSolver", "NotPositiveDefinite", "SolveReport",
           "SolverOptions", "as_csr"]


class NotPositiveDefinite(Fem3dError, np.linalg.LinAlgError):
    """The matrix handed to a Cholesky-type factorization is not positive definite.

    Parameters
    ----------
    message : str
        What failed.
    backend : str
        The solver that detected it.
    """

    def __init__(self, message: str, *, backend: str) -> None:
        self.backend = backend
        super().__init__(f"{backend}: {message}")


@dataclass(frozen=True)
class SolveReport:
    """What a solver's last phases did (:attr:`LinearSolver.report`).

    Attributes
    ----------
    backend : str
        The solver's registry name.
    iterations : int
        Krylov iterations of the last solve (0 for a direct solve).
    residual : float
        Relative residual ``|b - A x| / |b|`` of the last iterative solve; NaN for a direct
        solve (not computed: a factorization solves to round-off).
    converged : bool
        The last solve reached its tolerance (always True for a direct one).
    negative_curvature : bool
        An iterative solve stopped on ``p^T A p <= 0``: the matrix is not positive definite.
    shift : float
        The ``mu`` of the last factorization of ``A + mu S`` (0.0: ``A`` itself).
    analyse_seconds, factorize_seconds, solve_seconds : float
        Wall time of the last analysis, factorization (or AMG setup) and solve.
    """

    backend: str
    iterations: int = 0
    residual: float = float("nan")
    converged: bool = True
    negative_curvature: bool = False
    shift: float = 0.0
    analyse_seconds: float = 0.0
    factorize_seconds: float = 0.0
    solve_seconds: float = 0.0


@dataclass(frozen=True)
class SolverOptions:
    """What a solver may need to know beyond the matrices; each takes what applies to it.

    Attributes
    ----------
    cholmod_mode : {"auto", "supernodal", "simplicial"}
        CHOLMOD's factorization (:class:`fem3d.solve.linear.cholmod.CholmodSolver`).
    points : (n / 3, 3) float64 or None
        Rest positions of the vertices whose 3 DOFs are the unknowns, in order (AMG's
        near-nullspace: their rigid-body modes).
    petsc_options : str
        PETSc options of the ``"petsc"`` solver (``"-ksp_type cg -pc_type gamg"``;
        :mod:`fem3d.solve.linear.petsc`).
    """

    cholmod_mode: str = "auto"
    points: np.ndarray | None = None
    petsc_options: str = ""


@runtime_checkable
class LinearSolver(Protocol):
    """A solver of ``A x = b`` for symmetric positive-definite ``A`` of one sparsity pattern.

    Implementations are registered by name
    (:func:`~fem3d.solve.linear.registry.register_linear_solver`) and made by
    :func:`~fem3d.solve.linear.registry.make_linear_solver` with :class:`SolverOptions`.
    Class attributes: ``name`` (the registry name), ``iterative`` (a Krylov solver:
    :meth:`solve` takes the operator and a tolerance), ``auto_min_free_dofs`` (``"auto"``
    takes the solver from this many unknowns; the direct ones from 0).
    """

    name: ClassVar[str]
    iterative: ClassVar[bool]
    auto_min_free_dofs: ClassVar[int]

    @classmethod
    def available(cls) -> bool:
        """Whether its library imports here."""

    def analyse(self, pattern: sp.spmatrix | sp.sparray, *, symmetric: bool = False) -> None:
        """Symbolic work for ``pattern`` (its values are ignored); once per pattern."""

    def factorize(self, A: sp.spmatrix | sp.sparray) -> None:
        """Numeric work for ``A`` on the analysed pattern (may raise NotPositiveDefinite)."""

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``x`` with ``A x = b`` for the last factorized ``A``."""

    @property
    def report(self) -> SolveReport:
        """What the last analysis, factorization and solve did."""


@runtime_checkable
class IterativeSolver(LinearSolver, Protocol):
    """A Krylov solver: ``factorize`` builds a preconditioner that later matrices of the pattern
    reuse while it pays; ``solve`` takes the operator and the tolerance of each solve.

    Attributes
    ----------
    ready : bool
        A preconditioner exists.
    pattern_key : object
        What the last ``factorize`` was given as ``pattern_key`` (a pattern generation).
    """

    ready: bool
    pattern_key: object

    def factorize(self, A: sp.spmatrix | sp.sparray, *, pattern_key: object = None) -> None:
        """Build the preconditioner of ``A``."""

    def solve(self, b: np.ndarray, *, A: sp.spmatrix | sp.sparray | None = None,
              rtol: float | None = None, maxiter: int | None = None) -> np.ndarray:
        """``x`` with ``|b - A x| <= rtol |b|`` (``A``: default the matrix factorized)."""


def as_csr(A: sp.spmatrix | sp.sparray) -> sp.csr_matrix:
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



class DirectSolver:
    """What the sparse direct solvers share: the analysed pattern, the shift ladder, timings.

    Make one with :func:`~fem3d.solve.linear.registry.make_linear_solver` (or the back end's
    class), :meth:`analyse` it once per pattern (mesh + constraint set), then
    ``factorize(A)`` per matrix and ``solve(b)`` per right-hand side. Subclasses supply
    ``_analyse()``, ``_factor(data)`` (``data``: ``A``'s values in the pattern's CSR order)
    and ``_solve(b)``.

    Parameters
    ----------
    options : SolverOptions, optional

    Attributes
    ----------
    n : int
        Matrix size.
    analyze_seconds, factor_seconds, solve_seconds : float
        Wall time of the analysis and of the last factorization and solve.
    shift : float
        The ``mu`` of the last :meth:`factorize_shifted` (0.0 after a plain ``factorize``).

    Examples
    --------
    >>> solver = make_linear_solver("cholmod")
    >>> solver.analyse(A)                      # analysis once per pattern
    >>> solver.factorize(A)                    # numeric factorization
    >>> x = solver.solve(b)
    """

    name: ClassVar[str] = ""
    iterative: ClassVar[bool] = False
    auto_min_free_dofs: ClassVar[int] = 0
    #: How to install the library (the error when it is missing).
    install_hint: ClassVar[str] = ""

    def __init__(self, options: SolverOptions | None = None) -> None:
        self.options = options or SolverOptions()
        self.n = 0
        #: The pattern is one rank's part of a distributed matrix (rows of other ranks'
        #: vertices may lack their diagonal entry): not checked for a whole diagonal.
        self.partial = False
        self._factored = False
        self.shift = 0.0
        self.analyze_seconds = 0.0
        self.factor_seconds = 0.0
        self.solve_seconds = 0.0

    @classmethod
    def available(cls) -> bool:
        """Whether the back end's library imports here."""
        return True

    @property
    def backend(self) -> str:
        """The registry name (what :class:`NotPositiveDefinite` and reports name)."""
        return self.name

    @property
    def report(self) -> SolveReport:
        """The last analysis, factorization and solve (:class:`SolveReport`)."""
        return SolveReport(self.name, shift=self.shift, analyse_seconds=self.analyze_seconds,
                           factorize_seconds=self.factor_seconds,
                           solve_seconds=self.solve_seconds)

    def analyse(self, pattern: sp.spmatrix | sp.sparray, *, symmetric: bool = False) -> None:
        """The symbolic analysis of ``pattern`` (drops any factorization of an older one).

        Parameters
        ----------
        pattern : (n, n) scipy.sparse matrix
            A matrix with the sparsity pattern of every later ``A`` (its values are ignored).
            It must be structurally symmetric and hold the whole diagonal.
        symmetric : bool, optional
            The caller vouches that ``pattern`` is structurally symmetric (a
            :class:`~fem3d.solve.system.System`'s patterns are, by construction), so it is not
            checked (4 ms of each of the pile's 292 analyses). Default False: checked.
        """
        P = as_csr(pattern)
        n, m = P.shape
        if n != m:
            raise ValueError(f"pattern must be square, got shape {P.shape}")
        self.n = n
        self._indptr = P.indptr.copy()
        self._indices = P.indices.copy()
        rows = np.repeat(np.arange(n), np.diff(P.indptr))
        diag_pos = np.flatnonzero(rows == P.indices)
        if len(diag_pos) != n and not self.partial:
            raise ValueError("pattern must contain every diagonal entry")
        if not symmetric:
            ones = sp.csr_matrix((np.ones(len(P.indices)), P.indices, P.indptr), shape=P.shape)
            if (ones != ones.T).nnz:
                raise ValueError("pattern must be structurally symmetric")
        # each entry's row (a solver may let it go after its analysis: then remade if needed)
        self._rows: np.ndarray | None = rows
        self._keys: np.ndarray | None = None
        self._diag_pos = diag_pos
        self._factored = False
        self.shift = 0.0
        self.factor_seconds = 0.0
        self.solve_seconds = 0.0
        t0 = time.perf_counter()
        self._analyse()
        self.analyze_seconds = time.perf_counter() - t0

    def _analyse(self) -> None:
        raise NotImplementedError

    def _factor(self, data: np.ndarray) -> None:
        raise NotImplementedError

    def _solve(self, b: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def _csc_view(self, data: np.ndarray) -> sp.csc_matrix:
        # For a symmetric matrix the CSR arrays are also its CSC arrays.
        return sp.csc_matrix((data, self._indices, self._indptr), shape=(self.n, self.n))

    def _data_on_pattern(self, A: sp.spmatrix | sp.sparray) -> np.ndarray:
        """Values of ``A`` in the order of the analysed pattern, (nnz,) float64."""
        A = as_csr(A)
        if A.shape != (self.n, self.n):
            raise ValueError(f"matrix shape {A.shape} differs from the pattern's {(self.n,) * 2}")
        if np.array_equal(A.indptr, self._indptr) and np.array_equal(A.indices, self._indices):
            return A.data
        # A's pattern may be a subset (entries that cancelled, dropped zeros): embed it.
        a_rows = np.repeat(np.arange(self.n, dtype=np.int64), np.diff(A.indptr))
        keys = a_rows * self.n + A.indices
        if self._keys is None:
            rows = self._rows if self._rows is not None else \
                np.repeat(np.arange(self.n, dtype=np.int64), np.diff(self._indptr))
            self._keys = rows.astype(np.int64) * self.n + self._indices
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
            raise NotPositiveDefinite("matrix has non-finite entries", backend=self.name)
        t0 = time.perf_counter()
        self._factored = False
        self._factor(data)
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
                backend=self.name,
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
                    backend=self.name)
        return hi

    def release(self) -> None:
        """The caller is done solving with the last factorization: the back end may let go
        of what only solves read (PETSc's GAMG hierarchy, :meth:`_release`) before the next
        :meth:`factorize`. A :meth:`solve` before that raises. What the next factorization
        starts from (CHOLMOD's factor object, MUMPS' analysis) is kept.
        """
        self._factored = False
        self._release()

    def _release(self) -> None:
        """What a back end frees on :meth:`release` (default: nothing)."""

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
            raise RuntimeError(f"{self.name}: no factorization to solve with (factorize() "
                               "must succeed before solve(), and again after release())")
        b = np.asarray(b, dtype=np.float64)
        if b.shape[0] != self.n:
            raise ValueError(f"right-hand side has {b.shape[0]} rows, matrix has {self.n}")
        t0 = time.perf_counter()
        x = self._solve(b)
        self.solve_seconds = time.perf_counter() - t0
        return x

    __call__ = solve

    def as_linear_operator(self) -> spla.LinearOperator:
        """``A^{-1}`` of the current factorization as a LinearOperator (a preconditioner)."""
        return spla.LinearOperator((self.n, self.n), matvec=self.solve, dtype=np.float64)

