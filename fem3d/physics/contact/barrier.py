"""IPC's barrier potential and its adaptive stiffness: what fem3d owns of the normal contact.

``kappa * sum_k b(d_k^2, dhat^2)`` over the mesh-mesh pairs closer than ``dhat``
(``ipctk.BarrierPotential``, ``b`` the log barrier on squared distances) and the point-plane
pairs (:mod:`.planes`, the same ``b``), in positions ``q`` (fem3d's ``(3n,)`` vertex-major DOF
order); Hessians PSD-projected per pair by ``ipctk``.

Barrier stiffness: ``kappa=None`` is IPC's adaptive stiffness. ``ipctk.initial_barrier_stiffness``
balances the barrier's gradient against the rest of the objective's
(:meth:`Barrier.initialize_stiffness`), and ``ipctk.update_barrier_stiffness`` doubles it (up
to its maximum) when the minimum distance keeps shrinking below ``1e-9`` of the scene's size
(:meth:`Barrier.update_stiffness`), as in Li et al. 2020.
"""

from __future__ import annotations

import math
import time

import ipctk
import numpy as np
import scipy.sparse as sp

from fem3d.physics.contact.collisions import CollisionSets
from fem3d.physics.contact.geometry import Entries
from fem3d.physics.contact.planes import PlanePairs

__all__ = ["Barrier"]


