"""The :class:`Scheme` a time integrator is: its name, the history it owns, its step map, its
finish; :func:`fem3d.solve.minimise.minimise_step` does the rest.

A step of a minimising scheme is :meth:`Scheme.step`: the scheme makes the step's
:class:`Step` (:meth:`Scheme.prepare`: the :class:`~fem3d.physics.terms.base.StepMap`
``q(x) = q_base + h P^T x`` with the inertia target ``v_hat``, a warm start, and what its
finish needs), the objective's terms are minimised over ``x`` and :meth:`Scheme.finish` maps
the minimiser back to a :class:`~fem3d.solve.state.State`, which carries the scheme's own
history (:attr:`State.history <fem3d.solve.state.State.history>`). A checkpoint saves and
restores that history through the scheme (:meth:`Scheme.save_history`,
:meth:`Scheme.restore_history`), never by field names of its own.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from fem3d.errors import ParameterError
from fem3d.physics.model import validate_dt
from fem3d.physics.springs import Pull
from fem3d.physics.terms.base import StepMap
from fem3d.solve.minimise import minimise_step
from fem3d.solve.settings import NewtonSettings
from fem3d.solve.state import State, StepStats, check_finite
from fem3d.solve.substeps import step_with_substeps
from fem3d.solve.system import System

__all__ = ["Scheme", "Step", "model_terms"]


def model_terms(system: System, pull: Pull | None = None) -> list:
    """The terms of the system's model, in objective order: inertia, elasticity, the pull
    springs, gravity and Rayleigh damping (those present)."""
    return [*system.model_terms(), system.pull_term(pull), *system.loads.terms()]


@dataclass(frozen=True, eq=False)
class Step:
    """One step as a scheme sets it up (:meth:`Scheme.prepare`).

    Attributes
    ----------
    map : StepMap
        The unknowns ``x`` and the inertia target.
    guess : (n_free,) float64 or None
        A warm start Newton also tries (:func:`~fem3d.solve.minimise.minimise_step`).
    data : dict
        What the scheme's :meth:`~Scheme.finish` needs beyond the map (Newmark: ``a_n``).
    """

    map: StepMap
    guess: np.ndarray | None = None
    data: Mapping[str, Any] = field(default_factory=dict)


class Scheme:
    """A time integrator (one object per scheme, registered by :attr:`name` in
    :mod:`fem3d.solve.schemes.registry`).

    A minimising scheme writes :meth:`prepare` and :meth:`finish`; one that is not (the
    linearly-implicit Euler) or that solves more than once (static's load path) overrides
    :meth:`step`. Everything the scene schema, the CLI, the viewer, substeps, checkpoints
    and the adjoint (:mod:`fem3d.diff.schemes`) need of a scheme is here.
    """

    #: ``simulation.integrator``
    name: ClassVar[str] = ""
    #: the name shown in the viewer and in error messages
    label: ClassVar[str] = ""
    #: a time-dependent scheme with velocities (the viewer's N key cycles through these;
    #: False: bodies may not start moving)
    dynamic: ClassVar[bool] = True
    #: minimises the objective's terms by Newton (False: no line search, no extra terms)
    minimises: ClassVar[bool] = True
    #: runs contact scenes (IPC's barrier among the terms)
    contact: ClassVar[bool] = True
    #: ``newton.warm_start = "extrapolate"`` applies
    warm_starts: ClassVar[bool] = False
    #: a contact step may be redone as substeps (:mod:`fem3d.solve.substeps`)
    substeps: ClassVar[bool] = True
    #: runs under ``mpiexec -n N`` (:mod:`fem3d.parallel`: every solve through the distributed
    #: System, Newmark's start too: :meth:`System.solve_mass`)
    distributed: ClassVar[bool] = False
    #: the history arrays the scheme's states carry (``(n, 3)`` each, by name)
    history: ClassVar[tuple[str, ...]] = ()
    #: the history that is the state one step earlier, ``{name: State field}`` (it depends
    #: on the step size: dropped at the first substep, the whole step's start again after
    #: the substeps)
    previous_state: ClassVar[Mapping[str, str]] = {}
    #: Newton's cap where a solve must converge (:meth:`NewtonSettings.converged_cap`)
    converged_max_iterations: ClassVar[int] = 100

    # ------------------------------------------------------------------ a step
    def step(self, system: System, terms: Sequence, state: State, dt: float,
             settings: NewtonSettings, *, fixed_positions: np.ndarray | None = None,
             energy_bound: float | None = None) -> tuple[State, StepStats]:
        """One step minimising the sum of ``terms`` (the whole objective, in order).

        Parameters
        ----------
        system : System
        terms : sequence of Term
            :func:`model_terms` plus e.g. contact.
        state : State
        dt : float
        settings : NewtonSettings
        fixed_positions : (n_fixed, 3) float64, optional
            The fixed vertices at the end of the step (moving pins); None: they stay.
        energy_bound : float, optional
            The total energy no stable step exceeds (the runaway guard of a scheme without
            a line search; minimising schemes ignore it).

        Returns
        -------
        (State, StepStats)

        Raises
        ------
        SimulationError
            No acceptable Newton step, an inadmissible start, or a non-finite state.
        """
        dt = validate_dt(dt)
        step = self.prepare(system, terms, state, dt, fixed_positions, settings)
        x, stats = minimise_step(
            system, terms, state, step.map, settings, scheme=self.label, guess=step.guess,
            converged_max_iterations=settings.converged_cap(self.converged_max_iterations))
        new = self.finish(system, state, step, x, settings)
        check_finite(new.q, new.v, state.step, self.label)
        return new, stats

    def prepare(self, system: System, terms: Sequence, state: State, dt: float,
                fixed_positions: np.ndarray | None, settings: NewtonSettings) -> Step:
        """The step's map (and warm start) from the state at its start."""
        raise NotImplementedError(f"{type(self).__name__} has no step map")

    def finish(self, system: System, state: State, step: Step, x: np.ndarray,
               settings: NewtonSettings) -> State:
        """The state at the end of the step from the minimiser ``x`` (free DOFs)."""
        raise NotImplementedError(f"{type(self).__name__} has no finish")

    def model_step(self, system: System, state: State, dt: float, pull: Pull | None = None,
                   *, terms: Sequence = (), fixed_positions: np.ndarray | None = None,
                   max_substeps: int = 1, energy_bound: float | None = None,
                   hessian: str = "exact", linear_solver: str = "direct",
                   **newton) -> tuple[State, StepStats]:
        """One step of the system's model (:func:`model_terms`) plus ``terms``, the Newton
        settings as keywords (:meth:`NewtonSettings.make`), redone in up to
        ``max_substeps`` substeps where contact needs it."""
        settings = NewtonSettings.make(hessian, linear_solver, **newton)
        return self.advance(system, [*model_terms(system, pull), *terms], state, dt, settings,
                            fixed_positions=fixed_positions, max_substeps=max_substeps,
                            energy_bound=energy_bound)

    def advance(self, system: System, terms: Sequence, state: State, dt: float,
                settings: NewtonSettings, *, fixed_positions: np.ndarray | None = None,
                fixed_at=None, max_substeps: int = 1,
                energy_bound: float | None = None) -> tuple[State, StepStats]:
        """:meth:`step`, redone as substeps where a contact step needs them (schemes that
        allow it; :func:`fem3d.solve.substeps.step_with_substeps`)."""
        if max_substeps == 1 or not self.substeps:
            return self.step(system, terms, state, dt, settings,
                             fixed_positions=fixed_positions, energy_bound=energy_bound)
        return step_with_substeps(self, system, terms, state, dt, settings,
                                  max_substeps=max_substeps, fixed_positions=fixed_positions,
                                  fixed_at=fixed_at)

    # ------------------------------------------------------------------ history
    def acceleration(self, before: State, state: State, dt: float) -> np.ndarray | None:
        """``(3n,)`` the acceleration the step from ``before`` to ``state`` holds at its end
        (the reactions' inertia): the backward difference ``(v - v_n) / dt`` here; None for a
        scheme without inertia."""
        if not self.dynamic:
            return None
        return (state.v - before.v).reshape(-1) / dt

    def save_history(self, state: State) -> dict[str, np.ndarray]:
        """The history a checkpoint keeps: ``{name: (n, 3)}`` of :attr:`history` present."""
        return {k: state.history[k] for k in self.history if k in state.history}

    def restore_history(self, saved: Mapping[str, np.ndarray],
                        shape: tuple[int, ...]) -> dict[str, np.ndarray]:
        """The history of :attr:`history` in ``saved`` (empty arrays: absent), checked.

        Raises
        ------
        ParameterError
            A saved array of another shape, or not finite.
        """
        out = {}
        for k in self.history:
            a = np.array(saved.get(k, np.zeros(0)), dtype=np.float64)
            if a.size:
                if a.shape != shape or not np.isfinite(a).all():
                    raise ParameterError(f"saved {k} has shape {a.shape} or is not finite")
                out[k] = a
        return out

    def begin_substeps(self, state: State) -> State:
        """The state the first substep starts from: without :attr:`previous_state`."""
        if not any(k in state.history for k in self.previous_state):
            return state
        return state.with_history(**{k: v for k, v in state.history.items()
                                     if k not in self.previous_state})

    def end_substeps(self, start: State, end: State) -> State:
        """The state after the substeps: :attr:`previous_state` one whole step back again
        (the step's start), where the last substep carried it."""
        if not any(k in end.history for k in self.previous_state):
            return end
        return end.with_history(**{**end.history, **{k: getattr(start, f) for k, f
                                                     in self.previous_state.items()}})

    def __repr__(self) -> str:
        return f"<scheme {self.name}>"
