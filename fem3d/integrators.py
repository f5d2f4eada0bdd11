"""Deprecated alias of :mod:`fem3d.solve.integrators`.

Moved in the restructuring of fem3d 0.2; the alias goes in 0.3 (see docs/architecture.md).
"""

from fem3d._deprecated import forward

__getattr__ = forward(__name__, (
    "fem3d.solve.integrators, fem3d.solve.backward_euler, fem3d.solve.newton, "
    "fem3d.solve.state, fem3d.solve.system, fem3d.solve.directions, fem3d.physics.springs"))
