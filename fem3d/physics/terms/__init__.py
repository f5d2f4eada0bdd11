"""The terms of a time step's objective, one file each, all with the interface of
:class:`~fem3d.physics.terms.base.Term`: inertia, elasticity, gravity, Rayleigh damping,
pull springs and IPC contact. A new physical effect is one new term (and its scene key)."""
