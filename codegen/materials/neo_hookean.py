"""Compressible Neo-Hookean of the assignment: ``C (J^(-2/3) tr(F^T F) - 3) + D (J - 1)^2``."""

from __future__ import annotations

import sympy as sp

PARAM_NAMES = ("C", "D")
DESCRIPTION = "compressible Neo-Hookean, psi = C (J^(-2/3) tr(F^T F) - 3) + D (J - 1)^2"


def psi(F: sp.Matrix, params: dict[str, sp.Symbol]) -> sp.Expr:
    """Strain energy density; ``params`` maps ``C`` and ``D`` to symbols."""
    J = F.det()
    C, D = params["C"], params["D"]
    return C * (J ** sp.Rational(-2, 3) * (F.T * F).trace() - 3) + D * (J - 1) ** 2
