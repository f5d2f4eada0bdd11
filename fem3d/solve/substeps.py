"""Substeps: a contact step whose own straight motion is not intersection-free, or whose Newton
solve fails, is taken again as 2, then 4, ... substeps of ``dt / n``.

IPC's line search keeps every Newton segment intersection-free, so the chain of iterates from
``q_t`` to ``q_{t+1}`` never crosses a surface; the straight motion from ``q_t`` to
``q_{t+1}``, which the time discretisation assumes, may. A fast body can be steered by that
chain around another body's corner and end the next step wholly past it
(``docs/contact.md``, "The fast body through a free body"). After each step, every term with
a ``straight_path_is_free(q0, q1, t0, t1)`` method (IPC contact:
:meth:`fem3d.physics.terms.contact.ContactTerm.straight_path_is_free`) checks that motion; when
it is not free, when Newton stopped on its iteration cap, or when the step raised a
:class:`SimulationError`, the step is redone from its start as ``n = 2, 4, ...`` substeps of
``dt / n`` (each checked in turn), up to ``max_substeps``.

* **State.** The state after the substeps is the step's: time ``t + dt`` (exactly), step
  index ``step + 1``. Outputs stay per step.
* **Terms.** Terms with ``state_array`` / ``load_state_array`` (IPC's adaptive barrier
  stiffness) are put back to their state at the step's start before each redo, so a redo
  starts where the step did; each substep lags the friction at its own start (``begin_step``)
  and places the kinematic mesh obstacles at its own end time.
* **Pins.** The fixed vertices at each substep's end come from ``fixed_at(t)`` (keyframed pins
  at the substep times); without it, they move on the straight line from where they are to
  ``fixed_positions``.
* **Schemes.** Backward Euler and Newmark (whose history, the acceleration ``a``, does not
  depend on the step size) chain their substeps. History that is the state one step earlier
  (a scheme's ``previous_state``: BDF2's, backward Euler's extrapolated warm start) is
  dropped for the first substep (BDF2's backward-Euler start-up step), the later ones use
  the previous substep, and the state after the substeps carries the step's start as that
  history again, one ``dt`` earlier, as the next whole step expects
  (``Scheme.begin_substeps``, ``end_substeps``). ``static`` is not
  substepped (its load steps are its own).
* **Cap.** At ``max_substeps`` (a power of two): a straight motion that still meets a
  surface raises :class:`SimulationError`; so does a :class:`SimulationError` of the finest
  attempt (re-raised). A step that is only unconverged is kept, as without substeps (the
  finest complete attempt whose straight motions are free, ``StepStats.converged = False``).
* **Cost.** One straight-motion check per step (no mesh-mesh contact, e.g. a body on planes:
  none; :mod:`fem3d.physics.contact.path`: the model's CCD, then Tight-Inclusion only on a
  motion that one flags; 1-4 % of a gallery contact step); nothing else when it passes: the
  step's result is the one without substeps, bit for bit.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np

from fem3d.errors import ParameterError, SimulationError
from fem3d.solve.state import State, StepStats

__all__ = ["step_with_substeps", "check_max_substeps", "path_checked_terms", "merge_stats",
           "MAX_SUBSTEPS_LIMIT"]

#: The largest ``max_substeps`` accepted (substeps of ``dt / 1024``).
MAX_SUBSTEPS_LIMIT = 1024

#: StepStats counters summed over every attempt and substep.
_SUMMED = ("newton_iterations", "line_search_halvings", "shifted_factorizations",
           "factorizations", "cg_iterations", "psd_fallbacks", "amg_setups", "lagged_matrices",
           "load_increments")


def check_max_substeps(n) -> int:
    """``n`` as an int when it is a power of two in ``[1, MAX_SUBSTEPS_LIMIT]``.

    Raises
    ------
    ParameterError
        Anything else.
    """
    ok = isinstance(n, (int, np.integer)) and not isinstance(n, bool) and \
        1 <= int(n) <= MAX_SUBSTEPS_LIMIT and int(n) & (int(n) - 1) == 0
    if not ok:
        raise ParameterError(f"max_substeps must be a power of two from 1 to "
                             f"{MAX_SUBSTEPS_LIMIT} (1: no substeps), got {n!r}")
    return int(n)


def path_checked_terms(terms: Sequence) -> list:
    """The terms that check a step's straight motion (``straight_path_is_free``)."""
    return [t for t in terms if callable(getattr(t, "straight_path_is_free", None))]


def merge_stats(parts: Sequence[StepStats], accepted: Sequence[StepStats],
                substeps: int) -> StepStats:
    """One step's statistics from every attempt's substeps (``parts``, counters and seconds
    summed) and the accepted attempt's (``accepted``: convergence, gradient norms)."""
    out = StepStats(substeps=substeps)
    for s in parts:
        for name in _SUMMED:
            setattr(out, name, getattr(out, name) + getattr(s, name))
        for part, sec in s.seconds.items():
            out.add_seconds(part, sec)
    out.converged = all(s.converged for s in accepted)
    out.gradient_norms = [g for s in accepted for g in s.gradient_norms]
    out.gradient_tolerance = accepted[-1].gradient_tolerance
    return out


