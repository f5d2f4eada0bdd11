"""Optional dependencies (the ``fem3d[...]`` extras), checked before a command writes anything.

A command that needs an extra calls :func:`require` first; without it the user gets one line
naming what needs it and the extra to install, exit status 2 (an :class:`InputError` through
the CLI), and no output folder or lock file is created::

    fem3d run: error: --format usd (output.format) needs usd-core (module pxr):
    pip install 'fem3d[scenes]'

The check finds the module without importing it (:func:`importlib.util.find_spec`), so it
costs nothing when the extra is there.
"""

from __future__ import annotations

import importlib.util
import sys

from fem3d.errors import InputError

__all__ = ["EXTRAS", "MissingExtra", "has_module", "require"]

#: Top-level module -> (distribution to install, the fem3d extra that brings it).
EXTRAS: dict[str, tuple[str, str]] = {
    "distributed": ("dask.distributed", "sweep"),
    "pxr": ("usd-core", "scenes"),
    "wildmeshing": ("wildmeshing", "scenes"),
    "sksparse": ("scikit-sparse", "cholmod"),
    "viser": ("viser", "view"),
    "petsc4py": ("petsc4py", "mpi"),
    "mpi4py": ("mpi4py", "mpi"),
}


class MissingExtra(InputError):
    """An optional dependency is not installed (one line naming the extra to install)."""


def has_module(name: str) -> bool:
    """Whether the top-level module ``name`` can be imported (found, not imported)."""
    if name in sys.modules:
        return sys.modules[name] is not None  # None: blocked (python -X importtime, tests)
    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):
        return False


def install_hint(module: str) -> str:
    """``pip install 'fem3d[EXTRA]'`` for a module of :data:`EXTRAS`."""
    return f"pip install 'fem3d[{EXTRAS[module][1]}]'"


def require(module: str, what: str) -> None:
    """Raise :class:`MissingExtra` unless ``module`` (a key of :data:`EXTRAS`) is installed.

    Parameters
    ----------
    module : str
        Top-level module, e.g. ``"pxr"``.
    what : str
        What needs it, e.g. ``"--format usd (output.format)"``.

    Raises
    ------
    MissingExtra
        ``WHAT needs DIST (module M): pip install 'fem3d[EXTRA]'``.
    """
    if has_module(module):
        return
    dist, _ = EXTRAS[module]
    named = dist if dist == module else f"{dist} (module {module})"
    raise MissingExtra(f"{what} needs {named}: {install_hint(module)}")
