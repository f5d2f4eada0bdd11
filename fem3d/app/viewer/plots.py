"""The viewer's energy history and plots (no viser): what is sampled after each step and
which series the panel draws (re-exported by :mod:`fem3d.app.viewer.logic`)."""

from __future__ import annotations

import collections
import math

import numpy as np

__all__ = ["ENERGY_PLOTS", "HISTORY_COLUMNS", "EnergyHistory"]

#: The energy plots: (history column, label, colour). Each has its own y scale: the pull
#: spring's energy (up to 1e9 on the bunny) must not flatten the elastic energies (1e-6 at
#: rest), nor gravity's potential the strain.
ENERGY_PLOTS = (
    ("kinetic", "T (kinetic)", "#1f77b4"),
    ("strain", "strain (elastic)", "#ff7f0e"),
    ("gravity", "gravity (potential)", "#8c564b"),
    ("total", "T+V (V = strain + gravity)", "#2ca02c"),
    ("pull", "pull spring", "#d62728"),
)

#: Columns of :class:`EnergyHistory`'s rows.
HISTORY_COLUMNS = ("t", "kinetic", "potential", "total", "pull", "strain", "gravity")


class EnergyHistory:
    """Rolling history of (t, kinetic, potential, total, pull, strain, gravity) for the
    energy plots (``potential = strain + gravity``; without a split, all of it is strain).

    Parameters
    ----------
    maxlen : int
        Number of samples kept.
    """

    def __init__(self, maxlen: int = 4000) -> None:
        self._rows: collections.deque[tuple[float, ...]] = collections.deque(maxlen=maxlen)

    def __len__(self) -> int:
        return len(self._rows)

    def clear(self) -> None:
        self._rows.clear()

    def append(
        self, t: float, kinetic: float, potential: float, total: float, pull: float = 0.0,
        gravity: float = 0.0,
    ) -> None:
        """One sample; ``gravity`` is gravity's part of ``potential`` (the rest: strain)."""
        p, g = float(potential), float(gravity)
        self._rows.append(
            (float(t), float(kinetic), p, float(total), float(pull), p - g, g)
        )

    def plot_series(self, seconds: float, n: int = 400) -> tuple[np.ndarray, ...]:
        """``(x, *series)`` of the last ``seconds`` for :data:`ENERGY_PLOTS`, in its order
        (as :meth:`recent`: at most ``n`` real samples, ``x <= 0``)."""
        if not self._rows:
            return tuple(np.zeros(0) for _ in range(len(ENERGY_PLOTS) + 1))
        a = np.asarray(self._rows, dtype=np.float64)
        a = a[a[:, 0] >= a[-1, 0] - seconds]
        k = max(1, math.ceil(a.shape[0] / int(n)))
        a = a[::-1][::k][::-1]  # keep the newest sample
        cols = [a[:, HISTORY_COLUMNS.index(key)] for key, _l, _c in ENERGY_PLOTS]
        return (np.ascontiguousarray(a[:, 0] - a[-1, 0]),
                *(np.ascontiguousarray(c) for c in cols))

    def window(self, seconds: float | None = None) -> tuple[np.ndarray, ...]:
        """The samples of the last ``seconds`` of simulated time.

        Returns
        -------
        (t, kinetic, potential, total) : four (n,) float64 arrays
            ``n >= 1``: an empty history gives one sample of zeros, so the plot always has
            data.
        """
        if not self._rows:
            return tuple(np.zeros(1) for _ in range(4))
        a = np.asarray(self._rows, dtype=np.float64)
        if seconds is not None:
            a = a[a[:, 0] >= a[-1, 0] - seconds]
        return tuple(np.ascontiguousarray(a[:, i]) for i in range(4))

    def recent(self, seconds: float, n: int = 400) -> tuple[np.ndarray, ...]:
        """The real samples of the last ``seconds``, at most ``n`` of them (every k-th).

        Nothing is invented: before the first sample (after a reset) the plot stays
        empty, and between samples uPlot draws straight lines.

        Returns
        -------
        (x, kinetic, potential, total, pull) : five (m,) float64 arrays
            ``x = t - t_newest`` (seconds before the newest sample, ``<= 0``); ``m = 0``
            for an empty history.
        """
        if not self._rows:
            return tuple(np.zeros(0) for _ in range(5))
        a = np.asarray(self._rows, dtype=np.float64)
        a = a[a[:, 0] >= a[-1, 0] - seconds]
        k = max(1, math.ceil(a.shape[0] / int(n)))
        a = a[::-1][::k][::-1]  # keep the newest sample
        x = a[:, 0] - a[-1, 0]
        return (np.ascontiguousarray(x), *(np.ascontiguousarray(a[:, i]) for i in range(1, 5)))

    def latest(self) -> tuple[float, ...] | None:
        """The newest (t, kinetic, potential, total, pull), or None."""
        return self._rows[-1][:5] if self._rows else None

    def latest_split(self) -> tuple[float, ...] | None:
        """The newest (t, kinetic, potential, total, pull, strain, gravity), or None."""
        return self._rows[-1] if self._rows else None

    def rows(self) -> list[tuple[float, float, float, float]]:
        """(t, kinetic, potential, total) per sample (the split: :meth:`latest_split`)."""
        return [r[:4] for r in self._rows]
