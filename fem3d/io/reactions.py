"""The reactions of a run: ``reactions.csv``, the force each pin exerts per step.

Columns ``step,t`` then ``<pin>.fx,<pin>.fy,<pin>.fz`` for each pin (``bodies[0].pins[1]``),
in scene order; one row per step (:meth:`fem3d.simulation.Simulation.reactions`). Written
atomically (``repr`` precision) like ``energy.csv``; a resumed run keeps the rows up to its
checkpoint's step.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fem3d.errors import InputError
from fem3d.io.files import PathLike, atomic_write

__all__ = ["ReactionLog", "read_reactions_csv"]


class ReactionLog:
    """The reactions of a run's pins, saved as ``reactions.csv``.

    Parameters
    ----------
    path : str or PathLike
    pins : sequence of str
        The pins' keys, in the order of the rows' groups.
    """

    def __init__(self, path: PathLike, pins) -> None:
        self.path = Path(path)
        self.pins = list(pins)
        self._rows: list[tuple[float, ...]] = []

    @property
    def header(self) -> str:
        """The CSV header line."""
        return ",".join(["step", "t", *(f"{p}.f{a}" for p in self.pins for a in "xyz")])

    def append(self, step: int, t: float, forces: np.ndarray) -> None:
        """Add one step's ``(n_pins, 3)`` forces."""
        f = np.asarray(forces, dtype=np.float64).reshape(len(self.pins), 3)
        self._rows.append((float(step), float(t), *f.reshape(-1).tolist()))

    def keep_until(self, step: int) -> ReactionLog:
        """Read the rows of an earlier run at :attr:`path` up to ``step`` (a resume; none
        when the file is missing or has other pins)."""
        if self.path.is_file():
            try:
                rows = read_reactions_csv(self.path)
            except InputError:
                return self
            if rows.shape[1:] == (2 + 3 * len(self.pins),):
                self._rows = [tuple(map(float, r)) for r in rows if r[0] <= step]
        return self

    def write(self) -> None:
        """Write :attr:`path` atomically (nothing without pins)."""
        if not self.pins:
            return
        lines = [self.header] + [",".join([f"{r[0]:.0f}"] + [repr(x) for x in r[1:]])
                                 for r in self._rows]
        atomic_write(self.path, "\n".join(lines) + "\n")


def read_reactions_csv(path: PathLike) -> np.ndarray:
    """``(rows, 2 + 3 n_pins)`` float64: ``step, t`` and the forces of ``reactions.csv``.

    Raises
    ------
    InputError
        Not a reactions file.
    """
    path = Path(path)
    lines = path.read_text().splitlines()
    if not lines or not lines[0].startswith("step,t"):
        raise InputError("not a reactions.csv (header 'step,t,...')", path=str(path))
    width = len(lines[0].split(","))
    try:
        rows = [[float(x) for x in line.split(",")] for line in lines[1:] if line]
        return np.array(rows, dtype=np.float64).reshape(-1, width)
    except ValueError as exc:
        raise InputError(f"not a reactions.csv: {exc}", path=str(path)) from None
