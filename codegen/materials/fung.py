"""Fung-type exponential (isotropic, Demiray's form):
``mu/(2 b) (exp(b (I1b - 3)) - 1) + kappa/2 (J - 1)^2``.

``I1b = J^(-2/3) I_C``. Source: Y. C. Fung, "Elasticity of soft tissues in simple elongation",
American Journal of Physiology 213, 1532-1544, 1967 (the exponential strain-stiffening law);
H. Demiray, "A note on the elasticity of soft biological tissues", Journal of Biomechanics 5,
309-311, 1972 (this isotropic strain energy), with the decoupled volumetric term of Bonet and
Wood, 2008, section 6.6. At small strain: shear modulus ``mu``, bulk modulus ``kappa``, for
every ``b > 0``; ``b`` (dimensionless) sets how fast the material stiffens (``b -> 0`` is the
Neo-Hookean).
"""

from __future__ import annotations

import sympy as sp

PARAM_NAMES = ("mu", "kappa", "b")
DESCRIPTION = "Fung-type exponential, psi = mu/(2b) (exp(b (I1b - 3)) - 1) + kappa/2 (J - 1)^2"
ALLOWS_INVERSION = False
INVERSION = ("undefined: I1b divides by J^(2/3) (infinite at J = 0, meaningless for J < 0); "
             "inverted tets are refused by the line search")
EXACT_SMALL_STRAIN = True
SHAPE_PARAMS = ("b",)
POSITIVE = ("mu", "kappa", "b")  # must be > 0


def psi(F: sp.Matrix, params: dict[str, sp.Symbol]) -> sp.Expr:
    """Strain energy density; ``params`` maps ``mu``, ``kappa`` and ``b`` to symbols."""
    mu, kappa, b = params["mu"], params["kappa"], params["b"]
    J = sp.det(F)
    I1b = J ** sp.Rational(-2, 3) * sp.trace(F.T * F)
    return mu / (2 * b) * (sp.exp(b * (I1b - 3)) - 1) + kappa / 2 * (J - 1) ** 2


def from_E_nu(E: sp.Symbol, nu: sp.Symbol, params: dict[str, sp.Symbol]) -> dict[str, sp.Expr]:
    """``mu = E / (2 (1 + nu))``, ``kappa = E / (3 (1 - 2 nu))``; ``b`` is free (default 1)."""
    return {"mu": E / (2 * (1 + nu)), "kappa": E / (3 * (1 - 2 * nu)), "b": sp.Integer(1)}
