"""The assignment's function names, as thin wrappers over the generated kernels and the runtime
(an example of using the runtime's parts directly; ``tests/physics/test_assembly.py`` runs it).

For readers who know the CSC417 linear-tetrahedron assignment: each function below has the
assignment's name and computes the same quantity, vectorized over elements (a leading ``m``
axis) instead of one element at a time, and returning its result instead of filling an
output argument. Nothing here is derived by hand: material and spring derivatives come from
the SymPy-generated kernels (:mod:`fem3d.kernels.dispatch`), assembly from
:mod:`fem3d.physics.assembly`.

Conventions: ``X_e``/``x_e`` are ``(m, 4, 3)`` rest/deformed tet corners; element DOFs are
vertex-major (12); ``F`` is flattened row-major (9). ``C, D`` are the Neo-Hookean parameters
(``C = 0.5 E / (2 (1 + nu))``, ``D = 0.5 E nu / ((1 + nu)(1 - 2 nu))``).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.sparse as sp

from fem3d.kernels.dispatch import geometry_kernels, material_kernels, spring_kernels
from fem3d.mesh.skin import build_skinning_matrix
from fem3d.physics import assembly as _assembly
from fem3d.physics.constraints import fixed_point_constraints, pick_nearest_vertices
from fem3d.physics.model import Model
from fem3d.solve.integrators import implicit_euler, linearly_implicit_euler
from fem3d.solve.newton import newtons_method

__all__ = [
    "phi_linear_tetrahedron",
    "dphi_linear_tetrahedron_dX",
    "psi_neo_hookean",
    "dpsi_neo_hookean_dF",
    "d2psi_neo_hookean_dF2",
    "T_linear_tetrahedron",
    "quadrature_single_point",
    "V_linear_tetrahedron",
    "dV_linear_tetrahedron_dq",
    "d2V_linear_tetrahedron_dq2",
    "V_spring_particle_particle",
    "dV_spring_particle_particle_dq",
    "mass_matrix_linear_tetrahedron",
    "mass_matrix_mesh",
    "assemble_forces",
    "assemble_stiffness",
    "build_skinning_matrix",
    "fixed_point_constraints",
    "pick_nearest_vertices",
    "linearly_implicit_euler",
    "newtons_method",
    "implicit_euler",
]


def _nh(backend: str | None = None):
    return material_kernels("neo_hookean", backend=backend)


def _geo(backend: str | None = None):
    return geometry_kernels(backend=backend)


def _spring(backend: str | None = None):
    return spring_kernels(backend=backend)


def _elements(a: np.ndarray, shape: tuple[int, ...]) -> tuple[np.ndarray, bool]:
    """Add a leading element axis to a single element; returns (array, was_single)."""
    a = np.asarray(a, dtype=np.float64)
    if a.shape == shape:
        return a[None], True
    return a, False


def phi_linear_tetrahedron(X_e: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Linear shape functions (barycentric coordinates) of points in tets.

    Parameters
    ----------
    X_e : (m, 4, 3) or (4, 3) float64
        Rest corners.
    x : (m, 3) or (3,) float64
        One point per tet.

    Returns
    -------
    (m, 4) or (4,) float64
        ``phi_i(x)``, summing to 1.
    """
    X_e, single = _elements(X_e, (4, 3))
    p = np.asarray(x, dtype=np.float64).reshape(-1, 3)
    out = _geo().phi(X_e, p)
    return out[0] if single else out


def dphi_linear_tetrahedron_dX(X_e: np.ndarray) -> np.ndarray:
    """Gradients of the four linear shape functions (constant over each tet).

    Parameters
    ----------
    X_e : (m, 4, 3) or (4, 3) float64

    Returns
    -------
    (m, 4, 3) or (4, 3) float64
        Row ``i`` is ``d phi_i / dX``.
    """
    X_e, single = _elements(X_e, (4, 3))
    dphi, _ = _geo().rest_shape(X_e)
    return dphi[0] if single else dphi


def psi_neo_hookean(F: np.ndarray, C: float, D: float) -> np.ndarray:
    """Neo-Hookean energy density ``C (J^(-2/3) tr(F^T F) - 3) + D (J - 1)^2``.

    Parameters
    ----------
    F : (m, 3, 3) float64

    Returns
    -------
    (m,) float64
    """
    return _nh().psi(np.asarray(F, dtype=np.float64).reshape(-1, 3, 3), (C, D))


def dpsi_neo_hookean_dF(F: np.ndarray, C: float, D: float) -> np.ndarray:
    """First Piola-Kirchhoff stress ``dpsi/dF``.

    Returns
    -------
    (m, 3, 3) float64
    """
    return _nh().dpsi_dF(np.asarray(F, dtype=np.float64).reshape(-1, 3, 3), (C, D))


def d2psi_neo_hookean_dF2(F: np.ndarray, C: float, D: float) -> np.ndarray:
    """``d2psi/dF2`` with ``F`` flattened row-major: entry ``[a, b] = dP_a / dF_b``.

    Returns
    -------
    (m, 9, 9) float64
    """
    return _nh().d2psi_dF2(np.asarray(F, dtype=np.float64).reshape(-1, 3, 3), (C, D))


