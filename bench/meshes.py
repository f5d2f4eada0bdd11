"""Box tetrahedral meshes and a linear-elastic test system for the benchmarks.

Everything here is vectorized over elements (no per-element Python loops), so that building a
1e6-tet mesh and its stiffness matrix takes seconds and does not dominate a benchmark run.

Functions
---------
box_mesh(n_tets)                -> X (n_vertices, 3), T (n_tets, 4)
rest_shape(X, T)                -> dphi_dX (m, 4, 3), vol (m,)
assemble_csr(T, K_e, n)         -> (3 n, 3 n) CSR from per-element (m, 12, 12) blocks
linear_elastic_system(X, T)     -> A = M + dt^2 K restricted to free DOFs (SPD), and friends
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from fem3d.physics.model import element_dofs  # the one definition of the DOF layout

# The six tets of the Kuhn (Freudenthal) subdivision of the unit cube: each follows a monotone
# path 000 -> 111 along the axes in the order of one permutation. Corner index = x + 2 y + 4 z.
_AXIS_ORDERS = ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0))


def _kuhn_corners() -> np.ndarray:
    """Corner indices (6, 4) of the Kuhn subdivision, all positively oriented."""
    corners = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], float)
    tets = []
    for order in _AXIS_ORDERS:
        p = np.zeros(3, int)
        path = [0]
        for axis in order:
            p[axis] = 1
            path.append(int(p[0] + 2 * p[1] + 4 * p[2]))
        tets.append(path)
    tets_a = np.array(tets)
    e = corners[tets_a[:, 1:]] - corners[tets_a[:, :1]]
    neg = np.linalg.det(e) < 0
    tets_a[neg] = tets_a[neg][:, [0, 2, 1, 3]]
    return tets_a


def grid_shape(n_tets: float) -> tuple[int, int, int]:
    """Cells per axis of the cube grid whose 6-tet subdivision has about ``n_tets`` tets."""
    n = max(1, round((float(n_tets) / 6.0) ** (1.0 / 3.0)))
    return n, n, n


def box_mesh(
    n_tets: float, size: tuple[float, float, float] = (1.0, 1.0, 1.0)
) -> tuple[np.ndarray, np.ndarray]:
    """Structured tet mesh of a box with about ``n_tets`` tets (6 per grid cube).

    Parameters
    ----------
    n_tets : float
        Target tet count; the grid is ``n x n x n`` cubes with ``n = round((n_tets / 6)^(1/3))``,
        so e.g. 1e5 gives 26^3 cubes = 105,456 tets and 27^3 = 19,683 vertices.
    size : (3,) float
        Box extents.

    Returns
    -------
    X : (n_vertices, 3) float64
        Vertex positions, x fastest.
    T : (n_tets, 4) int64
        Tets, 0-based, positively oriented.
    """
    nx, ny, nz = grid_shape(n_tets)
    xs = np.linspace(0.0, size[0], nx + 1)
    ys = np.linspace(0.0, size[1], ny + 1)
    zs = np.linspace(0.0, size[2], nz + 1)
    Z, Y, Xg = np.meshgrid(zs, ys, xs, indexing="ij")
    X = np.stack([Xg.ravel(), Y.ravel(), Z.ravel()], axis=1)

    def vid(i: np.ndarray, j: np.ndarray, k: np.ndarray) -> np.ndarray:
        return i + (nx + 1) * (j + (ny + 1) * k)

    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    i, j, k = i.ravel(), j.ravel(), k.ravel()
    # (n_cubes, 8) global ids of the corners, corner index = dx + 2 dy + 4 dz
    cube = np.stack(
        [vid(i + dx, j + dy, k + dz) for dz in (0, 1) for dy in (0, 1) for dx in (0, 1)], axis=1
    )
    T = cube[:, _kuhn_corners()].reshape(-1, 4).astype(np.int64)
    return X, T


def rest_shape(X: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shape-function gradients and volumes of linear tets.

    Parameters
    ----------
    X : (n_vertices, 3) float64
    T : (m, 4) int64

    Returns
    -------
    dphi_dX : (m, 4, 3) float64
        ``dphi_dX[e, a, :]`` = gradient of vertex ``a``'s hat function in element ``e``.
    vol : (m,) float64
        Signed volumes (positive for positively oriented tets).
    """
    Xe = X[T]
    Dm = np.swapaxes(Xe[:, 1:] - Xe[:, :1], 1, 2)  # (m, 3, 3), columns = edges
    vol = np.linalg.det(Dm) / 6.0
    Dinv = np.linalg.inv(Dm)  # rows = gradients of phi_1..phi_3
    dphi = np.empty((len(T), 4, 3))
    dphi[:, 1:] = Dinv
    dphi[:, 0] = -Dinv.sum(axis=1)
    return dphi, vol


