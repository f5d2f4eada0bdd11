"""St. Venant-Kirchhoff: ``mu tr(E^2) + lambda/2 tr(E)^2`` with ``E = (F^T F - I) / 2``."""

from __future__ import annotations

import sympy as sp

PARAM_NAMES = ("mu", "lam")
DESCRIPTION = "St. Venant-Kirchhoff, psi = mu tr(E^2) + lam/2 tr(E)^2, E = (F^T F - I)/2"


def psi(F: sp.Matrix, params: dict[str, sp.Symbol]) -> sp.Expr:
    """Strain energy density; ``params`` maps ``mu`` and ``lam`` (Lame) to symbols."""
    E = (F.T * F - sp.eye(3)) / 2
    return params["mu"] * (E * E).trace() + params["lam"] / 2 * E.trace() ** 2
