"""Stable Neo-Hookean (Smith, de Goes and Kim 2018):
``mu/2 (I_C - 3) + lam/2 (J - alpha)^2 - mu/2 ln(I_C + 1)``, ``alpha = 1 + 3 mu / (4 lam)``.

Source: B. Smith, F. de Goes, T. Kim, "Stable Neo-Hookean Flesh Simulation", ACM Transactions
on Graphics 37(2), article 12, 2018, eq. (14) (the energy with the ``ln(I_C + 1)`` term that
keeps it rest-stable) and section 3.4 (``alpha = 1 + mu/lam - mu/(4 lam)``, and the Lame
re-parametrization ``mu = 4/3 mu_L``, ``lam = lam_L + 5/6 mu_L`` that matches linear elasticity
of Lame parameters ``mu_L, lam_L`` at small strain).

Written here as ``mu/2 (I_C - 3) + lam/2 (J - 1)^2 - 3 mu/4 (J - 1) - mu/2 ln((I_C + 1)/4)``:
the paper's energy minus its constant value at rest ``9 mu^2 / (32 lam)``, expanded so that
``lam -> 0`` (``nu = 0``) needs no division. Same stress and Hessian as the paper's.
"""

from __future__ import annotations

import sympy as sp

PARAM_NAMES = ("mu", "lam")
DESCRIPTION = "Stable Neo-Hookean, psi = mu/2 (I_C - 3) + lam/2 (J - alpha)^2 - mu/2 ln(I_C + 1)"
ALLOWS_INVERSION = True
INVERSION = ("defined for every F: J enters polynomially and I_C + 1 >= 1, so inverted tets "
             "have finite energy and a restoring force; the line search allows inversion")
EXACT_SMALL_STRAIN = True
SHAPE_PARAMS: tuple[str, ...] = ()
POSITIVE = ("mu",)  # must be > 0


def psi(F: sp.Matrix, params: dict[str, sp.Symbol]) -> sp.Expr:
    """Strain energy density; ``params`` maps the paper's ``mu`` and ``lam`` to symbols."""
    mu, lam = params["mu"], params["lam"]
    I_C = sp.trace(F.T * F)
    J = sp.det(F)
    return (mu / 2 * (I_C - 3) + lam / 2 * (J - 1) ** 2 - 3 * mu / 4 * (J - 1)
            - mu / 2 * sp.log((I_C + 1) / 4))


def from_E_nu(E: sp.Symbol, nu: sp.Symbol, params: dict[str, sp.Symbol]) -> dict[str, sp.Expr]:
    """The paper's section 3.4: ``mu = 4/3 mu_L``, ``lam = lam_L + 5/6 mu_L``."""
    mu_L = E / (2 * (1 + nu))
    lam_L = E * nu / ((1 + nu) * (1 - 2 * nu))
    return {"mu": sp.Rational(4, 3) * mu_L, "lam": lam_L + sp.Rational(5, 6) * mu_L}
