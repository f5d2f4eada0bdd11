"""The viewer's energy history and plots (no viser): what is sampled after each step, which
series the panel draws, and each plot's y axis (range, ticks and their labels; re-exported
by :mod:`fem3d.app.viewer.logic`).

The y axes are computed here rather than left to uPlot: its automatic range shrinks to the
data, so a scene at rest showed round-off (T ~ 1e-21) stretched over the whole plot, and its
tick labels keep three decimals, so every tick of such a range read "0".
"""

from __future__ import annotations

import collections
import dataclasses
import math

import numpy as np

__all__ = ["ENERGY_PLOTS", "HISTORY_COLUMNS", "SPAN_OWN", "SPAN_SCENE", "EnergyHistory", "YAxis",
           "tick_labels", "y_axis"]

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

#: The smallest y span of a plot, relative to the largest magnitude in its own kept history
#: (:data:`SPAN_OWN`) and to the scene's energy scale (:data:`SPAN_SCENE`: the largest |T|,
#: |strain|, |gravity|, |T+V| kept; the pull springs' energy is left out, it would flatten
#: the rest). At rest a plot is then a flat line on a readable scale, not round-off
#: stretched over its height.
SPAN_OWN = 1e-3
SPAN_SCENE = 1e-6
_SCENE_COLUMNS = ("kinetic", "strain", "gravity", "total")


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
        self._array: np.ndarray | None = None  # the rows as an array, until the next change

    def __len__(self) -> int:
        return len(self._rows)

    def clear(self) -> None:
        self._rows.clear()
        self._array = None

    def _as_array(self) -> np.ndarray:
        """(n, 7) float64 rows (kept until the next change: a panel update reads them twice)."""
        if self._array is None:
            self._array = np.asarray(self._rows, dtype=np.float64)
        return self._array

    def append(
        self, t: float, kinetic: float, potential: float, total: float, pull: float = 0.0,
        gravity: float = 0.0,
    ) -> None:
        """One sample; ``gravity`` is gravity's part of ``potential`` (the rest: strain)."""
        p, g = float(potential), float(gravity)
        self._rows.append(
            (float(t), float(kinetic), p, float(total), float(pull), p - g, g)
        )
        self._array = None

    def plot_series(self, seconds: float, n: int = 400) -> tuple[np.ndarray, ...]:
        """``(x, *series)`` of the last ``seconds`` for :data:`ENERGY_PLOTS`, in its order
        (as :meth:`recent`: at most ``n`` real samples, ``x <= 0``)."""
        if not self._rows:
            return tuple(np.zeros(0) for _ in range(len(ENERGY_PLOTS) + 1))
        a = self._as_array()
        a = a[a[:, 0] >= a[-1, 0] - seconds]
        k = max(1, math.ceil(a.shape[0] / int(n)))
        a = a[::-1][::k][::-1]  # keep the newest sample
        cols = [a[:, HISTORY_COLUMNS.index(key)] for key, _l, _c in ENERGY_PLOTS]
        return (np.ascontiguousarray(a[:, 0] - a[-1, 0]),
                *(np.ascontiguousarray(c) for c in cols))

    def peaks(self) -> tuple[tuple[float, ...], float]:
        """The largest magnitude of each plot's series over the kept history (in
        :data:`ENERGY_PLOTS`' order) and the scene's energy scale (:data:`SPAN_SCENE`); zeros
        for an empty history."""
        if not self._rows:
            return tuple(0.0 for _ in ENERGY_PLOTS), 0.0
        a = np.abs(self._as_array())
        a[~np.isfinite(a)] = 0.0
        top = a.max(axis=0)
        col = HISTORY_COLUMNS.index
        return (tuple(float(top[col(k)]) for k, _l, _c in ENERGY_PLOTS),
                float(max(top[col(k)] for k in _SCENE_COLUMNS)))

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


# --------------------------------------------------------------------------------------
# y axes
# --------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class YAxis:
    """A plot's y range and its ticks with their labels (what the panel sends to uPlot).

    Attributes
    ----------
    lo, hi : float
        The range.
    ticks : tuple of float
        Multiples of the tick step in ``[lo, hi]`` (both ends included).
    labels : tuple of str
        One per tick, all different.
    """

    lo: float
    hi: float
    ticks: tuple[float, ...]
    labels: tuple[str, ...]

    def scale(self) -> dict[str, object]:
        """The uPlot scale (a fixed range)."""
        return {"auto": False, "range": [self.lo, self.hi]}

    def axis(self) -> dict[str, object]:
        """The uPlot axis: its ticks, their labels and room for the longest."""
        width = max(len(label) for label in self.labels)
        return {"splits": list(self.ticks), "values": list(self.labels),
                "size": max(40, 16 + 7 * width)}

    def holds(self, lo: float, hi: float, span: float) -> bool:
        """True when ``[lo, hi]`` fits and a span of ``span`` would not be much tighter
        (the axis then stays: a new one rebuilds the page's chart)."""
        width = self.hi - self.lo
        return self.lo <= lo and hi <= self.hi and span <= width <= 4.0 * span


