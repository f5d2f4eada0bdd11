"""Linear elasticity (small strain): ``mu eps:eps + lam/2 tr(eps)^2``, ``eps = (F + F^T)/2 - I``.

Source: the classical isotropic Hooke's law of infinitesimal elasticity (e.g. Hughes, *The
Finite Element Method: Linear Static and Dynamic Finite Element Analysis*, 1987, section 2.7;
Sifakis and Barbic, *FEM Simulation of 3D Deformable Solids*, SIGGRAPH course 2012, section
3.2). The baseline every other material reduces to at small strain. It is not invariant under
rotations: a rotated element has non-zero energy (use it for small deformations only).
"""

from __future__ import annotations

import sympy as sp

from codegen.conventions import identity_like

PARAM_NAMES = ("mu", "lam")
DESCRIPTION = "linear elasticity, psi = mu eps:eps + lam/2 tr(eps)^2, eps = (F + F^T)/2 - I"
ALLOWS_INVERSION = True
INVERSION = ("defined for every F (a convex quadratic): inverted tets are allowed; the "
             "energy is not rotation invariant, so large rotations are wrong anyway")
EXACT_SMALL_STRAIN = True
ROTATION_INVARIANT = False
SHAPE_PARAMS: tuple[str, ...] = ()
POSITIVE = ("mu",)  # must be > 0


def psi(F: sp.Matrix, params: dict[str, sp.Symbol]) -> sp.Expr:
    """Strain energy density; ``params`` maps ``mu`` and ``lam`` (Lame) to symbols."""
    eps = (F + F.T) / 2 - identity_like(F)
    return params["mu"] * sp.trace(eps * eps) + params["lam"] / 2 * sp.trace(eps) ** 2


def from_E_nu(E: sp.Symbol, nu: sp.Symbol, params: dict[str, sp.Symbol]) -> dict[str, sp.Expr]:
    """Lame parameters of ``E, nu``."""
    return {"mu": E / (2 * (1 + nu)), "lam": E * nu / ((1 + nu) * (1 - 2 * nu))}
