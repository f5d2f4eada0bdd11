"""The contact model: one object that composes the collision geometry, its collision sets
and CCD, the planes, the barrier and the lagged friction of a scene (the package's overview:
:mod:`fem3d.physics.contact`)."""

from __future__ import annotations

import math
import time
from collections.abc import Sequence

import ipctk
import numpy as np
import scipy.sparse as sp

from fem3d.errors import ParameterError, SimulationError
from fem3d.mesh.element import ELEMENTS, Element
from fem3d.physics.contact.barrier import Barrier
from fem3d.physics.contact.collisions import CollisionSets, ContactStats, choice
from fem3d.physics.contact.diagnostics import intersecting_pairs
from fem3d.physics.contact.friction import FRICTION_HESSIANS, LaggedFriction
from fem3d.physics.contact.geometry import CollisionGeometry, Entries
from fem3d.physics.contact.obstacles import MeshObstacle, PlaneObstacle
from fem3d.physics.contact.planes import PlanePairs

__all__ = ["ContactModel", "HESSIAN_PROJECTIONS"]

#: PSD projections of the per-pair Hessians by name: negative eigenvalues clamped at zero, or
#: mirrored to their absolute value (Chen et al. 2024: fewer Newton iterations on nonconvex
#: configurations).
#: ``"exact"``: no projection in Newton's own matrix (its shift ladder handles an indefinite
#: one) but clamped where Newton asks for a PSD matrix (:meth:`ContactModel.projects`).
HESSIAN_PROJECTIONS: dict[str, ipctk.PSDProjectionMethod] = {
    "clamp": ipctk.PSDProjectionMethod.CLAMP,
    "abs": ipctk.PSDProjectionMethod.ABS,
    "exact": ipctk.PSDProjectionMethod.CLAMP,
}


def _positive(key: str, value: float) -> float:
    value = float(value)
    if not (math.isfinite(value) and value > 0):
        raise ParameterError(f"contact.{key} must be a finite number > 0, got {value}")
    return value


def _coefficients(mu: float, mu_k: float | None) -> tuple[float, float]:
    """``(mu_s, mu_k)`` checked: finite, ``0 <= mu_k <= mu_s``."""
    mu = float(mu)
    if not (math.isfinite(mu) and mu >= 0):
        raise ParameterError(f"contact.mu must be a finite number >= 0, got {mu}")
    kinetic = mu if mu_k is None else float(mu_k)
    if not (math.isfinite(kinetic) and 0 <= kinetic <= mu):
        raise ParameterError(f"contact.mu_k must be in [0, mu_s = {mu}], got {mu_k}")
    return mu, kinetic


