"""CCD of queries that carry the bodies far: in the frame that moves with them, and cut short.

Subtracting ``c0 + t (c1 - c0)`` from every vertex of a linear motion moves no pair of
vertices relative to each other, so the times of impact between bodies (and within one) are
the same in that frame; in the world frame, though, the swept boxes of a query that carries
the bodies far span the whole travel and make every pair of surface primitives a candidate.
``static``'s first load step is such a query: an unsupported body's stiffness is singular
along its fall, so Newton's first directions drop it kilometres (and deform it by
kilometres): the self-contact bunny drop spent 51 s of CPU in one step's CCD, the gallery
stack ran out of memory in ipctk's broad phase, the pile did not finish its first step in
minutes. A mesh obstacle does not travel with the bodies, so with one the query stays in the
world frame; in either frame a query that moves some vertex further than the reach is cut to
the reach first (the step is then at most the cut), which bounds the boxes.
"""

from __future__ import annotations

import ipctk
import numpy as np

__all__ = ["FAR_TRAVEL", "FarTravelCCD"]

#: A CCD query on which the bodies' mean position moves more than this fraction of their size
#: (bounding-box diagonal) is far; a far query moves no vertex further than that relative to
#: its frame, and a step's shared candidate boxes grow no wider. A tenth: 5.4 m/s for the
#: gallery's bunny (0.54 m) at dt = 0.01, above any dynamic step of the gallery (their boxes
#: reach at most half of it), so their runs keep the shared candidates and their bits.
FAR_TRAVEL = 0.1


class FarTravelCCD:
    """CCD of a query that carries the bodies far, with a broad phase of its own.

    Parameters
    ----------
    rest_surface : (k, 3) float64
        The bodies' surface vertices at rest, the first ``k`` rows of every query (their
        size, the bounding-box diagonal, sets the reach).
    obstacles : bool
        Whether mesh obstacles follow them in the queries (they stay behind: world frame).
    broad_phase, narrow_phase
        ipctk's broad phase and narrow-phase CCD objects.
    """

    def __init__(self, rest_surface: np.ndarray, obstacles: bool, broad_phase,
                 narrow_phase) -> None:
        self.n_surface = len(rest_surface)
        size = float(np.linalg.norm(np.ptp(rest_surface, axis=0))) if self.n_surface else 0.0
        #: how far the bodies' mean position moves before a query is far, and how far a
        #: far query may move a vertex (relative to its frame)
        self.reach = FAR_TRAVEL * size
        self.obstacles = bool(obstacles)
        self._broad_phase, self._ccd = broad_phase, narrow_phase

    def step(self, mesh: ipctk.CollisionMesh, P0: np.ndarray, P1: np.ndarray) -> float | None:
        """The largest collision-free fraction of ``P0 -> P1`` (every vertex of ``mesh``),
        or None when the bodies' mean position moves less than :data:`FAR_TRAVEL`
        of their size (the caller's CCD on the step's shared candidates then answers).
        """
        n = self.n_surface
        if not n:
            return None
        c0, c1 = P0[:n].mean(axis=0), P1[:n].mean(axis=0)
        reach = self.reach
        if not np.linalg.norm(c1 - c0) > reach:
            return None
        Q0, Q1 = (P0, P1) if self.obstacles else (P0 - c0, P1 - c1)
        rel = float(np.abs(Q1 - Q0).max())
        cut = min(1.0, reach / rel) if rel > 0.0 else 1.0
        if cut < 1.0:
            Q1 = Q0 + cut * (Q1 - Q0)
        return cut * float(ipctk.compute_collision_free_stepsize(
            mesh, Q0, Q1, broad_phase=self._broad_phase, narrow_phase_ccd=self._ccd))
