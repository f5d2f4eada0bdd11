"""Which mesh-mesh pairs are close, and how far a motion may go: broad phase, collision sets
and CCD on the collision mesh (the geometry borrowed from ``ipctk``).

Mesh-mesh pairs come from one ``ipctk.Candidates`` set per time step
(:meth:`CollisionSets.start_step`, :class:`~fem3d.physics.contact.candidates.StepCandidates`):
built from the step's swept volume, grown only when a query leaves it, shared by the collision
sets of every iterate and line-search trial, CCD and friction's lagging. The normal collision
set (pairs closer than ``dhat``) is cached for the last configuration asked about.
Planes are not here (:mod:`.planes`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import ipctk
import numpy as np

from fem3d.errors import ParameterError
from fem3d.physics.contact.candidates import StepCandidates
from fem3d.physics.contact.far_travel import FarTravelCCD
from fem3d.physics.contact.friction_majorizer import FrictionMajorizer
from fem3d.physics.contact.geometry import CollisionGeometry

__all__ = ["BROAD_PHASES", "NARROW_PHASES", "CollisionPart", "CollisionSets", "ContactStats",
           "choice"]

#: Padding of the step's candidate boxes, in ``dhat``, when a step starts (the collision
#: sets need ``dhat / 2``). Every query pays for every candidate: on the pile 2 ``dhat``
#: made 1e5 where an iterate's swept boxes hold 5e3 (docs/contact.md, "Stop 31").
STEP_PAD = 0.75
#: ... and once an iterate has left them (moving more than predicted, as a tumbling stack):
#: 0.75 there re-ran the stack's broad phase 1.7x as often.
GROWTH_PAD = 2.0

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


def choice(table: dict, name: str, what: str):
    """``table[name]``; a :class:`ParameterError` naming ``what`` and the choices if absent."""
    if name not in table:
        raise ParameterError(f"{what} must be one of {sorted(table)}, got {name!r}")
    return table[name]


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


class CollisionPart:
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


class CollisionSets:
    """The step's candidates, the collision sets and CCD of a :class:`CollisionGeometry`.

    Parameters
    ----------
    geometry : CollisionGeometry
    dhat : float
        Barrier activation distance: the collision sets hold the pairs closer.
    broad_phase : str
        A key of :data:`BROAD_PHASES`.
    narrow_phase : str
        A key of :data:`NARROW_PHASES` (CCD): ``"additive"`` (Li et al. 2021's conservative
        additive CCD, 0.9 of the time of impact; guarded near contact,
        :data:`CCD_GUARD_DISTANCE`) or ``"tight_inclusion"``.
    stats : ContactStats
        Counted into.

    Attributes
    ----------
    parts : list of CollisionPart
        The mesh with its sets, when two of its primitives can touch at all (else empty).
    ccd, ccd_guard, broad_phase
        ipctk's narrow-phase CCD, its guard (None: none needed) and broad phase objects.
    """

    def __init__(self, geometry: CollisionGeometry, dhat: float, broad_phase: str,
                 narrow_phase: str, stats: ContactStats) -> None:
        self.geometry = geometry
        self.dhat = float(dhat)
        self.stats = stats
        self.broad_phase_name = broad_phase
        self.broad_phase = choice(BROAD_PHASES, broad_phase, "contact broad phase")()
        self.ccd = choice(NARROW_PHASES, narrow_phase, "contact CCD")()
        self.ccd_guard = (ipctk.AdditiveCCD(CCD_GUARD_ITERATIONS) if narrow_phase == "additive"
                          else None)
        g = geometry
        self.far = FarTravelCCD(g.rest[: g.n_surface], bool(g.meshes), self.broad_phase,
                                self.ccd)
        self.parts: list[CollisionPart] = []
        if g.can_touch:
            self.parts.append(CollisionPart(g.mesh, g.n_collision_vertices, self.broad_phase,
                                            GROWTH_PAD * dhat, self.far.reach))

    # -- candidates ---------------------------------------------------------------------------
    def start_step(self, *configurations: np.ndarray, pad: float | None = None) -> None:
        """A new time step from ``configurations[0]`` (positions ``q``): the step's
        candidates are built around every configuration given (where the step is expected
        to go), inflated by ``pad`` (default :data:`STEP_PAD` ``dhat``), and grown only when
        a later query leaves them."""
        if not configurations:
            raise ValueError("start_step needs the step's start positions")
        Vs = [self.geometry.collision_vertices(q) for q in configurations]
        for part in self.parts:
            builds = part.step.builds
            part.step.reset(*[part.view(V) for V in Vs],
                            pad=STEP_PAD * self.dhat if pad is None else pad)
            self.stats.broad_phases += part.step.builds - builds
            part.key = None

    def candidates_near(self, part: CollisionPart, V: np.ndarray, radius: float
                        ) -> ipctk.Candidates:
        """The step's candidates of ``part`` that hold every pair closer than ``2 radius``
        at its vertices ``V`` (grown when needed)."""
        t0, builds = part.step.seconds, part.step.builds
        cands = part.step.near(V, radius)
        self.stats.broad_phases += part.step.builds - builds
        self.stats.seconds_build += part.step.seconds - t0
        return cands

    def candidates_within(self, part: CollisionPart, V: np.ndarray, radius: float
                          ) -> ipctk.Candidates:
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

    def candidates_along(self, part: CollisionPart, V0: np.ndarray, V1: np.ndarray
                         ) -> ipctk.Candidates:
        """The step's candidates of ``part`` that hold every pair whose linear trajectories
        from ``V0`` to ``V1`` could meet (grown when needed)."""
        builds = part.step.builds
        cands = part.step.along(V0, V1)
        self.stats.broad_phases += part.step.builds - builds
        return cands

    # -- collision sets -----------------------------------------------------------------------
    def build(self, part: CollisionPart, V: np.ndarray) -> ipctk.NormalCollisions:
        """The pairs of ``part`` closer than ``dhat`` at its vertices ``V``."""
        # boxes inflated by dhat / 2 each: pairs closer than dhat are candidates
        cands = self.candidates_near(part, V, 0.5 * self.dhat)
        t0 = time.perf_counter()
        col = ipctk.NormalCollisions()
        col.build(cands, part.mesh, V, self.dhat)
        self.stats.builds += 1
        self.stats.seconds_build += time.perf_counter() - t0
        return col

    def active_sets(self, q: np.ndarray) -> list[tuple[CollisionPart, np.ndarray]]:
        """``(part, its vertices)`` for every part with active pairs at ``q``."""
        V = self.geometry.collision_vertices(q)
        key = V.tobytes()
        out = []
        for part in self.parts:
            Vp = part.view(V)
            if part.key != key:
                part.collisions = self.build(part, Vp)
                part.key = key
            if len(part.collisions):
                out.append((part, Vp))
        return out

    def n_active(self, q: np.ndarray) -> int:
        """Number of mesh-mesh pairs closer than ``dhat`` at ``q``."""
        return sum(len(p.collisions) for p, _ in self.active_sets(q))

    def minimum_distance(self, q: np.ndarray) -> float:
        """Smallest distance of the mesh-mesh pairs closer than ``dhat`` at ``q`` (``inf``:
        none)."""
        d = math.inf
        for part, Vp in self.active_sets(q):
            # ipctk returns the squared distance
            d2 = float(part.collisions.compute_minimum_distance(part.mesh, Vp))
            d = min(d, math.sqrt(max(d2, 0.0)))
        return d

    # -- CCD ----------------------------------------------------------------------------------
    def max_step(self, q0: np.ndarray, V0: np.ndarray, V1: np.ndarray) -> float:
        """Largest collision-free fraction of the mesh's linear motion from ``V0`` (the
        collision vertices of ``q0``) to ``V1``: the far-travel CCD, or the narrow phase on
        the step's candidates (guarded from a nearly touching start)."""
        a = 1.0
        for part in self.parts:
            P0, P1 = part.view(V0), part.view(V1)
            far = self.far.step(part.mesh, P0, P1)  # None: the bodies stay near
            if far is not None:
                self.stats.far_ccd_calls += 1
                a = min(a, far)
                continue
            cands = self.candidates_along(part, P0, P1)
            a = min(a, float(cands.compute_collision_free_stepsize(
                part.mesh, P0, P1, narrow_phase_ccd=self.ccd)))
            if self.ccd_guard is not None and self.nearly_touching(q0):
                a = min(a, float(cands.compute_collision_free_stepsize(
                    part.mesh, P0, P1, narrow_phase_ccd=self.ccd_guard)))
        return a

    def nearly_touching(self, q: np.ndarray) -> bool:
        """Some mesh-mesh pair at ``q`` is closer than :data:`CCD_GUARD_DISTANCE` x the
        diagonal (ipctk returns squared distances)."""
        limit = (CCD_GUARD_DISTANCE * self.geometry.bbox_diagonal) ** 2
        return any(float(p.collisions.compute_minimum_distance(p.mesh, V)) < limit
                   for p, V in self.active_sets(q))

    def obstacle_step(self, q: np.ndarray, t0: float, t1: float) -> float:
        """CCD step of the kinematic obstacles moving from ``t0`` to ``t1`` with the bodies at
        ``q`` (1.0 without kinematic obstacles)."""
        g = self.geometry
        if not any(m.motion is not None for m in g.meshes):
            return 1.0
        V0 = g.collision_vertices(q, g.obstacle_positions(t0))
        V1 = g.collision_vertices(q, g.obstacle_positions(t1))
        return float(ipctk.compute_collision_free_stepsize(
            g.mesh, V0, V1, broad_phase=self.broad_phase, narrow_phase_ccd=self.ccd))

    def has_intersections(self, V: np.ndarray) -> bool:
        """Intersecting triangles of the collision mesh at its vertices ``V``
        (``ipctk.has_intersections``)."""
        return bool(ipctk.has_intersections(self.geometry.mesh, V,
                                            broad_phase=self.broad_phase))
