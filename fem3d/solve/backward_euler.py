"""Backward (implicit) Euler as an energy minimisation over the terms.

``v+ = argmin_v E(v)`` over the free DOFs, ``q(v) = q_base + dt P^T v`` (``q_base``: ``q_t``
with the fixed DOFs at their end-of-step positions), with the model's terms

``E(v) = 1/2 dv^T M dv + V(q) + V_pull(q) - dt f_g . v + dt/2 v^T D v + sum_i T_i(q)``

(:class:`~fem3d.physics.terms.inertia.Inertia` with ``dv = v - v_t`` over all DOFs, the fixed
ones' velocity ``(p - q_t)/dt`` prescribed; :class:`~fem3d.physics.terms.elasticity.
Elasticity`; :class:`~fem3d.physics.terms.pull.PullSprings`; :class:`~fem3d.physics.terms.
gravity.Gravity`, ``f_g = M g``; :class:`~fem3d.physics.terms.damping.RayleighDamping`, ``D``
at ``q_t``; further terms ``T_i`` such as contact), minimised by :func:`newtons_method` with
gradient ``M dv + dt (dV/dq + ...) - dt f_g + dt D v`` and Hessian ``M + dt^2 (H + H_pull +
sum H_i) + dt D``. Its minimiser is the backward-Euler update ``M (v+ - v_t) = dt (f(q+) + f_g
- D v+)``, and the line search sees this one energy.

Indefinite Hessian (compressed Neo-Hookean tets): each Newton direction
(:mod:`fem3d.solve.directions`) has its remedy (a shift ladder, the PSD-projected Hessian).
Any trial point with an inverted tet (``det F <= 0``; unless ``model.allows_inversion``) or a
non-finite energy counts as ``+inf`` in the line search, so accepted states never invert.

Linear solvers (``linear_solver``): ``"direct"`` factorizes at every Newton iteration,
``"reuse"`` solves by CG preconditioned with the kept factorization (an inexact Newton to the
same gradient tolerance), ``"amg"`` by AMG-preconditioned CG with Eisenstat-Walker forcing
terms; a :class:`System` whose back end is ``"amg"`` (``System(..., "amg")``, or ``"auto"``
above :data:`fem3d.solve.linear.AMG_AUTO_MIN_FREE_DOFS` free DOFs) always uses ``"amg"``. With
``"direct"`` and ``"reuse"`` the line search judges round-off against the strain energy's
scale ``E vol`` (``energy_scale`` of :func:`newtons_method`); ``"amg"`` has its own end game
(``roundoff_rtol``). :attr:`System.factorized_data` records the factorized matrix so that a
checkpoint can rebuild the same preconditioner.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence

import numpy as np

from fem3d.errors import SimulationError
from fem3d.physics.assembly import count_inverted
from fem3d.physics.model import validate_dt
from fem3d.physics.springs import Pull
from fem3d.physics.terms.base import StepMap
from fem3d.physics.terms.pull import PullSprings
from fem3d.solve.directions import (
    AMG_ITERATIONS_PER_DECADE,
    DIRECTIONS,
    FORCING_MAX,
    NewtonOptions,
    NewtonProgress,
    ReuseDirection,
)
from fem3d.solve.newton import newtons_method
from fem3d.solve.objective import Objective
from fem3d.solve.state import (
    State,
    StepStats,
    check_finite,
    new_state,
    pins_over_step,
    place_pins,
)
from fem3d.solve.substeps import step_with_substeps
from fem3d.solve.system import System

__all__ = ["implicit_euler", "backward_euler", "model_terms", "newton_options",
           "minimise_step", "check_linear_solver", "step_map", "AMG_ROUNDOFF_RTOL",
           "WARM_STARTS"]

#: ``"amg"``: energy increases below this fraction of the objective are round-off in the line
#: search (:func:`newtons_method`'s ``roundoff_rtol``).
AMG_ROUNDOFF_RTOL = 1e-10

#: Where backward Euler's Newton starts (``warm_start``): ``"previous"`` at the last step's
#: velocity ``v_t`` (the classic start); ``"extrapolate"`` at the lower-energy of ``v_t`` and
#: the linear extrapolation ``2 v_t - v_t-1`` (constant acceleration), the state carrying
#: ``v_t-1`` (:attr:`State.v_prev`) from step to step. On a smooth drag the extrapolated start
#: is often within one Newton iteration of the solution (``python -m bench.newton_step
#: --warm-start extrapolate``); it changes the trajectory only at the Newton tolerance's level.
#: Objectives with contact (a CCD-limited or stiff-barrier term) keep the classic start.
WARM_STARTS = ("previous", "extrapolate")


def model_terms(system: System, pull: Pull | None = None) -> list:
    """The terms of the system's model, in objective order: inertia, elasticity, the pull
    springs, gravity and Rayleigh damping (those present)."""
    return [*system.model_terms(), PullSprings(system.model, pull, spring=system.spring),
            *system.loads.terms()]


def newton_options(hessian: str = "exact", **settings) -> NewtonOptions:
    """:class:`NewtonOptions` with the Hessian named (``"exact"`` or ``"psd"``; the warm
    start, when given, one of :data:`WARM_STARTS`; the line search, one of
    :data:`fem3d.solve.newton.LINE_SEARCHES`, is checked by :func:`newtons_method`)."""
    if hessian not in ("exact", "psd"):
        raise ValueError(f"hessian must be 'exact' or 'psd', got {hessian!r}")
    warm = settings.get("warm_start", "previous")
    if warm not in WARM_STARTS:
        raise ValueError(f"warm_start must be one of {', '.join(WARM_STARTS)}, got {warm!r}")
    return NewtonOptions(psd=hessian == "psd", **settings)


def step_map(system: System, state: State, dt: float, pins) -> StepMap:
    """Backward Euler's unknowns: ``q(x) = q_base + dt P^T x``, inertia toward ``v_t``."""
    c = system.constraints
    v_t = state.v.reshape(-1)
    dv_fixed = None if pins.v_fixed is None else pins.v_fixed - pins.v_t_fixed
    return StepMap(constraints=c, h=dt, dt=dt, t=state.t, step=state.step,
                   q_t=state.q.reshape(-1), v_t=v_t, q_base=pins.q_base,
                   v_hat_free=v_t[c.free_dofs], v_prescribed=pins.v_fixed,
                   dv_prescribed=dv_fixed)


