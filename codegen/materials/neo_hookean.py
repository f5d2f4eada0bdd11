"""Compressible Neo-Hookean of the assignment: ``C (J^(-2/3) tr(F^T F) - 3) + D (J - 1)^2``.

Source: the course assignment's energy (a decoupled Neo-Hookean in the form of Bonet and Wood,
*Nonlinear Continuum Mechanics for Finite Element Analysis*, 2nd ed., 2008, section 6.6.2,
with ``C = mu / 2`` and ``D = kappa / 2``).

The assignment fixes the mapping ``C = mu / 2``, ``D = lambda / 2`` from the Lame parameters
of ``E, nu``. At small strain the model is linear elasticity with shear modulus ``2 C = mu``
and bulk modulus ``2 D``, i.e. an effective Lame ``lambda_eff = 2 D - 4 C / 3 = lambda - 2 mu /
3``: it is *not* exactly the linear elasticity of ``E, nu`` (its Poisson ratio is lower).
"""

from __future__ import annotations

import sympy as sp

PARAM_NAMES = ("C", "D")
DESCRIPTION = "compressible Neo-Hookean, psi = C (J^(-2/3) tr(F^T F) - 3) + D (J - 1)^2"
ALLOWS_INVERSION = False
INVERSION = ("undefined: J^(-2/3) is infinite at J = 0 and the isochoric invariant is "
             "meaningless for J < 0; inverted tets are refused by the line search")
EXACT_SMALL_STRAIN = False
SHAPE_PARAMS: tuple[str, ...] = ()
POSITIVE = ("C",)  # must be > 0


def psi(F: sp.Matrix, params: dict[str, sp.Symbol]) -> sp.Expr:
    """Strain energy density; ``params`` maps ``C`` and ``D`` to symbols."""
    J = sp.det(F)
    C, D = params["C"], params["D"]
    return C * (J ** sp.Rational(-2, 3) * sp.trace(F.T * F) - 3) + D * (J - 1) ** 2


def from_E_nu(E: sp.Symbol, nu: sp.Symbol, params: dict[str, sp.Symbol]) -> dict[str, sp.Expr]:
    """The assignment's mapping ``C = mu / 2``, ``D = lambda / 2`` (not exact: see above)."""
    return {"C": E / (4 * (1 + nu)), "D": E * nu / (2 * (1 + nu) * (1 - 2 * nu))}
