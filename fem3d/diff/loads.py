"""The adjoint of the follower pressure (:class:`fem3d.physics.terms.surface.FollowerPressure`):
its Hessian enters the step equation's ``dg/du`` as the elastic one does. Dead loads (tractions,
point forces) are constant in the positions and need nothing in the backward pass."""

from __future__ import annotations

from fem3d.diff.terms import AdjointTerm, StepPair
from fem3d.physics.terms.surface import FollowerPressure

__all__ = ["PressureAdjoint"]


class PressureAdjoint(AdjointTerm):
    """``h dP/dq(q_{n+1})`` of one pressure: ``h^2 H`` in ``u``, ``h H`` in ``q_B``, at the
    amplitude of the step's end time."""

    name = "pressure"

    def __init__(self, term: FollowerPressure) -> None:
        self.term = term

    def linearize(self, pair: StepPair) -> None:
        self.pair = pair
        amplitude = self.term.amplitude
        self.H = self.term.hessian_data(pair.q1, 1.0 if amplitude is None else
                                        amplitude(pair.t1))

    def matrix(self):
        return (self.pair.h * self.pair.h) * self.H

    def state_vjp(self, lf):
        return -self.pair.h * (self.term.model.csr(self.H) @ lf), None
