"""Newton's method with a backtracking (Armijo) line search, on any objective.

:func:`newtons_method` is the loop; one iteration (:func:`_iterate`) finds the direction,
asks the hooks (:class:`NewtonHooks`: a step limit such as CCD, a stopping rule, a changed
objective) and takes the step either at round-off (:func:`_roundoff_step`) or through the
line search (:class:`LineSearch`); the iterate and its counters live in :class:`_Newton`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from fem3d.solve.reductions import WHOLE, Reductions
from fem3d.solve.settings import LINE_SEARCHES

__all__ = ["NewtonResult", "newtons_method", "gradient_norm", "LineSearch", "NewtonHooks",
           "ROUNDOFF_GRADIENT_FACTOR", "LINE_SEARCHES", "PARABOLIC_TRIALS"]

#: With ``roundoff_rtol``: a failed full step with ``||g||`` under this many tolerances is
#: round-off (measured floors on the swinging box: 10-20 tolerances).
ROUNDOFF_GRADIENT_FACTOR = 1e3

#: ``"parabolic"``: the most extra energy evaluations per line search.
PARABOLIC_TRIALS = 2


@dataclass
class NewtonResult:
    """Result of :func:`newtons_method`.

    Attributes
    ----------
    x : (N,) float64
        Final iterate.
    iterations : int
        Newton steps taken.
    gradient_norms : list of float
        ``||g||`` at each iterate visited, including the last.
    converged : bool
        Stopped because ``||g|| <= tol`` or the line search stalled at round-off.
    line_search_halvings : int
        Total halvings.
    """

    x: np.ndarray
    iterations: int
    gradient_norms: list[float]
    converged: bool
    line_search_halvings: int


def gradient_norm(g: np.ndarray, reductions: Reductions = WHOLE) -> float:
    """``||g||`` without overflow for finite ``g``; raises on a non-finite gradient
    (:meth:`Reductions.norm`: an MPI rank's vector, over the ranks)."""
    return reductions.norm(g)


@dataclass(frozen=True)
class LineSearch:
    """The line search of :func:`newtons_method` and its round-off rules.

    Attributes
    ----------
    alpha, p, c : float
        Initial step, shrink factor and Armijo constant: accept ``x + a d`` when
        ``E(x + a d) <= E(x) + c a g.d``; otherwise ``a *= p``.
    max_halvings : int
        Trials before giving up.
    decrement_rtol : float
        When the Newton decrement ``-g.d`` is below ``decrement_rtol (|E(x)| +
        energy_scale)`` the decrease left is at the objective's round-off, where Armijo tests
        are noise: the full step is then taken if it is admissible and reduces ``||g||``;
        otherwise Newton stops (converged at round-off).
    energy_scale : float
        The magnitude of the objective's summands when it is a sum of terms that cancel (an
        elastic energy near rest sums element energies whose own round-off is relative to
        ``E vol``, not to their tiny total); 0: ``|E(x)|`` alone sets the round-off.
    roundoff_rtol : float
        ``> 0``: when the full (clamped) step fails the Armijo test but raises the energy by
        at most ``roundoff_rtol |E|`` (round-off for an inexact Newton direction near the
        solution), accept it if it reduces ``||g||``; and when ``||g||`` is already within
        :data:`ROUNDOFF_GRADIENT_FACTOR` of the tolerance (where a step changes the energy by
        less than its round-off, which scales with its terms rather than with ``|E|``), accept
        it whenever it is finite and reduces ``||g||``, or else stop (converged at round-off)
        rather than halve through noise. 0: plain backtracking.
    kind : {"backtrack", "parabolic"}
        :data:`LINE_SEARCHES`. ``"parabolic"`` pays off where the energy's curvature jumps
        along ``d`` (lagged friction, small ``eps_v``: a full step carries a slip far past
        the static zone; the halving that passes Armijo is far from the minimum along ``d``).
    """

    alpha: float = 1.0
    p: float = 0.5
    c: float = 1e-8
    max_halvings: int = 30
    decrement_rtol: float = 1e-14
    energy_scale: float = 0.0
    roundoff_rtol: float = 0.0
    kind: str = "backtrack"

    def __post_init__(self) -> None:
        if self.kind not in LINE_SEARCHES:
            raise ValueError(f"line_search must be one of {', '.join(LINE_SEARCHES)}, got "
                             f"{self.kind!r}")

    @property
    def refine(self) -> int:
        """The parabolic refinement's trials (0: none)."""
        return PARABOLIC_TRIALS if self.kind == "parabolic" else 0

    def at_roundoff(self, slope: float, fx: float) -> bool:
        """Whether the predicted decrease ``-slope`` is below the objective's round-off."""
        return -slope <= self.decrement_rtol * (abs(fx) + self.energy_scale)


@dataclass(frozen=True)
class NewtonHooks:
    """What the objective tells :func:`newtons_method` beyond its energy and gradient.

    Attributes
    ----------
    on_no_step : callable ``(x, d)`` or None
        Called when every trial point was inadmissible (``+inf``); expected to raise. When it
        is None or returns, Newton stops at the current ``x``.
    max_step : callable ``(x, d) -> float`` or None
        Largest admissible step fraction along ``d`` (e.g. continuous collision detection);
        the line search starts at ``min(alpha, max_step(x, d))`` and backtracks from there.
        A non-positive value stops Newton at ``x`` (not converged).
    converged_step : callable ``(x, d) -> bool`` or None
        A further stopping rule on the Newton direction (IPC's velocity-based tolerance),
        from the second iteration on and not on the gradient fallback (``-g`` says nothing
        of the step to the minimum): True stops Newton at ``x``, converged.
    accept_first_step : bool
        Judge the first direction too: one that passes is taken and ends the solve unless
        ``after_step`` changes the objective there (False: the second is judged).
    after_step : callable ``(x) -> bool`` or None
        Called at every accepted iterate; True means the objective itself changed there
        (IPC's adaptive barrier stiffness), so its value is re-evaluated.
    """

    on_no_step: Callable[[np.ndarray, np.ndarray], None] | None = None
    max_step: Callable[[np.ndarray, np.ndarray], float] | None = None
    converged_step: Callable[[np.ndarray, np.ndarray], bool] | None = None
    accept_first_step: bool = False
    after_step: Callable[[np.ndarray], bool] | None = None

    def last_step(self, x: np.ndarray, d: np.ndarray, newton_step: bool, it: int) -> bool:
        """Whether the stopping rule ends the solve at (iteration ``it > 0``) or after
        (the first, with ``accept_first_step``) the step ``d``."""
        return self.converged_step is not None and newton_step and \
            (it > 0 or self.accept_first_step) and self.converged_step(x, d)


@dataclass
class _Newton:
    """One solve's iterate ``x`` (energy ``fx``, gradient ``g``, ``||g|| = gn``), its
    tolerance and counters."""

    energy: Callable[[np.ndarray], float]
    gradient: Callable[[np.ndarray], np.ndarray]
    x: np.ndarray
    fx: float
    g: np.ndarray
    gn: float
    tol: float
    reductions: Reductions = WHOLE
    norms: list[float] = field(default_factory=list)
    halvings: int = 0
    it: int = 0

    @classmethod
    def start(cls, x0, energy, gradient, f0: float | None, rtol: float, atol: float,
              reductions: Reductions) -> _Newton:
        x = np.array(x0, dtype=np.float64)
        fx = energy(x) if f0 is None else float(f0)
        g = gradient(x)
        gn = reductions.norm(g)
        return cls(energy, gradient, x, fx, g, gn, max(atol, rtol * gn), reductions, [gn])

    def accept(self, x: np.ndarray, fx: float, g: np.ndarray, gn: float | None = None) -> None:
        """Move to ``x``: one iteration more."""
        self.x, self.fx, self.g = x, fx, g
        self.gn = self.reductions.norm(g) if gn is None else gn
        self.norms.append(self.gn)
        self.it += 1

    def result(self, converged: bool) -> NewtonResult:
        return NewtonResult(self.x, self.it, self.norms, converged, self.halvings)


def newtons_method(
    x0: np.ndarray,
    energy: Callable[[np.ndarray], float],
    gradient: Callable[[np.ndarray], np.ndarray],
    newton_direction: Callable[[np.ndarray, np.ndarray], np.ndarray],
    *,
    max_iterations: int | None = 5,
    rtol: float = 1e-10,
    atol: float = 0.0,
    alpha: float = 1.0,
    p: float = 0.5,
    c: float = 1e-8,
    max_halvings: int = 30,
    decrement_rtol: float = 1e-14,
    energy_scale: float = 0.0,
    on_no_step: Callable[[np.ndarray, np.ndarray], None] | None = None,
    max_step: Callable[[np.ndarray, np.ndarray], float] | None = None,
    converged_step: Callable[[np.ndarray, np.ndarray], bool] | None = None,
    accept_first_step: bool = False,
    after_step: Callable[[np.ndarray], bool] | None = None,
    roundoff_rtol: float = 0.0,
    f0: float | None = None,
    line_search: str = "backtrack",
    reductions: Reductions = WHOLE,
) -> NewtonResult:
    """Minimise ``energy`` by Newton's method with a backtracking (Armijo) line search.

    Parameters
    ----------
    x0 : (N,) float64
        Start; ``energy(x0)`` must be finite.
    energy : callable ``(N,) -> float``
        Objective; ``+inf`` marks an inadmissible point (e.g. an inverted tet).
    gradient : callable ``(N,) -> (N,)``
    newton_direction : callable ``(x, g) -> d``
        Solves ``H(x) d = -g`` with an SPD (possibly shifted) Hessian; a ``d`` that is not a
        finite descent direction is replaced by ``-g``.
    max_iterations : int or None, optional
        Cap on Newton steps (default 5, the assignment's); None: no cap (stops at tolerance
        or round-off).
    rtol, atol : float, optional
        Stop when ``||g|| <= max(atol, rtol ||g(x0)||)``.
    alpha, p, c, max_halvings, decrement_rtol, energy_scale, roundoff_rtol, line_search
        The line search (:class:`LineSearch`; ``line_search`` is its ``kind``).
    on_no_step, max_step, converged_step, accept_first_step, after_step
        The objective's hooks (:class:`NewtonHooks`).
    f0 : float, optional
        ``energy(x0)`` when the caller has it already (saves one evaluation).
    reductions : Reductions, optional
        How the vectors' dot products, norms and checks are reduced (an MPI rank's vectors:
        over the ranks, so every rank decides alike); default one process's.

    Returns
    -------
    NewtonResult
        A line search that finds only finite, non-decreasing trial points means round-off
        has been reached: Newton stops there and reports ``converged=True``.
    """
    search = LineSearch(alpha, p, c, max_halvings, decrement_rtol, energy_scale,
                        roundoff_rtol, line_search)
    hooks = NewtonHooks(on_no_step, max_step, converged_step, accept_first_step, after_step)
    run = _Newton.start(x0, energy, gradient, f0, rtol, atol, reductions)
    while max_iterations is None or run.it < max_iterations:
        stop = _iterate(run, newton_direction, search, hooks)
        if stop is not None:
            return run.result(stop)
    return run.result(run.gn <= run.tol)


def _iterate(run: _Newton, newton_direction, search: LineSearch,
             hooks: NewtonHooks) -> bool | None:
    """One Newton iteration from ``run``'s iterate: None to go on, or whether Newton
    converged where it stops."""
    if run.gn <= run.tol:
        return True
    x, g, gn, r = run.x, run.g, run.gn, run.reductions
    d = newton_direction(x, g)
    slope = r.dot(g, d)
    newton_step = slope < 0 and r.all_finite(d)
    if not newton_step:  # not a descent direction: fall back
        d, slope = -g, -gn * gn
    # the rule stops Newton at x; a first direction that passes is taken, then stops it
    last = hooks.last_step(x, d, newton_step, run.it)
    if last and run.it > 0:
        return True
    a0 = search.alpha
    if hooks.max_step is not None:
        a0 = min(search.alpha, float(hooks.max_step(x, d)))
        if not a0 > 0.0:
            return False
    if search.at_roundoff(slope, run.fx):
        # The predicted decrease is below the objective's round-off, so Armijo tests are
        # noise: take the full step while it is admissible and shrinks the gradient.
        taken = _roundoff_step(x, d, a0, gn, run.energy, run.gradient, r)
        if taken is None:
            return True
        run.accept(*taken)
        return True if last else None
    found = _backtrack(x, run.fx, gn, d, slope, a0, run.energy, run.gradient, p=search.p,
                       c=search.c, max_halvings=search.max_halvings,
                       roundoff_rtol=search.roundoff_rtol,
                       end_game=gn <= ROUNDOFF_GRADIENT_FACTOR * run.tol, refine=search.refine,
                       reductions=r)
    run.halvings += found.halvings
    if found.outcome != "accepted":  # round-off (converged, any_finite) or failed
        if not found.any_finite and hooks.on_no_step is not None:
            hooks.on_no_step(x, d)
        return found.any_finite
    x, fx, gt = found.x, found.f, found.g
    if hooks.after_step is not None and hooks.after_step(x):
        fx = run.energy(x)  # the objective changed at x (barrier stiffness)
        gt, last = None, False
    run.accept(x, fx, run.gradient(x) if gt is None else gt)
    return True if last else None

def _roundoff_step(x: np.ndarray, d: np.ndarray, a0: float, gn: float,
                   energy: Callable[[np.ndarray], float],
                   gradient: Callable[[np.ndarray], np.ndarray], reductions: Reductions):
    """The full (clamped) step ``x + a0 d`` with its energy, gradient and ``||g||`` when it
    is admissible and shrinks the gradient below ``gn``; else None (converged at round-off)."""
    xt = x + d if a0 == 1.0 else x + a0 * d
    ft = energy(xt)
    gt = gradient(xt) if math.isfinite(ft) else None
    gtn = math.inf if gt is None or not reductions.all_finite(gt) else reductions.norm(gt)
    return (xt, ft, gt, gtn) if gtn < gn else None


@dataclass
class _Search:
    """What one backtracking line search found.

    ``outcome``: ``"accepted"`` (``x``, ``f`` and, when it was evaluated, ``g`` at the
    accepted point), ``"failed"`` (no trial accepted; ``any_finite`` whether any was
    admissible) or ``"round-off"`` (the end game's full step did not shrink the gradient:
    converged at round-off).
    """

    outcome: str
    halvings: int
    any_finite: bool = False
    x: np.ndarray | None = None
    f: float = math.nan
    g: np.ndarray | None = None


def _backtrack(x: np.ndarray, fx: float, gn: float, d: np.ndarray, slope: float, a0: float,
               energy: Callable[[np.ndarray], float],
               gradient: Callable[[np.ndarray], np.ndarray], *, p: float, c: float,
               max_halvings: int, roundoff_rtol: float, end_game: bool,
               refine: int = 0, reductions: Reductions = WHOLE) -> _Search:
    """Armijo backtracking from the step ``a0`` along ``d`` (see :func:`newtons_method`'s
    ``alpha, p, c``, ``max_halvings`` and ``roundoff_rtol``; ``end_game``: ``||g||`` within
    :data:`ROUNDOFF_GRADIENT_FACTOR` of the tolerance; ``refine``: the parabolic
    refinement's trials, 0 for none)."""
    a = a0
    any_finite = False
    halvings = 0
    rejected = math.inf  # the energy at the last rejected trial, a / p
    for _ in range(max_halvings):
        xt = x + a * d
        if not reductions.any(bool((xt != x).any())):
            break  # the step vanished in x's round-off: accepting it would loop forever
        ft = energy(xt)
        if math.isfinite(ft):
            any_finite = True
            if ft <= fx + c * a * slope:
                if refine and halvings and math.isfinite(rejected) and ft < fx:
                    a, xt, ft = _parabolic(x, fx, d, slope, c, energy,
                                           [(0.0, fx), (a, ft), (a / p, rejected)], refine)
                return _Search("accepted", halvings, True, xt, ft)
            if roundoff_rtol and a == a0:
                # near the tolerance a Newton step changes the energy by less than its
                # round-off, which scales with its terms (elastic, kinetic), not with |E|
                if end_game or ft <= fx + roundoff_rtol * abs(fx):
                    # the energy cannot tell the trial from x: judge by the gradient
                    gt = gradient(xt)
                    if reductions.all_finite(gt) and reductions.norm(gt) < gn:
                        return _Search("accepted", halvings, True, xt, ft, gt)
                if end_game:
                    # a full step that does not shrink the gradient there is the
                    # gradient's round-off: stop rather than halve through noise
                    return _Search("round-off", halvings, True)
        rejected = ft
        a *= p
        halvings += 1
    return _Search("failed", halvings, any_finite)


def _parabolic(x: np.ndarray, fx: float, d: np.ndarray, slope: float, c: float,
               energy: Callable[[np.ndarray], float], points: list[tuple[float, float]],
               trials: int) -> tuple[float, np.ndarray, float]:
    """Successive parabolic interpolation along ``d`` from a bracket ``points`` (three
    ``(a, E(x + a d))`` in increasing ``a``, the middle one the lowest and Armijo-accepted):
    up to ``trials`` evaluations at the vertex of the parabola through the three lowest
    points around the best; returns the best ``(a, x + a d, E)`` seen (one that also passes
    Armijo's test). Every trial lies inside the bracket, so within the line search's first
    (CCD-limited) step."""
    best_a, best_f = points[1]
    best_x = None
    for _ in range(trials):
        (a1, f1), (a2, f2), (a3, f3) = points
        den = (a2 - a1) * (f2 - f3) - (a2 - a3) * (f2 - f1)
        if not den < 0.0:  # not convex through the three points
            break
        v = a2 - 0.5 * ((a2 - a1) ** 2 * (f2 - f3) - (a2 - a3) ** 2 * (f2 - f1)) / den
        if not (a1 < v < a3) or abs(v - a2) <= 1e-3 * a2:
            break
        xv = x + v * d
        fv = energy(xv)
        if not math.isfinite(fv):
            break
        if fv < best_f and fv <= fx + c * v * slope:
            best_a, best_x, best_f = v, xv, fv
        # the new bracket: the best point and its neighbours
        pts = sorted([*points, (v, fv)])
        i = min(range(4), key=lambda k: (pts[k][1], pts[k][0]))
        if i in (0, 3):
            break
        points = pts[i - 1:i + 2]
    return best_a, (x + best_a * d if best_x is None else best_x), best_f
