"""The adjoint of BDF2 (:mod:`fem3d.solve.schemes.bdf2`).

A BDF2 step from a state with history (``q_{n-1}``, ``v_{n-1}``: its history's ``q_prev``,
``v_prev``) is backward Euler's step equation with ``h = 2 dt / 3``,
``q_B = (4 q_n - q_{n-1}) / 3``, ``v_hat = (4 v_n - v_{n-1}) / 3`` (the pins at ``p_{n+1}``
with the secant velocity ``(p_{n+1} - q_n[F]) / dt``); the first step (no history) is a
backward-Euler step. The state after a step carries ``q_n``, ``v_n`` as its history, so the
backward pass carries the cotangents of two states: a state's ``q_prev``, ``v_prev``
cotangents flow to the state before it.

With contact the friction is lagged at ``q_n`` (the step's start, not ``q_B``) and its slip
is ``q_{n+1} - q_n``: the contact term's ``q_B`` and ``q_t`` products
(:class:`fem3d.diff.contact.ContactAdjoint`) carry the two apart.
"""

from __future__ import annotations

from fem3d.diff.schemes import SchemeAdjoint, StepLin, register_scheme
from fem3d.solve.schemes.bdf2 import BDF2

__all__ = ["BDF2Adjoint"]


class BDF2Adjoint(SchemeAdjoint):
    """BDF2 (see the module docstring)."""

    scheme = BDF2()
    contact = True

    def linear(self, s0, dt):
        if "q_prev" not in s0.history:  # the start-up step: backward Euler
            return super().linear(s0, dt)
        q, v = s0.q.reshape(-1), s0.v.reshape(-1)
        q_prev, v_prev = s0.history["q_prev"].reshape(-1), s0.history["v_prev"].reshape(-1)
        return StepLin(h=2.0 * dt / 3.0, tau=dt, qb=(4.0 * q - q_prev) / 3.0,
                       vh=(4.0 * v - v_prev) / 3.0)

    def split(self, s0, s1, bar1, fixed):
        bar0 = self.zero(s0)
        bar0["q"] += bar1["q_prev"]  # the state after the step carries q_n, v_n
        bar0["v"] += bar1["v_prev"]
        return bar1["q"], bar1["v"], bar0

    def pull_back(self, s0, lin, bar0, qb_bar, vh_bar):
        if "q_prev" not in s0.history:
            super().pull_back(s0, lin, bar0, qb_bar, vh_bar)
            return
        bar0["q"] += 4.0 / 3.0 * qb_bar
        bar0["v"] += 4.0 / 3.0 * vh_bar
        bar0["q_prev"] -= qb_bar / 3.0
        bar0["v_prev"] -= vh_bar / 3.0


register_scheme(BDF2Adjoint())
