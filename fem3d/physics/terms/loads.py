"""The model's loads: gravity and Rayleigh damping as terms, built once per scene.

:func:`fem3d.scene.build.build_loads` makes them from the scene (or a script's values); the
integrators read them through :attr:`fem3d.solve.system.System.loads`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fem3d.physics.model import Model
from fem3d.physics.terms.base import Term
from fem3d.physics.terms.damping import RayleighDamping
from fem3d.physics.terms.gravity import Gravity

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
    """

    gravity: Gravity | None = None
    damping: RayleighDamping | None = None
    rayleigh_alpha: float | np.ndarray = 0.0
    rayleigh_beta: float | np.ndarray = 0.0

    def terms(self) -> list[Term]:
        """The terms present, in objective order (gravity, then damping)."""
        return [t for t in (self.gravity, self.damping) if t is not None]

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
                     self.rayleigh_alpha, self.rayleigh_beta)
