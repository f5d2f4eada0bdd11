"""The energy log of a run: ``energy.csv`` with header ``t,kinetic,potential,total``.

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

__all__ = ["ENERGY_HEADER", "EnergyLog", "energy_columns", "read_energy_csv"]

#: Header line of ``energy.csv`` (the column names).
ENERGY_HEADER = "t,kinetic,potential,total"


class EnergyLog:
    """Energy history of a run, saved as ``energy.csv``.

    Parameters
    ----------
    path : str or PathLike, optional
        Default file of :meth:`write`.
    """

    def __init__(self, path: PathLike | None = None) -> None:
        self.path = None if path is None else Path(path)
        self._rows: list[tuple[float, float, float, float]] = []

    def append(
        self, t: float, kinetic: float, potential: float, total: float | None = None
    ) -> None:
        """Add one row; ``total`` defaults to ``kinetic + potential``."""
        k, p = float(kinetic), float(potential)
        self._rows.append((float(t), k, p, k + p if total is None else float(total)))

    def __len__(self) -> int:
        return len(self._rows)

    @classmethod
    def from_array(cls, rows: np.ndarray, path: PathLike | None = None) -> EnergyLog:
        """A log holding ``rows`` ``(n_rows, 4)`` (e.g. from a checkpoint), values exact."""
        a = np.asarray(rows, dtype=np.float64).reshape(-1, 4)
        log = cls(path)
        log._rows = [tuple(float(x) for x in row) for row in a]
        return log

    def as_array(self) -> np.ndarray:
        """Rows ``(t, kinetic, potential, total)`` as an ``(n_rows, 4)`` float64 array."""
        return np.array(self._rows, dtype=np.float64).reshape(-1, 4)

    def as_dict(self) -> dict[str, np.ndarray]:
        """Columns ``t``, ``kinetic``, ``potential``, ``total`` as ``(n_rows,)`` arrays."""
        a = self.as_array()
        return {name: a[:, i].copy() for i, name in enumerate(ENERGY_HEADER.split(","))}

    def to_csv(self) -> str:
        """CSV text with header ``t,kinetic,potential,total`` (``repr`` precision)."""
        out = [ENERGY_HEADER]
        out += [",".join(repr(v) for v in row) for row in self._rows]
        return "\n".join(out) + "\n"

    def write(self, path: PathLike | None = None) -> Path:
        """Write the CSV atomically to ``path`` (default: the constructor's path)."""
        target = path if path is not None else self.path
        if target is None:
            raise ValueError("EnergyLog.write needs a path")
        return atomic_write(target, self.to_csv())


def read_energy_csv(path: PathLike) -> dict[str, np.ndarray]:
    """Read an ``energy.csv``: columns ``t``, ``kinetic``, ``potential``, ``total``."""
    path = Path(path)
    with open(path, encoding="utf-8") as fh:
        header = fh.readline().strip()
        if header != ENERGY_HEADER:
            raise InputError(
                f"expected header {ENERGY_HEADER!r}, got {header!r}", path=path, line=1
            )
        rows = []
        for lineno, line in enumerate(fh, start=2):
            if not line.strip():
                continue
            parts = line.split(",")
            try:
                if len(parts) != 4:
                    raise ValueError
                rows.append([float(x) for x in parts])
            except ValueError:
                raise InputError(
                    "expected 4 comma-separated numbers", path=path, line=lineno
                ) from None
    a = np.array(rows, dtype=np.float64).reshape(-1, 4)
    return {name: a[:, i].copy() for i, name in enumerate(ENERGY_HEADER.split(","))}


def energy_columns(data: Any) -> dict[str, np.ndarray]:
    """Columns ``t``, ``kinetic``, ``potential``, ``total`` of an energy history.

    Parameters
    ----------
    data : path of an energy CSV, EnergyLog, mapping with keys t/kinetic/potential/total,
        or (n_rows, 4) array

    Returns
    -------
    dict of str to (n_rows,) float64
    """
    if isinstance(data, EnergyLog):
        return data.as_dict()
    if isinstance(data, str | os.PathLike):
        return read_energy_csv(data)
    if isinstance(data, Mapping):
        return {
            k: np.asarray(data[k], dtype=np.float64) for k in ("t", "kinetic", "potential", "total")
        }
    a = np.asarray(data, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 4:
        raise ValueError(f"energy rows must have shape (n, 4), got {a.shape}")
    return {name: a[:, i] for i, name in enumerate(ENERGY_HEADER.split(","))}
