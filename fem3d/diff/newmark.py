"""The adjoint of Newmark (:mod:`fem3d.solve.schemes.newmark`).

A step is backward Euler's step equation with ``h = gamma dt``, ``q_B = q_n + (1 - gamma) dt
v_n + (1/2 - gamma) dt^2 a_n``, ``v_hat = v_n + (1 - gamma) dt a_n`` (``beta = gamma^2``);
after it ``a_{n+1} = (v_{n+1} - v_hat) / (gamma dt)`` on the free DOFs and
``(v_{n+1} - v_n) / dt`` on the pinned ones. Without contact ``gamma = 1/2`` (average
acceleration: ``h = dt / 2``, ``q_B = q_n + dt/2 v_n``, ``v_hat = v_n + dt/2 a_n``,
``a_{n+1} = 2 (v_{n+1} - v_n) / dt - a_n``); with contact (IPC's barrier among the terms)
``gamma = 1/2 +`` :data:`fem3d.solve.schemes.newmark.CONTACT_ALPHA`, as the forward step picks it
(:func:`fem3d.solve.schemes.newmark.newmark_gamma`); the friction is lagged at ``q_n`` with the slip
``q_{n+1} - q_n`` (:class:`fem3d.diff.contact.ContactAdjoint`'s ``q_B`` and ``q_t``
products).

The state carries ``a`` (its history); the first state's ``a_0`` solves ``M a_0 + g(q_0,
v_0) = 0`` on the free DOFs (:func:`fem3d.solve.schemes.newmark.initial_acceleration`:
elasticity at ``q_0``, gravity, damping ``D(q_0) v_0``), whose adjoint
:meth:`NewmarkAdjoint.finish` adds: one solve with the mass matrix, the same terms at ``h =
1``, and, with contact, the barrier's force at ``q_0`` where a pair is within ``dhat`` there
(as ``fem3d run``'s ``a_0``: the stiffness before the first step, the friction not yet
lagged: :meth:`fem3d.diff.contact.ContactAdjoint.start_force_vjp`).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse.linalg as spla

from fem3d.diff.schemes import SchemeAdjoint, StepLin, register_scheme
from fem3d.diff.terms import StepPair, sparse_of
from fem3d.solve.schemes.base import model_terms
from fem3d.solve.schemes.newmark import Newmark, initial_acceleration, newmark_gamma

__all__ = ["NewmarkAdjoint"]


class NewmarkAdjoint(SchemeAdjoint):
    """Newmark with ``beta = gamma^2`` (see the module docstring).

    Parameters
    ----------
    gamma : float, optional
        1/2: average acceleration (no contact); :meth:`start` puts an instance with the
        contact's ``gamma`` into a contact run.
    """

    scheme = Newmark()
    contact = True

    def __init__(self, gamma: float = 0.5) -> None:
        self.gamma = float(gamma)

    def start(self, run, state):
        """``a_0`` as the forward run takes it (every term, contact's barrier at ``q_0``
        included); a contact run gets its own scheme with the forward step's ``gamma``
        (``run.scheme``)."""
        terms = [*model_terms(run.system), *(t for term in run.terms
                                             for t in term.forward_terms())]
        gamma = newmark_gamma(terms)
        if gamma != self.gamma:
            run.scheme = NewmarkAdjoint(gamma)
        return state.with_history(a=initial_acceleration(run.system, terms, state, run.dt))

    def linear(self, s0, dt):
        q, v, a = s0.q.reshape(-1), s0.v.reshape(-1), s0.history["a"].reshape(-1)
        g = self.gamma
        if g == 0.5:  # as fem3d.solve.schemes.newmark computes it (bit for bit)
            return StepLin(h=0.5 * dt, tau=dt, qb=q + 0.5 * dt * v, vh=v + 0.5 * dt * a)
        return StepLin(h=g * dt, tau=dt,
                       qb=q + ((1.0 - g) * dt * v + (0.5 - g) * dt * dt * a),
                       vh=v + (1.0 - g) * dt * a)

    def split(self, s0, s1, bar1, fixed):
        bar0 = self.zero(s0)
        a_bar = bar1["a"]
        free = np.ones(a_bar.size, dtype=bool)
        free[fixed] = False
        dt, g = s1.t - s0.t, self.gamma
        # a_{n+1} by v_{n+1} and by -v_n: 1 / (gamma dt) (free), 1 / dt (pinned)
        dv = np.where(free, 1.0 / (g * dt), 1.0 / dt) * a_bar
        bar0["v"] -= dv
        bar0["a"] -= np.where(free, (1.0 - g) / g * a_bar, 0.0)
        return bar1["q"], bar1["v"] + dv, bar0

    def pull_back(self, s0, lin, bar0, qb_bar, vh_bar):
        g = self.gamma
        dt = lin.h / g
        bar0["q"] += qb_bar
        bar0["v"] += (1.0 - g) * dt * qb_bar + vh_bar
        bar0["a"] += (0.5 - g) * dt * dt * qb_bar + (1.0 - g) * dt * vh_bar

    def finish(self, adj, s0, bar0):
        """``M a_0 + g(q_0, v_0) = 0``: the step equation's terms at ``h = 1`` with ``u = v_0``
        and ``v_hat = v_0 - a_0`` (so inertia's ``M (u - v_hat)`` is ``M a_0``)."""
        a_bar = bar0["a"]
        if not np.any(a_bar[adj.free]):
            return
        q, v, a = s0.q.reshape(-1), s0.v.reshape(-1), s0.history["a"].reshape(-1)
        lf = np.zeros(q.size)
        lf[adj.free] = spla.spsolve(adj.run.system.mass_free.tocsc(), a_bar[adj.free])
        pair = StepPair(q0=q, v0=v, q1=q, u=v, dt=adj.dt, t1=s0.t, t0=s0.t, step=s0.step,
                        h=1.0, qb=q, vh=v - a)
        for term in adj.terms:
            if term in adj.run.terms:  # registered (contact): its force at q_0 alone
                force_vjp = getattr(term, "start_force_vjp", None)
                if force_vjp is not None:
                    bar0["q"] += force_vjp(q, s0.t, lf, adj.grads)
                continue
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
