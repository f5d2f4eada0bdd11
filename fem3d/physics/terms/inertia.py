"""Inertia: ``1/2 (v - v_hat)^T M (v - v_hat)`` in the step's velocity unknowns."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from fem3d.physics.model import Model
from fem3d.physics.terms.base import HessianSink, StepMap, Term

__all__ = ["Inertia"]


class Inertia(Term):
    """The kinetic term of an incremental potential, ``1/2 dv^T M dv`` with ``dv = v(x) -
    v_hat`` over every DOF (the fixed ones' velocity change is prescribed and enters through
    the mass matrix's free-fixed coupling).

    Parameters
    ----------
    model : Model
    mass_free : (n_free, n_free) scipy.sparse.csr_matrix
        ``P M P^T`` (the solver's; its data also seeds the Newton matrix).
    """

    name = "inertia"
    variable = "velocity"
    inertial = True

    def __init__(self, model: Model, mass_free: sp.csr_matrix) -> None:
        self.model = model
        self.mass_free = mass_free
        self._step: StepMap | None = None
        # (x, M (x - v_hat)) of the last energy: the gradient at an accepted point reuses it
        self._last: tuple[np.ndarray, np.ndarray] | None = None

    def begin_step(self, step: StepMap) -> None:
        self._step = step
        self._last = None

    def _dv_full(self, x: np.ndarray) -> np.ndarray:
        step = self._step
        return step.constraints.expand_zero(x - step.v_hat_free) + step.dv_prescribed

    def energy(self, x: np.ndarray) -> float:
        step = self._step
        if step.dv_prescribed is None:
            dv = x - step.v_hat_free
            m_dv = self.mass_free @ dv
            self._last = (x, m_dv)
            return 0.5 * float(dv @ m_dv)
        dv = self._dv_full(x)
        return 0.5 * float(dv @ (self.model.mass @ dv))

    def gradient(self, x: np.ndarray) -> np.ndarray:
        step = self._step
        if step.dv_prescribed is None:
            last = self._last
            if last is not None and last[0] is x:  # Newton never changes an iterate in place
                return last[1]
            return self.mass_free @ (x - step.v_hat_free)
        return (self.model.mass @ self._dv_full(x))[step.constraints.free_dofs]

    def add_hessian(self, x: np.ndarray, sink: HessianSink) -> None:
        sink.add_pattern_values(self.model.mass.data, reduced=self.mass_free.data)
