"""One step of a model as a function: the schemes of :mod:`fem3d.solve.schemes` for scripts
and tests that hold a :class:`System` and a :class:`State` rather than a scene.

* :func:`implicit_euler`: one backward-Euler step of the system's model plus further terms,
  the Newton settings as keywords (``max_iterations``, ``rtol``, ``hessian``,
  ``linear_solver``, ...: :class:`~fem3d.solve.settings.NewtonSettings`).
* :func:`linearly_implicit_euler`: one linear solve per step.
* Any registered scheme the same way: ``SCHEMES[name].model_step(system, state, dt, ...)``
  (:meth:`fem3d.solve.schemes.base.Scheme.model_step`).

A state is immutable (:class:`State`); :class:`System` caches what does not change between
steps.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from fem3d.physics.springs import Pull
from fem3d.solve.schemes.base import model_terms
from fem3d.solve.schemes.implicit import IMPLICIT
from fem3d.solve.schemes.linear import linearly_implicit_euler
from fem3d.solve.state import State, StepStats
from fem3d.solve.system import System

__all__ = ["State", "StepStats", "System", "implicit_euler", "linearly_implicit_euler",
           "model_terms"]


def implicit_euler(system: System, state: State, dt: float, pull: Pull | None = None, *,
                   fixed_positions: np.ndarray | None = None, terms: Sequence = (),
                   max_substeps: int = 1, **newton) -> tuple[State, StepStats]:
    """One backward-Euler step of the system's model (:func:`model_terms`) plus ``terms``.

    Parameters
    ----------
    system : System
        Holds the model, its gravity and damping.
    state : State
    dt : float
    pull : Pull, optional
    fixed_positions : (n_fixed, 3) float64, optional
        The fixed vertices at the end of the step (moving pins); None: they stay.
    terms : sequence, optional
        Further terms (:class:`~fem3d.physics.terms.base.Term`, or plain objects with
        ``energy(q)``, ``gradient(q)``, ...: :class:`~fem3d.physics.terms.base.
        PositionTerm`).
    max_substeps : int, optional
        A power of two: a contact step whose own straight motion is not intersection-free
        (or that fails) is redone as up to this many substeps
        (:func:`fem3d.solve.substeps.step_with_substeps`); 1: never.
    **newton
        :meth:`NewtonSettings.make <fem3d.solve.settings.NewtonSettings.make>`: ``hessian``
        (``"exact"`` or ``"psd"``), ``linear_solver`` (``"direct"``, ``"reuse"``,
        ``"amg"``), ``max_iterations`` (default 5; None: until converged), ``rtol``,
        ``atol_factor``, ``cg_rtol``, ``warm_start``, ``line_search``, ...

    Returns
    -------
    (State, StepStats)
    """
    return IMPLICIT.model_step(system, state, dt, pull, terms=terms,
                               fixed_positions=fixed_positions, max_substeps=max_substeps,
                               **newton)
