"""How an integrator's step enters the adjoint (:mod:`fem3d.diff.adjoint`).

Every implicit scheme solves, per step, ``g(u; q_B, v_hat, q_t, p) = 0`` over the free DOFs of
a full "velocity" ``u`` (:mod:`fem3d.solve.step_maps`): ``q_{n+1} = q_B + h u``, the pins'
part ``u[F] = w = (p_{n+1} - q_t[F]) / tau`` (so ``q_B[F] = p - h w``), and::

    g = P [M (u - v_hat) + h dV/dq(q_{n+1}) - h M g_grav + h D(q_t) u]     (dynamic)
    g = P [dV/dq(q_{n+1}) - M g_grav]                                          (static)

The adjoint's core (terms, one transposed solve, the pins) is the same for every scheme; a
:class:`SchemeAdjoint` gives the rest: its forward step run to convergence, ``h``, ``tau``,
``q_B`` and ``v_hat`` as functions of the state before the step (:meth:`~SchemeAdjoint.
linear`), and their adjoint: the cotangents of ``(q_{n+1}, v_{n+1})`` from the state's
after the step (:meth:`~SchemeAdjoint.split`), the state's before the step from those of
``q_B`` and ``v_hat`` (:meth:`~SchemeAdjoint.pull_back`). A state's cotangent is a dict of
flat arrays by :class:`~fem3d.solve.state.State` field (``q``, ``v``, and ``q_prev``,
``v_prev``, ``a`` where the scheme's state carries them).

:func:`register_scheme` adds a scheme by its ``simulation.integrator`` name: backward Euler
here, ``static`` (:mod:`fem3d.diff.static`), ``bdf2`` (:mod:`fem3d.diff.bdf2`) and
``newmark`` (:mod:`fem3d.diff.newmark`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fem3d.solve.backward_euler import backward_euler, newton_options
from fem3d.solve.state import State, StepStats

__all__ = ["StepLin", "SchemeAdjoint", "BackwardEulerAdjoint", "register_scheme", "SCHEMES",
           "converged_settings"]


@dataclass
class StepLin:
    """One step's affine map: ``q_{n+1} = q_B + h u``, pins ``w = (p - q_t[F]) / tau``,
    inertia target ``v_hat`` (``(3n,)``; None: static)."""

    h: float
    tau: float
    qb: np.ndarray
    vh: np.ndarray | None


class SchemeAdjoint:
    """An integrator as the adjoint sees it (see the module docstring)."""

    #: ``simulation.integrator``
    name = ""
    #: inertia and Rayleigh damping in the step, ``v_{n+1} = u`` (False: static)
    dynamic = True
    #: whether registered terms (contact) may join its steps (every scheme here: the contact
    #: term reads the step map's ``h``, ``q_B`` and the step's start ``q_t`` apart)
    contact = False

    def start(self, run, state: State) -> State:
        """The first state as the scheme's steps read it (default: ``state``). Called once
        the run's registered terms are made; a scheme whose step map depends on them puts an
        instance of its own into ``run.scheme`` here (Newmark with contact: its ``gamma``)."""
        return state

    def finish(self, adj, s0: State, bar0: dict) -> None:
        """Pull the first state's cotangent back through :meth:`start` (default: nothing)."""

    def forward(self, run, state: State, terms: list) -> tuple[State, StepStats]:
        """One step from ``state`` with the objective ``terms``, Newton run to convergence."""
        raise NotImplementedError

    def linear(self, s0: State, dt: float) -> StepLin:
        """The step's ``h``, ``tau``, ``q_B``, ``v_hat`` from the state before it."""
        return StepLin(h=dt, tau=dt, qb=s0.q.reshape(-1), vh=s0.v.reshape(-1))

    def zero(self, s: State) -> dict:
        """A zero cotangent of ``s``."""
        return {f: np.zeros(s.q.size) for f in ("q", "v", "q_prev", "v_prev", "a")
                if getattr(s, f) is not None}

    def split(self, s0: State, s1: State, bar1: dict, fixed: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, dict]:
        """``(q1_bar, v1_bar, bar0)``: the cotangents of ``q_{n+1}``, ``v_{n+1}`` as the step
        equation sees them, and what ``bar1`` gives the state before the step directly
        (``fixed``: the pinned DOFs)."""
        return bar1["q"], bar1["v"], self.zero(s0)

    def pull_back(self, s0: State, lin: StepLin, bar0: dict, qb_bar: np.ndarray,
                  vh_bar: np.ndarray) -> None:
        """Add the cotangents of ``q_B`` (free DOFs) and ``v_hat`` into ``bar0``."""
        bar0["q"] += qb_bar
        bar0["v"] += vh_bar


def converged_settings(run) -> dict:
    """The forward step's Newton settings: to ``run.rtol``, exact Hessian, direct solver."""
    return dict(rtol=run.rtol, atol_factor=run.atol_factor, linear_solver="direct",
                options=newton_options("exact"))


class BackwardEulerAdjoint(SchemeAdjoint):
    """``simulation.integrator = "implicit"``: ``h = tau = dt``, ``q_B = q_n``,
    ``v_hat = v_n``."""

    name = "implicit"
    contact = True

    def forward(self, run, state, terms):
        return backward_euler(run.system, terms, state, run.dt,
                              fixed_positions=run.fixed_positions(state.t + run.dt),
                              max_iterations=None, **converged_settings(run))


#: The schemes by ``simulation.integrator`` name.
SCHEMES: dict[str, SchemeAdjoint] = {}


def register_scheme(scheme: SchemeAdjoint) -> None:
    """Make ``scheme`` the adjoint of ``simulation.integrator = scheme.name``."""
    SCHEMES[scheme.name] = scheme


register_scheme(BackwardEulerAdjoint())
