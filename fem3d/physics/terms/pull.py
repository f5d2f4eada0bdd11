"""Pull springs as a term: the interactive drag and the scenes' scripted pulls."""

from __future__ import annotations

import numpy as np

from fem3d.kernels.dispatch import spring_kernels
from fem3d.physics.model import Model
from fem3d.physics.springs import Pull
from fem3d.physics.terms.base import HessianSink, Term

__all__ = ["PullSprings"]


class PullSprings(Term):
    """``sum_i 1/2 k_i |x_i - target_i|^2`` of the current :class:`Pull` (none: zero).

    Parameters
    ----------
    model : Model
    pull : Pull, optional
        The springs; :attr:`pull` may be replaced between steps (a drag moves its target).
    spring : optional
        The model back end's generated spring kernels (made when not given).
    """

    name = "pull"

    def __init__(self, model: Model, pull: Pull | None = None, *, spring=None) -> None:
        self.model = model
        self.spring = spring_kernels(backend=model.backend) if spring is None else spring
        self.pull = pull

    @property
    def active(self) -> bool:
        """Whether a pull is attached (an objective leaves the term out otherwise)."""
        return self.pull is not None

    def energy(self, q: np.ndarray) -> float:
        return self.pull.energy(self.spring, q.reshape(-1, 3))

    def gradient(self, q: np.ndarray) -> np.ndarray:
        return self.pull.gradient(self.spring, q.reshape(-1, 3))

    def add_hessian(self, q: np.ndarray, sink: HessianSink) -> None:
        if self.pull.vertices.size:
            q3 = np.asarray(q, dtype=np.float64).reshape(-1, 3)
            sink.add_vertex_blocks(self.pull.vertices,
                                   self.pull.hessian_blocks(self.spring, q3),
                                   sink.position_scale)

    def with_model(self, model: Model) -> PullSprings:
        return PullSprings(model, self.pull, spring=self.spring)
