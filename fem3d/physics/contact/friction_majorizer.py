"""A quadratic majorizer of IPC's lagged friction, as the friction's part of Newton's matrix.

Per lagged pair ``k`` the friction potential is ``w_k lambda_k F(|u_k|)``: ``u_k = T_k dx`` the
tangential slip of the pair's stencil (``T_k = P_k^T J_k``, the lagged tangent basis times the
relative-displacement Jacobian at the lagged closest point), ``w_k`` its weight, ``lambda_k``
its lagged normal force, ``F' = g`` the smoothed Coulomb force per unit normal force
(``ipctk.smooth_mu_f1``). Its exact Hessian is ``w lambda T^T (g/y I + (g' - g/y) uh uh^T) T``
(``y = |u|``, ``uh = u / y``): along a slip well past the static zone, ``g' = 0``, the friction
has no curvature at all, so Newton's model is a ramp there. A step that carries the slip back
into the static zone, where the curvature is ``g / y ~ 1 / eps``, overshoots it; Armijo's
line search then halves the step 3-6 times per iteration (measured on the pile's impacts), and
Newton crawls.

``F(sqrt(s))`` is concave in ``s = y^2`` (``g / y`` does not increase with ``y``, also through
ipctk's static-to-kinetic blend), so

    ``F(|u + du|) <= F(y) + g/y u.du + 1/2 g/y |du|^2``

for every ``du``: ``w lambda (g / y) T^T T`` is the Hessian of a quadratic that touches the
friction at ``u`` (same value and gradient) and lies above it everywhere (iteratively
reweighted least squares, Weiszfeld's step for ``|u|``). In Newton's matrix it makes the
friction's part of every step a descent that never overshoots; the objective, its gradient and
its minimiser are IPC's own. It is positive semi-definite by construction (no eigen
projection) and equals the exact Hessian at zero slip. Where a pair slides, its step is
shorter than the exact Hessian's (the majorizer is stiffer along the slip), so IPC's stopping
rule on the step's length stops further from the minimiser at the same tolerance
(docs/contact.md "Stop 32").
"""

from __future__ import annotations

import ipctk
import numpy as np
import scipy.sparse as sp

__all__ = ["FrictionMajorizer"]


class FrictionMajorizer:
    """The majorizer's Hessian for one ``ipctk.TangentialCollisions`` (one lagging).

    Parameters
    ----------
    collisions : ipctk.TangentialCollisions
        The lagged pairs (their bases, closest points, normal forces and coefficients are
        read once, here).
    mesh : ipctk.CollisionMesh
    eps : float
        ipctk's friction smoothing as a slip (``FrictionPotential.eps_v``: ``eps_v dt``).
    """

    def __init__(self, collisions: ipctk.TangentialCollisions, mesh: ipctk.CollisionMesh,
                 eps: float) -> None:
        edges, faces = mesh.edges, mesh.faces
        pairs = [c for group in (collisions.vv_collisions, collisions.ev_collisions,
                                 collisions.ee_collisions, collisions.fv_collisions)
                 for c in group]
        m = len(pairs)
        # ipctk hands out its pairs one by one (no arrays): read once per lagging, here
        self.ids = np.full((m, 4), -1, dtype=np.int64)  # stencil vertices (-1: none)
        self.T = np.zeros((m, 2, 12))  # slip of the stencil's displacements
        self.scale = np.empty(m)  # w lambda
        self.mu = np.empty((m, 2))  # mu_s, mu_k
        for k, c in enumerate(pairs):
            jac = np.asarray(c.relative_velocity_jacobian(c.closest_point))
            n = jac.shape[1] // 3
            self.ids[k, :n] = np.asarray(c.vertex_ids(edges, faces))[:n]
            self.T[k, :, : 3 * n] = np.asarray(c.tangent_basis).T @ jac
            self.scale[k] = c.weight * c.normal_force_magnitude
            self.mu[k] = c.mu_s, c.mu_k
        self.eps = float(eps)
        self.n_vertices = mesh.num_vertices
        valid = np.repeat(self.ids >= 0, 3, axis=1)  # (m, 12)
        dofs = (np.maximum(self.ids, 0)[:, :, None] * 3 + np.arange(3)).reshape(m, 12)
        self._dofs = dofs
        self._valid = valid
        mask = valid[:, :, None] & valid[:, None, :]
        self._mask = mask
        self._rows = np.broadcast_to(dofs[:, :, None], mask.shape)[mask]
        self._cols = np.broadcast_to(dofs[:, None, :], mask.shape)[mask]

    def __len__(self) -> int:
        return len(self.scale)

    def slips(self, U: np.ndarray) -> np.ndarray:
        """``u_k``, ``(m, 2)``, of the collision vertices' displacements ``U`` (``(n, 3)``)."""
        stencil = np.where(self._valid, U.reshape(-1)[self._dofs], 0.0)
        return np.einsum("mij,mj->mi", self.T, stencil)

    def force_over_slip(self, y: np.ndarray) -> np.ndarray:
        """``mu(y) f1(y) / y`` per pair (its limit ``2 mu_s / eps`` at ``y = 0``):
        ``ipctk.smooth_mu_f1_over_x`` vectorized. ipctk's ``mu(y)`` falls from ``mu_s`` to
        ``mu_k`` over ``y < eps`` as ``1 - 2 t^2`` then ``2 (1 - t)^2`` (``t = y / eps``; a test
        holds it to ipctk's friction gradient)."""
        eps = self.eps
        mu_s, mu_k = self.mu[:, 0], self.mu[:, 1]
        small = y < eps
        f1_y = np.where(small, 2.0 / eps - y / (eps * eps), 1.0 / np.maximum(y, eps))
        t = np.minimum(y / eps, 1.0)
        blend = np.where(t < 0.5, 1.0 - 2.0 * t * t, 2.0 * (1.0 - t) ** 2)
        return (mu_k + (mu_s - mu_k) * blend) * f1_y

    def gradient(self, U: np.ndarray) -> np.ndarray:
        """The friction's gradient at ``U`` (the majorizer's is the same), ``(3n,)``."""
        u = self.slips(U)
        weight = self.scale * self.force_over_slip(np.linalg.norm(u, axis=1))
        local = weight[:, None] * np.einsum("mai,ma->mi", self.T, u)
        out = np.zeros(3 * self.n_vertices)
        np.add.at(out, self._dofs[self._valid], local[self._valid])
        return out

    def hessian(self, U: np.ndarray) -> sp.coo_matrix:
        """``sum_k w_k lambda_k (g / y)(|u_k|) T_k^T T_k`` at ``U``, ``(3n, 3n)`` COO in
        the collision mesh's DOFs (duplicates summed on conversion)."""
        weight = self.scale * self.force_over_slip(np.linalg.norm(self.slips(U), axis=1))
        local = weight[:, None, None] * np.einsum("mai,maj->mij", self.T, self.T)
        n = 3 * self.n_vertices
        return sp.coo_matrix((local[self._mask], (self._rows, self._cols)), shape=(n, n))
