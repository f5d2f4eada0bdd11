"""Transversely isotropic fibre-reinforced solid: a Neo-Hookean matrix plus one fibre family,
``mu/2 (I_C - 3) - mu ln J + lam/2 (ln J)^2 + k1/(2 k2) (exp(k2 (I4 - 1)^2) - 1 - k2 (I4 - 1)^2)``
with ``I4 = a . C a / (a . a)`` the squared fibre stretch along the element's fibre direction
``a`` (a per-element input; any non-zero length).

Source: G. A. Holzapfel, T. C. Gasser, R. W. Ogden, "A new constitutive framework for arterial
wall mechanics and a comparative study of material models", Journal of Elasticity 61, 1-48,
2000, eq. (2.3)-(2.4) (the exponential fibre term ``k1/(2 k2) (exp(k2 (I4 - 1)^2) - 1)``), on
the Neo-Hookean matrix of Bonet and Wood, 2008, eq. (6.28). Two changes, both stated: the
fibre term's quadratic part ``k1/2 (I4 - 1)^2`` is subtracted, so the fibres are slack at
small strain (crimped collagen recruited gradually, cf. Y. Lanir, J. Biomech. 16, 1-12, 1983)
and the small-strain response is exactly the isotropic linear elasticity of ``E, nu``; and
the fibres act in compression as well as tension (no switch, so the energy stays smooth).
"""

from __future__ import annotations

import sympy as sp

PARAM_NAMES = ("mu", "lam", "k1", "k2")
ELEMENT_INPUTS = {"a": (3,)}
DESCRIPTION = ("fibre-reinforced (HGO fibre on Neo-Hookean), psi = NH(mu, lam) "
               "+ k1/(2 k2) (exp(k2 (I4 - 1)^2) - 1 - k2 (I4 - 1)^2)")
ALLOWS_INVERSION = False
INVERSION = ("undefined: the matrix's ln J is -inf at J = 0 and not real for J < 0 (NaN); "
             "inverted tets are refused by the line search")
EXACT_SMALL_STRAIN = True
SHAPE_PARAMS = ("k1", "k2")
POSITIVE = ("mu", "k2")  # must be > 0
ROTATION_SYMMETRY = "a"  # invariant under rotations of the material about the fibre


def psi(F: sp.Matrix, params: dict[str, sp.Symbol]) -> sp.Expr:
    """Strain energy density; ``params`` maps ``mu``, ``lam``, ``k1``, ``k2`` to symbols and
    ``a`` to the fibre direction (a 3x1 matrix of symbols)."""
    mu, lam, k1, k2 = params["mu"], params["lam"], params["k1"], params["k2"]
    a = params["a"]
    C = F.T * F
    log_J = sp.log(sp.det(F))
    I4 = sp.trace(a.T * C * a) / sp.trace(a.T * a)
    matrix = mu / 2 * (sp.trace(C) - 3) - mu * log_J + lam / 2 * log_J**2
    x = k2 * (I4 - 1) ** 2
    return matrix + k1 / (2 * k2) * (sp.exp(x) - 1 - x)


def from_E_nu(E: sp.Symbol, nu: sp.Symbol, params: dict[str, sp.Symbol]) -> dict[str, sp.Expr]:
    """Lame parameters of ``E, nu`` for the matrix; fibre stiffness ``k1 = E`` and ``k2 = 5``
    by default (both free: they do not change the small-strain response)."""
    return {"mu": E / (2 * (1 + nu)), "lam": E * nu / ((1 + nu) * (1 - 2 * nu)),
            "k1": E, "k2": sp.Integer(5)}
