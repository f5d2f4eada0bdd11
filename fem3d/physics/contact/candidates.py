"""The collision candidates of one time step, built from the step's swept volume.

Every contact query of a backward-Euler step — the collision set at each Newton iterate and
line-search trial (pairs closer than ``dhat``), CCD along each trial step, the check that the
step's own motion from its start is intersection-free — needs the primitive pairs whose
bounding boxes overlap somewhere in a region of configuration space that changes little
within a step. :class:`StepCandidates` keeps one ``ipctk.Candidates`` set built from one
axis-aligned box per collision vertex that holds every position the step has asked about so
far (inflated by a pad); a query inside the boxes reuses the set, one outside grows the boxes
and rebuilds it (one broad phase). A primitive's box is the union of its vertices' boxes, so
the set holds every pair that could be closer than the query's inflation at any
configuration whose vertices lie inside their boxes, and every pair whose linear
trajectories between two such configurations could meet (a box is convex). The collision
set built from these candidates holds the pairs a fresh broad phase at the configuration
gives; with the hash grid (the default) or brute force, whose candidates come sorted, also
in the same order, so the energies are bit for bit the same (sweep and prune and the LBVH
list the same pairs in another order: round-off). Extra candidates can only lower a
conservative CCD's step (additive CCD flags a pair whose distance falls below a tenth of its
start); on the gallery's stack none did.
"""

from __future__ import annotations

import math
import time

import ipctk
import numpy as np

__all__ = ["StepCandidates"]


class StepCandidates:
    """Collision candidates of one ``ipctk.CollisionMesh`` covering a time step's motion.

    Parameters
    ----------
    mesh : ipctk.CollisionMesh
    broad_phase : ipctk.BroadPhase
    pad : float
        Added on every side of a box when it grows (and when a step's set is built, unless
        :meth:`reset` is given its own), so that iterates moving a little further reuse the
        set.
    max_extent : float, optional
        A box grows to hold a query only while no box gets wider than this; beyond, the set
        is rebuilt around the query alone (a step whose iterates travel far, as ``static``'s
        first load step, would otherwise make every pair a candidate).

    Attributes
    ----------
    builds : int
        Broad phases run.
    seconds : float
        Wall time in them.
    """

    def __init__(self, mesh: ipctk.CollisionMesh, broad_phase, pad: float,
                 max_extent: float = math.inf) -> None:
        self.mesh = mesh
        self._broad_phase = broad_phase
        self.pad = float(pad)
        self.max_extent = float(max_extent)
        self.lo: np.ndarray | None = None
        self.hi: np.ndarray | None = None
        self.candidates: ipctk.Candidates | None = None
        self.builds = 0
        self.seconds = 0.0

    def reset(self, *configurations: np.ndarray, pad: float | None = None) -> None:
        """Forget the boxes (a new step); with ``configurations`` (``(k, 3)`` each), build the
        set at once around the boxes that hold them (inflated by ``pad``, default
        :attr:`pad`, the padding of grown boxes)."""
        self.lo = self.hi = self.candidates = None
        if configurations:
            lo = np.minimum.reduce(configurations)
            hi = np.maximum.reduce(configurations)
            p = self.pad if pad is None else float(pad)
            self._build(lo - p, hi + p)

    def covering(self, lo: np.ndarray, hi: np.ndarray) -> ipctk.Candidates:
        """Candidates whose boxes hold the per-vertex boxes ``[lo, hi]`` (``(k, 3)`` each)."""
        if self.candidates is not None and (lo >= self.lo).all() and (hi <= self.hi).all():
            return self.candidates
        lo, hi = lo - self.pad, hi + self.pad
        if self.candidates is not None:
            grown_lo, grown_hi = np.minimum(lo, self.lo), np.maximum(hi, self.hi)
            if (grown_hi - grown_lo).max() <= self.max_extent:
                lo, hi = grown_lo, grown_hi
        self._build(lo, hi)
        return self.candidates

    def near(self, V: np.ndarray, radius: float) -> ipctk.Candidates:
        """Every pair of primitives closer than ``2 radius`` at ``V`` is a candidate."""
        return self.covering(V - radius, V + radius)

    def along(self, V0: np.ndarray, V1: np.ndarray) -> ipctk.Candidates:
        """Every pair whose linear trajectories from ``V0`` to ``V1`` could meet."""
        return self.covering(np.minimum(V0, V1), np.maximum(V0, V1))

    def _build(self, lo: np.ndarray, hi: np.ndarray) -> None:
        t0 = time.perf_counter()
        lo, hi = np.asfortranarray(lo), np.asfortranarray(hi)
        cands = ipctk.Candidates()
        # the swept-box build of ipctk: vertex i's box is bbox(lo[i], hi[i]) = [lo[i], hi[i]]
        cands.build(self.mesh, lo, hi, 0.0, broad_phase=self._broad_phase)
        self.lo, self.hi, self.candidates = lo, hi, cands
        self.builds += 1
        self.seconds += time.perf_counter() - t0
