"""IPC contact (Incremental Potential Contact) on the IPC Toolkit: :mod:`.model` says what
it does; the public names are re-exported here."""

from fem3d.physics.contact.model import (
    BROAD_PHASES,
    FRICTION_HESSIANS,
    HESSIAN_PROJECTIONS,
    NARROW_PHASES,
    ContactModel,
    ContactStats,
    MeshObstacle,
    PlaneObstacle,
)

__all__ = ["BROAD_PHASES", "FRICTION_HESSIANS", "HESSIAN_PROJECTIONS", "NARROW_PHASES",
           "ContactModel", "ContactStats", "MeshObstacle", "PlaneObstacle"]
