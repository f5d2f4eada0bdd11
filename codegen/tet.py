"""The linear tetrahedron in SymPy: shape functions, their gradients, exact mass matrix."""

from __future__ import annotations

from functools import cache

import sympy as sp

from codegen.conventions import symbol_matrix, symbol_vector


def edge_matrix(X_e: sp.Matrix) -> sp.Matrix:
    """Rest-pose edge matrix ``[X1 - X0, X2 - X0, X3 - X0]`` (edges as columns)."""
    return sp.Matrix.hstack(*[(X_e[v, :] - X_e[0, :]).T for v in (1, 2, 3)])


def barycentric(X_e: sp.Matrix, p: sp.Matrix) -> sp.Matrix:
    """Shape functions ``phi`` (4x1) at point ``p``: barycentric coordinates in the tet ``X_e``."""
    Dm = edge_matrix(X_e)
    tail = Dm.adjugate() * (p - X_e[0, :].T) / Dm.det()
    return sp.Matrix([1 - sum(tail), *tail])


def shape_gradients(X_e: sp.Matrix) -> sp.Matrix:
    """``dphi/dX`` (4x3): row ``v`` is the constant gradient of shape function ``v``."""
    p = symbol_vector("p", 3)
    return barycentric(X_e, p).jacobian(p)


def signed_volume(X_e: sp.Matrix) -> sp.Expr:
    """``det(edge matrix) / 6``: positive for a positively oriented tet."""
    return edge_matrix(X_e).det() / 6


@cache
def reference_mass_coefficients() -> sp.Matrix:
    """``integral_T N_i N_j dV / vol`` (4x4), integrated exactly over the reference tet."""
    u, v, w = sp.symbols("u v w", nonnegative=True)
    N = [1 - u - v - w, u, v, w]
    ref_volume = sp.Rational(1, 6)
    coefficients = sp.zeros(4, 4)
    for i in range(4):
        for j in range(4):
            integral = sp.integrate(N[i] * N[j], (w, 0, 1 - u - v), (v, 0, 1 - u), (u, 0, 1))
            coefficients[i, j] = integral / ref_volume
    return coefficients


def mass_matrix(rho: sp.Symbol, vol: sp.Symbol) -> sp.Matrix:
    """Exact consistent 12x12 mass matrix ``rho * integral_T N^T N dV`` (vertex-major DOFs)."""
    return rho * vol * sp.kronecker_product(reference_mass_coefficients(), sp.eye(3))


def rest_symbols() -> sp.Matrix:
    """Rest positions of a tet's vertices as a 4x3 symbol matrix."""
    return symbol_matrix("X", 4, 3)
