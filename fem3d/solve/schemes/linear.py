"""Linearly-implicit Euler: one linear solve per step.

``(M - dt^2 K(q_t) + dt D) v+ = M v_t + dt (f(q_t) + M g)``, ``q+ = q_t + dt v+`` (``K = -H``
the stiffness of the assignment, ``f = -dV/dq``). The pull springs' force is part of ``f`` and
their stiffness part of ``K`` (the whole force is linearised). The assignment's main program
linearises only the elastic force and adds the spring force explicitly; with the scenes'
spring stiffness (``k dt^2`` far above a vertex mass) that explicit term alone makes the
scheme explode on the first step of a scripted pull, on either mesh.

As a scheme (:class:`LinearlyImplicit`) it takes the objective's terms like the others and
linearises the model's own: the pull springs it finds among them, gravity, damping and the
bodies' surface and point loads from the system's loads (a load at its size at the step's
end, as the implicit schemes take it; a follower pressure's stiffness in ``K``); a term it
cannot linearise (contact) is refused. On MPI ranks the model is a rank's tets: the
right-hand side and the energies go through :meth:`System.summed`.
"""

from __future__ import annotations

import math

import numpy as np

from fem3d.errors import SimulationError
from fem3d.physics.assembly import (
    add_element_hessians,
    assemble_gradient,
    count_inverted,
    kinetic_energy,
    potential_energy,
)
from fem3d.physics.model import validate_dt
from fem3d.physics.springs import Pull
from fem3d.physics.terms.base import as_term
from fem3d.physics.terms.pull import PullSprings
from fem3d.solve.schemes.base import Scheme
from fem3d.solve.state import (
    State,
    StepStats,
    check_finite,
    new_state,
    pins_over_step,
    place_pins,
)
from fem3d.solve.system import System

__all__ = ["linearly_implicit_euler", "LinearlyImplicit"]


def linearly_implicit_euler(
    system: System,
    state: State,
    dt: float,
    pull: Pull | None = None,
    *,
    energy_bound: float | None = None,
    linearize_pull: bool = True,
    fixed_positions: np.ndarray | None = None,
) -> tuple[State, StepStats]:
    """One linearly-implicit Euler step.

    Solves ``(M - dt^2 K(q_t) + dt D) v+ = M v_t + dt (f(q_t) + M g)`` on the free DOFs
    (``K = -H``, ``D`` the Rayleigh damping :meth:`Loads.damping_data` at ``q_t``, ``g``
    gravity) and sets ``q+ = q_t + dt v+``. The pull springs' force is part of ``f`` and their
    stiffness part of ``K``; so are the surface and point loads' (:attr:`Loads.surface`, at
    their amplitude at ``t + dt``). Moving pins: the fixed DOFs' velocity ``v_c = (p - q_t) / dt``
    is known, so the free rows solve ``A_ff v_f = rhs_f - A_fc v_c``.

    Parameters
    ----------
    system : System
    state : State
        ``q, v`` of shape ``(n, 3)``.
    dt : float
        Time step (> 0).
    pull : Pull, optional
        Active pull springs.
    energy_bound : float, optional
        Runaway threshold: if the new total energy (kinetic + strain + pull, and the
        potentials of gravity and the loads) exceeds it, raise.
        :class:`fem3d.simulation.Simulation` passes 1000 x the energy put in so far.
    linearize_pull : bool, optional
        Include the pull springs' stiffness in the matrix (default True). False gives the
        assignment's variant (spring force explicit), which explodes for the scenes' pulls.
    fixed_positions : (n_fixed, 3) float64, optional
        Positions of the fixed vertices at the end of the step (moving pins; None: they stay
        where they are). The fixed vertices land on them exactly.

    Returns
    -------
    (State, StepStats)

    Raises
    ------
    SimulationError
        ``"... exploded ..."``: non-finite state, inverted tets (non-finite energy) or energy
        above ``energy_bound``. The input ``state`` is untouched.
    """
    dt = validate_dt(dt)
    model, c = system.model, system.constraints
    qf, vf = state.q.reshape(-1), state.v.reshape(-1)
    pins = pins_over_step(c, state, dt, fixed_positions)
    f = -assemble_gradient(model, qf)
    if pull is not None:
        f -= pull.gradient(system.spring, state.q)
    if system.loads.gravity_force is not None:
        f += system.loads.gravity_force
    loads = system.loads.surface  # tractions, point forces, pressures
    stiffness = None  # their Hessian on model.pattern (a follower pressure's)
    for load in loads:
        load.at_time(state.t + dt)  # the size the implicit schemes give them: the step's end
        f -= load.gradient(qf)
        h = load.hessian_data(qf)
        if h is not None:
            stiffness = h if stiffness is None else stiffness + h
    damping = system.loads.damping_data(qf)
    A = system.newton_matrix(qf, dt, pull if linearize_pull else None, damping=damping,
                             stiffness=stiffness)
    rhs = model.mass @ vf + dt * f
    if pins.v_fixed is not None:  # move A_fc v_c to the right-hand side
        vc = pins.v_fixed
        Avc = model.mass @ vc
        hdata = np.zeros(model.nnz)
        add_element_hessians(model, "hessian", qf, system._volumes_times(dt * dt),
                             model.scatter, hdata)
        if stiffness is not None:
            hdata += (dt * dt) * stiffness
        Avc += model.csr(hdata) @ vc
        if damping is not None:
            Avc += dt * (model.csr(damping) @ vc)
        rhs = rhs - Avc
    # a distributed system's model is a rank's tets: the right-hand side is summed over the
    # ranks (the matrix is summed by the distributed solver), and so is a verdict on it, so
    # that no rank raises while another goes on to the (collective) factorization
    rhs = system.summed(rhs)
    stats = StepStats(newton_iterations=1)
    if system.summed(0.0 if np.isfinite(A.data).all() else 1.0) or \
            not np.isfinite(rhs).all():
        raise SimulationError(
            "linearly-implicit Euler exploded: non-finite forces or stiffness", step=state.step
        )
    try:
        stats.shifted_factorizations = int(system.factorize(A) > 0)
    except SimulationError as exc:
        raise SimulationError(
            f"linearly-implicit Euler exploded: {exc.reason}", step=state.step
        ) from exc
    v_free = system.solve(c.restrict(rhs))
    system.release_factorization()  # the next step factorizes anew
    new = place_pins(c, new_state(c, state, v_free, dt), pins)
    check_finite(new.q, new.v, state.step, "linearly-implicit Euler")
    _check_runaway(system, new, pull, energy_bound, state.step)
    return new, stats