def step_with_substeps(
    scheme,
    system,
    terms: Sequence,
    state: State,
    dt: float,
    settings,
    *,
    max_substeps: int = 1,
    fixed_positions: np.ndarray | None = None,
    fixed_at: Callable[[float], np.ndarray | None] | None = None,
) -> tuple[State, StepStats]:
    """One step of ``scheme``, redone in substeps where needed (see the module docstring).

    Parameters
    ----------
    scheme : fem3d.solve.schemes.base.Scheme
        Its ``step(system, terms, state, dt, settings, *, fixed_positions)`` takes each
        (sub)step; its ``begin_substeps`` / ``end_substeps`` keep its history one step back.
    system : System
    terms : sequence of Term
    state : State
    dt : float
    max_substeps : int, optional
        A power of two; 1 (default): the step as ``scheme`` takes it, unchecked.
    fixed_positions : (n_fixed, 3) float64, optional
        The fixed vertices at the end of the step (None: they stay).
    fixed_at : callable, optional
        ``t -> (n_fixed, 3)`` (or None): the fixed vertices at a substep's end time.
    settings : NewtonSettings

    Returns
    -------
    (State, StepStats)

    Raises
    ------
    SimulationError
        At the cap: the straight motion of a substep still meets a surface, or the finest
        attempt failed.
    """
    max_substeps = check_max_substeps(max_substeps)
    checked = path_checked_terms(terms)
    if max_substeps == 1 or not checked:
        return scheme.step(system, terms, state, dt, settings, fixed_positions=fixed_positions)
    kept = [t for t in checked if callable(getattr(t, "state_array", None))]
    at_start = [t.state_array() for t in kept]
    pins = _pins(system, state, dt, fixed_positions, fixed_at)
    spent: list[StepStats] = []
    fallback = None
    n = 1
    while True:
        if n > 1:
            for t, a in zip(kept, at_start, strict=True):
                t.load_state_array(a)
        new, parts, failure = _attempt(scheme, system, terms, state, dt, n, pins, checked,
                                       fixed_positions, settings)
        spent += parts
        if failure is None:
            stats = merge_stats(spent, parts, n)
            if stats.converged:
                return new, stats
            fallback = (new, parts, n, [t.state_array() for t in kept])
        if 2 * n > max_substeps:
            break
        n *= 2
    if fallback is not None:  # only unconverged: kept, as without substeps
        new, parts, n_ok, states = fallback
        for t, a in zip(kept, states, strict=True):
            t.load_state_array(a)
        return new, merge_stats(spent, parts, n_ok)
    if isinstance(failure, SimulationError):
        raise failure
    raise SimulationError(
        f"contact: the step's straight motion passes through a surface even in {n} substeps "
        f"of dt/{n} (max_substeps = {max_substeps}): a body moves too fast for dt; use a "
        "smaller dt or a larger contact.max_substeps", step=state.step)


def _pins(system, state: State, dt: float, fixed_positions, fixed_at):
    """``pins(k, n)``: the fixed vertices at the end of substep ``k`` of ``n`` (None: they
    stay); the step's end is ``fixed_positions`` itself."""
    if fixed_positions is None and fixed_at is None:
        return lambda k, n: None
    fv = system.constraints.fixed_vertices
    p0 = state.q[fv]

    def pins(k: int, n: int):
        if k == n:
            return fixed_positions
        if fixed_at is not None:
            return fixed_at(state.t + dt * k / n)
        return p0 + (k / n) * (np.asarray(fixed_positions, dtype=np.float64) - p0)

    return pins


def _attempt(scheme, system, terms, state: State, dt: float, n: int, pins, checked,
             fixed_positions, settings):
    """The step as ``n`` substeps: ``(state, [StepStats], failure)``, ``failure`` None, the
    string ``"path"`` (a straight motion meets a surface) or the SimulationError raised."""
    if n == 1:  # exactly the call without substeps
        try:
            new, stats = scheme.step(system, terms, state, dt, settings,
                                     fixed_positions=fixed_positions)
        except SimulationError as exc:
            return None, [], exc
        free = all(t.straight_path_is_free(state.q, new.q, state.t, state.t + dt)
                   for t in checked)
        return new, [stats], None if free else "path"
    h = dt / n
    parts: list[StepStats] = []
    current = scheme.begin_substeps(state)
    for k in range(n):
        t0 = state.t + dt * k / n
        t1 = state.t + dt if k == n - 1 else state.t + dt * (k + 1) / n
        start = dataclasses.replace(current, t=t0, step=state.step)
        try:
            new, stats = scheme.step(system, terms, start, h, settings,
                                     fixed_positions=pins(k + 1, n))
        except SimulationError as exc:
            return None, parts, exc
        parts.append(stats)
        if not all(t.straight_path_is_free(start.q, new.q, t0, t1) for t in checked):
            return None, parts, "path"
        current = new
    current = scheme.end_substeps(state, current)
    return dataclasses.replace(current, t=state.t + dt, step=state.step + 1), parts, None
