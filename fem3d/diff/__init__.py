"""Differentiable simulation: exact adjoint gradients of backward-Euler trajectories.

>>> loss = PositionLoss({10: target_positions})                  # doctest: +SKIP
>>> value, grads = trajectory_gradient(scene, loss, ["bodies[0].material.E"])  # doctest: +SKIP

See :mod:`fem3d.diff.adjoint` for what is differentiated and what is held fixed.
"""

from fem3d.diff import bdf2 as _bdf2  # noqa: F401  (registers the BDF2 adjoint)
from fem3d.diff import contact as _contact  # noqa: F401  (registers the contact term)
from fem3d.diff import newmark as _newmark  # noqa: F401  (registers the Newmark adjoint)
from fem3d.diff import static as _static  # noqa: F401  (registers the static adjoint)
from fem3d.diff.adjoint import PositionLoss, simulate, trajectory_gradient

__all__ = ["PositionLoss", "simulate", "trajectory_gradient"]
