"""Static equilibrium per step (no inertia): the load path of :func:`fem3d.solve.static.static`
as a scheme."""

from __future__ import annotations

from fem3d.solve.schemes.base import Scheme
from fem3d.solve.static import static

__all__ = ["Static"]


class Static(Scheme):
    """Each step the equilibrium at its end time, in load increments where Newton fails
    (:mod:`fem3d.solve.static`); velocities zero, no history, no substeps."""

    name = "static"
    label = "static"
    dynamic = False
    substeps = False
    distributed = True  # its solves go through the system (load increments: its terms)
    converged_max_iterations = 50

    def step(self, system, terms, state, dt, settings, *, fixed_positions=None,
             energy_bound=None):
        return static(system, terms, state, dt, settings, fixed_positions=fixed_positions,
                      converged_max_iterations=settings.converged_cap(
                          self.converged_max_iterations))
