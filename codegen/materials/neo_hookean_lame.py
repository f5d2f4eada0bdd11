"""Compressible Neo-Hookean with the standard Lame mapping:
``mu/2 (I_C - 3) - mu ln J + lam/2 (ln J)^2``.

Source: Ogden, *Non-linear Elastic Deformations*, 1984, section 4.4; Bonet and Wood,
*Nonlinear Continuum Mechanics for Finite Element Analysis*, 2nd ed., 2008, eq. (6.28). Its
linearization at ``F = I`` is linear elasticity with Lame parameters ``mu, lam``, so the Lame
parameters of ``E, nu`` are exact at small strain.
"""

from __future__ import annotations

import sympy as sp

PARAM_NAMES = ("mu", "lam")
DESCRIPTION = "Neo-Hookean (Lame), psi = mu/2 (I_C - 3) - mu ln J + lam/2 (ln J)^2"
ALLOWS_INVERSION = False
INVERSION = ("undefined: ln J is -inf at J = 0 and not real for J < 0 (the kernels return "
             "NaN); inverted tets are refused by the line search")
EXACT_SMALL_STRAIN = True
SHAPE_PARAMS: tuple[str, ...] = ()
POSITIVE = ("mu",)  # must be > 0


def psi(F: sp.Matrix, params: dict[str, sp.Symbol]) -> sp.Expr:
    """Strain energy density; ``params`` maps ``mu`` and ``lam`` (Lame) to symbols."""
    mu, lam = params["mu"], params["lam"]
    log_J = sp.log(sp.det(F))
    return mu / 2 * (sp.trace(F.T * F) - 3) - mu * log_J + lam / 2 * log_J**2


def from_E_nu(E: sp.Symbol, nu: sp.Symbol, params: dict[str, sp.Symbol]) -> dict[str, sp.Expr]:
    """Lame parameters of ``E, nu``."""
    return {"mu": E / (2 * (1 + nu)), "lam": E * nu / ((1 + nu) * (1 - 2 * nu))}
