"""``fem3d sweep SWEEP.toml``: the command line of parameter sweeps (the stages and the
output folder are described in :mod:`fem3d.app.sweep`)."""

from __future__ import annotations

import argparse
import contextlib
import json
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from fem3d.app.sweep.plan import _json_safe, plan_sweep
from fem3d.app.sweep.run import run_sweep
from fem3d.app.sweep.spec import METRICS, ResultsSpec, load_sweep_file
from fem3d.errors import InputError
from fem3d.io import extras

__all__ = ["add_sweep_subcommand"]


def add_sweep_subcommand(subparsers) -> argparse.ArgumentParser:
    """Register ``fem3d sweep``."""
    p = subparsers.add_parser(
        "sweep",
        help="run a parameter sweep of a scene on Dask (local processes or a cluster)",
        description="Run every case of a sweep file (a base scene and the key paths to "
        "vary: grid, zip, sampled, explicit cases) as one Dask task each, in DIR/cases/<id>/, "
        "and write DIR/results.csv and DIR/results.png. Complete cases are skipped, so an "
        "interrupted sweep continues where it stopped. See docs/sweeps.md.",
    )
    p.add_argument("sweep", help="sweep file (.toml)")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="worker processes of the embedded cluster (default: one per core)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="use an existing Dask scheduler (tcp://host:8786) instead")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="output folder (default out/<sweep name>)")
    p.add_argument("--retry-failed", action="store_true",
                   help="run the cases recorded as failed again")
    p.add_argument("--metric", choices=METRICS, default=None, metavar="NAME",
                   help="the results.csv column plotted in results.png: "
                   f"{', '.join(METRICS)} (default: the sweep file's [results] metric, else "
                   "max_displacement)")
    p.add_argument("--list", action="store_true", dest="list_cases",
                   help="print the cases (id, state, overrides) and run nothing")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument(
        "--debug", action="store_true", default=argparse.SUPPRESS, help="show tracebacks"
    )
    p.set_defaults(func=_sweep_command)
    return p


@contextlib.contextmanager
def _sigterm_interrupts():
    """SIGTERM (a batch system stopping the job) acts as Ctrl-C: the cluster is shut down,
    the results so far are written, and the next invocation continues."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def _sweep_command(args: argparse.Namespace) -> int:
    if args.workers is not None and args.workers < 1:
        raise InputError(f"--workers must be >= 1, got {args.workers}")
    if args.workers is not None and args.scheduler is not None:
        raise InputError("--workers and --scheduler exclude each other")
    spec = load_sweep_file(args.sweep)
    if args.metric is not None:
        spec = spec.model_copy(update={"results": ResultsSpec(metric=args.metric)})
    out = Path(args.out) if args.out else Path("out") / spec.name
    plan = plan_sweep(spec, out, retry_failed=args.retry_failed, sweep_path=args.sweep)
    if args.list_cases:
        todo = {c.id for c in plan.todo}
        for c in plan.cases:
            state = "invalid" if c.error else ("to run" if c.id in todo else "complete")
            print(f"{c.index}\t{c.id}\t{state}\t{json.dumps(_json_safe(c.params))}")
        return 0
    # before "N cases" and before run_sweep writes sweep.json: one line, nothing written
    extras.require("distributed", "fem3d sweep (Dask)")
    invalid = sum(1 for c in plan.cases if c.error is not None)
    print(
        f"fem3d sweep {spec.name}: {len(plan.cases)} cases ({len(plan.todo)} to run, "
        f"{len(plan.done)} complete before, {invalid} rejected) -> {out}",
        file=sys.stderr,
    )
    with _sigterm_interrupts():
        report = run_sweep(plan, workers=args.workers, scheduler=args.scheduler,
                           quiet=args.quiet)
    ok, failed = report.count("ok"), report.count("failed")
    print(
        f"fem3d sweep {spec.name}: {ok} ok, {failed} failed, {len(report.lost)} lost, "
        f"{report.count('pending')} not run; ran {report.ran}, skipped {report.skipped}; "
        f"{out / 'results.csv'}",
        file=sys.stderr,
    )
    if report.interrupted:
        print("fem3d sweep: interrupted; run the same command again to continue",
              file=sys.stderr)
        return 130
    return 0 if ok == len(report.rows) else 1

