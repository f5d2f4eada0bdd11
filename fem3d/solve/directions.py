"""Newton directions: how one Newton iteration solves ``A d = -g`` for a step's objective.

Each strategy is a class that owns its state for one step (made afresh per step; what lasts
across steps, the factorization or the AMG hierarchy, lives in the :class:`System`):

* :class:`DirectDirection` (``"direct"``): factorize the Newton matrix at every iteration,
  shifted up a Levenberg-Marquardt ladder when indefinite, the PSD-projected Hessian where no
  shift works.
* :class:`ReuseDirection` (``"reuse"``): conjugate gradients preconditioned by the kept
  factorization, with forcing terms, lagged Newton matrices and the PSD-projected Hessian on
  indefinite iterations; refactorizes when CG does not pay.
* :class:`AMGDirection` (``"amg"``): CG preconditioned by a smoothed-aggregation V-cycle,
  solved to Eisenstat-Walker forcing terms, with a chord step near convergence.

They know the objective only through :class:`fem3d.solve.objective.Objective` (``matrix(x,
psd)``) and return a direction ``d`` (all NaN: :func:`newtons_method` falls back to ``-g``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from fem3d.errors import SimulationError
from fem3d.solve.linear import NotPositiveDefinite
from fem3d.solve.linear.krylov import PreconditionedCG, iterations_per_decade
from fem3d.solve.objective import Objective
from fem3d.solve.settings import AMG_ITERATIONS_PER_DECADE, FORCING_MAX, NewtonSettings
from fem3d.solve.state import StepStats
from fem3d.solve.system import SHIFT_LADDER_GROWTH, SHIFT_LADDER_START, System

__all__ = ["NewtonProgress", "DirectDirection", "ReuseDirection",
           "AMGDirection", "DIRECTIONS", "forcing_term", "eisenstat_walker",
           "AMG_ITERATIONS_PER_DECADE", "FORCING_MAX", "AMG_MATRIX_REUSE_FACTOR",
           "REUSE_FORCING_MAX", "REUSE_LAG_FRACTION"]

#: ``"amg"``: an iteration solves with the previous iteration's Newton matrix (no assembly)
#: when that iteration cut ``|g|`` by a factor below this fraction of the forcing term: the
#: Hessian's change is then far below the residual CG is asked for.
AMG_MATRIX_REUSE_FACTOR = 0.1

#: ``"reuse"``: the loosest relative CG residual; a solve is never tighter than reaching the
#: gradient tolerance in its Newton iteration needs (``0.5 tol / |g|``), nor looser than this.
REUSE_FORCING_MAX = 0.1
#: ``"reuse"``: a Newton iteration solves with the previous iterate's Newton matrix (no
#: assembly) when the gradient that lagging is estimated to leave is below this fraction of
#: the tolerance.
REUSE_LAG_FRACTION = 0.1


@dataclass
class NewtonProgress:
    """The gradient norms one step's Newton directions see: the first sets the tolerance
    ``newtons_method`` aims for (``max(atol, rtol |g_0|)``), the last one the
    Eisenstat-Walker ratio of the next iteration."""

    atol: float
    rtol: float
    tol: float = 0.0
    previous: float = 0.0

    def observe(self, gn: float) -> float:
        """Record ``|g_k|``; returns ``|g_k-1|`` (0 at the first iteration)."""
        if not self.tol:
            self.tol = max(self.atol, self.rtol * gn)
        previous, self.previous = self.previous, gn
        return previous


def eisenstat_walker(gn: float, gn_prev: float) -> float:
    """Eisenstat and Walker's choice 2 (``gamma = 0.9``, ``alpha = 2``): ``0.9 (|g_k| /
    |g_k-1|)^2``; 0 without a previous iteration."""
    return 0.9 * (gn / gn_prev) ** 2 if gn_prev > 0.0 else 0.0


def forcing_term(gn: float, gn_prev: float, eta_prev: float, tol: float,
                 forcing_max: float) -> float:
    """The relative CG residual of an inexact Newton iteration (Eisenstat and Walker's choice
    2, ``gamma = 0.9``, ``alpha = 2``): ``eta = 0.9 (|g_k| / |g_k-1|)^2``, at most
    ``forcing_max`` (the first iteration's), not much below ``0.9 eta_k-1^2`` while that is
    above 0.1 (no sudden over-solving after one lucky step), and never tighter than reaching
    ``|g| <= tol`` from ``|g_k|`` needs (``0.5 tol / |g_k|``).

    Loose while Newton is far from the solution, tightening as fast as Newton converges:
    each decade of gradient costs about one decade of CG residual, so a too loose term costs
    Newton iterations (an assembly and line search each) and a too tight one CG iterations.
    On the 1e5-tet swinging box: 4 Newton iterations and 30 CG iterations, where the older
    ``min(0.1, sqrt(|g_k| / |g_0|))`` needed 6 and 30.
    """
    if gn <= 0.0:
        return forcing_max
    if gn_prev > 0.0:
        eta = eisenstat_walker(gn, gn_prev)
        floor = 0.9 * eta_prev * eta_prev
        if floor > 0.1:
            eta = max(eta, floor)
        eta = min(forcing_max, eta)
    else:
        eta = forcing_max
    return min(forcing_max, max(eta, 0.5 * tol / gn))


@dataclass(eq=False)
class LaggedMatrix:
    """A Newton matrix kept for the next iterates of one step (``"reuse"``).

    Assembled at an iterate with gradient norm ``g_at``; ``expected`` is the iterate a full
    step along the direction solved with it reaches. At the first iterate after it (norm
    ``g_next``) Newton's quadratic model gives ``C = g_next / g_at^2`` (the next gradient of
    a fresh Newton step, ``C |g|^2``) and the contraction of a step solved with this older
    matrix: the matrix is off by about the step taken since, so such a step leaves about
    ``rho |g| + C |g|^2`` with ``rho = 2 g_next / g_at``.
    """

    A: sp.csr_matrix
    g_at: float
    expected: np.ndarray
    g_next: float = 0.0

    def lag(self, x: np.ndarray, gn: float, target: float) -> bool:
        """Whether to solve at ``x`` (gradient norm ``gn``) with this matrix: the last step
        was full and a step solved with it is estimated to leave a gradient below
        ``target``. (Lagging further, over more steps, does not pay: far from the solution
        the estimates are too optimistic, and each extra Newton iteration costs about an
        assembly.)"""
        if not np.array_equal(x, self.expected):
            return False  # the line search shortened the step: the estimates do not hold
        if not self.g_next:
            self.g_next = gn
        if not 0.0 < self.g_next < self.g_at:
            return False
        c = self.g_next / (self.g_at * self.g_at)
        rho = 2.0 * self.g_next / self.g_at
        return rho * gn + c * gn * gn <= target


class NewtonDirection:
    """What every strategy shares: the system, the step's objective, statistics, progress.

    Parameters
    ----------
    system : System
    objective : Objective
    stats : StepStats
        Counts and times are added to it.
    progress : NewtonProgress
    options : NewtonSettings
    """

    def __init__(self, system: System, objective: Objective, stats: StepStats,
                 progress: NewtonProgress, options: NewtonSettings) -> None:
        self.system = system
        self.objective = objective
        self.stats = stats
        self.progress = progress
        self.options = options

    #: the shift ``mu`` of the matrix that gave the last direction (0: Newton's own matrix, or
    #: a PSD-projected one)
    last_shift = 0.0

    def step_converged(self, x: np.ndarray, d: np.ndarray) -> bool:
        """The objective's stopping rule on the step ``d`` (IPC's: its length), which only a
        Newton step can pass: a shifted matrix's step is short because of its shift (a
        Levenberg-Marquardt shift of ``1e4 M`` makes a falling body's step look converged
        and stops it in mid-air)."""
        return self.last_shift == 0.0 and self.objective.step_converged(x, d)

    def matrix(self, x: np.ndarray, psd: bool) -> sp.csr_matrix:
        """The objective's Newton matrix at ``x``, timed as ``"matrix"``."""
        t0 = time.perf_counter()
        A = self.objective.matrix(x, psd)
        self.stats.add_seconds("matrix", time.perf_counter() - t0)
        return A

    def __call__(self, x: np.ndarray, g: np.ndarray) -> np.ndarray:
        raise NotImplementedError


