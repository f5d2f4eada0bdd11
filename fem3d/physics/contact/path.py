"""Whether a time step's own straight motion, from ``q_t`` to ``q_{t+1}``, is intersection-free.

Newton's iterates of a contact step are each reached by a CCD-checked segment, so the chain
of segments from ``q_t`` to ``q_{t+1}`` never passes through a surface; the straight motion
between the two states, which is what the time discretisation (and any playback of the
frames) assumes, may. A fast body can be steered by that chain around another one's corner
(``docs/contact.md``, "The fast body through a free body"): then the straight motion
intersects, and the step has to be shorter (:mod:`fem3d.solve.substeps`).

The test here is Tight-Inclusion CCD (Wang et al. 2021, through ``ipctk``) on the straight
motion of every collision vertex, the bodies from ``q0`` to ``q1`` and the mesh obstacles from
where they are at ``t0`` to where they are at ``t1``, with the minimum distance the line search
uses (0) and no conservative rescaling (``conservative_rescaling = 1``): it reports a time of
impact only where primitives meet, not where they merely come closer than a fraction of their
start distance (the line search's additive CCD does, to keep the barrier finite: that would
flag every landing). Tight-Inclusion decides to a tolerance: at ipctk's default (1e-6 m) it
also flags a pair that comes within about 1e-7 m without meeting, which a pair pressed into
resting contact by the barrier does (the pile, step 13: an edge pair 3e-7 m apart at its
closest); a motion it flags is checked again at 1e-9 and 1e-12 m
(:data:`PATH_CCD_TOLERANCES`), and it meets a surface only when every one flags it. Planes
need no test: each vertex moves on a line, so it crosses a plane within the step only if it
ends below it, which the line search never accepts. The candidates are the step's own
(:class:`~fem3d.physics.contact.candidates.StepCandidates`), grown when the motion leaves
their boxes. The model's own CCD (additive by default) runs first: it flags every pair whose
distance falls below a tenth of its start, so a motion it passes meets no surface, and only
a flagged motion (a landing, a hit) needs the exact test; on the twisted bar this halves the
check's cost (0.6 to 0.3 ms a step).
"""

from __future__ import annotations

import time

import ipctk
import numpy as np

from fem3d.physics.contact.collisions import CollisionSets

__all__ = ["straight_path_is_free", "PATH_CCD_TOLERANCE", "PATH_CCD_TOLERANCES"]

#: Tight-Inclusion's tolerances (co-domain widths, m), tried in turn: the first is ipctk's
#: default; a motion it flags is checked again at the next, and it meets a surface only when
#: the last flags it too. Tight-Inclusion reports a pair whose distance along the motion
#: falls below a fraction of its tolerance (scaled down to half the pair's start distance
#: where that is smaller; measured: about a tenth, faces off the axes), whether or not it
#: reaches 0: a pair pressed into resting contact by the barrier is flagged at 1e-6 without
#: crossing anything. A crossing (distance 0) is flagged at every tolerance.
PATH_CCD_TOLERANCES = (1e-6, 1e-9, 1e-12)

#: The first (ipctk's default).
PATH_CCD_TOLERANCE = PATH_CCD_TOLERANCES[0]

#: Tight-Inclusion's iteration budget (its default; past it, it reports a hit).
PATH_CCD_MAX_ITERATIONS = 10_000_000

_CCDS = tuple(ipctk.TightInclusionCCD(tol, PATH_CCD_MAX_ITERATIONS, 1.0)
              for tol in PATH_CCD_TOLERANCES)


def straight_path_is_free(collisions: CollisionSets, q0: np.ndarray, q1: np.ndarray,
                          t0: float, t1: float) -> bool:
    """Whether the straight motion from ``q0`` at ``t0`` to ``q1`` at ``t1`` meets no surface.

    Parameters
    ----------
    collisions : CollisionSets
        The contact model's (``ContactModel.collisions``): its geometry, the step's
        candidates, the model's CCD.
    q0, q1 : (3n,) or (n, 3) float64
        The bodies' positions at the start and the end of the motion.
    t0, t1 : float
        The times of ``q0`` and ``q1`` (the kinematic mesh obstacles' positions).

    Returns
    -------
    bool
        True when no pair of primitives that can touch meets along the motion (always True
        without mesh-mesh contact: a body against planes only).
    """
    if not collisions.parts:
        return True
    start = time.perf_counter()
    g = collisions.geometry
    V0 = g.collision_vertices(q0, g.obstacle_positions(t0))
    V1 = g.collision_vertices(q1, g.obstacle_positions(t1))
    free = True
    for part in collisions.parts:
        P0, P1 = np.asfortranarray(part.view(V0)), np.asfortranarray(part.view(V1))
        cands = collisions.candidates_along(part, P0, P1)
        # the model's CCD first (additive by default, cheaper): it flags every pair that
        # comes closer than a fraction of its start distance, so a motion it passes meets no
        # surface; only a flagged motion needs the exact test
        if cands.is_step_collision_free(part.mesh, P0, P1, min_distance=0.0,
                                        narrow_phase_ccd=collisions.ccd):
            continue
        if not any(cands.is_step_collision_free(part.mesh, P0, P1, min_distance=0.0,
                                                narrow_phase_ccd=ccd) for ccd in _CCDS):
            free = False
            break
    collisions.stats.ccd_calls += 1
    collisions.stats.seconds_ccd += time.perf_counter() - start
    return free