class ContactModel:
    """IPC barrier, lagged friction and CCD over one fem3d mesh and its obstacles.

    Parameters
    ----------
    X : (n, 3) float64
        Rest positions of the simulation mesh (every body, concatenated).
    T : (m, k) int64
        Elements of ``element`` (positively oriented), indexing ``X``.
    body_ids : (n,) int, optional
        Body of each vertex (default: all one body, 0).
    body_names : sequence of str, optional
        Names for messages (default ``"body 0"``, ...).
    planes, meshes : sequences of PlaneObstacle, MeshObstacle
    dhat : float
        Barrier activation distance (absolute, > 0).
    kappa : float, optional
        Barrier stiffness; None: IPC's adaptive stiffness (:meth:`initialize_stiffness`).
    mu : float, optional
        Static friction coefficient (>= 0; 0: frictionless).
    mu_k : float, optional
        Kinetic coefficient (``<= mu``; default ``mu``: one coefficient).
    eps_v : float, optional
        Friction smoothing velocity (absolute, > 0): slip below ``eps_v`` is static friction.
    self_contact : bool, optional
        Let a body touch itself.
    broad_phase : str, optional
        A key of :data:`~fem3d.physics.contact.collisions.BROAD_PHASES`.
    narrow_phase : str, optional
        A key of :data:`~fem3d.physics.contact.collisions.NARROW_PHASES` (CCD):
        ``"additive"`` (default; Li et al. 2021's conservative additive CCD, 0.9 of the time
        of impact) or ``"tight_inclusion"``.
    hessian_projection : str, optional
        A key of :data:`HESSIAN_PROJECTIONS`: how the per-pair barrier and friction Hessians
        are made PSD (``"clamp"``, default; ``"abs"``), or ``"exact"``: left as they are in
        the Newton matrix unless Newton asks for a PSD one (:meth:`projects`).
    friction_hessian : str, optional
        A key of :data:`~fem3d.physics.contact.friction.FRICTION_HESSIANS`: ``"exact"``
        (default; ipctk's, projected as the barrier's) or ``"majorizer"``
        (:mod:`fem3d.physics.contact.friction_majorizer`).
    element : Element, optional
        The finite element of ``T`` (default P1): it gives the collision surface
        (:meth:`fem3d.mesh.element.Element.surface_triangles`).
    triangles : (f, 3) int64, optional
        The collision surface's triangles when given (bodies of several elements:
        :meth:`fem3d.scene.arrays.SceneArrays.surface_triangles`); ``T`` and ``element`` are
        then not asked.
    Attributes
    ----------
    geometry : CollisionGeometry
        The collision mesh and its maps to fem3d's DOFs (``surface``, ``mesh``,
        ``bbox_diagonal``, ... are its, shared here).
    collisions : CollisionSets
        The step's candidates, collision sets and CCD.
    plane_pairs : PlanePairs
    barrier : Barrier
        The barrier potential and its (adaptive) stiffness.
    friction : LaggedFriction
    stats : ContactStats
    """

    def __init__(self, X: np.ndarray, T: np.ndarray, *, body_ids: np.ndarray | None = None,
                 body_names: Sequence[str] | None = None,
                 planes: Sequence[PlaneObstacle] = (), meshes: Sequence[MeshObstacle] = (),
                 dhat: float, kappa: float | None = None, mu: float = 0.0,
                 mu_k: float | None = None, eps_v: float = 1e-3, self_contact: bool = False,
                 broad_phase: str = "hash_grid", narrow_phase: str = "additive",
                 hessian_projection: str = "clamp", friction_hessian: str = "exact",
                 element: Element = ELEMENTS["p1"],
                 triangles: np.ndarray | None = None) -> None:
        dhat = _positive("dhat", dhat)
        mu, mu_k = _coefficients(mu, mu_k)
        eps_v = _positive("eps_v", eps_v)
        if kappa is not None and not (math.isfinite(kappa) and kappa > 0):
            raise ParameterError(f"contact.kappa must be a finite number > 0, got {kappa}")
        # ipctk's multithreaded assembly sums per-thread parts in a varying order: the same
        # step differs in the last bits from run to run, which breaks bit-exact resume
        ipctk.set_num_threads(1)
        self.dhat, self.eps_v = dhat, eps_v
        self.stats = ContactStats()
        g = self.geometry = CollisionGeometry(X, T, body_ids=body_ids, body_names=body_names,
                                              meshes=meshes, self_contact=self_contact,
                                              element=element, triangles=triangles)
        self.collisions = CollisionSets(g, dhat, broad_phase, narrow_phase, self.stats)
        psd = choice(HESSIAN_PROJECTIONS, hessian_projection, "contact.hessian_projection")
        self.hessian_projection = hessian_projection
        self.friction_hessian_kind = choice(FRICTION_HESSIANS, friction_hessian,
                                            "contact.friction_hessian")
        self.plane_pairs = PlanePairs(planes, g.surface, dhat)
        self.barrier = Barrier(self.collisions, self.plane_pairs, kappa, psd)
        self.friction = LaggedFriction(self.collisions, self.plane_pairs, mu=mu, mu_k=mu_k,
                                       eps_v=eps_v, hessian_kind=self.friction_hessian_kind,
                                       psd=psd, mirror=hessian_projection == "abs")
        # the geometry's, shared (read-only)
        self.planes, self.meshes = self.plane_pairs.planes, g.meshes
        self.n_vertices, self.surface, self.n_surface = g.n_vertices, g.surface, g.n_surface
        self.n_collision_vertices, self.faces, self.mesh = (g.n_collision_vertices, g.faces,
                                                            g.mesh)
        self.body_ids, self.body_names = g.body_ids, g.body_names
        self.self_contact, self.bbox_diagonal = g.self_contact, g.bbox_diagonal
        self.broad_phase_name = broad_phase

    # -- parameters that change ---------------------------------------------------------------
    @property
    def kappa(self) -> float:
        """The current barrier stiffness."""
        return self.barrier.kappa

    @property
    def max_kappa(self) -> float:
        """The ceiling of the adaptive stiffness' updates."""
        return self.barrier.max_kappa

    @property
    def adaptive(self) -> bool:
        """IPC's adaptive stiffness (no ``kappa`` given)."""
        return self.barrier.adaptive

    @property
    def mu(self) -> float:
        """Static friction coefficient (settable, unchecked, as ``mu_k``: the adjoint lags
        with one coefficient 1 and the other 0; takes effect at the next lagging)."""
        return self.friction.mu

    @mu.setter
    def mu(self, value: float) -> None:
        self.friction.mu = float(value)

    @property
    def mu_k(self) -> float:
        """Kinetic friction coefficient (settable, as ``mu``)."""
        return self.friction.mu_k

    @mu_k.setter
    def mu_k(self, value: float) -> None:
        self.friction.mu_k = float(value)

    def set_kappa(self, kappa: float) -> None:
        """Set the barrier stiffness (the cached collision set stays valid)."""
        self.barrier.set_kappa(kappa)

    def projects(self, psd: bool) -> bool:
        """Whether the contact Hessians of a Newton matrix are PSD-projected: always, except
        with ``hessian_projection="exact"`` where only a PSD matrix (``psd``) asks for it."""
        return psd or self.hessian_projection != "exact"

    # -- positions and the step's collision sets ----------------------------------------------
    def obstacle_positions(self, t: float) -> np.ndarray:
        """Positions of every mesh obstacle's vertices at time ``t``, ``(k, 3)``."""
        return self.geometry.obstacle_positions(t)

    def set_time(self, t: float) -> None:
        """Place the kinematic obstacles at time ``t`` (for the potentials and CCD)."""
        self.geometry.set_time(t)

    def collision_vertices(self, q: np.ndarray, obstacles: np.ndarray | None = None
                           ) -> np.ndarray:
        """Collision-mesh vertex positions ``(n_collision, 3)`` (Fortran order) of ``q``."""
        return self.geometry.collision_vertices(q, obstacles)

    def start_step(self, *configurations: np.ndarray, pad: float | None = None) -> None:
        """A new time step (:meth:`CollisionSets.start_step
        <fem3d.physics.contact.collisions.CollisionSets.start_step>`)."""
        self.collisions.start_step(*configurations, pad=pad)

    def n_active(self, q: np.ndarray) -> int:
        """Number of contact pairs closer than ``dhat`` at ``q``."""
        return self.collisions.n_active(q) + self.plane_pairs.n_active(q)

    # -- potentials ---------------------------------------------------------------------------
    def barrier_energy(self, q: np.ndarray) -> float:
        """``kappa * B(q)``; ``+inf`` when two primitives touch (distance 0)."""
        return self.barrier.energy(q)

    def barrier_gradient(self, q: np.ndarray) -> np.ndarray:
        """``kappa dB/dq``, ``(3n,)``."""
        return self.barrier.gradient(q)

    def barrier_hessian(self, q: np.ndarray, *, project: bool = True,
                        triplets: bool = False) -> sp.coo_matrix | Entries:
        """``kappa d2B/dq2`` (:meth:`Barrier.hessian
        <fem3d.physics.contact.barrier.Barrier.hessian>`)."""
        return self.barrier.hessian(q, project=project, triplets=triplets)

    def lag_friction(self, q_lag: np.ndarray, dt: float, t_start: float | None = None,
                     q_basis: np.ndarray | None = None) -> None:
        """Fix the friction's normal forces and tangent bases at ``q_basis`` (default
        ``q_lag``, the start of a step); the slip is measured from ``q_lag``.

        Parameters
        ----------
        q_lag : (3n,) or (n, 3) float64
            Lagged positions (the step's start ``q_t``).
        dt : float
            The step: slip displacement below ``eps_v * dt`` is static friction.
        t_start : float, optional
            Time of ``q_lag`` (kinematic obstacles' displacement over the step starts at their
            positions then; default: where they are now).
        q_basis : (3n,) or (n, 3) float64, optional
            Where the normal forces and tangent bases are taken (a re-lagging: the last
            Newton solution, obstacles where they are now).
        """
        self.friction.lag(q_lag, dt, self.barrier, t_start, q_basis)

    def friction_energy(self, q: np.ndarray) -> float:
        """Lagged friction potential ``D(q)`` (0 without friction or lagged contacts)."""
        return self.friction.energy(q)

    def friction_gradient(self, q: np.ndarray) -> np.ndarray:
        """``dD/dq``, ``(3n,)``."""
        return self.friction.gradient(q)

    def friction_hessian(self, q: np.ndarray, *, project: bool = True,
                         triplets: bool = False) -> sp.coo_matrix | Entries:
        """``d2D/dq2`` (:meth:`LaggedFriction.hessian
        <fem3d.physics.contact.friction.LaggedFriction.hessian>`)."""
        return self.friction.hessian(q, project=project, triplets=triplets)

    @property
    def n_friction_pairs(self) -> int:
        """Lagged friction pairs (0 when frictionless)."""
        return self.friction.n_pairs

    def energy(self, q: np.ndarray) -> float:
        """Barrier + friction."""
        e = self.barrier.energy(q)
        if not math.isfinite(e):
            return math.inf
        return e + self.friction.energy(q)

    def gradient(self, q: np.ndarray) -> np.ndarray:
        """Gradient of :meth:`energy`, ``(3n,)``."""
        return self.barrier.gradient(q) + self.friction.gradient(q)

    def hessian(self, q: np.ndarray, *, project: bool = True) -> sp.coo_matrix:
        """Hessian of :meth:`energy` (PSD-projected per pair), ``(3n, 3n)`` COO (duplicates
        summed on conversion)."""
        Hb = self.barrier.hessian(q, project=project)
        if not self.n_friction_pairs:
            return Hb
        Hf = self.friction.hessian(q, project=project)
        N = 3 * self.n_vertices
        return sp.coo_matrix((np.concatenate([Hb.data, Hf.data]),
                              (np.concatenate([Hb.row, Hf.row]),
                               np.concatenate([Hb.col, Hf.col]))), shape=(N, N))

    # -- barrier stiffness (IPC) --------------------------------------------------------------
    def initialize_stiffness(self, q: np.ndarray, grad_energy: np.ndarray,
                             average_mass: float) -> float:
        """IPC's initial ``kappa`` (:meth:`Barrier.initialize_stiffness
        <fem3d.physics.contact.barrier.Barrier.initialize_stiffness>`)."""
        return self.barrier.initialize_stiffness(q, grad_energy, average_mass)

    def update_stiffness(self, q: np.ndarray) -> float:
        """IPC's update: double ``kappa`` (up to :attr:`max_kappa`) when the minimum distance
        shrinks below ``1e-9`` of the scene's size. Returns the (possibly new) ``kappa``."""
        if not self.barrier.adaptive:
            return self.barrier.kappa
        return self.barrier.update_stiffness(self.minimum_distance(q))

    # -- CCD, distances, intersections --------------------------------------------------------
    def max_step(self, q0: np.ndarray, q1: np.ndarray) -> float:
        """Largest ``a`` in ``[0, 1]`` such that ``q0 + a (q1 - q0)`` is collision free.

        Linear trajectories, bodies against each other, themselves (self-contact) and the
        obstacles (at their current positions); the narrow phase of the model (additive CCD
        by default, conservative) on the step's candidates (:meth:`start_step`).
        """
        t0 = time.perf_counter()
        V0 = self.geometry.collision_vertices(q0)
        V1 = self.geometry.collision_vertices(q1)
        a = self.collisions.max_step(q0, V0, V1)
        a = min(a, self.plane_pairs.step(V0[: self.n_surface], V1[: self.n_surface]))
        self.stats.ccd_calls += 1
        self.stats.seconds_ccd += time.perf_counter() - t0
        return a

    def obstacle_step(self, q: np.ndarray, t0: float, t1: float) -> float:
        """CCD step of the kinematic obstacles moving from ``t0`` to ``t1`` with the bodies at
        ``q`` (1.0 without kinematic obstacles)."""
        return self.collisions.obstacle_step(q, t0, t1)

    def minimum_distance(self, q: np.ndarray) -> float:
        """Smallest distance between primitives that can touch (planes included); ``inf``
        when no pair is closer than ``dhat``."""
        V = self.geometry.collision_vertices(q)
        d = self.collisions.minimum_distance(q)
        return min(d, self.plane_pairs.minimum_gap(V[: self.n_surface]))

    def plane_gaps(self, q: np.ndarray) -> np.ndarray:
        """Signed distance of every surface vertex to every plane, ``(n_planes, n_surface)``."""
        return self.plane_pairs.gaps(q)

    def has_intersections(self, q: np.ndarray) -> bool:
        """Intersecting triangles (``ipctk.has_intersections``) or a vertex on or below a
        plane."""
        V = self.geometry.collision_vertices(q)
        if self.planes and (self.plane_gaps(q) <= 0).any():
            return True
        return self.collisions.has_intersections(V)

    def check_admissible(self, q: np.ndarray, *, step: int | None = None) -> None:
        """Raise :class:`SimulationError` naming the bodies when ``q`` intersects or touches.

        Raises
        ------
        SimulationError
            Intersecting bodies/obstacles, or primitives at distance 0 (infinite barrier).
        """
        if self.has_intersections(q):
            pairs = intersecting_pairs(self.geometry, self.planes, q)
            what = "; ".join(f"{a} and {b}" if a != b else f"{a} with itself"
                             for a, b in pairs) or "the collision surfaces"
            raise SimulationError(f"contact: {what} intersect (not intersection-free)",
                                  step=step)
        if not math.isfinite(self.barrier_energy(q)):
            raise SimulationError("contact: two surfaces touch (distance 0); separate them "
                                  "by more than 0", step=step)