class DirectDirection(NewtonDirection):
    """``-A^{-1} g`` by a fresh factorization at every iteration (``"direct"``).

    An indefinite ``A`` is shifted up the ladder (:meth:`System.factorize`); a shifted step
    that would pass the objective's stopping rule is replaced by Newton's own step when ``A``
    has become positive definite (:meth:`NewtonDirection.step_converged` judges only those).
    """

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.shift_hint = 0.0  # where this step's next shift ladder starts (0: unshifted)
        self.last_cg = 0  # CG iterations of this step's last solve (0 after a factorization)

    def on_indefinite(self) -> None:
        """An iteration's exact Hessian was indefinite where no ladder was climbed."""

    def factorized(self, x: np.ndarray, g: np.ndarray, A_free: sp.csr_matrix,
                   psd_matrix: bool, ladder: bool):
        """``-A^{-1} g`` by a fresh factorization; with ``ladder`` an indefinite ``A`` is
        shifted up the ladder first, else replaced by the PSD-projected Hessian at once.
        Returns the direction and the matrix factorized when it was not shifted (else None).
        """
        system, stats = self.system, self.stats
        t_factor = time.perf_counter()
        try:
            mu = system.factorize(A_free, shift_hint=self.shift_hint, shifts=ladder)
        except SimulationError:
            if psd_matrix:
                raise
            # no shift up to the ladder's end makes the exact Hessian positive definite (tets
            # close to inversion); the PSD-projected one always is
            if not ladder:
                self.on_indefinite()
            A_free = self.matrix(x, True)
            mu = system.factorize(A_free)
            stats.psd_fallbacks += 1
        # Levenberg-Marquardt memory: the next iteration starts one rung lower, back to the
        # exact Hessian once below the ladder (a failed attempt costs a whole factorization)
        lower = mu / SHIFT_LADDER_GROWTH
        self.shift_hint = lower if lower >= SHIFT_LADDER_START * (1 - 1e-9) else 0.0
        stats.shifted_factorizations += int(mu > 0)
        stats.factorizations += 1
        self.last_cg = 0
        self.last_shift = mu
        d = -system.solve(g)
        stats.add_seconds("factorize", time.perf_counter() - t_factor)
        return d, (A_free if mu == 0.0 else None)

    def __call__(self, x: np.ndarray, g: np.ndarray) -> np.ndarray:
        psd = self.options.psd
        A_free = self.matrix(x, psd)
        if not self.system.reductions.all_finite(A_free.data):
            return np.full_like(g, np.nan)  # newtons_method falls back to -g
        d = self.factorized(x, g, A_free, psd, ladder=True)[0]
        if self.last_shift > 0.0 and self.objective.has_stopping_rule and \
                self.objective.step_converged(x, d):
            # the shifted step passes the rule on a step's length: Newton's own step decides,
            # where the matrix has become positive definite (the ladder's hint lags behind)
            d = self._newton_step(g, A_free, d)
        # no later solve reads this factorization (the next iteration factorizes anew): the
        # solver may free it before the next assembly (PETSc's GAMG hierarchy)
        self.system.release_factorization()
        return d

    def _newton_step(self, g: np.ndarray, A_free: sp.csr_matrix,
                     shifted: np.ndarray) -> np.ndarray:
        """``-A^{-1} g`` when ``A`` is positive definite, else the ``shifted`` direction."""
        t0 = time.perf_counter()
        try:
            self.system.factorize(A_free, shifts=False)
        except SimulationError:
            return shifted
        finally:
            self.stats.add_seconds("factorize", time.perf_counter() - t0)
        self.stats.factorizations += 1
        self.last_shift = self.shift_hint = 0.0
        return -self.system.solve(g)