def _nice_step(raw: float) -> float:
    """The smallest 1, 2 or 5 times a power of ten that is >= ``raw`` (> 0)."""
    e = math.floor(math.log10(raw))
    for m in (1.0, 2.0, 5.0, 10.0):
        if m * 10.0**e >= raw * (1.0 - 1e-12):
            return m * 10.0**e
    return 10.0 ** (e + 1)  # pragma: no cover - unreachable


def _fits(labels: list[str], ticks: np.ndarray, step: float) -> bool:
    return all(abs(float(s) - t) <= 0.01 * step for s, t in zip(labels, ticks, strict=True))


def _compact(label: str) -> str:
    """``1.5e-04`` -> ``1.5e-4``, ``2e+09`` -> ``2e9``; ``-0`` -> ``0``."""
    if "e" in label:
        mant, exp = label.split("e")
        label = f"{mant}e{int(exp)}"
    return "0" if float(label) == 0.0 else label


def tick_labels(ticks: np.ndarray, step: float) -> tuple[str, ...]:
    """Labels for ticks ``step`` apart: as few digits as keep each within 1 % of a step of
    its tick (so no two read the same); fixed notation for magnitudes in [1e-3, 1e5) that
    need at most four decimals, else scientific (``2.5e-10``)."""
    ticks = np.asarray(ticks, dtype=np.float64)
    big = float(np.abs(ticks).max()) if ticks.size else 0.0
    if big == 0.0:
        return tuple("0" for _ in ticks)
    if 1e-3 <= big < 1e5:
        for d in range(5):
            labels = [f"{t:.{d}f}" for t in ticks]
            if _fits(labels, ticks, step):
                return tuple(_compact(s) for s in labels)
    for d in range(16):
        labels = [f"{t:.{d}e}" for t in ticks]
        if _fits(labels, ticks, step):
            break
    return tuple(_compact(s) for s in labels)


def y_axis(y: np.ndarray, peak: float, scene: float, current: YAxis | None = None,
           intervals: int = 3) -> YAxis:
    """The y axis of one energy plot.

    Parameters
    ----------
    y : (n,) float
        The values shown (non-finite ones are ignored).
    peak : float
        The largest magnitude in the plot's kept history.
    scene : float
        The scene's energy scale (:meth:`EnergyHistory.peaks`).
    current : YAxis, optional
        The axis shown now: kept while the values fit and would not need a much tighter one.
    intervals : int
        About how many tick intervals the range has.

    Returns
    -------
    YAxis
        A range that holds the values, at least ``max(SPAN_OWN peak, SPAN_SCENE scene)``
        wide (1 when everything is zero), starting at 0 for values that are all >= 0 (ending
        at 0 for values all <= 0), on multiples of a 1-2-5 tick step.
    """
    y = np.asarray(y, dtype=np.float64)
    y = y[np.isfinite(y)]
    lo_d, hi_d = (float(y.min()), float(y.max())) if y.size else (0.0, 0.0)
    span = max(hi_d - lo_d, SPAN_OWN * peak, SPAN_SCENE * scene)
    if span == 0.0:
        span = max(abs(hi_d), 1.0)
    if current is not None and current.holds(lo_d, hi_d, span):
        return current
    mid, half = 0.5 * (lo_d + hi_d), 0.6 * span  # 10 % room on each side
    lo, hi = mid - half, mid + half
    if lo_d >= 0.0 > lo:
        lo, hi = 0.0, hi - lo
    elif hi_d <= 0.0 < hi:
        lo, hi = lo - hi, 0.0
    step = _nice_step((hi - lo) / intervals)
    k = np.arange(math.floor(lo / step + 1e-9), math.ceil(hi / step - 1e-9) + 1)
    ticks = k * step
    ticks[k == 0] = 0.0
    return YAxis(float(ticks[0]), float(ticks[-1]), tuple(float(t) for t in ticks),
                 tick_labels(ticks, step))
