"""Incremental Potential Contact (IPC) for fem3d, on the IPC Toolkit (``ipctk``).

The geometry — distances, the barrier and its derivatives, lagged friction, broad phase and
continuous collision detection (CCD) — comes from ``ipctk``; this module owns how it maps onto
fem3d's degrees of freedom and how it enters backward Euler's objective.

Collision mesh
    The boundary surface of the simulation mesh (:func:`fem3d.mesh.tetmesh.boundary_faces`; interior
    vertices are not in it), followed by the vertices and triangles of the triangle-mesh
    obstacles (static, or kinematic: their positions are a function of time), in one
    ``ipctk.CollisionMesh``; plane obstacles are ``ipctk`` planes (point + normal). Collision
    vertex ``i < n_surface`` is fem3d vertex :attr:`ContactModel.surface` ``[i]``; the
    obstacles' vertices are not degrees of freedom.

Which pairs can touch
    Different bodies always; a body with itself only with ``self_contact=True``; obstacles
    never with each other (an ``ipctk.CollisionFilter`` over vertex groups, evaluated in C++).

Potentials, in positions ``q`` (fem3d's ``(3n,)`` vertex-major DOF order)
    * barrier ``kappa * sum_k b(d_k^2, dhat^2)`` over the pairs closer than ``dhat``
      (``ipctk.BarrierPotential``; ``b`` the log barrier on squared distances);
    * lagged friction ``sum_k mu lambda_k f0(|T_k^T u_k|)`` with ``u = x - x_t`` the step's
      displacement, ``lambda_k`` the normal force and ``T_k`` the tangent basis of the contact
      pairs at the lagged positions (the start of the step), and IPC's smoothing of Coulomb's
      law below the slip displacement ``eps_v * dt`` (``ipctk.FrictionPotential``);
    * Hessians PSD-projected per pair by ``ipctk``: negative eigenvalues clamped at zero
      (``hessian_projection="clamp"``, the default) or mirrored to their absolute value
      (``"abs"``, Chen et al. 2024, "Trust-Region Eigenvalue Filtering for Projected Newton").

Determinism
    ``ipctk`` runs single-threaded (``ipctk.set_num_threads(1)`` when a model is built): its
    threaded assembly adds per-thread partial sums in a varying order, so two runs of the same
    step would differ in the last bits and a resumed run would not repeat the uninterrupted one.

Candidates
    Mesh-mesh pairs come from one ``ipctk.Candidates`` set per time step
    (:meth:`ContactModel.start_step`, :class:`fem3d.physics.contact.candidates.StepCandidates`):
    built from the step's swept volume, grown only when a query leaves it, shared by the
    collision sets of every iterate and line-search trial, CCD and friction's lagging.

Barrier stiffness
    ``kappa=None``: ``ipctk.initial_barrier_stiffness`` balances the barrier's gradient against
    the rest of the objective's (:meth:`ContactModel.initialize_stiffness`), and
    ``ipctk.update_barrier_stiffness`` doubles it (up to its maximum) when the minimum distance
    keeps shrinking below ``1e-9`` of the scene's size (:meth:`ContactModel.update_stiffness`),
    as in Li et al. 2020.

Planes are point-plane pairs evaluated here in NumPy with ipctk's own formulas (the same
barrier ``b(s^2, dhat^2)`` of the signed distance ``s``, the same normal force, tangent
projection and friction mollifier; the tests compare the two), for two reasons measured on
ipctk 1.6.1: its plane-vertex candidates inflate only the vertex's box, so the one-call
``NormalCollisions.build(mesh, V, dhat)`` activates a plane only within ``dhat / 2`` (the
energy would jump there), and its plane CCD and candidates go through a broad phase over the
surface vertices that cost more than the rest of a bunny step.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import ipctk
import numpy as np
import scipy.sparse as sp

from fem3d.errors import ParameterError, SimulationError
from fem3d.mesh.tetmesh import boundary_faces
from fem3d.physics.contact.candidates import StepCandidates
from fem3d.physics.contact.diagnostics import group_chain, intersecting_pairs
from fem3d.physics.contact.far_travel import FarTravelCCD
from fem3d.physics.contact.friction_majorizer import FrictionMajorizer
from fem3d.physics.contact.planes import Entries, PlanePairs

#: Padding of the step's candidate boxes, in ``dhat``, when a step starts (the collision
#: sets need ``dhat / 2``). Every query pays for every candidate: on the pile 2 ``dhat``
#: made 1e5 where an iterate's swept boxes hold 5e3 (docs/contact.md, "Stop 31").
STEP_PAD = 0.75
#: ... and once an iterate has left them (moving more than predicted, as a tumbling stack):
#: 0.75 there re-ran the stack's broad phase 1.7x as often.
GROWTH_PAD = 2.0

__all__ = [
    "PlaneObstacle",
    "MeshObstacle",
    "ContactModel",
    "BROAD_PHASES",
    "NARROW_PHASES",
    "HESSIAN_PROJECTIONS",
]

#: Broad phases by name (``ipctk`` classes).
BROAD_PHASES: dict[str, Callable[[], object]] = {
    "hash_grid": ipctk.HashGrid,
    "sweep_and_prune": ipctk.SweepAndPrune,
    "lbvh": ipctk.LBVH,
    "brute_force": ipctk.BruteForce,
}

#: Narrow-phase CCD by name. Tight Inclusion's default iteration cap (1e7) costs seconds on
#: the parallel faces of axis-aligned meshes; capped, it returns its conservative lower bound.
NARROW_PHASES: dict[str, Callable[[], object]] = {
    "additive": ipctk.AdditiveCCD,
    "tight_inclusion": lambda: ipctk.TightInclusionCCD(1e-6, 10_000),
}

#: Additive CCD (ipctk 1.6.1) can miss a crossing that starts closer than this fraction of the
#: scene's diagonal (IPC's adaptive stiffness acts below 1e-9 too). The pile's step 184: an
#: edge-edge pair 2.5e-11 m apart crosses at 0.67 of a step; ipctk's 1e7 conservative
#: advancements (of about 2e-7 of the step each) pass the crossing in round-off and call the
#: step free (bench/results/accd_miss_pile_step184.npz). From such a start the step is checked
#: again with at most :data:`CCD_GUARD_ITERATIONS` advancements: additive CCD that runs out of
#: them reports a collision where it stands (here at 0.11), before the round-off.
CCD_GUARD_DISTANCE = 1e-9
CCD_GUARD_ITERATIONS = 100_000

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
#: The friction's part of Newton's matrix: ipctk's Hessian (projected as the barrier's), or the
#: Hessian of a quadratic majorizer (:mod:`fem3d.physics.contact.friction_majorizer`).
FRICTION_HESSIANS = {"exact": "exact", "majorizer": "majorizer"}


def _narrow_phases(name: str) -> tuple[object, object | None]:
    """The CCD ``name`` and its guard for nearly touching starts (:data:`CCD_GUARD_DISTANCE`;
    None: the CCD needs none)."""
    ccd = _choice(NARROW_PHASES, name, "contact CCD")()
    return ccd, (ipctk.AdditiveCCD(CCD_GUARD_ITERATIONS) if name == "additive" else None)


def _choice(table: dict, name: str, what: str):
    """``table[name]``; a :class:`ParameterError` naming ``what`` and the choices if absent."""
    if name not in table:
        raise ParameterError(f"{what} must be one of {sorted(table)}, got {name!r}")
    return table[name]


@dataclass(frozen=True, eq=False)
class PlaneObstacle:
    """A static plane; the half-space ``(x - point) . normal < 0`` is solid.

    Attributes
    ----------
    point : (3,) float64
    normal : (3,) float64
        Unit normal (normalised on construction), pointing to the free side.
    name : str
    """

    point: np.ndarray
    normal: np.ndarray
    name: str = "plane"

    def __post_init__(self) -> None:
        p = np.asarray(self.point, dtype=np.float64).reshape(-1)
        n = np.asarray(self.normal, dtype=np.float64).reshape(-1)
        if p.shape != (3,) or n.shape != (3,) or not (np.isfinite(p).all() and
                                                       np.isfinite(n).all()):
            raise ParameterError(f"obstacle {self.name!r}: point and normal must be 3 finite "
                                 "numbers")
        norm = float(np.linalg.norm(n))
        if norm == 0.0:
            raise ParameterError(f"obstacle {self.name!r}: the normal is zero")
        object.__setattr__(self, "point", p)
        object.__setattr__(self, "normal", n / norm)

    def signed_distance(self, x: np.ndarray) -> np.ndarray:
        """``(x - point) . normal`` of points ``x (k, 3)``."""
        return (np.asarray(x).reshape(-1, 3) - self.point) @ self.normal


@dataclass(frozen=True, eq=False)
class MeshObstacle:
    """A triangle-mesh obstacle, static or kinematic (a prescribed motion).

    Attributes
    ----------
    vertices : (k, 3) float64
        Rest positions (the motion's reference).
    faces : (f, 3) int64
    motion : callable ``(rest (k, 3), t) -> (k, 3)``, optional
        Positions at time ``t`` (for example ``fem3d.physics.motion.Keyframes.apply``); None:
        static.
    name : str
    """

    vertices: np.ndarray
    faces: np.ndarray
    motion: Callable[[np.ndarray, float], np.ndarray] | None = None
    name: str = "obstacle"

    def __post_init__(self) -> None:
        V = np.ascontiguousarray(self.vertices, dtype=np.float64)
        F = np.ascontiguousarray(self.faces, dtype=np.int64)
        if V.ndim != 2 or V.shape[1] != 3 or not np.isfinite(V).all():
            raise ParameterError(f"obstacle {self.name!r}: vertices must be finite (k, 3)")
        if F.ndim != 2 or F.shape[1] != 3 or F.size == 0:
            raise ParameterError(f"obstacle {self.name!r}: faces must be (f, 3), f >= 1")
        if F.min() < 0 or F.max() >= V.shape[0]:
            raise ParameterError(f"obstacle {self.name!r}: a face index is out of range "
                                 f"[0, {V.shape[0]})")
        object.__setattr__(self, "vertices", V)
        object.__setattr__(self, "faces", F)

    def positions(self, t: float) -> np.ndarray:
        """Vertex positions at time ``t``, ``(k, 3)``."""
        if self.motion is None:
            return self.vertices
        x = np.asarray(self.motion(self.vertices, t), dtype=np.float64)
        if x.shape != self.vertices.shape:
            raise ValueError(f"obstacle {self.name!r}: motion returned shape {x.shape}")
        return x


@dataclass
class ContactStats:
    """Counters of the contact work (for benchmarks and step statistics).

    Attributes
    ----------
    builds : int
        Collision-set builds (narrow phase on the step's candidates).
    broad_phases : int
        Candidate-set builds (:class:`~fem3d.physics.contact.candidates.StepCandidates`).
    ccd_calls : int
    far_ccd_calls : int
        CCD calls that carried the bodies far (:mod:`fem3d.physics.contact.far_travel`).
    seconds_build, seconds_ccd, seconds_derivatives : float
        Wall time in collision-set builds (broad phases included), CCD, and barrier/friction
        evaluation.
    """

    builds: int = 0
    broad_phases: int = 0
    ccd_calls: int = 0
    far_ccd_calls: int = 0
    seconds_build: float = 0.0
    seconds_ccd: float = 0.0
    seconds_derivatives: float = 0.0

    def reset(self) -> None:
        """Zero every counter."""
        self.__init__()


class _Part:
    """One collision mesh with its collision sets: the step's candidates, the normal set
    cached for the last configuration, the lagged tangential set for friction."""

    def __init__(self, mesh: ipctk.CollisionMesh, n_vertices: int, broad_phase,
                 pad: float, reach: float) -> None:
        self.mesh = mesh
        self.n = n_vertices
        self.key: bytes | None = None
        self.collisions = ipctk.NormalCollisions()
        self.tangential: ipctk.TangentialCollisions | None = None
        self.majorizer: FrictionMajorizer | None = None  # of ``tangential``, when asked
        # grown boxes padded by GROWTH_PAD dhat, no wider than a far query's reach
        self.step = StepCandidates(mesh, broad_phase, pad, max_extent=reach)

    def view(self, V: np.ndarray) -> np.ndarray:
        """This part's rows of the full collision-vertex array (Fortran order)."""
        return V if V.shape[0] == self.n else np.asfortranarray(V[: self.n])


class ContactModel(PlanePairs):
    """IPC barrier, lagged friction and CCD over one fem3d mesh and its obstacles.

    Parameters
    ----------
    X : (n, 3) float64
        Rest positions of the simulation mesh (every body, concatenated).
    T : (m, 4) int64
        Tets (positively oriented), indexing ``X``.
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
        A key of :data:`BROAD_PHASES`.
    narrow_phase : str, optional
        A key of :data:`NARROW_PHASES` (CCD): ``"additive"`` (default; Li et al. 2021's
        conservative additive CCD, 0.9 of the time of impact) or ``"tight_inclusion"``.
    hessian_projection : str, optional
        A key of :data:`HESSIAN_PROJECTIONS`: how the per-pair barrier and friction Hessians
        are made PSD (``"clamp"``, default; ``"abs"``), or ``"exact"``: left as they are in
        the Newton matrix unless Newton asks for a PSD one (:meth:`projects`).
    friction_hessian : str, optional
        A key of :data:`FRICTION_HESSIANS`: ``"exact"`` (default; ipctk's, projected as the
        barrier's) or ``"majorizer"`` (:mod:`fem3d.physics.contact.friction_majorizer`).

    Attributes
    ----------
    surface : (n_surface,) int64
        fem3d vertex of each dynamic collision vertex.
    mesh : ipctk.CollisionMesh
    bbox_diagonal : float
        Diagonal of the scene's bounding box (bodies and mesh obstacles at rest).
    kappa, max_kappa : float
        Current barrier stiffness and the ceiling of its adaptive updates.
    stats : ContactStats
    """

    def __init__(
        self,
        X: np.ndarray,
        T: np.ndarray,
        *,
        body_ids: np.ndarray | None = None,
        body_names: Sequence[str] | None = None,
        planes: Sequence[PlaneObstacle] = (),
        meshes: Sequence[MeshObstacle] = (),
        dhat: float,
        kappa: float | None = None,
        mu: float = 0.0,
        mu_k: float | None = None,
        eps_v: float = 1e-3,
        self_contact: bool = False,
        broad_phase: str = "hash_grid",
        narrow_phase: str = "additive",
        hessian_projection: str = "clamp",
        friction_hessian: str = "exact",
    ) -> None:
        X = np.ascontiguousarray(X, dtype=np.float64)
        T = np.ascontiguousarray(T, dtype=np.int64)
        n = X.shape[0]
        self.n_vertices = n
        dhat = float(dhat)
        if not (math.isfinite(dhat) and dhat > 0):
            raise ParameterError(f"contact.dhat must be a finite number > 0, got {dhat}")
        mu = float(mu)
        if not (math.isfinite(mu) and mu >= 0):
            raise ParameterError(f"contact.mu must be a finite number >= 0, got {mu}")
        self.mu_k = mu if mu_k is None else float(mu_k)
        if not (math.isfinite(self.mu_k) and 0 <= self.mu_k <= mu):
            raise ParameterError(f"contact.mu_k must be in [0, mu_s = {mu}], got {mu_k}")
        eps_v = float(eps_v)
        if not (math.isfinite(eps_v) and eps_v > 0):
            raise ParameterError(f"contact.eps_v must be a finite number > 0, got {eps_v}")
        if kappa is not None and not (math.isfinite(kappa) and kappa > 0):
            raise ParameterError(f"contact.kappa must be a finite number > 0, got {kappa}")
        if broad_phase not in BROAD_PHASES:
            raise ParameterError(f"contact broad phase must be one of {sorted(BROAD_PHASES)}, "
                                 f"got {broad_phase!r}")
        self.dhat, self.mu, self.eps_v, self.self_contact = dhat, mu, eps_v, bool(self_contact)
        # ipctk's multithreaded assembly sums per-thread parts in a varying order: the same
        # step differs in the last bits from run to run, which breaks bit-exact resume
        ipctk.set_num_threads(1)
        self._ccd, self._ccd_guard = _narrow_phases(narrow_phase)
        self._psd = _choice(HESSIAN_PROJECTIONS, hessian_projection, "contact.hessian_projection")
        self.hessian_projection = hessian_projection
        self.friction_hessian_kind = _choice(FRICTION_HESSIANS, friction_hessian, "contact."
                                             "friction_hessian")
        self.broad_phase_name = broad_phase
        self._broad_phase = BROAD_PHASES[broad_phase]()
        self.planes, self.meshes = tuple(planes), tuple(meshes)

        if body_ids is None:
            body_ids = np.zeros(n, dtype=np.int64)
        body_ids = np.asarray(body_ids, dtype=np.int64).reshape(-1)
        if body_ids.shape != (n,):
            raise ValueError(f"body_ids must be ({n},), got {body_ids.shape}")
        self.body_ids = body_ids
        self.body_names = (list(body_names) if body_names is not None else
                           [f"body {i}" for i in range(int(body_ids.max()) + 1 if n else 0)])

        # dynamic part: the boundary surface, renumbered
        F = boundary_faces(T)
        self.surface = surface = np.unique(F)
        renum = np.full(n, -1, dtype=np.int64)
        renum[surface] = np.arange(surface.size)
        faces = [renum[F]]
        verts = [X[surface]]
        groups = [body_ids[surface]]
        # kinematic / static meshes
        offset = surface.size
        self._mesh_offsets = []
        for m in self.meshes:
            faces.append(m.faces + offset)
            verts.append(m.vertices)
            groups.append(np.full(m.vertices.shape[0], -1, dtype=np.int64))
            self._mesh_offsets.append(offset)
            offset += m.vertices.shape[0]
        self.n_surface = surface.size
        self.n_collision_vertices = offset
        self.faces = Fc = np.ascontiguousarray(np.concatenate(faces), dtype=np.int32)
        self._rest = V0 = np.asfortranarray(np.concatenate(verts))
        E = ipctk.edges(Fc)
        self._groups = np.concatenate(groups)
        #: Every surface and mesh obstacle (no planes): intersection checks and messages.
        self.mesh = ipctk.CollisionMesh(V0, E, Fc)
        self.mesh.can_collide = self._filter(self._groups)
        # triangle meshes against each other through ipctk, only when two groups can touch
        # at all (a lone body without self-contact skips the mesh broad phase); the planes
        # are point-plane pairs evaluated here, vectorized (see the module's note)
        self._far = FarTravelCCD(X[surface], bool(self.meshes), self._broad_phase, self._ccd)
        self._parts: list[_Part] = []
        if self.self_contact or np.unique(self._groups).size > 1:
            self._parts.append(_Part(self.mesh, offset, self._broad_phase,
                                     GROWTH_PAD * dhat, self._far.reach))
        self._plane_n = np.array([p.normal for p in self.planes]).reshape(-1, 3)
        self._plane_o = np.array([p.point @ p.normal for p in self.planes]).reshape(-1)
        self._plane_lag: tuple[np.ndarray, ...] | None = None
        pts = np.concatenate([X] + [m.vertices for m in self.meshes])
        self.bbox_diagonal = float(np.linalg.norm(np.ptp(pts, axis=0))) if pts.size else 1.0
        # fem3d DOF of each collision DOF (-1: obstacle)
        dof = np.full((offset, 3), -1, dtype=np.int64)
        dof[: surface.size] = 3 * surface[:, None] + np.arange(3)
        self._dof = dof.reshape(-1)
        self._n_dyn_dofs = 3 * surface.size

        self.kappa = float(kappa) if kappa is not None else 1.0
        self.adaptive = kappa is None
        self.max_kappa = math.inf if kappa is not None else self.kappa
        self._stiffness_initialized = kappa is not None
        self._prev_min_distance: float | None = None
        self._barrier = ipctk.BarrierPotential(dhat, self.kappa)
        self._friction = ipctk.FrictionPotential(eps_v)
        self._obstacles_at = self._rest[surface.size:].copy()
        self._obstacles_t: np.ndarray = self._obstacles_at
        self._lagged_V: np.ndarray | None = None
        self._dt = 1.0
        self.stats = ContactStats()

    # -- set-up -------------------------------------------------------------------------------
    def _filter(self, groups: np.ndarray) -> ipctk.CollisionFilter:
        """Vertices of one group cannot touch: a group is one body (unless self-contact) or
        all the obstacles together."""
        if self.self_contact:
            return ipctk.make_static_obstacle_filter(self.n_surface)
        # ipctk's connected-components filter over synthetic faces chaining each group
        chain = group_chain(groups)
        return ipctk.make_connected_components_filter(chain)

    def set_kappa(self, kappa: float) -> None:
        """Set the barrier stiffness (the cached collision set stays valid)."""
        self.kappa = float(kappa)
        self._barrier = ipctk.BarrierPotential(self.dhat, self.kappa)

    def projects(self, psd: bool) -> bool:
        """Whether the contact Hessians of a Newton matrix are PSD-projected: always, except
        with ``hessian_projection="exact"`` where only a PSD matrix (``psd``) asks for it."""
        return psd or self.hessian_projection != "exact"

    # -- positions ----------------------------------------------------------------------------
    def obstacle_positions(self, t: float) -> np.ndarray:
        """Positions of every mesh obstacle's vertices at time ``t``, ``(k, 3)``."""
        if not self.meshes:
            return self._rest[self.n_surface:]
        return np.concatenate([m.positions(t) for m in self.meshes])

    def set_time(self, t: float) -> None:
        """Place the kinematic obstacles at time ``t`` (for the potentials and CCD)."""
        self._obstacles_at = np.asarray(self.obstacle_positions(t), dtype=np.float64)

    def collision_vertices(self, q: np.ndarray, obstacles: np.ndarray | None = None
                           ) -> np.ndarray:
        """Collision-mesh vertex positions ``(n_collision, 3)`` (Fortran order) of ``q``."""
        q3 = np.asarray(q, dtype=np.float64).reshape(-1, 3)
        obs = self._obstacles_at if obstacles is None else obstacles
        V = np.empty((self.n_collision_vertices, 3), order="F")
        V[: self.n_surface] = q3[self.surface]
        V[self.n_surface:] = obs
        return V

    # -- collision sets -----------------------------------------------------------------------
    def start_step(self, *configurations: np.ndarray, pad: float | None = None) -> None:
        """A new time step from ``configurations[0]`` (positions ``q``): the step's
        candidates are built around every configuration given (where the step is expected
        to go), inflated by ``pad`` (default :data:`STEP_PAD` ``dhat``), and grown only when
        a later query leaves them."""
        if not configurations:
            raise ValueError("start_step needs the step's start positions")
        Vs = [self.collision_vertices(q) for q in configurations]
        for part in self._parts:
            builds = part.step.builds
            part.step.reset(*[part.view(V) for V in Vs],
                            pad=STEP_PAD * self.dhat if pad is None else pad)
            self.stats.broad_phases += part.step.builds - builds
            part.key = None

    def candidates_near(self, part: _Part, V: np.ndarray, radius: float) -> ipctk.Candidates:
        """The step's candidates of ``part`` that hold every pair closer than ``2 radius``
        at its vertices ``V`` (grown when needed)."""
        t0, builds = part.step.seconds, part.step.builds
        cands = part.step.near(V, radius)
        self.stats.broad_phases += part.step.builds - builds
        self.stats.seconds_build += part.step.seconds - t0
        return cands

    def candidates_within(self, part: _Part, V: np.ndarray, radius: float) -> ipctk.Candidates:
        """Every pair of ``part`` closer than ``2 radius`` at its vertices ``V``, in no
        particular order, from a broad phase of its own (the step's set is left as it is: a
        wide query, as the pattern's margin, would make every later query of the step pay
        for its pairs). ipctk's LBVH: 3x faster than its hash grid on the pile, and the
        order it lists pairs in, which moves round-off elsewhere, does not matter here."""
        t0 = time.perf_counter()
        cands = ipctk.Candidates()
        cands.build(part.mesh, V, radius, broad_phase=ipctk.LBVH())
        self.stats.broad_phases += 1
        self.stats.seconds_build += time.perf_counter() - t0
        return cands

    def _candidates_along(self, part: _Part, V0: np.ndarray, V1: np.ndarray):
        builds = part.step.builds
        cands = part.step.along(V0, V1)
        self.stats.broad_phases += part.step.builds - builds
        return cands

    def _build(self, part: _Part, V: np.ndarray) -> ipctk.NormalCollisions:
        # boxes inflated by dhat / 2 each: pairs closer than dhat are candidates
        cands = self.candidates_near(part, V, 0.5 * self.dhat)
        t0 = time.perf_counter()
        col = ipctk.NormalCollisions()
        col.build(cands, part.mesh, V, self.dhat)
        self.stats.builds += 1
        self.stats.seconds_build += time.perf_counter() - t0
        return col

    def _active_sets(self, q: np.ndarray) -> list[tuple[_Part, np.ndarray]]:
        """``(part, its vertices)`` for every part with active pairs at ``q``."""
        V = self.collision_vertices(q)
        key = V.tobytes()
        out = []
        for part in self._parts:
            Vp = part.view(V)
            if part.key != key:
                part.collisions = self._build(part, Vp)
                part.key = key
            if len(part.collisions):
                out.append((part, Vp))
        return out

    def n_active(self, q: np.ndarray) -> int:
        """Number of contact pairs closer than ``dhat`` at ``q``."""
        n = sum(len(p.collisions) for p, _ in self._active_sets(q))
        if self.planes:
            n += int(np.count_nonzero(self._plane_distances(q) < self.dhat))
        return n

    # -- maps to fem3d DOFs ---------------------------------------------------------------------
    def _to_full_vector(self, g: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        if out is None:
            out = np.zeros(3 * self.n_vertices)
        out[self._dof[: self._n_dyn_dofs]] += g[: self._n_dyn_dofs]
        return out

    def _to_full_matrix(self, Hs: Sequence, triplets: bool = False):
        """The collision-DOF matrices ``Hs`` (sparse or :class:`Entries`) in full DOFs, as
        one COO matrix or (``triplets``) :class:`Entries`."""
        N = 3 * self.n_vertices
        rows, cols, vals = [], [], []
        nd = self._n_dyn_dofs
        for H in Hs:
            H = H.tocoo()
            keep = (H.row < nd) & (H.col < nd)
            rows.append(self._dof[H.row[keep]])
            cols.append(self._dof[H.col[keep]])
            vals.append(H.data[keep])
        if triplets:
            if not rows:
                return Entries(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
            return Entries(np.concatenate(rows), np.concatenate(cols), np.concatenate(vals))
        if not rows:
            return sp.coo_matrix((N, N))
        return sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows),
                                                     np.concatenate(cols))), shape=(N, N))

    # -- barrier ------------------------------------------------------------------------------
    def barrier_energy(self, q: np.ndarray) -> float:
        """``kappa * B(q)``; ``+inf`` when two primitives touch (distance 0)."""
        active = self._active_sets(q)
        t0 = time.perf_counter()
        e = sum(float(self._barrier(p.collisions, p.mesh, V)) for p, V in active)
        e += self._plane_barrier(q, 0)
        self.stats.seconds_derivatives += time.perf_counter() - t0
        return e if math.isfinite(e) else math.inf

    def barrier_gradient(self, q: np.ndarray) -> np.ndarray:
        """``kappa dB/dq``, ``(3n,)``."""
        active = self._active_sets(q)
        t0 = time.perf_counter()
        out = np.zeros(3 * self.n_vertices)
        for p, V in active:
            self._to_full_vector(self._barrier.gradient(p.collisions, p.mesh, V), out)
        if self.planes:
            self._to_full_vector(self._plane_barrier(q, 1), out)
        self.stats.seconds_derivatives += time.perf_counter() - t0
        return out

    def barrier_hessian(self, q: np.ndarray, *, project: bool = True,
                        triplets: bool = False) -> sp.coo_matrix | Entries:
        """``kappa d2B/dq2`` (per-pair PSD-projected when ``project``), ``(3n, 3n)`` COO
        (``triplets``: its ``row, col, data`` arrays alone, :class:`Entries`)."""
        active = self._active_sets(q)
        t0 = time.perf_counter()
        how = self._psd if project else ipctk.PSDProjectionMethod.NONE
        Hs = [self._barrier.hessian(p.collisions, p.mesh, V, how) for p, V in active]
        if self.planes:
            Hs.append(self._plane_barrier(q, 2, project=project))
        self.stats.seconds_derivatives += time.perf_counter() - t0
        return self._to_full_matrix(Hs, triplets)

    # -- friction (lagged) --------------------------------------------------------------------
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
        self._dt = float(dt)
        self._friction = ipctk.FrictionPotential(self.eps_v * self._dt)
        obs_t = self._obstacles_at if t_start is None else self.obstacle_positions(t_start)
        self._obstacles_t = np.asarray(obs_t, dtype=np.float64)
        V = self.collision_vertices(q_lag, self._obstacles_t)
        self._lagged_V = V
        if q_basis is not None:
            q_lag, V = q_basis, self.collision_vertices(q_basis)
        self._lag_planes(q_lag)
        for part in self._parts:
            part.tangential = part.majorizer = None
            if self.mu == 0.0:
                continue
            Vp = part.view(V)
            col = self._build(part, Vp)
            if len(col):
                tc = ipctk.TangentialCollisions()
                if self.mu_k == self.mu:
                    tc.build(part.mesh, Vp, col, self._barrier, self.mu)
                else:  # ipctk's own static-to-kinetic blend (friction_profile)
                    tc.build(part.mesh, Vp, col, self._barrier, self.mu, self.mu_k)
                part.tangential = tc if len(tc) else None

    def _slips(self, q: np.ndarray) -> list[tuple[_Part, np.ndarray]]:
        """``(part, slip displacement of its vertices)`` for the parts with friction pairs."""
        parts = [p for p in self._parts if p.tangential is not None]
        if not parts or self._lagged_V is None:
            return []
        U = np.asfortranarray(self.collision_vertices(q) - self._lagged_V)
        return [(p, p.view(U)) for p in parts]

    def friction_energy(self, q: np.ndarray) -> float:
        """Lagged friction potential ``D(q)`` (0 without friction or lagged contacts)."""
        e = sum(float(self._friction(p.tangential, p.mesh, U)) for p, U in self._slips(q))
        return e + self._plane_friction(q, 0)

    def friction_gradient(self, q: np.ndarray) -> np.ndarray:
        """``dD/dq``, ``(3n,)``."""
        out = np.zeros(3 * self.n_vertices)
        for p, U in self._slips(q):
            self._to_full_vector(self._friction.gradient(p.tangential, p.mesh, U), out)
        if self._plane_lag is not None:
            self._to_full_vector(self._plane_friction(q, 1), out)
        return out

    def friction_hessian(self, q: np.ndarray, *, project: bool = True,
                         triplets: bool = False) -> sp.coo_matrix | Entries:
        """``d2D/dq2`` (PSD-projected per pair when ``project``; the majorizer's is PSD as it
        is), ``(3n, 3n)`` COO (``triplets``: :class:`Entries`)."""
        how = self._psd if project else ipctk.PSDProjectionMethod.NONE
        if self.friction_hessian_kind == "majorizer":
            Hs = [self._majorizer(p).hessian(U) for p, U in self._slips(q)]
        else:
            Hs = [self._friction.hessian(p.tangential, p.mesh, U, how)
                  for p, U in self._slips(q)]
        if self._plane_lag is not None:
            Hs.append(self._plane_friction(q, 2, project=project))
        return self._to_full_matrix(Hs, triplets)

    def _majorizer(self, part: _Part) -> FrictionMajorizer:
        if part.majorizer is None:  # read once per lagging
            part.majorizer = FrictionMajorizer(part.tangential, part.mesh, self._friction.eps_v)
        return part.majorizer

    @property
    def n_friction_pairs(self) -> int:
        """Lagged friction pairs (0 when frictionless)."""
        n = sum(len(p.tangential) for p in self._parts if p.tangential is not None)
        return n + (0 if self._plane_lag is None else int(self._plane_lag[0].size))

    # -- totals -------------------------------------------------------------------------------
    def energy(self, q: np.ndarray) -> float:
        """Barrier + friction."""
        e = self.barrier_energy(q)
        if not math.isfinite(e):
            return math.inf
        return e + self.friction_energy(q)

    def gradient(self, q: np.ndarray) -> np.ndarray:
        """Gradient of :meth:`energy`, ``(3n,)``."""
        return self.barrier_gradient(q) + self.friction_gradient(q)

    def hessian(self, q: np.ndarray, *, project: bool = True) -> sp.coo_matrix:
        """Hessian of :meth:`energy` (PSD-projected per pair), ``(3n, 3n)`` COO (duplicates
        summed on conversion)."""
        Hb = self.barrier_hessian(q, project=project)
        if not self.n_friction_pairs:
            return Hb
        Hf = self.friction_hessian(q, project=project)
        N = 3 * self.n_vertices
        return sp.coo_matrix((np.concatenate([Hb.data, Hf.data]),
                              (np.concatenate([Hb.row, Hf.row]),
                               np.concatenate([Hb.col, Hf.col]))), shape=(N, N))

    # -- CCD, distances, intersections --------------------------------------------------------
    def max_step(self, q0: np.ndarray, q1: np.ndarray) -> float:
        """Largest ``a`` in ``[0, 1]`` such that ``q0 + a (q1 - q0)`` is collision free.

        Linear trajectories, bodies against each other, themselves (self-contact) and the
        obstacles (at their current positions); the narrow phase of the model (additive CCD
        by default, conservative) on the step's candidates (:meth:`start_step`).
        """
        t0 = time.perf_counter()
        V0 = self.collision_vertices(q0)
        V1 = self.collision_vertices(q1)
        a = 1.0
        for part in self._parts:
            if part.mesh is not self.mesh:
                continue  # planes: below
            P0, P1 = part.view(V0), part.view(V1)
            far = self._far.step(part.mesh, P0, P1)  # None: the bodies stay near
            if far is not None:
                self.stats.far_ccd_calls += 1
                a = min(a, far)
                continue
            cands = self._candidates_along(part, P0, P1)
            a = min(a, float(cands.compute_collision_free_stepsize(
                part.mesh, P0, P1, narrow_phase_ccd=self._ccd)))
            if self._ccd_guard is not None and self._nearly_touching(q0):
                a = min(a, float(cands.compute_collision_free_stepsize(
                    part.mesh, P0, P1, narrow_phase_ccd=self._ccd_guard)))
        a = min(a, self._plane_step(V0[: self.n_surface], V1[: self.n_surface]))
        self.stats.ccd_calls += 1
        self.stats.seconds_ccd += time.perf_counter() - t0
        return a

    def _nearly_touching(self, q: np.ndarray) -> bool:
        """Some mesh-mesh pair at ``q`` is closer than :data:`CCD_GUARD_DISTANCE` x the
        diagonal (ipctk returns squared distances)."""
        limit = (CCD_GUARD_DISTANCE * self.bbox_diagonal) ** 2
        return any(float(p.collisions.compute_minimum_distance(p.mesh, V)) < limit
                   for p, V in self._active_sets(q))

    def obstacle_step(self, q: np.ndarray, t0: float, t1: float) -> float:
        """CCD step of the kinematic obstacles moving from ``t0`` to ``t1`` with the bodies at
        ``q`` (1.0 without kinematic obstacles)."""
        if not any(m.motion is not None for m in self.meshes):
            return 1.0
        V0 = self.collision_vertices(q, self.obstacle_positions(t0))
        V1 = self.collision_vertices(q, self.obstacle_positions(t1))
        return float(ipctk.compute_collision_free_stepsize(
            self.mesh, V0, V1, broad_phase=self._broad_phase, narrow_phase_ccd=self._ccd))


    def minimum_distance(self, q: np.ndarray) -> float:
        """Smallest distance between primitives that can touch (planes included); ``inf``
        when no pair is closer than ``dhat``."""
        V = self.collision_vertices(q)
        d = math.inf
        for part, Vp in self._active_sets(q):
            # ipctk returns the squared distance
            d2 = float(part.collisions.compute_minimum_distance(part.mesh, Vp))
            d = min(d, math.sqrt(max(d2, 0.0)))
        for p in self.planes:
            d = min(d, float(p.signed_distance(V[: self.n_surface]).min()))
        return d

    def plane_gaps(self, q: np.ndarray) -> np.ndarray:
        """Signed distance of every surface vertex to every plane, ``(n_planes, n_surface)``."""
        if not self.planes:
            return np.zeros((0, self.n_surface))
        return self._plane_distances(q)

    def has_intersections(self, q: np.ndarray) -> bool:
        """Intersecting triangles (``ipctk.has_intersections``) or a vertex on or below a
        plane."""
        V = self.collision_vertices(q)
        if self.planes and (self.plane_gaps(q) <= 0).any():
            return True
        return bool(ipctk.has_intersections(self.mesh, V, broad_phase=self._broad_phase))

    def check_admissible(self, q: np.ndarray, *, step: int | None = None) -> None:
        """Raise :class:`SimulationError` naming the bodies when ``q`` intersects or touches.

        Raises
        ------
        SimulationError
            Intersecting bodies/obstacles, or primitives at distance 0 (infinite barrier).
        """
        if self.has_intersections(q):
            pairs = intersecting_pairs(self, q)
            what = "; ".join(f"{a} and {b}" if a != b else f"{a} with itself"
                             for a, b in pairs) or "the collision surfaces"
            raise SimulationError(f"contact: {what} intersect (not intersection-free)",
                                  step=step)
        if not math.isfinite(self.barrier_energy(q)):
            raise SimulationError("contact: two surfaces touch (distance 0); separate them "
                                  "by more than 0", step=step)

    # -- barrier stiffness (IPC) --------------------------------------------------------------
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
        unit = ipctk.BarrierPotential(self.dhat, 1.0)
        gb = np.zeros(3 * self.n_vertices)
        for part, Vp in self._active_sets(q):
            self._to_full_vector(unit.gradient(part.collisions, part.mesh, Vp), gb)
        if self.planes:
            kappa = self.kappa
            self.kappa = 1.0
            self._to_full_vector(self._plane_barrier(q, 1), gb)
            self.kappa = kappa
        kappa, kmax = ipctk.initial_barrier_stiffness(
            self.bbox_diagonal, unit.barrier, self.dhat, float(average_mass),
            np.asarray(grad_energy, dtype=np.float64), gb)
        self.max_kappa = float(kmax)
        self.set_kappa(float(kappa))
        self._stiffness_initialized = True
        self._prev_min_distance = None
        return self.kappa

    def update_stiffness(self, q: np.ndarray) -> float:
        """IPC's update: double ``kappa`` (up to :attr:`max_kappa`) when the minimum distance
        shrinks below ``1e-9`` of the scene's size. Returns the (possibly new) ``kappa``."""
        if not self.adaptive:
            return self.kappa
        d = self.minimum_distance(q)
        if not math.isfinite(d):
            self._prev_min_distance = d
            return self.kappa
        prev = self._prev_min_distance if self._prev_min_distance is not None else d
        prev = prev if math.isfinite(prev) else d
        # ipctk takes squared distances (its barrier is on d^2)
        new = float(ipctk.update_barrier_stiffness(prev * prev, d * d, self.max_kappa,
                                                   self.kappa, self.bbox_diagonal))
        self._prev_min_distance = d
        if new != self.kappa:
            self.set_kappa(new)
        return self.kappa
