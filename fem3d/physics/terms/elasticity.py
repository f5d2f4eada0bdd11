"""Elasticity: the strain energy ``V(q)`` of the model's generated material."""

from __future__ import annotations

import math

import numpy as np

from fem3d.physics.assembly import assemble_gradient, count_inverted, potential_energy
from fem3d.physics.model import Model
from fem3d.physics.terms.base import HessianSink, Term

__all__ = ["Elasticity"]


class Elasticity(Term):
    """``V(q) = sum_e vol_e psi(F_e)``; a point with an inverted tet (``det F <= 0``) is
    inadmissible (``+inf``) unless the material is defined through inversion
    (``model.allows_inversion``), so no accepted state inverts.

    Parameters
    ----------
    model : Model
    """

    name = "elasticity"

    def __init__(self, model: Model) -> None:
        self.model = model
        self.check_inversion = not getattr(model, "allows_inversion", False)
        # element energies cancel near rest to much less than their own size, about E vol
        self.energy_scale = model.E * float(model.vol.sum())

    def energy(self, q: np.ndarray) -> float:
        if self.check_inversion and count_inverted(self.model, q):
            return math.inf
        return potential_energy(self.model, q)

    def gradient(self, q: np.ndarray) -> np.ndarray:
        return assemble_gradient(self.model, q)

    def add_hessian(self, q: np.ndarray, sink: HessianSink) -> None:
        sink.add_elements(self.model, self.model.psd_hessian if sink.psd else "hessian", q)

    def with_model(self, model: Model) -> Elasticity:
        return Elasticity(model)
