"""BDF2 (second-order backward differentiation) as an energy minimisation over the terms.

With ``x = v_{n+1}`` on the free DOFs, BDF2's ``v_{n+1} = (3 q_{n+1} - 4 q_n + q_{n-1}) /
(2 dt)`` and ``a_{n+1} = (3 v_{n+1} - 4 v_n + v_{n-1}) / (2 dt) = M^-1 f(q_{n+1}, v_{n+1})``
are the stationarity conditions of the same objective as backward Euler's with

``h = 2 dt / 3``, ``q_base = (4 q_n - q_{n-1}) / 3``, ``v_hat = (4 v_n - v_{n-1}) / 3``

(``q(x) = q_base + h x``; the inertia term ``1/2 |x - v_hat|_M^2``, gravity ``-h f_g . x``,
Rayleigh ``h/2 x^T D x``), so one Newton solve with one line-searched energy per step.
The first step (a state without ``q_prev``) is a backward-Euler step: the usual start-up,
which keeps second-order global accuracy (one first-order step's local error is
``O(dt^2)``). The steps assume a constant ``dt``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from fem3d.physics.model import validate_dt
from fem3d.solve.backward_euler import backward_euler, check_linear_solver, minimise_step
from fem3d.solve.directions import NewtonOptions
from fem3d.solve.state import State, StepStats, check_finite
from fem3d.solve.step_maps import affine_step_map, end_positions
from fem3d.solve.system import System

__all__ = ["bdf2"]


def bdf2(
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
    """One BDF2 step minimising the sum of ``terms`` (see the module docstring).

    Parameters and returns as in :func:`fem3d.solve.backward_euler.backward_euler`; the
    returned state carries ``q_prev``, ``v_prev`` (the state at the start of the step).
    """
    if state.q_prev is None or state.v_prev is None:
        new, stats = backward_euler(
            system, terms, state, dt, fixed_positions=fixed_positions,
            max_iterations=max_iterations, rtol=rtol, atol_factor=atol_factor,
            linear_solver=linear_solver, options=options,
            converged_max_iterations=converged_max_iterations)
        return replace(new, q_prev=state.q, v_prev=state.v), stats
    dt = validate_dt(dt)
    options = NewtonOptions() if options is None else options
    linear_solver = check_linear_solver(system, linear_solver)
    p = end_positions(system, state, fixed_positions)
    q_n, v_n = state.q.reshape(-1), state.v.reshape(-1)
    offset = (q_n - state.q_prev.reshape(-1)) / 3.0
    v_hat = (4.0 * v_n - state.v_prev.reshape(-1)) / 3.0
    step = affine_step_map(system, state, dt, p, h=2.0 * dt / 3.0, offset=offset,
                           v_hat=v_hat)
    x, stats = minimise_step(
        system, terms, state, step, max_iterations=max_iterations, rtol=rtol,
        atol_factor=atol_factor, linear_solver=linear_solver, options=options,
        converged_max_iterations=converged_max_iterations, scheme="BDF2")
    q = step.positions(x).reshape(-1, 3)
    v = step.velocity(x).reshape(-1, 3)
    check_finite(q, v, state.step, "BDF2")
    return State(q=q, v=v, t=state.t + dt, step=state.step + 1, q_prev=state.q,
                 v_prev=state.v), stats
