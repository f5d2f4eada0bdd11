"""Deprecated alias of :mod:`fem3d.solve.linear`.

Moved in the restructuring of fem3d 0.2; the alias goes in 0.3 (see docs/architecture.md).
"""

from fem3d._deprecated import forward

__getattr__ = forward(__name__, (
    "fem3d.solve.linear, fem3d.solve.linear.krylov, fem3d.solve.linear.amg"))
