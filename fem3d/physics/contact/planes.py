"""Point-plane contact pairs of :class:`fem3d.physics.contact.model.ContactModel`, vectorized.

Planes are point-plane pairs evaluated in NumPy with ipctk's own formulas (the same barrier
``b(s^2, dhat^2)`` of the signed distance ``s``, the same normal force, tangent projection and
friction mollifier); :mod:`fem3d.physics.contact.model` says why. :class:`PlanePairs` holds the
methods; the model holds the state they read (``planes``, ``surface``, ``dhat``, ``kappa``,
the lagged normal forces).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from fem3d.physics.contact.friction_profile import point_plane_friction

__all__ = ["Entries", "PlanePairs"]


class Entries(NamedTuple):
    """COO triplets of a sparse matrix (duplicates summed later), without building a SciPy
    matrix: its construction checks the indices, which costs more than the contact blocks
    themselves on a Newton iteration."""

    row: np.ndarray
    col: np.ndarray
    data: np.ndarray

    def tocoo(self) -> Entries:
        """Itself (the duck type of ``scipy.sparse`` matrices' ``tocoo``)."""
        return self


class PlanePairs:
    """The point-plane barrier, lagged friction and CCD of a contact model's planes (a
    mixin of :class:`fem3d.physics.contact.model.ContactModel`)."""

    def _plane_distances(self, q: np.ndarray) -> np.ndarray:
        """Signed distances ``(n_planes, n_surface)`` of the surface vertices."""
        P = np.asarray(q, dtype=np.float64).reshape(-1, 3)[self.surface]
        return self._plane_n @ P.T - self._plane_o[:, None]

    def _plane_barrier(self, q: np.ndarray, order: int, *, project: bool = True):
        """``kappa sum b(s^2, dhat^2)`` over point-plane pairs closer than ``dhat``: the
        energy (``order`` 0), its gradient on the collision DOFs (1) or Hessian (2, sparse on
        the collision DOFs; PSD-projected: the one eigenvalue along the normal clamped)."""
        ns = self.n_surface
        if not self.planes:
            return 0.0 if order == 0 else np.zeros(3 * ns)
        S = self._plane_distances(q)
        if order == 0 and (S <= 0).any():
            return math.inf
        pl, vi = np.nonzero(S < self.dhat)
        s = S[pl, vi]
        z, zh = s * s, self.dhat * self.dhat
        k = self.kappa
        if order == 0:
            return float(k * (-(z - zh) ** 2 * np.log(z / zh)).sum())
        b1 = -2.0 * (z - zh) * np.log(z / zh) - (z - zh) ** 2 / z  # db/dz
        n = self._plane_n[pl]
        if order == 1:
            g = np.zeros((ns, 3))
            np.add.at(g, vi, (k * b1 * 2.0 * s)[:, None] * n)
            return g.reshape(-1)
        b2 = -2.0 * np.log(z / zh) - 4.0 * (z - zh) / z + (z - zh) ** 2 / (z * z)
        c = k * (4.0 * z * b2 + 2.0 * b1)
        if project:  # a guard: c > 0 for s in (0, dhat), so clamping and mirroring agree
            c = np.maximum(c, 0.0)
        blocks = c[:, None, None] * n[:, :, None] * n[:, None, :]
        return self._blocks_matrix(vi, blocks)

    def _plane_projection(self, project: bool) -> bool | str:
        """``project`` for :func:`point_plane_friction`: ``"abs"`` when the model mirrors
        negative eigenvalues (``hessian_projection``)."""
        return "abs" if project and self.hessian_projection == "abs" else project

    def _blocks_matrix(self, vi: np.ndarray, blocks: np.ndarray) -> Entries:
        """``(k, 3, 3)`` blocks on the diagonal of collision vertices ``vi``, as COO triplets
        on the collision DOFs (duplicates summed later)."""
        d = 3 * vi[:, None] + np.arange(3)
        rows = np.broadcast_to(d[:, :, None], blocks.shape).reshape(-1)
        cols = np.broadcast_to(d[:, None, :], blocks.shape).reshape(-1)
        return Entries(rows, cols, blocks.reshape(-1))

    def _lag_planes(self, q_lag: np.ndarray) -> None:
        """Normal forces ``lambda = kappa |db/ds|`` and vertices of the point-plane pairs active
        at ``q_lag`` (tangent planes are the planes': fixed)."""
        self._plane_lag = None
        if not self.planes or self.mu == 0.0:
            return
        S = self._plane_distances(q_lag)
        pl, vi = np.nonzero((S < self.dhat) & (S > 0))
        if pl.size == 0:
            return
        s = S[pl, vi]
        z, zh = s * s, self.dhat * self.dhat
        b1 = -2.0 * (z - zh) * np.log(z / zh) - (z - zh) ** 2 / z
        lam = self.kappa * np.abs(b1 * 2.0 * s)
        self._plane_lag = (pl, vi, lam)

    def _plane_friction(self, q: np.ndarray, order: int, *, project: bool = True):
        """Lagged point-plane friction ``sum lambda F(|P (x - x_lag)|)`` (ipctk's mollifier
        with ``eps = eps_v dt``, ``mu_s``/``mu_k``: :mod:`.friction_profile`): energy,
        gradient or Hessian on collision DOFs."""
        ns = self.n_surface
        if self._plane_lag is None:
            return 0.0 if order == 0 else (np.zeros(3 * ns) if order == 1 else None)
        pl, vi, lam = self._plane_lag
        P = np.asarray(q, dtype=np.float64).reshape(-1, 3)[self.surface]
        out = point_plane_friction(self._plane_n[pl], P[vi] - self._lagged_V[vi], lam,
                                   self.eps_v * self._dt, self.mu, self.mu_k, order,
                                   project=self._plane_projection(project))
        if order == 1:
            g = np.zeros((ns, 3))
            np.add.at(g, vi, out)
            return g.reshape(-1)
        return out if order == 0 else self._blocks_matrix(vi, out)

    def _plane_step(self, P0: np.ndarray, P1: np.ndarray) -> float:
        """CCD of points moving linearly against the static planes: ``0.9`` of the first time
        of impact (the conservative rescaling of ipctk's additive CCD). Done here, vectorized:
        ipctk's plane CCD goes through a vertex-vertex broad phase of the point cloud."""
        a = 1.0
        for p in self.planes:
            s0 = (P0 - p.point) @ p.normal
            s1 = (P1 - p.point) @ p.normal
            hit = s1 < 0.0
            if hit.any():
                toi = s0[hit] / (s0[hit] - s1[hit])
                a = min(a, 0.9 * float(toi.min()))
        return max(a, 0.0)
