"""Newmark's average-acceleration scheme (``beta = 1/4``, ``gamma = 1/2``, the trapezoidal
rule) as an energy minimisation over the terms.

``q_{n+1} = q_n + dt/2 (v_n + v_{n+1})`` and ``M a_{n+1} = f(q_{n+1}, v_{n+1})`` with
``v_{n+1} = v_n + dt/2 (a_n + a_{n+1})`` are, with ``x = v_{n+1}`` on the free DOFs, the
stationarity conditions of backward Euler's objective with

``h = dt / 2``, ``q_base = q_n + dt/2 v_n``, ``v_hat = v_n + dt/2 a_n``;

then ``a_{n+1} = 2 (v_{n+1} - v_n) / dt - a_n``. Second order, no numerical damping: on a
linear problem ``1/2 v^T M v + V(q)`` (kinetic + strain + gravity potential: the energy the
run logs) is conserved to the solver's tolerance; on a nonlinear one it stays bounded.
Rayleigh damping enters as ``h/2 x^T D x``, so the damping force is averaged over the step
like the others (``D`` at the start of the step).

The state carries ``a`` in its history. A state without it (the first step, a changed integrator, a
:meth:`~fem3d.simulation.Simulation.set_state`) gets ``a_0`` from ``M a_0 = f(q_0, v_0)``:
one solve with the mass matrix on the free DOFs; the fixed DOFs' acceleration is zero. Pins
move with the secant velocity ``(p - q_n) / dt`` and the backward-difference acceleration.

With contact (a term whose ``newton_policy`` is ``stiff``, IPC's barrier) the
trapezoidal rule gains energy at every impact: the barrier is far stiffer than ``dt``
resolves and average acceleration does not damp the unresolved modes, so the stiff
accelerations chatter and grow (measured on the bunny drop: ~8,000 J from 0 J by t = 1.5 s,
whether Newton stops by IPC's rule or at a gradient tolerance 1e-4 times tighter). Newmark
then uses the dissipative member of the family ``gamma = 1/2 + alpha``, ``beta = gamma^2``
(:data:`CONTACT_ALPHA` = 0.05; unconditionally stable, damps high frequencies, first order):
in the same objective ``h = gamma dt``, ``q_base = q_n + (1 - gamma) dt v_n + (1/2 - gamma)
dt^2 a_n``, ``v_hat = v_n + (1 - gamma) dt a_n``, ``a_{n+1} = (v_{n+1} - v_hat) / (gamma
dt)`` (``docs/integrators.md``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from fem3d.physics.terms.base import NewtonPolicy, StepMap, as_term
from fem3d.solve.schemes.base import Scheme, Step
from fem3d.solve.state import State
from fem3d.solve.step_maps import affine_step_map, end_positions, fixed_dofs
from fem3d.solve.system import System

__all__ = ["Newmark", "initial_acceleration", "newmark_gamma", "CONTACT_ALPHA"]

#: Newmark with contact: ``gamma = 1/2 + CONTACT_ALPHA``, ``beta = gamma^2``; spectral radius
#: 0.914 at ``omega dt -> inf``, 0.9998 at ``omega dt = 0.1``. On the bunny drop (150 steps)
#: 0 grows to ~8,000 J, 0.01 regains 7 J within 10 steps at t = 0.8 s, 0.02 and 0.05 lose
#: energy monotonically to rest (final kinetic 0.32 J and 0.16 J against a 22.7 J drop).
CONTACT_ALPHA = 0.05


def newmark_gamma(terms: Sequence) -> float:
    """``gamma`` of the step: 1/2 (average acceleration), or ``1/2 + CONTACT_ALPHA`` when a
    term is stiff (:attr:`NewtonPolicy.stiff <fem3d.physics.terms.base.NewtonPolicy.stiff>`:
    IPC contact's barrier)."""
    contact = NewtonPolicy.combine(t.newton_policy for t in map(as_term, terms)
                                   if t.active).stiff
    return 0.5 + CONTACT_ALPHA if contact else 0.5


def initial_acceleration(system: System, terms: Sequence, state: State, dt: float
                         ) -> np.ndarray:
    """``a`` with ``M a = f(q, v)`` on the free DOFs (every term's force but inertia's;
    position terms at ``q`` as they stand, velocity terms at ``v``), zero on fixed DOFs.

    Returns
    -------
    (n, 3) float64
    """
    c = system.constraints
    q, v = state.q.reshape(-1), state.v.reshape(-1)
    fd = fixed_dofs(system)
    v_fixed = None
    if fd.size and np.any(v[fd]):
        v_fixed = np.zeros(c.n_dofs)
        v_fixed[fd] = v[fd]
    probe = StepMap(constraints=c, h=1.0, dt=dt, t=state.t, step=state.step, q_t=q, v_t=v,
                    q_base=q, v_hat_free=np.zeros(c.n_free), v_prescribed=v_fixed)
    x = np.ascontiguousarray(v[c.free_dofs])
    g = np.zeros(c.n_free)
    for term in map(as_term, terms):
        if term.inertial or not term.active:
            continue
        if term.variable == "position":
            g += np.asarray(term.gradient(q))[c.free_dofs]
        else:
            term.begin_step(probe)
            g += term.gradient(x)
    a = np.zeros(c.n_dofs)
    if system.reductions.any(bool(np.any(g))):  # (an MPI rank: any rank's force)
        a[c.free_dofs] = system.solve_mass(-g)
    return a.reshape(-1, 3)


class Newmark(Scheme):
    """Newmark, average acceleration (see the module docstring); its states carry the
    acceleration ``a``."""

    name = "newmark"
    label = "Newmark"
    history = ("a",)
    distributed = True  # the initial acceleration's mass solve goes through the system

    def prepare(self, system, terms, state, dt, fixed_positions, settings) -> Step:
        """``h = gamma dt``, ``q_base``, ``v_hat`` from ``q_n``, ``v_n``, ``a_n`` (``a_n``
        from ``M a = f`` where the state has none)."""
        p = end_positions(system, state, fixed_positions)
        a_n = state.history.get("a")
        if a_n is None:
            a_n = initial_acceleration(system, terms, state, dt)
        a_n = a_n.reshape(-1)
        v_n = state.v.reshape(-1)
        gamma = newmark_gamma(terms)
        if gamma == 0.5:  # average acceleration
            h = 0.5 * dt
            offset, v_hat = h * v_n, v_n + h * a_n
        else:  # beta = gamma^2 (module docstring)
            h = gamma * dt
            offset = (1.0 - gamma) * dt * v_n + (0.5 - gamma) * dt * dt * a_n
            v_hat = v_n + (1.0 - gamma) * dt * a_n
        step = affine_step_map(system, state, dt, p, h=h, offset=offset, v_hat=v_hat)
        return Step(step, data={"a_n": a_n, "v_hat": v_hat, "gamma": gamma})

    def acceleration(self, before, state, dt):
        if "a" in state.history:  # the state's own
            return state.history["a"].reshape(-1)
        return super().acceleration(before, state, dt)

    def finish(self, system, state, step, x, settings) -> State:
        """``a_{n+1}`` from ``v_{n+1}`` (the pins': the backward difference)."""
        a_n, v_hat, gamma = step.data["a_n"], step.data["v_hat"], step.data["gamma"]
        h, dt = step.map.h, step.map.dt
        v_n = state.v.reshape(-1)
        q = step.map.positions(x).reshape(-1, 3)
        v = step.map.velocity(x)
        a = (v - v_n) / h - a_n if gamma == 0.5 else (v - v_hat) / h
        fd = fixed_dofs(system)
        a[fd] = (v[fd] - v_n[fd]) / dt
        return State(q=q, v=v.reshape(-1, 3), t=state.t + dt, step=state.step + 1,
                     history={"a": a.reshape(-1, 3)})
