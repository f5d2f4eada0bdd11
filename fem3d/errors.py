"""Error types of fem3d.

User mistakes (bad files, bad parameters) raise :class:`InputError`, whose message names the
file, the line or element, and what is wrong; the CLI prints it on one line and exits with
status 2. A simulation that cannot go on (non-finite state, runaway energy, no acceptable
Newton step) raises :class:`SimulationError`.
"""

from __future__ import annotations

from os import PathLike


class Fem3dError(Exception):
    """Base class of every error fem3d raises on purpose."""


class InputError(Fem3dError, ValueError):
    """Bad user input: a mesh file, a display mesh or a parameter.

    Parameters
    ----------
    message : str
        What is wrong, in a few words.
    path : str or PathLike, optional
        The file the problem is in.
    line : int, optional
        1-based line number in ``path``.
    element : int, optional
        0-based index of the offending element (tet, triangle or vertex).
    """

    def __init__(
        self,
        message: str,
        *,
        path: str | PathLike[str] | None = None,
        line: int | None = None,
        element: int | None = None,
    ) -> None:
        self.path = None if path is None else str(path)
        self.line = line
        self.element = element
        self.reason = message
        where = []
        if self.path is not None:
            where.append(self.path if line is None else f"{self.path}:{line}")
        elif line is not None:
            where.append(f"line {line}")
        if element is not None:
            where.append(f"element {element}")
        super().__init__(f"{', '.join(where)}: {message}" if where else message)


class ParameterError(InputError):
    """A physical or numerical parameter is out of its valid range."""


class SimulationError(Fem3dError, RuntimeError):
    """The simulation cannot go on (blow-up, inverted elements, no descent step).

    Parameters
    ----------
    message : str
        What happened.
    step : int, optional
        The 0-based index of the step that failed.
    """

    def __init__(self, message: str, *, step: int | None = None) -> None:
        self.step = step
        self.reason = message
        super().__init__(message if step is None else f"step {step}: {message}")
