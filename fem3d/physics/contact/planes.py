"""Point-plane contact pairs, vectorized in NumPy: the planes' barrier, lagged friction and CCD.

Planes are point-plane pairs evaluated here with ipctk's own formulas (the same barrier
``b(s^2, dhat^2)`` of the signed distance ``s``, the same normal force, tangent projection and
friction mollifier; the tests compare the two), for two reasons measured on ipctk 1.6.1: its
plane-vertex candidates inflate only the vertex's box, so the one-call
``NormalCollisions.build(mesh, V, dhat)`` activates a plane only within ``dhat / 2`` (the
energy would jump there), and its plane CCD and candidates go through a broad phase over the
surface vertices that cost more than the rest of a bunny step.

:class:`PlanePairs` holds the planes and the surface vertices they act on; the barrier's
stiffness and the friction's lagged data are passed in by their owners (:mod:`.barrier`,
:mod:`.friction`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from fem3d.physics.contact.friction_profile import point_plane_friction
from fem3d.physics.contact.geometry import Entries
from fem3d.physics.contact.obstacles import PlaneObstacle

__all__ = ["PlaneLag", "PlanePairs"]


class PlaneLag(NamedTuple):
    """The point-plane pairs active at a lagging: plane and surface vertex of each pair,
    and its normal force."""

    planes: np.ndarray
    vertices: np.ndarray
    normal_forces: np.ndarray


class PlanePairs:
    """The point-plane pairs of static planes and the bodies' surface vertices.

    Parameters
    ----------
    planes : sequence of PlaneObstacle
    surface : (n_surface,) int64
        fem3d vertex of each surface (collision) vertex.
    dhat : float
        Barrier activation distance.
    """

    def __init__(self, planes: Sequence[PlaneObstacle], surface: np.ndarray,
                 dhat: float) -> None:
        self.planes = tuple(planes)
        self.surface = surface
        self.n_surface = surface.size
        self.dhat = float(dhat)
        self.normals = np.array([p.normal for p in self.planes]).reshape(-1, 3)
        self.offsets = np.array([p.point @ p.normal for p in self.planes]).reshape(-1)

    def distances(self, q: np.ndarray) -> np.ndarray:
        """Signed distances ``(n_planes, n_surface)`` of the surface vertices."""
        P = np.asarray(q, dtype=np.float64).reshape(-1, 3)[self.surface]
        return self.normals @ P.T - self.offsets[:, None]

    def n_active(self, q: np.ndarray) -> int:
        """Number of point-plane pairs closer than ``dhat`` at ``q``."""
        if not self.planes:
            return 0
        return int(np.count_nonzero(self.distances(q) < self.dhat))

    def barrier(self, q: np.ndarray, order: int, kappa: float, *, project: bool = True):
        """``kappa sum b(s^2, dhat^2)`` over point-plane pairs closer than ``dhat``: the
        energy (``order`` 0), its gradient on the collision DOFs (1) or Hessian (2, sparse on
        the collision DOFs; PSD-projected: the one eigenvalue along the normal clamped)."""
        ns = self.n_surface
        if not self.planes:
            return 0.0 if order == 0 else np.zeros(3 * ns)
        S = self.distances(q)
        if order == 0 and (S <= 0).any():
            return math.inf
        pl, vi = np.nonzero(S < self.dhat)
        s = S[pl, vi]
        z, zh = s * s, self.dhat * self.dhat
        k = kappa
        if order == 0:
            return float(k * (-(z - zh) ** 2 * np.log(z / zh)).sum())
        b1 = -2.0 * (z - zh) * np.log(z / zh) - (z - zh) ** 2 / z  # db/dz
        n = self.normals[pl]
        if order == 1:
            g = np.zeros((ns, 3))
            np.add.at(g, vi, (k * b1 * 2.0 * s)[:, None] * n)
            return g.reshape(-1)
        b2 = -2.0 * np.log(z / zh) - 4.0 * (z - zh) / z + (z - zh) ** 2 / (z * z)
        c = k * (4.0 * z * b2 + 2.0 * b1)
        if project:  # a guard: c > 0 for s in (0, dhat), so clamping and mirroring agree
            c = np.maximum(c, 0.0)
        blocks = c[:, None, None] * n[:, :, None] * n[:, None, :]
        return self.blocks_matrix(vi, blocks)

    @staticmethod
    def blocks_matrix(vi: np.ndarray, blocks: np.ndarray) -> Entries:
        """``(k, 3, 3)`` blocks on the diagonal of collision vertices ``vi``, as COO triplets
        on the collision DOFs (duplicates summed later)."""
        d = 3 * vi[:, None] + np.arange(3)
        rows = np.broadcast_to(d[:, :, None], blocks.shape).reshape(-1)
        cols = np.broadcast_to(d[:, None, :], blocks.shape).reshape(-1)
        return Entries(rows, cols, blocks.reshape(-1))

    def lag(self, q_lag: np.ndarray, kappa: float) -> PlaneLag | None:
        """Normal forces ``lambda = kappa |db/ds|`` and vertices of the point-plane pairs active
        at ``q_lag`` (tangent planes are the planes': fixed); None without any."""
        if not self.planes:
            return None
        S = self.distances(q_lag)
        pl, vi = np.nonzero((S < self.dhat) & (S > 0))
        if pl.size == 0:
            return None
        s = S[pl, vi]
        z, zh = s * s, self.dhat * self.dhat
        b1 = -2.0 * (z - zh) * np.log(z / zh) - (z - zh) ** 2 / z
        return PlaneLag(pl, vi, kappa * np.abs(b1 * 2.0 * s))

    def friction(self, q: np.ndarray, order: int, lag: PlaneLag | None,
                 lagged_V: np.ndarray, eps: float, mu_s: float, mu_k: float,
                 project: bool | str = True):
        """Lagged point-plane friction ``sum lambda F(|P (x - x_lag)|)`` (ipctk's mollifier
        with ``eps = eps_v dt``, ``mu_s``/``mu_k``: :mod:`.friction_profile`) of the pairs
        ``lag``, the slips measured from the collision vertices ``lagged_V``: energy,
        gradient or Hessian on collision DOFs (``project``: as
        :func:`~fem3d.physics.contact.friction_profile.point_plane_friction`'s)."""
        ns = self.n_surface
        if lag is None:
            return 0.0 if order == 0 else (np.zeros(3 * ns) if order == 1 else None)
        pl, vi, lam = lag
        P = np.asarray(q, dtype=np.float64).reshape(-1, 3)[self.surface]
        out = point_plane_friction(self.normals[pl], P[vi] - lagged_V[vi], lam, eps, mu_s,
                                   mu_k, order, project=project)
        if order == 1:
            g = np.zeros((ns, 3))
            np.add.at(g, vi, out)
            return g.reshape(-1)
        return out if order == 0 else self.blocks_matrix(vi, out)

    def step(self, P0: np.ndarray, P1: np.ndarray) -> float:
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

    def gaps(self, q: np.ndarray) -> np.ndarray:
        """Signed distance of every surface vertex to every plane, ``(n_planes, n_surface)``."""
        if not self.planes:
            return np.zeros((0, self.n_surface))
        return self.distances(q)

    def minimum_gap(self, V_surface: np.ndarray) -> float:
        """Smallest signed distance of the surface vertices ``V_surface`` to a plane (``inf``
        without planes)."""
        d = math.inf
        for p in self.planes:
            d = min(d, float(p.signed_distance(V_surface).min()))
        return d
