"""The adjoint of the static scheme (:mod:`fem3d.solve.schemes.static`, :mod:`fem3d.solve.static`).

A static step is the equilibrium ``P [dV/dq(q_{n+1}) - M g_grav] = 0`` at the pins'
end-of-step positions ``p_{n+1}``, ``q_{n+1} = q_n + x`` (``h = 1``, ``q_B = q_n``); no
inertia, no damping, velocities zero. Its adjoint is one solve with the exact (unprojected)
Hessian ``H_ff(q_{n+1})`` per step; the cotangent of ``q_n`` through ``q_B`` cancels
(``q_{n+1}`` does not depend on ``q_n`` where the equilibrium is unique: ``q_n`` is only
Newton's start). With contact the barrier ``kappa B(q_{n+1})`` joins the equilibrium, and
the friction lagged at ``q_n`` (normal forces, slip ``q_{n+1} - q_n`` against ``eps_v dt``):
through it, and only through it, ``q_{n+1}`` depends on ``q_n``
(:meth:`fem3d.diff.contact.ContactAdjoint.start_vjp`). The load path's increments
(:data:`fem3d.solve.static.MAX_HALVINGS`) change how Newton gets there, not the
equilibrium, so they are not differentiated.
"""

from __future__ import annotations

import numpy as np

from fem3d.diff.schemes import SchemeAdjoint, StepLin, converged_settings, register_scheme
from fem3d.solve.schemes.static import Static

__all__ = ["StaticAdjoint"]


class StaticAdjoint(SchemeAdjoint):
    """``h = tau = 1``, ``q_B = q_n`` (the pins' ``w = p - q_n[F]``: a displacement)."""

    scheme = Static()
    contact = True

    def forward(self, run, state, terms):
        return self.scheme.step(
            run.system, terms, state, run.dt,
            converged_settings(run).with_(converged_max_iterations=200),
            fixed_positions=run.fixed_positions(state.t + run.dt))

    def linear(self, s0, dt):
        return StepLin(h=1.0, tau=1.0, qb=s0.q.reshape(-1), vh=None)

    def split(self, s0, s1, bar1, fixed):
        return bar1["q"], np.zeros_like(bar1["q"]), self.zero(s0)  # v_{n+1} = 0

    def pull_back(self, s0, lin, bar0, qb_bar, vh_bar):
        bar0["q"] += qb_bar


register_scheme(StaticAdjoint())
