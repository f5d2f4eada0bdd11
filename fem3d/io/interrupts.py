"""SIGINT / SIGTERM while a run steps (``fem3d run``, ``fem3d resume``; in one process or on
MPI ranks): the run finishes the step, saves a checkpoint, says how to continue in one line
(:func:`interrupted_message`) and exits with :data:`EXIT_INTERRUPTED`.

One process (:class:`fem3d.app.run.RunLoop`): a second signal abandons the step in
progress (the state stays at the last finished step). MPI ranks
(:class:`fem3d.parallel.run.DistributedLoop`): every rank finishes its step, whatever it
was sent (a rank that left a step would leave the others waiting in a collective call);
the ranks agree on the first signal at the step's end (docs/parallel.md: what Open MPI's
``mpiexec`` sends its ranks).
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

__all__ = ["EXIT_INTERRUPTED", "Interrupts", "interrupted_message"]

#: Exit status of an interrupted run (128 + SIGINT).
EXIT_INTERRUPTED = 130


class Interrupts:
    """Signal handlers that remember a signal came (:attr:`signum`: the last); with
    ``abandon``, a second one while :attr:`in_step` raises :class:`KeyboardInterrupt`
    (the step is abandoned).

    Parameters
    ----------
    signals : sequence of signal.Signals
        The signals caught (default SIGINT and SIGTERM).
    abandon : bool
        A second signal abandons the step in progress (one process only).
    """

    def __init__(self, signals: Sequence[signal.Signals] = (signal.SIGINT, signal.SIGTERM),
                 *, abandon: bool = True) -> None:
        self.signals = tuple(signals)
        self.abandon = abandon
        self.signum: int | None = None
        self.in_step = False

    def __call__(self, signum: int, frame: Any) -> None:
        first = self.signum is None
        self.signum = signum
        if not first and self.abandon and self.in_step:
            raise KeyboardInterrupt

    @staticmethod
    def name_of(signum: int | None) -> str:
        """``"SIGINT"`` of ``signal.SIGINT`` (``""`` for None)."""
        return signal.Signals(signum).name if signum is not None else ""

    @property
    def name(self) -> str:
        """The signal's name (``""``: none came)."""
        return self.name_of(self.signum)

    @contextlib.contextmanager
    def installed(self) -> Iterator[Interrupts]:
        """The handlers in place for the ``with`` block (the main thread only: signals are
        delivered there), the previous ones after it."""
        if threading.current_thread() is not threading.main_thread():
            yield self
            return
        old = {s: signal.signal(s, self) for s in self.signals}
        try:
            yield self
        finally:
            for s, h in old.items():
                signal.signal(s, h)


def interrupted_message(name: str, step: int, t: float, checkpoint: Path, out: Path) -> str:
    """The line an interrupted run ends with (after ``fem3d run: ``)."""
    return (f"interrupted by {name} at step {step} (t = {t:.4g}); checkpoint {checkpoint}; "
            f"continue with: fem3d resume {out}")
