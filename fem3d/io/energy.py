"""The energy log of a run: ``energy.csv``.

Two layouts, told apart by the header: ``t,kinetic,potential,total`` (runs written before
the split, and logs without it) and ``t,kinetic,potential,total,strain,gravity,pull``
(``potential = strain + gravity``; ``pull``: the pull springs' energy, not in ``total``).
Both are read; a run resumed from an old checkpoint writes the new layout with ``nan`` in the
split columns of the rows it inherited (their split was never recorded).

- :class:`EnergyLog` - the rows of a run, written atomically as CSV (``repr`` precision).
- :func:`read_energy_csv` - read one back.
- :func:`energy_columns` - the columns of a log, a CSV file, a mapping or an array.

The plot of a log is :func:`fem3d.io.preview.plot_energy`.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from fem3d.errors import InputError
from fem3d.io.files import PathLike, atomic_write

__all__ = ["ENERGY_HEADER", "ENERGY_HEADER_SPLIT", "EnergyLog", "energy_columns",
           "read_energy_csv"]

#: Header line of ``energy.csv`` without the split (the column names).
ENERGY_HEADER = "t,kinetic,potential,total"
#: Header line of ``energy.csv`` with strain, gravity and pull energies.
ENERGY_HEADER_SPLIT = ENERGY_HEADER + ",strain,gravity,pull"
_WIDTHS = {4: ENERGY_HEADER, 7: ENERGY_HEADER_SPLIT}


class EnergyLog:
    """Energy history of a run, saved as ``energy.csv``.

    Parameters
    ----------
    path : str or PathLike, optional
        Default file of :meth:`write`.
    """

    def __init__(self, path: PathLike | None = None) -> None:
        self.path = None if path is None else Path(path)
        self._rows: list[tuple[float, ...]] = []

    def append(
        self, t: float, kinetic: float, potential: float, total: float | None = None, *,
        gravity: float | None = None, pull: float = 0.0,
    ) -> None:
        """Add one row; ``total`` defaults to ``kinetic + potential``. With ``gravity``
        (gravity's part of ``potential``) the row carries the split: strain, gravity, pull."""
        k, p = float(kinetic), float(potential)
        row = (float(t), k, p, k + p if total is None else float(total))
        if gravity is not None:
            row += (p - float(gravity), float(gravity), float(pull))
        self._rows.append(row)

    def __len__(self) -> int:
        return len(self._rows)

    @property
    def split(self) -> bool:
        """Whether the log has the strain/gravity/pull columns (any row carries them)."""
        return any(len(r) == 7 for r in self._rows)

    @classmethod
    def from_array(cls, rows: np.ndarray, path: PathLike | None = None) -> EnergyLog:
        """A log holding ``rows`` ``(n_rows, 4)`` or ``(n_rows, 7)`` (e.g. from a
        checkpoint), values exact."""
        a = np.asarray(rows, dtype=np.float64)
        a = a.reshape(-1, a.shape[-1] if a.ndim == 2 and a.shape[-1] in _WIDTHS else 4)
        log = cls(path)
        log._rows = [tuple(float(x) for x in row) for row in a]
        return log

    def as_array(self) -> np.ndarray:
        """Rows ``(t, kinetic, potential, total[, strain, gravity, pull])`` as an
        ``(n_rows, 4)`` or ``(n_rows, 7)`` float64 array (``nan`` where a row has no split)."""
        width = 7 if self.split else 4
        nan = (float("nan"),) * 3
        rows = [r if len(r) == width else r + nan for r in self._rows]
        return np.array(rows, dtype=np.float64).reshape(-1, width)

    def as_dict(self) -> dict[str, np.ndarray]:
        """The columns by name as ``(n_rows,)`` arrays (the split's when present)."""
        a = self.as_array()
        return {name: a[:, i].copy() for i, name in enumerate(_WIDTHS[a.shape[1]].split(","))}

    def to_csv(self) -> str:
        """CSV text with its layout's header (``repr`` precision)."""
        a = self.as_array()
        out = [_WIDTHS[a.shape[1]]]
        out += [",".join(repr(float(v)) for v in row) for row in a]
        return "\n".join(out) + "\n"

    def write(self, path: PathLike | None = None) -> Path:
        """Write the CSV atomically to ``path`` (default: the constructor's path)."""
        target = path if path is not None else self.path
        if target is None:
            raise ValueError("EnergyLog.write needs a path")
        return atomic_write(target, self.to_csv())


def read_energy_csv(path: PathLike) -> dict[str, np.ndarray]:
    """Read an ``energy.csv`` of either layout: columns ``t``, ``kinetic``, ``potential``,
    ``total`` (and ``strain``, ``gravity``, ``pull`` in the split layout)."""
    path = Path(path)
    with open(path, encoding="utf-8") as fh:
        header = fh.readline().strip()
        if header not in (ENERGY_HEADER, ENERGY_HEADER_SPLIT):
            raise InputError(
                f"expected header {ENERGY_HEADER!r} or {ENERGY_HEADER_SPLIT!r}, got {header!r}",
                path=path, line=1,
            )
        names = header.split(",")
        rows = []
        for lineno, line in enumerate(fh, start=2):
            if not line.strip():
                continue
            parts = line.split(",")
            try:
                if len(parts) != len(names):
                    raise ValueError
                rows.append([float(x) for x in parts])
            except ValueError:
                raise InputError(
                    f"expected {len(names)} comma-separated numbers", path=path, line=lineno
                ) from None
    a = np.array(rows, dtype=np.float64).reshape(-1, len(names))
    return {name: a[:, i].copy() for i, name in enumerate(names)}


def energy_columns(data: Any) -> dict[str, np.ndarray]:
    """Columns ``t``, ``kinetic``, ``potential``, ``total`` of an energy history.

    Parameters
    ----------
    data : path of an energy CSV, EnergyLog, mapping with keys t/kinetic/potential/total
        (and optionally strain/gravity/pull), or (n_rows, 4) or (n_rows, 7) array

    Returns
    -------
    dict of str to (n_rows,) float64
    """
    if isinstance(data, EnergyLog):
        return data.as_dict()
    if isinstance(data, str | os.PathLike):
        return read_energy_csv(data)
    if isinstance(data, Mapping):
        keys = ENERGY_HEADER_SPLIT.split(",") if all(
            k in data for k in ("strain", "gravity", "pull")) else ENERGY_HEADER.split(",")
        return {k: np.asarray(data[k], dtype=np.float64) for k in keys}
    a = np.asarray(data, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] not in _WIDTHS:
        raise ValueError(f"energy rows must have shape (n, 4) or (n, 7), got {a.shape}")
    return {name: a[:, i] for i, name in enumerate(_WIDTHS[a.shape[1]].split(","))}
