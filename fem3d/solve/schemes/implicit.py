"""Backward (implicit) Euler as an energy minimisation over the terms.

``v+ = argmin_v E(v)`` over the free DOFs, ``q(v) = q_base + dt P^T v`` (``q_base``: ``q_t``
with the fixed DOFs at their end-of-step positions), with the model's terms

``E(v) = 1/2 dv^T M dv + V(q) + V_pull(q) - dt f_g . v + dt/2 v^T D v + sum_i T_i(q)``

(:class:`~fem3d.physics.terms.inertia.Inertia` with ``dv = v - v_t`` over all DOFs, the fixed
ones' velocity ``(p - q_t)/dt`` prescribed; :class:`~fem3d.physics.terms.elasticity.
Elasticity`; :class:`~fem3d.physics.terms.pull.PullSprings`; :class:`~fem3d.physics.terms.
gravity.Gravity`, ``f_g = M g``; :class:`~fem3d.physics.terms.damping.RayleighDamping`, ``D``
at ``q_t``; further terms ``T_i`` such as contact), minimised by Newton's method
(:func:`fem3d.solve.minimise.minimise_step`) with gradient ``M dv + dt (dV/dq + ...) - dt
f_g + dt D v`` and Hessian ``M + dt^2 (H + H_pull + sum H_i) + dt D``. Its minimiser is the
backward-Euler update ``M (v+ - v_t) = dt (f(q+) + f_g - D v+)``, and the line search sees
this one energy.

Indefinite Hessian (compressed Neo-Hookean tets): each Newton direction
(:mod:`fem3d.solve.directions`) has its remedy (a shift ladder, the PSD-projected Hessian).
Linear solvers (``NewtonSettings.solver``): ``"direct"`` factorizes at every Newton
iteration, ``"reuse"`` solves by CG preconditioned with the kept factorization (an inexact
Newton to the same gradient tolerance), ``"amg"`` by AMG-preconditioned CG with
Eisenstat-Walker forcing terms; a :class:`~fem3d.solve.system.System` whose back end is
``"amg"`` always uses ``"amg"``. :attr:`System.factorized_data` records the factorized matrix
so that a checkpoint can rebuild the same preconditioner.

Warm start (``NewtonSettings.warm_start = "extrapolate"``): Newton also tries ``2 v_t -
v_t-1``; the state then carries the step's start as its history (``q_prev``, ``v_prev``).
"""

from __future__ import annotations

from fem3d.physics.terms.base import StepMap
from fem3d.solve.schemes.base import Scheme, Step
from fem3d.solve.state import Pins, State, new_state, pins_over_step, place_pins

__all__ = ["BackwardEuler", "IMPLICIT"]


class BackwardEuler(Scheme):
    """Backward Euler (see the module docstring)."""

    name = "implicit"
    label = "backward Euler"
    warm_starts = True
    distributed = True
    history = ("q_prev", "v_prev")
    previous_state = {"q_prev": "q", "v_prev": "v"}

    def prepare(self, system, terms, state, dt, fixed_positions, settings) -> Step:
        """``q(x) = q_base + dt P^T x``, inertia toward ``v_t``; the pins over the step."""
        c = system.constraints
        pins = pins_over_step(c, state, dt, fixed_positions)
        v_t = state.v.reshape(-1)
        dv_fixed = None if pins.v_fixed is None else pins.v_fixed - pins.v_t_fixed
        step = StepMap(constraints=c, h=dt, dt=dt, t=state.t, step=state.step,
                       q_t=state.q.reshape(-1), v_t=v_t, q_base=pins.q_base,
                       v_hat_free=v_t[c.free_dofs], v_prescribed=pins.v_fixed,
                       dv_prescribed=dv_fixed)
        guess = None
        v_prev = state.history.get("v_prev")
        if settings.warm_start == "extrapolate" and v_prev is not None:
            free = c.free_dofs
            guess = 2.0 * v_t[free] - v_prev.reshape(-1)[free]
        return Step(step, guess, {"pins": pins})

    def finish(self, system, state, step, x, settings) -> State:
        """``q+ = q_t + dt v+``, the pins where they go; with the extrapolated warm start the
        step's start as the history the next step extrapolates from."""
        c = system.constraints
        pins: Pins = step.data["pins"]
        new = place_pins(c, new_state(c, state, x, step.map.dt), pins)
        if settings.warm_start == "extrapolate":
            new = new.with_history(q_prev=state.q, v_prev=state.v)
        return new


#: The scheme object (``simulation.integrator = "implicit"``).
IMPLICIT = BackwardEuler()
