"""Run ONE benchmark case at ONE size in this process and print one JSON result line.

``python -m bench.worker CASE SIZE REPEATS [BUDGET_S]``

Run by the runner in a fresh subprocess per (case, size) so that the peak resident memory
(``getrusage(RUSAGE_SELF).ru_maxrss``, which sees C/Fortran allocations, unlike tracemalloc)
belongs to that case alone. Protocol: the last stdout line starting with ``BENCH_RESULT `` holds
the JSON record; anything else on stdout/stderr is the case's own chatter.

Timing: ``setup`` (untimed, reported), one warm-up call (JIT compilation, caches; reported as
``first_s``), then up to ``REPEATS`` timed calls, fewer when they would exceed ``BUDGET_S``
(at least one). A warm-up call longer than ``BUDGET_S`` is itself the one sample unless the
case says ``warmup_required``. Reported: median and min of the timed calls.

Memory: ``peak_rss_mb`` is the process peak (``ru_maxrss``: interpreter, libraries, mesh,
setup, calls); ``call_extra_mb`` is the peak during the calls above the RSS after setup
(``VmHWM`` reset through ``/proc/self/clear_refs``), i.e. what the timed work itself
allocates (a factorization's fill, a Hessian's arrays).
"""

from __future__ import annotations

import json
import os
import resource
import statistics
import sys
import time
import traceback

import numpy as np

RESULT_PREFIX = "BENCH_RESULT "


def _rss_mb() -> float:
    """Current resident set size in MiB (Linux /proc; 0 if unknown)."""
    try:
        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[1])
        return pages * resource.getpagesize() / 2**20
    except OSError:
        return 0.0


def _maxrss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def _status_mb(field: str) -> float | None:
    """``VmHWM`` (peak) or ``VmRSS`` of this process from /proc/self/status, MiB."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return None


def _reset_peak() -> bool:
    """Reset ``VmHWM`` to the current RSS (Linux >= 4.0: write 5 to clear_refs)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _check_value(result: object) -> float | None:
    """A number summarising a case's output, to compare rows doing the same work."""
    import scipy.sparse as sp

    if isinstance(result, tuple) and result:
        result = result[0]
    if sp.issparse(result):
        return float(np.linalg.norm(result.data))
    if isinstance(result, np.ndarray):
        return float(np.linalg.norm(result))
    if isinstance(result, float | int | np.floating):
        return float(result)
    return None


def run_case(name: str, size: float, repeats: int, budget_s: float) -> dict:
    """Time one case; the returned record is what the runner stores."""
    from bench import BenchMesh, Skip, load_cases

    cases = load_cases()
    case = cases[name]
    rec: dict = {"case": name, "group": case.group, "library": case.library, "size": size}
    t0 = time.perf_counter()
    mesh = BenchMesh.make(size)
    rec.update(n_tets=mesh.n_tets, n_vertices=mesh.n_vertices, mesh_s=time.perf_counter() - t0)
    base_rss = _rss_mb()
    base_maxrss = _maxrss_mb()
    try:
        t0 = time.perf_counter()
        fn = case.setup(mesh)
        rec["setup_s"] = time.perf_counter() - t0
        if case.group in ("factor", "solve", "analyze"):
            rec["n_dofs"] = int(mesh.system.A.shape[0])
            rec["nnz"] = int(mesh.system.A.nnz)
        # memory of the timed work alone: peak over the calls minus the RSS after setup
        rec["setup_peak_mb"] = _status_mb("VmHWM")
        rec["rss_after_setup_mb"] = _status_mb("VmRSS")
        can_reset = _reset_peak()
        t0 = time.perf_counter()
        out = fn()
        first = time.perf_counter() - t0
        rec["first_s"] = first
        rec["check"] = _check_value(out)
        del out
        if first > budget_s and not case.warmup_required:
            times = [first]  # too slow to repeat; nothing to warm up (no JIT)
        else:
            n = max(1, min(repeats, int(budget_s / max(first, 1e-9))))
            times = []
            for _ in range(n):
                t0 = time.perf_counter()
                fn()
                times.append(time.perf_counter() - t0)
        n = len(times)
        if can_reset:
            peak = _status_mb("VmHWM")
            rec["call_peak_mb"] = peak
            rec["call_extra_mb"] = max(0.0, peak - (rec["rss_after_setup_mb"] or 0.0))
        rec.update(status="ok", median_s=statistics.median(times), min_s=min(times),
                   repeats=n, times_s=times)
    except Skip as err:
        rec.update(status="skip", reason=str(err))
    except Exception as err:  # noqa: BLE001 - recorded, the suite goes on
        rec.update(status="error", reason=f"{type(err).__name__}: {err}",
                   traceback=traceback.format_exc(limit=6))
    rec["loadavg_1m"] = os.getloadavg()[0]  # other processes competing for the cores
    rec["peak_rss_mb"] = _maxrss_mb()
    rec["base_rss_mb"] = base_rss
    # extra peak memory of setup + calls over what the mesh alone had needed (a lower bound
    # when the mesh construction's own temporaries peaked higher)
    rec["extra_peak_mb"] = max(0.0, rec["peak_rss_mb"] - max(base_rss, base_maxrss))
    return rec


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) not in (3, 4):
        print(__doc__, file=sys.stderr)
        return 2
    name, size, repeats = argv[0], float(argv[1]), int(argv[2])
    budget = float(argv[3]) if len(argv) == 4 else 30.0
    rec = run_case(name, size, repeats, budget)
    sys.stdout.flush()
    print(RESULT_PREFIX + json.dumps(rec), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
