"""Minimising one step's objective: what every implicit scheme shares.

A scheme (:mod:`fem3d.solve.schemes`) makes its :class:`~fem3d.physics.terms.base.StepMap`
(``h``, ``q_base``, ``v_hat``); :func:`minimise_step` sums the terms over it
(:class:`~fem3d.solve.objective.Objective`), picks the Newton direction the
:class:`~fem3d.solve.settings.NewtonSettings` name, finds the start and runs
:func:`~fem3d.solve.newton.newtons_method`, again while a term re-lags (friction).

Any trial point with an inverted tet (``det F <= 0``; unless ``model.allows_inversion``) or a
non-finite energy counts as ``+inf`` in the line search, so accepted states never invert.
With ``"direct"`` and ``"reuse"`` the line search judges round-off against the strain
energy's scale ``E vol`` (``energy_scale``); ``"amg"`` has its own end game
(:data:`AMG_ROUNDOFF_RTOL`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence

import numpy as np

from fem3d.errors import SimulationError
from fem3d.physics.assembly import count_inverted
from fem3d.physics.terms.base import StepMap
from fem3d.solve.directions import DIRECTIONS, NewtonProgress, ReuseDirection
from fem3d.solve.newton import NewtonResult, newtons_method
from fem3d.solve.objective import Objective
from fem3d.solve.settings import NewtonSettings
from fem3d.solve.state import State, StepStats
from fem3d.solve.system import System

__all__ = ["minimise_step", "direction_name", "AMG_ROUNDOFF_RTOL"]

#: ``"amg"``: energy increases below this fraction of the objective are round-off in the line
#: search (:func:`newtons_method`'s ``roundoff_rtol``).
AMG_ROUNDOFF_RTOL = 1e-10


def direction_name(system: System, settings: NewtonSettings) -> str:
    """The Newton direction's name: ``settings.solver``, ``"amg"`` whenever the system's
    back end is AMG."""
    return "amg" if system.linear_backend == "amg" else settings.solver


def minimise_step(
    system: System,
    terms: Sequence,
    state: State,
    step: StepMap,
    settings: NewtonSettings,
    *,
    converged_max_iterations: int,
    scheme: str = "backward Euler",
    guess: np.ndarray | None = None,
) -> tuple[np.ndarray, StepStats]:
    """Minimise the sum of ``terms`` over one step's unknowns.

    Parameters
    ----------
    system : System
    terms : sequence of Term
    state : State
        The state at the start of the step (its ``step`` index names errors).
    step : StepMap
        The scheme's unknowns (``h``, ``q_base``, ``v_hat``); Newton starts at ``v_hat``
        (clamped by the terms' CCD from ``x_start``).
    settings : NewtonSettings
        The absolute tolerance is ``atol_factor h E L^2``.
    converged_max_iterations : int
        The iteration cap when a term requires convergence (the scheme's, resolved by
        :meth:`NewtonSettings.converged_cap`).
    scheme : str, optional
        The scheme's name in error messages.
    guess : (n_free,) float64, optional
        Another start (a warm start): Newton starts there when its energy is below the
        start's (ties: the start). Not tried when a term limits the step (CCD) or is a stiff
        barrier (contact): there an extrapolated start costs Newton iterations (the bunny
        drop: 372 instead of 251 in its first 60 steps).

    Returns
    -------
    (x, StepStats)
        The minimiser ``(n_free,)`` and the step's statistics.

    Raises
    ------
    SimulationError
        No acceptable Newton step or an inadmissible start.
    """
    model = system.model
    objective = Objective(system, terms, step)
    max_iterations = settings.max_iterations
    if max_iterations is not None and objective.requires_convergence:
        max_iterations = max(max_iterations, converged_max_iterations)
    stats = StepStats()
    L = float(np.linalg.norm(system.reductions.extent(model.X)))
    atol = settings.atol_factor * step.h * model.E * L * L
    progress = NewtonProgress(atol, settings.rtol)  # the gradient norms the directions see
    name = direction_name(system, settings)
    extra = {"lag_matrices": objective.allows_lagged_matrix} \
        if DIRECTIONS[name] is ReuseDirection else {}
    direction = DIRECTIONS[name](system, objective, stats, progress, settings, **extra)
    x0, e0 = _start(objective, state)
    if guess is not None and not (objective.clamps or objective.policy.stiff):
        x0, e0 = _better_start(objective, x0, e0, guess)
    if objective.initializes_stiffness:
        objective.initialize_stiffness(x0, float(model.mass.sum()) / model.n_dofs)
    f0 = None if objective.initializes_stiffness else e0  # stiffness changes E

    def solve(x_start: np.ndarray, f_start: float | None) -> NewtonResult:
        try:
            return newtons_method(
                x_start, _timed(objective.energy, stats), _timed(objective.gradient, stats),
                direction, max_iterations=max_iterations, rtol=settings.rtol, atol=atol,
                on_no_step=_no_step(objective, state, scheme),
                max_step=objective.max_step if objective.clamps else None,
                converged_step=direction.step_converged if objective.has_stopping_rule
                else None,
                accept_first_step=objective.policy.accept_first_step,
                after_step=objective.after_iteration if objective.changes_between_iterates
                else None,
                roundoff_rtol=AMG_ROUNDOFF_RTOL if name == "amg" else 0.0,
                f0=f_start, energy_scale=objective.energy_scale if name != "amg" else 0.0,
                line_search=settings.line_search, reductions=system.reductions,
            )
        except SimulationError as exc:
            if exc.step is not None:
                raise
            raise SimulationError(f"{scheme}: {exc.reason}", step=state.step) from exc

    res = _solve_relagging(objective, solve, x0, f0)
    stats.newton_iterations = res.iterations
    stats.gradient_norms = res.gradient_norms
    stats.gradient_tolerance = max(atol, settings.rtol * res.gradient_norms[0])
    stats.line_search_halvings = res.line_search_halvings
    stats.converged = res.converged
    return res.x, stats


def _solve_relagging(objective: Objective, solve, x0: np.ndarray,
                     f0: float | None) -> NewtonResult:
    """``solve(x0, f0)``, again from its answer while a term re-lags there (friction
    iterations); the counts of every solve summed into the last one's result."""
    iterations, norms, halvings = 0, [], 0
    while True:
        res = solve(x0, f0)
        iterations += res.iterations
        norms += res.gradient_norms
        halvings += res.line_search_halvings
        if not (res.converged and objective.relag(res.x)):
            break
        x0, f0 = res.x, None
    res.iterations, res.gradient_norms, res.line_search_halvings = iterations, norms, halvings
    return res


def _no_step(objective: Objective, state: State, scheme: str):
    """Newton's ``on_no_step``: raise naming how many tets the full step inverts."""
    system = objective.system
    model = system.model

    def no_step(x: np.ndarray, d: np.ndarray) -> None:
        n_inv = int(system.summed(count_inverted(model, objective.positions(x + d))))
        raise SimulationError(
            f"{scheme} found no acceptable Newton step: the full step inverts {n_inv} "
            f"of {int(system.summed(model.n_tets))} tets and every shorter trial also inverts "
            "tets or is not "
            "finite (try a smaller dt or softer pull)", step=state.step)

    return no_step


def _start(objective: Objective, state: State) -> tuple[np.ndarray, float]:
    """Newton's start and its energy: ``v_hat`` (clamped by the terms' ``max_step`` from
    ``x_start``, where the free DOFs are at ``q_t``: a start that tunnelled through an
    obstacle would be finite but wrong), or ``x_start`` itself when that is inadmissible
    (backward Euler: ``v_t`` clamped from ``v = 0``) or when the clamp cut the step and a
    term asks for it (:attr:`NewtonPolicy.restart_when_clamped
    <fem3d.physics.terms.base.NewtonPolicy.restart_when_clamped>`)."""
    step = objective.step
    vt_free = step.v_hat_free
    restart = objective.policy.restart_when_clamped
    if step.x_start is None:
        x0 = vt_free.copy()
        if objective.clamps:
            a = objective.max_step(np.zeros_like(vt_free), vt_free)
            if restart and a < 1.0:
                x0 = np.zeros_like(vt_free)
            else:
                x0 *= a
    else:
        x0 = vt_free.copy()
        if objective.clamps:
            d = vt_free - step.x_start
            a = objective.max_step(step.x_start, d)
            x0 = step.x_start.copy() if restart and a < 1.0 else step.x_start + a * d
    e0 = objective.energy(x0)
    if not math.isfinite(e0):
        x0 = np.zeros_like(vt_free) if step.x_start is None else step.x_start.copy()
        e0 = objective.energy(x0)
        if not math.isfinite(e0):
            n_inv = count_inverted(objective.system.model, step.start_positions())
            raise SimulationError(
                f"the current state is inadmissible ({n_inv} inverted tets or a non-finite "
                "energy)", step=state.step)
    return x0, e0


def _better_start(objective: Objective, x0: np.ndarray, e0: float,
                  guess: np.ndarray) -> tuple[np.ndarray, float]:
    """``guess`` and its energy when that is below ``e0``, else ``(x0, e0)``."""
    x = np.asarray(guess, dtype=np.float64)
    e = objective.energy(x)
    return (x, e) if e < e0 else (x0, e0)


def _timed(f, stats: StepStats):
    """``f`` adding its wall time to ``stats.seconds["objective"]``."""
    def call(x):
        t0 = time.perf_counter()
        try:
            return f(x)
        finally:
            stats.add_seconds("objective", time.perf_counter() - t0)
    return call