def backward_euler(
    system: System,
    terms: Sequence,
    state: State,
    dt: float,
    *,
    fixed_positions: np.ndarray | None = None,
    max_iterations: int | None = 5,
    rtol: float = 1e-10,
    atol_factor: float = 1e-12,
    linear_solver: str = "direct",
    options: NewtonOptions | None = None,
    converged_max_iterations: int = 100,
) -> tuple[State, StepStats]:
    """One backward-Euler step minimising the sum of ``terms`` (see the module docstring).

    Parameters
    ----------
    system : System
    terms : sequence of Term
        The whole objective, in order (:func:`model_terms` plus e.g. contact).
    state : State
    dt : float
    fixed_positions : (n_fixed, 3) float64, optional
        The fixed vertices at the end of the step (moving pins); None: they stay.
    max_iterations : int or None, optional
        Newton iterations per step (None: until converged); a term that
        ``requires_convergence`` raises it to ``converged_max_iterations``.
    rtol, atol_factor : float, optional
        Relative gradient tolerance, and the absolute one as a fraction of ``dt E L^2`` (``L``
        the diagonal of the rest bounding box).
    linear_solver : {"direct", "reuse", "amg"}, optional
    options : NewtonOptions, optional
        The directions' settings (PSD Hessian, CG tolerances and budgets; default
        ``NewtonOptions()``).

    Returns
    -------
    (State, StepStats)

    Raises
    ------
    SimulationError
        No acceptable Newton step, an inadmissible start, or a non-finite state.
    """
    dt = validate_dt(dt)
    options = NewtonOptions() if options is None else options
    linear_solver = check_linear_solver(system, linear_solver)
    c = system.constraints
    pins = pins_over_step(c, state, dt, fixed_positions)
    extrapolate = options.warm_start == "extrapolate"
    guess = None
    if extrapolate and state.v_prev is not None:
        free = c.free_dofs
        guess = 2.0 * state.v.reshape(-1)[free] - state.v_prev.reshape(-1)[free]
    x, stats = minimise_step(
        system, terms, state, step_map(system, state, dt, pins),
        max_iterations=max_iterations, rtol=rtol, atol_factor=atol_factor,
        linear_solver=linear_solver, options=options,
        converged_max_iterations=converged_max_iterations, guess=guess)
    new = place_pins(c, new_state(c, state, x, dt), pins)
    check_finite(new.q, new.v, state.step, "backward Euler")
    if extrapolate:  # the next step extrapolates from this one's start
        new = dataclasses.replace(new, q_prev=state.q, v_prev=state.v)
    return new, stats