def assemble_csr(T: np.ndarray, K_e: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """Assemble per-element blocks into a CSR matrix (COO -> CSR, duplicates summed).

    Parameters
    ----------
    T : (m, 4) int64
    K_e : (m, 12, 12) float64
    n_vertices : int

    Returns
    -------
    (3 n_vertices, 3 n_vertices) scipy.sparse.csr_matrix
    """
    dofs = element_dofs(T)
    rows = np.broadcast_to(dofs[:, :, None], K_e.shape).ravel()
    cols = np.broadcast_to(dofs[:, None, :], K_e.shape).ravel()
    n = 3 * n_vertices
    A = sp.coo_matrix((K_e.ravel(), (rows, cols)), shape=(n, n)).tocsr()
    A.sum_duplicates()
    return A


@dataclass(frozen=True)
class LinearSystem:
    """A = M + dt^2 K restricted to the free DOFs (SPD), plus its parts."""

    A: sp.csr_matrix  #: (n_free, n_free) M + dt^2 K on free DOFs
    M: sp.csr_matrix  #: (n_free, n_free) consistent mass matrix on free DOFs
    K: sp.csr_matrix  #: (n_free, n_free) linear-elastic stiffness on free DOFs
    free: np.ndarray  #: (n_free,) indices of the free DOFs among the 3 n_vertices


def linear_elastic_system(
    X: np.ndarray,
    T: np.ndarray,
    *,
    E: float = 6e5,
    nu: float = 0.4,
    rho: float = 0.1,
    dt: float = 0.01,
) -> LinearSystem:
    """Backward-Euler system matrix of a linear-elastic box clamped at its bottom (z = min).

    This is the Neo-Hookean Hessian at rest (Lame mu, lambda from E, nu), a stand-in with the
    same sparsity pattern and conditioning as the matrices a Newton step factorizes.

    Parameters
    ----------
    X : (n_vertices, 3) float64
    T : (m, 4) int64
    E, nu, rho, dt : float
        Young's modulus, Poisson ratio, density, time step (the armadillo scene's by default).

    Returns
    -------
    LinearSystem
    """
    dphi, vol = rest_shape(X, T)
    mu = E / (2.0 * (1.0 + nu))
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    g = dphi
    # K[a i, b j] = vol (lam g_ai g_bj + mu (g_aj g_bi + delta_ij g_a . g_b))
    Ke = lam * np.einsum("mai,mbj->maibj", g, g)
    Ke += mu * np.einsum("maj,mbi->maibj", g, g)
    gg = np.einsum("mak,mbk->mab", g, g)
    Ke += mu * np.einsum("mab,ij->maibj", gg, np.eye(3))
    Ke *= vol[:, None, None, None, None]
    Ke = Ke.reshape(len(T), 12, 12)
    Me = (rho * vol / 20.0)[:, None, None, None, None] * np.einsum(
        "ab,ij->aibj", np.ones((4, 4)) + np.eye(4), np.eye(3)
    )[None]
    Me = Me.reshape(len(T), 12, 12)
    n = len(X)
    fixed_v = X[:, 2] <= X[:, 2].min() + 1e-12
    free = np.flatnonzero(~np.repeat(fixed_v, 3))
    # Assemble each matrix on its own so that all three share the full 12x12-block pattern
    # (stored zeros kept), as an assembler with a fixed scatter map produces.
    Kf = assemble_csr(T, Ke, n)[free][:, free].tocsr()
    Mf = assemble_csr(T, Me, n)[free][:, free].tocsr()
    A = assemble_csr(T, Me + (dt * dt) * Ke, n)[free][:, free].tocsr()
    for Z in (Kf, Mf, A):
        Z.sort_indices()
    return LinearSystem(A=A, M=Mf, K=Kf, free=free)


# The octahedron left inside a tet by cutting its four corners is split along one of its three
# diagonals (pairs of opposite edge midpoints); around each diagonal the other four midpoints
# form a cycle. Local edge order: 01, 02, 03, 12, 13, 23.
_EDGES = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))
_DIAGONALS = (((0, 5), (1, 2, 4, 3)), ((1, 4), (0, 2, 5, 3)), ((2, 3), (0, 1, 5, 4)))


def refine_tets(X: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Red (1:8) refinement: every tet split into 8 by its edge midpoints.

    The four corner tets are similar to the parent; the inner octahedron is cut along its
    shortest diagonal. The shape (and so the scene: fixed feet, picked hand) is unchanged.

    Parameters
    ----------
    X : (n, 3) float64
    T : (m, 4) int64

    Returns
    -------
    X : (n + n_edges, 3) float64
        The old vertices first (their indices are kept), then the edge midpoints.
    T : (8 m, 4) int64
        Positively oriented.
    """
    X = np.asarray(X, dtype=np.float64)
    T = np.asarray(T, dtype=np.int64)
    m = len(T)
    pairs = np.sort(T[:, np.array(_EDGES)], axis=2).reshape(-1, 2)
    edges, inverse = np.unique(pairs, axis=0, return_inverse=True)
    mid = len(X) + inverse.reshape(m, 6)
    X_new = np.vstack([X, 0.5 * (X[edges[:, 0]] + X[edges[:, 1]])])
    v, e = T.T, mid.T
    tets = [np.stack([v[0], e[0], e[1], e[2]], 1), np.stack([e[0], v[1], e[3], e[4]], 1),
            np.stack([e[1], e[3], v[2], e[5]], 1), np.stack([e[2], e[4], e[5], v[3]], 1)]
    lengths = np.stack([np.linalg.norm(X_new[mid[:, a]] - X_new[mid[:, b]], axis=1)
                        for (a, b), _ in _DIAGONALS], axis=1)
    choice = np.argmin(lengths, axis=1)
    for k in range(4):
        inner = np.zeros((m, 4), dtype=np.int64)
        for d, ((a, b), ring) in enumerate(_DIAGONALS):
            sel = choice == d
            c0, c1 = ring[k], ring[(k + 1) % 4]
            inner[sel] = mid[sel][:, [a, b, c0, c1]]
        tets.append(inner)
    T_new = np.concatenate(tets, axis=0)
    edges_new = X_new[T_new[:, 1:]] - X_new[T_new[:, :1]]
    negative = np.linalg.det(edges_new) < 0
    T_new[negative] = T_new[negative][:, [0, 2, 1, 3]]
    return X_new, T_new
