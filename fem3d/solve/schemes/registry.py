"""The time integrators by name: the one registry of schemes.

The scene schema's ``simulation.integrator`` choices, ``fem3d run --integrator``'s help, the
viewer's N cycle (:func:`dynamic_scheme_names`), the adjoint's schemes
(:mod:`fem3d.diff.schemes`) and the checkpoint's history all come from here. Adding a
scheme is one module (a :class:`~fem3d.solve.schemes.base.Scheme` subclass) and one line in
:data:`SCHEMES`, or :func:`register_scheme` from a plug-in or a test.
"""

from __future__ import annotations

from fem3d.errors import ParameterError
from fem3d.solve.schemes.base import Scheme
from fem3d.solve.schemes.bdf2 import BDF2
from fem3d.solve.schemes.implicit import IMPLICIT
from fem3d.solve.schemes.linear import LinearlyImplicit
from fem3d.solve.schemes.newmark import Newmark
from fem3d.solve.schemes.static import Static

__all__ = ["SCHEMES", "DEFAULT_SCHEME", "register_scheme", "get_scheme", "scheme_names",
           "dynamic_scheme_names"]

#: The schemes by ``simulation.integrator`` name, in the order the docs and the viewer list
#: them.
SCHEMES: dict[str, Scheme] = {s.name: s for s in (
    LinearlyImplicit(),
    IMPLICIT,
    BDF2(),
    Newmark(),
    Static(),
)}

#: ``simulation.integrator`` when a scene names none.
DEFAULT_SCHEME = IMPLICIT.name


def register_scheme(scheme: Scheme) -> Scheme:
    """Add ``scheme`` (an instance) under its ``name``; returns it.

    Raises
    ------
    ValueError
        No name, or the name is taken by another scheme.
    """
    if not scheme.name:
        raise ValueError(f"{type(scheme).__name__} has no name")
    if scheme.name in SCHEMES and SCHEMES[scheme.name] is not scheme:
        raise ValueError(f"a scheme named {scheme.name!r} is registered already")
    SCHEMES[scheme.name] = scheme
    return scheme


def scheme_names() -> tuple[str, ...]:
    """Every registered scheme's name."""
    return tuple(SCHEMES)


def dynamic_scheme_names() -> tuple[str, ...]:
    """The time-dependent schemes' names (the viewer's N key cycles through them)."""
    return tuple(n for n, s in SCHEMES.items() if s.dynamic)


def get_scheme(name: str) -> Scheme:
    """The scheme named ``name``.

    Raises
    ------
    ParameterError
        ``unknown integrator 'x'; choose one of linear, implicit, ...``.
    """
    try:
        return SCHEMES[name]
    except (KeyError, TypeError):
        raise ParameterError(f"unknown integrator {name!r}; choose one of "
                       f"{', '.join(SCHEMES)}") from None