def check_linear_solver(system: System, linear_solver: str) -> str:
    """The Newton direction's name (``"amg"`` whenever the system's back end is AMG).

    Raises
    ------
    ValueError
        Not ``"direct"``, ``"reuse"`` or ``"amg"``.
    """
    if linear_solver not in DIRECTIONS:
        raise ValueError(
            f"linear_solver must be 'direct', 'reuse' or 'amg', got {linear_solver!r}")
    if system.linear_backend == "amg":
        linear_solver = "amg"
    return linear_solver


def minimise_step(
    system: System,
    terms: Sequence,
    state: State,
    step: StepMap,
    *,
    max_iterations: int | None,
    rtol: float,
    atol_factor: float,
    linear_solver: str,
    options: NewtonOptions,
    converged_max_iterations: int,
    scheme: str = "backward Euler",
    guess: np.ndarray | None = None,
) -> tuple[np.ndarray, StepStats]:
    """Minimise the sum of ``terms`` over one step's unknowns (every implicit scheme's core).

    Parameters
    ----------
    system : System
    terms : sequence of Term
    state : State
        The state at the start of the step (its ``step`` index names errors).
    step : StepMap
        The scheme's unknowns (``h``, ``q_base``, ``v_hat``); Newton starts at ``v_hat``
        (clamped by the terms' CCD from ``x_start``).
    max_iterations, rtol, atol_factor, converged_max_iterations
        As in :func:`backward_euler`; the absolute tolerance is ``atol_factor h E L^2``.
    linear_solver : str
        :func:`check_linear_solver`'s answer.
    options : NewtonOptions
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
    if max_iterations is not None and objective.requires_convergence:
        max_iterations = max(max_iterations, converged_max_iterations)
    stats = StepStats()
    L = float(np.linalg.norm(np.ptp(model.X, axis=0)))
    atol = atol_factor * step.h * model.E * L * L
    progress = NewtonProgress(atol, rtol)  # the gradient norms the directions see
    extra = {"lag_matrices": objective.allows_lagged_matrix} \
        if DIRECTIONS[linear_solver] is ReuseDirection else {}
    direction = DIRECTIONS[linear_solver](system, objective, stats, progress, options, **extra)
    x0, e0 = _start(objective, state)
    if guess is not None and not (objective.clamps or objective.policy.stiff):
        x0, e0 = _better_start(objective, x0, e0, guess)
    if objective.initializes_stiffness:
        objective.initialize_stiffness(x0, float(model.mass.sum()) / model.n_dofs)

    def no_step(x: np.ndarray, d: np.ndarray) -> None:
        n_inv = count_inverted(model, objective.positions(x + d))
        raise SimulationError(
            f"{scheme} found no acceptable Newton step: the full step inverts {n_inv} "
            f"of {model.n_tets} tets and every shorter trial also inverts tets or is not "
            "finite (try a smaller dt or softer pull)", step=state.step)

    f0 = None if objective.initializes_stiffness else e0  # stiffness changes E
    iterations, norms, halvings = 0, [], 0
    while True:  # one Newton solve, again while a term re-lags (friction iterations)
        try:
            res = newtons_method(
                x0, _timed(objective.energy, stats), _timed(objective.gradient, stats),
                direction, max_iterations=max_iterations, rtol=rtol, atol=atol,
                on_no_step=no_step, max_step=objective.max_step if objective.clamps else None,
                converged_step=direction.step_converged if objective.has_stopping_rule
                else None,
                accept_first_step=objective.policy.accept_first_step,
                after_step=objective.after_iteration if objective.changes_between_iterates
                else None,
                roundoff_rtol=AMG_ROUNDOFF_RTOL if linear_solver == "amg" else 0.0,
                f0=f0, energy_scale=objective.energy_scale if linear_solver != "amg" else 0.0,
                line_search=options.line_search,
            )
        except SimulationError as exc:
            if exc.step is not None:
                raise
            raise SimulationError(f"{scheme}: {exc.reason}", step=state.step) from exc
        iterations += res.iterations
        norms += res.gradient_norms
        halvings += res.line_search_halvings
        if not (res.converged and objective.relag(res.x)):
            break
        x0, f0 = res.x, None
    res.iterations, res.gradient_norms, res.line_search_halvings = iterations, norms, halvings
    stats.newton_iterations = res.iterations
    stats.gradient_norms = res.gradient_norms
    stats.gradient_tolerance = max(atol, rtol * res.gradient_norms[0])
    stats.line_search_halvings = res.line_search_halvings
    stats.converged = res.converged
    return res.x, stats


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


def implicit_euler(
    system: System,
    state: State,
    dt: float,
    pull: Pull | None = None,
    *,
    fixed_positions: np.ndarray | None = None,
    terms: Sequence = (),
    max_iterations: int | None = 5,
    rtol: float = 1e-10,
    atol_factor: float = 1e-12,
    hessian: str = "exact",
    linear_solver: str = "direct",
    cg_rtol: float = 1e-6,
    cg_maxiter: int = 16,
    converged_max_iterations: int = 100,
    amg_maxiter: int = 200,
    amg_budget: float = AMG_ITERATIONS_PER_DECADE,
    forcing_max: float = FORCING_MAX,
    warm_start: str = "previous",
    max_substeps: int = 1,
    line_search: str = "backtrack",
) -> tuple[State, StepStats]:
    """One backward-Euler step of the system's model (:func:`model_terms`) plus ``terms``.

    Parameters
    ----------
    system : System
        Holds the model, its gravity and damping.
    state : State
    dt : float
    pull : Pull, optional
    fixed_positions, max_iterations, rtol, atol_factor, linear_solver,
    converged_max_iterations
        As in :func:`backward_euler`.
    terms : sequence, optional
        Further terms (:class:`~fem3d.physics.terms.base.Term`, or plain objects with
        ``energy(q)``, ``gradient(q)``, ...: :class:`~fem3d.physics.terms.base.
        PositionTerm`).
    hessian : {"exact", "psd"}, optional
        ``"psd"``: per-element ``dP/dF`` projected to positive semi-definite (generated
        ``hessian_psd``), always SPD, linear convergence near the solution.
    cg_rtol, cg_maxiter : optional
        ``"reuse"``: the tightest relative CG residual, and CG iterations per solve before
        refactorizing (16: about the cost of one factorization on armadillo-class meshes).
    amg_maxiter, amg_budget, forcing_max : optional
        ``"amg"``: CG iterations per solve, the rebuild threshold in iterations per decade
        and the loosest forcing term.
    warm_start : {"previous", "extrapolate"}, optional
        Newton's start (:data:`WARM_STARTS`): ``"extrapolate"`` also tries ``2 v_t -
        v_t-1`` (the returned state carries ``v_prev`` for the next step).
    max_substeps : int, optional
        A power of two: a contact step whose own straight motion is not intersection-free
        (or that fails) is redone as up to this many substeps
        (:func:`fem3d.solve.substeps.step_with_substeps`); 1: never.
    line_search : {"backtrack", "parabolic"}, optional
        Newton's line search (:data:`fem3d.solve.newton.LINE_SEARCHES`).

    Returns
    -------
    (State, StepStats)
    """
    options = newton_options(hessian, cg_rtol=cg_rtol, cg_maxiter=cg_maxiter,
                             amg_maxiter=amg_maxiter, amg_budget=amg_budget,
                             forcing_max=forcing_max, warm_start=warm_start,
                             line_search=line_search)
    return step_with_substeps(
        backward_euler, system, [*model_terms(system, pull), *terms], state, dt,
        max_substeps=max_substeps,
        fixed_positions=fixed_positions, max_iterations=max_iterations, rtol=rtol,
        atol_factor=atol_factor, linear_solver=linear_solver, options=options,
        converged_max_iterations=converged_max_iterations)
