"""The model's loads: gravity, Rayleigh damping and the bodies' surface and point loads as
terms, built once per scene.

:func:`fem3d.scene.build.build_loads` makes them from the scene (or a script's values); the
integrators read them through :attr:`fem3d.solve.system.System.loads`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fem3d.physics.model import Model
from fem3d.physics.terms.base import Term
from fem3d.physics.terms.damping import RayleighDamping
from fem3d.physics.terms.gravity import Gravity
from fem3d.physics.terms.surface import DeadLoad, FollowerPressure

__all__ = ["Loads"]


@dataclass(frozen=True, eq=False)
class Loads:
    """Gravity and Rayleigh damping of one model (each None when absent).

    Attributes
    ----------
    gravity : Gravity or None
        ``f_g = M g``; None without gravity.
    damping : RayleighDamping or None
        ``D = alpha M + beta K``; None when it is zero.
    rayleigh_alpha, rayleigh_beta : float or ndarray
        The checked coefficients (per vertex / per tet, or one value), zero included.
    surface : tuple of DeadLoad or FollowerPressure
        The bodies' ``loads`` (tractions, point forces, pressures), in scene order.
    """

    gravity: Gravity | None = None
    damping: RayleighDamping | None = None
    rayleigh_alpha: float | np.ndarray = 0.0
    rayleigh_beta: float | np.ndarray = 0.0
    surface: tuple[DeadLoad | FollowerPressure, ...] = field(default=())

    def terms(self) -> list[Term]:
        """The terms present, in objective order (gravity, damping, the surface loads)."""
        return [t for t in (self.gravity, self.damping, *self.surface) if t is not None]

    def applied_forces(self, q: np.ndarray) -> np.ndarray:
        """``(3n,)`` the external forces at ``q``: gravity, and the surface and point loads
        at their last step's scale."""
        f = np.zeros(q.size) if self.gravity is None else np.array(self.gravity.force)
        for load in self.surface:
            f += load.applied(q) if isinstance(load, FollowerPressure) else load.applied()
        return f

    @property
    def gravity_force(self) -> np.ndarray | None:
        """``M g`` (read-only), or None without gravity."""
        return None if self.gravity is None else self.gravity.force

    def gravity_energy(self, q: np.ndarray) -> float:
        """Gravity's potential ``-f_g . (q - X)`` (zero at rest)."""
        return 0.0 if self.gravity is None else self.gravity.potential(q)

    def damping_data(self, q: np.ndarray) -> np.ndarray | None:
        """CSR ``data`` on ``model.pattern`` of the damping matrix at ``q``
        (:meth:`RayleighDamping.matrix_data`; None without damping)."""
        return None if self.damping is None else self.damping.matrix_data(q)

    def with_model(self, model: Model) -> Loads:
        """The same loads on ``model`` (new material values, same mesh)."""
        return Loads(None if self.gravity is None else self.gravity.with_model(model),
                     None if self.damping is None else self.damping.with_model(model),
                     self.rayleigh_alpha, self.rayleigh_beta,
                     tuple(t.with_model(model) for t in self.surface))
