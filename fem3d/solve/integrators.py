"""The time integrators by name, and the names an integrator's caller needs.

* :func:`~fem3d.solve.linearly_implicit.linearly_implicit_euler` (``"linear"``): one linear
  solve per step.
* :func:`~fem3d.solve.backward_euler.implicit_euler` (``"implicit"``): backward Euler as the
  minimisation of the objective terms by Newton's method.
* ``"bdf2"`` (:func:`~fem3d.solve.bdf2.bdf2`), ``"newmark"`` (:func:`~fem3d.solve.newmark.
  newmark`, average acceleration) and ``"static"`` (:func:`~fem3d.solve.static.static`,
  equilibrium with load stepping): the same terms and Newton with another
  :class:`~fem3d.physics.terms.base.StepMap` (``docs/integrators.md``).

Both work on the free DOFs ``q_free = P q`` (fixed vertices removed with the selection
matrix of :class:`fem3d.physics.constraints.Constraints`). A state is immutable
(:class:`State`); an integrator is ``step(system, state, dt, pull) -> (State, StepStats)``,
where :class:`System` caches what does not change between steps.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from fem3d.physics.springs import Pull
from fem3d.solve.backward_euler import (
    backward_euler,
    implicit_euler,
    model_terms,
    newton_options,
)
from fem3d.solve.bdf2 import bdf2
from fem3d.solve.linearly_implicit import linearly_implicit_euler
from fem3d.solve.newmark import newmark
from fem3d.solve.state import State, StepStats
from fem3d.solve.static import static
from fem3d.solve.system import System

__all__ = ["State", "StepStats", "System", "implicit_euler", "backward_euler", "model_terms",
           "linearly_implicit_euler", "bdf2", "newmark", "static", "INTEGRATORS",
           "TERM_INTEGRATORS", "DYNAMIC_INTEGRATORS", "on_model_terms"]


def on_model_terms(scheme: Callable[..., tuple[State, StepStats]]
                   ) -> Callable[..., tuple[State, StepStats]]:
    """``scheme(system, terms, state, dt, ...)`` as ``step(system, state, dt, pull, *,
    terms=(), hessian="exact", ...)`` on the model's terms (:func:`model_terms`) plus
    ``terms``, like :func:`implicit_euler`."""
    def step(system: System, state: State, dt: float, pull: Pull | None = None, *,
             terms: Sequence = (), hessian: str = "exact", **settings
             ) -> tuple[State, StepStats]:
        return scheme(system, [*model_terms(system, pull), *terms], state, dt,
                      options=newton_options(hessian), **settings)
    step.__name__ = step.__qualname__ = f"{scheme.__name__}_step"
    step.__doc__ = f"One ``{scheme.__name__}`` step of the system's model plus ``terms``."
    return step


#: Integrator names accepted by :class:`fem3d.simulation.Simulation` and the CLI, each as
#: ``step(system, state, dt, pull, ...) -> (State, StepStats)``.
INTEGRATORS: dict[str, Callable[..., tuple[State, StepStats]]] = {
    "linear": linearly_implicit_euler,
    "implicit": implicit_euler,
    "bdf2": on_model_terms(bdf2),
    "newmark": on_model_terms(newmark),
    "static": on_model_terms(static),
}

#: The schemes that minimise the objective terms, as ``scheme(system, terms, state, dt,
#: ...)`` (what :meth:`fem3d.simulation.Simulation.step` calls).
TERM_INTEGRATORS: dict[str, Callable[..., tuple[State, StepStats]]] = {
    "implicit": backward_euler,
    "bdf2": bdf2,
    "newmark": newmark,
    "static": static,
}

#: The time-dependent schemes (the viewer's N key cycles through them).
DYNAMIC_INTEGRATORS = ("linear", "implicit", "bdf2", "newmark")
