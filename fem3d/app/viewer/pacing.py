"""When the viewer's simulation thread steps (no viser): only while a browser page watches,
paced so that simulated time advances no faster than wall time.

:class:`RealtimePacer` keeps simulated time with wall time; :class:`StepGate` adds the
watchers: with no page connected the simulation thread idles on an event (no CPU), and the
first page to connect sees the scene from where it was left (t = 0 for the first page
ever). Both take the clock as an argument, so they are unit-tested without a browser and
without sleeping.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Hashable

from fem3d.errors import ParameterError

__all__ = ["RealtimePacer", "StepGate"]


class RealtimePacer:
    """Keep simulated time advancing about as fast as wall time.

    Parameters
    ----------
    max_lag : float
        When the simulation falls behind wall time by more than this (seconds), the
        pacer re-anchors instead of letting it race to catch up.
    enabled : bool
        When False, :meth:`delay` is always 0 (run as fast as possible).
    rate : float
        Simulated seconds per wall-clock second (``< 1``: slow motion).
    """

    def __init__(self, max_lag: float = 0.1, *, enabled: bool = True, rate: float = 1.0) -> None:
        if not rate > 0:
            raise ParameterError(f"time scale must be positive, got {rate}")
        self.max_lag = float(max_lag)
        self.enabled = enabled
        self.rate = float(rate)
        self._anchor: tuple[float, float] | None = None

    def reset(self) -> None:
        """Forget the anchor (after a pause, a reset, a scene switch, an idle spell)."""
        self._anchor = None

    def delay(self, t_sim: float, now: float) -> float:
        """Seconds to wait before the next step.

        Parameters
        ----------
        t_sim : float
            Current simulated time (s).
        now : float
            Current wall-clock time (s, monotonic).
        """
        if not self.enabled:
            return 0.0
        if self._anchor is None:
            self._anchor = (t_sim, now)
            return 0.0
        t0, w0 = self._anchor
        d = (w0 + (t_sim - t0) / self.rate) - now
        if d < -self.max_lag:
            self._anchor = (t_sim, now)
            return 0.0
        return max(d, 0.0)


class StepGate:
    """Whether and when the simulation thread steps: only while a page is connected.

    Parameters
    ----------
    pacer : RealtimePacer
        Paces the steps while watched (re-anchored whenever watching starts again, so an
        idle spell is never caught up).
    wake : threading.Event
        Set when a page connects (the idle simulation thread waits on it).
    unwatched : bool
        Step with no page connected too (scripts and tests that drive the viewer from
        Python).
    clock : callable
        Monotonic wall clock in seconds (injected by tests).
    """

    def __init__(self, pacer: RealtimePacer, wake: threading.Event, *, unwatched: bool = False,
                 clock: Callable[[], float] = time.perf_counter) -> None:
        self.pacer = pacer
        self.unwatched = bool(unwatched)
        self._wake = wake
        self._clock = clock
        self._lock = threading.Lock()
        self._clients: set[Hashable] = set()
        self._idle = True  # no step since watching (re)started: re-anchor the pacer

    @property
    def watchers(self) -> int:
        """The pages connected now."""
        with self._lock:
            return len(self._clients)

    def connect(self, client: Hashable) -> None:
        """A page connected (viser's thread): wake the simulation thread."""
        with self._lock:
            self._clients.add(client)
        self._wake.set()

    def disconnect(self, client: Hashable) -> None:
        """A page left; with none left the simulation thread idles after its current step."""
        with self._lock:
            self._clients.discard(client)

    def next_wait(self, t_sim: float, running: bool) -> float | None:
        """What the simulation thread does next (called by that thread only).

        Parameters
        ----------
        t_sim : float
            Current simulated time (s).
        running : bool
            False while paused or stopped by an error.

        Returns
        -------
        float or None
            ``None``: nobody watches, idle until woken (a page connects, a command, stop);
            ``0.0``: step now (also when a step costs more than its dt: as fast as it
            can); ``> 0``: seconds until the next step is due; ``inf`` while paused
            (nothing to step: the caller wakes for commands and its display updates).
        """
        if not (self.unwatched or self.watchers):
            self._idle = True
            return None
        if self._idle:
            self.pacer.reset()
            self._idle = False
        if not running:
            return math.inf
        return self.pacer.delay(t_sim, self._clock())
