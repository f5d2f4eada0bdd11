"""Static equilibrium: each step minimises the potential energy at the end of the step.

The unknowns are the free DOFs' displacements from ``q_n``: ``q(x) = q_base + x`` (``h =
1``, ``q_base = q_n`` with the pins at their time-``t + dt`` positions). The objective is the
terms without inertia and Rayleigh damping (no velocities in an equilibrium): elasticity,
pull springs, gravity's potential ``-f_g . x`` and contact (barrier; friction is lagged at
``q_n``, so a body pressed onto an obstacle holds where friction can hold it). A run of
static steps is a quasi-static load path: gravity, keyframed pins, scripted pulls and
obstacles at each step's end time. The state's velocities are zero.

Load stepping: when Newton fails on the whole step (no acceptable step, an inadmissible
start, or not converged within ``max_iterations``) the load is applied in increments
``lambda``: the pins go ``lambda`` of their way and the objective is ``E_lambda(x) - (1 -
lambda) g_0 . x`` with ``g_0`` the gradient of the step's objective at ``x = 0`` *with the
pins where the last equilibrium had them* (``p_n``). So ``lambda = 0`` has ``q_n`` as its
equilibrium, ``lambda = 1`` is the step, and in between every load (gravity, tractions,
pressure, pulls, their keyframes) is ``(1 - lambda) L_n + lambda L_(n+1)`` while the pins
sit at ``p_n + lambda (p - p_n)``, their forces on the free DOFs included in full (a ramp
that cancelled ``(1 - lambda)`` of the gradient with the pins already moved would cancel
that much of the moved pins' pull too: the free DOFs would lag behind the pins as
``lambda^2``). A failed increment is halved, down to ``1 / 2**MAX_HALVINGS``.
``StepStats.load_increments`` counts the solves.

Convergence: ``||g|| <= max(rtol ||g_start||, STATIC_ATOL_FACTOR E L^2)`` per solve (``L``
the diagonal of the rest bounding box): the absolute floor is about ten times the
gradient's round-off (measured: ``1.1e-16 E L^2`` on a 20 x 4 x 4 beam), so a tiny load
still converges to ``rtol`` of itself.

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
from fem3d.solve.reductions import WHOLE, Reductions
from fem3d.solve.settings import NewtonSettings
from fem3d.solve.state import State, StepStats, check_finite
from fem3d.solve.step_maps import affine_step_map, end_positions
from fem3d.solve.system import System

__all__ = ["static", "LoadRamp", "MAX_HALVINGS", "STATIC_ATOL_FACTOR"]

#: The smallest load increment is ``1 / 2**MAX_HALVINGS`` of a step's.
MAX_HALVINGS = 6

#: The absolute gradient floor as a fraction of ``E L^2`` (see the module docstring).
STATIC_ATOL_FACTOR = 1e-15


class LoadRamp(Term):
    """``c . x``: the homotopy term of a partial load (see the module docstring)."""

    name = "load ramp"
    variable = "velocity"

    def __init__(self, c: np.ndarray, reductions: Reductions = WHOLE) -> None:
        self.c = c
        self.reductions = reductions  # an MPI rank's x: c . x over the ranks

    def energy(self, x: np.ndarray) -> float:
        return self.reductions.dot(self.c, x)

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
    atol_factor: float = STATIC_ATOL_FACTOR,
    converged_max_iterations: int = 50,
) -> tuple[State, StepStats]:
    """The equilibrium at ``t + dt`` (see the module docstring).

    Parameters and returns as in :meth:`fem3d.solve.schemes.base.Scheme.step`, but each
    solve must converge: the settings' ``max_iterations`` caps the Newton iterations of each
    load increment (None: ``converged_max_iterations``), and one that does not converge within
    it is halved. ``dt`` is the load path's step.

    Raises
    ------
    SimulationError
        Newton failed on the smallest load increment.
    """
    dt = validate_dt(dt)
    p = end_positions(system, state, fixed_positions)
    p_n = state.q[system.constraints.fixed_vertices]
    terms = [t for t in map(as_term, terms) if not (t.inertial or t.dissipative)]
    n_free = system.constraints.n_free
    total = StepStats(load_increments=0)
    cap = settings.converged_cap(converged_max_iterations) if settings.max_iterations is None \
        else settings.max_iterations
    settings = settings.with_(max_iterations=cap, atol_factor=atol_factor)
    ramp = _Ramp(system, terms, state, dt, p_n, p)

    def solve(lam: float, x_start: np.ndarray) -> np.ndarray | None:
        step = _with_start(ramp.step_map(lam), x_start)
        try:
            x, stats = minimise_step(
                system, ramp.terms(lam), state, step, settings,
                converged_max_iterations=converged_max_iterations,
                scheme="static")
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
    step = ramp.step_map(1.0)
    q = step.positions(x).reshape(-1, 3)
    v = np.zeros_like(q)
    check_finite(q, v, state.step, "static")
    return State(q=q, v=v, t=state.t + dt, step=state.step + 1), total


class _Ramp:
    """The objectives along one step's load path (see the module docstring): ``lambda``'s
    step map (pins at ``p_n + lambda (p - p_n)``) and terms (plus the ramp below 1)."""

    def __init__(self, system: System, terms: list[Term], state: State, dt: float,
                 p_n: np.ndarray, p: np.ndarray) -> None:
        self.system, self._terms, self.state, self.dt = system, terms, state, dt
        self.p_n, self.p = p_n, p
        self._g0: np.ndarray | None = None

    def step_map(self, lam: float):
        """``q(x) = q_n + x`` on the free DOFs, the pins ``lam`` of their way."""
        pins = self.p if lam == 1.0 else self.p_n + lam * (self.p - self.p_n)
        return affine_step_map(self.system, self.state, self.dt, pins, h=1.0, offset=None,
                               v_hat=np.zeros(self.system.constraints.n_dofs),
                               moving_pins=False)

    def terms(self, lam: float) -> list[Term]:
        """The step's terms, with ``LoadRamp(-(1 - lam) g_0)`` below ``lam = 1``."""
        if lam >= 1.0:
            return self._terms
        if self._g0 is None:  # the pins where the last equilibrium had them
            start = self.step_map(0.0)
            zero = np.zeros(self.system.constraints.n_free)
            self._g0 = Objective(self.system, self._terms, start).gradient(zero)
        return [*self._terms, LoadRamp(-(1.0 - lam) * self._g0, self.system.reductions)]


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
