"""The time integrators by name, and the names an integrator's caller needs.

* :func:`~fem3d.solve.linearly_implicit.linearly_implicit_euler` (``"linear"``): one linear
  solve per step.
* :func:`~fem3d.solve.backward_euler.implicit_euler` (``"implicit"``): backward Euler as the
  minimisation of the objective terms by Newton's method.

Both work on the free DOFs ``q_free = P q`` (fixed vertices removed with the selection
matrix of :class:`fem3d.physics.constraints.Constraints`). A state is immutable
(:class:`State`); an integrator is ``step(system, state, dt, pull) -> (State, StepStats)``,
where :class:`System` caches what does not change between steps.
"""

from __future__ import annotations

from collections.abc import Callable

from fem3d.solve.backward_euler import backward_euler, implicit_euler, model_terms
from fem3d.solve.linearly_implicit import linearly_implicit_euler
from fem3d.solve.state import State, StepStats
from fem3d.solve.system import System

__all__ = ["State", "StepStats", "System", "implicit_euler", "backward_euler", "model_terms",
           "linearly_implicit_euler", "INTEGRATORS"]

#: Integrator names accepted by :class:`fem3d.simulation.Simulation` and the CLI.
INTEGRATORS: dict[str, Callable[..., tuple[State, StepStats]]] = {
    "linear": linearly_implicit_euler,
    "implicit": implicit_euler,
}
