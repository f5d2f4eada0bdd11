"""Time integrators as objects: :class:`~fem3d.solve.schemes.base.Scheme` (``base``), one
module per scheme, and the registry by name (``registry``)."""
