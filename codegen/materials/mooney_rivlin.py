"""Compressible Mooney-Rivlin: ``C10 (I1b - 3) + C01 (I2b - 3) + kappa/2 (J - 1)^2``.

``I1b = J^(-2/3) I_C`` and ``I2b = J^(-4/3) (I_C^2 - tr(C^2)) / 2`` are the isochoric
invariants of ``C = F^T F``.

Source: M. Mooney, "A theory of large elastic deformation", Journal of Applied Physics 11,
582-592, 1940; R. S. Rivlin, "Large elastic deformations of isotropic materials IV",
Phil. Trans. R. Soc. A 241, 379-397, 1948; the decoupled compressible form of Bonet and Wood,
*Nonlinear Continuum Mechanics for Finite Element Analysis*, 2nd ed., 2008, section 6.6.3.
At small strain: shear modulus ``2 (C10 + C01)``, bulk modulus ``kappa``; the mapping from
``E, nu`` splits the shear modulus equally between the two invariants.
"""

from __future__ import annotations

import sympy as sp

PARAM_NAMES = ("C10", "C01", "kappa")
DESCRIPTION = "compressible Mooney-Rivlin, psi = C10 (I1b - 3) + C01 (I2b - 3) + kappa/2 (J - 1)^2"
ALLOWS_INVERSION = False
INVERSION = ("undefined: the isochoric invariants divide by powers of J (infinite at J = 0, "
             "meaningless for J < 0); inverted tets are refused by the line search")
EXACT_SMALL_STRAIN = True
SHAPE_PARAMS: tuple[str, ...] = ()
POSITIVE = ("kappa",)  # must be > 0


def psi(F: sp.Matrix, params: dict[str, sp.Symbol]) -> sp.Expr:
    """Strain energy density; ``params`` maps ``C10``, ``C01`` and ``kappa`` to symbols."""
    C = F.T * F
    J = sp.det(F)
    I1, I2 = sp.trace(C), (sp.trace(C) ** 2 - sp.trace(C * C)) / 2
    I1b, I2b = J ** sp.Rational(-2, 3) * I1, J ** sp.Rational(-4, 3) * I2
    return (params["C10"] * (I1b - 3) + params["C01"] * (I2b - 3)
            + params["kappa"] / 2 * (J - 1) ** 2)


def from_E_nu(E: sp.Symbol, nu: sp.Symbol, params: dict[str, sp.Symbol]) -> dict[str, sp.Expr]:
    """``C10 = C01 = mu / 4`` (shear modulus ``mu``), ``kappa = E / (3 (1 - 2 nu))``."""
    mu = E / (2 * (1 + nu))
    return {"C10": mu / 4, "C01": mu / 4, "kappa": E / (3 * (1 - 2 * nu))}
