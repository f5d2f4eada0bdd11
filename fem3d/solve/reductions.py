"""How Newton's method measures its vectors: the reductions over a vector's entries.

In one process a vector is the whole reduced vector and the reductions are NumPy's
(:class:`Reductions`). An MPI rank of a distributed run holds the entries of its own
vertices, some of them also held by other ranks (ghosts): its reductions count the entries
it owns and sum over the ranks (:class:`fem3d.parallel.system.OwnedReductions`), so every
rank takes the same decision.
"""

from __future__ import annotations

import math

import numpy as np

from fem3d.errors import SimulationError

__all__ = ["Reductions", "WHOLE"]


class Reductions:
    """The reductions of a whole vector in one process."""

    def dot(self, a: np.ndarray, b: np.ndarray) -> float:
        """``a . b``."""
        return float(a @ b)

    def all(self, flag: bool) -> bool:
        """Whether ``flag`` holds everywhere (every rank)."""
        return bool(flag)

    def any(self, flag: bool) -> bool:
        """Whether ``flag`` holds somewhere (on some rank)."""
        return bool(flag)

    def all_finite(self, a: np.ndarray) -> bool:
        """Whether every entry of ``a`` is finite."""
        return self.all(bool(np.isfinite(a).all()))

    def _scaled_norm(self, g: np.ndarray) -> float:
        s = float(np.abs(g).max()) if g.size else 0.0
        return s * float(np.linalg.norm(g / s)) if s > 0 else 0.0

    def norm(self, g: np.ndarray) -> float:
        """``||g||`` without overflow for finite ``g``.

        Raises
        ------
        SimulationError
            ``g`` not finite, or its norm overflows.
        """
        if not self.all_finite(g):
            raise SimulationError(
                "Newton's method: the gradient is not finite (forces overflow: parameters or "
                "state out of range)"
            )
        n = self._scaled_norm(g)
        if not math.isfinite(n):
            raise SimulationError("Newton's method: the gradient norm overflows")
        return n

    def extent(self, X: np.ndarray) -> np.ndarray:
        """``(3,)`` the extent of the points ``X`` ``(n, 3)`` along each axis."""
        return np.ptp(X, axis=0)


#: The reductions of one process.
WHOLE = Reductions()
