"""``fem3d run --profile``: wall time, CPU time and memory of each stage of a run's start.

The stages are marked where they end by a DEBUG record on the logger ``fem3d.stages``
(:data:`STAGES_LOGGER`; the message is the stage's name): reading the mesh file, validating
it, the scene's arrays, the model's rest shape, sparsity pattern and mass matrix, the reduced
system and the solver's analysis, the simulation's set-up, the outputs' set-up and the first
step. A mark costs one disabled-logger check when nothing listens, so the marks stay in the
code. :class:`StageProfile` listens while a run is profiled: each mark closes a stage, which
gets the wall and CPU seconds (user and system) since the previous mark, the resident memory
at its end and the peak during it (Linux: ``VmRSS``/``VmHWM`` of ``/proc/self/status``, the
peak reset at every mark through ``/proc/self/clear_refs``; elsewhere the process's peak so
far). The first stage runs from the process's start (the interpreter and the imports).

Below the table: the thread count each family of threaded C kernels got during the run and
why (measured times on one and on all threads, or ``FEM3D_THREADS``;
:func:`fem3d.kernels.threads.report`), when a kernel chose one (large systems only; choices
are made once per process, so a later run in the same process reuses them silently).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import sys
import time
from collections.abc import Iterator
from typing import TextIO

from fem3d.kernels.threads import mark, report

__all__ = ["STAGES_LOGGER", "Stage", "StageProfile", "profiled"]

#: The logger whose DEBUG records mark the end of a stage (message: the stage's name).
STAGES_LOGGER = "fem3d.stages"

#: The stage after which a run is stepping (what "time to first step" counts up to).
FIRST_STEP = "first step"


@dataclasses.dataclass(frozen=True)
class Stage:
    """One stage: its name, wall / user / system seconds, resident memory at its end and the
    peak during it (MiB; NaN where the platform does not say)."""

    name: str
    wall: float
    user: float
    system: float
    rss_mib: float
    peak_mib: float


def _process_age() -> float:
    """Seconds since this process started (0 where ``/proc`` does not say)."""
    try:
        with open("/proc/self/stat") as f:
            start_ticks = float(f.read().rsplit(")", 1)[1].split()[19])
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
        return max(0.0, uptime - start_ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError):
        return 0.0


def _memory_mib() -> tuple[float, float]:
    """``(VmRSS, VmHWM)`` of this process in MiB (NaN where unknown)."""
    rss = peak = float("nan")
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    rss = int(line.split()[1]) / 1024
                elif line.startswith("VmHWM:"):
                    peak = int(line.split()[1]) / 1024
    except (OSError, ValueError):
        pass
    return rss, peak


def _reset_peak() -> None:
    """Start a new ``VmHWM`` at the current resident size (Linux >= 4.0; else nothing)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass


class StageProfile(logging.Handler):
    """Collects the stages marked on :data:`STAGES_LOGGER` (see the module's docstring)."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.stages: list[Stage] = []
        # the first stage runs from the process's start: all its CPU time so far
        self._last = (time.perf_counter() - _process_age(), 0.0, 0.0)

    def emit(self, record: logging.LogRecord) -> None:
        self.mark(record.getMessage())

    def mark(self, name: str) -> None:
        """Close the stage ``name`` now."""
        now, t = time.perf_counter(), os.times()
        rss, peak = _memory_mib()
        wall0, user0, sys0 = self._last
        self.stages.append(Stage(name, now - wall0, t.user - user0, t.system - sys0, rss, peak))
        _reset_peak()
        self._last = (now, t.user, t.system)

    def until(self, name: str) -> float:
        """Wall seconds of the stages before the first one called ``name`` (all: none is)."""
        total = 0.0
        for s in self.stages:
            if s.name == name:
                break
            total += s.wall
        return total

    def table(self) -> str:
        """The stages as an aligned text table, with the time to the first step."""
        width = max([len(s.name) for s in self.stages] + [24])
        lines = [f"{'stage':<{width}}  {'wall s':>7}  {'user s':>7}  {'sys s':>6}  "
                 f"{'RSS MiB':>8}  {'peak MiB':>8}"]
        for s in self.stages:
            lines.append(f"{s.name:<{width}}  {s.wall:7.2f}  {s.user:7.2f}  {s.system:6.2f}  "
                         f"{s.rss_mib:8.0f}  {s.peak_mib:8.0f}")
        peak = max((s.peak_mib for s in self.stages), default=float("nan"))
        names = [s.name for s in self.stages]
        if FIRST_STEP in names:
            lines.append(f"{'time to first step':<{width}}  {self.until(FIRST_STEP):7.2f}"
                         f"{'':>36}{peak:8.0f}")
        return "\n".join(lines)


@contextlib.contextmanager
def profiled(enabled: bool = True, out: TextIO | None = None,
             title: str = "fem3d run --profile") -> Iterator[StageProfile | None]:
    """Collect the stages marked inside the block and print their table to ``out`` (stderr)
    when it ends (also on an error). Yields the :class:`StageProfile` (None: not enabled)."""
    if not enabled:
        yield None
        return
    logger = logging.getLogger(STAGES_LOGGER)
    prof = StageProfile()
    prof.mark("start-up (Python, imports)")
    chosen_before = mark()
    saved = (logger.level, logger.propagate)
    logger.addHandler(prof)
    logger.setLevel(logging.DEBUG)
    logger.propagate = False
    try:
        yield prof
    finally:
        stepped = any(st.name == FIRST_STEP for st in prof.stages)
        prof.mark("rest of the run (later steps, outputs)" if stepped else
                  "until the run ended (no step)")
        logger.removeHandler(prof)
        logger.setLevel(saved[0])
        logger.propagate = saved[1]
        policy = report(since=chosen_before)
        print(f"{title}:\n{prof.table()}" + (f"\n{policy}" if policy else ""),
              file=out or sys.stderr, flush=True)
