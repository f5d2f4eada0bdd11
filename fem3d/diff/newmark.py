"""The adjoint of ``simulation.integrator = "newmark"`` without contact (:mod:`fem3d.solve.
newmark`: average acceleration, ``gamma = 1/2``, ``beta = 1/4``).

A step is backward Euler's step equation with ``h = dt / 2``, ``q_B = q_n + dt/2 v_n``,
``v_hat = v_n + dt/2 a_n``; after it ``a_{n+1} = 2 (v_{n+1} - v_n) / dt - a_n`` on the free
DOFs and ``(v_{n+1} - v_n) / dt`` on the pinned ones. The state carries ``a``; the first
state's ``a_0`` solves ``M a_0 + g(q_0, v_0) = 0`` on the free DOFs
(:func:`fem3d.solve.newmark.initial_acceleration`: elasticity at ``q_0``, gravity, damping
``D(q_0) v_0``), whose adjoint :meth:`NewmarkAdjoint.finish` adds: one solve with the mass
matrix, the same terms at ``h = 1``. With contact Newmark changes ``gamma``
(:data:`fem3d.solve.newmark.CONTACT_ALPHA`): refused (contact is differentiated with backward
Euler only).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import scipy.sparse.linalg as spla

from fem3d.diff.schemes import SchemeAdjoint, StepLin, converged_settings, register_scheme
from fem3d.diff.terms import StepPair, sparse_of
from fem3d.solve.backward_euler import model_terms
from fem3d.solve.newmark import initial_acceleration, newmark

__all__ = ["NewmarkAdjoint"]


class NewmarkAdjoint(SchemeAdjoint):
    """Average acceleration (see the module docstring)."""

    name = "newmark"

    def start(self, run, state):
        a0 = initial_acceleration(run.system, model_terms(run.system), state, run.dt)
        return replace(state, a=a0)

    def forward(self, run, state, terms):
        return newmark(run.system, terms, state, run.dt,
                       fixed_positions=run.fixed_positions(state.t + run.dt),
                       max_iterations=None, **converged_settings(run))

    def linear(self, s0, dt):
        q, v, a = s0.q.reshape(-1), s0.v.reshape(-1), s0.a.reshape(-1)
        return StepLin(h=0.5 * dt, tau=dt, qb=q + 0.5 * dt * v, vh=v + 0.5 * dt * a)

    def split(self, s0, s1, bar1, fixed):
        bar0 = self.zero(s0)
        a_bar = bar1["a"]
        free = np.ones(a_bar.size, dtype=bool)
        free[fixed] = False
        dt = s1.t - s0.t
        dv = np.where(free, 2.0 / dt, 1.0 / dt) * a_bar  # a_{n+1} by v_{n+1}, by -v_n
        bar0["v"] -= dv
        bar0["a"] -= np.where(free, a_bar, 0.0)
        return bar1["q"], bar1["v"] + dv, bar0

    def pull_back(self, s0, lin, bar0, qb_bar, vh_bar):
        dt = 2.0 * lin.h
        bar0["q"] += qb_bar
        bar0["v"] += 0.5 * dt * qb_bar + vh_bar
        bar0["a"] += 0.5 * dt * vh_bar

    def finish(self, adj, s0, bar0):
        """``M a_0 + g(q_0, v_0) = 0``: the step equation's terms at ``h = 1`` with ``u = v_0``
        and ``v_hat = v_0 - a_0`` (so inertia's ``M (u - v_hat)`` is ``M a_0``)."""
        a_bar = bar0["a"]
        if not np.any(a_bar[adj.free]):
            return
        q, v, a = s0.q.reshape(-1), s0.v.reshape(-1), s0.a.reshape(-1)
        lf = np.zeros(q.size)
        lf[adj.free] = spla.spsolve(adj.run.system.mass_free.tocsc(), a_bar[adj.free])
        pair = StepPair(q0=q, v0=v, q1=q, u=v, dt=adj.dt, t1=s0.t, t0=s0.t, step=s0.step,
                        h=1.0, qb=q, vh=v - a)
        for term in adj.terms:
            term.linearize(pair)
            m = term.matrix()
            dq, dv = term.state_vjp(lf)  # dv: by v_hat = v_0 - a_0, with u = v_0 below
            if dq is not None:
                bar0["q"] += dq
            if dv is not None:
                bar0["v"] += dv
            if term.variable == "velocity" and m is not None:
                bar0["v"] -= sparse_of(adj.model, m) @ lf
            dq = term.start_vjp(lf)
            if dq is not None:
                bar0["q"] += dq
            term.param_vjp(lf, adj.grads)


register_scheme(NewmarkAdjoint())