class ReuseDirection(DirectDirection):
    """CG preconditioned by the kept factorization (``"reuse"``).

    Solves to the forcing term ``max(cg_rtol, min(REUSE_FORCING_MAX, max(0.9 (|g_k| /
    |g_k-1|)^2, 0.5 tol / |g_k|)))`` and refactorizes when CG does not converge within
    ``cg_maxiter`` iterations, meets negative curvature or returns a non-descent direction,
    when the step's previous solve needed more than ``cg_maxiter / 2`` iterations (the
    preconditioner has aged), or when no factorization exists yet. With ``lag_matrices`` an
    iteration right after a full step solves with the previous iterate's Newton matrix when
    the gradient that leaves is estimated below :data:`REUSE_LAG_FRACTION` of the tolerance.
    An indefinite exact Hessian gives way to the PSD-projected one for that iteration; after
    two in a row, for the rest of the step.
    """

    def __init__(self, *args, lag_matrices: bool = True, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        opts = self.options
        self.pcg = PreconditionedCG(self.system.solver, rtol=opts.cg_rtol,
                                    maxiter=opts.cg_maxiter, refactorize_on_stall=False)
        self.lag_matrices = lag_matrices
        self.lagged: LaggedMatrix | None = None  # the last Newton matrix (lagging)
        self.psd_rest_of_step = opts.psd  # the PSD-projected Hessian for the rest of the step
        self.indefinite_in_a_row = 0  # consecutive iterations with an indefinite Hessian

    def on_indefinite(self) -> None:
        """This iteration's exact Hessian is indefinite; after two iterations in a row, the
        rest of the step assembles the PSD-projected one directly."""
        self.indefinite_in_a_row += 1
        if self.indefinite_in_a_row >= 2:
            self.psd_rest_of_step = True

    def cg(self, A_free: sp.csr_matrix, g: np.ndarray, eta: float):
        """CG preconditioned by the kept factorization to the relative residual ``eta``:
        the direction (None when CG fails) and whether it met negative curvature."""
        stats, pcg = self.stats, self.pcg
        t0 = time.perf_counter()
        pcg.solver = self.system.solver  # an objective term may have widened the pattern
        pcg.rtol = eta
        try:
            result = pcg.solve(A_free, -g)
        except NotPositiveDefinite:
            # no kept factorization (the pattern was widened) and this matrix has none
            return None, True
        finally:
            stats.add_seconds("cg", time.perf_counter() - t0)
        stats.cg_iterations += result.iterations
        self.last_cg = result.iterations
        # CG can converge on an indefinite A to a direction that is not a descent one;
        # a factorization always gives one
        if result.converged and float(g @ result.x) < 0.0:
            return result.x, False
        return None, result.negative_curvature

    def __call__(self, x: np.ndarray, g: np.ndarray) -> np.ndarray:
        opts, progress = self.options, self.progress
        gn = float(np.linalg.norm(g))
        gn_prev = progress.observe(gn)
        # forcing term: never tighter than reaching the tolerance in this iteration needs, and
        # loose while Newton converges slowly (Eisenstat-Walker: the last iteration's gradient
        # ratio squared), where a tight solve buys nothing
        eta = opts.cg_rtol
        if gn > 0.0:
            ew = eisenstat_walker(gn, gn_prev)
            eta = max(opts.cg_rtol, min(REUSE_FORCING_MAX, max(ew, 0.5 * progress.tol / gn)))
        # an aged preconditioner (the last solve needed over half the budget) is replaced now
        # rather than after another long CG run
        half = opts.cg_maxiter // 2
        use_cg = self.system.factorized_data is not None and self.last_cg <= half
        lagged, self.lagged = self.lagged, None
        if use_cg and lagged is not None and \
                lagged.lag(x, gn, REUSE_LAG_FRACTION * progress.tol):
            d, _ = self.cg(lagged.A, g, eta)
            if d is not None:
                self.stats.lagged_matrices += 1
                lagged.expected = x + d
                self.lagged = lagged
                return d
            use_cg = self.last_cg <= half
        return self._solve(x, g, gn, eta, use_cg)

    def _solve(self, x: np.ndarray, g: np.ndarray, gn: float, eta: float,
               use_cg: bool) -> np.ndarray:
        """A fresh Newton matrix solved by CG, else factorized."""
        psd_matrix = self.psd_rest_of_step
        A_free = self.matrix(x, psd_matrix)
        if not np.isfinite(A_free.data).all():
            return np.full_like(g, np.nan)  # newtons_method falls back to -g
        if use_cg:
            d, negative = self.cg(A_free, g, eta)
            if d is not None:
                if not psd_matrix:
                    self.indefinite_in_a_row = 0
                if self.lag_matrices:
                    self.lagged = LaggedMatrix(A_free, gn, x + d)
                return d
            if negative and not psd_matrix:
                # indefinite exact Hessian: the PSD-projected one for this iteration (a shift
                # ladder costs a factorization per rung, and large shifts make Newton crawl)
                self.on_indefinite()
                self.stats.psd_fallbacks += 1
                psd_matrix = True
                A_free = self.matrix(x, True)
        d, A_spd = self.factorized(x, g, A_free, psd_matrix, ladder=False)
        if not psd_matrix and A_spd is A_free:
            self.indefinite_in_a_row = 0
        if self.lag_matrices and A_spd is not None:
            self.lagged = LaggedMatrix(A_spd, gn, x + d)
        return d


class AMGDirection(NewtonDirection):
    """An inexact Newton: CG preconditioned by an AMG V-cycle (``"amg"``).

    Solved to the forcing term :func:`forcing_term`; the hierarchy is kept across iterations
    and steps and rebuilt when the last solve needed more than ``amg_budget`` CG iterations
    per decade or did not converge within ``amg_maxiter``, and when an objective term widened
    the pattern. An indefinite Newton matrix (CG meets negative curvature) is replaced by the
    PSD-projected one for the rest of the step (``psd_fallbacks``).
    """

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.psd_now = self.options.psd  # switched to the PSD-projected Hessian for the step
        self.eta_prev = self.options.forcing_max  # the forcing term's memory
        self.last_per_decade = 0.0
        self.kept: sp.csr_matrix | None = None  # the last Newton matrix solved with
        self.kept_psd = False  # and whether it is the PSD-projected one

    def __call__(self, x: np.ndarray, g: np.ndarray) -> np.ndarray:
        opts, progress = self.options, self.progress
        gn = float(np.linalg.norm(g))
        gn_prev = progress.observe(gn)
        ratio = gn / gn_prev if gn_prev else math.inf
        eta = forcing_term(gn, gn_prev, self.eta_prev, progress.tol, opts.forcing_max)
        self.eta_prev = eta
        # A chord step: when the last iteration cut |g| by `ratio`, the Hessian moved by about
        # that fraction along it, so the last matrix still solves to well within eta (the
        # final iteration of a converging step: one assembly saved)
        reuse = self.kept_psd == self.psd_now and ratio <= AMG_MATRIX_REUSE_FACTOR * eta
        A_free, self.kept = self.kept if reuse else None, None
        if A_free is None:
            A_free = self.matrix(x, self.psd_now)
        if not np.isfinite(A_free.data).all():
            return np.full_like(g, np.nan)
        return self._solve(x, g, A_free, eta)

    def _solve(self, x: np.ndarray, g: np.ndarray, A_free: sp.csr_matrix,
               eta: float) -> np.ndarray:
        """CG to ``eta``, rebuilding the hierarchy or switching to the PSD Hessian when CG
        says so (at most three attempts)."""
        system, stats, opts = self.system, self.stats, self.options
        amg = system.amg
        for _attempt in range(3):
            fresh = False
            if not system.amg_current or self.last_per_decade > opts.amg_budget:
                t0 = time.perf_counter()
                system.amg_setup(A_free)
                stats.add_seconds("amg_setup", time.perf_counter() - t0)
                stats.amg_setups += 1
                fresh = True
            t0 = time.perf_counter()
            x = amg.solve(-g, A=A_free, rtol=eta, maxiter=opts.amg_maxiter)
            result = amg.report
            stats.add_seconds("cg", time.perf_counter() - t0)
            stats.cg_iterations += result.iterations
            self.last_per_decade = iterations_per_decade(result)
            if result.negative_curvature and not self.psd_now:
                # indefinite exact Hessian: the PSD-projected one for the rest of the step
                self.psd_now = True
                stats.psd_fallbacks += 1
                A_free = self.matrix(x, True)
                self.last_per_decade = 0.0
                continue
            if result.converged or (fresh and result.iterations and not
                                    result.negative_curvature):
                # a fresh hierarchy's best effort is still a descent direction (CG from 0)
                self.kept, self.kept_psd = A_free, self.psd_now
                return x
            if fresh:  # negative curvature on the PSD matrix: only round-off can do that
                break
            self.last_per_decade = math.inf  # rebuild on this matrix and try again
        return np.full_like(g, np.nan)  # newtons_method falls back to -g


#: The strategies by their ``linear_solver`` name.
DIRECTIONS: dict[str, type[NewtonDirection]] = {
    "direct": DirectDirection,
    "reuse": ReuseDirection,
    "amg": AMGDirection,
}
