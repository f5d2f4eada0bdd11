"""Conjugate gradients preconditioned by smoothed-aggregation AMG V-cycles, the ``"amg"`` solver.

The iterative solver of the seam (:class:`fem3d.solve.linear.base.LinearSolver`): ``analyse``
aggregates the pattern's vertices (once per pattern), ``factorize`` builds the numeric
hierarchy of one matrix, ``solve`` runs CG on the operator it is given (a later Newton matrix
of the same pattern: a hierarchy is kept while it still pays) to a relative tolerance. The
hierarchy itself is :class:`fem3d.solve.linear.amg.AMGPreconditioner`.
"""

from __future__ import annotations

import functools
import time
from typing import ClassVar

import numpy as np
import scipy.sparse as sp

from fem3d.solve.linear.amg import AMGPreconditioner, rigid_body_modes
from fem3d.solve.linear.base import SolveReport, SolverOptions
from fem3d.solve.linear.krylov import CGResult

__all__ = ["AMG_AUTO_MIN_FREE_DOFS", "AMGCGSolver"]

#: ``"auto"`` takes AMG-preconditioned CG (``"amg"``) for Newton systems with at least this many
#: free DOFs, a direct factorization below. Measured with ``python -m bench.newton_step --mesh
#: box --tets N --steps 3 --swing 4 --modes direct,reuse,amg`` (one thread, the project's
#: shared 2-core machine, load ~10; speed-ups over refactorizing every Newton iteration):
#: 882 free DOFs: amg 1.9x, reuse 3.7x; 2,700: amg 1.4x, reuse 1.1x; 6,084: amg 2.3x, reuse
#: 2.8x; 16,524: amg 4.7x, reuse 2.6x. AMG beats both direct modes from about 1e4 free DOFs.
AMG_AUTO_MIN_FREE_DOFS = 10000


class AMGCGSolver:
    """AMG-preconditioned conjugate gradients (``"amg"``).

    Parameters
    ----------
    options : SolverOptions
        ``points``: the rest positions of the vertices whose DOFs are the unknowns (the
        near-nullspace is their rigid-body modes, so a hierarchy depends on its matrix alone).
    rtol : float
        Default relative residual of :meth:`solve`.
    maxiter : int
        Default CG iteration limit of :meth:`solve`.

    Attributes
    ----------
    hierarchy : AMGPreconditioner
        The aggregation and the numeric hierarchy.
    pattern_key : object
        What the caller passed to the last :meth:`factorize` (a pattern generation).
    last : CGResult or None
        The last solve's outcome.
    """

    name: ClassVar[str] = "amg"
    iterative: ClassVar[bool] = True
    auto_min_free_dofs: ClassVar[int] = AMG_AUTO_MIN_FREE_DOFS
    install_hint: ClassVar[str] = "pip install pyamg"

    def __init__(self, options: SolverOptions | None = None, *, rtol: float = 1e-8,
                 maxiter: int = 200) -> None:
        options = options or SolverOptions()
        if options.points is None:
            raise ValueError("the 'amg' linear solver needs the unknowns' vertex positions "
                             "(SolverOptions.points)")
        self.options = options
        self.hierarchy = AMGPreconditioner(rigid_body_modes(options.points))
        self.rtol = rtol
        self.maxiter = maxiter
        self.pattern_key: object = None
        self.last: CGResult | None = None
        self._A: sp.csr_matrix | None = None
        self._factorize_seconds = 0.0
        self._solve_seconds = 0.0

    @classmethod
    @functools.cache
    def available(cls) -> bool:
        """Whether pyamg imports."""
        try:
            import pyamg  # noqa: F401
        except ImportError:
            return False
        return True

    @property
    def ready(self) -> bool:
        """A hierarchy exists."""
        return self.hierarchy.ready

    @property
    def report(self) -> SolveReport:
        """The last analysis, setup and solve (:class:`SolveReport`)."""
        last = self.last
        solved = {} if last is None else dict(
            iterations=last.iterations, residual=last.residual, converged=last.converged,
            negative_curvature=last.negative_curvature)
        return SolveReport(self.name, analyse_seconds=self.hierarchy.analyze_seconds,
                           factorize_seconds=self._factorize_seconds,
                           solve_seconds=self._solve_seconds, **solved)

    def analyse(self, pattern: sp.spmatrix | sp.sparray, *, symmetric: bool = False) -> None:
        """Aggregate the vertices of ``pattern`` (symmetric, whole 3-DOF vertices)."""
        self.hierarchy.analyze(pattern)

    def factorize(self, A: sp.spmatrix | sp.sparray, *, pattern_key: object = None) -> None:
        """Build the hierarchy of ``A`` (aggregating its pattern first when it is new);
        ``pattern_key`` is kept as :attr:`pattern_key`."""
        t0 = time.perf_counter()
        self.hierarchy.setup(A, pattern_key=pattern_key)
        self.pattern_key = pattern_key
        self._A = A
        self._factorize_seconds = time.perf_counter() - t0

    def solve(self, b: np.ndarray, *, A: sp.spmatrix | sp.sparray | None = None,
              rtol: float | None = None, maxiter: int | None = None) -> np.ndarray:
        """CG from ``x = 0`` on ``A x = b`` to ``|r| <= rtol |b|``
        (:meth:`AMGPreconditioner.solve`); the outcome is :attr:`last` and :attr:`report`.

        Parameters
        ----------
        b : (n,) float64
        A : (n, n) scipy.sparse matrix, optional
            The operator (default: the matrix of the hierarchy).
        rtol, maxiter : optional
            Default :attr:`rtol`, :attr:`maxiter`.
        """
        op = self._A if A is None else A
        if op is None:
            raise RuntimeError("factorize() must run before solve()")
        t0 = time.perf_counter()
        self.last = self.hierarchy.solve(op, b, rtol=self.rtol if rtol is None else rtol,
                                         maxiter=self.maxiter if maxiter is None else maxiter)
        self._solve_seconds = time.perf_counter() - t0
        return self.last.x