def _check_runaway(system: System, new: State, pull: Pull | None,
                   energy_bound: float | None, step: int) -> None:
    """The runaway guard of a step without a line search: the total energy of ``new``
    (kinetic, strain, the pull springs', and the potentials of gravity and the surface and
    point loads: the work they did is not a runaway) finite and within ``energy_bound``.

    Raises
    ------
    SimulationError
        ``linearly-implicit Euler exploded: ...``.
    """
    model = system.model
    total = kinetic_energy(model, new.v) + potential_energy(model, new.q)
    if pull is not None:
        total += pull.energy(system.spring, new.q)
    for load in system.loads.surface:
        total += load.energy(new.q.reshape(-1))
    total = system.summed(total)
    if system.loads.gravity_force is not None:  # (the loads sum their energy themselves)
        total += system.loads.gravity_energy(new.q)
    if not math.isfinite(total):
        n_inv = int(system.summed(count_inverted(model, new.q)))
        n_tets = int(system.summed(model.n_tets))
        raise SimulationError(
            f"linearly-implicit Euler exploded: the energy is not finite ({n_inv} of "
            f"{n_tets} tets inverted); try --integrator implicit or a smaller dt", step=step)
    if energy_bound is not None and total > energy_bound:
        raise SimulationError(
            f"linearly-implicit Euler exploded: total energy {total:.3g} exceeds the runaway "
            f"bound {energy_bound:.3g}; try --integrator implicit or a smaller dt", step=step)


class LinearlyImplicit(Scheme):
    """Linearly-implicit Euler (:func:`linearly_implicit_euler`): one linear solve, no line
    search; the runaway guard ``energy_bound`` stands in for one."""

    name = "linear"
    label = "linearly-implicit Euler"
    minimises = False
    contact = False
    substeps = False
    #: the model's forces, right-hand side and energies through :meth:`System.summed`
    distributed = True

    def step(self, system, terms, state, dt, settings, *, fixed_positions=None,
             energy_bound=None):
        """One step of the model's terms among ``terms`` (the pull springs read from their
        :class:`~fem3d.physics.terms.pull.PullSprings`); ``settings`` unused."""
        own = {id(t) for t in (*system.model_terms(), *system.loads.terms())}
        pull = None
        for term in map(as_term, terms):
            if isinstance(term, PullSprings):
                pull = term.pull if pull is None else pull
            elif id(term) not in own and term.active:
                raise SimulationError(f"{self.label} linearises only the model's terms, not "
                                      f"{term.name!r} (choose a minimising integrator)",
                                      step=state.step)
        return linearly_implicit_euler(system, state, dt, pull, energy_bound=energy_bound,
                                       fixed_positions=fixed_positions)
