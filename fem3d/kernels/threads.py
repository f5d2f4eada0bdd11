"""How many OpenMP threads each family of threaded C kernels runs on, chosen from measured times.

The threaded C kernels (the AMG-PCG kernels of :mod:`fem3d.solve.sparse_threads`, the fused
assemblies of :mod:`fem3d.kernels.dispatch`) give the same bits on any number of threads, so
the count is a matter of speed alone, and the speed differs by kernel: on a quiet 2-vCPU VM
the AMG setup's Galerkin products (compute-bound) gained from a second thread while the
mat-vecs, CG and the Newton matrices' assembly (memory-bound) lost; on a loaded machine
nearly everything loses (a barrier waits for a descheduled thread). The kernels of one
solve (sweeps, mat-vecs, dot products) share one count, measured on whole PCG rounds: measured
apart, mat-vecs on two threads looked 1.1-1.3x faster, yet CG with them between one-thread
sweeps took 1.5x as long (each vector moves between the cores' caches twice per round). So
every
family gets its own count (:data:`FAMILIES`), passed to the C kernels (their ``n_threads``
argument: OpenMP's ``num_threads`` clause), chosen once per process:

* **forced** by the environment variable :data:`ENV` (``FEM3D_THREADS``): ``2`` (every
  family), ``solve=1,products=2`` (those families; the others measured) or ``auto``
  (the default: measure all);
* else **measured** on the real data: the work runs on one thread and on all available ones,
  alternately, ``repeats`` times each (:func:`measure`: a few PCG rounds and a sample of a
  product at an AMG setup; :func:`adaptive`: the first calls of a fused
  assembly themselves, no extra work), and the family keeps the faster count (more threads
  only when at least :data:`MARGIN` faster: each one costs a core the other processes on the
  machine could use);
* one thread when only one is available.

``OMP_NUM_THREADS`` (OpenMP's count, :func:`available_threads`) caps every count, a forced one
too. The choices are logged (logger ``fem3d.threads``, INFO), listed by :func:`choices` and
printed by ``fem3d run --profile`` (:func:`report`). Only kernels that run threaded at all ask
(systems above the AMG's ``threads_min_rows``, meshes above
:data:`fem3d.kernels.schedule.PARALLEL_MIN_TETS` tets), so small scenes measure nothing.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from fem3d.errors import InputError
from fem3d.kernels.backend import c_extension

__all__ = ["ENV", "FAMILIES", "MARGIN", "Choice", "adaptive", "available_threads", "choices",
           "forced_threads", "mark", "measure", "report", "reset", "settled_threads"]

#: The environment variable forcing thread counts (see the module's docstring).
ENV = "FEM3D_THREADS"

#: The kernel families with a count of their own, and how a report names them.
FAMILIES: dict[str, str] = {
    "solve": "AMG-PCG solve (Gauss-Seidel sweeps, mat-vecs, dot products)",
    "products": "AMG setup Galerkin products",
    "assembly": "fused assembly",
}

#: More threads are kept only when they take at most ``1 - MARGIN`` of one thread's time.
MARGIN = 0.05
#: :func:`measure` runs more rounds (up to :data:`MAX_ROUNDS`) while its trials took less than
#: this many seconds in all: a best of many short trials is steadier on a busy machine.
MIN_MEASURE_SECONDS = 0.05
MAX_ROUNDS = 10
#: Measuring stops after the first round (:func:`measure`) or pair of calls (:func:`adaptive`)
#: when all threads took more than this many times one thread's time (a loaded machine: a
#: clear loss, not worth confirming at that price). Only a loss ends it early, never a gain.
CLEAR_LOSS = 2.0

_log = logging.getLogger("fem3d.threads")


@dataclass(frozen=True)
class Choice:
    """The thread count of one kernel (family, or one fused assembly kernel).

    Attributes
    ----------
    key : str
        What runs on it: a family of :data:`FAMILIES`, or ``"assembly <module>.<kernel>"``.
    family : str
        Its family.
    threads : int
        The count its kernels get.
    available : int
        OpenMP's count when it was chosen (``OMP_NUM_THREADS``).
    how : str
        ``"measured"``, ``"forced"`` (:data:`ENV`) or ``"single"`` (one thread available).
    seconds : dict
        The best measured seconds per thread count (``"measured"`` only).
    note : str
        What forced it (``"forced"`` only).
    """

    key: str
    family: str
    threads: int
    available: int
    how: str
    seconds: dict[int, float] = field(default_factory=dict)
    note: str = ""

    def line(self) -> str:
        """One line for a log or a profile, e.g. ``AMG Gauss-Seidel sweeps: 1 of 2 threads
        (measured 4.10 ms on 1, 5.30 ms on 2: 2 threads 0.77x)``."""
        head = f"{_display_name(self.key)}: {self.threads} of {self.available} thread" + \
            ("s" if self.available > 1 else "")
        if self.how == "forced":
            return f"{head} (forced by {self.note})"
        if self.how == "single":
            return f"{head} (one available: OMP_NUM_THREADS or the machine)"
        one, many = self.seconds[1], self.seconds[self.available]
        return (f"{head} (measured {1e3 * one:.2f} ms on 1, {1e3 * many:.2f} ms on "
                f"{self.available}: {self.available} threads {one / many:.2f}x)")


def _display_name(key: str) -> str:
    """How a report names ``key``: its family's name, then what follows the family in the key
    (``"assembly neo_hookean.hessian"`` -> ``"fused assembly neo_hookean.hessian"``)."""
    family, _, rest = key.partition(" ")
    return FAMILIES[family] + (f" {rest}" if rest else "")


_CHOICES: dict[str, Choice] = {}
_TRIALS: dict[str, list[tuple[int, float]]] = {}
#: When (a count of events: choices made, measurements begun) each choice was made and each
#: pending measurement began; :func:`mark` reads the count.
_WHEN: dict[str, int] = {}
_EVENTS = [0]


def _event(key: str) -> None:
    _EVENTS[0] += 1
    _WHEN[key] = _EVENTS[0]


def available_threads() -> int:
    """OpenMP's thread count (``OMP_NUM_THREADS``, else the cores); 1 without the C extension
    or OpenMP."""
    ext = c_extension()
    return max(1, int(ext.max_threads())) if ext is not None else 1


def _parse_count(text: str, value: str) -> int | None:
    text = text.strip()
    if text == "auto":
        return None
    if not text.isdigit() or int(text) < 1:
        raise InputError(f"{ENV}={value!r}: a thread count must be 'auto' or a whole number "
                         f">= 1, got {text!r}")
    return int(text)


def settled_threads(family: str) -> int | None:
    """The count of ``family`` when it is chosen (measured before in this process, forced,
    or one thread available), else None; measures nothing."""
    choice = _settled(family, family)
    return None if choice is None else choice.threads


def forced_threads(family: str) -> int | None:
    """The count :data:`ENV` forces on ``family`` (not capped), or None (measure it).

    Raises
    ------
    fem3d.errors.InputError
        (a ValueError) One line naming the variable when its value is not ``auto``, a count, or
        ``family=count`` pairs of known families separated by commas.
    """
    value = os.environ.get(ENV, "").strip()
    if not value:
        return None
    if "=" not in value:
        return _parse_count(value, value)
    forced: int | None = None
    for item in value.split(","):
        name, sep, count = item.partition("=")
        name = name.strip()
        if not sep or name not in FAMILIES:
            raise InputError(f"{ENV}={value!r}: expected 'auto', a count, or family=count "
                             f"pairs separated by commas (families: {', '.join(FAMILIES)})")
        if name == family:
            forced = _parse_count(count, value)
    return forced


def _decide(key: str, family: str, times: dict[int, float], available: int) -> Choice:
    many = available if times[available] <= (1.0 - MARGIN) * times[1] else 1
    return _record(Choice(key, family, many, available, "measured", dict(times)))


def _record(choice: Choice) -> Choice:
    _CHOICES[choice.key] = choice
    _TRIALS.pop(choice.key, None)
    _event(choice.key)
    _log.info("threads: %s", choice.line())
    return choice


def _settled(key: str, family: str) -> Choice | None:
    """The choice of ``key`` when made or when nothing is left to measure (forced, one
    thread available); None while it is to be measured."""
    if family not in FAMILIES:
        raise ValueError(f"unknown kernel family {family!r}; known: {', '.join(FAMILIES)}")
    choice = _CHOICES.get(key)
    if choice is not None:
        return choice
    available = available_threads()
    forced = forced_threads(family)
    if forced is not None:
        return _record(Choice(key, family, min(forced, available), available, "forced",
                              note=f"{ENV}={os.environ.get(ENV, '').strip()}"))
    if available == 1:
        return _record(Choice(key, family, 1, 1, "single"))
    return None


def measure(family: str, trial: Callable[[int], object], *, repeats: int = 3) -> int:
    """The thread count of ``family``, measured the first time in the process (then cached:
    :func:`reset` forgets it).

    Parameters
    ----------
    family : str
        One of :data:`FAMILIES` (:data:`ENV` may force its count).
    trial : callable
        ``trial(n)`` runs a short representative piece of the family's work on ``n`` threads
        (any result is ignored). Called once to warm up, then ``repeats`` times (more, up to
        :data:`MAX_ROUNDS`, while the trials took under :data:`MIN_MEASURE_SECONDS` in all;
        fewer when all threads lose clearly, :data:`CLEAR_LOSS`) on one thread and on all
        available ones, alternately; the best time of each counts.
    repeats : int, optional

    Returns
    -------
    int
        The count to pass to the family's kernels.
    """
    choice = _settled(family, family)
    if choice is not None:
        return choice.threads
    available = available_threads()
    trial(available)
    times = {1: float("inf"), available: float("inf")}
    rounds, spent = 0, 0.0
    while rounds < max(1, repeats) or (spent < MIN_MEASURE_SECONDS and rounds < MAX_ROUNDS):
        for n in (1, available):
            t0 = time.perf_counter()
            trial(n)
            seconds = time.perf_counter() - t0
            times[n] = min(times[n], seconds)
            spent += seconds
        rounds += 1
        if times[available] > CLEAR_LOSS * times[1]:
            break
    return _decide(family, family, times, available).threads


def adaptive(key: str, family: str, run: Callable[[int], object], *, repeats: int = 2
             ) -> object:
    """``run(n)`` on the chosen count ``n`` of ``key``; while it is being measured, the calls
    themselves are the measurement (alternately one thread and all available ones,
    ``repeats`` times each, or once each on a :data:`CLEAR_LOSS`, then the faster is kept).
    Returns ``run``'s result."""
    choice = _settled(key, family)
    if choice is not None:
        return run(choice.threads)
    available = available_threads()
    if key not in _TRIALS:
        _event(key)
    trials = _TRIALS.setdefault(key, [])
    n = 1 if len(trials) % 2 == 0 else available
    t0 = time.perf_counter()
    result = run(n)
    trials.append((n, time.perf_counter() - t0))
    if len(trials) % 2 == 0:
        times = {c: min(s for m, s in trials if m == c) for c in (1, available)}
        if len(trials) >= 2 * max(1, repeats) or times[available] > CLEAR_LOSS * times[1]:
            _decide(key, family, times, available)
    return result


def choices() -> list[Choice]:
    """The choices made in this process so far, in the order made."""
    return list(_CHOICES.values())


def mark() -> int:
    """A point in time for :func:`report`'s ``since``."""
    return _EVENTS[0]


def report(since: int = 0) -> str:
    """The choices made after ``since`` (a :func:`mark`; 0: all) as lines, then the fused
    assemblies whose measurement began after it and goes on (too few calls yet); empty when
    there is none."""
    lines = [f"  {c.line()}" for c in choices() if _WHEN[c.key] > since]
    for key, trials in _TRIALS.items():
        if _WHEN[key] <= since:
            continue
        runs = ", ".join(f"{1e3 * seconds:.2f} ms on {n}" for n, seconds in trials)
        lines.append(f"  {_display_name(key)}: still measuring after {len(trials)} call"
                     f"{'s' if len(trials) > 1 else ''} ({runs})")
    if not lines:
        return ""
    return "\n".join([f"threads per kernel family (fem3d.kernels.threads; {ENV} forces them):",
                      *lines])


def reset() -> None:
    """Forget every choice (the next threaded kernels measure, or read :data:`ENV`, again)."""
    _CHOICES.clear()
    _TRIALS.clear()
    _WHEN.clear()
