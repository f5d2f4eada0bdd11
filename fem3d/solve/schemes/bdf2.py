"""BDF2 (second-order backward differentiation) as an energy minimisation over the terms.

With ``x = v_{n+1}`` on the free DOFs, BDF2's ``v_{n+1} = (3 q_{n+1} - 4 q_n + q_{n-1}) /
(2 dt)`` and ``a_{n+1} = (3 v_{n+1} - 4 v_n + v_{n-1}) / (2 dt) = M^-1 f(q_{n+1}, v_{n+1})``
are the stationarity conditions of the same objective as backward Euler's with

``h = 2 dt / 3``, ``q_base = (4 q_n - q_{n-1}) / 3``, ``v_hat = (4 v_n - v_{n-1}) / 3``

(``q(x) = q_base + h x``; the inertia term ``1/2 |x - v_hat|_M^2``, gravity ``-h f_g . x``,
Rayleigh ``h/2 x^T D x``), so one Newton solve with one line-searched energy per step.
The first step (a state without the history ``q_prev``, ``v_prev``) is a backward-Euler
step: the usual start-up, which keeps second-order global accuracy (one first-order step's
local error is ``O(dt^2)``). The steps assume a constant ``dt``.
"""

from __future__ import annotations

from fem3d.solve.schemes.base import Scheme, Step
from fem3d.solve.schemes.implicit import IMPLICIT
from fem3d.solve.state import State
from fem3d.solve.step_maps import affine_step_map, end_positions

__all__ = ["BDF2"]


class BDF2(Scheme):
    """BDF2 (see the module docstring); its states carry the step's start as ``q_prev``,
    ``v_prev``."""

    name = "bdf2"
    label = "BDF2"
    history = ("q_prev", "v_prev")
    previous_state = {"q_prev": "q", "v_prev": "v"}
    distributed = True

    def step(self, system, terms, state, dt, settings, *, fixed_positions=None,
             energy_bound=None):
        if "q_prev" not in state.history or "v_prev" not in state.history:
            new, stats = IMPLICIT.step(system, terms, state, dt, settings,
                                       fixed_positions=fixed_positions)
            return new.with_history(q_prev=state.q, v_prev=state.v), stats
        return super().step(system, terms, state, dt, settings,
                            fixed_positions=fixed_positions)

    def prepare(self, system, terms, state, dt, fixed_positions, settings) -> Step:
        """``h = 2 dt / 3``, ``q_base = (4 q_n - q_{n-1}) / 3``, ``v_hat = (4 v_n -
        v_{n-1}) / 3``."""
        p = end_positions(system, state, fixed_positions)
        q_n, v_n = state.q.reshape(-1), state.v.reshape(-1)
        offset = (q_n - state.history["q_prev"].reshape(-1)) / 3.0
        v_hat = (4.0 * v_n - state.history["v_prev"].reshape(-1)) / 3.0
        return Step(affine_step_map(system, state, dt, p, h=2.0 * dt / 3.0, offset=offset,
                                    v_hat=v_hat))

    def acceleration(self, before, state, dt):
        if "v_prev" in before.history:  # two steps: BDF2's own difference
            v_nm1 = before.history["v_prev"]
            return (3.0 * state.v - 4.0 * before.v + v_nm1).reshape(-1) / (2.0 * dt)
        return super().acceleration(before, state, dt)  # the first step is backward Euler's

    def finish(self, system, state, step, x, settings) -> State:
        q = step.map.positions(x).reshape(-1, 3)
        v = step.map.velocity(x).reshape(-1, 3)
        return State(q=q, v=v, t=state.t + step.map.dt, step=state.step + 1,
                     history={"q_prev": state.q, "v_prev": state.v})
