"""Peer: plain vectorized NumPy + SciPy Neo-Hookean, written the textbook way.

``psi(F) = C (J^(-2/3) tr(F^T F) - 3) + D (J - 1)^2`` with hand-derived derivatives in the
9-vector form (``F`` flattened row-major), the per-element ``(9, 12)`` matrices
``B = dvec(F)/dx_e`` and ``einsum`` products, a fresh COO -> CSR conversion for every Hessian,
and ``scipy.sparse.linalg.spsolve`` (SuperLU) for the linear system. No code generation, no
precomputed scatter map: what a careful NumPy user writes first.

With ``g = cof(F) = J F^-T``, ``a = J^(-2/3)``, ``b = J^(-5/3)``, ``c = J^(-8/3)``:

* ``P = 2 C a F - (2/3) C I1 b g + 2 D (J - 1) g``
* ``d2psi = 2 C a I9 - (4/3) C b (F g^T + g F^T) + ((10/9) C I1 c + 2 D) g g^T + s H_J``,
  ``s = 2 D (J - 1) - (2/3) C I1 b``, ``H_J[(i,l),(j,m)] = eps_ijk eps_lmn F_kn``.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from bench import BenchMesh, register

LIB = "numpy-baseline"

_EPS = np.zeros((3, 3, 3))
_EPS[0, 1, 2] = _EPS[1, 2, 0] = _EPS[2, 0, 1] = 1.0
_EPS[0, 2, 1] = _EPS[2, 1, 0] = _EPS[1, 0, 2] = -1.0


def b_matrices(dphi: np.ndarray) -> np.ndarray:
    """``B[e] = dvec(F_e)/dx_e``: (m, 9, 12), ``B[3i+j, 3a+k] = delta_ik dphi[a, j]``."""
    m = len(dphi)
    return np.einsum("ik,maj->mijak", np.eye(3), dphi).reshape(m, 9, 12)


def deformation_gradient(x_e: np.ndarray, dphi: np.ndarray) -> np.ndarray:
    """``F = sum_a x_a dphi_a^T``: x_e (m, 4, 3), dphi (m, 4, 3) -> (m, 3, 3)."""
    return np.einsum("mai,maj->mij", x_e, dphi)


def _invariants(F: np.ndarray):
    f0, f1, f2 = F[:, :, 0], F[:, :, 1], F[:, :, 2]
    g = np.stack([np.cross(f1, f2), np.cross(f2, f0), np.cross(f0, f1)], axis=2)  # cof(F)
    J = np.einsum("mi,mi->m", f0, g[:, :, 0])
    I1 = np.einsum("mij,mij->m", F, F)
    return g, J, I1


def psi(F: np.ndarray, C: float, D: float) -> np.ndarray:
    """(m, 3, 3) -> (m,)."""
    _, J, I1 = _invariants(F)
    return C * (J ** (-2.0 / 3.0) * I1 - 3.0) + D * (J - 1.0) ** 2


def pk1(F: np.ndarray, C: float, D: float) -> np.ndarray:
    """First Piola-Kirchhoff stress (m, 3, 3)."""
    g, J, I1 = _invariants(F)
    a = J ** (-2.0 / 3.0)
    b = a / J
    return (2 * C * a)[:, None, None] * F + (
        -(2.0 / 3.0) * C * I1 * b + 2 * D * (J - 1.0)
    )[:, None, None] * g


def d2psi_dF2(F: np.ndarray, C: float, D: float) -> np.ndarray:
    """(m, 9, 9), ``[a, b] = d P_flat[a] / d F_flat[b]`` (row-major flattening)."""
    m = len(F)
    g, J, I1 = _invariants(F)
    a = J ** (-2.0 / 3.0)
    b = a / J
    c = b / J
    f9 = F.reshape(m, 9)
    g9 = g.reshape(m, 9)
    HJ = np.einsum("ijk,lmn,ekn->eiljm", _EPS, _EPS, F).reshape(m, 9, 9)
    s = 2 * D * (J - 1.0) - (2.0 / 3.0) * C * I1 * b
    H = (s[:, None, None]) * HJ
    H += ((10.0 / 9.0) * C * I1 * c + 2 * D)[:, None, None] * np.einsum("ma,mb->mab", g9, g9)
    fg = np.einsum("ma,mb->mab", f9, g9)
    H -= ((4.0 / 3.0) * C * b)[:, None, None] * (fg + np.swapaxes(fg, 1, 2))
    H[:, np.arange(9), np.arange(9)] += (2 * C * a)[:, None]
    return H


class NumpyNeoHookean:
    """Energy, gradient and Hessian of a tet mesh, plain NumPy.

    Parameters
    ----------
    X : (n, 3) float64
    T : (m, 4) int64
    C, D : float
    """

    def __init__(self, X: np.ndarray, T: np.ndarray, C: float, D: float) -> None:
        from bench.meshes import element_dofs, rest_shape

        self.T = T
        self.n = len(X)
        self.C, self.D = C, D
        self.dphi, self.vol = rest_shape(X, T)
        self.B = b_matrices(self.dphi)
        self.dofs = element_dofs(T)

    def energy(self, q: np.ndarray) -> float:
        F = deformation_gradient(q[self.T], self.dphi)
        return float(np.dot(self.vol, psi(F, self.C, self.D)))

    def element_gradients(self, q: np.ndarray) -> np.ndarray:
        """(m, 12)."""
        F = deformation_gradient(q[self.T], self.dphi)
        P9 = pk1(F, self.C, self.D).reshape(len(F), 9)
        return self.vol[:, None] * np.einsum("mab,ma->mb", self.B, P9)

    def gradient(self, q: np.ndarray) -> np.ndarray:
        """(3n,)."""
        ge = self.element_gradients(q)
        return np.bincount(self.dofs.ravel(), weights=ge.ravel(), minlength=3 * self.n)

    def element_hessians(self, q: np.ndarray) -> np.ndarray:
        """(m, 12, 12) = vol B^T d2psi B."""
        F = deformation_gradient(q[self.T], self.dphi)
        H9 = d2psi_dF2(F, self.C, self.D)
        He = np.einsum("mai,mab,mbj->mij", self.B, H9, self.B, optimize=True)
        return He * self.vol[:, None, None]

    def hessian(self, q: np.ndarray) -> sp.csr_matrix:
        """(3n, 3n) CSR via COO -> CSR."""
        He = self.element_hessians(q)
        rows = np.broadcast_to(self.dofs[:, :, None], He.shape).ravel()
        cols = np.broadcast_to(self.dofs[:, None, :], He.shape).ravel()
        N = 3 * self.n
        return sp.coo_matrix((He.ravel(), (rows, cols)), shape=(N, N)).tocsr()


def _model(mesh: BenchMesh) -> NumpyNeoHookean:
    C, D = mesh.params
    return NumpyNeoHookean(mesh.X, mesh.T, float(C), float(D))


@register("energy/numpy-baseline", group="energy", library=LIB)
def _energy(mesh: BenchMesh):
    nh = _model(mesh)
    return lambda: nh.energy(mesh.q)


@register("gradient/numpy-baseline", group="gradient", library=LIB)
def _gradient(mesh: BenchMesh):
    nh = _model(mesh)
    return lambda: nh.gradient(mesh.q)


@register("hessian_elements/numpy-baseline", group="hessian_elements", library=LIB)
def _hess_e(mesh: BenchMesh):
    nh = _model(mesh)
    return lambda: nh.element_hessians(mesh.q)


@register("hessian_csr/numpy-baseline", group="hessian_csr", library=LIB)
def _hess_csr(mesh: BenchMesh):
    nh = _model(mesh)
    return lambda: nh.hessian(mesh.q)


@register(
    "factor/scipy-spsolve",
    group="factor",
    library="scipy spsolve",
    max_tets=1.1e5,
    note="scipy spsolve: SuperLU factor + solve from scratch, COLAMD ordering each call.",
)
def _spsolve(mesh: BenchMesh):
    A = mesh.system.A.tocsc()
    b = np.ones(A.shape[0])
    return lambda: spla.spsolve(A, b)
