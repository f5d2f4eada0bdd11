"""Static equilibrium: each step minimises the potential energy at the end of the step.

The unknowns are the free DOFs' displacements from ``q_n``: ``q(x) = q_base + x`` (``h =
1``, ``q_base = q_n`` with the pins at their time-``t + dt`` positions). The objective is the
terms without inertia and Rayleigh damping (no velocities in an equilibrium): elasticity,
pull springs, gravity's potential ``-f_g . x`` and contact (barrier; friction is lagged at
``q_n``, so a body pressed onto an obstacle holds where friction can hold it). A run of
static steps is a quasi-static load path: gravity, keyframed pins, scripted pulls and
obstacles at each step's end time. The state's velocities are zero.

Load stepping: when Newton fails on the whole step (no acceptable step, or not converged
within ``converged_max_iterations``) the load is applied in increments ``lambda``: the pins
go ``lambda`` of their way and the objective is ``E(x) - (1 - lambda) g_0 . x`` (``g_0``: its
gradient at ``x = 0``, so ``lambda = 0`` has ``q_n`` as its equilibrium: a homotopy that
ramps every load, whatever term it comes from); a failed increment is halved, down to
``1 / 2**MAX_HALVINGS``. ``StepStats.load_increments`` counts the solves.

The Newton matrix has no mass; where it is singular or indefinite (a body held only by
contact, compressed tets) :meth:`System.factorize`'s shift ladder adds ``mu M``: a
Levenberg-Marquardt step toward mass-weighted gradient descent, which is what a mass-free
scheme needs (the identity would weigh DOFs by mesh resolution).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from fem3d.errors import SimulationError
from fem3d.physics.model import validate_dt
from fem3d.physics.terms.base import Term, as_term
from fem3d.solve.minimise import minimise_step
from fem3d.solve.objective import Objective
from fem3d.solve.settings import NewtonSettings
from fem3d.solve.state import State, StepStats, check_finite
from fem3d.solve.step_maps import affine_step_map, end_positions
from fem3d.solve.system import System

__all__ = ["static", "LoadRamp", "MAX_HALVINGS"]

#: The smallest load increment is ``1 / 2**MAX_HALVINGS`` of a step's.
MAX_HALVINGS = 6


class LoadRamp(Term):
    """``c . x``: the homotopy term of a partial load (see the module docstring)."""

    name = "load ramp"
    variable = "velocity"

    def __init__(self, c: np.ndarray) -> None:
        self.c = c

    def energy(self, x: np.ndarray) -> float:
        return float(self.c @ x)

    def gradient(self, x: np.ndarray) -> np.ndarray:
        return self.c


def static(
    system: System,
    terms: Sequence,
    state: State,
    dt: float,
    settings: NewtonSettings,
    *,
    fixed_positions: np.ndarray | None = None,
    converged_max_iterations: int = 50,
) -> tuple[State, StepStats]:
    """The equilibrium at ``t + dt`` (see the module docstring).

    Parameters and returns as in :meth:`fem3d.solve.schemes.base.Scheme.step`, but Newton
    runs to convergence (at most ``converged_max_iterations`` per solve; the settings'
    ``max_iterations`` is a dynamic scheme's). ``dt`` is the load path's step.

    Raises
    ------
    SimulationError
        Newton failed on the smallest load increment.
    """
    dt = validate_dt(dt)
    settings = settings.with_(max_iterations=converged_max_iterations)
    p = end_positions(system, state, fixed_positions)
    p_n = state.q[system.constraints.fixed_vertices]
    terms = [t for t in map(as_term, terms) if not (t.inertial or t.dissipative)]
    n_free = system.constraints.n_free
    total = StepStats(load_increments=0)

    def solve(lam: float, x_start: np.ndarray) -> np.ndarray | None:
        step = affine_step_map(system, state, dt, p_n + lam * (p - p_n), h=1.0, offset=None,
                               v_hat=np.zeros(system.constraints.n_dofs), moving_pins=False)
        step_terms = terms
        if lam < 1.0:
            g0 = Objective(system, terms, step).gradient(np.zeros(n_free))
            step_terms = [*terms, LoadRamp(-(1.0 - lam) * g0)]
        step = _with_start(step, x_start)
        try:
            x, stats = minimise_step(
                system, step_terms, state, step, settings,
                converged_max_iterations=converged_max_iterations, scheme="static")
        except SimulationError:
            return None
        _merge(total, stats)
        return x if stats.converged else None

    x = _load_path(solve, np.zeros(n_free))
    if x is None:
        raise SimulationError(
            f"static: no equilibrium found even in load increments of 1/{2 ** MAX_HALVINGS} "
            "of a step (a body without support, or a load beyond what the material holds; "
            "try a smaller dt)", step=state.step)
    step = affine_step_map(system, state, dt, p, h=1.0, offset=None,
                           v_hat=np.zeros(system.constraints.n_dofs), moving_pins=False)
    q = step.positions(x).reshape(-1, 3)
    v = np.zeros_like(q)
    check_finite(q, v, state.step, "static")
    return State(q=q, v=v, t=state.t + dt, step=state.step + 1), total


def _load_path(solve, x0: np.ndarray) -> np.ndarray | None:
    """Solve at ``lambda = 1`` from ``x0``, halving failed increments (depth-first)."""
    todo = [1.0]  # the load levels still to reach, nearest last
    lam, x = 0.0, x0
    while todo:
        target = todo[-1]
        x_new = solve(target, x)
        if x_new is not None:
            lam, x = target, x_new
            todo.pop()
            continue
        if target - lam <= 1.0 / 2 ** MAX_HALVINGS:
            return None
        todo.append(0.5 * (lam + target))
    return x


def _with_start(step, x_start: np.ndarray):
    """``step`` whose Newton start (its ``v_hat``: no inertia term reads it) is ``x_start``."""
    return replace(step, v_hat_free=x_start)


def _merge(total: StepStats, stats: StepStats) -> None:
    """Add one solve's statistics to the step's."""
    total.load_increments += 1
    total.newton_iterations += stats.newton_iterations
    total.gradient_norms = stats.gradient_norms
    total.gradient_tolerance = stats.gradient_tolerance
    total.converged = stats.converged
    for name in ("line_search_halvings", "shifted_factorizations", "factorizations",
                 "cg_iterations", "psd_fallbacks", "amg_setups", "lagged_matrices"):
        setattr(total, name, getattr(total, name) + getattr(stats, name))
    for part, seconds in stats.seconds.items():
        total.add_seconds(part, seconds)
