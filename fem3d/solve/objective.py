"""One step's objective: the sum of the terms over the step's unknowns.

``E(x) = sum_i T_i(u_i(x))`` with ``u_i`` the positions ``q(x)`` for position terms and ``x``
itself for velocity terms (:class:`fem3d.physics.terms.base.StepMap`). Energies are summed
in the order of the terms; the gradients of the position terms are summed in positions and
mapped once by the chain rule (``h P``), then the velocity terms' gradients are added in
order; each term adds its Hessian to the Newton matrix in order
(:class:`fem3d.solve.newton_matrix.NewtonMatrixBuilder`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np
import scipy.sparse as sp

from fem3d.physics.terms.base import NewtonPolicy, StepMap, Term, as_term, overrides
from fem3d.solve.newton_matrix import NewtonMatrixBuilder
from fem3d.solve.system import System

__all__ = ["Objective"]


class Objective:
    """The terms of one step, bound to its :class:`StepMap`.

    Parameters
    ----------
    system : System
    terms : iterable of Term (or plain position-term objects, see
        :class:`fem3d.physics.terms.base.PositionTerm`)
        In objective order; inactive terms (:attr:`Term.active`) are left out.
    step : StepMap
        Each term's :meth:`Term.begin_step` is called with it, in order.
    """

    def __init__(self, system: System, terms: Iterable, step: StepMap) -> None:
        self.system = system
        self.step = step
        self.terms: list[Term] = [t for t in map(as_term, terms) if t.active]
        for term in self.terms:
            term.begin_step(step)
        self.requires_convergence = any(t.requires_convergence for t in self.terms)
        self.allows_lagged_matrix = all(t.allows_lagged_matrix for t in self.terms)
        self.energy_scale = sum(t.energy_scale for t in self.terms)
        #: what the active terms ask of Newton, combined
        self.policy = NewtonPolicy.combine(t.newton_policy for t in self.terms)
        self._positional = [t for t in self.terms if t.variable == "position"]
        self._velocity = [t for t in self.terms if t.variable != "position"]
        self._clamping = [t for t in self.terms if overrides(t, "max_step")]
        self._stopping = [t for t in self.terms if overrides(t, "newton_converged")]
        self._changing = [t for t in self.terms if overrides(t, "after_iteration")]
        self._stiffening = [t for t in self.terms if overrides(t, "initialize_stiffness")]

    # -- value, gradient, Newton matrix -----------------------------------------------------
    def positions(self, x: np.ndarray) -> np.ndarray:
        """``q(x)``, ``(3n,)``."""
        return self.step.positions(x)

    def energy(self, x: np.ndarray) -> float:
        """``E(x)``; ``+inf`` at an inadmissible point (or a non-finite sum)."""
        q = self.positions(x)
        e = 0.0
        for term in self.terms:
            e += float(term.energy(q if term.variable == "position" else x))
            if not math.isfinite(e):
                return math.inf
        return e

    def gradient(self, x: np.ndarray, *, without: Iterable[Term] = ()) -> np.ndarray:
        """``dE/dx``, ``(n_free,)`` (``without``: terms left out)."""
        positional, velocity = self._positional, self._velocity
        if without:
            skip = {id(t) for t in without}
            positional = [t for t in positional if id(t) not in skip]
            velocity = [t for t in velocity if id(t) not in skip]
        g = None
        if positional:
            q = self.positions(x)
            gq = np.array(positional[0].gradient(q), dtype=np.float64)
            for term in positional[1:]:
                gq += term.gradient(q)
            g = self.step.h * gq[self.step.constraints.free_dofs]
        for term in velocity:
            g = np.array(term.gradient(x), dtype=np.float64) if g is None else \
                g + term.gradient(x)
        return g

    def matrix(self, x: np.ndarray, psd: bool) -> sp.csr_matrix:
        """The Newton matrix ``d2E/dx2`` at ``x`` (``psd``: the terms' PSD-projected
        Hessians), on :attr:`System.pattern_free` or the solver's widened pattern."""
        q = self.positions(x)
        builder = NewtonMatrixBuilder(self.system, self.step.h * self.step.h, psd)
        for term in self.terms:
            term.add_hessian(q if term.variable == "position" else x, builder)
        return builder.matrix()

    # -- the line search's hooks -----------------------------------------------------------
    @property
    def clamps(self) -> bool:
        """Some term limits the step (CCD)."""
        return bool(self._clamping)

    def max_step(self, x: np.ndarray, dx: np.ndarray) -> float:
        """The largest admissible fraction of the step ``dx`` from ``x`` (at most 1)."""
        q = self.positions(x)
        dq = self.step.position_change(dx)
        return min([1.0] + [float(t.max_step(q, dq)) for t in self._clamping])

    @property
    def has_stopping_rule(self) -> bool:
        """Some term has its own rule on the Newton step (IPC's velocity tolerance)."""
        return bool(self._stopping)

    def step_converged(self, x: np.ndarray, dx: np.ndarray) -> bool:
        """Every term with a stopping rule accepts the Newton step ``dx``."""
        dq = self.step.position_change(dx)
        votes = [t.newton_converged(dq) for t in self._stopping]
        return all([v is None or bool(v) for v in votes])

    @property
    def changes_between_iterates(self) -> bool:
        """Some term may change at an accepted iterate (adaptive barrier stiffness)."""
        return bool(self._changing)

    def after_iteration(self, x: np.ndarray) -> bool:
        """Call every term's :meth:`Term.after_iteration`; True when the objective changed."""
        q = self.positions(x)
        return any([t.after_iteration(q) for t in self._changing])

    def relag(self, x: np.ndarray) -> bool:
        """Newton converged at ``x``: every term's :meth:`Term.relag`; True when one asks for
        another solve."""
        q = self.positions(x)
        return any([t.relag(q) for t in self.terms])

    @property
    def initializes_stiffness(self) -> bool:
        """Some term sets its stiffness from the rest of the objective at Newton's start."""
        return bool(self._stiffening)

    def initialize_stiffness(self, x0: np.ndarray, average_mass: float) -> None:
        """Give each such term the gradient of the other terms at ``x0`` in positions (per
        unit ``h``; fixed DOFs zeroed)."""
        c = self.step.constraints
        grad_rest = c.expand_zero(self.gradient(x0, without=self._stiffening)) / self.step.h
        q = self.positions(x0)
        for term in self._stiffening:
            term.initialize_stiffness(q, grad_rest, average_mass)
