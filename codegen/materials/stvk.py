"""St. Venant-Kirchhoff: ``mu tr(E^2) + lambda/2 tr(E)^2`` with ``E = (F^T F - I) / 2``.

Source: the classical Saint Venant-Kirchhoff model, e.g. Bonet and Wood, *Nonlinear Continuum
Mechanics for Finite Element Analysis*, 2nd ed., 2008, section 6.4.1. Its linearization at
``F = I`` is linear elasticity with the same Lame parameters, so ``mu, lam`` from ``E, nu``
are exact at small strain.
"""

from __future__ import annotations

import sympy as sp

from codegen.conventions import identity_like

PARAM_NAMES = ("mu", "lam")
DESCRIPTION = "St. Venant-Kirchhoff, psi = mu tr(E^2) + lam/2 tr(E)^2, E = (F^T F - I)/2"
ALLOWS_INVERSION = False
INVERSION = ("finite for every F, but it resists compression ever less and collapses "
             "(zero energy for F = -I...); kept non-inverting: the line search refuses J <= 0")
EXACT_SMALL_STRAIN = True
SHAPE_PARAMS: tuple[str, ...] = ()
POSITIVE = ("mu",)  # must be > 0


def psi(F: sp.Matrix, params: dict[str, sp.Symbol]) -> sp.Expr:
    """Strain energy density; ``params`` maps ``mu`` and ``lam`` (Lame) to symbols."""
    E = (F.T * F - identity_like(F)) / 2
    return params["mu"] * sp.trace(E * E) + params["lam"] / 2 * sp.trace(E) ** 2


def from_E_nu(E: sp.Symbol, nu: sp.Symbol, params: dict[str, sp.Symbol]) -> dict[str, sp.Expr]:
    """Lame parameters of ``E, nu``."""
    return {"mu": E / (2 * (1 + nu)), "lam": E * nu / ((1 + nu) * (1 - 2 * nu))}
