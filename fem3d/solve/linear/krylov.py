"""Conjugate gradients for the Newton systems, preconditioned by a factorization.

:class:`PreconditionedCG` keeps one factorization and uses it as the preconditioner of conjugate
gradients on later matrices of the same pattern (the Hessian changes little between Newton
iterations or time steps); it reports iterations and says when CG stalls so the caller
refactorizes.

:func:`iterations_per_decade` measures how fast a CG solve converged (the AMG direction of
:mod:`fem3d.solve.linear.amg_cg` solver uses it to decide when a hierarchy has aged).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from fem3d.solve.linear.base import DirectSolver, SolveReport, as_csr

__all__ = ["CGResult", "PreconditionedCG", "iterations_per_decade"]


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
    solver : DirectSolver
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
        solver: DirectSolver,
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
        A = as_csr(A)
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


def iterations_per_decade(result: CGResult | SolveReport) -> float:
    """CG iterations per factor 10 of residual reduction (``inf`` when it did not reduce)."""
    if result.iterations == 0:
        return 0.0
    if not 0.0 < result.residual < 1.0:
        return math.inf
    return result.iterations / -math.log10(result.residual)