class Barrier:
    """The barrier potential of a contact model and the state of its stiffness.

    Parameters
    ----------
    collisions : CollisionSets
        The mesh-mesh pairs (and the geometry mapping them to fem3d's DOFs).
    planes : PlanePairs
    kappa : float or None
        Barrier stiffness; None: adaptive (starting at 1 until :meth:`initialize_stiffness`).
    psd : ipctk.PSDProjectionMethod
        How a projected per-pair Hessian is made PSD.

    Attributes
    ----------
    kappa, max_kappa : float
        Current stiffness and the ceiling of its adaptive updates.
    adaptive : bool
    initialized : bool
        Whether the adaptive stiffness has been set (always True for a given ``kappa``).
    prev_min_distance : float or None
        The minimum distance at the last update (None: none yet).
    """

    def __init__(self, collisions: CollisionSets, planes: PlanePairs, kappa: float | None,
                 psd: ipctk.PSDProjectionMethod) -> None:
        self.collisions = collisions
        self.geometry = collisions.geometry
        self.planes = planes
        self.dhat = collisions.dhat
        self.stats = collisions.stats
        self.psd = psd
        self.kappa = float(kappa) if kappa is not None else 1.0
        self.adaptive = kappa is None
        self.max_kappa = math.inf if kappa is not None else self.kappa
        self.initialized = kappa is not None
        self.prev_min_distance: float | None = None
        self.potential = ipctk.BarrierPotential(self.dhat, self.kappa)

    def set_kappa(self, kappa: float) -> None:
        """Set the barrier stiffness (the cached collision sets stay valid)."""
        self.kappa = float(kappa)
        self.potential = ipctk.BarrierPotential(self.dhat, self.kappa)

    def energy(self, q: np.ndarray) -> float:
        """``kappa * B(q)``; ``+inf`` when two primitives touch (distance 0)."""
        active = self.collisions.active_sets(q)
        t0 = time.perf_counter()
        e = sum(float(self.potential(p.collisions, p.mesh, V)) for p, V in active)
        e += self.planes.barrier(q, 0, self.kappa)
        self.stats.seconds_derivatives += time.perf_counter() - t0
        return e if math.isfinite(e) else math.inf

    def gradient(self, q: np.ndarray) -> np.ndarray:
        """``kappa dB/dq``, ``(3n,)``."""
        active = self.collisions.active_sets(q)
        t0 = time.perf_counter()
        g = self.geometry
        out = np.zeros(3 * g.n_vertices)
        for p, V in active:
            g.to_full_vector(self.potential.gradient(p.collisions, p.mesh, V), out)
        if self.planes.planes:
            g.to_full_vector(self.planes.barrier(q, 1, self.kappa), out)
        self.stats.seconds_derivatives += time.perf_counter() - t0
        return out

    def hessian(self, q: np.ndarray, *, project: bool = True,
                triplets: bool = False) -> sp.coo_matrix | Entries:
        """``kappa d2B/dq2`` (per-pair PSD-projected when ``project``), ``(3n, 3n)`` COO
        (``triplets``: its ``row, col, data`` arrays alone, :class:`Entries`)."""
        active = self.collisions.active_sets(q)
        t0 = time.perf_counter()
        how = self.psd if project else ipctk.PSDProjectionMethod.NONE
        Hs = [self.potential.hessian(p.collisions, p.mesh, V, how) for p, V in active]
        if self.planes.planes:
            Hs.append(self.planes.barrier(q, 2, self.kappa, project=project))
        self.stats.seconds_derivatives += time.perf_counter() - t0
        return self.geometry.to_full_matrix(Hs, triplets)

    def initialize_stiffness(self, q: np.ndarray, grad_energy: np.ndarray,
                             average_mass: float) -> float:
        """IPC's initial ``kappa`` (and its ceiling) from the gradients at ``q``.

        Parameters
        ----------
        q : (3n,) float64
        grad_energy : (3n,) float64
            Gradient of the rest of the objective with respect to the positions.
        average_mass : float
            Mean vertex mass.

        Returns
        -------
        float
            The new ``kappa`` (unchanged when it was given explicitly).
        """
        if not self.adaptive:
            return self.kappa
        g = self.geometry
        unit = ipctk.BarrierPotential(self.dhat, 1.0)
        gb = np.zeros(3 * g.n_vertices)
        for part, Vp in self.collisions.active_sets(q):
            g.to_full_vector(unit.gradient(part.collisions, part.mesh, Vp), gb)
        if self.planes.planes:
            g.to_full_vector(self.planes.barrier(q, 1, 1.0), gb)
        kappa, kmax = ipctk.initial_barrier_stiffness(
            g.bbox_diagonal, unit.barrier, self.dhat, float(average_mass),
            np.asarray(grad_energy, dtype=np.float64), gb)
        self.max_kappa = float(kmax)
        self.set_kappa(float(kappa))
        self.initialized = True
        self.prev_min_distance = None
        return self.kappa

    def update_stiffness(self, d: float) -> float:
        """IPC's update at the minimum distance ``d`` (the pairs' and the planes'): double
        ``kappa`` (up to :attr:`max_kappa`) when it shrinks below ``1e-9`` of the scene's
        size. Returns the (possibly new) ``kappa``."""
        if not self.adaptive:
            return self.kappa
        if not math.isfinite(d):
            self.prev_min_distance = d
            return self.kappa
        prev = self.prev_min_distance if self.prev_min_distance is not None else d
        prev = prev if math.isfinite(prev) else d
        # ipctk takes squared distances (its barrier is on d^2)
        new = float(ipctk.update_barrier_stiffness(prev * prev, d * d, self.max_kappa,
                                                   self.kappa, self.geometry.bbox_diagonal))
        self.prev_min_distance = d
        if new != self.kappa:
            self.set_kappa(new)
        return self.kappa

    def state_array(self) -> np.ndarray:
        """The adaptive stiffness as ``(4,) float64``: ``kappa, max_kappa, initialized,
        prev_min_distance`` (nan: none)."""
        prev = np.nan if self.prev_min_distance is None else self.prev_min_distance
        return np.array([self.kappa, self.max_kappa, float(self.initialized), prev],
                        dtype=np.float64)

    def load_state_array(self, a: np.ndarray) -> None:
        """Back to a :meth:`state_array`."""
        self.set_kappa(float(a[0]))
        self.max_kappa = float(a[1])
        self.initialized = bool(a[2])
        self.prev_min_distance = None if np.isnan(a[3]) else float(a[3])
