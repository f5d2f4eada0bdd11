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
flat arrays by name: ``q``, ``v`` and the state's history (:attr:`State.history
<fem3d.solve.state.State.history>`: ``q_prev``, ``v_prev``, ``a`` where the scheme's state
carries them).

A :class:`SchemeAdjoint` is the adjoint hook of one scheme object of
:mod:`fem3d.solve.schemes` (its :attr:`~SchemeAdjoint.scheme`; the forward step is that
scheme's own :meth:`~fem3d.solve.schemes.base.Scheme.step`): :func:`register_scheme` adds it
under the scheme's name: backward Euler here, static (:mod:`fem3d.diff.static`), BDF2
(:mod:`fem3d.diff.bdf2`) and Newmark (:mod:`fem3d.diff.newmark`). The schemes of the
registry without one are refused by name.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fem3d.solve.schemes.base import Scheme
from fem3d.solve.schemes.implicit import IMPLICIT
from fem3d.solve.settings import NewtonSettings
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

    #: the forward scheme (:mod:`fem3d.solve.schemes`)
    scheme: Scheme = IMPLICIT
    #: whether registered terms (contact) may join its steps (every scheme here: the contact
    #: term reads the step map's ``h``, ``q_B`` and the step's start ``q_t`` apart)
    contact = False

    @property
    def name(self) -> str:
        """``simulation.integrator``: the scheme's name."""
        return self.scheme.name

    @property
    def dynamic(self) -> bool:
        """Inertia and Rayleigh damping in the step, ``v_{n+1} = u`` (False: static)."""
        return self.scheme.dynamic

    def start(self, run, state: State) -> State:
        """The first state as the scheme's steps read it (default: ``state``). Called once
        the run's registered terms are made; a scheme whose step map depends on them puts an
        instance of its own into ``run.scheme`` here (Newmark with contact: its ``gamma``)."""
        return state

    def finish(self, adj, s0: State, bar0: dict) -> None:
        """Pull the first state's cotangent back through :meth:`start` (default: nothing)."""

    def forward(self, run, state: State, terms: list) -> tuple[State, StepStats]:
        """One step from ``state`` with the objective ``terms``, Newton run to convergence
        (:func:`converged_settings`)."""
        return self.scheme.step(run.system, terms, state, run.dt, converged_settings(run),
                                fixed_positions=run.fixed_positions(state.t + run.dt))

    def linear(self, s0: State, dt: float) -> StepLin:
        """The step's ``h``, ``tau``, ``q_B``, ``v_hat`` from the state before it."""
        return StepLin(h=dt, tau=dt, qb=s0.q.reshape(-1), vh=s0.v.reshape(-1))

    def zero(self, s: State) -> dict:
        """A zero cotangent of ``s``."""
        return {f: np.zeros(s.q.size) for f in ("q", "v", *s.history)}

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


def converged_settings(run) -> NewtonSettings:
    """The forward step's Newton settings: to ``run.rtol``, no iteration cap, exact Hessian,
    direct solver."""
    return NewtonSettings(max_iterations=None, rtol=run.rtol, atol_factor=run.atol_factor)


class BackwardEulerAdjoint(SchemeAdjoint):
    """Backward Euler (:data:`fem3d.solve.schemes.implicit.IMPLICIT`): ``h = tau = dt``,
    ``q_B = q_n``, ``v_hat = v_n``."""

    scheme = IMPLICIT
    contact = True


#: The adjoints by ``simulation.integrator`` name (the schemes' registry's names).
SCHEMES: dict[str, SchemeAdjoint] = {}


def register_scheme(adjoint: SchemeAdjoint) -> None:
    """Make ``adjoint`` the adjoint of its scheme (``simulation.integrator =
    adjoint.scheme.name``)."""
    SCHEMES[adjoint.name] = adjoint


register_scheme(BackwardEulerAdjoint())
