"""Rayleigh damping: the dissipation ``h/2 v^T D v`` with ``D = alpha M + beta K_psd(q_t)``.

``h`` is the step map's ``dq/dx`` (backward Euler: ``h = dt``; BDF2: ``2 dt / 3``; Newmark:
``dt / 2``), so that the minimiser's damping force is ``-D v+`` with the weight the scheme
gives the end-of-step forces.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp

from fem3d.errors import ParameterError
from fem3d.physics.assembly import add_element_hessians
from fem3d.physics.model import Model
from fem3d.physics.terms.base import HessianSink, StepMap, Term

__all__ = ["RayleighDamping", "check_coefficient"]


def check_coefficient(value, name: str, count: int, what: str) -> float | np.ndarray:
    """A damping coefficient: a number >= 0 or one per ``what`` (``(count,)``, read-only).

    Raises
    ------
    ParameterError
        Names the bad value (and its index).
    """
    a = np.asarray(value, dtype=np.float64)
    if a.ndim == 0:
        v = float(a)
        if not math.isfinite(v) or v < 0:
            raise ParameterError(f"{name} must be a finite number >= 0, got {v}")
        return v
    if a.shape != (count,):
        raise ParameterError(f"{name} must be a number or one per {what} ({count},), got "
                             f"shape {a.shape}")
    if not (np.isfinite(a).all() and (a >= 0).all()):
        bad = int(np.flatnonzero(~(np.isfinite(a) & (a >= 0)))[0])
        raise ParameterError(f"{name} of {what} {bad} must be finite and >= 0, got {a[bad]}")
    a = a.copy()
    a.setflags(write=False)
    return a


class RayleighDamping(Term):
    """``h/2 v^T D v`` in a step's velocity unknowns, ``D`` evaluated at the start of the
    step (constant during it, so the dissipation stays quadratic).

    ``D = alpha M + beta K_psd(q_t)``: ``K_psd`` is the elastic Hessian with each element's
    ``dP/dF`` projected to positive semi-definite (generated ``hessian_psd``), scaled per tet
    by ``beta``. The projection keeps ``D`` positive semi-definite where the exact ``K`` is
    indefinite (compressed tets), so damping never feeds energy in; at rest it is the exact
    stiffness (the classic Rayleigh ``beta K``).

    Parameters
    ----------
    model : Model
    alpha : float or (n_vertices,) float64
        Mass-proportional coefficient (:func:`check_coefficient`).
    beta : float or (n_tets,) float64
        Stiffness-proportional coefficient.
    """

    name = "damping"
    variable = "velocity"
    dissipative = True

    def __init__(self, model: Model, alpha, beta) -> None:
        self.model = model
        self.alpha, self.beta = alpha, beta
        self._alpha_mass: np.ndarray | None = None
        if np.ndim(alpha) == 0:
            if alpha > 0:
                self._alpha_mass = float(alpha) * model.mass.data
        elif np.any(alpha > 0):
            # S M S with S = diag(sqrt(alpha)) per DOF: symmetric positive semi-definite, and
            # alpha M on every body whose vertices share one alpha
            s = np.repeat(np.sqrt(alpha), 3)
            pat = model.pattern
            rows = np.repeat(np.arange(pat.shape[0]), np.diff(pat.indptr))
            self._alpha_mass = model.mass.data * s[rows] * s[pat.indices]
        self._beta_vol: np.ndarray | None = None
        if np.ndim(beta) == 0:
            if beta > 0:
                self._beta_vol = model.vol * float(beta)
        elif np.any(beta > 0):
            # per element; vol may be per point
            self._beta_vol = model.scaled_volumes(np.asarray(beta, dtype=np.float64))
        self._step: StepMap | None = None
        self._data: np.ndarray | None = None
        self._D: sp.csr_matrix | None = None
        # h D's values, and gathered to a system's reduced pattern: constant within a step,
        # so each Newton matrix adds them without scaling and gathering 1e5-1e6 values again
        self._scaled: np.ndarray | None = None
        self._reduced: tuple[np.ndarray, np.ndarray] | None = None  # (kept slots, values)

    @property
    def active(self) -> bool:
        """Whether ``D`` is non-zero."""
        return self._alpha_mass is not None or self._beta_vol is not None

    def matrix_data(self, q: np.ndarray) -> np.ndarray | None:
        """CSR ``data`` of ``D`` at ``q`` on ``model.pattern`` (None without damping)."""
        if not self.active:
            return None
        data = np.zeros(self.model.nnz)
        if self._beta_vol is not None:
            add_element_hessians(self.model, self.model.psd_hessian, q, self._beta_vol,
                                 self.model.scatter, data)
        if self._alpha_mass is not None:
            data += self._alpha_mass
        return data

    def begin_step(self, step: StepMap) -> None:
        self._step = step
        self._data = self.matrix_data(step.q_t)
        self._D = None if self._data is None else self.model.csr(self._data)
        self._scaled = self._reduced = None

    def energy(self, x: np.ndarray) -> float:
        v = self._step.velocity(x)
        return 0.5 * self._step.h * float(v @ (self._D @ v))

    def gradient(self, x: np.ndarray) -> np.ndarray:
        step = self._step
        return step.h * (self._D @ step.velocity(x))[step.constraints.free_dofs]

    def add_hessian(self, x: np.ndarray, sink: HessianSink) -> None:
        if self._scaled is None:
            self._scaled = self._step.h * self._data
        kept = getattr(sink, "kept", None)  # NewtonMatrixBuilder's reduced-pattern slots
        if kept is None:
            sink.add_pattern_values(self._scaled)
            return
        if self._reduced is None or self._reduced[0] is not kept:
            self._reduced = (kept, self._scaled[kept])
        sink.add_pattern_values(self._scaled, reduced=self._reduced[1])

    def with_model(self, model: Model) -> RayleighDamping:
        return RayleighDamping(model, self.alpha, self.beta)
