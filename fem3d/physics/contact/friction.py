"""IPC's lagged friction: what fem3d owns of the tangential contact.

``sum_k mu lambda_k f0(|T_k^T u_k|)`` with ``u = x - x_t`` the step's displacement,
``lambda_k`` the normal force and ``T_k`` the tangent basis of the contact pairs at the lagged
positions (the start of the step), and IPC's smoothing of Coulomb's law below the slip
displacement ``eps_v * dt`` (``ipctk.FrictionPotential`` for the mesh-mesh pairs,
:mod:`.planes` and :mod:`.friction_profile` for the point-plane pairs; ``mu_s``/``mu_k``).
Newton's matrix takes ipctk's per-pair PSD-projected Hessian, or the Hessian of a quadratic
majorizer (:mod:`.friction_majorizer`).
"""

from __future__ import annotations

import ipctk
import numpy as np
import scipy.sparse as sp

from fem3d.physics.contact.barrier import Barrier
from fem3d.physics.contact.collisions import CollisionPart, CollisionSets
from fem3d.physics.contact.friction_majorizer import FrictionMajorizer
from fem3d.physics.contact.geometry import Entries
from fem3d.physics.contact.planes import PlaneLag, PlanePairs

__all__ = ["FRICTION_HESSIANS", "LaggedFriction"]

#: The friction's part of Newton's matrix: ipctk's Hessian (projected as the barrier's), or the
#: Hessian of a quadratic majorizer (:mod:`fem3d.physics.contact.friction_majorizer`).
FRICTION_HESSIANS = {"exact": "exact", "majorizer": "majorizer"}


class LaggedFriction:
    """The lagged friction potential of a contact model and its lagged data.

    Parameters
    ----------
    collisions : CollisionSets
    planes : PlanePairs
    mu, mu_k : float
        Static and kinetic coefficients (``0 <= mu_k <= mu``; ``mu = 0``: frictionless).
    eps_v : float
        Friction smoothing velocity (absolute, > 0).
    hessian_kind : str
        A key of :data:`FRICTION_HESSIANS`.
    psd : ipctk.PSDProjectionMethod
        How a projected per-pair Hessian is made PSD.
    mirror : bool
        The projection mirrors negative eigenvalues (``hessian_projection = "abs"``): the
        planes' blocks do the same.

    Attributes
    ----------
    potential : ipctk.FrictionPotential
        Of the last lagging (its ``eps_v`` is ``eps_v * dt``).
    """

    def __init__(self, collisions: CollisionSets, planes: PlanePairs, *, mu: float,
                 mu_k: float, eps_v: float, hessian_kind: str,
                 psd: ipctk.PSDProjectionMethod, mirror: bool) -> None:
        self.collisions = collisions
        self.geometry = collisions.geometry
        self.planes = planes
        self.mu, self.mu_k, self.eps_v = mu, mu_k, eps_v
        self.hessian_kind = hessian_kind
        self.psd, self.mirror = psd, mirror
        self.potential = ipctk.FrictionPotential(eps_v)
        self.dt = 1.0
        self.lagged_V: np.ndarray | None = None
        self.plane_lag: PlaneLag | None = None

    def lag(self, q_lag: np.ndarray, dt: float, barrier: Barrier, t_start: float | None = None,
            q_basis: np.ndarray | None = None) -> None:
        """Fix the normal forces (of ``barrier``) and tangent bases at ``q_basis`` (default
        ``q_lag``); the slip is measured from ``q_lag`` (:meth:`ContactModel.lag_friction
        <fem3d.physics.contact.model.ContactModel.lag_friction>`)."""
        g = self.geometry
        self.dt = float(dt)
        self.potential = ipctk.FrictionPotential(self.eps_v * self.dt)
        obs_t = g.obstacles_at if t_start is None else g.obstacle_positions(t_start)
        V = g.collision_vertices(q_lag, np.asarray(obs_t, dtype=np.float64))
        self.lagged_V = V
        if q_basis is not None:
            q_lag, V = q_basis, g.collision_vertices(q_basis)
        self.plane_lag = None if self.mu == 0.0 else self.planes.lag(q_lag, barrier.kappa)
        for part in self.collisions.parts:
            part.tangential = part.majorizer = None
            if self.mu == 0.0:
                continue
            Vp = part.view(V)
            col = self.collisions.build(part, Vp)
            if len(col):
                tc = ipctk.TangentialCollisions()
                if self.mu_k == self.mu:
                    tc.build(part.mesh, Vp, col, barrier.potential, self.mu)
                else:  # ipctk's own static-to-kinetic blend (.friction_profile)
                    tc.build(part.mesh, Vp, col, barrier.potential, self.mu, self.mu_k)
                part.tangential = tc if len(tc) else None

    def slips(self, q: np.ndarray) -> list[tuple[CollisionPart, np.ndarray]]:
        """``(part, slip displacement of its vertices)`` for the parts with friction pairs."""
        parts = [p for p in self.collisions.parts if p.tangential is not None]
        if not parts or self.lagged_V is None:
            return []
        U = np.asfortranarray(self.geometry.collision_vertices(q) - self.lagged_V)
        return [(p, p.view(U)) for p in parts]

    def _planes(self, q: np.ndarray, order: int, project: bool | str = True):
        return self.planes.friction(q, order, self.plane_lag, self.lagged_V,
                                    self.eps_v * self.dt, self.mu, self.mu_k, project)

    def energy(self, q: np.ndarray) -> float:
        """Lagged friction potential ``D(q)`` (0 without friction or lagged contacts)."""
        e = sum(float(self.potential(p.tangential, p.mesh, U)) for p, U in self.slips(q))
        return e + self._planes(q, 0)

    def gradient(self, q: np.ndarray) -> np.ndarray:
        """``dD/dq``, ``(3n,)``."""
        g = self.geometry
        out = np.zeros(3 * g.n_vertices)
        for p, U in self.slips(q):
            g.to_full_vector(self.potential.gradient(p.tangential, p.mesh, U), out)
        if self.plane_lag is not None:
            g.to_full_vector(self._planes(q, 1), out)
        return out

    def hessian(self, q: np.ndarray, *, project: bool = True,
                triplets: bool = False) -> sp.coo_matrix | Entries:
        """``d2D/dq2`` (PSD-projected per pair when ``project``; the majorizer's is PSD as it
        is), ``(3n, 3n)`` COO (``triplets``: :class:`Entries`)."""
        how = self.psd if project else ipctk.PSDProjectionMethod.NONE
        if self.hessian_kind == "majorizer":
            Hs = [self.majorizer(p).hessian(U) for p, U in self.slips(q)]
        else:
            Hs = [self.potential.hessian(p.tangential, p.mesh, U, how)
                  for p, U in self.slips(q)]
        if self.plane_lag is not None:
            Hs.append(self._planes(q, 2, "abs" if project and self.mirror else project))
        return self.geometry.to_full_matrix(Hs, triplets)

    def majorizer(self, part: CollisionPart) -> FrictionMajorizer:
        """The majorizer of ``part``'s lagged pairs (read once per lagging)."""
        if part.majorizer is None:
            part.majorizer = FrictionMajorizer(part.tangential, part.mesh, self.potential.eps_v)
        return part.majorizer

    @property
    def n_pairs(self) -> int:
        """Lagged friction pairs (0 when frictionless)."""
        n = sum(len(p.tangential) for p in self.collisions.parts if p.tangential is not None)
        return n + (0 if self.plane_lag is None else int(self.plane_lag.planes.size))
