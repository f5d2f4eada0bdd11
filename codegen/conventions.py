"""Conventions shared by every derivation and by the runtime; defined once, here.

* Deformation gradient ``F`` (3x3) flattens **row-major**: flat index ``3*i + j`` holds
  ``F[i, j]`` (NumPy's ``F.reshape(m, 9)``). ``dP/dF`` is the 9x9 matrix
  ``d2psi_dF2[a, b] = d P_flat[a] / d F_flat[b]``.
* Element DOFs of a linear tetrahedron (12) are vertex-major: ``x_e.reshape(m, 12)`` with
  ``x_e`` of shape ``(m, 4, 3)``, so DOF ``3*v + c`` is coordinate ``c`` of vertex ``v``.
* ``dphi_dX`` is ``(4, 3)``: row ``v`` is the gradient of shape function ``v``.
"""

from __future__ import annotations

import sympy as sp


def symbol_matrix(name: str, rows: int, cols: int) -> sp.Matrix:
    """A matrix of real symbols ``name_i_j``, laid out row-major."""
    return sp.Matrix(rows, cols, lambda i, j: sp.Symbol(f"{name}_{i}_{j}", real=True))


def symbol_vector(name: str, n: int) -> sp.Matrix:
    """A column of real symbols ``name_i``."""
    return sp.Matrix(n, 1, lambda i, _: sp.Symbol(f"{name}_{i}", real=True))


def flatten(matrix: sp.Matrix) -> list[sp.Expr]:
    """Row-major flattening, the one order used for ``F``, ``P`` and element DOFs."""
    return [matrix[i, j] for i in range(matrix.rows) for j in range(matrix.cols)]


def deformation_gradient(x_e: sp.Matrix, dphi_dX: sp.Matrix) -> sp.Matrix:
    """``F = sum_v x_v dphi_v/dX^T`` for ``x_e`` (4x3, rows are vertices) and ``dphi_dX`` (4x3)."""
    return x_e.T * dphi_dX


def identity_like(F: sp.MatrixBase | sp.MatrixExpr) -> sp.MatrixBase | sp.MatrixExpr:
    """The 3x3 identity as ``F`` holds it: explicit for a matrix of symbols (derivations),
    ``Identity(3)`` for a matrix symbol (the formula shown by ``show`` and the docs)."""
    return sp.Identity(3) if isinstance(F, sp.MatrixExpr) else sp.eye(3)