def mass_matrix_linear_tetrahedron(vol: np.ndarray, rho: float) -> np.ndarray:
    """Exact consistent mass matrix of linear tets, ``rho vol / 20 (1 + delta_ij) I_3``.

    Parameters
    ----------
    vol : (m,) float64
        Rest volumes.
    rho : float
        Density.

    Returns
    -------
    (m, 12, 12) float64
    """
    return _geo().mass_matrix(np.asarray(vol, dtype=np.float64).reshape(-1), (rho,))


def T_linear_tetrahedron(qdot_e: np.ndarray, vol: np.ndarray, rho: float) -> np.ndarray:
    """Kinetic energy of each tet, ``1/2 qdot_e^T M_e qdot_e``.

    Parameters
    ----------
    qdot_e : (m, 4, 3) float64
        Corner velocities.
    vol : (m,) float64
    rho : float

    Returns
    -------
    (m,) float64
    """
    v = np.asarray(qdot_e, dtype=np.float64).reshape(-1, 12)
    M = mass_matrix_linear_tetrahedron(vol, rho)
    return 0.5 * np.einsum("ei,eij,ej->e", v, M, v)


def quadrature_single_point(integrand: Callable[[], np.ndarray], vol: np.ndarray) -> np.ndarray:
    """One-point quadrature over tets: ``vol * f`` (exact for the constant strain of P1 tets).

    Parameters
    ----------
    integrand : callable ``() -> (m, ...)``
        The integrand evaluated at the tet (constant over it for linear tets).
    vol : (m,) float64

    Returns
    -------
    (m, ...) float64
    """
    f = np.asarray(integrand(), dtype=np.float64)
    v = np.asarray(vol, dtype=np.float64).reshape(-1)
    return f * v.reshape(v.shape + (1,) * (f.ndim - 1))


def V_linear_tetrahedron(x_e, dphi_dX, vol, C: float, D: float) -> np.ndarray:
    """Strain energy of each tet, ``vol psi(F)`` with ``F = x_e^T dphi_dX``.

    Parameters
    ----------
    x_e : (m, 4, 3) float64
    dphi_dX : (m, 4, 3) float64
    vol : (m,) float64

    Returns
    -------
    (m,) float64
    """
    return _nh().energy(x_e, dphi_dX, vol, (C, D))


def dV_linear_tetrahedron_dq(x_e, dphi_dX, vol, C: float, D: float) -> np.ndarray:
    """Gradient of each tet's strain energy w.r.t. its 12 vertex-major DOFs.

    Returns
    -------
    (m, 12) float64
    """
    return _nh().gradient(x_e, dphi_dX, vol, (C, D))


def d2V_linear_tetrahedron_dq2(x_e, dphi_dX, vol, C: float, D: float) -> np.ndarray:
    """Hessian of each tet's strain energy (vertex-major DOFs).

    Returns
    -------
    (m, 12, 12) float64
    """
    return _nh().hessian(x_e, dphi_dX, vol, (C, D))


def _check_zero_rest(l0: float) -> None:
    if l0 != 0.0:
        raise ValueError(
            "only zero-rest-length springs (the pull spring) are generated; l0 must be 0"
        )


def V_spring_particle_particle(q0, q1, l0: float, k: float) -> np.ndarray:
    """Energy ``1/2 k |q0 - q1|^2`` of zero-rest-length springs.

    Parameters
    ----------
    q0, q1 : (m, 3) float64
        End points.
    l0 : float
        Rest length; must be 0 (the generated spring is the assignment's mouse spring).
    k : float
        Stiffness.

    Returns
    -------
    (m,) float64
    """
    _check_zero_rest(l0)
    return _spring().energy(np.reshape(q0, (-1, 3)), np.reshape(q1, (-1, 3)), (k,))


def dV_spring_particle_particle_dq(q0, q1, l0: float, k: float) -> np.ndarray:
    """Gradient of zero-rest-length spring energy w.r.t. ``(q0, q1)``.

    Returns
    -------
    (m, 6) float64
    """
    _check_zero_rest(l0)
    return _spring().gradient(np.reshape(q0, (-1, 3)), np.reshape(q1, (-1, 3)), (k,))


def mass_matrix_mesh(model: Model) -> sp.csr_matrix:
    """Assembled consistent mass matrix, ``(3n, 3n)`` CSR (precomputed in ``model``)."""
    return _assembly.mass_matrix_mesh(model)


def assemble_forces(model: Model, q: np.ndarray) -> np.ndarray:
    """Generalized elastic forces ``f = -dV/dq``, ``(3n,)``; ``q`` is ``(n, 3)`` or ``(3n,)``."""
    return _assembly.assemble_forces(model, q)


def assemble_stiffness(model: Model, q: np.ndarray) -> sp.csr_matrix:
    """Stiffness ``K = -d2V/dq2`` (the assignment's sign), ``(3n, 3n)`` CSR."""
    return _assembly.assemble_stiffness(model, q)
