"""Incremental Potential Contact (IPC) for fem3d, on the IPC Toolkit (``ipctk``).

The geometry — the collision mesh, distances, broad phase, continuous collision detection
(CCD), intersection tests — comes from ``ipctk``; fem3d owns the potentials (the barrier and
the lagged friction) and how they map onto its degrees of freedom and enter the objective
(:mod:`fem3d.physics.terms.contact`). The modules, from the geometry up:

``obstacles``
    :class:`PlaneObstacle`, :class:`MeshObstacle` (static or kinematic).
``geometry``
    The collision mesh: the bodies' boundary surface and the mesh obstacles in one
    ``ipctk.CollisionMesh``, which pairs can touch, the maps to fem3d's DOFs.
``candidates``, ``far_travel``, ``collisions``
    The step's collision candidates (one broad phase per step), CCD of queries that carry the
    bodies far, and the collision sets and CCD of the step's queries.
``path``
    Whether a step's own straight motion is intersection-free (the substeps' check).
``planes``
    Point-plane pairs, vectorized: barrier, friction and CCD against the planes.
``barrier``
    The barrier potential ``kappa * sum b(d^2, dhat^2)`` and IPC's adaptive stiffness.
``friction``, ``friction_profile``, ``friction_majorizer``
    The lagged friction potential, the planes' static-to-kinetic profile, and the friction's
    quadratic majorizer for Newton's matrix.
``diagnostics``
    Which bodies intersect (the named answer of an error message).
``model``
    :class:`ContactModel`: the one object the terms, the scene build and the adjoint use,
    composing the parts above.

Determinism: ``ipctk`` runs single-threaded (``ipctk.set_num_threads(1)`` when a model is
built): its threaded assembly adds per-thread partial sums in a varying order, so two runs of
the same step would differ in the last bits and a resumed run would not repeat the
uninterrupted one.
"""

from fem3d.physics.contact.collisions import BROAD_PHASES, NARROW_PHASES, ContactStats
from fem3d.physics.contact.friction import FRICTION_HESSIANS
from fem3d.physics.contact.model import HESSIAN_PROJECTIONS, ContactModel
from fem3d.physics.contact.obstacles import MeshObstacle, PlaneObstacle

__all__ = ["BROAD_PHASES", "FRICTION_HESSIANS", "HESSIAN_PROJECTIONS", "NARROW_PHASES",
           "ContactModel", "ContactStats", "MeshObstacle", "PlaneObstacle"]
