"""Gravity: the work of the body force ``f_g = M g``."""

from __future__ import annotations

import numpy as np

from fem3d.errors import ParameterError
from fem3d.physics.model import Model
from fem3d.physics.terms.base import StepMap, Term

__all__ = ["Gravity", "check_gravity"]


def check_gravity(gravity) -> np.ndarray | None:
    """Gravity as a read-only ``(3,)`` array, None when absent or zero.

    Raises
    ------
    ParameterError
        Not 3 finite numbers.
    """
    if gravity is None:
        return None
    g = np.array(gravity, dtype=np.float64).reshape(-1)
    if g.shape != (3,) or not np.isfinite(g).all():
        raise ParameterError(f"gravity must be 3 finite numbers, got {gravity!r}")
    if not g.any():
        return None
    g.setflags(write=False)
    return g


class Gravity(Term):
    """``-h f_g . x`` in a step's unknowns: gravity's potential ``-f_g . q`` relative to the
    step's base positions (linear, no Hessian).

    Parameters
    ----------
    model : Model
    g : (3,) float64
        The acceleration (:func:`check_gravity`).

    Attributes
    ----------
    force : (3n,) float64
        ``M g``, read-only.
    """

    name = "gravity"
    variable = "velocity"

    def __init__(self, model: Model, g: np.ndarray) -> None:
        self.model = model
        self.g = g
        f = model.mass @ np.tile(g, model.n_vertices)
        f.setflags(write=False)
        self.force = f
        self._h = 0.0
        self._f_free: np.ndarray | None = None

    def begin_step(self, step: StepMap) -> None:
        self._h = step.h
        self._f_free = self.force[step.constraints.free_dofs]

    def energy(self, x: np.ndarray) -> float:
        return -(self._h * float(self._f_free @ x))

    def gradient(self, x: np.ndarray) -> np.ndarray:
        return -(self._h * self._f_free)

    def potential(self, q: np.ndarray) -> float:
        """``-f_g . (q - X)``: zero at rest."""
        dq = np.asarray(q, dtype=np.float64).reshape(-1) - self.model.X.reshape(-1)
        return -float(self.force @ dq)

    def with_model(self, model: Model) -> Gravity:
        return Gravity(model, self.g)
