"""A step's state and statistics, and where the pinned vertices go over a step.

A state is immutable (:class:`State`); an integrator is ``step(...) -> (State, StepStats)``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from fem3d.errors import ParameterError, SimulationError
from fem3d.physics.model import Model

__all__ = ["State", "StepStats", "Pins", "pins_over_step", "new_state", "place_pins",
           "check_finite"]


@dataclass(frozen=True, eq=False)
class State:
    """Positions and velocities at one instant.

    Attributes
    ----------
    q : (n, 3) float64
        Positions.
    v : (n, 3) float64
        Velocities.
    t : float
        Time.
    step : int
        Number of steps taken to get here.
    history : mapping of str to (n, 3) float64
        What the scheme that made the state carries to its next step, by name, never changed
        once made (:attr:`fem3d.solve.schemes.base.Scheme.history`: BDF2's ``q_prev``,
        ``v_prev``, the positions and velocities one step earlier; Newmark's acceleration
        ``a``). A name absent: no history (the scheme starts afresh: BDF2 with a
        backward-Euler step).
    """

    q: np.ndarray
    v: np.ndarray
    t: float = 0.0
    step: int = 0
    history: Mapping[str, np.ndarray] = field(default_factory=dict)

    def with_history(self, **history: np.ndarray) -> State:
        """The same instant with ``history`` (and nothing else) as its history."""
        return replace(self, history=history)

    @classmethod
    def at_rest(cls, model: Model) -> State:
        """Rest positions, zero velocity, ``t = 0``."""
        return cls(q=model.X.copy(), v=np.zeros_like(model.X), t=0.0, step=0)


@dataclass
class StepStats:
    """What one step did.

    Attributes
    ----------
    newton_iterations : int
        Newton iterations (1 for the linearly-implicit scheme: one linear solve).
    gradient_norms : list of float
        Norm of the objective's gradient at each Newton iterate (implicit Euler).
    line_search_halvings : int
        Total step halvings in the line searches.
    factorizations, cg_iterations : int
        Numeric factorizations and preconditioned-CG iterations of the step's linear solves.
    shifted_factorizations : int
        Factorizations that needed a diagonal shift (indefinite Hessian).
    psd_fallbacks : int
        Newton iterations whose exact Hessian no shift made positive definite (with
        ``"reuse"``: that was indefinite), solved with the PSD-projected Hessian instead.
    gradient_tolerance : float
        The ``||g||`` Newton aimed for (implicit Euler); a converged step can end above it
        only where the line search met the objective's round-off.
    converged : bool
        Newton stopped on its tolerance (or at round-off), not on the iteration cap.
    amg_setups : int
        AMG hierarchies built during the step (``"amg"`` back end).
    lagged_matrices : int
        Newton iterations that solved with the previous iterate's Newton matrix instead of
        assembling one (``"reuse"``).
    load_increments : int
        ``static``: the equilibrium solves of the step (1: the whole load at once; more: the
        load was applied in smaller increments after a Newton failure).
    substeps : int
        The substeps the step was taken in (:mod:`fem3d.solve.substeps`; 1: the whole step at
        once). The other counts then sum every attempt, the rejected ones included.
    seconds : dict of str to float
        Wall time of the step's parts (implicit Euler): ``"matrix"`` (Newton-matrix
        assembly), ``"factorize"``, ``"cg"`` (CG iterations, preconditioner included),
        ``"amg_setup"``, ``"objective"`` (energies and gradients, line search included).
    """

    newton_iterations: int = 0
    gradient_norms: list[float] = field(default_factory=list)
    line_search_halvings: int = 0
    shifted_factorizations: int = 0
    converged: bool = True
    factorizations: int = 0
    cg_iterations: int = 0
    psd_fallbacks: int = 0
    gradient_tolerance: float = 0.0
    amg_setups: int = 0
    lagged_matrices: int = 0
    load_increments: int = 0
    substeps: int = 1
    seconds: dict[str, float] = field(default_factory=dict)

    def add_seconds(self, part: str, seconds: float) -> None:
        """Accumulate wall time into :attr:`seconds`."""
        self.seconds[part] = self.seconds.get(part, 0.0) + seconds


@dataclass(frozen=True, eq=False)
class Pins:
    """The fixed vertices over one step: end positions ``p`` and velocities ``v_c``."""

    p: np.ndarray  # (n_fixed, 3) positions at the end of the step
    q_base: np.ndarray  # (3n,) q_t with the fixed DOFs at p
    v_fixed: np.ndarray | None  # (3n,) v_c on fixed DOFs, 0 on free ones (None: static pins)
    v_t_fixed: np.ndarray | None  # (3n,) v_t on fixed DOFs, 0 on free ones


def pins_over_step(constraints, state: State, dt: float, fixed_positions) -> Pins:
    """Where the fixed vertices go this step (``fixed_positions`` None: they stay)."""
    c = constraints
    fv = c.fixed_vertices
    q_t = state.q.reshape(-1)
    fixed_dofs = c.fixed_dofs
    v_t_fixed = None
    if fixed_dofs.size and np.any(state.v.reshape(-1)[fixed_dofs]):
        v_t_fixed = np.zeros(c.n_dofs)
        v_t_fixed[fixed_dofs] = state.v.reshape(-1)[fixed_dofs]
    if fixed_positions is None:
        v_fixed = None if v_t_fixed is None else np.zeros(c.n_dofs)
        return Pins(state.q[fv], q_t, v_fixed, v_t_fixed)
    p = np.array(fixed_positions, dtype=np.float64)
    if p.shape != (fv.size, 3):
        raise ParameterError(f"fixed_positions must have shape ({fv.size}, 3), got {p.shape}")
    if not np.isfinite(p).all():
        raise ParameterError("fixed_positions are not finite")
    p_fixed = p.reshape(-1)[c.fixed_slots]
    q_base = q_t.copy()
    q_base[fixed_dofs] = p_fixed
    v_fixed = np.zeros(c.n_dofs)
    v_fixed[fixed_dofs] = (p_fixed - q_t[fixed_dofs]) / dt
    if v_t_fixed is None:
        v_t_fixed = np.zeros(c.n_dofs)
    return Pins(p, q_base, v_fixed, v_t_fixed)


def new_state(constraints, state: State, v_free: np.ndarray, dt: float) -> State:
    """``q+ = q_t + dt v+`` from the free velocities; fixed DOFs at rest."""
    v = constraints.expand_zero(v_free).reshape(-1, 3)
    q = state.q + dt * v
    if constraints.fixed_vertices.size:  # fixed DOFs stay exactly at rest
        fd = constraints.fixed_dofs
        q.reshape(-1)[fd] = constraints.x0[fd]
    return State(q=q, v=v, t=state.t + dt, step=state.step + 1)


def place_pins(constraints, new: State, pins: Pins) -> State:
    """``new`` with the fixed DOFs where ``pins`` puts them (exactly) and their velocity."""
    fv = constraints.fixed_vertices
    if fv.size == 0:
        return new
    fd = constraints.fixed_dofs
    q = np.array(new.q)
    q.reshape(-1)[fd] = pins.p.reshape(-1)[constraints.fixed_slots]
    v = new.v
    if pins.v_fixed is not None:
        v = np.array(v)
        v.reshape(-1)[fd] = pins.v_fixed[fd]
    return State(q=q, v=v, t=new.t, step=new.step)


def check_finite(q: np.ndarray, v: np.ndarray, step: int, what: str) -> None:
    """Raise when the new state is not finite."""
    if not (np.isfinite(q).all() and np.isfinite(v).all()):
        raise SimulationError(
            f"{what} exploded: the new state has non-finite positions or velocities "
            "(state left at the last good step)",
            step=step,
        )
